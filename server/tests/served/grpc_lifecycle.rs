//! Sessions through gRPC end to end: the lifecycle for N = 1 and N = 64, both autoreset modes,
//! fork and snapshot futures, Render, ServerInfo, Rollout, and a replay of the recorded
//! conformance trajectories.

use crate::grpc_support;
use crate::recorded;

use dinerdash_server::pb;
use dinerdash_server::policy::{PolicyKind, expert_action, run_episode};
use dinerdash_server::sim::{self, Config, Game};
use grpc_support::*;
use tonic::Code;

#[tokio::test]
async fn single_environment_lifecycle() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let created = c
        .create_session(create_request(1, pb::AutoresetMode::Unspecified, Some(7)))
        .await
        .unwrap()
        .into_inner();
    let id = created.session_id;
    assert_eq!(id.len(), 32);
    assert!(id.bytes().all(|b| b.is_ascii_hexdigit()));
    let spec = created.spec.unwrap();
    let (low, high) = sim::observation_bounds();
    assert_eq!(spec.num_envs, 1);
    assert_eq!(spec.observation_size, 40);
    assert_eq!(
        spec.observation_low,
        low.iter().map(|&v| i32::from(v)).collect::<Vec<_>>()
    );
    assert_eq!(
        spec.observation_high,
        high.iter().map(|&v| i32::from(v)).collect::<Vec<_>>()
    );
    assert_eq!(spec.observation_dtype, "float32");
    assert_eq!(spec.num_actions, 57);
    assert_eq!(spec.ruleset, "v0");
    // Unspecified means no autoreset for a single environment.
    assert_eq!(spec.autoreset_mode(), pb::AutoresetMode::Disabled);
    let config = spec.config.unwrap();
    assert_eq!(
        (config.patience_type1, config.lives, config.time_limit),
        (Some(600), Some(5), Some(0))
    );

    // The first Reset uses the creation seed.
    let (mut model, want) = Model::reset(1, Config::default(), 7, Mode::Disabled);
    let got = reset(&mut c, &id, None).await;
    assert_eq!(got, want);
    assert_eq!(got.seeds, vec![7]);

    // Play the expert to the end, checking every Batch.
    let mut expert = got.expert_actions[0];
    let mut steps = 0;
    loop {
        let want = model.step(&[i32::from(expert)]);
        let got = step(&mut c, &id, &[i32::from(expert)]).await;
        assert_eq!(got, want, "step {steps}");
        steps += 1;
        if got.terminated[0] == 1 {
            break;
        }
        assert!(steps < 100_000, "the episode never ended");
        expert = got.expert_actions[0];
    }
    let summary = run_episode(PolicyKind::Expert, Config::default(), 7, 100_000).unwrap();
    assert_eq!(steps, summary.steps);

    // The episode is over: no autoreset for N = 1.
    let err = c
        .step(pb::StepRequest {
            session_id: id.clone(),
            actions: pack(&[0]),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert_eq!(err.message(), "episode is over; call reset");

    // An unseeded Reset continues the stream.
    let again = reset(&mut c, &id, None).await;
    assert_eq!((again.seeds[0], again.stream_episodes[0]), (7, 1));
    let text = c
        .render(pb::RenderRequest {
            session_id: id.clone(),
            env_index: 0,
            color: false,
        })
        .await
        .unwrap()
        .into_inner()
        .text;
    assert!(!text.is_empty());
    assert!(!text.contains('\x1b'));

    c.close_session(pb::CloseSessionRequest {
        session_id: id.clone(),
    })
    .await
    .unwrap();
    let err = c
        .close_session(pb::CloseSessionRequest { session_id: id })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::NotFound);
    server.stop().await;
}

/// One life and a time limit make episodes end by both termination and truncation.
fn short() -> Config {
    Config {
        lives: 1,
        time_limit: 90,
        ..Config::default()
    }
}

/// Steps a session of `n` environments `steps` times with deterministic actions, comparing every
/// Batch with the local model.
async fn run_vector(
    n: u32,
    mode: pb::AutoresetMode,
    model_mode: Mode,
    config: Config,
    steps: usize,
) -> u64 {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mut request = create_request(n, mode, None);
    request.config = Some(pb::GameConfig {
        lives: Some(config.lives),
        time_limit: Some(config.time_limit),
        ..Default::default()
    });
    let id = create(&mut c, request).await;
    let (mut model, want) = Model::reset(n as usize, config, 1000, model_mode);
    let got = reset(&mut c, &id, Some(1000)).await;
    assert_eq!(got, want);
    assert_eq!(got.seeds, (1000..1000 + u64::from(n)).collect::<Vec<_>>());
    let mut actions = Actions::new(u64::from(n));
    let mut resets = 0;
    for s in 0..steps {
        let a: Vec<i32> = (0..n).map(|_| actions.next()).collect();
        let want = model.step(&a);
        let got = step(&mut c, &id, &a).await;
        assert_eq!(got, want, "step {s}");
        resets += got.reset.iter().map(|&r| u64::from(r)).sum::<u64>();
    }
    server.stop().await;
    resets
}

/// Every autoreset mode against the model, for 64 environments and for one (a vector env of one
/// environment, or one environment per server, asks for NEXT_STEP or SAME_STEP explicitly).
#[tokio::test]
async fn autoreset_modes_follow_the_model() {
    let cases = [
        (64, pb::AutoresetMode::Unspecified, Mode::NextStep),
        (64, pb::AutoresetMode::SameStep, Mode::SameStep),
        (1, pb::AutoresetMode::NextStep, Mode::NextStep),
        (1, pb::AutoresetMode::SameStep, Mode::SameStep),
    ];
    for (n, mode, model_mode) in cases {
        let resets = run_vector(n, mode, model_mode, short(), 400).await;
        assert!(
            resets > u64::from(n),
            "{mode:?} x {n}: autoreset happened {resets} times"
        );
    }
}

#[tokio::test]
async fn disabled_autoreset_refuses_ended_environments() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mut request = create_request(2, pb::AutoresetMode::Disabled, Some(3));
    request.config = Some(pb::GameConfig {
        time_limit: Some(3),
        ..Default::default()
    });
    let id = create(&mut c, request).await;
    reset(&mut c, &id, None).await;
    for _ in 0..3 {
        step(&mut c, &id, &[0, 0]).await;
    }
    let err = c
        .step(pb::StepRequest {
            session_id: id.clone(),
            actions: pack(&[0, 0]),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert_eq!(err.message(), "environment 0: episode is over; call reset");
    server.stop().await;
}

#[tokio::test]
async fn fork_and_snapshot_share_the_future() {
    let server = TestServer::start().await;
    let other = TestServer::start().await;
    let mut c = server.client().await;
    let mut c2 = other.client().await;
    let id = create(
        &mut c,
        create_request(4, pb::AutoresetMode::NextStep, Some(11)),
    )
    .await;
    reset(&mut c, &id, None).await;
    let mut actions = Actions::new(5);
    for _ in 0..30 {
        let a: Vec<i32> = (0..4).map(|_| actions.next()).collect();
        step(&mut c, &id, &a).await;
    }
    let fork = c
        .fork(pb::ForkRequest {
            session_id: id.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_ne!(fork.session_id, id);
    assert_eq!(fork.spec.unwrap().num_envs, 4);
    let snapshot = snapshot(&mut c, &id).await;
    let here = restore(&mut c, snapshot.clone()).await;
    // The snapshot also recreates the session on another server.
    let there = restore(&mut c2, snapshot).await;

    // Unseeded resets draw from the copied random streams too.
    for round in 0..3 {
        for s in 0..200 {
            let a: Vec<i32> = (0..4).map(|_| actions.next()).collect();
            let want = step(&mut c, &id, &a).await;
            assert_eq!(
                step(&mut c, &fork.session_id, &a).await,
                want,
                "fork, round {round} step {s}"
            );
            assert_eq!(
                step(&mut c, &here, &a).await,
                want,
                "restore, round {round} step {s}"
            );
            assert_eq!(
                step(&mut c2, &there, &a).await,
                want,
                "other server, round {round} step {s}"
            );
        }
        let want = reset(&mut c, &id, None).await;
        assert_eq!(reset(&mut c, &fork.session_id, None).await, want);
        assert_eq!(reset(&mut c, &here, None).await, want);
        assert_eq!(reset(&mut c2, &there, None).await, want);
    }
    other.stop().await;
    server.stop().await;
}

#[tokio::test]
async fn reset_with_seeds_arrivals_and_config() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let id = create(&mut c, create_request(3, pb::AutoresetMode::NextStep, None)).await;
    // Without any seed every environment seeds itself and reports it.
    let first = reset(&mut c, &id, None).await;
    assert_eq!(first.reset, vec![1, 1, 1]);
    for (i, &seed) in first.seeds.iter().enumerate() {
        let mut g = Game::new(Config::default()).unwrap();
        g.reset(Some(seed), None).unwrap();
        let obs = wire_observation(&g);
        assert_eq!(
            &first.observations[40 * i..40 * (i + 1)],
            &obs[..],
            "env {i} replays from its seed"
        );
    }
    let batch = c
        .reset(pb::ResetRequest {
            session_id: id.clone(),
            seeds: vec![5, 50, 500],
            arrivals: vec![pb::ArrivalList {
                groups: vec![pb::Arrival {
                    customer_type: 2,
                    size: 6,
                }],
            }],
            config: Some(pb::GameConfig {
                lives: Some(2),
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(batch.seeds, vec![5, 50, 500]);
    for i in 0..3 {
        let mut g = Game::new(Config {
            lives: 2,
            ..Config::default()
        })
        .unwrap();
        g.reset(Some([5, 50, 500][i]), Some(&[(2, 6)])).unwrap();
        let obs = wire_observation(&g);
        assert_eq!(&batch.observations[40 * i..40 * (i + 1)], &obs[..]);
        // The waiting group is the scripted one: size 6.
        assert_eq!(batch.observations[40 * i + 25], 6);
    }
    server.stop().await;
}

#[tokio::test]
async fn server_info_counts_sessions() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let info = c
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.ruleset, "v0");
    assert_eq!(info.live_sessions, 0);
    assert_eq!(info.snapshot_version, u32::from(sim::SNAPSHOT_VERSION));
    assert!(info.max_message_bytes >= 4 << 20);
    create(&mut c, create_request(2, pb::AutoresetMode::NextStep, None)).await;
    let info = c
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.live_sessions, 1);
    server.stop().await;
}

#[tokio::test]
async fn rollout_streams_one_episode_per_seed() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    for (policy, kind) in [
        (pb::Policy::Expert, PolicyKind::Expert),
        (pb::Policy::Random, PolicyKind::Random),
    ] {
        let mut stream = c
            .rollout(pb::RolloutRequest {
                policy: policy.into(),
                seeds: vec![3, 1, 2],
                config: None,
                max_steps: None,
                action_masks: true,
            })
            .await
            .unwrap()
            .into_inner();
        let mut seeds = vec![];
        while let Some(ep) = stream.message().await.unwrap() {
            let summary = run_episode(kind, Config::default(), ep.seed, 100_000).unwrap();
            assert_eq!(
                (ep.score, ep.steps, ep.lost, ep.terminated),
                (summary.score, summary.steps, summary.lost, true)
            );
            let t = ep.steps as usize;
            assert_eq!(ep.observations.len(), 40 * (t + 1));
            assert_eq!(ep.action_masks.len(), 57 * (t + 1));
            assert_eq!(
                i32s(&ep.rewards).iter().map(|&r| i64::from(r)).sum::<i64>(),
                ep.score
            );
            // Replay: the expert's choice is the one in the state before each step.
            let mut g = Game::new(Config::default()).unwrap();
            g.reset(Some(ep.seed), None).unwrap();
            for i in 0..t {
                assert_eq!(
                    ep.expert_actions[i],
                    expert_action(g.restaurant()),
                    "seed {} step {i}",
                    ep.seed
                );
                g.step(i64::from(ep.actions[i])).unwrap();
                let obs = wire_observation(&g);
                assert_eq!(&ep.observations[40 * (i + 1)..40 * (i + 2)], &obs[..]);
            }
            if policy == pb::Policy::Expert {
                assert_eq!(ep.actions, ep.expert_actions);
            }
            seeds.push(ep.seed);
        }
        assert_eq!(seeds, vec![3, 1, 2]);
    }
    server.stop().await;
}

fn obs_i64(bytes: &[u8]) -> Vec<i64> {
    bytes.iter().map(|&b| i64::from(b as i8)).collect()
}

#[tokio::test]
async fn conformance_trajectories_replay_through_grpc() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let mut episodes = 0;
    for (at, ep) in recorded::episodes() {
        let id = create(
            &mut c,
            create_request(1, pb::AutoresetMode::Unspecified, None),
        )
        .await;
        let mut batch = reset(&mut c, &id, Some(ep.seed)).await;
        assert_eq!(obs_i64(&batch.observations), ep.reset_obs, "{at}: reset");
        for (i, s) in ep.steps.iter().enumerate() {
            assert_eq!(
                i64::from(batch.expert_actions[0]),
                s.expert_action,
                "{at} step {i}: expert"
            );
            batch = step(&mut c, &id, &[s.action as i32]).await;
            assert_eq!(
                obs_i64(&batch.observations),
                s.obs,
                "{at} step {i}: observation"
            );
            assert_eq!(
                i64::from(i32s(&batch.rewards)[0]),
                s.reward,
                "{at} step {i}: reward"
            );
            assert_eq!(
                batch.terminated[0] == 1,
                s.terminated,
                "{at} step {i}: terminated"
            );
            assert_eq!(
                i64::from(i32s(&batch.scores)[0]),
                s.score,
                "{at} step {i}: score"
            );
            assert_eq!(u32s(&batch.lost)[0], s.lost, "{at} step {i}: lost");
            assert_eq!(u32s(&batch.ticks)[0] as usize, i + 1, "{at} step {i}: tick");
        }
        c.close_session(pb::CloseSessionRequest { session_id: id })
            .await
            .unwrap();
        episodes += 1;
    }
    assert!(episodes > 0);
    server.stop().await;
}
