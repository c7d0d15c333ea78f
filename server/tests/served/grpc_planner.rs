//! The planner through gRPC: a session whose expert actions come from the planner (stepped on
//! the CPU pool) plays exactly the episode Rollout's POLICY_PLANNER streams for the same seed,
//! snapshots keep the choice, and a bad expert_policy is refused.

use crate::grpc_support;

use dinerdash_server::pb;
use grpc_support::*;
use tonic::Code;

/// Steps compared: enough for many planner decisions, few enough to stay fast.
const STEPS: u32 = 200;

fn planner_session(seed: u64) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest {
        expert_policy: pb::Policy::Planner.into(),
        ..create_request(1, pb::AutoresetMode::Disabled, Some(seed))
    }
}

#[tokio::test]
async fn a_planner_session_replays_the_planner_rollout() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let seed = 5;
    let mut stream = c
        .rollout(pb::RolloutRequest {
            policy: pb::Policy::Planner.into(),
            seeds: vec![seed],
            config: None,
            max_steps: Some(STEPS),
            action_masks: false,
        })
        .await
        .unwrap()
        .into_inner();
    let episode = stream.message().await.unwrap().expect("one episode");
    assert!(stream.message().await.unwrap().is_none());
    assert_eq!(episode.steps, STEPS);

    let created = c
        .create_session(planner_session(seed))
        .await
        .unwrap()
        .into_inner();
    let spec = created.spec.unwrap();
    assert!(spec.expert_actions);
    assert_eq!(spec.expert_policy, i32::from(pb::Policy::Planner));
    let id = created.session_id;
    let mut batch = reset(&mut c, &id, None).await;
    let mut actions = Vec::new();
    for step_index in 0..STEPS {
        let action = batch.expert_actions[0];
        assert_eq!(
            batch.action_masks[usize::from(action)],
            1,
            "step {step_index}"
        );
        actions.push(action);
        if step_index == STEPS / 2 {
            // A restored copy keeps the planner and makes the same choice.
            let bytes = snapshot(&mut c, &id).await;
            let copy = restore(&mut c, bytes).await;
            let copy_batch = step(&mut c, &copy, &[i32::from(action)]).await;
            batch = step(&mut c, &id, &[i32::from(action)]).await;
            assert_eq!(copy_batch.expert_actions, batch.expert_actions);
            continue;
        }
        batch = step(&mut c, &id, &[i32::from(action)]).await;
    }
    assert_eq!(actions, episode.actions);
    assert_eq!(i64::from(i32s(&batch.scores)[0]), episode.score);
    server.stop().await;
}

#[tokio::test]
async fn expert_policy_must_name_an_expert() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    for bad in [i32::from(pb::Policy::Random), 9] {
        let request = pb::CreateSessionRequest {
            expert_policy: bad,
            ..create_request(1, pb::AutoresetMode::Disabled, None)
        };
        let status = c.create_session(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(
            status.message().contains("expert_policy"),
            "{}",
            status.message()
        );
    }
    // Without expert actions the policy does not matter, and the Spec says none.
    let request = pb::CreateSessionRequest {
        expert_actions: false,
        expert_policy: pb::Policy::Planner.into(),
        ..create_request(1, pb::AutoresetMode::Disabled, None)
    };
    let spec = c
        .create_session(request)
        .await
        .unwrap()
        .into_inner()
        .spec
        .unwrap();
    assert!(!spec.expert_actions);
    assert_eq!(spec.expert_policy, i32::from(pb::Policy::Unspecified));
    server.stop().await;
}
