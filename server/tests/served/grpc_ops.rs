//! Running the server: idle expiry, the metrics endpoint, health, graceful shutdown, the bearer
//! token, TLS with a certificate made here, and the binary itself (the listening line on stdout,
//! the `health` command, exit 0 on SIGTERM).

use crate::grpc_support;

use std::process::{Command, Stdio};
use std::time::Duration;

use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::{ServerConfig, TlsPem};
use dinerdash_server::session::Limits;
use grpc_support::*;
use tonic::Code;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

#[tokio::test]
async fn idle_sessions_expire() {
    let config = ServerConfig {
        limits: Limits {
            session_ttl: Duration::from_millis(200),
            ..Limits::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, true).await;
    let mut c = server.client().await;
    let id = create(
        &mut c,
        create_request(2, pb::AutoresetMode::NextStep, Some(1)),
    )
    .await;
    reset(&mut c, &id, None).await;
    // Poll with ServerInfo, which does not touch the session, until the sweeper evicted it.
    let started = std::time::Instant::now();
    loop {
        let info = c
            .server_info(pb::ServerInfoRequest {})
            .await
            .unwrap()
            .into_inner();
        if info.live_sessions == 0 {
            break;
        }
        assert!(
            started.elapsed() < PATIENCE,
            "the idle session was never evicted"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let status = c
        .step(pb::StepRequest {
            session_id: id.clone(),
            actions: pack(&[0, 0]),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert_eq!(
        status.message(),
        format!("session {id} not found (closed or expired)")
    );
    let text = scrape(server.metrics_addr.unwrap()).await;
    assert_eq!(metric(&text, "dinerdash_sessions_expired_total"), 1);
    assert_eq!(metric(&text, "dinerdash_live_sessions"), 0);
    server.stop().await;
}

#[tokio::test]
async fn health_reports_serving() {
    let server = TestServer::start().await;
    let channel = server.channel().await;
    let mut health = HealthClient::new(channel);
    for service in ["", "dinerdash.v1.DinerDash"] {
        let reply = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            reply.status(),
            ServingStatus::Serving,
            "service {service:?}"
        );
    }
    let unknown = health
        .check(HealthCheckRequest {
            service: "no.such.Service".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);
    server.stop().await;
}

#[tokio::test]
async fn shutdown_drains_rpcs_in_flight() {
    let mut server = TestServer::start().await;
    let mut c = server.client().await;
    let seeds: Vec<u64> = (0..12).collect();
    let mut stream = c
        .rollout(pb::RolloutRequest {
            policy: pb::Policy::Expert.into(),
            seeds: seeds.clone(),
            config: None,
            max_steps: None,
            action_masks: false,
        })
        .await
        .unwrap()
        .into_inner();
    // The Rollout is surely in flight once its first episode arrived.
    let first = stream.message().await.unwrap().unwrap();
    server.trigger_stop();
    let mut got = vec![first.seed];
    while let Some(ep) = stream.message().await.unwrap() {
        got.push(ep.seed);
    }
    assert_eq!(got, seeds, "every episode of the in-flight Rollout arrived");
    let addr = server.addr;
    server.stop().await;
    // Stopped: no longer accepting connections.
    assert!(
        DinerDashClient::connect(format!("http://{addr}"))
            .await
            .is_err()
    );
}

#[tokio::test]
async fn auth_token_is_required() {
    let config = ServerConfig {
        auth_token: Some("s3cret-0123456789".into()),
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let channel = server.channel().await;
    let with_token = |token: &'static str| {
        DinerDashClient::with_interceptor(channel.clone(), move |mut request: tonic::Request<()>| {
            request
                .metadata_mut()
                .insert("authorization", token.parse().unwrap());
            Ok(request)
        })
    };
    let mut bare = DinerDashClient::new(channel.clone());
    let status = bare
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Unauthenticated);
    assert_eq!(
        status.message(),
        "missing authorization metadata: send `authorization: Bearer <token>`"
    );
    for wrong in [
        "Bearer s3cre",
        "Bearer s3cret-0123456789 ",
        "s3cret-0123456789",
        "Bearer S3CRET-0123456789",
    ] {
        let status = with_token(wrong)
            .server_info(pb::ServerInfoRequest {})
            .await
            .unwrap_err();
        assert_eq!(
            (status.code(), status.message()),
            (Code::Unauthenticated, "invalid auth token")
        );
    }
    let status = with_token("Bearer nope")
        .rollout(pb::RolloutRequest {
            policy: pb::Policy::Random.into(),
            seeds: vec![1],
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Unauthenticated);

    let mut good = with_token("Bearer s3cret-0123456789");
    let id = good
        .create_session(create_request(1, pb::AutoresetMode::NextStep, Some(1)))
        .await
        .unwrap()
        .into_inner()
        .session_id;
    good.reset(pb::ResetRequest {
        session_id: id,
        ..Default::default()
    })
    .await
    .unwrap();
    // Health stays open, for orchestrators' probes.
    let reply = HealthClient::new(channel)
        .check(HealthCheckRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(reply.status(), ServingStatus::Serving);
    server.stop().await;
}

#[tokio::test]
async fn tls_with_a_generated_certificate() {
    let key = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).unwrap();
    let cert_pem = key.cert.pem();
    let tls = TlsPem {
        cert: cert_pem.clone().into_bytes(),
        key: key.signing_key.serialize_pem().into_bytes(),
    };
    let config = ServerConfig {
        tls: Some(tls),
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let channel = tls_channel(format!("https://{}", server.addr), &cert_pem).await;
    let mut c = DinerDashClient::new(channel);
    let id = create(
        &mut c,
        create_request(2, pb::AutoresetMode::NextStep, Some(4)),
    )
    .await;
    let batch = reset(&mut c, &id, None).await;
    assert_eq!(batch.seeds, vec![4, 5]);
    let batch = step(&mut c, &id, &[15, 0]).await;
    assert_eq!(i32s(&batch.rewards)[0], 10);

    // A plaintext client gets nowhere.
    let plain = DinerDashClient::connect(format!("http://{}", server.addr)).await;
    if let Ok(mut plain) = plain {
        assert!(plain.server_info(pb::ServerInfoRequest {}).await.is_err());
    }
    server.stop().await;
}

/// The real binary: the listening line, `health`, metrics flags, and exit 0 on SIGTERM.
#[tokio::test]
async fn binary_prints_its_port_answers_health_and_exits_cleanly() {
    let exe = env!("CARGO_BIN_EXE_dinerdash-server");
    let result = tokio::task::spawn_blocking(move || {
        let mut child = Command::new(exe)
            .args(["--port", "0", "--session-ttl", "5m", "--log-format", "json"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let addr = grpc_support::listening_addr(&mut child);
        let port: u16 = addr.rsplit(':').next().unwrap().parse().unwrap();
        assert_ne!(port, 0);
        let health = Command::new(exe)
            .args(["health", "--address", &addr, "--timeout", "20"])
            .output()
            .unwrap();
        let pid = child.id().to_string();
        let killed = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        assert!(killed.success());
        let status = child.wait().unwrap();
        (health, status)
    })
    .await
    .unwrap();
    let (health, status) = result;
    assert!(health.status.success(), "health: {health:?}");
    assert_eq!(String::from_utf8_lossy(&health.stdout).trim(), "SERVING");
    assert_eq!(status.code(), Some(0), "exit status after SIGTERM");

    // Nothing listens there any more: health fails.
    let down = tokio::task::spawn_blocking(move || {
        Command::new(exe)
            .args(["health", "--address", "127.0.0.1:1", "--timeout", "5"])
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(!down.status.success());
}
