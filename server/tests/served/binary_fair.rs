//! The CPU shared between tenants, tried against the real binary as a greedy tenant would
//! (issue 46), two ways:
//!
//! - Rollouts: tenant A keeps every worker of the CPU pool busy with planner Rollouts of
//!   episodes tens of seconds long, and more of them queued; tenant B's planner Steps are still
//!   served in its turn, between two chunks of A's episodes, not after A's episodes. Checked by
//!   order, not by a clock: all of B's Steps are answered while every one of A's episodes is
//!   still being recorded. A first-come pool (the binary before) answers B's first Step only
//!   after A's first episode (13.9 s in): the test then fails when that episode arrives.
//! - Large planner Steps: tenant A steps more sessions of 16,384 planner environments than the
//!   pool has workers, two Steps of each at once, each again as soon as it answers; tenant B's
//!   one-environment and 256-environment planner Steps wait about a chunk, not A's whole Steps.
//!   Checked against A's own measured Step, not a clock: B's slowest Step of each kind must be
//!   under a quarter of A's median Step (about two Steps' run, two being asked at once). The
//!   binary before held a worker for each of A's whole Steps and took large Steps first come,
//!   first served: B's slowest Steps took longer than A's median.
//!
//! The latencies are printed for the record (`--nocapture`).
//! `DINERDASH_SERVER_EXE=/path/to/dinerdash-server` runs the tests against another build.

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
    let (server, dir) = start_two_tenants("rollouts", &format!("rollouts={rollouts}"), "");
    let url = format!("http://{}", server.addr);
    let mut a = DinerDashClient::connect(url.clone())
        .await
        .unwrap()
        .max_decoding_message_size(64 << 20);
    let mut b = DinerDashClient::connect(url).await.unwrap();

    // B's planner session, and its Steps' time with the pool idle.
    let (id, mut batch) = planner_session(&mut b, TOKEN_B, 1, 3, None).await;
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

/// The binary (`DINERDASH_SERVER_EXE`, else this build's) serving tenants A and B from a tokens
/// file in a directory of its own (`name`), A's line ending in `a_options`, with `args`; and
/// that directory, to remove.
fn start_two_tenants(name: &str, a_options: &str, args: &str) -> (Process, std::path::PathBuf) {
    let dir = std::env::temp_dir().join(format!("dinerdash-fair-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    std::fs::write(
        &file,
        format!("team-a {TOKEN_A} {a_options}\nteam-b {TOKEN_B}\n"),
    )
    .unwrap();
    let args = format!("--auth-tokens-file '{}' {args}", file.display());
    let server = match std::env::var("DINERDASH_SERVER_EXE") {
        Ok(exe) => Process::start_exe(&exe, "", &args),
        Err(_) => Process::start("", &args),
    };
    (server, dir)
}

/// A planner session of `token`'s of `num_envs` environments playing `config`, reset: its ID and first Batch.
async fn planner_session(
    client: &mut DinerDashClient<Channel>,
    token: &str,
    num_envs: u32,
    seed: u64,
    config: Option<pb::GameConfig>,
) -> (String, pb::Batch) {
    let created = client
        .create_session(authed(
            token,
            pb::CreateSessionRequest {
                expert_policy: pb::Policy::Planner.into(),
                config,
                ..create_request(num_envs, pb::AutoresetMode::NextStep, Some(seed))
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
    let batch = client
        .reset(authed(token, reset))
        .await
        .unwrap()
        .into_inner();
    (id, batch)
}

/// One Step of `token`'s session `id` playing each environment's expert action in `batch`, its
/// last Batch: the next Batch and how long the Step took.
async fn expert_step(
    client: &mut DinerDashClient<Channel>,
    token: &str,
    id: &str,
    batch: &pb::Batch,
) -> (pb::Batch, Duration) {
    let actions: Vec<i32> = batch.expert_actions.iter().map(|&x| i32::from(x)).collect();
    let request = pb::StepRequest {
        session_id: id.to_owned(),
        actions: pack(&actions),
    };
    let started = Instant::now();
    let next = client
        .step(authed(token, request))
        .await
        .unwrap()
        .into_inner();
    (next, started.elapsed())
}

/// Environments of each of A's sessions: the most the default `--max-envs-per-session`
/// allows, a whole Step of one of them many chunks of planner decisions long.
const LARGE: u32 = dinerdash_server::session::DEFAULT_MAX_ENVS_PER_SESSION;
/// Steps A asks of each of its sessions at once.
const A_AT_ONCE: usize = 2;
/// Steps of each of A's sessions before they are timed (and B starts).
const A_WARM_UP: usize = 3;
/// Environments of B's large session: cut in chunks, but a small Step beside A's.
const B_LARGE: u32 = 256;
/// B's timed Steps beside A's large ones, small and large in turn.
const B_STEPS_BESIDE: usize = 40;

#[tokio::test]
async fn a_tenants_large_planner_steps_leave_another_tenant_its_turn() {
    // More of A's large sessions than the CPU pool has workers, each stepped again as soon as
    // it answers: before B asks, every worker could be held by one of A's Steps and more wait.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let workers = cores.saturating_sub(1).max(1);
    let sessions = workers + 2;
    let (server, dir) =
        start_two_tenants("steps", &format!("envs={}", sessions * LARGE as usize), "");
    let url = format!("http://{}", server.addr);
    let mut b = DinerDashClient::connect(url.clone()).await.unwrap();
    let (b_id, mut b_batch) = planner_session(&mut b, TOKEN_B, 1, 3, None).await;
    // And a large one (its Steps cut in chunks on the stepping threads), small beside A's.
    let (b_large, mut b_large_batch) = planner_session(&mut b, TOKEN_B, B_LARGE, 4, None).await;

    // A's sessions, each stepped in a loop of its own until told to stop, in a busy game
    // (groups every other tick, never over) whose planner decisions weigh: each Step's time
    // is kept once the session's games are under way.
    let busy_game = pb::GameConfig {
        arrival_interval: Some(1),
        lives: Some(1000),
        ..Default::default()
    };
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (under_way, mut ready) = tokio::sync::mpsc::unbounded_channel();
    let mut loops = Vec::new();
    for seed in 0..sessions as u64 {
        let mut a = DinerDashClient::connect(url.clone())
            .await
            .unwrap()
            .max_decoding_message_size(64 << 20);
        let (id, batch) = planner_session(&mut a, TOKEN_A, LARGE, seed, Some(busy_game)).await;
        // Two Steps of each session at once: the second waits for the first.
        for _ in 0..A_AT_ONCE {
            let (mut a, id, mut batch) = (a.clone(), id.clone(), batch.clone());
            let (stop, under_way) = (stop.clone(), under_way.clone());
            loops.push(tokio::spawn(async move {
                let mut times = Vec::new();
                for step in 0.. {
                    if stop.load(std::sync::atomic::Ordering::SeqCst) {
                        break;
                    }
                    let took;
                    (batch, took) = expert_step(&mut a, TOKEN_A, &id, &batch).await;
                    if step >= A_WARM_UP {
                        times.push(took);
                    } else if step + 1 == A_WARM_UP {
                        let _ = under_way.send(());
                    }
                }
                times
            }));
        }
    }
    for _ in 0..loops.len() {
        ready.recv().await.unwrap();
    }
    let from = Instant::now();

    // B's small and large planner Steps meanwhile, in turn, a few milliseconds apart, so that
    // they fall in every part of A's Steps.
    let (mut waits, mut large_waits) = (Vec::new(), Vec::new());
    for i in 0..B_STEPS_BESIDE {
        tokio::time::sleep(Duration::from_millis(3 + (i % 7) as u64 * 4)).await;
        if i % 2 == 0 {
            let (next, took) =
                timed_step(&mut b, &b_id, i32::from(b_batch.expert_actions[0])).await;
            b_batch = next;
            waits.push(took);
        } else {
            let took;
            (b_large_batch, took) = expert_step(&mut b, TOKEN_B, &b_large, &b_large_batch).await;
            large_waits.push(took);
        }
    }
    let b_span = from.elapsed();
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    let mut a_times = Vec::new();
    for steps in loops {
        a_times.extend(steps.await.unwrap());
    }
    a_times.sort();
    waits.sort();
    large_waits.sort();
    let a_median = a_times[a_times.len() / 2];
    let (b_max, b_large_max) = (*waits.last().unwrap(), *large_waits.last().unwrap());
    eprintln!(
        "A's {sessions} sessions of {LARGE} planner environments: {} Steps, median {a_median:?}; \
         beside them (in {b_span:?}) B's one-environment planner Steps: median {:?}, max \
         {b_max:?}; B's {B_LARGE}-environment ones: median {:?}, max {b_large_max:?}",
        a_times.len(),
        waits[waits.len() / 2],
        large_waits[large_waits.len() / 2],
    );
    // A's median Step, asked two at a time of a session, is about two Steps' run: B's slowest
    // Step must be under a quarter of it, about half a Step's run.
    assert!(!a_times.is_empty());
    // B's large Steps' chunks take turns with A's on the stepping threads: before, they waited
    // for A's Steps already there (first come, first served).
    assert!(
        b_large_max * 4 < a_median,
        "B's slowest {B_LARGE}-environment Step {b_large_max:?} is not well below A's median \
         Step {a_median:?}"
    );
    // B waits about a chunk, not a Step of A's: before, a worker held for A's whole Step (or by
    // A's second Step waiting for the session) kept B waiting about as long as one or more.
    assert!(
        b_max * 4 < a_median,
        "B's slowest small Step {b_max:?} is not well below A's median large Step {a_median:?}"
    );
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}
