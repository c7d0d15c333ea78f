//! Every refusal of the service, asserted by status code and message; the server keeps serving
//! after each one.

use crate::grpc_support;

use dinerdash_server::pb;
use dinerdash_server::server::ServerConfig;
use dinerdash_server::session::Limits;
use grpc_support::*;
use tonic::{Code, Status};

#[track_caller]
fn assert_status<T: std::fmt::Debug>(result: Result<T, Status>, code: Code, message: &str) {
    let status = result.expect_err("expected an error");
    assert_eq!((status.code(), status.message()), (code, message));
}

fn step_request(id: &str, actions: &[i32]) -> pb::StepRequest {
    pb::StepRequest {
        session_id: id.to_owned(),
        actions: pack(actions),
    }
}

#[tokio::test]
async fn unknown_sessions_are_not_found() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let ghost = "0123456789abcdef0123456789abcdef";
    let message = format!("session {ghost} not found (closed or expired)");
    let id = || ghost.to_owned();
    let refusals = [
        ("step", c.step(step_request(ghost, &[0])).await.map(drop)),
        (
            "reset",
            c.reset(pb::ResetRequest {
                session_id: id(),
                ..Default::default()
            })
            .await
            .map(drop),
        ),
        (
            "fork",
            c.fork(pb::ForkRequest { session_id: id() }).await.map(drop),
        ),
        (
            "snapshot",
            c.snapshot(pb::SnapshotRequest {
                session_id: id(),
                ..Default::default()
            })
            .await
            .map(drop),
        ),
        (
            "render",
            c.render(pb::RenderRequest {
                session_id: id(),
                ..Default::default()
            })
            .await
            .map(drop),
        ),
        (
            "close_session",
            c.close_session(pb::CloseSessionRequest { session_id: id() })
                .await
                .map(drop),
        ),
    ];
    for (call, result) in refusals {
        let status = result.expect_err(call);
        assert_eq!(
            (status.code(), status.message()),
            (Code::NotFound, &*message),
            "{call}"
        );
    }
    assert_status(
        c.step(step_request("not-an-id", &[0])).await,
        Code::NotFound,
        "session not-an-id not found (closed or expired)",
    );
    // A huge bogus ID is not echoed whole.
    let long = "x".repeat(10_000);
    let status = c.step(step_request(&long, &[0])).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().len() < 200);
    server.stop().await;
}

#[tokio::test]
async fn bad_steps_name_the_field_and_range() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let id = create(
        &mut c,
        create_request(4, pb::AutoresetMode::NextStep, Some(1)),
    )
    .await;
    assert_status(
        c.step(step_request(&id, &[0, 0, 0, 0])).await,
        Code::FailedPrecondition,
        "the session was never reset; call reset",
    );
    reset(&mut c, &id, None).await;
    assert_status(
        c.step(step_request(&id, &[0, 0, 0])).await,
        Code::InvalidArgument,
        "actions must hold 4 little-endian int32 (16 bytes), got 12 bytes",
    );
    assert_status(
        c.step(pb::StepRequest {
            session_id: id.clone(),
            actions: vec![0; 17],
        })
        .await,
        Code::InvalidArgument,
        "actions must hold 4 little-endian int32 (16 bytes), got 17 bytes",
    );
    assert_status(
        c.step(step_request(&id, &[0, 0, 0, 57])).await,
        Code::InvalidArgument,
        "actions[3] must be in 0..=56, got 57",
    );
    assert_status(
        c.step(step_request(&id, &[-1, 0, 0, 0])).await,
        Code::InvalidArgument,
        "actions[0] must be in 0..=56, got -1",
    );
    // Refused steps changed nothing: the session still steps from tick 0.
    let batch = step(&mut c, &id, &[0, 0, 0, 0]).await;
    assert_eq!(u32s(&batch.ticks), vec![1, 1, 1, 1]);
    server.stop().await;
}

#[tokio::test]
async fn bad_sessions_are_refused() {
    let limits = Limits {
        max_sessions: 2,
        max_envs_per_session: 8,
        ..Limits::default()
    };
    let config = ServerConfig {
        limits,
        ..ServerConfig::default()
    };
    let server = TestServer::start_with(config, false).await;
    let mut c = server.client().await;
    for (n, got) in [(0, 0), (9, 9)] {
        assert_status(
            c.create_session(create_request(n, pb::AutoresetMode::NextStep, None))
                .await,
            Code::InvalidArgument,
            &format!("num_envs must be in 1..=8, got {got}"),
        );
    }
    let mut request = create_request(1, pb::AutoresetMode::NextStep, None);
    request.config = Some(pb::GameConfig {
        patience_type2: Some(1000),
        ..Default::default()
    });
    assert_status(
        c.create_session(request).await,
        Code::InvalidArgument,
        "patience_type2 must be in 1..=999, got 1000",
    );
    let mut request = create_request(1, pb::AutoresetMode::NextStep, None);
    request.autoreset_mode = 9;
    assert_status(
        c.create_session(request).await,
        Code::InvalidArgument,
        "autoreset_mode must be in 0..=3, got 9",
    );

    // The session limit, for CreateSession, Fork and Restore alike.
    let a = create(
        &mut c,
        create_request(4, pb::AutoresetMode::NextStep, Some(1)),
    )
    .await;
    let snapshot = snapshot(&mut c, &a).await;
    create(&mut c, create_request(1, pb::AutoresetMode::NextStep, None)).await;
    let full = "the server holds its maximum of 2 sessions; close one or raise --max-sessions";
    assert_status(
        c.create_session(create_request(1, pb::AutoresetMode::NextStep, None))
            .await,
        Code::ResourceExhausted,
        full,
    );
    assert_status(
        c.fork(pb::ForkRequest {
            session_id: a.clone(),
        })
        .await,
        Code::ResourceExhausted,
        full,
    );
    assert_status(
        c.restore(pb::RestoreRequest {
            snapshot: snapshot.clone(),
        })
        .await,
        Code::ResourceExhausted,
        full,
    );
    c.close_session(pb::CloseSessionRequest { session_id: a })
        .await
        .unwrap();
    c.restore(pb::RestoreRequest { snapshot }).await.unwrap();
    server.stop().await;
}

#[tokio::test]
async fn bad_resets_are_refused() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let id = create(&mut c, create_request(2, pb::AutoresetMode::NextStep, None)).await;
    let list = |groups: &[(u32, u32)]| pb::ArrivalList {
        groups: groups
            .iter()
            .map(|&(customer_type, size)| pb::Arrival {
                customer_type,
                size,
            })
            .collect(),
    };
    let cases: Vec<(pb::ResetRequest, &str)> = vec![
        (
            pb::ResetRequest {
                seed: Some(1),
                seeds: vec![1, 2],
                ..Default::default()
            },
            "seed and seeds are exclusive: give at most one",
        ),
        (
            pb::ResetRequest {
                seeds: vec![1, 2, 3],
                ..Default::default()
            },
            "seeds must hold 0 or 2 entries (one per environment), got 3",
        ),
        (
            pb::ResetRequest {
                arrivals: vec![list(&[(1, 1)]); 3],
                ..Default::default()
            },
            "arrivals must hold 0, 1 or 2 lists, got 3",
        ),
        (
            pb::ResetRequest {
                arrivals: vec![list(&[])],
                ..Default::default()
            },
            "arrivals[0] must hold 1..=200 groups, got 0",
        ),
        (
            pb::ResetRequest {
                arrivals: vec![list(&[(1, 1); 201])],
                ..Default::default()
            },
            "arrivals[0] must hold 1..=200 groups, got 201",
        ),
        (
            pb::ResetRequest {
                arrivals: vec![list(&[(1, 1)]), list(&[(1, 1), (3, 2)])],
                ..Default::default()
            },
            "arrivals[1].groups[1].customer_type must be in 1..=2, got 3",
        ),
        (
            pb::ResetRequest {
                arrivals: vec![list(&[(2, 0)])],
                ..Default::default()
            },
            "arrivals[0].groups[0].size must be in 1..=6, got 0",
        ),
        (
            pb::ResetRequest {
                config: Some(pb::GameConfig {
                    lives: Some(0),
                    ..Default::default()
                }),
                ..Default::default()
            },
            "lives must be in 1..=1000, got 0",
        ),
        (
            pb::ResetRequest {
                reset_mask: vec![1, 2],
                ..Default::default()
            },
            "reset_mask[1] must be 0 or 1, got 2",
        ),
        (
            pb::ResetRequest {
                reset_mask: vec![1, 0],
                ..Default::default()
            },
            "environment 1 has never been reset: include it in reset_mask",
        ),
    ];
    for (mut request, message) in cases {
        request.session_id = id.clone();
        assert_status(c.reset(request).await, Code::InvalidArgument, message);
    }
    // Nothing was reset by the refused requests.
    assert_status(
        c.step(step_request(&id, &[0, 0])).await,
        Code::FailedPrecondition,
        "the session was never reset; call reset",
    );
    server.stop().await;
}

#[tokio::test]
async fn bad_render_restore_and_rollout_requests_are_refused() {
    let limits = Limits {
        max_envs_per_session: 3,
        ..Limits::default()
    };
    let server = TestServer::start_with(
        ServerConfig {
            limits,
            ..ServerConfig::default()
        },
        false,
    )
    .await;
    let mut c = server.client().await;
    let id = create(
        &mut c,
        create_request(3, pb::AutoresetMode::NextStep, Some(2)),
    )
    .await;
    let render = |env_index| pb::RenderRequest {
        session_id: id.clone(),
        env_index,
        color: true,
    };
    assert_status(
        c.render(render(0)).await,
        Code::FailedPrecondition,
        "the session was never reset; call reset",
    );
    reset(&mut c, &id, None).await;
    assert_status(
        c.render(render(3)).await,
        Code::InvalidArgument,
        "env_index must be in 0..=2, got 3",
    );
    assert!(
        c.render(render(2))
            .await
            .unwrap()
            .into_inner()
            .text
            .contains('\x1b')
    );

    let taken = snapshot(&mut c, &id).await;
    let restore = |snapshot: Vec<u8>| pb::RestoreRequest { snapshot };
    assert_status(
        c.restore(restore(b"garbage".to_vec())).await,
        Code::InvalidArgument,
        "snapshot: not a DDss snapshot",
    );
    let mut other_version = taken.clone();
    other_version[4] = 99;
    assert_status(
        c.restore(restore(other_version)).await,
        Code::InvalidArgument,
        "snapshot: snapshot version 99 is not supported (this server reads version 1)",
    );
    let status = c
        .restore(restore(taken[..taken.len() / 2].to_vec()))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().starts_with("snapshot: corrupt snapshot"),
        "{}",
        status.message()
    );

    // A snapshot of more environments than this server allows.
    let big = TestServer::start().await;
    let mut cb = big.client().await;
    let wide = create(
        &mut cb,
        create_request(4, pb::AutoresetMode::NextStep, Some(2)),
    )
    .await;
    let wide = snapshot(&mut cb, &wide).await;
    assert_status(
        c.restore(restore(wide)).await,
        Code::InvalidArgument,
        "snapshot: the number of environments must be in 1..=3, got 4",
    );
    big.stop().await;

    let rollout =
        |policy: pb::Policy, seeds: Vec<u64>, max_steps: Option<u32>| pb::RolloutRequest {
            policy: policy.into(),
            seeds,
            config: None,
            max_steps,
            action_masks: false,
        };
    assert_status(
        c.rollout(rollout(pb::Policy::Expert, vec![], None)).await,
        Code::InvalidArgument,
        "seeds must hold 1..=10000 seeds, got 0",
    );
    assert_status(
        c.rollout(rollout(pb::Policy::Unspecified, vec![1], None))
            .await,
        Code::InvalidArgument,
        "policy must be POLICY_EXPERT (1), POLICY_RANDOM (2) or POLICY_PLANNER (3), got 0",
    );
    assert_status(
        c.rollout(rollout(pb::Policy::Random, vec![1], Some(0)))
            .await,
        Code::InvalidArgument,
        "max_steps must be in 1..=100000, got 0",
    );
    let mut bad_config = rollout(pb::Policy::Random, vec![1], None);
    bad_config.config = Some(pb::GameConfig {
        arrival_interval: Some(0),
        ..Default::default()
    });
    assert_status(
        c.rollout(bad_config).await,
        Code::InvalidArgument,
        "arrival_interval must be in 1..=1000, got 0",
    );
    server.stop().await;
}

#[tokio::test]
async fn oversized_messages_are_refused_by_limit() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let status = c
        .restore(pb::RestoreRequest {
            snapshot: vec![0; 17 << 20],
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    assert!(
        status.message().contains("too large"),
        "{}",
        status.message()
    );
    // Still serving.
    c.server_info(pb::ServerInfoRequest {}).await.unwrap();
    server.stop().await;
}
