//! Where errors become `tonic::Status`: one mapping per module's error, each variant mapped once,
//! with the structured details clients read: [`status`] for the session store's
//! [`SessionError`], [`rollout_status`] for the Rollout rules' [`RolloutError`]; both share the
//! memory budget's reasons ([`BudgetError`]).

use std::collections::HashMap;

use tonic::metadata::{MetadataMap, MetadataValue};
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

use crate::budget::BudgetError;
use crate::rollout::RolloutError;
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
        SessionError::OverBudget(b) => over_budget(b),
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
    let field = match &e {
        SessionError::ActionOutOfRange { env, .. } => Some(format!("actions[{env}]")),
        SessionError::KeptNeverReset(i) => Some(format!("reset_mask[{i}]")),
        _ if code == Code::InvalidArgument => Some(offending_field(&message).to_owned()),
        _ => None,
    };
    refusal(code, reason, metadata, message, field)
}

/// Maps a Rollout request's refusal to its gRPC status, with the same reasons and details as
/// the session store's errors of the same kind.
pub fn rollout_status(e: RolloutError) -> Status {
    let message = e.to_string();
    match &e {
        RolloutError::InvalidArgument(_) => {
            let field = offending_field(&message).to_owned();
            refusal(
                Code::InvalidArgument,
                "INVALID_ARGUMENT",
                vec![],
                message,
                Some(field),
            )
        }
        RolloutError::OverBudget(b) => {
            let (code, reason, metadata) = over_budget(b);
            refusal(code, reason, metadata, message, None)
        }
    }
}

impl From<SessionError> for Status {
    fn from(e: SessionError) -> Status {
        status(e)
    }
}

impl From<RolloutError> for Status {
    fn from(e: RolloutError) -> Status {
        rollout_status(e)
    }
}

/// The code, reason and metadata of a refusal by the memory budget.
fn over_budget(b: &BudgetError) -> (Code, &'static str, Vec<(&'static str, String)>) {
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

/// A status of `code` with `message`, an `ErrorInfo` of `reason` and `metadata`, and, when
/// `field` is given, a `BadRequest` violation naming it.
fn refusal(
    code: Code,
    reason: &str,
    metadata: Vec<(&'static str, String)>,
    message: String,
    field: Option<String>,
) -> Status {
    let metadata: HashMap<String, String> = metadata
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
    let mut details = ErrorDetails::with_error_info(reason, ERROR_DOMAIN, metadata);
    if let Some(field) = field {
        details.add_bad_request_violation(field, message.clone());
    }
    Status::with_error_details(code, message, details)
}

/// The trailer of gRPC retry push-back (gRFC A6): a client whose service config retries a
/// status reads it before retrying; a negative value means "do not retry".
pub const RETRY_PUSHBACK: &str = "grpc-retry-pushback-ms";

/// The refusal of new work (CreateSession, Fork, Restore, Rollout) by a draining server:
/// `UNAVAILABLE`, reason `DRAINING`, metadata "drain_remaining_ms", and the trailer
/// `grpc-retry-pushback-ms: -1`, so that a client whose channel retries `UNAVAILABLE` (its
/// `retryPolicy`) does not ask again: a draining server will not take the work however often it
/// is asked, and the caller must go elsewhere at once.
pub fn draining(e: Draining) -> Status {
    let metadata = HashMap::from([("drain_remaining_ms".to_string(), e.remaining_ms.to_string())]);
    let details = ErrorDetails::with_error_info("DRAINING", ERROR_DOMAIN, metadata);
    let mut trailers = MetadataMap::new();
    trailers.insert(RETRY_PUSHBACK, MetadataValue::from_static("-1"));
    Status::with_error_details_and_metadata(Code::Unavailable, e.to_string(), details, trailers)
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
