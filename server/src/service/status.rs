//! Where errors become `tonic::Status`: each [`SessionError`] mapped once, with the structured
//! details clients read.

use std::collections::HashMap;

use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

use crate::budget::BudgetError;
use crate::session::SessionError;
use crate::shutdown::Draining;

/// `ErrorInfo.domain` of every error this server returns.
pub const ERROR_DOMAIN: &str = "dinerdash.v1";

/// Maps a session error to its gRPC status: the one place that decides the codes and the
/// structured details (google.rpc `ErrorInfo`, and `BadRequest` for INVALID_ARGUMENT) that
/// clients map from, never from the message text. The reasons are listed in the proto's header.
pub fn status(e: SessionError) -> Status {
    let message = e.to_string();
    let (code, reason, metadata) = match &e {
        SessionError::NotFound(id) => (
            Code::NotFound,
            "SESSION_NOT_FOUND",
            vec![("session_id", id.clone())],
        ),
        SessionError::InvalidArgument(_) => (Code::InvalidArgument, "INVALID_ARGUMENT", vec![]),
        SessionError::KeptNeverReset(i) => (
            Code::InvalidArgument,
            "INVALID_ARGUMENT",
            vec![("env_index", i.to_string())],
        ),
        SessionError::ActionOutOfRange { env, action } => (
            Code::InvalidArgument,
            "ACTION_OUT_OF_RANGE",
            vec![
                ("env_index", env.to_string()),
                ("action", action.to_string()),
            ],
        ),
        SessionError::TooManySessions(max) => (
            Code::ResourceExhausted,
            "TOO_MANY_SESSIONS",
            vec![("max_sessions", max.to_string())],
        ),
        SessionError::OverBudget(b) => {
            let (reason, metadata) = match b {
                BudgetError::Memory { needed, used, max } => (
                    "MEMORY_BUDGET",
                    vec![
                        ("needed_bytes", needed.to_string()),
                        ("used_bytes", used.to_string()),
                        ("max_bytes", max.to_string()),
                    ],
                ),
                BudgetError::TenantEnvs { tenant, max, .. } => (
                    "TENANT_ENVS",
                    vec![("tenant", tenant.clone()), ("max", max.to_string())],
                ),
                BudgetError::TenantSessions { tenant, max } => (
                    "TENANT_SESSIONS",
                    vec![("tenant", tenant.clone()), ("max", max.to_string())],
                ),
                BudgetError::TenantRollouts { tenant, max } => (
                    "TENANT_ROLLOUTS",
                    vec![("tenant", tenant.clone()), ("max", max.to_string())],
                ),
                BudgetError::Sessions(max) => {
                    ("TOO_MANY_SESSIONS", vec![("max_sessions", max.to_string())])
                }
            };
            (Code::ResourceExhausted, reason, metadata)
        }
        SessionError::NotReset => (Code::FailedPrecondition, "NOT_RESET", vec![]),
        SessionError::EpisodeOver => (
            Code::FailedPrecondition,
            "EPISODE_OVER",
            vec![("env_index", "0".to_string())],
        ),
        SessionError::EnvEpisodeOver(i) => (
            Code::FailedPrecondition,
            "EPISODE_OVER",
            vec![("env_index", i.to_string())],
        ),
        SessionError::Internal(_) => (Code::Internal, "INTERNAL", vec![]),
    };
    let metadata: HashMap<String, String> = metadata
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
    let mut details = ErrorDetails::with_error_info(reason, ERROR_DOMAIN, metadata);
    match &e {
        SessionError::ActionOutOfRange { env, .. } => {
            details.add_bad_request_violation(format!("actions[{env}]"), message.clone());
        }
        SessionError::KeptNeverReset(i) => {
            details.add_bad_request_violation(format!("reset_mask[{i}]"), message.clone());
        }
        _ if code == Code::InvalidArgument => {
            details.add_bad_request_violation(offending_field(&message), message.clone());
        }
        _ => {}
    }
    Status::with_error_details(code, message, details)
}

/// The refusal of new work (CreateSession, Fork, Restore, Rollout) by a draining server:
/// `UNAVAILABLE`, reason `DRAINING`, metadata "drain_remaining_ms".
pub fn draining(e: Draining) -> Status {
    let metadata = HashMap::from([("drain_remaining_ms".to_string(), e.remaining_ms.to_string())]);
    let details = ErrorDetails::with_error_info("DRAINING", ERROR_DOMAIN, metadata);
    Status::with_error_details(Code::Unavailable, e.to_string(), details)
}

/// The field an INVALID_ARGUMENT message is about: by the convention of every such message in
/// this server, its leading path (`actions[3]`, `arrivals[0].groups[2].size`, `snapshot`,
/// `lives`), up to the first character that cannot be part of one.
fn offending_field(message: &str) -> &str {
    let end = message
        .find(|c: char| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '[' | ']')))
        .unwrap_or(message.len());
    &message[..end]
}
