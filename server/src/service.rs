//! The tonic glue of `dinerdash.v1.DinerDash`: decode a request, call the session store (or the
//! rollout recorder), encode the reply. This is the only module where errors become
//! `tonic::Status`, each [`SessionError`] mapped once in [`status`]; it also holds the bearer
//! token interceptor. StepStream steps each request exactly as the unary Step does
//! ([`StepReplies`]).

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Response, Status, Streaming};
use tonic_types::{ErrorDetails, StatusExt};

use crate::budget::{BudgetError, Share, Tenant};
use crate::connections::conn_info;
use crate::cpu::CpuPool;
use crate::expert::PolicyKind;
use crate::metrics::Metrics;
use crate::pb;
use crate::rollout::{
    self, MAX_BYTES_PER_STEP, MAX_ROLLOUT_EPISODES, MAX_ROLLOUT_STEPS, Recording,
};
use crate::session::{
    Autoreset, Batch, ExpertActions, ResetArgs, SessionError, SessionId, SessionOptions,
    SessionSpec, Store,
};
use crate::shutdown::{STREAM_DRAIN_DEADLINE, Shutdown};
use crate::sim::{self, Config, NUM_ACTIONS, OBSERVATION_SIZE, SNAPSHOT_VERSION};

/// Largest message the server reads or writes. The biggest legitimate ones are a Restore of a
/// 1024-environment session (~3.5 MB) and a Rollout episode of 100,000 steps with action masks
/// (~10 MB); anything larger is refused by this limit before it is buffered.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;
/// Rollout episodes recorded ahead of the reader: one, so that a stream is produced on demand.
const ROLLOUT_BUFFER: usize = 1;
/// Episodes a Rollout stream may hold at once, for the memory budget: the one buffered, one in
/// the transport's send buffer, and the one being recorded.
const ROLLOUT_EPISODES_HELD: u64 = ROLLOUT_BUFFER as u64 + 2;
/// A Rollout stream whose reader takes no episode for this long is cancelled.
pub const ROLLOUT_UNREAD_TIMEOUT: Duration = Duration::from_secs(60);

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

/// The field an INVALID_ARGUMENT message is about: by the convention of every such message in
/// this server, its leading path (`actions[3]`, `arrivals[0].groups[2].size`, `snapshot`,
/// `lives`), up to the first character that cannot be part of one.
fn offending_field(message: &str) -> &str {
    let end = message
        .find(|c: char| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '[' | ']')))
        .unwrap_or(message.len());
    &message[..end]
}

/// The game configuration of a request: absent fields (or an absent message) keep `v0`.
fn config_from(config: Option<&pb::GameConfig>) -> Config {
    let d = Config::default();
    let Some(c) = config else {
        return d;
    };
    Config {
        arrival_interval: c.arrival_interval.unwrap_or(d.arrival_interval),
        patience: [
            c.patience_type1.unwrap_or(d.patience[0]),
            c.patience_type2.unwrap_or(d.patience[1]),
        ],
        decay: [
            c.decay_type1.unwrap_or(d.decay[0]),
            c.decay_type2.unwrap_or(d.decay[1]),
        ],
        reading_ticks: c.reading_ticks.unwrap_or(d.reading_ticks),
        cooking_ticks: c.cooking_ticks.unwrap_or(d.cooking_ticks),
        eating_ticks: c.eating_ticks.unwrap_or(d.eating_ticks),
        lives: c.lives.unwrap_or(d.lives),
        time_limit: c.time_limit.unwrap_or(d.time_limit),
    }
}

/// A configuration with every field present.
fn config_to(c: &Config) -> pb::GameConfig {
    pb::GameConfig {
        arrival_interval: Some(c.arrival_interval),
        patience_type1: Some(c.patience[0]),
        patience_type2: Some(c.patience[1]),
        decay_type1: Some(c.decay[0]),
        decay_type2: Some(c.decay[1]),
        reading_ticks: Some(c.reading_ticks),
        cooking_ticks: Some(c.cooking_ticks),
        eating_ticks: Some(c.eating_ticks),
        lives: Some(c.lives),
        time_limit: Some(c.time_limit),
    }
}

fn autoreset_to(mode: Autoreset) -> pb::AutoresetMode {
    match mode {
        Autoreset::NextStep => pb::AutoresetMode::NextStep,
        Autoreset::SameStep => pb::AutoresetMode::SameStep,
        Autoreset::Disabled => pb::AutoresetMode::Disabled,
    }
}

/// The wire's mode; UNSPECIFIED is DISABLED for one environment (a Gymnasium `Env`), else NEXT_STEP.
fn autoreset_from(value: i32, num_envs: u32) -> Result<Autoreset, SessionError> {
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
fn expert_actions_from(enabled: bool, policy: i32) -> Result<ExpertActions, SessionError> {
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
        config: Some(config_to(&spec.config)),
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

fn created(id: SessionId, spec: &SessionSpec) -> pb::CreateSessionResponse {
    pb::CreateSessionResponse {
        session_id: id.to_string(),
        spec: Some(spec_to(spec)),
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
    }
}

fn episode_to(r: Recording) -> pb::Episode {
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

/// The `DinerDash` service. Cloning is shallow.
#[derive(Debug, Clone)]
pub struct DinerDashService {
    /// The sessions.
    store: Store,
    /// Counts failed RPCs by code.
    metrics: Arc<Metrics>,
    /// Where Rollout episodes are recorded, and Reset and Step of sessions whose expert actions
    /// come from the planner: off the async workers and leaving them a core, so that neither can
    /// starve the Step path of every other client.
    cpu: CpuPool,
    /// The tenant of requests that came neither with a tenant token nor on a connection this
    /// server accepted (an embedding that serves its own listener).
    unknown: Arc<Tenant>,
    /// Fires when the server starts draining: Rollout streams then get a short deadline.
    stopping: Shutdown,
    /// Where the HTTP endpoint (the sessions and watch pages) listens, told by ServerInfo.
    http_addr: Option<std::net::SocketAddr>,
}

impl DinerDashService {
    /// A service over `store`; connections of no known tenant get `share`.
    pub fn new(
        store: Store,
        metrics: Arc<Metrics>,
        share: Share,
        stopping: Shutdown,
    ) -> DinerDashService {
        DinerDashService {
            store,
            metrics,
            cpu: CpuPool::beside_steps(),
            unknown: Arc::new(Tenant::new("an unknown connection".into(), share)),
            stopping,
            http_addr: None,
        }
    }

    /// The same service, telling clients in ServerInfo that its pages are served at `addr`.
    pub fn with_http_addr(self, addr: Option<std::net::SocketAddr>) -> DinerDashService {
        DinerDashService {
            http_addr: addr,
            ..self
        }
    }

    /// Runs `job` (a Reset or Step of session `id`) here, or on the CPU pool when the session's
    /// expert actions come from the planner: its decisions cost too much for an async worker.
    async fn heavy_if_planner<F>(&self, id: &str, job: F) -> Result<Batch, Status>
    where
        F: FnOnce() -> Result<Batch, SessionError> + Send + 'static,
    {
        let expert = self.store.expert_actions(id).map_err(|e| self.fail(e))?;
        let result = if expert == ExpertActions::Planner {
            self.cpu
                .run(job)
                .await
                .unwrap_or_else(|e| Err(SessionError::Internal(e.to_string())))
        } else {
            job()
        };
        result.map_err(|e| self.fail(e))
    }

    /// One Step, as the unary call and each message of a StepStream do it.
    async fn step_one(&self, r: pb::StepRequest) -> Result<pb::Batch, Status> {
        let store = self.store.clone();
        let id = r.session_id;
        let actions = r.actions;
        let batch = self
            .heavy_if_planner(&id.clone(), move || store.step(&id, &actions))
            .await?;
        Ok(batch_to(batch))
    }

    /// Whose share a request counts against: its token's tenant, else its connection.
    fn tenant<T>(&self, request: &Request<T>) -> Arc<Tenant> {
        if let Some(tenant) = request.extensions().get::<Arc<Tenant>>() {
            return Arc::clone(tenant);
        }
        conn_info(request).map_or_else(|| Arc::clone(&self.unknown), |c| Arc::clone(&c.tenant))
    }

    /// The status for `e`, counted.
    fn fail(&self, e: SessionError) -> Status {
        let status = status(e);
        self.metrics.count_error(status.code() as usize);
        tracing::debug!(code = ?status.code(), message = status.message(), "request refused");
        status
    }
}

#[tonic::async_trait]
impl pb::diner_dash_server::DinerDash for DinerDashService {
    #[tracing::instrument(skip_all, fields(num_envs = request.get_ref().num_envs))]
    async fn create_session(
        &self,
        request: Request<pb::CreateSessionRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        let tenant = self.tenant(&request);
        let r = request.into_inner();
        let options = SessionOptions {
            autoreset: autoreset_from(r.autoreset_mode, r.num_envs).map_err(|e| self.fail(e))?,
            action_masks: r.action_masks,
            expert_actions: expert_actions_from(r.expert_actions, r.expert_policy)
                .map_err(|e| self.fail(e))?,
        };
        let config = config_from(r.config.as_ref());
        let (id, spec) = self
            .store
            .create(&tenant, r.num_envs, config, options, r.seed)
            .map_err(|e| self.fail(e))?;
        tracing::info!(session = %id, "session created");
        Ok(Response::new(created(id, &spec)))
    }

    #[tracing::instrument(skip_all, fields(session = %request.get_ref().session_id))]
    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        self.store
            .close(&request.get_ref().session_id)
            .map_err(|e| self.fail(e))?;
        tracing::info!("session closed");
        Ok(Response::new(pb::CloseSessionResponse {}))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn reset(
        &self,
        request: Request<pb::ResetRequest>,
    ) -> Result<Response<pb::Batch>, Status> {
        let r = request.into_inner();
        let args = ResetArgs {
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
            reset_mask: flags("reset_mask", &r.reset_mask).map_err(|e| self.fail(e))?,
        };
        let store = self.store.clone();
        let id = r.session_id;
        let batch = self
            .heavy_if_planner(&id.clone(), move || store.reset(&id, &args))
            .await?;
        Ok(Response::new(batch_to(batch)))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn step(&self, request: Request<pb::StepRequest>) -> Result<Response<pb::Batch>, Status> {
        self.step_one(request.into_inner()).await.map(Response::new)
    }

    type StepStreamStream = StepReplies;

    #[tracing::instrument(level = "debug", skip_all)]
    async fn step_stream(
        &self,
        request: Request<Streaming<pb::StepRequest>>,
    ) -> Result<Response<StepReplies>, Status> {
        let inbound = Inbound {
            service: self.clone(),
            requests: request.into_inner(),
            stopping: self.stopping.clone(),
        };
        Ok(Response::new(StepReplies {
            next: Some(Box::pin(inbound.next())),
            handed: false,
        }))
    }

    #[tracing::instrument(skip_all, fields(session = %request.get_ref().session_id))]
    async fn fork(
        &self,
        request: Request<pb::ForkRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        let (id, spec) = self
            .store
            .fork(&self.tenant(&request), &request.get_ref().session_id)
            .map_err(|e| self.fail(e))?;
        tracing::info!(fork = %id, "session forked");
        Ok(Response::new(created(id, &spec)))
    }

    #[tracing::instrument(skip_all, fields(session = %request.get_ref().session_id))]
    async fn snapshot(
        &self,
        request: Request<pb::SnapshotRequest>,
    ) -> Result<Response<pb::SnapshotResponse>, Status> {
        let snapshot = self
            .store
            .snapshot(&request.get_ref().session_id)
            .map_err(|e| self.fail(e))?;
        Ok(Response::new(pb::SnapshotResponse { snapshot }))
    }

    #[tracing::instrument(skip_all)]
    async fn restore(
        &self,
        request: Request<pb::RestoreRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        let (id, spec) = self
            .store
            .restore(&self.tenant(&request), &request.get_ref().snapshot)
            .map_err(|e| self.fail(e))?;
        tracing::info!(session = %id, "session restored");
        Ok(Response::new(created(id, &spec)))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn render(
        &self,
        request: Request<pb::RenderRequest>,
    ) -> Result<Response<pb::RenderResponse>, Status> {
        let r = request.get_ref();
        let text = self
            .store
            .render(&r.session_id, r.env_index, r.color)
            .map_err(|e| self.fail(e))?;
        Ok(Response::new(pb::RenderResponse { text }))
    }

    type RolloutStream = ReceiverStream<Result<pb::Episode, Status>>;

    #[tracing::instrument(skip_all, fields(episodes = request.get_ref().seeds.len()))]
    async fn rollout(
        &self,
        request: Request<pb::RolloutRequest>,
    ) -> Result<Response<Self::RolloutStream>, Status> {
        let tenant = self.tenant(&request);
        let r = request.into_inner();
        let invalid = |msg: String| self.fail(SessionError::InvalidArgument(msg));
        let policy = match pb::Policy::try_from(r.policy) {
            Ok(pb::Policy::Expert) => PolicyKind::Expert,
            Ok(pb::Policy::Random) => PolicyKind::Random,
            Ok(pb::Policy::Planner) => PolicyKind::Planner,
            _ => {
                return Err(invalid(format!(
                    "policy must be POLICY_EXPERT (1), POLICY_RANDOM (2) or POLICY_PLANNER (3), got {}",
                    r.policy
                )));
            }
        };
        if r.seeds.is_empty() || r.seeds.len() > MAX_ROLLOUT_EPISODES as usize {
            return Err(invalid(format!(
                "seeds must hold 1..={MAX_ROLLOUT_EPISODES} seeds, got {}",
                r.seeds.len()
            )));
        }
        let max_steps = r.max_steps.unwrap_or(MAX_ROLLOUT_STEPS);
        if !(1..=MAX_ROLLOUT_STEPS).contains(&max_steps) {
            return Err(invalid(format!(
                "max_steps must be in 1..={MAX_ROLLOUT_STEPS}, got {max_steps}"
            )));
        }
        let config = config_from(r.config.as_ref());
        config.validate().map_err(|e| invalid(e.to_string()))?;
        let episode_bytes = (u64::from(max_steps) + 1) * MAX_BYTES_PER_STEP;
        let charge = self
            .store
            .budget()
            .charge_rollout(&tenant, ROLLOUT_EPISODES_HELD * episode_bytes)
            .map_err(|e| self.fail(e.into()))?;

        let (tx, rx) = tokio::sync::mpsc::channel(ROLLOUT_BUFFER);
        let produce = Produce {
            cpu: self.cpu.clone(),
            metrics: Arc::clone(&self.metrics),
            stopping: self.stopping.clone(),
            policy,
            config,
            max_steps,
            masks: r.action_masks,
            work_cap: self.store.limits().max_rollout_work_steps,
        };
        tokio::spawn(async move {
            produce.run(r.seeds, tx).await;
            // The producer is done: what it charged is given back (an episode still waiting in
            // the channel for its reader is within the transport's share of the estimate).
            drop(charge);
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn server_info(
        &self,
        _request: Request<pb::ServerInfoRequest>,
    ) -> Result<Response<pb::ServerInfoResponse>, Status> {
        let limits = self.store.limits();
        Ok(Response::new(pb::ServerInfoResponse {
            server_version: crate::SERVER_VERSION.into(),
            ruleset: sim::RULESET.into(),
            max_sessions: u32::try_from(limits.max_sessions).unwrap_or(u32::MAX),
            max_envs_per_session: u32::try_from(limits.max_envs_per_session).unwrap_or(u32::MAX),
            session_ttl_seconds: limits.session_ttl.as_secs(),
            live_sessions: self.store.live() as u64,
            max_rollout_episodes: MAX_ROLLOUT_EPISODES,
            max_memory_bytes: self.store.budget().max_bytes(),
            memory_used_bytes: self.store.budget().used_bytes(),
            max_rollout_work_steps: limits.max_rollout_work_steps,
            max_message_bytes: MAX_MESSAGE_BYTES as u64,
            snapshot_version: u32::from(SNAPSHOT_VERSION),
            http_port: self.http_addr.map_or(0, |a| u32::from(a.port())),
            http_host: self
                .http_addr
                .map_or_else(String::new, |a| a.ip().to_string()),
        }))
    }
}

/// The reply of one StepStream request and the stream's state for the next; `None`: the client
/// closed its side.
type NextReply = Option<(Result<pb::Batch, Status>, Inbound)>;

/// The replies of one StepStream, computed one at a time as the transport asks for them: the
/// next request is read only once the previous reply has been handed on (see
/// [`StepReplies::poll_next`]), so a client that does not read its replies holds at most one
/// reply beyond HTTP/2 flow control, and stops the server reading its requests.
pub struct StepReplies {
    /// Reads the next request and steps it; `None` once the stream has ended.
    next: Option<Pin<Box<dyn Future<Output = NextReply> + Send>>>,
    /// A reply was just yielded and not yet handed to the transport.
    handed: bool,
}

/// What a StepStream reads from.
struct Inbound {
    /// Steps each request as the unary Step does.
    service: DinerDashService,
    /// The client's requests.
    requests: Streaming<pb::StepRequest>,
    /// Fires when the server drains.
    stopping: Shutdown,
}

impl Inbound {
    /// Waits for the next request (or the server's shutdown) and steps it.
    async fn next(mut self) -> NextReply {
        let message = tokio::select! {
            // A draining server answers UNAVAILABLE, as it does new unary calls; a stream waiting
            // for a request ends at once rather than holding the drain until its deadline.
            biased;
            () = self.stopping.wait() => return Some((Err(shutting_down()), self)),
            message = self.requests.message() => message,
        };
        match message {
            Ok(Some(request)) => {
                let reply = self.service.step_one(request).await;
                Some((reply, self))
            }
            Ok(None) => None,
            // Undecodable or oversized (the codec's and transport's statuses, as for Step), or
            // the client reset the stream.
            Err(status) => Some((Err(status), self)),
        }
    }
}

impl tokio_stream::Stream for StepReplies {
    type Item = Result<pb::Batch, Status>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        // tonic's encoder polls again right after a reply, to pack more into one frame: answer
        // Pending once (waking ourselves), so that the reply goes to the transport before the
        // next request is read. Without this, a client pipelining requests without reading
        // would have up to the encoder's 32 KiB of replies computed ahead of flow control.
        if std::mem::take(&mut self.handed) {
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        let Some(next) = self.next.as_mut() else {
            return Poll::Ready(None);
        };
        match next.as_mut().poll(cx) {
            Poll::Pending => Poll::Pending,
            Poll::Ready(None) => {
                self.next = None;
                Poll::Ready(None)
            }
            Poll::Ready(Some((reply, inbound))) => {
                // An error ends the stream, as it ends a unary call.
                self.next = match reply {
                    Ok(_) => Some(Box::pin(inbound.next())),
                    Err(_) => None,
                };
                self.handed = true;
                Poll::Ready(Some(reply))
            }
        }
    }
}

/// What one Rollout stream records, and where.
struct Produce {
    /// The bounded pool episodes are recorded on.
    cpu: CpuPool,
    /// Counts recorded episodes.
    metrics: Arc<Metrics>,
    /// Fires when the server drains.
    stopping: Shutdown,
    /// Who plays.
    policy: PolicyKind,
    /// The game.
    config: Config,
    /// Per episode.
    max_steps: u32,
    /// Whether episodes carry action masks.
    masks: bool,
    /// Most steps over all the stream's episodes.
    work_cap: u64,
}

/// How a stream's next episode ended up.
enum Next {
    /// Recorded; send it.
    Episode(Recording),
    /// The reader left or never read: stop quietly.
    Gone,
    /// End the stream with this status.
    Fail(Status),
}

impl Produce {
    /// Records one episode per seed, each only once the reader has room for it: a stream that is
    /// not read holds no worker, and is cancelled after [`ROLLOUT_UNREAD_TIMEOUT`]. A reader that
    /// leaves stops the episode being recorded within a step; one still queued never starts.
    async fn run(
        self,
        seeds: Vec<u64>,
        tx: tokio::sync::mpsc::Sender<Result<pb::Episode, Status>>,
    ) {
        let mut stopping = self.stopping.clone();
        let drained = async move {
            stopping.wait().await;
            tokio::time::sleep(STREAM_DRAIN_DEADLINE).await;
        };
        tokio::pin!(drained);
        let cap = self.work_cap;
        let mut work_left = cap;
        for (done, seed) in seeds.into_iter().enumerate() {
            let slot = tokio::select! {
                slot = tokio::time::timeout(ROLLOUT_UNREAD_TIMEOUT, tx.reserve()) => slot,
                () = &mut drained => {
                    let _ = tx.try_send(Err(shutting_down()));
                    return;
                }
            };
            let slot = match slot {
                Ok(Ok(slot)) => slot,
                Ok(Err(_)) => return,
                Err(_) => {
                    tracing::info!(
                        "Rollout stream unread for {} s: cancelled",
                        ROLLOUT_UNREAD_TIMEOUT.as_secs()
                    );
                    return;
                }
            };
            if work_left == 0 {
                slot.send(Err(Status::resource_exhausted(format!(
                    "this Rollout reached its work cap of {cap} steps after \
                     {done} episodes; ask for fewer seeds or a smaller max_steps"
                ))));
                return;
            }
            let steps = self
                .max_steps
                .min(u32::try_from(work_left).unwrap_or(u32::MAX));
            let next = tokio::select! {
                next = self.record(seed, steps) => next,
                () = tx.closed() => Next::Gone,
                () = &mut drained => Next::Fail(shutting_down()),
            };
            match next {
                Next::Episode(rec)
                    if rec.truncated
                        && !rec.terminated
                        && rec.steps < self.max_steps
                        && u64::from(rec.steps) == work_left =>
                {
                    // Cut short by the work cap, not by the game: not a real episode.
                    slot.send(Err(Status::resource_exhausted(format!(
                        "this Rollout reached its work cap of {cap} steps \
                         after {done} episodes; ask for fewer seeds or a smaller max_steps"
                    ))));
                    return;
                }
                Next::Episode(rec) => {
                    work_left -= u64::from(rec.steps);
                    self.metrics
                        .rollout_episodes
                        .fetch_add(1, Ordering::Relaxed);
                    slot.send(Ok(episode_to(rec)));
                }
                Next::Gone => return,
                Next::Fail(status) => {
                    slot.send(Err(status));
                    return;
                }
            }
        }
    }

    /// Records one episode on the pool. Dropping the returned future (the reader left, the
    /// server drains) stops the recording at its next step.
    async fn record(&self, seed: u64, max_steps: u32) -> Next {
        let stop = Arc::new(AtomicBool::new(false));
        // Set on every way out of this function, the early ones included.
        let _stop_on_drop = StopOnDrop(Arc::clone(&stop));
        let Ok(worker) = self.cpu.acquire().await else {
            return Next::Fail(shutting_down());
        };
        let (policy, config, masks) = (self.policy, self.config, self.masks);
        let job = CpuPool::run_with(worker, move || {
            rollout::record_until(policy, config, seed, max_steps, masks, &stop)
        });
        match job.await {
            Ok(Ok(Some(rec))) => Next::Episode(rec),
            Ok(Ok(None)) => Next::Gone,
            Ok(Err(e)) => Next::Fail(status(SessionError::InvalidArgument(e.to_string()))),
            Err(e) => {
                tracing::error!("rollout worker failed: {e}");
                Next::Fail(Status::internal(format!("rollout worker failed: {e}")))
            }
        }
    }
}

/// Sets its flag when dropped.
struct StopOnDrop(Arc<AtomicBool>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// The answer to calls that arrive, or streams still running, once the server drains.
fn shutting_down() -> Status {
    Status::unavailable("the server is shutting down; retry on another server")
}

/// A token clients may send, and the tenant it stands for.
#[derive(Debug, Clone)]
pub struct Token {
    /// The secret, sent as `authorization: Bearer <token>`.
    pub token: String,
    /// Whose share its requests count against; `None`: each connection's own (`--auth-token`).
    pub tenant: Option<Arc<Tenant>>,
}

/// An accepted `authorization` value (`Bearer <token>`) and the tenant it stands for.
type Accepted = (Box<[u8]>, Option<Arc<Tenant>>);

/// Stands in front of every RPC but health checks: answers `UNAVAILABLE` once the server drains,
/// `RESOURCE_EXHAUSTED` on a connection over the connection limit, and, when the server has
/// tokens, checks `authorization: Bearer <token>` and tags the request with the token's tenant.
#[derive(Debug, Clone)]
pub struct AuthInterceptor {
    /// Accepted `Bearer <token>` values and their tenants; empty lets every request in.
    tokens: Arc<[Accepted]>,
    /// Fires when the server drains.
    stopping: Shutdown,
}

impl AuthInterceptor {
    /// An interceptor accepting `tokens` (none: an open server).
    pub fn new(tokens: &[Token], stopping: Shutdown) -> AuthInterceptor {
        let tokens = tokens
            .iter()
            .map(|t| {
                let expected = format!("Bearer {}", t.token)
                    .into_bytes()
                    .into_boxed_slice();
                (expected, t.tenant.clone())
            })
            .collect();
        AuthInterceptor { tokens, stopping }
    }
}

/// Compares without returning early, so that the time taken does not reveal the token.
pub(crate) fn same_bytes(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl tonic::service::Interceptor for AuthInterceptor {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if self.stopping.is_stopping() {
            return Err(shutting_down());
        }
        if let Some(max) = conn_info(&request).and_then(|c| c.over_limit) {
            return Err(Status::resource_exhausted(format!(
                "the server serves its maximum of {max} connections; retry later or raise \
                 --max-connections"
            )));
        }
        if self.tokens.is_empty() {
            return Ok(request);
        }
        let Some(value) = request.metadata().get("authorization") else {
            return Err(Status::unauthenticated(
                "missing authorization metadata: send `authorization: Bearer <token>`",
            ));
        };
        // Every token is compared, so that the time taken does not reveal which one matched.
        let mut found = None;
        for (expected, tenant) in self.tokens.iter() {
            if same_bytes(value.as_bytes(), expected) {
                found = Some(tenant.clone());
            }
        }
        match found {
            None => Err(Status::unauthenticated("invalid auth token")),
            Some(tenant) => {
                if let Some(tenant) = tenant {
                    request.extensions_mut().insert(tenant);
                }
                Ok(request)
            }
        }
    }
}
