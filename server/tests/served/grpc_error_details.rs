//! The structured details of every kind of refusal: the google.rpc `ErrorInfo` reason (and its
//! metadata) and the `BadRequest` field that clients map errors from, never from message text.

use crate::grpc_support;

use dinerdash_server::pb;
use dinerdash_server::service::ERROR_DOMAIN;
use grpc_support::*;
use tonic::{Code, Status};
use tonic_types::StatusExt;

/// The reason, the metadata entry `key` (if given) and the BadRequest field of a refusal.
#[track_caller]
fn details<T: std::fmt::Debug>(
    result: Result<T, Status>,
    code: Code,
    key: &str,
) -> (String, Option<String>, Option<String>) {
    let status = result.expect_err("expected an error");
    assert_eq!(status.code(), code, "{}", status.message());
    let details = status.get_error_details();
    let info = details
        .error_info()
        .expect("every refusal carries an ErrorInfo");
    assert_eq!(info.domain, ERROR_DOMAIN);
    let field = details
        .bad_request()
        .map(|b| b.field_violations[0].field.clone());
    (info.reason.clone(), info.metadata.get(key).cloned(), field)
}

fn step_request(id: &str, actions: &[i32]) -> pb::StepRequest {
    pb::StepRequest {
        session_id: id.to_owned(),
        actions: pack(actions),
    }
}

#[tokio::test]
async fn refusals_carry_reason_field_and_environment() {
    let server = TestServer::start().await;
    let mut c = server.client().await;
    let ghost = "0123456789abcdef0123456789abcdef";
    assert_eq!(
        details(
            c.step(step_request(ghost, &[0])).await,
            Code::NotFound,
            "session_id"
        ),
        ("SESSION_NOT_FOUND".into(), Some(ghost.into()), None)
    );

    let id = create(
        &mut c,
        create_request(4, pb::AutoresetMode::Disabled, Some(1)),
    )
    .await;
    assert_eq!(
        details(
            c.step(step_request(&id, &[0; 4])).await,
            Code::FailedPrecondition,
            ""
        ),
        ("NOT_RESET".into(), None, None)
    );
    reset(&mut c, &id, None).await;
    assert_eq!(
        details(
            c.step(step_request(&id, &[0, 0, 57, 0])).await,
            Code::InvalidArgument,
            "env_index"
        ),
        (
            "ACTION_OUT_OF_RANGE".into(),
            Some("2".into()),
            Some("actions[2]".into())
        )
    );
    assert_eq!(
        details(
            c.step(step_request(&id, &[0, 0, 0])).await,
            Code::InvalidArgument,
            ""
        ),
        ("INVALID_ARGUMENT".into(), None, Some("actions".into()))
    );
    let bad_arrivals = pb::ResetRequest {
        session_id: id.clone(),
        arrivals: vec![pb::ArrivalList {
            groups: vec![pb::Arrival {
                customer_type: 1,
                size: 9,
            }],
        }],
        ..Default::default()
    };
    assert_eq!(
        details(c.reset(bad_arrivals).await, Code::InvalidArgument, "").2,
        Some("arrivals[0].groups[0].size".into())
    );
    let bad_render = pb::RenderRequest {
        session_id: id.clone(),
        env_index: 9,
        color: false,
    };
    assert_eq!(
        details(c.render(bad_render).await, Code::InvalidArgument, "").2,
        Some("env_index".into())
    );

    let fresh = create(
        &mut c,
        create_request(2, pb::AutoresetMode::NextStep, Some(1)),
    )
    .await;
    let keep_unreset = pb::ResetRequest {
        session_id: fresh,
        reset_mask: vec![1, 0],
        ..Default::default()
    };
    assert_eq!(
        details(
            c.reset(keep_unreset).await,
            Code::InvalidArgument,
            "env_index"
        ),
        (
            "INVALID_ARGUMENT".into(),
            Some("1".into()),
            Some("reset_mask[1]".into())
        )
    );

    // A one-group-per-life game that never seats anyone ends once a group is lost; with
    // autoreset DISABLED the next step names the environment whose episode is over.
    let mut config = create_request(2, pb::AutoresetMode::Disabled, Some(1));
    config.config = Some(pb::GameConfig {
        lives: Some(1),
        ..Default::default()
    });
    let over = create(&mut c, config).await;
    reset(&mut c, &over, None).await;
    let mut refusal = None;
    for _ in 0..100_000 {
        match c.step(step_request(&over, &[0, 0])).await {
            Ok(_) => continue,
            Err(status) => {
                refusal = Some(status);
                break;
            }
        }
    }
    let refusal = refusal.expect("a waiting-only game loses its one life");
    let (reason, env, _) = details::<()>(Err(refusal), Code::FailedPrecondition, "env_index");
    assert_eq!(reason, "EPISODE_OVER");
    assert!(matches!(env.as_deref(), Some("0" | "1")), "{env:?}");
    server.stop().await;
}
