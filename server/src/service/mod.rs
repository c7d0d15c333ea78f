//! The tonic glue of `dinerdash.v1.DinerDash`: decode a request, call the session store (or the
//! rollout recorder), encode the reply.
//!
//! - [`status`](mod@status): the only place errors become `tonic::Status`, each
//!   [`SessionError`] mapped once.
//! - [`convert`]: the protocol's messages to the store's types and back.
//! - [`step_stream`]: StepStream's replies, each request stepped exactly as the unary Step does.
//! - [`step_path`]: the one path of a found session's work, whichever transport asked: on the CPU
//!   pool for the planner, refusals counted. The handlers and the shared-memory data plane both
//!   take it.
//! - [`rollout_stream`]: the producer of a Rollout stream's episodes.
//!
//! Requests reach these handlers through the [`crate::auth::RequestGate`], which tags a tenant
//! token's request with its tenant: that tenant is the request's identity ([`Owner`]), else the
//! shared one, and every call that names a session names it with that identity (another
//! identity's session is NOT_FOUND, as an unknown ID).
//!
//! No handler takes a session's lock on an async worker when a planner Step may hold it: Reset,
//! Step, Render, Snapshot and Fork of a session whose expert actions come from the planner all
//! run on the CPU pool ([`DinerDashService::with_session`]); other sessions' locks are held for
//! one cheap Step at most, and are taken inline.

pub mod convert;
pub mod rollout_stream;
pub mod status;
pub mod step_path;
pub mod step_stream;

use std::sync::Arc;

use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

pub use rollout_stream::ROLLOUT_UNREAD_TIMEOUT;
pub use status::{ERROR_DOMAIN, RETRY_PUSHBACK, draining, rollout_status, status};
pub use step_stream::StepReplies;

use convert::{
    autoreset_from, batch_to, config_from, created, expert_actions_from, policy_from, reset_from,
};
use rollout_stream::Produce;
use step_path::StepPath;

use crate::auth::SharedShare;
use crate::budget::{Share, Tenant};
use crate::connections::conn_info;
use crate::metrics::Metrics;
use crate::pb;
use crate::pools::{CpuPool, Turn};
use crate::rollout::{self, MAX_ROLLOUT_EPISODES, ROLLOUT_BUFFER, RolloutPlan};
use crate::session::{
    Batch, Caller, FoundSession, Owner, SessionError, SessionId, SessionOptions, Store,
    short_id as short,
};
use crate::shutdown::Shutdown;
use crate::sim::{self, SNAPSHOT_VERSION};

/// Largest message the server reads or writes. The biggest legitimate ones are a Restore of a
/// 1024-environment session (~3.5 MB) and a Rollout episode of 100,000 steps with action masks
/// (~10 MB); anything larger is refused by this limit before it is buffered.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// The `DinerDash` service. Cloning is shallow.
#[derive(Debug, Clone)]
pub struct DinerDashService {
    /// The sessions.
    store: Store,
    /// Counts failed RPCs by code.
    metrics: Arc<Metrics>,
    /// Where Rollout episodes are recorded: off the async workers and leaving them a core, so
    /// that they cannot starve the Step path of every other client.
    cpu: CpuPool,
    /// The one step path both transports take: the planner's work on the same pool, refusals
    /// counted ([`step_path`]).
    path: StepPath,
    /// The tenant of requests that came neither with a tenant token nor on a connection this
    /// server accepted (an embedding that serves its own listener).
    unknown: Arc<Tenant>,
    /// Says when the server drains (new sessions are refused, Batches carry the time left) and
    /// when it stops (Rollout streams then get a short deadline).
    stopping: Shutdown,
    /// Where the HTTP endpoint (the sessions and watch pages) listens, told by ServerInfo.
    http_addr: Option<std::net::SocketAddr>,
    /// What one Rollout request may do.
    rollout: rollout::Limits,
    /// The shared-memory doorbell told in CreateSession, Fork and Restore replies ([`crate::shm`],
    /// which comes after this module); empty when the server offers none.
    shm_doorbell: Arc<str>,
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
            path: StepPath::new(CpuPool::beside_steps(), Arc::clone(&metrics)),
            metrics,
            cpu: CpuPool::beside_steps(),
            unknown: Arc::new(Tenant::new("an unknown connection".into(), share)),
            stopping,
            http_addr: None,
            rollout: rollout::Limits::default(),
            shm_doorbell: Arc::from(""),
        }
    }

    /// The same service, letting each Rollout request do what `limits` allow.
    pub fn with_rollout_limits(self, limits: rollout::Limits) -> DinerDashService {
        DinerDashService {
            rollout: limits,
            ..self
        }
    }

    /// The same service, naming `doorbell` in the replies that create a session.
    pub fn with_shm_doorbell(self, doorbell: &str) -> DinerDashService {
        DinerDashService {
            shm_doorbell: Arc::from(doorbell),
            ..self
        }
    }

    /// The same service, telling clients in ServerInfo that its pages are served at `addr`.
    pub fn with_http_addr(self, addr: Option<std::net::SocketAddr>) -> DinerDashService {
        DinerDashService {
            http_addr: addr,
            ..self
        }
    }

    /// Looks session `id` of `owner`'s up (once) and runs `job` (its Reset, Step, Render,
    /// Snapshot or Fork) on it here, or on the CPU pool when the session's expert actions come
    /// from the planner: its decisions cost too much for an async worker, and a job waiting for
    /// that session's lock would block the worker while a planner Step holds it.
    async fn with_session<F, R>(&self, owner: &Owner, id: &str, job: F) -> Result<R, Status>
    where
        F: FnOnce(&FoundSession) -> Result<R, SessionError> + Send + 'static,
        R: Send + 'static,
    {
        self.path.run(self.store.find(owner, id), job).await
    }

    /// One Step by `owner`, as the unary call and each message of a StepStream do it.
    async fn step_one(&self, owner: &Owner, r: pb::StepRequest) -> Result<pb::Batch, Status> {
        let actions = r.actions;
        let batch = self
            .with_session(owner, &r.session_id, move |session| session.step(&actions))
            .await?;
        Ok(self.reply(batch))
    }

    /// A Step's or Reset's reply, telling the client how long a draining server has left.
    fn reply(&self, batch: Batch) -> pb::Batch {
        pb::Batch {
            drain_remaining_ms: self.stopping.drain_remaining_ms(),
            ..batch_to(batch)
        }
    }

    /// `UNAVAILABLE` (reason `DRAINING`), counted, when the server drains: it starts no new
    /// work then.
    fn admit(&self) -> Result<(), Status> {
        self.stopping.admit().map_err(|e| {
            let status = draining(e);
            self.metrics.count_error(status.code());
            status
        })
    }

    /// Who sends a request that creates a session: its token's tenant (owner and share), else
    /// the shared identity with the shared token's share (one for all its connections), or on a
    /// server without tokens its connection's.
    fn caller<T>(&self, request: &Request<T>) -> Caller {
        if let Some(tenant) = request.extensions().get::<Arc<Tenant>>() {
            return Caller::tenant(Arc::clone(tenant));
        }
        if let Some(SharedShare(share)) = request.extensions().get::<SharedShare>() {
            return Caller::shared(Arc::clone(share));
        }
        let share =
            conn_info(request).map_or_else(|| Arc::clone(&self.unknown), |c| Arc::clone(&c.tenant));
        Caller::shared(share)
    }

    /// The status for `e` (a session or Rollout refusal), counted.
    fn fail(&self, e: impl Into<Status>) -> Status {
        self.path.fail(e)
    }
}

/// The identity of a request: its token's tenant, else the shared identity.
fn owner<T>(request: &Request<T>) -> Owner {
    Owner::of(request.extensions().get::<Arc<Tenant>>())
}

#[tonic::async_trait]
impl pb::diner_dash_server::DinerDash for DinerDashService {
    #[tracing::instrument(skip_all, fields(num_envs = request.get_ref().num_envs))]
    async fn create_session(
        &self,
        request: Request<pb::CreateSessionRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        self.admit()?;
        let caller = self.caller(&request);
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
            .create(&caller, r.num_envs, config, options, r.seed)
            .map_err(|e| self.fail(e))?;
        created_log(id, &caller, "session created");
        Ok(Response::new(created(id, &spec, &self.shm_doorbell)))
    }

    #[tracing::instrument(skip_all, fields(session = short(&request.get_ref().session_id)))]
    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        let caller = self.caller(&request);
        self.store
            .close(&caller.owner, &request.get_ref().session_id)
            .map_err(|e| self.fail(e))?;
        tracing::info!(tenant = caller.tenant.name(), "session closed");
        Ok(Response::new(pb::CloseSessionResponse {}))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn reset(
        &self,
        request: Request<pb::ResetRequest>,
    ) -> Result<Response<pb::Batch>, Status> {
        let owner = owner(&request);
        let (id, args) = reset_from(request.into_inner());
        let batch = self
            .with_session(&owner, &id, move |s| s.reset(&args.args(s.num_envs())?))
            .await?;
        Ok(Response::new(self.reply(batch)))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn step(&self, request: Request<pb::StepRequest>) -> Result<Response<pb::Batch>, Status> {
        let owner = owner(&request);
        self.step_one(&owner, request.into_inner())
            .await
            .map(Response::new)
    }

    type StepStreamStream = StepReplies;

    #[tracing::instrument(level = "debug", skip_all)]
    async fn step_stream(
        &self,
        request: Request<Streaming<pb::StepRequest>>,
    ) -> Result<Response<StepReplies>, Status> {
        Ok(Response::new(StepReplies::new(
            self.clone(),
            owner(&request),
            request.into_inner(),
            self.stopping.clone(),
        )))
    }

    #[tracing::instrument(skip_all, fields(session = short(&request.get_ref().session_id)))]
    async fn fork(
        &self,
        request: Request<pb::ForkRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        self.admit()?;
        let caller = self.caller(&request);
        let store = self.store.clone();
        let forker = caller.clone();
        let (id, spec) = self
            .with_session(&caller.owner, &request.get_ref().session_id, move |found| {
                store.fork(&forker, found)
            })
            .await?;
        created_log(id, &caller, "session forked");
        Ok(Response::new(created(id, &spec, &self.shm_doorbell)))
    }

    #[tracing::instrument(skip_all, fields(session = short(&request.get_ref().session_id)))]
    async fn snapshot(
        &self,
        request: Request<pb::SnapshotRequest>,
    ) -> Result<Response<pb::SnapshotResponse>, Status> {
        let r = request.get_ref();
        let (start, count) = (r.env_start, r.env_count);
        let snapshot = self
            .with_session(&owner(&request), &r.session_id, move |found| {
                found.snapshot_range(start, count)
            })
            .await?;
        Ok(Response::new(pb::SnapshotResponse { snapshot }))
    }

    #[tracing::instrument(skip_all)]
    async fn restore(
        &self,
        request: Request<pb::RestoreRequest>,
    ) -> Result<Response<pb::CreateSessionResponse>, Status> {
        self.admit()?;
        let caller = self.caller(&request);
        let (id, spec) = self
            .store
            .restore(&caller, &request.get_ref().snapshot)
            .map_err(|e| self.fail(e))?;
        created_log(id, &caller, "session restored");
        Ok(Response::new(created(id, &spec, &self.shm_doorbell)))
    }

    #[tracing::instrument(level = "debug", skip_all, fields(session = %request.get_ref().session_id))]
    async fn render(
        &self,
        request: Request<pb::RenderRequest>,
    ) -> Result<Response<pb::RenderResponse>, Status> {
        let owner = owner(&request);
        let r = request.into_inner();
        let (env_index, color) = (r.env_index, r.color);
        let text = self
            .with_session(&owner, &r.session_id, move |found| {
                found.render(env_index, color)
            })
            .await?;
        Ok(Response::new(pb::RenderResponse { text }))
    }

    type RolloutStream = ReceiverStream<Result<pb::Episode, Status>>;

    #[tracing::instrument(skip_all, fields(episodes = request.get_ref().seeds.len()))]
    async fn rollout(
        &self,
        request: Request<pb::RolloutRequest>,
    ) -> Result<Response<Self::RolloutStream>, Status> {
        self.admit()?;
        // A Rollout names no session: it plays fresh games, charged to the caller's share.
        let tenant = self.caller(&request).tenant;
        let r = request.into_inner();
        let policy = policy_from(r.policy).map_err(|e| self.fail(e))?;
        let plan = RolloutPlan::new(
            policy,
            r.seeds,
            r.max_steps,
            config_from(r.config.as_ref()),
            r.action_masks,
        )
        .map_err(|e| self.fail(e))?;
        let charge = plan
            .charge(self.store.budget(), &tenant)
            .map_err(|e| self.fail(e))?;

        let (tx, rx) = tokio::sync::mpsc::channel(ROLLOUT_BUFFER);
        let produce = Produce {
            cpu: self.cpu.clone(),
            turn: Turn::of(&tenant),
            metrics: Arc::clone(&self.metrics),
            stopping: self.stopping.clone(),
            policy: plan.policy,
            config: plan.config,
            max_steps: plan.max_steps,
            masks: plan.action_masks,
            work_cap: self.rollout.max_work_steps,
        };
        tokio::spawn(async move {
            produce.run(plan.seeds, tx).await;
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
            max_rollout_work_steps: self.rollout.max_work_steps,
            max_message_bytes: MAX_MESSAGE_BYTES as u64,
            snapshot_version: u32::from(SNAPSHOT_VERSION),
            http_port: self.http_addr.map_or(0, |a| u32::from(a.port())),
            http_host: self
                .http_addr
                .map_or_else(String::new, |a| a.ip().to_string()),
        }))
    }
}

/// Logs a session the caller now owns: its short ID and its tenant (whose share it counts
/// against) at info level, its full ID at debug level (see [`crate::session::LOGGED_ID`]).
fn created_log(id: SessionId, caller: &Caller, what: &'static str) {
    let full = id.to_string();
    tracing::info!(
        session = short(&full),
        tenant = caller.tenant.name(),
        "{what}"
    );
    tracing::debug!(session = %full, "{what}: full ID");
}
