//! StepStream against unary Step on one real server: the same seeds and actions give
//! byte-identical Batches in every autoreset mode, a refused request ends the stream with
//! exactly the Status the unary call returns, and a shutdown ends an open stream UNAVAILABLE.

use crate::grpc_support;

use std::collections::BTreeMap;

use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::ServerConfig;
use grpc_support::*;
use prost::Message as _;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Status, Streaming};
use tonic_types::StatusExt;

/// One open StepStream: requests go in through `tx`, replies come out of `replies`.
struct Stream {
    tx: mpsc::Sender<pb::StepRequest>,
    replies: Streaming<pb::Batch>,
}

impl Stream {
    async fn open(c: &mut DinerDashClient<Channel>) -> Stream {
        // Room for every request a test pipelines ahead of its reads.
        let (tx, rx) = mpsc::channel(64);
        let replies = tokio::time::timeout(PATIENCE, c.step_stream(ReceiverStream::new(rx)))
            .await
            .expect("StepStream did not open")
            .unwrap()
            .into_inner();
        Stream { tx, replies }
    }

    async fn send(&self, id: &str, actions: &[i32]) {
        self.tx
            .send(pb::StepRequest {
                session_id: id.to_owned(),
                actions: pack(actions),
            })
            .await
            .unwrap();
    }

    /// The next reply: a Batch, an error, or `Ok(None)` once the stream ended.
    async fn next(&mut self) -> Result<Option<pb::Batch>, Status> {
        tokio::time::timeout(PATIENCE, self.replies.message())
            .await
            .expect("no reply")
    }

    async fn step(&mut self, id: &str, actions: &[i32]) -> Result<pb::Batch, Status> {
        self.send(id, actions).await;
        self.next().await.map(|b| b.expect("stream ended early"))
    }
}

/// A session of `n` environments, reset with `seed`.
async fn session(
    c: &mut DinerDashClient<Channel>,
    n: u32,
    mode: pb::AutoresetMode,
    expert: bool,
    seed: u64,
) -> String {
    let mut request = create_request(n, mode, None);
    request.action_masks = expert;
    request.expert_actions = expert;
    // One life and a short time limit: episodes end often, by termination and by truncation.
    request.config = Some(pb::GameConfig {
        lives: Some(1),
        time_limit: Some(60),
        ..Default::default()
    });
    let id = create(c, request).await;
    reset(c, &id, Some(seed)).await;
    id
}

/// Steps twin sessions, one through unary Step and one through a StepStream, with the same
/// actions; every pair of Batches must encode to the same bytes. With autoreset DISABLED, both
/// are reset (by unary Reset, the stream staying open) once an episode ends.
async fn twins(n: u32, mode: pb::AutoresetMode, expert: bool) {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let unary = session(&mut c, n, mode, expert, 77).await;
    let streamed = session(&mut c, n, mode, expert, 77).await;
    let mut stream = Stream::open(&mut c).await;
    let mut actions = Actions::new(u64::from(n) + 5);
    let mut ended = 0;
    for s in 0..300 {
        let a: Vec<i32> = (0..n).map(|_| actions.next()).collect();
        let want = step(&mut c, &unary, &a).await;
        let got = stream.step(&streamed, &a).await.unwrap();
        assert_eq!(
            got.encode_to_vec(),
            want.encode_to_vec(),
            "{mode:?} step {s}"
        );
        let over = got
            .terminated
            .iter()
            .zip(&got.truncated)
            .any(|(&t, &u)| t == 1 || u == 1);
        if over {
            ended += 1;
            if mode == pb::AutoresetMode::Disabled {
                let seed = Some(1000 + s);
                assert_eq!(
                    reset(&mut c, &streamed, seed).await,
                    reset(&mut c, &unary, seed).await
                );
            }
        }
    }
    assert!(ended > 1, "{mode:?}: only {ended} episodes ended");
    // The client closing its side ends the stream with OK.
    drop(stream.tx);
    assert_eq!(stream.replies.message().await.unwrap(), None);
    server.stop().await;
}

#[tokio::test]
async fn step_stream_matches_unary_step_in_every_autoreset_mode() {
    for mode in [
        pb::AutoresetMode::NextStep,
        pb::AutoresetMode::SameStep,
        pb::AutoresetMode::Disabled,
    ] {
        for expert in [true, false] {
            twins(1, mode, expert).await;
            twins(8, mode, expert).await;
        }
    }
}

/// Requests sent ahead of the replies are answered in order, one Batch each, and one stream may
/// step several sessions.
#[tokio::test]
async fn pipelined_requests_over_two_sessions_are_answered_in_order() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mode = pb::AutoresetMode::NextStep;
    let ids = [
        session(&mut c, 2, mode, true, 5).await,
        session(&mut c, 3, mode, true, 6).await,
    ];
    let twins = [
        session(&mut c, 2, mode, true, 5).await,
        session(&mut c, 3, mode, true, 6).await,
    ];
    let mut stream = Stream::open(&mut c).await;
    let mut actions = Actions::new(9);
    let mut sent = Vec::new();
    for k in 0..40 {
        let which = k % 2;
        let a: Vec<i32> = (0..2 + which).map(|_| actions.next()).collect();
        stream.send(&ids[which], &a).await;
        sent.push((which, a));
    }
    for (k, (which, a)) in sent.iter().enumerate() {
        let got = stream.next().await.unwrap().expect("a reply per request");
        let want = step(&mut c, &twins[*which], a).await;
        assert_eq!(got, want, "request {k}");
    }
    drop(stream.tx);
    assert_eq!(stream.replies.message().await.unwrap(), None);
    server.stop().await;
}

/// The ErrorInfo (reason, domain, metadata) and BadRequest violations (field, description) of a
/// status.
type Details = (
    Option<(String, String, BTreeMap<String, String>)>,
    Vec<(String, String)>,
);

fn details(status: &Status) -> Details {
    let d = status.get_error_details();
    let info = d.error_info().map(|i| {
        let metadata = i.metadata.clone().into_iter().collect();
        (i.reason.clone(), i.domain.clone(), metadata)
    });
    let violations = d.bad_request().map_or_else(Vec::new, |b| {
        b.field_violations
            .iter()
            .map(|v| (v.field.clone(), v.description.clone()))
            .collect()
    });
    (info, violations)
}

/// Asserts that a StepStream request refused by the server ends the stream with the very Status
/// that a unary Step of the same request returns on the same session state.
async fn same_refusal(
    c: &mut DinerDashClient<Channel>,
    stream: &mut Stream,
    id: &str,
    actions: &[i32],
    code: Code,
) -> Status {
    let unary = c
        .step(pb::StepRequest {
            session_id: id.to_owned(),
            actions: pack(actions),
        })
        .await
        .expect_err("the unary Step must be refused");
    let streamed = stream
        .step(id, actions)
        .await
        .expect_err("the streamed Step must be refused");
    assert_eq!(unary.code(), code, "{}", unary.message());
    assert_eq!(streamed.code(), unary.code());
    assert_eq!(streamed.message(), unary.message());
    // The same structured details (compared decoded: ErrorInfo's metadata is a map, whose
    // encoding order may differ from one encoding to the next).
    assert_eq!(details(&streamed), details(&unary));
    assert!(details(&unary).0.is_some(), "refusals carry an ErrorInfo");
    // The error ended the stream.
    assert_eq!(stream.next().await.unwrap(), None);
    streamed
}

#[tokio::test]
async fn refusals_end_the_stream_with_the_unary_status() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mode = pb::AutoresetMode::Disabled;
    let id = session(&mut c, 2, mode, true, 3).await;

    let ghost = "0123456789abcdef0123456789abcdef";
    let mut stream = Stream::open(&mut c).await;
    // Replies before the refusal stand.
    stream.step(&id, &[0, 0]).await.unwrap();
    same_refusal(&mut c, &mut stream, ghost, &[0], Code::NotFound).await;

    let mut stream = Stream::open(&mut c).await;
    let status = same_refusal(&mut c, &mut stream, &id, &[0, 57], Code::InvalidArgument).await;
    assert!(
        status.message().contains("actions[1]"),
        "{}",
        status.message()
    );

    let mut stream = Stream::open(&mut c).await;
    same_refusal(&mut c, &mut stream, &id, &[0, 0, 0], Code::InvalidArgument).await;

    let fresh = create(&mut c, create_request(1, mode, Some(1))).await;
    let mut stream = Stream::open(&mut c).await;
    same_refusal(&mut c, &mut stream, &fresh, &[0], Code::FailedPrecondition).await;

    // Step both environments to the end of their episode (a time limit of 60 ticks), then once
    // more: with autoreset DISABLED that is EPISODE_OVER.
    let mut stream = Stream::open(&mut c).await;
    let mut over = false;
    for _ in 0..1000 {
        let b = stream.step(&id, &[0, 0]).await.unwrap();
        if b.truncated.contains(&1) || b.terminated.contains(&1) {
            over = true;
            break;
        }
    }
    assert!(over, "the episode never ended");
    same_refusal(&mut c, &mut stream, &id, &[0, 0], Code::FailedPrecondition).await;

    // The refused requests were not applied: the session still steps after a reset.
    reset(&mut c, &id, Some(4)).await;
    step(&mut c, &id, &[0, 0]).await;
    server.stop().await;
}

/// A shutdown ends a stream that waits for its next request with UNAVAILABLE, so that the drain
/// does not wait for it, and the server then stops.
#[tokio::test]
async fn shutdown_ends_an_open_stream_unavailable() {
    let mut server = TestServer::start().await;
    let mut c = server.client().await;
    let id = session(&mut c, 1, pb::AutoresetMode::NextStep, false, 8).await;
    let mut stream = Stream::open(&mut c).await;
    stream.step(&id, &[0]).await.unwrap();
    server.trigger_stop();
    let status = stream
        .next()
        .await
        .expect_err("the stream must end with an error");
    assert_eq!(status.code(), Code::Unavailable, "{}", status.message());
    server.stop().await;
}

/// Steps the server has done, from its metrics.
async fn step_calls(server: &TestServer) -> u64 {
    metric(
        &scrape(server.metrics_addr.unwrap()).await,
        "dinerdash_step_calls_total",
    )
}

/// A client that sends requests but does not read its replies stops the server stepping once
/// flow control is full (the server holds at most one reply beyond it); reading resumes it, and
/// every request is answered.
#[tokio::test]
async fn unread_replies_stop_the_stream() {
    let server = TestServer::start_with(ServerConfig::default(), true).await;
    // HTTP/2's default 64 KiB window: about two N = 256 replies (~31 KB each).
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", server.addr))
        .unwrap()
        .initial_stream_window_size(65_535)
        .initial_connection_window_size(65_535)
        .connect()
        .await
        .unwrap();
    let mut c = DinerDashClient::new(channel);
    let id = session(&mut c, 256, pb::AutoresetMode::NextStep, true, 2).await;
    let mut stream = Stream::open(&mut c).await;
    let sent = 64;
    for _ in 0..sent {
        stream.send(&id, &[0; 256]).await;
    }
    // Wait until the server has stepped and then stops: the count is above 0 and the same at
    // three reads 100 ms apart (bounded: it must stop, or the assertion below fails).
    let (mut last, mut same) = (0, 0);
    for _ in 0..600 {
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        let now = step_calls(&server).await;
        same = if now > 0 && now == last { same + 1 } else { 0 };
        last = now;
        if same == 2 {
            break;
        }
    }
    // Two replies within the window, a third straddling its end (the rest held by h2), and
    // the one stepped as the transport took the third: 4 with tonic 0.14 / h2 0.4. Without the
    // hand-off of StepReplies::poll_next, tonic's encoder steps ahead for up to 32 KiB: 6 here,
    // and hundreds of single-environment replies. At least the two replies that fit the window
    // must have been stepped: a stream that does not step at all fails here.
    assert!(
        (2..=4).contains(&last),
        "{last} of {sent} requests stepped with no reply read"
    );
    for k in 0..sent {
        let b = stream.next().await.unwrap().expect("a reply per request");
        assert_eq!(b.num_envs, 256, "reply {k}");
    }
    assert_eq!(step_calls(&server).await, sent);
    drop(stream.tx);
    assert_eq!(stream.replies.message().await.unwrap(), None);
    server.stop().await;
}

/// The server announces its per-connection stream limit in its HTTP/2 SETTINGS, so that one
/// connection cannot hold unboundedly many idle StepStreams: read with a bare HTTP/2 handshake.
#[tokio::test]
async fn the_server_limits_streams_per_connection() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let server = TestServer::start().await;
    let mut tcp = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    // The client preface, then an empty SETTINGS frame (length 0, type 4, no flags, stream 0).
    tcp.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\0\0\0\x04\0\0\0\0\0")
        .await
        .unwrap();
    let mut header = [0u8; 9];
    tokio::time::timeout(PATIENCE, tcp.read_exact(&mut header))
        .await
        .unwrap()
        .unwrap();
    // The server's first frame is its SETTINGS.
    assert_eq!(header[3], 4, "frame type");
    let len = u32::from_be_bytes([0, header[0], header[1], header[2]]) as usize;
    let mut payload = vec![0u8; len];
    tcp.read_exact(&mut payload).await.unwrap();
    // Settings are 6 bytes each: a 16-bit identifier, a 32-bit value. 0x3: MAX_CONCURRENT_STREAMS.
    let max_streams = payload.chunks_exact(6).find_map(|s| {
        (u16::from_be_bytes([s[0], s[1]]) == 3)
            .then(|| u32::from_be_bytes([s[2], s[3], s[4], s[5]]))
    });
    assert_eq!(
        max_streams,
        Some(dinerdash_server::connections::MAX_STREAMS_PER_CONNECTION)
    );
    drop(tcp);
    server.stop().await;
}
