//! Many clients at once: each of 64 tasks steps its own session thousands of times and sees only
//! its own game; several tasks hammering one session see its steps serialized.

use crate::grpc_support;

use std::collections::BTreeSet;

use dinerdash_server::pb;
use dinerdash_server::sim::{Config, Game};
use grpc_support::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixty_four_sessions_in_parallel_do_not_cross_talk() {
    const TASKS: u64 = 64;
    const STEPS: usize = 1000;
    let server = TestServer::start().await;
    // A few connections, shared by the tasks as a real trainer's workers would.
    let mut clients = Vec::new();
    for _ in 0..4 {
        clients.push(server.client().await);
    }
    let mut tasks = Vec::new();
    for t in 0..TASKS {
        let mut c = clients[t as usize % clients.len()].clone();
        tasks.push(tokio::spawn(async move {
            let mut request = create_request(1, pb::AutoresetMode::Unspecified, Some(t));
            request.action_masks = false;
            request.expert_actions = false;
            let id = create(&mut c, request).await;
            let mut game = Game::new(Config::default()).unwrap();
            game.reset(Some(t), None).unwrap();
            reset(&mut c, &id, None).await;
            let mut actions = Actions::new(t);
            for s in 0..STEPS {
                let a = actions.next();
                let batch = step(&mut c, &id, &[a]).await;
                let out = game.step(i64::from(a)).unwrap();
                let obs = wire_observation(&game);
                assert_eq!(batch.observations, obs, "task {t} step {s}");
                assert_eq!(
                    i32s(&batch.rewards),
                    vec![out.reward as i32],
                    "task {t} step {s}"
                );
                if out.terminated {
                    let again = reset(&mut c, &id, None).await;
                    game.reset(None, None).unwrap();
                    assert_eq!(again.seeds, vec![t]);
                }
            }
            c.close_session(pb::CloseSessionRequest { session_id: id })
                .await
                .unwrap();
        }));
    }
    for task in tasks {
        task.await.unwrap();
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_session_hammered_by_many_tasks_stays_consistent() {
    const TASKS: usize = 8;
    const STEPS: usize = 400;
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mut request = create_request(1, pb::AutoresetMode::Unspecified, Some(9));
    // Waiting only: with 1000 lives the episode outlasts every step below.
    request.config = Some(pb::GameConfig {
        lives: Some(1000),
        ..Default::default()
    });
    let id = create(&mut c, request).await;
    reset(&mut c, &id, None).await;
    let mut tasks = Vec::new();
    for _ in 0..TASKS {
        let mut c = server.client().await;
        let id = id.clone();
        tasks.push(tokio::spawn(async move {
            let mut ticks = Vec::with_capacity(STEPS);
            for _ in 0..STEPS {
                let batch = step(&mut c, &id, &[0]).await;
                assert_eq!(batch.terminated, vec![0]);
                ticks.push(u32s(&batch.ticks)[0]);
            }
            ticks
        }));
    }
    let mut seen = BTreeSet::new();
    for task in tasks {
        let ticks = task.await.unwrap();
        // Each task sees its own steps in order...
        assert!(ticks.windows(2).all(|w| w[0] < w[1]));
        seen.extend(ticks);
    }
    // ...and together the steps were applied one at a time, none lost or doubled.
    let total = (TASKS * STEPS) as u32;
    assert_eq!(seen, (1..=total).collect::<BTreeSet<_>>());
    // The session ends up exactly where a local game waiting as many ticks is.
    let mut game = Game::new(Config {
        lives: 1000,
        ..Config::default()
    })
    .unwrap();
    game.reset(Some(9), None).unwrap();
    for _ in 0..total {
        game.step(0).unwrap();
    }
    let snapshot = snapshot(&mut c, &id).await;
    let copy = restore(&mut c, snapshot).await;
    let last = step(&mut c, &copy, &[0]).await;
    game.step(0).unwrap();
    let obs = wire_observation(&game);
    assert_eq!(last.observations, obs);
    assert_eq!(u32s(&last.ticks), vec![total + 1]);
    server.stop().await;
}
