//! The real binary under abuse (issue 12): SIGTERM with a Rollout running answers new calls at
//! once instead of hanging, and at the open-file limit the accept loop backs off with a warning
//! instead of spinning a core.

use crate::binary_support;
use crate::grpc_support;

use std::process::Command;
use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::PATIENCE;
use tonic::Code;

#[tokio::test]
async fn sigterm_answers_new_calls_at_once_and_exits() {
    let server = Process::start("", "--log-format json");
    let url = format!("http://{}", server.addr);
    let mut reader = DinerDashClient::connect(url.clone()).await.unwrap();
    let mut stream = reader
        .rollout(pb::RolloutRequest {
            policy: pb::Policy::Expert.into(),
            seeds: (0..1000).collect(),
            max_steps: None,
            config: None,
            action_masks: true,
        })
        .await
        .unwrap()
        .into_inner();
    stream.message().await.unwrap().unwrap();
    let mut c = DinerDashClient::connect(url.clone()).await.unwrap();
    c.server_info(pb::ServerInfoRequest {}).await.unwrap();

    server.signal("-TERM");
    // Until the signal is handled the call may still succeed; after it, it must fail fast with
    // UNAVAILABLE (never hang): every attempt is bounded by PATIENCE.
    let started = Instant::now();
    let status = loop {
        let call = tokio::time::timeout(PATIENCE, c.server_info(pb::ServerInfoRequest {}));
        match call.await.expect("a call to a draining server hung") {
            Err(status) => break status,
            Ok(_) => {
                assert!(started.elapsed() < PATIENCE, "never started draining");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    let fresh = tokio::time::timeout(PATIENCE, DinerDashClient::connect(url)).await;
    assert!(matches!(fresh, Ok(Err(_))), "a new connection was accepted");
    // Keep reading: the stream ends within its drain deadline, then the process exits 0.
    while let Ok(Some(_)) = stream.message().await {}
    let (status, _) = tokio::task::spawn_blocking(move || server.wait())
        .await
        .unwrap();
    assert_eq!(status.code(), Some(0));
}

#[tokio::test]
async fn at_the_open_file_limit_the_accept_loop_backs_off() {
    // So few descriptors that the server's own (about 12) leave less than its connection cap
    // (8 at this limit): accepting fails before any connection can be shed. The per-address cap
    // (2 here) would close the strangers' idle connections as new ones come, and the limit
    // might then never be reached: it is set out of the way.
    let server = Process::start(
        "ulimit -n 16 &&",
        "--idle-timeout 1h --log-format json --max-connections-per-address 100000",
    );
    // Hold more connections than the process has descriptors.
    let mut held = Vec::new();
    for _ in 0..80 {
        held.push(tokio::net::TcpStream::connect(&server.addr).await.unwrap());
    }
    // Let the server reach the limit and fail to accept the rest, then watch its CPU.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let before = server.cpu_ticks();
    let wall = Instant::now();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let ticks = server.cpu_ticks() - before;
    let elapsed = wall.elapsed();
    // A spinning accept loop burns ~100 ticks a second; backing off burns almost none.
    assert!(
        ticks < 50,
        "{ticks} ticks of CPU in {elapsed:?} at the open-file limit"
    );
    // Connections released, the server serves again.
    drop(held);
    let url = format!("http://{}", server.addr);
    let served = tokio::time::timeout(PATIENCE, async {
        loop {
            if let Ok(mut c) = DinerDashClient::connect(url.clone()).await {
                if c.server_info(pb::ServerInfoRequest {}).await.is_ok() {
                    break;
                }
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(served.is_ok(), "the server did not recover");
    let (status, stderr) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    assert!(
        stderr.contains("cannot accept connections"),
        "no warning logged:\n{stderr}"
    );
}

#[tokio::test]
async fn tokens_file_tenants_and_a_public_metrics_port() {
    let exe = env!("CARGO_BIN_EXE_dinerdash-server");
    // Metrics beyond this machine without a token: refused at start, with the reason.
    let refused = tokio::task::spawn_blocking(move || {
        Command::new(exe)
            .args([
                "--port",
                "0",
                "--metrics-port",
                "0",
                "--metrics-host",
                "0.0.0.0",
            ])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("--auth-tokens-file"), "{stderr}");

    let dir = std::env::temp_dir().join(format!("dinerdash-tenants-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(
        &file,
        "# two trainers\nteam-a team-a-token-aaaa envs=8\nteam-b team-b-token-bbbb\n",
    )
    .unwrap();
    let server = Process::start("", &format!("--auth-tokens-file '{}'", file.display()));
    let mut c = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    let create = |token: &str, num_envs: u32| {
        let mut request = tonic::Request::new(pb::CreateSessionRequest {
            num_envs,
            ..Default::default()
        });
        let value = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
        request
    };
    c.create_session(create("team-a-token-aaaa", 8))
        .await
        .unwrap();
    let over = c
        .create_session(create("team-a-token-aaaa", 1))
        .await
        .unwrap_err();
    assert_eq!(over.code(), Code::ResourceExhausted);
    assert!(over.message().starts_with("tenant team-a"), "{over:?}");
    c.create_session(create("team-b-token-bbbb", 64))
        .await
        .unwrap();
    let stranger = c
        .create_session(create("stranger-token-cccc", 1))
        .await
        .unwrap_err();
    assert_eq!(stranger.code(), Code::Unauthenticated);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}
