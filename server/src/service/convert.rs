//! Conversion between the protocol's messages and the session store's types: absent fields
//! filled in, enums and packed flags checked (INVALID_ARGUMENT as a [`SessionError`]), replies
//! moved rather than copied.

use crate::pb;
use crate::policy::PolicyKind;
use crate::rollout::Recording;
use crate::session::{
    Autoreset, Batch, ExpertActions, ResetArgs, SessionError, SessionId, SessionSpec,
};
use crate::sim::{self, Config, NUM_ACTIONS, OBSERVATION_SIZE};

/// The game configuration of a request: absent fields (or an absent message) keep `v0`.
pub(super) fn config_from(config: Option<&pb::GameConfig>) -> Config {
    config.map_or_else(Config::default, pb::GameConfig::config)
}

fn autoreset_to(mode: Autoreset) -> pb::AutoresetMode {
    match mode {
        Autoreset::NextStep => pb::AutoresetMode::NextStep,
        Autoreset::SameStep => pb::AutoresetMode::SameStep,
        Autoreset::Disabled => pb::AutoresetMode::Disabled,
    }
}

/// The wire's mode; UNSPECIFIED is DISABLED for one environment (a Gymnasium `Env`), else NEXT_STEP.
pub(super) fn autoreset_from(value: i32, num_envs: u32) -> Result<Autoreset, SessionError> {
    match pb::AutoresetMode::try_from(value) {
        Ok(pb::AutoresetMode::Unspecified) if num_envs == 1 => Ok(Autoreset::Disabled),
        Ok(pb::AutoresetMode::Unspecified | pb::AutoresetMode::NextStep) => Ok(Autoreset::NextStep),
        Ok(pb::AutoresetMode::SameStep) => Ok(Autoreset::SameStep),
        Ok(pb::AutoresetMode::Disabled) => Ok(Autoreset::Disabled),
        Err(_) => Err(SessionError::InvalidArgument(format!(
            "autoreset_mode must be in 0..=3, got {value}"
        ))),
    }
}

/// Which expert fills a session's `expert_actions`: the reference unless the request asks for the
/// planner.
pub(super) fn expert_actions_from(
    enabled: bool,
    policy: i32,
) -> Result<ExpertActions, SessionError> {
    let expert = match pb::Policy::try_from(policy) {
        Ok(pb::Policy::Unspecified | pb::Policy::Expert) => ExpertActions::Reference,
        Ok(pb::Policy::Planner) => ExpertActions::Planner,
        _ => {
            return Err(SessionError::InvalidArgument(format!(
                "expert_policy must be POLICY_UNSPECIFIED (0), POLICY_EXPERT (1) or POLICY_PLANNER (3), got {policy}"
            )));
        }
    };
    Ok(if enabled { expert } else { ExpertActions::None })
}

/// Which policy a Rollout request asks for.
pub(super) fn policy_from(policy: i32) -> Result<PolicyKind, SessionError> {
    match pb::Policy::try_from(policy) {
        Ok(pb::Policy::Expert) => Ok(PolicyKind::Expert),
        Ok(pb::Policy::Random) => Ok(PolicyKind::Random),
        Ok(pb::Policy::Planner) => Ok(PolicyKind::Planner),
        _ => Err(SessionError::InvalidArgument(format!(
            "policy must be POLICY_EXPERT (1), POLICY_RANDOM (2) or POLICY_PLANNER (3), got {policy}"
        ))),
    }
}

/// Packed uint8 flags of the wire (each 0 or 1).
fn flags(field: &str, bytes: &[u8]) -> Result<Vec<bool>, SessionError> {
    match bytes.iter().position(|&b| b > 1) {
        Some(i) => Err(SessionError::InvalidArgument(format!(
            "{field}[{i}] must be 0 or 1, got {}",
            bytes[i]
        ))),
        None => Ok(bytes.iter().map(|&b| b == 1).collect()),
    }
}

/// A Reset request's arguments as they came, converted only once the session they name is
/// found and its number of environments bounds them ([`PendingReset::args`]): an unknown
/// session or an oversized list costs no conversion.
#[derive(Debug)]
pub(super) struct PendingReset(pb::ResetRequest);

/// A Reset request as the session it names and its arguments, not yet converted.
pub(super) fn reset_from(mut r: pb::ResetRequest) -> (String, PendingReset) {
    (std::mem::take(&mut r.session_id), PendingReset(r))
}

impl PendingReset {
    /// The arguments for a session of `n` environments. Seeds, arrival lists and reset flags
    /// beyond `n` are refused before anything is converted (the session then checks the exact
    /// counts, with the same messages).
    pub(super) fn args(self, n: usize) -> Result<ResetArgs, SessionError> {
        let r = self.0;
        let over = |field: &str, allowed: String, got: usize| {
            Err(SessionError::InvalidArgument(format!(
                "{field} must hold {allowed}, got {got}"
            )))
        };
        let each = format!("0 or {n} entries (one per environment)");
        if r.seeds.len() > n {
            return over("seeds", each, r.seeds.len());
        }
        if r.arrivals.len() > n {
            return over("arrivals", format!("0, 1 or {n} lists"), r.arrivals.len());
        }
        if r.reset_mask.len() > n {
            return over("reset_mask", each, r.reset_mask.len());
        }
        Ok(ResetArgs {
            seed: r.seed,
            seeds: r.seeds,
            arrivals: r
                .arrivals
                .iter()
                .map(|list| {
                    list.groups
                        .iter()
                        .map(|g| (g.customer_type, g.size))
                        .collect()
                })
                .collect(),
            config: r.config.as_ref().map(|c| config_from(Some(c))),
            reset_mask: flags("reset_mask", &r.reset_mask)?,
        })
    }
}

fn spec_to(spec: &SessionSpec) -> pb::Spec {
    let (low, high) = sim::observation_bounds();
    pb::Spec {
        num_envs: spec.num_envs as u32,
        observation_size: OBSERVATION_SIZE as u32,
        observation_low: low.iter().map(|&v| i32::from(v)).collect(),
        observation_high: high.iter().map(|&v| i32::from(v)).collect(),
        observation_dtype: "float32".into(),
        num_actions: NUM_ACTIONS as u32,
        ruleset: sim::RULESET.into(),
        server_version: crate::SERVER_VERSION.into(),
        autoreset_mode: autoreset_to(spec.options.autoreset).into(),
        config: Some(pb::GameConfig::of(&spec.config)),
        action_masks: spec.options.action_masks,
        expert_actions: spec.options.expert_actions.enabled(),
        expert_policy: match spec.options.expert_actions {
            ExpertActions::None => pb::Policy::Unspecified,
            ExpertActions::Reference => pb::Policy::Expert,
            ExpertActions::Planner => pb::Policy::Planner,
        }
        .into(),
    }
}

/// The reply naming a new session to its creator; `shm_doorbell` is the server's doorbell, or
/// empty: then neither the session's shared-memory secret nor the server's pid is told.
pub(super) fn created(
    id: SessionId,
    spec: &SessionSpec,
    shm_doorbell: &str,
) -> pb::CreateSessionResponse {
    let offered = !shm_doorbell.is_empty();
    pb::CreateSessionResponse {
        session_id: id.to_string(),
        spec: Some(spec_to(spec)),
        shm_doorbell: shm_doorbell.to_owned(),
        shm_secret: if offered {
            spec.shm_secret.expose().to_vec()
        } else {
            Vec::new()
        },
        shm_server_pid: if offered { std::process::id() } else { 0 },
    }
}

/// Every field but the shared-memory secret, of which only the length shows (prost's derived
/// `Debug` is skipped for this message in `build.rs`).
impl std::fmt::Debug for pb::CreateSessionResponse {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CreateSessionResponse")
            .field("session_id", &self.session_id)
            .field("spec", &self.spec)
            .field("shm_doorbell", &self.shm_doorbell)
            .field(
                "shm_secret",
                &format_args!("<{} bytes redacted>", self.shm_secret.len()),
            )
            .field("shm_server_pid", &self.shm_server_pid)
            .finish()
    }
}

/// A session's [`Batch`] as the protocol's: every array moved, none copied (public for the
/// `batch` bench, which measures a Step's reply).
pub fn batch_to(b: Batch) -> pb::Batch {
    pb::Batch {
        num_envs: b.num_envs,
        observations: b.observations,
        rewards: b.rewards,
        terminated: b.terminated,
        truncated: b.truncated,
        scores: b.scores,
        lost: b.lost,
        ticks: b.ticks,
        action_masks: b.action_masks,
        expert_actions: b.expert_actions,
        reset: b.reset,
        seeds: b.seeds,
        final_observations: b.final_observations,
        final_scores: b.final_scores,
        final_lost: b.final_lost,
        final_ticks: b.final_ticks,
        final_action_masks: b.final_action_masks,
        final_expert_actions: b.final_expert_actions,
        stream_episodes: b.stream_episodes,
        // The service's to say (it knows whether the server drains).
        drain_remaining_ms: 0,
    }
}

pub(super) fn episode_to(r: Recording) -> pb::Episode {
    pb::Episode {
        seed: r.seed,
        steps: r.steps,
        observations: r.observations,
        actions: r.actions,
        rewards: r.rewards,
        expert_actions: r.expert_actions,
        action_masks: r.action_masks,
        score: r.score,
        lost: r.lost,
        terminated: r.terminated,
        truncated: r.truncated,
    }
}
