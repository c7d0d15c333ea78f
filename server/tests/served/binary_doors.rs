//! The real binary tried as someone on the cluster network would (issue 46, items 1 and 2):
//! every byte and every connection slot a client can make the server hold is bounded, whoever
//! sends it, with a token or without.
//!
//! - Memory: thousands of streams each holding a message one byte short of 16 KiB, unfinished,
//!   on a health Check (no token) or on Step (a tenant's token), keep the server's peak RSS
//!   (`VmHWM`) under `--max-memory` + the intake bound + [`ALLOWANCE`], and another tenant is
//!   served meanwhile.
//! - Intake: health Checks announcing 4 MiB are refused at their header, so they never hold the
//!   intake bound that a tenant's large Reset needs.
//! - Connection slots: connections that never made an authenticated call, each holding a health
//!   Watch, are shed before a tenant's: tenant B connects and is served, tenant A's idle
//!   connection stays open.
//! - Web endpoint slots (item 4): tenant A holding 32 event streams and 32 silent sockets
//!   without a token do not make the endpoint refuse tenant B.
//! - Quotas (item 5): a tenant holds at most its fair part of `--max-connections` and of the
//!   calls open at once (its streams); beyond them its calls are refused `RESOURCE_EXHAUSTED`
//!   naming the quota, and the other tenants connect and are served.
//! - One address (item 2): connections from one address that made no authenticated call hold
//!   at most a quarter of `--max-connections`; the tenants' connections from the same address
//!   stay, and a tenant still connects.
//!
//! The attacks speak raw HTTP/2 ([`h2`]) so that a message can be left unfinished. Nothing
//! depends on the machine's speed: counts are fixed, every wait is bounded by a deadline, and
//! the bounds are far from what the server holds. `DINERDASH_SERVER_EXE=/path/to/dinerdash-server`
//! runs the same attacks against another build (they fail against the build before issue 46).

use crate::binary_support;
use crate::grpc_support;

use std::net::IpAddr;
use std::time::Duration;

use binary_support::Process;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::{PATIENCE, create_request};
use prost::Message as _;
use prost::bytes::Bytes;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tonic::codegen::http;
use tonic::transport::Channel;

/// `--max-memory` of the servers under test: small, so that the bound means something.
const MAX_MEMORY: u64 = 64 << 20;
/// The intake bound at that budget: its floor, 64 MiB.
const INTAKE_BOUND: u64 = 64 << 20;
/// What the server may hold beyond those: its runtime, code and allocator slack, and what
/// the open streams cost outside the two bounds.
const ALLOWANCE: u64 = 32 << 20;
/// Connections of a memory attack.
const CONNECTIONS: usize = 24;
/// Streams each of them holds open.
const STREAMS: usize = 250;
/// The length each stream's message announces; it sends one byte less.
const ANNOUNCED: usize = 16 << 10;
/// The tenants file: two tenants.
const TENANTS: &str = "team-a team-a-token-aaaa\nteam-b team-b-token-bbbb\n";
const TOKEN_A: &str = "team-a-token-aaaa";
const TOKEN_B: &str = "team-b-token-bbbb";

/// The server under test, with the two tenants and `args`; its tenants file in `dir`.
fn start(dir: &std::path::Path, args: &str) -> Process {
    start_with(dir, TENANTS, args)
}

/// The server under test, with the tenants file `tenants` (in `dir`) and `args`.
fn start_with(dir: &std::path::Path, tenants: &str, args: &str) -> Process {
    std::fs::create_dir_all(dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(&file, tenants).unwrap();
    let args = format!(
        "--auth-tokens-file '{}' --drain-timeout 0 {args}",
        file.display()
    );
    match std::env::var("DINERDASH_SERVER_EXE") {
        Ok(exe) => Process::start_exe(&exe, "RUST_LOG=warn", &args),
        Err(_) => Process::start("RUST_LOG=warn", &args),
    }
}

/// A directory of this test's own.
fn scratch(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("dinerdash-doors-{name}-{}", std::process::id()))
}

/// The server's peak RSS (`VmHWM`), in bytes.
fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).unwrap();
    let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib << 10
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / f64::from(1 << 20)
}

/// A raw HTTP/2 connection to `addr` from `from` (a loopback address; `None`: any).
pub(crate) async fn h2_connect(addr: &str, from: Option<IpAddr>) -> h2::client::SendRequest<Bytes> {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    if let Some(ip) = from {
        socket.bind((ip, 0).into()).unwrap();
    }
    let tcp = socket.connect(addr.parse().unwrap()).await.unwrap();
    let (send, connection) = h2::client::handshake(tcp).await.unwrap();
    tokio::spawn(async move {
        let _ = connection.await;
    });
    send
}

/// The headers of a gRPC call to `path`, with `token`'s authorization if any.
pub(crate) fn grpc_headers(addr: &str, path: &str, token: Option<&str>) -> http::Request<()> {
    let mut request = http::Request::builder()
        .method("POST")
        .uri(format!("http://{addr}{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers");
    if let Some(token) = token {
        request = request.header("authorization", format!("Bearer {token}"));
    }
    request.body(()).unwrap()
}

/// A gRPC message's 5-byte header announcing `length`, then `payload`.
pub(crate) fn framed(length: usize, payload: &[u8]) -> Bytes {
    let mut out = vec![0];
    out.extend_from_slice(&u32::try_from(length).unwrap().to_be_bytes());
    out.extend_from_slice(payload);
    Bytes::from(out)
}

/// The `grpc-status` of a response: from its headers (a trailers-only answer) or trailers.
pub(crate) async fn grpc_status(response: h2::client::ResponseFuture) -> Option<u32> {
    let response = response.await.ok()?;
    let status = |headers: &http::HeaderMap| {
        headers
            .get("grpc-status")
            .and_then(|v| v.to_str().ok()?.parse().ok())
    };
    if let Some(code) = status(response.headers()) {
        return Some(code);
    }
    let mut body = response.into_body();
    while let Some(data) = body.data().await {
        let data = data.ok()?;
        let _ = body.flow_control().release_capacity(data.len());
    }
    status(&body.trailers().await.ok()??)
}

/// A unary call over a raw connection: its `grpc-status` (`None`: the connection failed).
pub(crate) async fn unary(
    send: &mut h2::client::SendRequest<Bytes>,
    addr: &str,
    path: &str,
    token: Option<&str>,
    message: &[u8],
) -> Option<u32> {
    let mut ready = send.clone().ready().await.ok()?;
    let (response, mut stream) = ready
        .send_request(grpc_headers(addr, path, token), false)
        .ok()?;
    stream
        .send_data(framed(message.len(), message), true)
        .ok()?;
    *send = ready;
    tokio::time::timeout(PATIENCE, grpc_status(response))
        .await
        .ok()?
}

/// Opens a health Watch without a token on `send`'s connection to `addr` and asserts it is
/// served (its answer's headers carry no status: the stream goes on); returns what keeps it
/// open.
pub(crate) async fn served_watch(
    send: &mut h2::client::SendRequest<Bytes>,
    addr: &str,
) -> (h2::SendStream<Bytes>, http::Response<h2::RecvStream>) {
    let mut ready = send.clone().ready().await.unwrap();
    let headers = grpc_headers(addr, "/grpc.health.v1.Health/Watch", None);
    let (response, mut stream) = ready.send_request(headers, false).unwrap();
    stream.send_data(framed(0, &[]), true).unwrap();
    *send = ready;
    let response = tokio::time::timeout(PATIENCE, response)
        .await
        .unwrap()
        .unwrap();
    assert!(
        response.headers().get("grpc-status").is_none(),
        "{response:?}"
    );
    (stream, response)
}

/// Opens [`CONNECTIONS`] × [`STREAMS`] calls to `path`, each sending a message announcing
/// [`ANNOUNCED`] bytes and one byte less, never finished; returns what keeps them open.
async fn flood(addr: &str, path: &str, token: Option<&str>) -> Vec<h2::SendStream<Bytes>> {
    let payload = vec![0x55u8; ANNOUNCED - 1];
    let message = framed(ANNOUNCED, &payload);
    let mut held = Vec::new();
    for _ in 0..CONNECTIONS {
        let mut send = h2_connect(addr, None).await;
        for _ in 0..STREAMS {
            let Ok(mut ready) = send.ready().await else {
                break;
            };
            let Ok((_response, mut stream)) =
                ready.send_request(grpc_headers(addr, path, token), false)
            else {
                break;
            };
            let _ = stream.send_data(message.clone(), false);
            held.push(stream);
            send = ready;
        }
    }
    held
}

/// A tenant's client of the server at `addr`.
async fn client(addr: &str) -> DinerDashClient<Channel> {
    DinerDashClient::connect(format!("http://{addr}"))
        .await
        .unwrap()
}

fn with_token<T>(token: &str, message: T) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    let value = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    request
}

/// Creates a session of `n` environments as `token`, resets it and steps it once: the tenant
/// is served.
async fn served(c: &mut DinerDashClient<Channel>, token: &str, n: u32) -> String {
    let request = create_request(n, pb::AutoresetMode::NextStep, Some(1));
    let id = c
        .create_session(with_token(token, request))
        .await
        .unwrap()
        .into_inner()
        .session_id;
    let reset = pb::ResetRequest {
        session_id: id.clone(),
        ..Default::default()
    };
    c.reset(with_token(token, reset)).await.unwrap();
    step(c, token, &id, n).await;
    id
}

async fn step(c: &mut DinerDashClient<Channel>, token: &str, id: &str, n: u32) {
    let step = pb::StepRequest {
        session_id: id.to_owned(),
        actions: grpc_support::pack(&vec![0; n as usize]),
    };
    let call = c.step(with_token(token, step));
    tokio::time::timeout(PATIENCE, call)
        .await
        .expect("a tenant's Step hung")
        .unwrap();
}

/// Floods `path` (with `token`, or without), watches the server's peak RSS while the streams
/// are held, and checks tenant B is served meanwhile.
async fn memory_attack(name: &str, path: &str, token: Option<&str>) {
    let dir = scratch(name);
    let server = start(&dir, &format!("--max-memory {MAX_MEMORY}"));
    let mut b = client(&server.addr).await;
    let id = served(&mut b, TOKEN_B, 16).await;
    let idle = peak_rss(server.pid());
    let held = flood(&server.addr, path, token).await;
    // The streams' bytes reach the server within moments; watch it for a while longer.
    for _ in 0..20 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        step(&mut b, TOKEN_B, &id, 16).await;
    }
    let peak = peak_rss(server.pid());
    let bound = MAX_MEMORY + INTAKE_BOUND + ALLOWANCE;
    println!(
        "{name}: {CONNECTIONS} connections x {STREAMS} streams of {} bytes unfinished ({} held \
         by the client): peak RSS {:.1} MiB (idle {:.1} MiB), bound {:.0} MiB",
        ANNOUNCED - 1,
        held.len(),
        mib(peak),
        mib(idle),
        mib(bound)
    );
    assert!(
        peak <= bound,
        "{name}: peak RSS {:.1} MiB is over --max-memory + the intake bound + {:.0} MiB",
        mib(peak),
        mib(ALLOWANCE)
    );
    drop(held);
    drop(b);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn unfinished_health_checks_without_a_token_stay_within_the_memory_bound() {
    memory_attack("health", "/grpc.health.v1.Health/Check", None).await;
}

#[tokio::test]
async fn a_tenants_unfinished_steps_stay_within_the_memory_bound() {
    memory_attack("step", "/dinerdash.v1.DinerDash/Step", Some(TOKEN_A)).await;
}

#[tokio::test]
async fn health_checks_announcing_megabytes_do_not_hold_the_intake_bound() {
    let dir = scratch("intake");
    let server = start(&dir, &format!("--max-memory {MAX_MEMORY}"));
    let addr = server.addr.clone();
    // 32 Checks each announcing 4 MiB (charged 8 MiB each before this change: the whole bound).
    let mut send = h2_connect(&addr, None).await;
    let mut answers = Vec::new();
    let mut held = Vec::new();
    for _ in 0..32 {
        let mut ready = send.ready().await.unwrap();
        let headers = grpc_headers(&addr, "/grpc.health.v1.Health/Check", None);
        let (response, mut stream) = ready.send_request(headers, false).unwrap();
        stream.send_data(framed(4 << 20, &[]), false).unwrap();
        answers.push(response);
        held.push(stream);
        send = ready;
    }
    // A tenant's Reset over 16 KiB (charged 17 times its size) is taken while they are open.
    let mut a = client(&addr).await;
    let n = 2048;
    let id = served(&mut a, TOKEN_A, n).await;
    let reset = pb::ResetRequest {
        session_id: id,
        seeds: vec![u64::MAX; n as usize],
        ..Default::default()
    };
    assert!(reset.encoded_len() > 16 << 10);
    a.reset(with_token(TOKEN_A, reset)).await.unwrap();
    // Each was refused at its header: over 1 KiB, or over the calls outside the service that
    // may be open from one address.
    for response in answers {
        let code = tokio::time::timeout(PATIENCE, grpc_status(response)).await;
        let refused = [tonic::Code::InvalidArgument, tonic::Code::ResourceExhausted];
        assert!(
            refused
                .map(|c| Some(c as u32))
                .contains(&code.ok().flatten()),
            "a health Check announcing 4 MiB was not refused at its header"
        );
    }
    drop(held);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn health_watches_without_a_token_cannot_keep_a_tenant_out() {
    let dir = scratch("slots");
    let server = start(&dir, "--max-connections 8");
    let addr = server.addr.clone();
    const INFO: &str = "/dinerdash.v1.DinerDash/ServerInfo";
    // Tenant A connects, makes a call, and stays idle.
    let mut a = h2_connect(&addr, None).await;
    assert_eq!(
        unary(&mut a, &addr, INFO, Some(TOKEN_A), &[]).await,
        Some(0)
    );
    // Eight connections without a token, each holding a health Watch (a call that never ends),
    // each from its own address (so that no cap on one address's Watches refuses them).
    let mut watches = Vec::new();
    for i in 0..8 {
        let from = IpAddr::from([127, 0, 0, 2 + i]);
        let mut send = h2_connect(&addr, Some(from)).await;
        let watch = served_watch(&mut send, &addr).await;
        watches.push((send, watch));
    }
    // Tenant B connects and is served while they hold the server.
    let mut b = client(&addr).await;
    tokio::time::timeout(PATIENCE, served(&mut b, TOKEN_B, 4))
        .await
        .expect("tenant B was not served");
    // Tenant A's idle connection was not closed for them: a call on it is answered.
    assert_eq!(
        unary(&mut a, &addr, INFO, Some(TOKEN_A), &[]).await,
        Some(0),
        "tenant A's connection was closed"
    );
    drop(watches);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Opens a connection to the web endpoint at `addr` and sends `path`'s GET as `token`; returns
/// the socket (unread beyond the status line) and the status.
async fn web_get(addr: std::net::SocketAddr, path: &str, token: &str) -> (TcpStream, u16) {
    let mut socket = TcpStream::connect(addr).await.unwrap();
    let request =
        format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {token}\r\n\r\n");
    socket.write_all(request.as_bytes()).await.unwrap();
    let mut head = [0u8; 12];
    let read = tokio::time::timeout(PATIENCE, socket.read_exact(&mut head)).await;
    assert!(read.is_ok(), "no answer from the web endpoint");
    let status = std::str::from_utf8(&head[9..12]).unwrap().parse().unwrap();
    (socket, status)
}

#[tokio::test]
async fn neither_strangers_nor_one_tenant_take_the_web_endpoints_slots() {
    let dir = scratch("web");
    let server = start(&dir, "--http-port 0");
    let mut a = client(&server.addr).await;
    let info = a.server_info(with_token(TOKEN_A, pb::ServerInfoRequest {}));
    let port = info.await.unwrap().into_inner().http_port;
    let web = std::net::SocketAddr::from(([127, 0, 0, 1], u16::try_from(port).unwrap()));
    // Tenant A holds as many event streams as the endpoint has connections.
    let mut streams = Vec::new();
    let mut served = 0;
    for _ in 0..32 {
        let (socket, status) = web_get(web, "/api/sessions/events", TOKEN_A).await;
        served += usize::from(status == 200);
        streams.push(socket);
    }
    // Then 32 silent sockets without a token.
    let mut silent = Vec::new();
    for _ in 0..32 {
        silent.push(TcpStream::connect(web).await.unwrap());
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    // Tenant B is served.
    let (_, status) = web_get(web, "/api/sessions", TOKEN_B).await;
    println!("tenant A's event streams served: {served} of 32; tenant B's request: {status}");
    assert_eq!(
        status, 200,
        "tenant B was refused while A and strangers held the endpoint"
    );
    // A's streams served before the strangers came were not closed for them.
    assert!(served > 0);
    drop((streams, silent));
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// How many calls or connections the server refused for `reason`
/// (`dinerdash_refusals_total{reason=...}`), read from its metrics as `token`.
async fn refusals(addr: &str, token: &str, reason: &str) -> u64 {
    let mut c = client(addr).await;
    let info = c.server_info(with_token(token, pb::ServerInfoRequest {}));
    let port = info.await.unwrap().into_inner().http_port;
    let web = std::net::SocketAddr::from(([127, 0, 0, 1], u16::try_from(port).unwrap()));
    let request = format!(
        "GET /metrics HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {token}\r\n\
         Connection: close\r\n\r\n"
    );
    let (status, text) = grpc_support::http_exchange(web, &request).await;
    assert_eq!(status, 200, "{text}");
    let line = format!("dinerdash_refusals_total{{reason=\"{reason}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&line))
        .map_or(0, |n| n.trim().parse().unwrap())
}

/// A held StepStream: what keeps it open.
type Held = (h2::client::SendRequest<Bytes>, h2::SendStream<Bytes>);

/// Opens a StepStream as `token` on `send` and leaves it open: held (the server answered its
/// headers and the stream goes on), or refused with its `grpc-status` and `grpc-message`.
async fn open_stream(
    send: h2::client::SendRequest<Bytes>,
    addr: &str,
    token: &str,
) -> Result<Held, (u32, String)> {
    let failed = || (u32::MAX, "the connection failed".to_owned());
    let mut ready = send.ready().await.map_err(|_| failed())?;
    let headers = grpc_headers(addr, "/dinerdash.v1.DinerDash/StepStream", Some(token));
    let (response, stream) = ready.send_request(headers, false).map_err(|_| failed())?;
    let response = tokio::time::timeout(PATIENCE, response)
        .await
        .expect("no answer to a StepStream's headers")
        .map_err(|_| failed())?;
    match tonic::Status::from_header_map(response.headers()) {
        None => Ok((ready, stream)),
        Some(status) => Err((status.code() as u32, status.message().to_owned())),
    }
}

#[tokio::test]
async fn a_tenant_holds_at_most_its_part_of_the_connections() {
    let dir = scratch("connections");
    // Two tenants: 4 connections each.
    let server = start(&dir, "--max-connections 8 --http-port 0");
    let addr = server.addr.clone();
    // Tenant A opens as many connections as the server takes, each holding a StepStream.
    let (mut held, mut refused) = (Vec::new(), Vec::new());
    for _ in 0..8 {
        match open_stream(h2_connect(&addr, None).await, &addr, TOKEN_A).await {
            Ok(stream) => held.push(stream),
            Err(refusal) => refused.push(refusal),
        }
    }
    println!(
        "tenant A's connections holding a stream: {} of 8; refused: {refused:?}",
        held.len()
    );
    // Tenant B connects and is served while A holds its part.
    let mut b = client(&addr).await;
    tokio::time::timeout(PATIENCE, served(&mut b, TOKEN_B, 4))
        .await
        .expect("tenant B was not served");
    assert_eq!(held.len(), 4, "tenant A holds more than its part");
    for (code, message) in &refused {
        assert_eq!(*code, tonic::Code::ResourceExhausted as u32, "{message}");
        assert!(
            message.contains("tenant team-a holds 4 connections")
                && message.contains("connections quota of 4"),
            "{message}"
        );
    }
    // A's held streams were not closed for it: each still takes a Step request's frame.
    for (_, stream) in &mut held {
        stream
            .send_data(framed(0, &[]), false)
            .expect("a stream of tenant A was closed");
    }
    // Each refusal is counted by its quota.
    assert_eq!(
        refusals(&addr, TOKEN_B, "connections_quota").await,
        refused.len() as u64
    );
    drop(held);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn a_tenant_holds_at_most_its_part_of_the_open_calls() {
    let dir = scratch("streams");
    // Three tenants share the calls the intake bound holds (1,365 at 64 MiB): 455 each.
    let tenants = format!("{TENANTS}team-c team-c-token-cccc\n");
    let args = format!("--max-memory {MAX_MEMORY} --http-port 0");
    let server = start_with(&dir, &tenants, &args);
    let addr = server.addr.clone();
    // Tenant A opens 600 StepStreams over 3 connections (256 streams a connection at most).
    let (mut held, mut refused) = (Vec::new(), Vec::new());
    for _ in 0..3 {
        let mut send = h2_connect(&addr, None).await;
        for _ in 0..200 {
            match open_stream(send.clone(), &addr, TOKEN_A).await {
                Ok((ready, stream)) => {
                    send = ready;
                    held.push(stream);
                }
                Err(refusal) => refused.push(refusal),
            }
        }
    }
    println!(
        "tenant A's StepStreams held: {} of 600; refused: {} ({:?})",
        held.len(),
        refused.len(),
        refused.first()
    );
    assert_eq!(held.len(), 455, "tenant A holds more than its part");
    for (code, message) in &refused {
        assert_eq!(*code, tonic::Code::ResourceExhausted as u32, "{message}");
        assert!(
            message.contains("tenant team-a has 455 calls open, its streams quota of 455"),
            "{message}"
        );
    }
    // Tenants B and C are served meanwhile, and each may open as many.
    for token in [TOKEN_B, "team-c-token-cccc"] {
        let mut c = client(&addr).await;
        tokio::time::timeout(PATIENCE, served(&mut c, token, 4))
            .await
            .expect("another tenant was not served");
    }
    let mut send = h2_connect(&addr, None).await;
    let mut b_held = Vec::new();
    for _ in 0..200 {
        let (ready, stream) = open_stream(send, &addr, TOKEN_B)
            .await
            .expect("tenant B's StepStream was refused");
        send = ready;
        b_held.push(stream);
    }
    assert_eq!(
        refusals(&addr, TOKEN_B, "streams_quota").await,
        refused.len() as u64
    );
    drop((held, b_held));
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test]
async fn strangers_from_one_address_hold_at_most_a_quarter_of_the_connections() {
    let dir = scratch("address");
    // A quarter of 32: 8 connections without an authenticated call from one address.
    let server = start(&dir, "--max-connections 32 --http-port 0");
    let addr = server.addr.clone();
    const INFO: &str = "/dinerdash.v1.DinerDash/ServerInfo";
    // Tenant A's 6 connections, from the address the strangers will use.
    let mut tenant = Vec::new();
    for _ in 0..6 {
        let mut send = h2_connect(&addr, None).await;
        assert_eq!(
            unary(&mut send, &addr, INFO, Some(TOKEN_A), &[]).await,
            Some(0)
        );
        tenant.push(send);
    }
    // 24 connections without a token from that address: the HTTP/2 handshake, then silence.
    let mut strangers = Vec::new();
    for _ in 0..24 {
        let tcp = TcpStream::connect(&addr).await.unwrap();
        let (send, connection) = h2::client::handshake(tcp).await.unwrap();
        strangers.push((send, tokio::spawn(connection)));
    }
    let open = |strangers: &[(_, tokio::task::JoinHandle<_>)]| {
        strangers.iter().filter(|(_, c)| !c.is_finished()).count()
    };
    let deadline = tokio::time::Instant::now() + PATIENCE;
    while open(&strangers) > 8 && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let left = open(&strangers);
    println!("strangers' connections from one address still open: {left} of 24");
    assert!(
        left <= 8,
        "{left} connections without a token from one address are open"
    );
    // The tenant's connections from that address stay, and another tenant connects.
    for send in &mut tenant {
        assert_eq!(
            unary(send, &addr, INFO, Some(TOKEN_A), &[]).await,
            Some(0),
            "a connection of tenant A was closed"
        );
    }
    let mut b = client(&addr).await;
    tokio::time::timeout(PATIENCE, served(&mut b, TOKEN_B, 4))
        .await
        .expect("tenant B was not served");
    // Each stranger's connection closed for the cap is counted.
    let closed = refusals(&addr, TOKEN_B, "address_cap").await;
    assert!(
        closed >= 16,
        "{closed} connections closed for the address's cap"
    );
    drop(strangers);
    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}
