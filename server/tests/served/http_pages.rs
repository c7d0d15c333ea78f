//! The HTTP endpoint's routes against an in-process server on 127.0.0.1:0: the pages and their
//! status codes, the JSON and event feeds following a session as a client steps it, ServerInfo
//! naming the endpoint, and tokens choosing which sessions a viewer sees.

use crate::grpc_support;

use std::net::SocketAddr;
use std::sync::Arc;

use dinerdash_server::auth::Token;
use dinerdash_server::budget::{Share, Tenant};
use dinerdash_server::pb;
use dinerdash_server::server::ServerConfig;
use grpc_support::{PATIENCE, TestServer, create, create_request, reset, step};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// A whole HTTP response: status code, head, body.
struct Reply {
    status: u16,
    head: String,
    body: String,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_str(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.body))
    }
}

/// `GET path` with `token` as a bearer token, if any.
async fn get(addr: SocketAddr, path: &str, token: Option<&str>) -> Reply {
    request(addr, "GET", path, token).await
}

async fn request(addr: SocketAddr, method: &str, path: &str, token: Option<&str>) -> Reply {
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    raw(
        addr,
        &format!("{method} {path} HTTP/1.1\r\nHost: localhost\r\n{auth}\r\n"),
    )
    .await
}

/// Sends `head` as it is and reads the whole reply.
async fn raw(addr: SocketAddr, head: &str) -> Reply {
    let (status, text) = grpc_support::http_exchange(addr, head).await;
    let (head, body) = text.split_once("\r\n\r\n").unwrap();
    Reply {
        status,
        head: head.to_owned(),
        body: body.to_owned(),
    }
}

/// An open event stream: its body arrives in HTTP/1.1 chunks, decoded here.
struct Events {
    stream: TcpStream,
    /// Bytes read and not yet decoded (chunk sizes and data).
    raw: String,
    /// The decoded body not yet returned as blocks.
    buffer: String,
}

impl Events {
    async fn open(addr: SocketAddr, path: &str) -> Events {
        let mut stream = TcpStream::connect(addr).await.unwrap();
        let head = format!("GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n");
        stream.write_all(head.as_bytes()).await.unwrap();
        let mut events = Events {
            stream,
            raw: String::new(),
            buffer: String::new(),
        };
        while !events.raw.contains("\r\n\r\n") {
            events.read().await;
        }
        let end = events.raw.find("\r\n\r\n").unwrap();
        let head: String = events.raw.drain(..end + 4).collect();
        assert!(head.starts_with("HTTP/1.1 200 OK"), "{head}");
        assert!(head.contains("text/event-stream"), "{head}");
        let lower = head.to_ascii_lowercase();
        assert!(lower.contains("transfer-encoding: chunked"), "{head}");
        events
    }

    /// Reads what has arrived into `raw`.
    async fn read(&mut self) {
        let mut buf = [0u8; 4096];
        let n = tokio::time::timeout(PATIENCE, self.stream.read(&mut buf))
            .await
            .expect("no event in time")
            .unwrap();
        assert!(n > 0, "the stream ended");
        self.raw.push_str(std::str::from_utf8(&buf[..n]).unwrap());
    }

    /// Moves the whole chunks of `raw` into `buffer`.
    fn dechunk(&mut self) {
        while let Some(line) = self.raw.find("\r\n") {
            let size = usize::from_str_radix(self.raw[..line].trim(), 16).unwrap();
            let end = line + 2 + size + 2;
            if self.raw.len() < end {
                return;
            }
            self.buffer.push_str(&self.raw[line + 2..line + 2 + size]);
            self.raw.drain(..end);
        }
    }

    /// The next event block, up to its blank line.
    async fn block(&mut self) -> String {
        loop {
            self.dechunk();
            if let Some(end) = self.buffer.find("\n\n") {
                let block = self.buffer[..end].to_owned();
                self.buffer.drain(..end + 2);
                return block;
            }
            self.read().await;
        }
    }

    /// The next data event as JSON (skipping comments), or the name of a named event.
    async fn next(&mut self) -> Result<Value, String> {
        loop {
            let block = self.block().await;
            if let Some(name) = block.strip_prefix("event: ") {
                return Err(name.lines().next().unwrap_or_default().to_owned());
            }
            if let Some(data) = block.strip_prefix("data: ") {
                return Ok(serde_json::from_str(data).unwrap());
            }
        }
    }
}

async fn http_server(config: ServerConfig) -> (TestServer, SocketAddr) {
    let server = TestServer::start_with(config, true).await;
    let addr = server.metrics_addr.unwrap();
    (server, addr)
}

#[tokio::test]
async fn pages_feeds_and_status_codes() {
    let (server, addr) = http_server(ServerConfig::default()).await;
    let mut c = server.client().await;
    let info = c
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.http_port, u32::from(addr.port()));
    assert_eq!(info.http_host, "127.0.0.1");

    let page = get(addr, "/", None).await;
    assert_eq!(page.status, 200);
    assert!(page.head.contains("text/html"));
    assert!(page.body.contains("/static/sessions.js"));
    for file in [
        "style.css",
        "common.js",
        "sessions.js",
        "board.js",
        "watch.js",
    ] {
        assert_eq!(
            get(addr, &format!("/static/{file}"), None).await.status,
            200
        );
    }
    assert_eq!(get(addr, "/static/nope.js", None).await.status, 404);
    assert_eq!(get(addr, "/nowhere", None).await.status, 404);
    assert_eq!(request(addr, "POST", "/", None).await.status, 405);
    let head = request(addr, "HEAD", "/", None).await;
    assert_eq!((head.status, head.body.as_str()), (200, ""));
    let metrics = get(addr, "/metrics", None).await;
    assert!(metrics.body.contains("dinerdash_live_sessions 0"));
    assert!(
        metrics.head.contains("text/plain; version=0.0.4"),
        "{}",
        metrics.head
    );
    // Every response: one request a connection, never cached, no sniffing, nothing from
    // elsewhere (header names compared in lower case, as HTTP does).
    let head = page.head.to_ascii_lowercase();
    for header in [
        "connection: close",
        "cache-control: no-store",
        "x-content-type-options: nosniff",
        "referrer-policy: no-referrer",
        "content-security-policy: default-src 'self'",
    ] {
        assert!(head.contains(header), "{header} missing in {head}");
    }
    // hyper refuses what is not a request, and request heads past 8 KiB.
    assert_eq!(raw(addr, "hello\r\n\r\n").await.status, 400);
    let huge = format!("GET / HTTP/1.1\r\nX-Big: {}\r\n\r\n", "x".repeat(16 << 10));
    assert_eq!(raw(addr, &huge).await.status, 431);

    let id = create(
        &mut c,
        create_request(3, pb::AutoresetMode::NextStep, Some(2)),
    )
    .await;
    let unknown = "0123456789abcdef0123456789abcdef";
    let missing = get(addr, &format!("/watch/{unknown}?env=0"), None).await;
    assert_eq!(missing.status, 404);
    assert!(
        missing.body.contains("Session not found"),
        "{}",
        missing.body
    );
    assert!(missing.body.contains(unknown));
    assert_eq!(get(addr, "/watch/short", None).await.status, 404);
    let watch = get(addr, &format!("/watch/{id}?env=2"), None).await;
    assert_eq!(watch.status, 200);
    assert!(watch.body.contains("<canvas"));
    let api = |path: String| async move { get(addr, &path, None).await };
    assert_eq!(api(format!("/api/watch/{unknown}")).await.status, 404);
    assert_eq!(api(format!("/api/watch/{id}?env=3")).await.status, 400);
    assert_eq!(api(format!("/api/watch/{id}?env=x")).await.status, 400);

    // Before the first reset there is nothing to draw.
    let frame = api(format!("/api/watch/{id}?env=1")).await.json();
    assert_eq!(frame["started"], false);
    assert_eq!(frame["num_envs"], 3);

    let mut events = Events::open(addr, &format!("/api/watch/{id}/events?env=1")).await;
    let first = events.next().await.unwrap();
    assert_eq!(first["started"], false);
    let batch = reset(&mut c, &id, Some(5)).await;
    let after_reset = events.next().await.unwrap();
    assert_eq!(after_reset["started"], true);
    assert_eq!(after_reset["tick"], 0);
    let obs: Vec<i8> = batch.observations[40..80]
        .iter()
        .map(|&b| b as i8)
        .collect();
    assert_eq!(after_reset["obs"], serde_json::json!(obs));
    // The session's expert (the reference) chose this action; the page shows it.
    let choice = batch.expert_actions[1];
    assert_eq!(after_reset["expert"]["action"], choice);
    assert_eq!(after_reset["expert"]["by"], "reference");
    step(&mut c, &id, &[0, i32::from(choice), 0]).await;
    let stepped = events.next().await.unwrap();
    assert_eq!(stepped["tick"], 1);
    assert_eq!(stepped["moves"][0]["action"], choice);
    assert_eq!(stepped["moves"][1]["reset"], true);
    assert_eq!(stepped["steps"], 3);

    let sessions = api("/api/sessions".into()).await.json();
    let row = &sessions["sessions"][0];
    assert_eq!(row["id"], id.as_str());
    assert_eq!(row["short"], &id[..8]);
    assert_eq!(row["envs"], 3);
    assert_eq!(row["expert"], "reference");
    assert_eq!(row["steps"], 3);
    assert_eq!(row["viewers"], 1);
    assert_eq!(sessions["totals"]["sessions"], 1);
    assert_eq!(sessions["totals"]["envs"], 3);
    assert!(sessions["totals"]["memory_used"].as_u64().unwrap() > 0);

    // The sessions stream gives rates from its second update on.
    let mut listing = Events::open(addr, "/api/sessions/events").await;
    let first = listing.next().await.unwrap();
    assert!(first["sessions"][0]["steps_per_s"].is_null());
    for _ in 0..20 {
        step(&mut c, &id, &[0, 0, 0]).await;
    }
    let second = listing.next().await.unwrap();
    assert_eq!(second["sessions"][0]["steps"], 63);
    assert!(second["sessions"][0]["steps_per_s"].as_f64().unwrap() > 0.0);

    // Closing the session ends its watch stream with a `gone` event.
    c.close_session(pb::CloseSessionRequest {
        session_id: id.clone(),
    })
    .await
    .unwrap();
    let gone = loop {
        match events.next().await {
            Ok(_) => continue,
            Err(name) => break name,
        }
    };
    assert_eq!(gone, "gone");
    assert_eq!(get(addr, &format!("/watch/{id}"), None).await.status, 404);
    server.stop().await;
}

#[tokio::test]
async fn tokens_show_each_tenant_its_own_sessions() {
    let tenant = |name: &str| Arc::new(Tenant::new(format!("tenant {name}"), Share::default()));
    let config = ServerConfig {
        auth_token: Some("shared-token-ssss".into()),
        tenants: vec![
            Token {
                token: "team-a-token-aaaa".into(),
                tenant: Some(tenant("a")),
            },
            Token {
                token: "team-b-token-bbbb".into(),
                tenant: Some(tenant("b")),
            },
        ],
        ..ServerConfig::default()
    };
    let (server, addr) = http_server(config).await;
    let mut c = server.client().await;
    let mut created = Vec::new();
    for token in [
        "team-a-token-aaaa",
        "team-b-token-bbbb",
        "shared-token-ssss",
    ] {
        let mut request = tonic::Request::new(create_request(1, pb::AutoresetMode::NextStep, None));
        let value = format!("Bearer {token}").parse().unwrap();
        request.metadata_mut().insert("authorization", value);
        let id = c
            .create_session(request)
            .await
            .unwrap()
            .into_inner()
            .session_id;
        created.push(id);
    }
    let [a, b, shared] = created.as_slice() else {
        unreachable!()
    };

    // The pages carry no data and load without a token; the data needs one.
    assert_eq!(get(addr, "/", None).await.status, 200);
    assert_eq!(get(addr, &format!("/watch/{a}"), None).await.status, 200);
    for path in ["/api/sessions", "/api/sessions/events", "/metrics"] {
        let refused = get(addr, path, None).await;
        assert_eq!(refused.status, 401, "{path}");
        // Header names are case-insensitive (hyper writes them in lower case).
        let head = refused.head.to_ascii_lowercase();
        assert!(head.contains("www-authenticate: bearer"), "{head}");
        assert_eq!(get(addr, path, Some("nope")).await.status, 401, "{path}");
    }
    assert_eq!(
        get(addr, "/metrics", Some("team-b-token-bbbb"))
            .await
            .status,
        200
    );
    let ids = |reply: Reply| -> Vec<String> {
        reply.json()["sessions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["id"].as_str().unwrap().to_owned())
            .collect()
    };
    assert_eq!(
        ids(get(addr, "/api/sessions", Some("team-a-token-aaaa")).await),
        [a.as_str()]
    );
    assert_eq!(
        ids(get(addr, "/api/sessions", Some("team-b-token-bbbb")).await),
        [b.as_str()]
    );
    assert_eq!(
        ids(get(addr, "/api/sessions", Some("shared-token-ssss")).await),
        [shared.as_str()]
    );
    let listing = get(addr, "/api/sessions", Some("team-a-token-aaaa"))
        .await
        .json();
    assert_eq!(listing["sessions"][0]["tenant"], "tenant a");
    // Server totals are the server's, as /metrics gives them to any token holder.
    assert_eq!(listing["totals"]["sessions"], 3);

    // Another tenant's session is not found, whatever its ID.
    let watch = |id: &str, token: &str| {
        let path = format!("/api/watch/{id}?env=0");
        let token = token.to_owned();
        async move { get(addr, &path, Some(&token)).await.status }
    };
    assert_eq!(watch(a, "team-a-token-aaaa").await, 200);
    assert_eq!(watch(a, "team-b-token-bbbb").await, 404);
    assert_eq!(watch(a, "shared-token-ssss").await, 404);
    assert_eq!(watch(shared, "shared-token-ssss").await, 200);
    assert_eq!(watch(b, "nope").await, 401);
    server.stop().await;
}

/// The viewers of a session's first row in `/api/sessions`.
async fn viewers(addr: SocketAddr) -> u64 {
    get(addr, "/api/sessions", None).await.json()["sessions"][0]["viewers"]
        .as_u64()
        .unwrap()
}

/// A viewer of the real endpoint that stops reading is cut off by the endpoint's write deadline,
/// and while it is stuck (its socket full, the server's write to it blocked) another viewer gets
/// its frames and a client's Steps are answered. Without the deadline on the endpoint's sockets
/// the stuck viewer would be kept for ever: the loop below would run out of patience.
#[tokio::test]
async fn a_viewer_that_does_not_read_is_cut_off_while_others_are_served() {
    use std::os::fd::AsFd;
    let (server, addr) = http_server(ServerConfig::default()).await;
    let mut c = server.client().await;
    let id = create(
        &mut c,
        create_request(3, pb::AutoresetMode::NextStep, Some(2)),
    )
    .await;
    reset(&mut c, &id, Some(5)).await;
    let path = format!("/api/watch/{id}/events?env=0");

    // The stuck viewer: a small receive buffer, a request, and never a read.
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let mut stuck = socket.connect(addr).await.unwrap();
    let head = format!("GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n");
    stuck.write_all(head.as_bytes()).await.unwrap();
    let mut healthy = Events::open(addr, &path).await;
    let attached = tokio::time::Instant::now() + PATIENCE;
    while viewers(addr).await != 2 {
        assert!(
            tokio::time::Instant::now() < attached,
            "the stuck viewer never attached"
        );
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }

    // Each round: a Step, the healthy viewer's frame of it, and whether the stuck viewer is
    // still attached. The stuck viewer counts as stuck once the bytes waiting in its socket stop
    // growing for three rounds although every round made a new frame.
    let deadline = tokio::time::Instant::now() + PATIENCE;
    let (mut queued, mut still, mut served_while_stuck) = (0, 0, 0);
    let mut rounds: i64 = 0;
    loop {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the stuck viewer was never cut off ({served_while_stuck} rounds served while stuck)"
        );
        step(&mut c, &id, &[0, 0, 0]).await;
        rounds += 1;
        let frame = loop {
            let frame = healthy.next().await.unwrap();
            if frame["steps"] == 3 * rounds {
                break frame;
            }
        };
        assert_eq!(frame["steps"], 3 * rounds);
        if viewers(addr).await < 2 {
            break;
        }
        let now = rustix::io::ioctl_fionread(stuck.as_fd()).unwrap();
        if now > 0 && now == queued {
            still += 1;
        } else {
            still = 0;
        }
        queued = now;
        if still >= 3 {
            served_while_stuck += 1;
        }
    }
    // A blocked write is given WRITE_TIMEOUT, ~60 frame intervals: rounds go on meanwhile.
    assert!(
        served_while_stuck >= 1,
        "no round was served while the viewer was stuck"
    );
    println!("{served_while_stuck} of {rounds} rounds served while the viewer was stuck");

    // The stuck viewer's connection ends: what was queued, then the end (or a reset).
    let ended = tokio::time::timeout(PATIENCE, async {
        let mut buf = vec![0u8; 64 << 10];
        loop {
            match stuck.read(&mut buf).await {
                Ok(0) | Err(_) => break,
                Ok(_) => continue,
            }
        }
    })
    .await;
    assert!(ended.is_ok(), "the stuck viewer's connection stayed open");
    // The healthy viewer goes on.
    step(&mut c, &id, &[0, 0, 0]).await;
    loop {
        if healthy.next().await.unwrap()["steps"] == 3 * (rounds + 1) {
            break;
        }
    }
    server.stop().await;
}

#[tokio::test]
async fn connections_past_the_limit_are_answered_503() {
    use dinerdash_server::http::MAX_CONNECTIONS;
    let (server, addr) = http_server(ServerConfig::default()).await;
    let mut streams = Vec::new();
    for _ in 0..MAX_CONNECTIONS {
        streams.push(Events::open(addr, "/api/sessions/events").await);
    }
    let busy = get(addr, "/", None).await;
    assert_eq!(busy.status, 503, "{}", busy.body);
    assert!(busy.body.contains("maximum"), "{}", busy.body);
    drop(streams);
    // The slots come back as the streams close.
    let mut status = 0;
    for _ in 0..200 {
        status = get(addr, "/", None).await.status;
        if status == 200 {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert_eq!(status, 200);
    server.stop().await;
}
