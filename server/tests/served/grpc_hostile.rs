//! Hostile and broken clients against a real server on 127.0.0.1 (issue 12): the memory budget
//! refuses before it is passed, one connection or tenant cannot take everything, unread Rollout
//! streams block no one and cancelled ones stop, undecodable bytes are INVALID_ARGUMENT, silent
//! connections are closed, connections over the limit are answered, and a draining server
//! answers new calls UNAVAILABLE.

use crate::grpc_support;

use std::sync::Arc;
use std::time::Duration;

use dinerdash_server::auth::Token;
use dinerdash_server::budget::{Share, Tenant};
use dinerdash_server::connections;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::ServerConfig;
use dinerdash_server::session::{Limits, session_bytes};
use grpc_support::*;
use tokio::io::AsyncReadExt;
use tonic::Code;
use tonic::transport::Channel;

fn big(num_envs: u32) -> pb::CreateSessionRequest {
    create_request(num_envs, pb::AutoresetMode::NextStep, Some(0))
}

async fn info(c: &mut DinerDashClient<Channel>) -> pb::ServerInfoResponse {
    c.server_info(pb::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner()
}

#[tokio::test]
async fn the_memory_budget_refuses_before_it_is_passed() {
    // Room for three sessions of 1024 environments and a little more, not four.
    let max_memory = 3 * session_bytes(1024) + session_bytes(100);
    let config = ServerConfig {
        limits: Limits {
            max_memory,
            ..Limits::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, true).await;
    let mut c = server.client().await;
    let first = create(&mut c, big(1024)).await;
    reset(&mut c, &first, Some(0)).await;
    let forked = c
        .fork(pb::ForkRequest {
            session_id: first.clone(),
        })
        .await
        .unwrap()
        .into_inner()
        .session_id;
    create(&mut c, big(1024)).await;
    let used = info(&mut c).await;
    assert_eq!(used.max_memory_bytes, max_memory);
    assert_eq!(used.memory_used_bytes, 3 * session_bytes(1024));

    // A fourth big session, a fork of one, and a restore of one are all refused ...
    let refused = c.create_session(big(1024)).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused.message().contains("memory budget") && refused.message().contains("--max-memory"),
        "{}",
        refused.message()
    );
    let fork = c
        .fork(pb::ForkRequest {
            session_id: first.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(fork.code(), Code::ResourceExhausted);
    let bytes = snapshot(&mut c, &first).await;
    let restored = c
        .restore(pb::RestoreRequest {
            snapshot: bytes.clone(),
        })
        .await
        .unwrap_err();
    assert_eq!(restored.code(), Code::ResourceExhausted);
    // ... and the refusals held nothing.
    assert!(info(&mut c).await.memory_used_bytes <= max_memory);
    // A small session still fits.
    create(&mut c, big(100)).await;

    // Closing a session gives its bytes back.
    c.close_session(pb::CloseSessionRequest { session_id: forked })
        .await
        .unwrap();
    restore(&mut c, bytes).await;
    let text = scrape(server.metrics_addr.unwrap()).await;
    assert_eq!(metric(&text, "dinerdash_memory_budget_bytes"), max_memory);
    assert_eq!(
        metric(&text, "dinerdash_memory_used_bytes"),
        3 * session_bytes(1024) + session_bytes(100)
    );
    assert_eq!(metric(&text, "dinerdash_live_sessions"), 4);
    server.stop().await;
}

#[tokio::test]
async fn one_connection_cannot_take_every_environment() {
    let config = ServerConfig {
        connection_share: Share {
            max_envs: 2048,
            ..Share::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    // Each client is its own channel, so its own connection.
    let mut greedy = server.client().await;
    create(&mut greedy, big(1024)).await;
    create(&mut greedy, big(1024)).await;
    let refused = greedy.create_session(big(1)).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused.message().starts_with("connection 127.0.0.1:")
            && refused.message().contains("may hold 2048"),
        "{}",
        refused.message()
    );
    let mut other = server.client().await;
    create(&mut other, big(1024)).await;
    server.stop().await;
}

#[tokio::test]
async fn tenant_tokens_have_their_own_shares() {
    let tenant = |name: &str, max_envs| {
        Some(Arc::new(Tenant::new(
            format!("tenant {name}"),
            Share {
                max_envs,
                ..Share::default()
            },
        )))
    };
    let config = ServerConfig {
        tenants: vec![
            Token {
                token: "small-tenant-secret".into(),
                tenant: tenant("small", 4),
            },
            Token {
                token: "big-tenant-secret-1".into(),
                tenant: tenant("big", 1000),
            },
        ],
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let mut c = server.client().await;
    let with = |token: &str, num_envs| {
        let mut request = tonic::Request::new(big(num_envs));
        let value = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
        request
    };
    c.create_session(with("small-tenant-secret", 3))
        .await
        .unwrap();
    let refused = c
        .create_session(with("small-tenant-secret", 2))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused.message().starts_with("tenant small holds 3"),
        "{}",
        refused.message()
    );
    // The same connection, another tenant: its own share.
    c.create_session(with("big-tenant-secret-1", 500))
        .await
        .unwrap();
    let wrong = c.create_session(with("nope", 1)).await.unwrap_err();
    assert_eq!(wrong.code(), Code::Unauthenticated);
    let missing = c.create_session(big(1)).await.unwrap_err();
    assert_eq!(missing.code(), Code::Unauthenticated);
    server.stop().await;
}

fn rollout(seeds: u64, max_steps: Option<u32>) -> pb::RolloutRequest {
    pb::RolloutRequest {
        policy: pb::Policy::Expert.into(),
        seeds: (0..seeds).collect(),
        config: None,
        max_steps,
        action_masks: true,
    }
}

#[tokio::test]
async fn unread_rollout_streams_do_not_block_other_clients() {
    let server = TestServer::start().await;
    // More unread streams than the pool has workers (sized from this machine's cores), each on
    // its own connection, none of them read past its first message.
    let workers = dinerdash_server::pools::CpuPool::beside_steps().workers();
    let mut unread = Vec::new();
    for _ in 0..workers + 2 {
        let mut c = server.client().await;
        let mut stream = c.rollout(rollout(1000, None)).await.unwrap().into_inner();
        stream.message().await.unwrap().unwrap();
        unread.push((c, stream));
    }
    let mut c = server.client().await;
    let short = async {
        let mut stream = c.rollout(rollout(1, Some(10))).await.unwrap().into_inner();
        let episode = stream.message().await.unwrap().unwrap();
        assert!(stream.message().await.unwrap().is_none());
        episode
    };
    let episode = tokio::time::timeout(PATIENCE, short)
        .await
        .expect("a 10-step Rollout waited behind unread streams");
    assert_eq!(episode.steps, 10);
    drop(unread);
    server.stop().await;
}

#[tokio::test]
async fn cancelled_rollouts_give_back_their_share_and_bytes() {
    let config = ServerConfig {
        connection_share: Share {
            max_rollouts: 1,
            ..Share::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, true).await;
    let mut c = server.client().await;
    let mut stream = c.rollout(rollout(1000, None)).await.unwrap().into_inner();
    stream.message().await.unwrap().unwrap();
    // The connection's one Rollout is running: a second is refused.
    let second = c.rollout(rollout(1, Some(1))).await.unwrap_err();
    assert_eq!(second.code(), Code::ResourceExhausted);
    assert!(second.message().contains("Rollout"), "{}", second.message());
    drop(stream);
    // The producer notices the reader left and ends: the share and the bytes come back.
    let started = std::time::Instant::now();
    loop {
        let text = scrape(server.metrics_addr.unwrap()).await;
        if metric(&text, "dinerdash_live_rollouts") == 0 {
            assert_eq!(metric(&text, "dinerdash_memory_used_bytes"), 0);
            break;
        }
        assert!(
            started.elapsed() < PATIENCE,
            "the cancelled Rollout never ended"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut again = c.rollout(rollout(1, Some(5))).await.unwrap().into_inner();
    assert_eq!(again.message().await.unwrap().unwrap().steps, 5);
    server.stop().await;
}

/// A message whose field 1 has the wrong wire type for every request of the service.
#[derive(Clone, PartialEq, prost::Message)]
struct Garbled {
    #[prost(fixed64, tag = "1")]
    session_id: u64,
}

#[tokio::test]
async fn undecodable_bytes_are_invalid_argument() {
    let server = TestServer::start().await;
    let channel = server.channel().await;
    for method in ["Step", "CreateSession", "Restore", "Rollout"] {
        let mut grpc = tonic::client::Grpc::new(channel.clone());
        grpc.ready().await.unwrap();
        let path = format!("/dinerdash.v1.DinerDash/{method}").parse().unwrap();
        let codec = tonic_prost::ProstCodec::<Garbled, pb::ServerInfoResponse>::default();
        let status = grpc
            .unary(tonic::Request::new(Garbled { session_id: 7 }), path, codec)
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{method}: {status:?}");
        assert!(status.message().contains("undecodable"), "{status:?}");
    }
    server.stop().await;
}

#[tokio::test]
async fn silent_connections_are_closed() {
    let config = ServerConfig {
        connections: connections::Limits {
            idle_timeout: Duration::from_millis(200),
            ..connections::Limits::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let mut silent = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    // The server sends its HTTP/2 settings, then closes the connection: reading to the end
    // finishes (EOF or reset) instead of waiting forever.
    let mut sent = Vec::new();
    tokio::time::timeout(PATIENCE, silent.read_to_end(&mut sent))
        .await
        .expect("a silent connection was never closed")
        .ok();
    server.stop().await;
}

#[tokio::test]
async fn connections_over_the_limit_are_answered_resource_exhausted() {
    let config = ServerConfig {
        connections: connections::Limits {
            max_connections: 1,
            ..connections::Limits::default()
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let mut first = server.client().await;
    info(&mut first).await;
    // A stream open on the only connection: a call in flight, so it is not shed for another.
    let mut stream = first
        .rollout(rollout(1000, None))
        .await
        .unwrap()
        .into_inner();
    stream.message().await.unwrap().unwrap();
    let mut second = server.client().await;
    let refused = second
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(
        refused.message().contains("maximum of 1 connections"),
        "{}",
        refused.message()
    );
    // The first connection is served as before.
    info(&mut first).await;
    stream.message().await.unwrap().unwrap();
    drop(stream);
    server.stop().await;
}

#[tokio::test]
async fn a_draining_server_answers_new_calls_unavailable() {
    let mut server = TestServer::start().await;
    let mut c = server.client().await;
    // A stream in flight keeps the server draining rather than stopped.
    let mut reader = server.client().await;
    let mut stream = reader
        .rollout(rollout(1000, None))
        .await
        .unwrap()
        .into_inner();
    stream.message().await.unwrap().unwrap();
    info(&mut c).await;
    server.trigger_stop();
    let started = std::time::Instant::now();
    // The shutdown future runs on the server's task: poll until it has started draining.
    let status = loop {
        match c.server_info(pb::ServerInfoRequest {}).await {
            Err(status) => break status,
            Ok(_) => {
                assert!(started.elapsed() < PATIENCE, "never started draining");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    // A new connection is refused: nothing listens any more.
    let refused = tokio::time::timeout(
        PATIENCE,
        DinerDashClient::connect(format!("http://{}", server.addr)),
    )
    .await
    .expect("connecting to a draining server hung");
    assert!(refused.is_err());
    // The stream ends within its drain deadline, with UNAVAILABLE or after its episodes.
    let ended = tokio::time::timeout(PATIENCE, async {
        loop {
            match stream.message().await {
                Ok(Some(_)) => {}
                Ok(None) => break None,
                Err(status) => break Some(status.code()),
            }
        }
    })
    .await
    .expect("the stream outlived the drain");
    assert!(matches!(ended, Some(Code::Unavailable) | None), "{ended:?}");
    server.stop().await;
}

#[tokio::test]
async fn unreachable_snapshots_are_refused() {
    use dinerdash_server::session::Envs;
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let id = create(&mut c, big(2)).await;
    reset(&mut c, &id, Some(4)).await;
    step(&mut c, &id, &[0, 0]).await;
    let taken = snapshot(&mut c, &id).await;
    let mut v = serde_json::to_value(Envs::restore(&taken, 2).unwrap()).unwrap();
    v["envs"][1]["game"]["restaurant"]["queue"][0]["patience"] = i32::MAX.into();
    let bad: Envs = serde_json::from_value(v).unwrap();
    let refused = c
        .restore(pb::RestoreRequest {
            snapshot: bad.snapshot(),
        })
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::InvalidArgument);
    assert_eq!(
        refused.message(),
        "snapshot: environment 1: inconsistent game state: queue"
    );
    // The untouched snapshot is still welcome.
    restore(&mut c, taken).await;
    server.stop().await;
}

/// One raw HTTP request to the metrics endpoint; the whole response.
async fn get_metrics(addr: std::net::SocketAddr, header: &str) -> String {
    let request = format!("GET /metrics HTTP/1.1\r\nHost: localhost\r\n{header}\r\n");
    http_exchange(addr, &request).await.1
}

#[tokio::test]
async fn metrics_ask_for_the_servers_token() {
    let config = ServerConfig {
        auth_token: Some("s3cret-0123456789".into()),
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, true).await;
    let addr = server.metrics_addr.unwrap();
    let without = get_metrics(addr, "").await;
    assert!(without.starts_with("HTTP/1.1 401"), "{without}");
    let wrong = get_metrics(addr, "Authorization: Bearer nope\r\n").await;
    assert!(wrong.starts_with("HTTP/1.1 401"), "{wrong}");
    let with = get_metrics(addr, "authorization: Bearer s3cret-0123456789\r\n").await;
    assert!(with.starts_with("HTTP/1.1 200 OK"), "{with}");
    assert_eq!(metric(&with, "dinerdash_live_sessions"), 0);
    server.stop().await;
}

#[tokio::test]
async fn a_rollout_stops_at_its_work_cap() {
    let config = ServerConfig {
        rollout: dinerdash_server::rollout::Limits {
            max_work_steps: 1000,
        },
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let mut c = server.client().await;
    assert_eq!(info(&mut c).await.max_rollout_work_steps, 1000);
    let mut stream = c.rollout(rollout(100, None)).await.unwrap().into_inner();
    let mut steps = 0;
    let status = loop {
        match stream.message().await {
            Ok(Some(episode)) => {
                assert!(
                    episode.terminated,
                    "a whole episode, not one cut by the cap"
                );
                steps += episode.steps;
            }
            Ok(None) => panic!("100 expert episodes fit in 1,000 steps?"),
            Err(status) => break status,
        }
    };
    assert!(steps <= 1000);
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(
        status.message().contains("work cap of 1000 steps"),
        "{}",
        status.message()
    );
    server.stop().await;
}
