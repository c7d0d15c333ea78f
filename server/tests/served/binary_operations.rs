//! The operator's tools, on the real binary (issue 46): the tokens file read again on SIGHUP (a
//! new token works on its first call, a removed one is refused on its next, a rotated tenant
//! keeps its sessions, a bad file keeps the tokens before and says why in the log); a token
//! given both as the shared token and as a tenant's refused at start; failed authentications
//! counted in `dinerdash_auth_failures_total` and logged with their peer and method, a bounded
//! number of lines; session create, fork, restore, close and expiry logged at info with the
//! tenant's name; and the quotas by default: a tenant's fair part of `--max-sessions`, the
//! shared token's share counted once for all its connections.

use crate::binary_support;
use crate::grpc_support;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::audit::{LINES_PER_WINDOW, LOG_WINDOW};
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::{PATIENCE, create_request, pack};
use tonic::transport::Channel;
use tonic::{Code, Request, Status};

/// Tenant A's first token.
const TOKEN_A: &str = "ops-tenant-a-token-9Xk2Qw";
/// Tenant A's token after rotation.
const TOKEN_A2: &str = "ops-tenant-a-rotated-4Rt7";
/// Tenant B's token.
const TOKEN_B: &str = "ops-tenant-b-token-6Lm3Zp";

/// A folder of this test's own, removed when dropped.
struct Dir(PathBuf);

impl Dir {
    fn new(name: &str) -> Dir {
        let dir = std::env::temp_dir().join(format!("dinerdash-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Dir(dir)
    }

    fn path(&self, file: &str) -> PathBuf {
        self.0.join(file)
    }
}

impl Drop for Dir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The server with `args`, its log lines (stderr) written to `log`.
fn start(log: &Path, args: &str) -> Process {
    Process::start(
        &format!("exec 2>'{}';", log.display()),
        &format!("--drain-timeout 0 {args}"),
    )
}

/// Lines of `log` containing `text`.
fn lines_with(log: &Path, text: &str) -> usize {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter(|l| l.contains(text))
        .count()
}

/// Waits (bounded) until `log` has `n` lines containing `text`.
async fn wait_for_lines(log: &Path, text: &str, n: usize) {
    let started = Instant::now();
    while lines_with(log, text) < n {
        assert!(
            started.elapsed() < PATIENCE,
            "no {n} lines with {text:?} in\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// `message` carrying `authorization: Bearer <token>`.
fn with<T>(token: &str, message: T) -> Request<T> {
    let mut request = Request::new(message);
    let value = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    request
}

async fn connect(addr: &str) -> DinerDashClient<Channel> {
    DinerDashClient::connect(format!("http://{addr}"))
        .await
        .unwrap()
}

async fn create(c: &mut DinerDashClient<Channel>, token: &str) -> Result<String, Status> {
    let request = with(
        token,
        create_request(2, pb::AutoresetMode::NextStep, Some(5)),
    );
    Ok(c.create_session(request).await?.into_inner().session_id)
}

async fn step(c: &mut DinerDashClient<Channel>, token: &str, id: &str) -> Result<(), Status> {
    let reset = pb::ResetRequest {
        session_id: id.to_owned(),
        ..Default::default()
    };
    c.reset(with(token, reset)).await?;
    let message = pb::StepRequest {
        session_id: id.to_owned(),
        actions: pack(&[0, 1]),
    };
    c.step(with(token, message)).await.map(drop)
}

#[tokio::test]
async fn sighup_reads_the_tokens_file_again_and_keeps_every_session() {
    let dir = Dir::new("reload");
    let (file, log) = (dir.path("tenants"), dir.path("log"));
    std::fs::write(&file, format!("team-a {TOKEN_A}\n")).unwrap();
    let server = start(&log, &format!("--auth-tokens-file '{}'", file.display()));
    let mut c = connect(&server.addr).await;
    let mine = create(&mut c, TOKEN_A).await.unwrap();
    let refused = create(&mut c, TOKEN_B).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated);

    // A's token rotated, B added: both work on their first call, A's old token is refused on
    // its next, and A's session is still A's.
    let read_again = "SIGHUP: tokens file read again";
    std::fs::write(&file, format!("team-a {TOKEN_A2}\nteam-b {TOKEN_B}\n")).unwrap();
    server.signal("-HUP");
    wait_for_lines(&log, read_again, 1).await;
    let theirs = create(&mut c, TOKEN_B).await.unwrap();
    step(&mut c, TOKEN_A2, &mine).await.unwrap();
    let old = step(&mut c, TOKEN_A, &mine).await.unwrap_err();
    assert_eq!(old.code(), Code::Unauthenticated);
    // The tenant wall holds across the reload.
    let walled = step(&mut c, TOKEN_B, &mine).await.unwrap_err();
    assert_eq!(walled.code(), Code::NotFound);

    // A bad file changes nothing, and the log says why (naming the line, not the token).
    std::fs::write(&file, format!("team-a {TOKEN_A2}\nteam-b\n")).unwrap();
    server.signal("-HUP");
    wait_for_lines(&log, "SIGHUP: the tokens file is refused", 1).await;
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("line 2"), "{text}");
    step(&mut c, TOKEN_A2, &mine).await.unwrap();
    step(&mut c, TOKEN_B, &theirs).await.unwrap();

    // B removed: refused on its next call; brought back, it finds its session again.
    std::fs::write(&file, format!("team-a {TOKEN_A2}\n")).unwrap();
    server.signal("-HUP");
    wait_for_lines(&log, read_again, 2).await;
    let removed = step(&mut c, TOKEN_B, &theirs).await.unwrap_err();
    assert_eq!(removed.code(), Code::Unauthenticated);
    std::fs::write(&file, format!("team-a {TOKEN_A2}\nteam-b {TOKEN_B}\n")).unwrap();
    server.signal("-HUP");
    wait_for_lines(&log, read_again, 3).await;
    step(&mut c, TOKEN_B, &theirs).await.unwrap();
    step(&mut c, TOKEN_A2, &mine).await.unwrap();

    let (status, _) = server.terminate().await;
    assert!(status.success(), "{status:?}");
    let text = std::fs::read_to_string(&log).unwrap();
    for token in [TOKEN_A, TOKEN_A2, TOKEN_B] {
        assert!(!text.contains(token), "the log holds a token:\n{text}");
    }
}

#[tokio::test]
async fn a_token_given_as_the_shared_one_and_a_tenants_is_refused_at_start() {
    let dir = Dir::new("twice");
    let file = dir.path("tenants");
    std::fs::write(&file, format!("team-a {TOKEN_A}\nteam-b {TOKEN_B}\n")).unwrap();
    let file = file.to_str().unwrap();
    let by_flag = ["--auth-token", TOKEN_B, "--auth-tokens-file", file];
    for (env, args) in [
        (Some(TOKEN_A), &["--auth-tokens-file", file][..]),
        (None, &by_flag[..]),
    ] {
        let mut command = Command::new(env!("CARGO_BIN_EXE_dinerdash-server"));
        command
            .args(["--port", "0"])
            .args(args)
            .env_remove("DINERDASH_AUTH_TOKEN")
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        if let Some(token) = env {
            command.env("DINERDASH_AUTH_TOKEN", token);
        }
        let mut child = command.spawn().unwrap();
        let started = Instant::now();
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            if started.elapsed() > PATIENCE {
                let _ = child.kill();
                panic!("the server started with a token given twice");
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let mut stderr = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
        assert!(!status.success(), "{stderr}");
        let tenant = if env.is_some() { "team-a" } else { "team-b" };
        assert!(
            stderr.contains(&format!(
                "tenant \"{tenant}\"'s token is also the shared token"
            )),
            "{stderr}"
        );
        assert!(
            !stderr.contains(TOKEN_A) && !stderr.contains(TOKEN_B),
            "{stderr}"
        );
    }
}

/// A GET of the web endpoint's metrics with `token`.
async fn metrics(addr: SocketAddr, token: &str) -> String {
    let head = format!(
        "GET /metrics HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\n\
         Connection: close\r\n\r\n"
    );
    let (status, text) = grpc_support::http_exchange(addr, &head).await;
    assert_eq!(status, 200, "{text}");
    text
}

#[tokio::test]
async fn failed_authentications_are_counted_and_logged_in_few_lines() {
    let dir = Dir::new("audit");
    let (file, log) = (dir.path("tenants"), dir.path("log"));
    std::fs::write(&file, format!("team-a {TOKEN_A}\n")).unwrap();
    let server = start(
        &log,
        &format!("--auth-tokens-file '{}' --http-port 0", file.display()),
    );
    let mut c = connect(&server.addr).await;
    let started = Instant::now();
    for i in 0..51 {
        let wrong = format!("wrong-token-{i:04}-0123456789");
        let refused = step(&mut c, &wrong, "0123456789abcdef0123456789abcdef")
            .await
            .unwrap_err();
        assert_eq!(refused.code(), Code::Unauthenticated);
    }
    let elapsed = started.elapsed();
    let info = c
        .server_info(with(TOKEN_A, pb::ServerInfoRequest {}))
        .await
        .unwrap()
        .into_inner();
    let http: SocketAddr = format!("127.0.0.1:{}", info.http_port).parse().unwrap();
    let text = metrics(http, TOKEN_A).await;
    assert_eq!(
        grpc_support::metric(&text, "dinerdash_auth_failures_total"),
        51
    );

    let (status, _) = server.terminate().await;
    assert!(status.success(), "{status:?}");
    let lines: Vec<String> = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .filter(|l| l.contains("authentication failed"))
        .map(str::to_owned)
        .collect();
    // At most LINES_PER_WINDOW lines in each window the 51 calls overlapped.
    let windows = elapsed.as_secs_f64() / LOG_WINDOW.as_secs_f64();
    let bound = LINES_PER_WINDOW as usize * (windows.ceil() as usize + 1);
    assert!(
        !lines.is_empty() && lines.len() <= bound,
        "{} lines, bound {bound}",
        lines.len()
    );
    for line in &lines {
        assert!(line.contains("peer=127.0.0.1:"), "{line}");
        assert!(
            line.contains("method=/dinerdash.v1.DinerDash/Reset"),
            "{line}"
        );
        assert!(!line.contains("wrong-token"), "{line}");
    }
}

#[tokio::test]
async fn one_tenant_cannot_take_every_session_by_default() {
    let dir = Dir::new("quota");
    let (file, log) = (dir.path("tenants"), dir.path("log"));
    std::fs::write(&file, format!("team-a {TOKEN_A}\nteam-b {TOKEN_B}\n")).unwrap();
    let server = start(
        &log,
        &format!("--auth-tokens-file '{}' --max-sessions 4", file.display()),
    );
    let mut c = connect(&server.addr).await;
    // Each of the two tenants may hold half of --max-sessions.
    for _ in 0..2 {
        create(&mut c, TOKEN_A).await.unwrap();
    }
    let refused = create(&mut c, TOKEN_A).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused
            .message()
            .starts_with("tenant team-a holds its maximum of 2 sessions"),
        "{}",
        refused.message()
    );
    for _ in 0..2 {
        create(&mut c, TOKEN_B).await.unwrap();
    }
    // The lifecycle is logged with the tenant's name.
    wait_for_lines(&log, "tenant=\"tenant team-b\"", 2).await;
    assert_eq!(lines_with(&log, "session created"), 4);
}

#[tokio::test]
async fn the_shared_tokens_share_is_one_for_all_its_connections() {
    let dir = Dir::new("shared");
    let log = dir.path("log");
    let server = start(
        &log,
        &format!("--auth-token {TOKEN_A} --max-envs-per-tenant 3"),
    );
    let (mut first, mut second) = (connect(&server.addr).await, connect(&server.addr).await);
    create(&mut first, TOKEN_A).await.unwrap();
    // A second connection adds to the same share: 2 + 2 > 3.
    let refused = create(&mut second, TOKEN_A).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused
            .message()
            .starts_with("the shared token holds 2 environments and may hold 3"),
        "{}",
        refused.message()
    );
}

#[tokio::test]
async fn every_session_event_is_logged_with_its_tenant() {
    let dir = Dir::new("lifecycle");
    let (file, log) = (dir.path("tenants"), dir.path("log"));
    std::fs::write(&file, format!("team-a {TOKEN_A}\n")).unwrap();
    let server = start(
        &log,
        &format!("--auth-tokens-file '{}' --session-ttl 2s", file.display()),
    );
    let mut c = connect(&server.addr).await;
    let made = create(&mut c, TOKEN_A).await.unwrap();
    step(&mut c, TOKEN_A, &made).await.unwrap();
    let fork = pb::ForkRequest {
        session_id: made.clone(),
    };
    let forked = c.fork(with(TOKEN_A, fork)).await.unwrap().into_inner();
    let snapshot = pb::SnapshotRequest {
        session_id: made.clone(),
        ..Default::default()
    };
    let snapshot = c.snapshot(with(TOKEN_A, snapshot)).await.unwrap();
    let restore = pb::RestoreRequest {
        snapshot: snapshot.into_inner().snapshot,
    };
    c.restore(with(TOKEN_A, restore)).await.unwrap();
    let close = pb::CloseSessionRequest {
        session_id: forked.session_id,
    };
    c.close_session(with(TOKEN_A, close)).await.unwrap();
    // The two left (the first and the restored one) expire, idle.
    wait_for_lines(&log, "session expired", 2).await;
    let text = std::fs::read_to_string(&log).unwrap();
    for event in [
        "session created",
        "session forked",
        "session restored",
        "session closed",
        "session expired",
    ] {
        let line = text
            .lines()
            .find(|l| l.contains(event) && l.contains(" INFO "))
            .unwrap_or_else(|| panic!("no INFO line {event:?} in\n{text}"));
        assert!(line.contains("tenant=\"tenant team-a\""), "{line}");
        assert!(!line.contains(&made), "the whole ID at info level: {line}");
    }
}
