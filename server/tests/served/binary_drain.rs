//! Planned restarts of the real binary (issue 26): on SIGTERM or SIGINT the server drains for
//! `--drain-timeout`: new sessions (CreateSession, Fork, Restore) and Rollouts are refused with
//! UNAVAILABLE and reason DRAINING, health says NOT_SERVING, and the sessions it has are served on,
//! each Batch counting down `drain_remaining_ms`, until the last one closes or the timeout
//! passes; a second signal ends it at once; `--drain-timeout 0` stops at once as before.

use crate::binary_support;
use crate::grpc_support;

use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::cmd::health::{self, Probe, ServingStatus};
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::server::LIVENESS_SERVICE;
use dinerdash_server::service::{ERROR_DOMAIN, RETRY_PUSHBACK};
use grpc_support::{PATIENCE, create, create_request, pack, reset, snapshot, step};
use tonic::transport::Channel;
use tonic::{Code, Status};
use tonic_types::StatusExt;

/// A client of `server`.
async fn client(server: &Process) -> DinerDashClient<Channel> {
    DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap()
}

/// A session of two environments, reset.
async fn session(c: &mut DinerDashClient<Channel>) -> String {
    let id = create(c, create_request(2, pb::AutoresetMode::NextStep, Some(5))).await;
    reset(c, &id, None).await;
    id
}

/// The server's grpc.health.v1 status for `service` ("" is the whole server).
async fn health_of(server: &Process, service: &str) -> ServingStatus {
    health::check(&Probe {
        address: server.addr.clone(),
        timeout: PATIENCE,
        service: service.into(),
        tls_ca: None,
        token: None,
    })
    .await
    .unwrap()
}

/// The `drain_remaining_ms` of a DRAINING refusal; panics on any other outcome.
#[track_caller]
fn drain_refusal<T: std::fmt::Debug>(result: Result<T, Status>) -> u32 {
    let status = result.expect_err("a draining server took new work");
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    let details = status.get_error_details();
    let info = details
        .error_info()
        .expect("a DRAINING refusal carries an ErrorInfo");
    assert_eq!(
        (info.reason.as_str(), info.domain.as_str()),
        ("DRAINING", ERROR_DOMAIN)
    );
    // The retry push-back trailer (gRFC A6) survives the wire: a client whose channel retries
    // UNAVAILABLE by its service config's retryPolicy does not ask a draining server again.
    assert_eq!(
        status
            .metadata()
            .get(RETRY_PUSHBACK)
            .map(|v| v.to_str().unwrap()),
        Some("-1"),
        "{status:?}"
    );
    info.metadata["drain_remaining_ms"].parse().unwrap()
}

/// Sends `signal` and waits (bounded) until CreateSession is refused: the server drains. Returns
/// the refusal's `drain_remaining_ms`.
async fn signal_and_wait_for_the_drain(
    server: &Process,
    c: &mut DinerDashClient<Channel>,
    signal: &str,
) -> u32 {
    server.signal(signal);
    let started = Instant::now();
    loop {
        match c
            .create_session(create_request(1, pb::AutoresetMode::Unspecified, None))
            .await
        {
            // Until the signal is handled the server still takes sessions: closed again, so
            // that only the test's own sessions hold the drain.
            Ok(created) => {
                let session_id = created.into_inner().session_id;
                c.close_session(pb::CloseSessionRequest { session_id })
                    .await
                    .unwrap();
                assert!(started.elapsed() < PATIENCE, "never started draining");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            refused => return drain_refusal(refused),
        }
    }
}

/// Waits for the server process to exit (within PATIENCE) and checks it exited 0; returns its
/// stderr.
async fn exits_cleanly(server: Process) -> String {
    let (status, stderr) = tokio::task::spawn_blocking(move || server.wait())
        .await
        .unwrap();
    assert_eq!(status.code(), Some(0), "{stderr}");
    stderr
}

#[tokio::test]
async fn a_draining_server_serves_its_sessions_until_the_last_one_closes() {
    // A drain timeout far beyond PATIENCE: an exit within PATIENCE is the last session's doing.
    let server = Process::start("", "--drain-timeout 1h --log-format json");
    let mut c = client(&server).await;
    let id = session(&mut c).await;
    let kept = snapshot(&mut c, &id).await;
    assert_eq!(step(&mut c, &id, &[0, 0]).await.drain_remaining_ms, 0);
    for service in ["", "dinerdash.v1.DinerDash", LIVENESS_SERVICE] {
        assert_eq!(health_of(&server, service).await, ServingStatus::Serving);
    }

    let refused_with = signal_and_wait_for_the_drain(&server, &mut c, "-TERM").await;
    assert!(
        (1..=3_600_000).contains(&refused_with),
        "{refused_with} ms left"
    );
    // Nothing else that starts new work is taken either.
    drain_refusal(
        c.fork(pb::ForkRequest {
            session_id: id.clone(),
        })
        .await,
    );
    drain_refusal(c.restore(pb::RestoreRequest { snapshot: kept }).await);
    drain_refusal(
        c.rollout(pb::RolloutRequest {
            policy: pb::Policy::Expert.into(),
            seeds: vec![0],
            ..Default::default()
        })
        .await,
    );
    for service in ["", "dinerdash.v1.DinerDash"] {
        assert_eq!(
            health_of(&server, service).await,
            ServingStatus::NotServing,
            "{service:?}"
        );
    }
    // Alive all the same, for liveness probes.
    assert_eq!(
        health_of(&server, LIVENESS_SERVICE).await,
        ServingStatus::Serving
    );

    // The session is served on, every reply counting down the time left.
    let first = step(&mut c, &id, &[1, 2]).await.drain_remaining_ms;
    assert!((1..=refused_with).contains(&first), "{first} ms left");
    tokio::time::sleep(Duration::from_millis(50)).await;
    let second = step(&mut c, &id, &[3, 4]).await.drain_remaining_ms;
    assert!(
        second > 0 && second < first,
        "{second} ms left after {first}"
    );
    let reset_left = reset(&mut c, &id, Some(9)).await.drain_remaining_ms;
    assert!(reset_left > 0 && reset_left <= second, "{reset_left} ms");
    // StepStream replies carry it too; and a connection opened while draining is served (a
    // client that reconnects finds its session).
    let mut fresh = client(&server).await;
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    tx.send(pb::StepRequest {
        session_id: id.clone(),
        actions: pack(&[0, 0]),
    })
    .await
    .unwrap();
    let mut replies = fresh
        .step_stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let streamed = replies.message().await.unwrap().unwrap();
    assert!(
        streamed.drain_remaining_ms > 0 && streamed.drain_remaining_ms <= reset_left,
        "{} ms",
        streamed.drain_remaining_ms
    );
    drop(tx);
    assert!(replies.message().await.unwrap().is_none());

    // The last session closes: the server stops, long before its drain timeout.
    c.close_session(pb::CloseSessionRequest { session_id: id })
        .await
        .unwrap();
    let stderr = exits_cleanly(server).await;
    assert!(stderr.contains("drained: no session left"), "{stderr}");
}

#[tokio::test]
async fn the_drain_timeout_ends_the_sessions_left() {
    let timeout = Duration::from_secs(1);
    let server = Process::start("", "--drain-timeout 1s --log-format json");
    let mut c = client(&server).await;
    let id = session(&mut c).await;
    let signalled = Instant::now();
    let refused_with = signal_and_wait_for_the_drain(&server, &mut c, "-INT").await;
    assert!(refused_with <= 1000, "{refused_with} ms left");
    // Held, never closed: the deadline ends it (or, on a slow machine, already has).
    if let Ok(batch) = c
        .step(pb::StepRequest {
            session_id: id,
            actions: pack(&[0, 0]),
        })
        .await
    {
        assert!((1..=1000).contains(&batch.get_ref().drain_remaining_ms));
    }
    let stderr = exits_cleanly(server).await;
    assert!(signalled.elapsed() >= timeout);
    assert!(
        stderr.contains("the drain timeout passed: ending the sessions left"),
        "{stderr}"
    );
}

#[tokio::test]
async fn a_second_signal_ends_the_drain_at_once() {
    let server = Process::start("", "--drain-timeout 1h --log-format json");
    let mut c = client(&server).await;
    let _held = session(&mut c).await;
    signal_and_wait_for_the_drain(&server, &mut c, "-TERM").await;
    server.signal("-INT");
    // Within PATIENCE, an hour before the drain timeout.
    let stderr = exits_cleanly(server).await;
    assert!(
        stderr.contains("a second signal: exiting at once"),
        "{stderr}"
    );
    // The drain's first line told the operator so.
    assert!(
        stderr.contains("a second Ctrl-C or SIGTERM exits at once"),
        "{stderr}"
    );
}

#[tokio::test]
async fn drain_timeout_zero_stops_at_once() {
    let server = Process::start("", "--drain-timeout 0 --log-format json");
    let mut c = client(&server).await;
    let id = session(&mut c).await;
    server.signal("-TERM");
    // The session is not served on: calls fail fast with UNAVAILABLE, and the process exits
    // although a session is left.
    let started = Instant::now();
    let status = loop {
        let call = c.step(pb::StepRequest {
            session_id: id.clone(),
            actions: pack(&[0, 0]),
        });
        match tokio::time::timeout(PATIENCE, call)
            .await
            .expect("a call hung")
        {
            Err(status) => break status,
            Ok(batch) => {
                // 0 while serving; 1 for a call already in flight when it stopped.
                assert!(batch.get_ref().drain_remaining_ms <= 1);
                assert!(started.elapsed() < PATIENCE, "never stopped");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
    };
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    let stderr = exits_cleanly(server).await;
    assert!(!stderr.contains("draining: no new sessions"), "{stderr}");
}
