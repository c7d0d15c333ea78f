//! Connection shedding (issue 22). The real binary at `ulimit -n 1024`, held by 1,100 silent
//! connections, serves another client while they still hold it (not after they time out) and
//! idles under 30 % of a core; in process: a connection that sends no HTTP/2 preface is closed,
//! and an idle connection makes room for a new one while its session lives on. (Busy connections
//! are never shed:
//! `grpc_hostile::connections_over_the_limit_are_answered_resource_exhausted`.)

use crate::binary_support;
use crate::grpc_support;

use std::io::{ErrorKind, Read};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::connections;
use dinerdash_server::connections::fd_limit::{self, Capacity};
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::ServerConfig;
use grpc_support::{PATIENCE, TestServer, create, create_request, scrape, step};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::Code;
use tonic::transport::Channel;

/// The broken client's connections: more than the server has descriptors.
const SILENT: usize = 1100;
/// The server's open-file limit, soft and hard.
const SERVER_NOFILE: u64 = 1024;

/// Whether the server has closed this connection (EOF or an error), reading what it sent (its
/// HTTP/2 SETTINGS) without waiting.
fn closed_by_server(socket: &mut TcpStream) -> bool {
    let mut buf = [0u8; 256];
    loop {
        match socket.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => {}
            Err(e) if e.kind() == ErrorKind::WouldBlock => return false,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(_) => return true,
        }
    }
}

fn count_closed(silent: &mut [TcpStream]) -> usize {
    silent
        .iter_mut()
        .map(closed_by_server)
        .filter(|&c| c)
        .count()
}

/// Connects, creates a session, resets and steps it: a client's first moments.
async fn create_and_step(url: String) -> Result<(), Box<dyn std::error::Error>> {
    let mut client = DinerDashClient::connect(url).await?;
    let id = client
        .create_session(create_request(4, pb::AutoresetMode::NextStep, Some(1)))
        .await?
        .into_inner()
        .session_id;
    client
        .reset(pb::ResetRequest {
            session_id: id.clone(),
            ..Default::default()
        })
        .await?;
    client
        .step(pb::StepRequest {
            session_id: id,
            actions: grpc_support::pack(&[0; 4]),
        })
        .await?;
    Ok(())
}

#[tokio::test]
async fn at_the_file_limit_silent_connections_make_room_for_a_client() {
    // This process holds the silent connections: it needs the descriptors too.
    let ours = fd_limit::raise().and_then(|r| r.soft);
    assert!(
        ours.is_none_or(|n| n > SILENT as u64 + 64),
        "this test needs an open-file limit above {SILENT}"
    );
    let server = Process::start(
        &format!("ulimit -n {SERVER_NOFILE} &&"),
        // All from one address: its cap on connections without a call (a quarter of the
        // limit) would shed them before the limit this test is about.
        "--idle-timeout 1h --log-format json --max-connections-per-address 100000",
    );
    let capacity = Capacity::for_limit(connections::DEFAULT_MAX_CONNECTIONS, Some(SERVER_NOFILE));

    // The broken client: connects and never sends a byte.
    let connecting = Instant::now();
    let addr = server.addr.clone();
    let mut silent = tokio::task::spawn_blocking(move || {
        (0..SILENT)
            .map(|_| {
                let s = TcpStream::connect(&addr).unwrap();
                s.set_nonblocking(true).unwrap();
                s
            })
            .collect::<Vec<_>>()
    })
    .await
    .unwrap();

    let connected = connecting.elapsed();
    // Another client, queued behind all of them.
    let started = Instant::now();
    let served = tokio::time::timeout(PATIENCE, create_and_step(format!("http://{}", server.addr)))
        .await
        .expect("the client was never served");
    let to_serve = started.elapsed();
    served.unwrap();
    let sockets = server.sockets();
    let closed_when_served = count_closed(&mut silent);

    // The server idles, the silent connections still open.
    let before = server.cpu_ticks();
    let window = Instant::now();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let ticks = server.cpu_ticks() - before;
    // Clock ticks are 1/100 s on Linux: ticks per second is per cent of a core.
    let cpu_percent = ticks as f64 / window.elapsed().as_secs_f64();

    // The rest are closed for never sending the preface (3 s after they were accepted).
    let closing = Instant::now();
    let mut closed = count_closed(&mut silent);
    while closed < SILENT && closing.elapsed() < PATIENCE {
        tokio::time::sleep(Duration::from_millis(50)).await;
        closed = count_closed(&mut silent);
    }
    let all_closed_after = started.elapsed();

    println!(
        "server at ulimit -n {SERVER_NOFILE} (max {} connections), {SILENT} silent connections \
         (made in {:.0} ms): client served (connect, create, reset, step) in {:.0} ms; {closed_when_served} silent \
         connections closed by then and {sockets} sockets open in the server; idle CPU \
         {cpu_percent:.1} % of a core; all {closed} silent connections closed {:.1} s after the \
         client started",
        capacity.max_connections,
        connected.as_secs_f64() * 1000.0,
        to_serve.as_secs_f64() * 1000.0,
        all_closed_after.as_secs_f64(),
    );
    // Served while silent connections still held the server: by shedding, not because every
    // one of them had timed out for want of a preface.
    assert!(
        closed_when_served < SILENT,
        "the client was served only after all {SILENT} silent connections were closed"
    );
    assert!(
        cpu_percent < 30.0,
        "{cpu_percent:.1} % of a core with silent connections held"
    );
    assert_eq!(closed, SILENT, "silent connections left open");
    // Never more sockets than the cap, those on their way out and the listener.
    assert!(
        sockets <= capacity.max_connections + capacity.max_over_limit + 1,
        "{sockets} sockets at {capacity:?}"
    );

    drop(silent);
    let (status, stderr) = server.terminate().await;
    assert_eq!(status.code(), Some(0), "{stderr}");
    // The limit was capped and logged; accept never ran out of descriptors.
    assert!(
        stderr.contains("connection limit capped below the open-file limit")
            && stderr.contains(&format!("\"max_connections\":{}", capacity.max_connections)),
        "no cap logged:\n{stderr}"
    );
    // Shedding made room, unless this machine took so long to connect that the first silent
    // connections were closed for want of a preface before the last arrived.
    if connected < Duration::from_secs(2) {
        assert!(
            stderr.contains("at the connection limit: closing the longest-idle connection"),
            "no shedding logged:\n{stderr}"
        );
    }
    assert!(
        !stderr.contains("cannot accept connections"),
        "accept ran out of descriptors:\n{stderr}"
    );
}

async fn info(c: &mut DinerDashClient<Channel>) -> Result<(), tonic::Status> {
    c.server_info(pb::ServerInfoRequest {}).await.map(|_| ())
}

fn config(limits: connections::Limits) -> ServerConfig {
    ServerConfig {
        connections: limits,
        ..ServerConfig::default()
    }
}

#[tokio::test]
async fn a_connection_without_the_preface_is_closed() {
    let server = TestServer::start_with(
        config(connections::Limits {
            preface_timeout: Duration::from_millis(300),
            ..connections::Limits::default()
        }),
        true,
    )
    .await;
    let mut silent = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    // Most of the preface, then nothing: a slow client is not given more time.
    let mut partial = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    partial.write_all(b"PRI * HTTP/2.0\r\n").await.unwrap();
    let mut client = server.client().await;
    for socket in [&mut silent, &mut partial] {
        let mut sent = Vec::new();
        tokio::time::timeout(PATIENCE, socket.read_to_end(&mut sent))
            .await
            .expect("a connection without the preface was never closed")
            .ok();
    }
    // A client that sent it is served on the same connection long after the preface timeout.
    tokio::time::sleep(Duration::from_millis(500)).await;
    info(&mut client).await.unwrap();
    let metrics = scrape(server.metrics_addr.unwrap()).await;
    assert!(
        metrics.contains("\ndinerdash_connections_without_preface_total 2\n"),
        "{metrics}"
    );
    assert!(metrics.contains("\ndinerdash_connections_shed_total 0\n"));
    assert!(metrics.contains("\ndinerdash_over_limit_connections 0\n"));
    server.stop().await;
}

/// Calls until one succeeds: a client whose connection was shed reconnects on its next call, and
/// a call sent while the connection was closing may fail once.
async fn retried<F, T>(mut call: impl FnMut() -> F) -> T
where
    F: std::future::Future<Output = Result<T, tonic::Status>>,
{
    let started = Instant::now();
    loop {
        match call().await {
            Ok(value) => return value,
            Err(status) => {
                assert_eq!(status.code(), Code::Unavailable, "{status:?}");
                assert!(
                    started.elapsed() < PATIENCE,
                    "never reconnected: {status:?}"
                );
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    }
}

#[tokio::test]
async fn an_idle_connection_makes_room_and_its_session_lives_on() {
    let server = TestServer::start_with(
        config(connections::Limits {
            max_connections: 1,
            ..connections::Limits::default()
        }),
        true,
    )
    .await;
    let mut first = server.client().await;
    let id = create(
        &mut first,
        create_request(2, pb::AutoresetMode::NextStep, Some(7)),
    )
    .await;
    first
        .reset(pb::ResetRequest {
            session_id: id.clone(),
            ..Default::default()
        })
        .await
        .unwrap();
    let stepped = step(&mut first, &id, &[0, 0]).await;
    // The first connection is idle: the second is served in its place.
    let mut second = server.client().await;
    info(&mut second).await.unwrap();
    // The session outlived its connection: the first client reconnects and steps it on.
    let next = retried(|| {
        let mut c = first.clone();
        let request = pb::StepRequest {
            session_id: id.clone(),
            actions: grpc_support::pack(&[0, 0]),
        };
        async move { c.step(request).await }
    })
    .await
    .into_inner();
    assert_eq!(next.num_envs, stepped.num_envs);
    // At least the first connection, then the second when the first came back (the scrape is
    // HTTP, not a gRPC connection).
    let metrics = scrape(server.metrics_addr.unwrap()).await;
    let shed = metrics
        .lines()
        .find_map(|l| l.strip_prefix("dinerdash_connections_shed_total "))
        .and_then(|n| n.parse::<u64>().ok());
    assert!(shed.is_some_and(|n| n >= 1), "{metrics}");
    first
        .close_session(pb::CloseSessionRequest { session_id: id })
        .await
        .unwrap();
    server.stop().await;
}
