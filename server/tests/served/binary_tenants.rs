//! The real binary with two tenants (`--auth-tokens-file`), tried as a hostile tenant would (issue
//! 34): every call that names a session, given another tenant's session ID, answers exactly as
//! for an ID that never existed (code, message and details, the ID substituted), and the owner's
//! session is untouched (its next Step's whole reply equals an undisturbed twin's, a planner
//! session's too). Sessions a tenant forks or restores are its own; the web feeds answer the
//! other tenant's session as unknown, and its listings (`/api/sessions` and the event feed
//! `/api/sessions/events`) hold only its own sessions.

use crate::binary_support;
use crate::grpc_support;

use std::net::SocketAddr;

use binary_support::Process;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::{create_request, pack};
use tonic::transport::Channel;
use tonic::{Request, Status};

/// Tenant A's token (at least 16 characters, no `#`).
const TOKEN_A: &str = "tenant-a-token-7Hq2Lx9Pz4";
/// Tenant B's token.
const TOKEN_B: &str = "tenant-b-token-3Vd8Kw1Ns6";
/// A well-formed session ID that no session has.
const UNKNOWN: &str = "0123456789abcdef0123456789abcdef";

/// One tenant's client: every request carries its token.
struct Tenant {
    client: DinerDashClient<Channel>,
    token: &'static str,
}

impl Tenant {
    fn request<T>(&self, message: T) -> Request<T> {
        let mut request = Request::new(message);
        let value = format!("Bearer {}", self.token).parse().unwrap();
        request.metadata_mut().insert("authorization", value);
        request
    }

    async fn create(&mut self, expert: pb::Policy, seed: u64) -> String {
        let message = pb::CreateSessionRequest {
            expert_policy: expert.into(),
            ..create_request(2, pb::AutoresetMode::NextStep, Some(seed))
        };
        let request = self.request(message);
        self.client
            .create_session(request)
            .await
            .unwrap()
            .into_inner()
            .session_id
    }

    async fn reset(&mut self, id: &str) -> Result<pb::Batch, Status> {
        let request = self.request(pb::ResetRequest {
            session_id: id.to_owned(),
            ..Default::default()
        });
        self.client.reset(request).await.map(|r| r.into_inner())
    }

    async fn step(&mut self, id: &str, actions: &[i32]) -> Result<pb::Batch, Status> {
        let request = self.request(pb::StepRequest {
            session_id: id.to_owned(),
            actions: pack(actions),
        });
        self.client.step(request).await.map(|r| r.into_inner())
    }

    /// One request on a StepStream: its reply.
    async fn step_stream(&mut self, id: &str) -> Result<pb::Batch, Status> {
        let message = pb::StepRequest {
            session_id: id.to_owned(),
            actions: pack(&[0, 0]),
        };
        let request = self.request(tokio_stream::iter([message]));
        let mut replies = self.client.step_stream(request).await?.into_inner();
        match replies.message().await {
            Ok(Some(batch)) => Ok(batch),
            Ok(None) => panic!("the stream ended without a reply"),
            Err(status) => Err(status),
        }
    }

    async fn close(&mut self, id: &str) -> Result<(), Status> {
        let request = self.request(pb::CloseSessionRequest {
            session_id: id.to_owned(),
        });
        self.client.close_session(request).await.map(|_| ())
    }

    async fn fork(&mut self, id: &str) -> Result<String, Status> {
        let request = self.request(pb::ForkRequest {
            session_id: id.to_owned(),
        });
        let reply = self.client.fork(request).await?;
        Ok(reply.into_inner().session_id)
    }

    async fn snapshot(&mut self, id: &str) -> Result<Vec<u8>, Status> {
        let request = self.request(pb::SnapshotRequest {
            session_id: id.to_owned(),
            ..Default::default()
        });
        Ok(self.client.snapshot(request).await?.into_inner().snapshot)
    }

    async fn restore(&mut self, snapshot: Vec<u8>) -> Result<String, Status> {
        let request = self.request(pb::RestoreRequest { snapshot });
        Ok(self.client.restore(request).await?.into_inner().session_id)
    }

    async fn render(&mut self, id: &str) -> Result<String, Status> {
        let request = self.request(pb::RenderRequest {
            session_id: id.to_owned(),
            env_index: 1,
            color: false,
        });
        Ok(self.client.render(request).await?.into_inner().text)
    }

    /// Every call that names a session, on `id`: each one's status, labelled.
    async fn every_call(&mut self, id: &str) -> Vec<(&'static str, Status)> {
        let refused = |what: &'static str, result: Result<(), Status>| match result {
            Ok(()) => panic!("{what} of {id} was served"),
            Err(status) => (what, status),
        };
        vec![
            refused("Reset", self.reset(id).await.map(drop)),
            refused("Step", self.step(id, &[0, 0]).await.map(drop)),
            refused("StepStream", self.step_stream(id).await.map(drop)),
            refused("Render", self.render(id).await.map(drop)),
            refused("Snapshot", self.snapshot(id).await.map(drop)),
            refused("Fork", self.fork(id).await.map(drop)),
            refused("CloseSession", self.close(id).await),
        ]
    }
}

/// `bytes` with every occurrence of `from` replaced by `to` (of the same length).
fn substitute(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    assert_eq!(from.len(), to.len());
    let mut out = bytes.to_vec();
    let mut i = 0;
    while i + from.len() <= out.len() {
        if &out[i..i + from.len()] == from.as_bytes() {
            out[i..i + from.len()].copy_from_slice(to.as_bytes());
            i += from.len();
        } else {
            i += 1;
        }
    }
    out
}

/// Asserts that tenant `b`'s calls on `id` (not its own) answer exactly as on [`UNKNOWN`].
async fn answered_as_unknown(b: &mut Tenant, id: &str) {
    let foreign = b.every_call(id).await;
    let unknown = b.every_call(UNKNOWN).await;
    for ((what, on_id), (_, on_unknown)) in foreign.iter().zip(&unknown) {
        assert_eq!(
            on_unknown.code(),
            tonic::Code::NotFound,
            "{what}: {on_unknown:?}"
        );
        assert_eq!(on_id.code(), on_unknown.code(), "{what}: {on_id:?}");
        assert_eq!(
            on_id.message().replace(id, UNKNOWN),
            on_unknown.message(),
            "{what}"
        );
        assert!(on_id.message().contains(id), "{what}: {on_id:?}");
        assert_eq!(
            substitute(on_id.details(), id, UNKNOWN),
            on_unknown.details(),
            "{what}"
        );
    }
}

/// A GET of the web endpoint with `token`: the status and the body.
async fn get(addr: SocketAddr, path: &str, token: &str) -> (u16, String) {
    let head = format!(
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\n\
         Connection: close\r\n\r\n"
    );
    let (status, text) = grpc_support::http_exchange(addr, &head).await;
    (status, text.split_once("\r\n\r\n").unwrap().1.to_owned())
}

/// The head and first event of the event feed at `path`, read with `token` (the feed itself
/// never ends: the connection is dropped after its first event).
async fn first_event(addr: SocketAddr, path: &str, token: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head =
        format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\n\r\n");
    stream.write_all(head.as_bytes()).await.unwrap();
    let mut text = Vec::new();
    let read = async {
        loop {
            let mut chunk = [0u8; 4096];
            let n = stream.read(&mut chunk).await.unwrap();
            assert!(n > 0, "the feed closed: {}", String::from_utf8_lossy(&text));
            text.extend_from_slice(&chunk[..n]);
            let so_far = String::from_utf8_lossy(&text);
            if let Some((head, body)) = so_far.split_once("\r\n\r\n") {
                assert!(head.starts_with("HTTP/1.1 200"), "{head}");
                if body
                    .split_once("data:")
                    .is_some_and(|(_, e)| e.contains("\n\n"))
                {
                    return so_far.into_owned();
                }
            }
        }
    };
    tokio::time::timeout(grpc_support::PATIENCE, read)
        .await
        .expect("no first event")
}

#[tokio::test]
async fn another_tenants_session_answers_as_an_unknown_id() {
    let dir = std::env::temp_dir().join(format!("dinerdash-owners-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(&file, format!("team-a {TOKEN_A}\nteam-b {TOKEN_B}\n")).unwrap();
    let server = Process::start(
        "",
        &format!("--auth-tokens-file '{}' --http-port 0", file.display()),
    );
    let url = format!("http://{}", server.addr);
    let mut a = Tenant {
        client: DinerDashClient::connect(url.clone()).await.unwrap(),
        token: TOKEN_A,
    };
    let mut b = Tenant {
        client: DinerDashClient::connect(url.clone()).await.unwrap(),
        token: TOKEN_B,
    };

    // A's session and its twin (same seed, same actions); a planner session, whose calls run
    // on the CPU pool.
    let mine = a.create(pb::Policy::Expert, 7).await;
    let twin = a.create(pb::Policy::Expert, 7).await;
    let planned = a.create(pb::Policy::Planner, 8).await;
    let planned_twin = a.create(pb::Policy::Planner, 8).await;
    for id in [&mine, &twin, &planned, &planned_twin] {
        a.reset(id).await.unwrap();
        for t in 0..5 {
            a.step(id, &[t % 3, 1]).await.unwrap();
        }
    }

    for id in [&mine, &planned] {
        answered_as_unknown(&mut b, id).await;
    }

    // Untouched: the next Step of each of A's sessions is its twin's, the whole reply.
    for (id, twin) in [(&mine, &twin), (&planned, &planned_twin)] {
        let next = a.step(id, &[2, 0]).await.unwrap();
        let twins = a.step(twin, &[2, 0]).await.unwrap();
        assert_eq!(next, twins);
    }
    // The owner's Render, Snapshot and Fork of the planner session are served (off the async
    // workers).
    assert!(!a.render(&planned).await.unwrap().is_empty());
    let forked = a.fork(&planned).await.unwrap();
    a.step(&forked, &[0, 0]).await.unwrap();
    assert!(!a.snapshot(&planned).await.unwrap().is_empty());

    // B's forks and restores of its own sessions are B's: A cannot see them.
    let own = b.create(pb::Policy::Expert, 9).await;
    b.reset(&own).await.unwrap();
    let fork = b.fork(&own).await.unwrap();
    let snapshot = b.snapshot(&own).await.unwrap();
    let restored = b.restore(snapshot).await.unwrap();
    for id in [&own, &fork, &restored] {
        b.step(id, &[0, 0]).await.unwrap();
        answered_as_unknown(&mut a, id).await;
    }
    // A Restore of A's snapshot by B is B's, not A's.
    let copied = b.restore(a.snapshot(&mine).await.unwrap()).await.unwrap();
    answered_as_unknown(&mut a, &copied).await;

    // The web feeds: B's token finds A's session as it finds an unknown one, and lists only
    // B's sessions.
    let mut info = b.client.clone();
    let info = info
        .server_info(b.request(pb::ServerInfoRequest {}))
        .await
        .unwrap()
        .into_inner();
    let http: SocketAddr = format!("127.0.0.1:{}", info.http_port).parse().unwrap();
    for path in ["/api/watch/{}?env=0", "/api/watch/{}/events?env=0"] {
        let on_a = get(http, &path.replace("{}", &mine), TOKEN_B).await;
        let on_unknown = get(http, &path.replace("{}", UNKNOWN), TOKEN_B).await;
        assert_eq!(on_a.0, 404, "{path}: {on_a:?}");
        assert_eq!(on_a, on_unknown, "{path}");
    }
    let page = get(http, &format!("/watch/{mine}"), TOKEN_B).await;
    let unknown_page = get(http, &format!("/watch/{UNKNOWN}"), TOKEN_B).await;
    assert_eq!(page, unknown_page, "the watch page tells IDs apart");
    let (status, listing) = get(http, "/api/sessions", TOKEN_B).await;
    assert_eq!(status, 200);
    let feed = first_event(http, "/api/sessions/events", TOKEN_B).await;
    for listed in [&listing, &feed] {
        for a_s in [&mine, &twin, &planned, &planned_twin] {
            assert!(
                !listed.contains(a_s.as_str()),
                "B sees A's session: {listed}"
            );
        }
        assert!(
            listed.contains(&own) && listed.contains(&copied),
            "{listed}"
        );
    }
    let (status, watched) = get(http, &format!("/api/watch/{mine}?env=0"), TOKEN_A).await;
    assert_eq!(status, 200, "{watched}");

    // Closing is the owner's too.
    a.close(&mine).await.unwrap();
    assert_eq!(
        a.step(&mine, &[0, 0]).await.unwrap_err().code(),
        tonic::Code::NotFound
    );
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}
