//! The CPU pool shared between tenants, tried against the real binary as a greedy tenant would
//! (issue 46): tenant A keeps every worker of the pool busy with planner Rollouts of episodes
//! tens of seconds long, and more of them queued; tenant B's planner Steps are still served in
//! its turn, between two chunks of A's episodes, not after A's episodes.
//!
//! The promise is checked by order, not by a clock: all of B's Steps are answered while every
//! one of A's episodes is still being recorded. A first-come pool (the binary before the fix)
//! answers B's first Step only after A's first episode: the test then fails when that episode
//! arrives. The latencies are printed for the record (`--nocapture`).
//!
//! `DINERDASH_SERVER_EXE=/path/to/dinerdash-server` runs it against another build (the binary
//! before the fix answered B's first Step after A's first episode, 13.9 s in).

use crate::binary_support;
use crate::grpc_support;

use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::{create_request, pack};
use tonic::Request;
use tonic::transport::Channel;

/// Tenant A's token (at least 16 characters, no `#`).
const TOKEN_A: &str = "tenant-a-token-Fq8Lw2Zr5Tc1";
/// Tenant B's token.
const TOKEN_B: &str = "tenant-b-token-Mx4Hs7Vb9Kd3";
/// B's Steps while A's Rollouts run.
const B_STEPS: usize = 20;

/// `message` carrying `token`.
fn authed<T>(token: &str, message: T) -> Request<T> {
    let mut request = Request::new(message);
    let value = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    request
}

/// One planner Step of B's session, played with its expert's choice: its reply and how long it
/// took.
async fn timed_step(
    b: &mut DinerDashClient<Channel>,
    id: &str,
    action: i32,
) -> (pb::Batch, Duration) {
    let started = Instant::now();
    let request = authed(
        TOKEN_B,
        pb::StepRequest {
            session_id: id.to_owned(),
            actions: pack(&[action]),
        },
    );
    let batch = b.step(request).await.unwrap().into_inner();
    (batch, started.elapsed())
}

#[tokio::test]
async fn a_tenants_rollouts_leave_another_tenant_its_turn_on_the_cpu_pool() {
    // More Rollouts than the pool has workers (the server's pool leaves one core to the async
    // workers), so that A's episodes hold every worker and more of them wait: the premise holds
    // on any number of cores.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let workers = cores.saturating_sub(1).max(1);
    let rollouts = workers + 3;
    let dir = std::env::temp_dir().join(format!("dinerdash-fair-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(
        &file,
        format!("team-a {TOKEN_A} rollouts={rollouts}\nteam-b {TOKEN_B}\n"),
    )
    .unwrap();
    let args = format!("--auth-tokens-file '{}'", file.display());
    let server = match std::env::var("DINERDASH_SERVER_EXE") {
        Ok(exe) => Process::start_exe(&exe, "", &args),
        Err(_) => Process::start("", &args),
    };
    let url = format!("http://{}", server.addr);
    let mut a = DinerDashClient::connect(url.clone())
        .await
        .unwrap()
        .max_decoding_message_size(64 << 20);
    let mut b = DinerDashClient::connect(url).await.unwrap();

    // B's planner session, and its Steps' time with the pool idle.
    let created = b
        .create_session(authed(
            TOKEN_B,
            pb::CreateSessionRequest {
                expert_policy: pb::Policy::Planner.into(),
                ..create_request(1, pb::AutoresetMode::NextStep, Some(3))
            },
        ))
        .await
        .unwrap()
        .into_inner();
    let id = created.session_id;
    let reset = pb::ResetRequest {
        session_id: id.clone(),
        ..Default::default()
    };
    let mut batch = b.reset(authed(TOKEN_B, reset)).await.unwrap().into_inner();
    let mut idle = Vec::new();
    for _ in 0..B_STEPS {
        let (next, took) = timed_step(&mut b, &id, i32::from(batch.expert_actions[0])).await;
        batch = next;
        idle.push(took);
    }

    // A's planner Rollouts: one episode each, of 100,000 steps (a thousand lives are not lost
    // sooner): tens of seconds of a worker each. Each stream's first message (an episode or an
    // error) is told on `arrived`.
    let (arrived, mut first_arrival) = tokio::sync::mpsc::unbounded_channel();
    let long_game = pb::GameConfig {
        lives: Some(1000),
        ..Default::default()
    };
    let mut readers = Vec::new();
    for seed in 0..rollouts as u64 {
        let request = pb::RolloutRequest {
            policy: pb::Policy::Planner.into(),
            seeds: vec![seed],
            config: Some(long_game),
            max_steps: None,
            action_masks: false,
        };
        let mut stream = a
            .rollout(authed(TOKEN_A, request))
            .await
            .unwrap()
            .into_inner();
        let arrived = arrived.clone();
        readers.push(tokio::spawn(async move {
            let first = stream.message().await;
            let _ = arrived.send(format!("{first:?}").chars().take(200).collect::<String>());
        }));
    }
    // Every Rollout has asked for a worker (they do so as their call returns); let them start.
    tokio::time::sleep(Duration::from_millis(200)).await;

    // B's Steps, each in B's turn: all answered before any of A's episodes ends.
    let started = Instant::now();
    let b_steps = async {
        let mut busy = Vec::new();
        for _ in 0..B_STEPS {
            let (next, took) = timed_step(&mut b, &id, i32::from(batch.expert_actions[0])).await;
            batch = next;
            busy.push(took);
        }
        busy
    };
    let busy = tokio::select! {
        busy = b_steps => busy,
        first = first_arrival.recv() => panic!(
            "one of A's Rollouts delivered before B's {B_STEPS} Steps were answered (after {:?}): \
             B waited for whole episodes; A's stream said {first:?}",
            started.elapsed()
        ),
    };
    // Still none of A's episodes is done: B was served between chunks of them.
    assert!(
        first_arrival.try_recv().is_err(),
        "an episode of A ended while B stepped"
    );
    let max = |times: &[Duration]| times.iter().max().copied().unwrap_or_default();
    let mut sorted = idle.clone();
    sorted.sort();
    eprintln!(
        "B's planner Step: idle median {:?} max {:?}; beside A's {rollouts} Rollouts on \
         {workers} worker(s): max {:?}, {B_STEPS} Steps in {:?}",
        sorted[sorted.len() / 2],
        max(&idle),
        max(&busy),
        started.elapsed()
    );
    for reader in readers {
        reader.abort();
    }
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}
