//! The whole `/metrics` text after a known sequence of calls, compared with the committed
//! golden file `tests/golden/metrics.txt` (and the text of the fresh server, before any call,
//! with `tests/golden/metrics_fresh.txt`): every metric's name, type, help, labels and value,
//! in order. A change to any of them shows here as a diff; if it is meant, regenerate the files
//! and commit them with the change (and say so in docs/operations.md):
//!
//! ```text
//! UPDATE_GOLDEN=1 cargo test --release -p dinerdash-server --test served metrics_golden
//! ```
//!
//! The sequence, on a server in this process on 127.0.0.1:0 with the default limits: scrape
//! (the fresh text), open one gRPC connection, create a session of 1 environment and one of 4, reset both, step each 10
//! times, three refused calls (a Step of an unknown session and a CloseSession of one:
//! `NOT_FOUND`; a Step with too few actions: `INVALID_ARGUMENT`), one Rollout of the expert
//! over two seeds read to its end, close the first session, scrape.
//!
//! What is normalised, and why: only the order of the `dinerdash_rpc_errors_total` lines. The
//! family keeps its label sets in a hash map (`prometheus-client`'s `Family`), whose order is
//! random per process, so the test sorts that family's sample lines before comparing. Nothing
//! else varies: the server exports no latency histograms, no uptime and no process metrics
//! (which would be normalised if it did), the sessions' bytes are their fixed in-memory sizes,
//! and the HTTP scrape is not a counted connection. The test waits (bounded) until the Rollout
//! stream has given its budget back before it takes the scrape it compares, since the stream's
//! charge is released just after its last message.

use crate::grpc_support;

use std::path::PathBuf;
use std::time::Instant;

use dinerdash_server::pb;
use dinerdash_server::server::ServerConfig;
use grpc_support::*;
use tonic::Code;

/// Compares `got` with the committed golden file `tests/golden/<name>`, or rewrites the file
/// when `UPDATE_GOLDEN=1`.
fn assert_golden(name: &str, got: &str) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name);
    if std::env::var_os("UPDATE_GOLDEN").is_some_and(|v| v == "1") {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, got).unwrap();
        return;
    }
    let want = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "cannot read {} ({e}); write it with UPDATE_GOLDEN=1",
            path.display()
        )
    });
    if got != want {
        let diff: Vec<String> = want
            .lines()
            .zip(got.lines())
            .filter(|(w, g)| w != g)
            .map(|(w, g)| format!("- {w}\n+ {g}"))
            .collect();
        panic!(
            "/metrics differs from {} (UPDATE_GOLDEN=1 rewrites it if the change is meant)\n\
             {}\nlines: {} in the file, {} scraped\n--- scraped:\n{got}",
            path.display(),
            diff.join("\n"),
            want.lines().count(),
            got.lines().count(),
        );
    }
}

/// The body of an HTTP/1.1 response (`Content-Length` or chunked).
fn body(response: &str) -> String {
    let (head, body) = response
        .split_once("\r\n\r\n")
        .expect("an HTTP response with a head");
    if !head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        return body.to_owned();
    }
    let (mut out, mut rest) = (String::new(), body);
    loop {
        let (size, after) = rest.split_once("\r\n").expect("a chunk size line");
        let size = usize::from_str_radix(size.trim(), 16).expect("a hex chunk size");
        if size == 0 {
            return out;
        }
        out.push_str(&after[..size]);
        rest = &after[size + 2..];
    }
}

/// `text` with the sample lines of `dinerdash_rpc_errors_total` sorted (see the module doc).
fn normalised(text: &str) -> String {
    let mut lines: Vec<&str> = text.lines().collect();
    let is_error_sample = |l: &&str| l.starts_with("dinerdash_rpc_errors_total{");
    if let Some(first) = lines.iter().position(is_error_sample) {
        let count = lines[first..]
            .iter()
            .take_while(|l| is_error_sample(l))
            .count();
        lines[first..first + count].sort_unstable();
    }
    let mut out = lines.join("\n");
    out.push('\n');
    out
}

#[tokio::test]
async fn the_metrics_text_after_a_known_sequence_matches_the_golden_file() {
    let server = TestServer::start_with(ServerConfig::default(), true).await;
    let addr = server.metrics_addr.unwrap();
    // Before any connection: every counter 0, no `dinerdash_rpc_errors_total` at all (an empty
    // family has no lines, HELP and TYPE included).
    assert_golden("metrics_fresh.txt", &normalised(&body(&scrape(addr).await)));
    let mut c = server.client().await;

    let one = create(
        &mut c,
        create_request(1, pb::AutoresetMode::NextStep, Some(1)),
    )
    .await;
    let four = create(
        &mut c,
        create_request(4, pb::AutoresetMode::NextStep, Some(2)),
    )
    .await;
    reset(&mut c, &one, None).await;
    reset(&mut c, &four, None).await;
    for _ in 0..10 {
        step(&mut c, &one, &[0]).await;
        step(&mut c, &four, &[0, 0, 0, 0]).await;
    }

    let unknown = c.step(pb::StepRequest::default()).await.unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);
    let short = c
        .step(pb::StepRequest {
            session_id: four.clone(),
            actions: pack(&[0]),
        })
        .await
        .unwrap_err();
    assert_eq!(short.code(), Code::InvalidArgument);
    let closed = c
        .close_session(pb::CloseSessionRequest {
            session_id: "no-such-session".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(closed.code(), Code::NotFound);

    let mut episodes = c
        .rollout(pb::RolloutRequest {
            policy: pb::Policy::Expert.into(),
            seeds: vec![5, 6],
            config: None,
            max_steps: Some(40),
            action_masks: true,
        })
        .await
        .unwrap()
        .into_inner();
    let mut read = 0;
    while episodes.message().await.unwrap().is_some() {
        read += 1;
    }
    assert_eq!(read, 2);

    c.close_session(pb::CloseSessionRequest { session_id: one })
        .await
        .unwrap();

    let started = Instant::now();
    let text = loop {
        let text = body(&scrape(addr).await);
        if metric(&text, "dinerdash_live_rollouts") == 0 {
            break text;
        }
        assert!(
            started.elapsed() < PATIENCE,
            "the Rollout stream never gave its budget back:\n{text}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    };
    server.stop().await;

    assert_golden("metrics.txt", &normalised(&text));
}
