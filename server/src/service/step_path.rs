//! One path for a Step (or Reset) once its session is looked up, whichever transport asked:
//! the lookup's refusal, the choice of where the work runs (here, or under a permit of the
//! bounded [`CpuPool`], in the turn of the tenant the session is charged to, when the session's
//! expert actions come from the planner, whose decisions cost too much to run unbounded), the
//! step, and every refusal counted in the error counter and logged at debug level as the gRPC
//! handlers do.
//!
//! The lookup stays with the caller, because the transports ask different questions: the gRPC
//! handlers find a session by its ID for the caller, the shared-memory data plane by its ID and
//! its secret ([`crate::session::Store::find_shm`]).
//!
//! - [`StepPath::run`]: for an async handler; the planner's job goes to a blocking thread.
//! - [`StepPath::run_blocking`]: for a thread of its own (a shared-memory session's): it waits
//!   for a permit of the same pool and runs the job itself while it holds it.

use std::sync::Arc;

use tonic::Status;

use crate::metrics::Metrics;
use crate::pools::{CpuPool, Turn};
use crate::session::{Batch, ExpertActions, FoundSession, SessionError};

/// Where Steps run and where their refusals are counted. Cloning is shallow.
#[derive(Debug, Clone)]
pub struct StepPath {
    /// Where the planner's Steps and Resets run, at most its workers at once.
    cpu: CpuPool,
    /// Counts refusals by gRPC code.
    metrics: Arc<Metrics>,
}

impl StepPath {
    /// Steps on `cpu`, refusals counted in `metrics`.
    pub fn new(cpu: CpuPool, metrics: Arc<Metrics>) -> StepPath {
        StepPath { cpu, metrics }
    }

    /// Whether the session's work needs the pool: the planner fills its expert actions.
    pub fn heavy(session: &FoundSession) -> bool {
        session.expert_actions() == ExpertActions::Planner
    }

    /// Runs `job` (the found session's Step or Reset, or its Render, Snapshot or Fork, which
    /// wait for its lock) here, or on the pool's blocking threads for a planner session, whose
    /// Step may hold that lock for long: after the session's calls before it, waited for
    /// without a worker ([`FoundSession::queue`]). A refusal (the lookup's or the job's) is
    /// counted and returned as its status.
    pub async fn run<F, R>(
        &self,
        found: Result<FoundSession, SessionError>,
        job: F,
    ) -> Result<R, Status>
    where
        F: FnOnce(&FoundSession) -> Result<R, SessionError> + Send + 'static,
        R: Send + 'static,
    {
        let session = found.map_err(|e| self.fail(e))?;
        let result = if Self::heavy(&session) {
            let queued = session.queue().await;
            self.cpu
                .run(Turn::of(session.tenant()), move || {
                    let result = job(&session);
                    drop(queued);
                    result
                })
                .await
                .unwrap_or_else(|e| Err(SessionError::Internal(e.to_string())))
        } else {
            job(&session)
        };
        result.map_err(|e| self.fail(e))
    }

    /// As [`StepPath::run`], from a thread outside the runtime that may block: a planner
    /// session's job waits for a permit of the same pool (driven by `runtime`) and runs here
    /// while this thread holds it (a large Step gives it back to sleep, as on the pool).
    pub fn run_blocking<F>(
        &self,
        runtime: &tokio::runtime::Handle,
        found: Result<FoundSession, SessionError>,
        job: F,
    ) -> Result<Batch, Status>
    where
        F: FnOnce(&FoundSession) -> Result<Batch, SessionError>,
    {
        let session = found.map_err(|e| self.fail(e))?;
        let result = if Self::heavy(&session) {
            let queued = runtime.block_on(session.queue());
            match self
                .cpu
                .acquire_blocking(Turn::of(session.tenant()), runtime)
            {
                Ok(permit) => {
                    let result = permit.hold_while(|| job(&session));
                    drop(queued);
                    result
                }
                Err(e) => Err(SessionError::Internal(e.to_string())),
            }
        } else {
            job(&session)
        };
        result.map_err(|e| self.fail(e))
    }

    /// The status for `e`, counted and logged as the gRPC handlers do.
    pub fn fail(&self, e: impl Into<Status>) -> Status {
        let status = e.into();
        self.metrics.count_error(status.code());
        tracing::debug!(code = ?status.code(), message = status.message(), "request refused");
        status
    }
}
