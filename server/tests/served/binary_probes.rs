//! The probe listener of the real binary (issue 46, item 1): with `--probe-port`,
//! `grpc.health.v1` alone is served on a port of its own, plaintext and without a token, for
//! orchestrators' probes, and the gRPC port serves health only to callers with a token.
//!
//! - The probe port answers health without a token and nothing else (`UNIMPLEMENTED`, with a
//!   token or without); the gRPC port refuses a health Check without a token
//!   (`UNAUTHENTICATED`) and answers one with it.
//! - Strangers from many addresses, opening on the gRPC port the health Watches and unfinished
//!   Checks that filled the health calls' caps before, hold none of them: each is refused at
//!   its headers, and the probe port answers Checks and Watches meanwhile.
//! - On SIGTERM the probe port says `NOT_SERVING` while the server drains (`liveness` stays
//!   `SERVING`), and the server, probe listener and all, exits when the drain ends.
//!
//! `DINERDASH_SERVER_EXE=/path/to/dinerdash-server` runs them against another build (the build
//! before the probe listener refuses `--probe-port`, so each fails at its start).

use crate::binary_doors::{framed, grpc_headers, grpc_status, h2_connect, served_watch, unary};
use crate::binary_support::Process;
use crate::grpc_support::{PATIENCE, create, create_request, reset};

use std::net::IpAddr;
use std::time::{Duration, Instant};

use dinerdash_server::cmd::health::{self, Probe, ServingStatus};
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::LIVENESS_SERVICE;
use tonic::Code;
use tonic::transport::Channel;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_client::HealthClient;

/// The tenants file: one tenant.
const TENANTS: &str = "team-a team-a-token-aaaa\n";
const TOKEN: &str = "team-a-token-aaaa";
/// The health Check and Watch.
const CHECK: &str = "/grpc.health.v1.Health/Check";
const WATCH: &str = "/grpc.health.v1.Health/Watch";
/// The gRPC status codes the raw calls read.
const UNAUTHENTICATED: u32 = Code::Unauthenticated as u32;
const UNIMPLEMENTED: u32 = Code::Unimplemented as u32;

/// The server under test with `--probe-port 0` and `args` (the build `DINERDASH_SERVER_EXE`
/// names, if set), and its probe listener's address.
fn start(args: &str) -> (Process, String) {
    let exe = std::env::var("DINERDASH_SERVER_EXE")
        .unwrap_or_else(|_| env!("CARGO_BIN_EXE_dinerdash-server").to_owned());
    Process::start_probed(&exe, "RUST_LOG=warn", args)
}

/// [`start`] with the tenants file (in a directory of the test's own, `name`), so that the gRPC
/// port asks for a token; the directory is returned to be removed.
fn start_with_a_tenant(name: &str, args: &str) -> (Process, String, std::path::PathBuf) {
    let dir = std::env::temp_dir().join(format!("dinerdash-probes-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(&file, TENANTS).unwrap();
    let (server, probes) = start(&format!(
        "--auth-tokens-file '{}' --drain-timeout 0 {args}",
        file.display()
    ));
    (server, probes, dir)
}

/// The status `service` ("" the whole server) reports at `addr`, asked as the Docker
/// HEALTHCHECK asks (`dinerdash-server health`).
async fn probe(addr: &str, service: &str) -> Result<ServingStatus, String> {
    health::check(&Probe {
        address: addr.to_owned(),
        timeout: PATIENCE,
        service: service.into(),
        tls_ca: None,
        token: None,
    })
    .await
}

async fn channel(addr: &str) -> Channel {
    Channel::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap()
}

fn with_token<T>(token: Option<&str>, message: T) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    if let Some(token) = token {
        let value = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
    }
    request
}

/// A health Check of the whole server at `addr`, with `token` or without.
async fn check(addr: &str, token: Option<&str>) -> Result<ServingStatus, tonic::Status> {
    let mut health = HealthClient::new(channel(addr).await);
    let request = with_token(token, HealthCheckRequest::default());
    let reply = tokio::time::timeout(PATIENCE, health.check(request))
        .await
        .expect("a health Check hung")?;
    Ok(reply.into_inner().status())
}

/// `dinerdash-server health --address addr`, with `DINERDASH_AUTH_TOKEN=token` or without it.
async fn health_command(addr: &str, token: Option<&str>) -> std::process::Output {
    let exe = std::env::var("DINERDASH_SERVER_EXE")
        .unwrap_or_else(|_| env!("CARGO_BIN_EXE_dinerdash-server").to_owned());
    let mut command = std::process::Command::new(exe);
    command.args(["health", "--address", addr, "--timeout", "20"]);
    command.env_remove("DINERDASH_AUTH_TOKEN");
    if let Some(token) = token {
        command.env("DINERDASH_AUTH_TOKEN", token);
    }
    tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap()
}

#[tokio::test]
async fn the_probe_port_serves_health_alone_and_the_grpc_port_only_with_a_token() {
    let (server, probes, dir) = start_with_a_tenant("alone", "");
    for service in ["", "dinerdash.v1.DinerDash", LIVENESS_SERVICE] {
        assert_eq!(
            probe(&probes, service).await,
            Ok(ServingStatus::Serving),
            "{service:?}"
        );
    }
    // The gRPC port: a health Check is a call like any other, refused without the token.
    let refused = check(&server.addr, None).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused:?}");
    assert_eq!(
        check(&server.addr, Some(TOKEN)).await.unwrap(),
        ServingStatus::Serving
    );
    // `dinerdash-server health` (the Docker HEALTHCHECK) sends DINERDASH_AUTH_TOKEN when set.
    for (token, expected) in [(None, None), (Some(TOKEN), Some("SERVING"))] {
        let out = health_command(&server.addr, token).await;
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert_eq!(out.status.success(), expected.is_some(), "{out:?}");
        if let Some(expected) = expected {
            assert_eq!(stdout.trim(), expected);
        } else {
            assert!(
                String::from_utf8_lossy(&out.stderr).contains("Unauthenticated"),
                "{out:?}"
            );
        }
    }
    // The probe port serves nothing but health, with the token or without: neither the
    // DinerDash service nor reflection.
    let mut c = DinerDashClient::new(channel(&probes).await);
    for token in [None, Some(TOKEN)] {
        let request = with_token(token, pb::ServerInfoRequest::default());
        let status = c.server_info(request).await.unwrap_err();
        assert_eq!(status.code(), Code::Unimplemented, "{status:?}");
    }
    let mut raw = h2_connect(&probes, None).await;
    let reflection = "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo";
    assert_eq!(
        unary(&mut raw, &probes, reflection, Some(TOKEN), &[]).await,
        Some(UNIMPLEMENTED)
    );
    // Its calls have the gRPC port's bounds: a Check announcing 4 MiB is refused at its header.
    let mut ready = raw.ready().await.unwrap();
    let (response, mut stream) = ready
        .send_request(grpc_headers(&probes, CHECK, None), false)
        .unwrap();
    stream.send_data(framed(4 << 20, &[]), false).unwrap();
    let code = tokio::time::timeout(PATIENCE, grpc_status(response)).await;
    assert_eq!(code, Ok(Some(Code::InvalidArgument as u32)));
    drop((ready, stream));
    // And the DinerDash service on the gRPC port is untouched.
    let mut tenant = DinerDashClient::new(channel(&server.addr).await);
    let request = with_token(Some(TOKEN), pb::ServerInfoRequest::default());
    tenant.server_info(request).await.unwrap();
    let (status, stderr) = server.terminate().await;
    assert_eq!(status.code(), Some(0), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn strangers_on_the_grpc_port_hold_no_health_call_and_probes_are_answered() {
    let (server, probes, dir) = start_with_a_tenant("strangers", "");
    let addr = server.addr.clone();
    // What filled the health calls' caps on the gRPC port before (docs/security.md, "Not
    // promised"): from each of 16 addresses 4 Watches (the 64 Watches of all, 4 a peer) and 28
    // Checks whose message never ends (192 other calls of all, 28 a peer, beyond the 256 in
    // all), none with a token. Each is refused at its headers; their connections stay open.
    let message = framed(100, &[0x55; 99]);
    let (mut held, mut connections) = (Vec::new(), Vec::new());
    let mut refused = 0;
    for i in 0..16 {
        let from = IpAddr::from([127, 0, 0, 2 + i]);
        let mut send = h2_connect(&addr, Some(from)).await;
        let mut answers = Vec::new();
        for path in [[WATCH; 4].as_slice(), &[CHECK; 28]].concat() {
            let mut ready = send.ready().await.unwrap();
            let (response, mut stream) = ready
                .send_request(grpc_headers(&addr, path, None), false)
                .unwrap();
            let _ = stream.send_data(message.clone(), false);
            answers.push(tokio::time::timeout(PATIENCE, grpc_status(response)));
            held.push(stream);
            send = ready;
        }
        for answer in answers {
            let status = answer.await.expect("a stranger's health call was held");
            assert_eq!(status, Some(UNAUTHENTICATED));
            refused += 1;
        }
        connections.push(send);
    }
    assert_eq!(refused, 16 * 32);
    // Meanwhile the probe port answers Checks, and serves Watches from one address up to its
    // cap of 4 (its own: a fifth is refused).
    for service in ["", LIVENESS_SERVICE] {
        assert_eq!(
            probe(&probes, service).await,
            Ok(ServingStatus::Serving),
            "{service:?}"
        );
    }
    let mut watches = Vec::new();
    let mut send = h2_connect(&probes, None).await;
    for _ in 0..4 {
        watches.push(served_watch(&mut send, &probes).await);
    }
    let mut ready = send.ready().await.unwrap();
    let (response, mut stream) = ready
        .send_request(grpc_headers(&probes, WATCH, None), false)
        .unwrap();
    stream.send_data(framed(0, &[]), true).unwrap();
    let code = tokio::time::timeout(PATIENCE, grpc_status(response)).await;
    assert_eq!(code, Ok(Some(Code::ResourceExhausted as u32)));
    drop((held, connections, watches));
    let (status, stderr) = server.terminate().await;
    assert_eq!(status.code(), Some(0), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn the_probe_port_says_not_serving_while_the_server_drains_and_stops_with_it() {
    // A drain timeout far beyond PATIENCE: the drain lasts until the test closes the session.
    let (server, probes) = start("--drain-timeout 1h");
    let mut c = DinerDashClient::new(channel(&server.addr).await);
    let id = create(
        &mut c,
        create_request(2, pb::AutoresetMode::NextStep, Some(5)),
    )
    .await;
    reset(&mut c, &id, None).await;
    for service in ["", "dinerdash.v1.DinerDash", LIVENESS_SERVICE] {
        assert_eq!(probe(&probes, service).await, Ok(ServingStatus::Serving));
    }

    server.signal("-TERM");
    let started = Instant::now();
    while probe(&probes, "").await != Ok(ServingStatus::NotServing) {
        assert!(
            started.elapsed() < PATIENCE,
            "the probe port did not say NOT_SERVING"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(
        probe(&probes, "dinerdash.v1.DinerDash").await,
        Ok(ServingStatus::NotServing)
    );
    // Alive all the same, for liveness probes; and the session is still served.
    assert_eq!(
        probe(&probes, LIVENESS_SERVICE).await,
        Ok(ServingStatus::Serving)
    );
    let batch = crate::grpc_support::step(&mut c, &id, &[0, 0]).await;
    assert!(batch.drain_remaining_ms > 0);

    // The last session closed, the server exits, its probe listener with it.
    c.close_session(pb::CloseSessionRequest { session_id: id })
        .await
        .unwrap();
    let (status, stderr) = tokio::task::spawn_blocking(move || server.wait())
        .await
        .unwrap();
    assert_eq!(status.code(), Some(0), "{stderr}");
    assert!(tokio::net::TcpStream::connect(&probes).await.is_err());
}
