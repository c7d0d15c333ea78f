//! One tenant's large Steps, stepped in parallel on the stepping threads, do not starve another
//! tenant's small ones: while three clients step sessions of 4,096 environments back to back on
//! a server with two async workers, a fourth client's single-environment session completes its
//! Steps, a good part of them while every large Step that was in flight when it was sent is
//! still in flight when its reply comes: a server that ran Steps one at a time would have
//! finished the large Step it was running before the small one.

use crate::grpc_support;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use dinerdash_server::pb;
use dinerdash_server::pools::Stepping;
use dinerdash_server::server::ServerConfig;
use dinerdash_server::session::Limits;
use grpc_support::*;

const LARGE: u32 = 4096;
const LARGE_CLIENTS: usize = 3;
const SMALL_STEPS: usize = 100;
/// A large stepper's own bound, should the test never tell it to stop.
const MOST_LARGE_STEPS: u64 = 100_000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn small_steps_are_served_while_large_sessions_step_in_parallel() {
    let config = ServerConfig {
        limits: Limits {
            stepping: Stepping {
                threads: 2,
                ..Stepping::default()
            },
            ..Limits::default()
        },
        ..ServerConfig::default()
    };
    assert!(config.limits.stepping.chunks(LARGE as usize, false) > 1);
    assert_eq!(config.limits.stepping.chunks(1, false), 1);
    let server = TestServer::start_with(config, false).await;
    let stop = Arc::new(AtomicBool::new(false));
    // Each large client's Steps begun and ended: its Step number `begun` is in flight while
    // `ended` is below it.
    let begun: Arc<Vec<AtomicU64>> = Arc::new((0..LARGE_CLIENTS).map(|_| 0.into()).collect());
    let ended: Arc<Vec<AtomicU64>> = Arc::new((0..LARGE_CLIENTS).map(|_| 0.into()).collect());
    let large_steps = Arc::new(AtomicU64::new(0));
    let mut large = Vec::new();
    for k in 0..LARGE_CLIENTS {
        let mut c = server.client().await;
        let (stop, large_steps) = (stop.clone(), large_steps.clone());
        let (begun, ended) = (begun.clone(), ended.clone());
        large.push(tokio::spawn(async move {
            let id = create(
                &mut c,
                create_request(LARGE, pb::AutoresetMode::NextStep, Some(k as u64)),
            )
            .await;
            reset(&mut c, &id, None).await;
            let mut actions = Actions::new(k as u64);
            let batch: Vec<i32> = (0..LARGE).map(|_| actions.next()).collect();
            let mut steps = 0;
            while !stop.load(Ordering::SeqCst) && steps < MOST_LARGE_STEPS {
                begun[k].fetch_add(1, Ordering::SeqCst);
                step(&mut c, &id, &batch).await;
                ended[k].fetch_add(1, Ordering::SeqCst);
                steps += 1;
                large_steps.fetch_add(1, Ordering::SeqCst);
            }
            steps
        }));
    }
    // Every large client is stepping before the small one starts.
    let started = Instant::now();
    while large_steps.load(Ordering::SeqCst) < 2 * LARGE_CLIENTS as u64 {
        assert!(
            started.elapsed() < PATIENCE,
            "the large sessions never stepped"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }

    let mut c = server.client().await;
    let id = create(
        &mut c,
        create_request(1, pb::AutoresetMode::NextStep, Some(9)),
    )
    .await;
    reset(&mut c, &id, None).await;
    let mut actions = Actions::new(9);
    let mut latencies = Vec::with_capacity(SMALL_STEPS);
    let mut beside_large = 0;
    let large_before = large_steps.load(Ordering::SeqCst);
    for _ in 0..SMALL_STEPS {
        // The large Steps in flight now: (client, its Step's number).
        let in_flight: Vec<(usize, u64)> = (0..LARGE_CLIENTS)
            .map(|k| (k, begun[k].load(Ordering::SeqCst)))
            .filter(|&(k, n)| ended[k].load(Ordering::SeqCst) < n)
            .collect();
        let sent = Instant::now();
        let a = actions.next();
        tokio::time::timeout(PATIENCE, step(&mut c, &id, &[a]))
            .await
            .expect("a small Step waited for ever");
        latencies.push(sent.elapsed());
        // Answered while every one of them was still running.
        if !in_flight.is_empty()
            && in_flight
                .iter()
                .all(|&(k, n)| ended[k].load(Ordering::SeqCst) < n)
        {
            beside_large += 1;
        }
    }
    let large_during = large_steps.load(Ordering::SeqCst) - large_before;
    stop.store(true, Ordering::SeqCst);
    for task in large {
        let steps = tokio::time::timeout(PATIENCE, task).await.unwrap().unwrap();
        assert!(
            steps < MOST_LARGE_STEPS,
            "a large client stopped on its own"
        );
    }
    latencies.sort();
    eprintln!(
        "small Steps beside {LARGE_CLIENTS} clients stepping N={LARGE}: median {:?}, max {:?}; \
         {large_during} large Steps meanwhile",
        latencies[SMALL_STEPS / 2],
        latencies[SMALL_STEPS - 1],
    );
    // A good part of the small Steps were answered while the large Steps they found in flight
    // kept running. One at a time, each small Step would wait for the large Step being run
    // (only a reply read out of order could count it, never a quarter of them).
    eprintln!("{beside_large} of {SMALL_STEPS} small Steps answered inside large ones");
    assert!(
        beside_large >= SMALL_STEPS / 4,
        "only {beside_large} of {SMALL_STEPS} small Steps were answered while the large Steps \
         in flight at their sending still ran"
    );
    server.stop().await;
}
