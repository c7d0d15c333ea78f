//! One tenant's large Steps, stepped in parallel on the stepping threads, do not starve another
//! tenant's small ones: while three clients step sessions of 4,096 environments back to back on
//! a server with two async workers, a fourth client's single-environment session completes its
//! Steps, each answered while large Steps are in flight.

use crate::grpc_support;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
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
    let in_flight = Arc::new(AtomicUsize::new(0));
    let large_steps = Arc::new(AtomicU64::new(0));
    let mut large = Vec::new();
    for k in 0..LARGE_CLIENTS {
        let mut c = server.client().await;
        let (stop, in_flight, large_steps) = (stop.clone(), in_flight.clone(), large_steps.clone());
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
                in_flight.fetch_add(1, Ordering::SeqCst);
                step(&mut c, &id, &batch).await;
                in_flight.fetch_sub(1, Ordering::SeqCst);
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
        let sent = Instant::now();
        let a = actions.next();
        tokio::time::timeout(PATIENCE, step(&mut c, &id, &[a]))
            .await
            .expect("a small Step waited for ever");
        latencies.push(sent.elapsed());
        if in_flight.load(Ordering::SeqCst) > 0 {
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
    // The small Steps were answered while the large ones kept stepping (never all between two
    // requests at once at every one of them).
    assert!(beside_large > 0, "no small Step ran beside a large one");
    server.stop().await;
}
