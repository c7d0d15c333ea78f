//! The producer of one Rollout stream: records an episode per seed on the CPU pool, in chunks
//! taken in its tenant's turn, each episode only once the reader has room for it, within the
//! request's work cap and the drain deadline.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use tonic::Status;

use super::convert::episode_to;
use super::status::rollout_status;
use crate::metrics::Metrics;
use crate::pb;
use crate::policy::PolicyKind;
use crate::pools::{CpuPool, Turn};
use crate::rollout::{Played, ROLLOUT_CHUNK, Recorder, Recording, RolloutError};
use crate::shutdown::{self, STREAM_DRAIN_DEADLINE, Shutdown};
use crate::sim::Config;

/// A Rollout stream whose reader takes no episode for this long is cancelled.
pub const ROLLOUT_UNREAD_TIMEOUT: Duration = Duration::from_secs(60);

/// What one Rollout stream records, and where.
pub(super) struct Produce {
    /// The bounded pool episodes are recorded on.
    pub(super) cpu: CpuPool,
    /// Whose turn on the pool: the tenant the stream is charged to.
    pub(super) turn: Turn,
    /// Counts recorded episodes.
    pub(super) metrics: Arc<Metrics>,
    /// Fires when the server drains.
    pub(super) stopping: Shutdown,
    /// Who plays.
    pub(super) policy: PolicyKind,
    /// The game.
    pub(super) config: Config,
    /// Per episode.
    pub(super) max_steps: u32,
    /// Whether episodes carry action masks.
    pub(super) masks: bool,
    /// Most steps over all the stream's episodes.
    pub(super) work_cap: u64,
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
    pub(super) async fn run(
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
                    let _ = tx.try_send(Err(shutdown::unavailable()));
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
                () = &mut drained => Next::Fail(shutdown::unavailable()),
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
                    self.metrics.rollout_episodes.inc();
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

    /// Records one episode on the pool, a chunk of [`ROLLOUT_CHUNK`] at a time, each in the
    /// stream's tenant's turn: between chunks the worker serves whoever's turn is next. Dropping
    /// the returned future (the reader left, the server drains) stops the recording at its next
    /// step.
    async fn record(&self, seed: u64, max_steps: u32) -> Next {
        let stop = Arc::new(AtomicBool::new(false));
        // Set on every way out of this function, the early ones included.
        let _stop_on_drop = StopOnDrop(Arc::clone(&stop));
        let recorder = Recorder::new(self.policy, self.config, seed, max_steps, self.masks);
        let mut recorder = match recorder {
            Ok(recorder) => recorder,
            Err(e) => {
                return Next::Fail(rollout_status(RolloutError::InvalidArgument(e.to_string())));
            }
        };
        loop {
            let Ok(worker) = self.cpu.acquire(self.turn).await else {
                return Next::Fail(shutdown::unavailable());
            };
            let stop = Arc::clone(&stop);
            let chunk = CpuPool::run_with(worker, move || {
                let played = recorder.play(Some(Instant::now() + ROLLOUT_CHUNK), &stop);
                (recorder, played)
            });
            match chunk.await {
                Ok((done, Played::Ended)) => return Next::Episode(done.finish()),
                Ok((paused, Played::Paused)) => recorder = paused,
                Ok((_, Played::Stopped)) => return Next::Gone,
                Err(e) => {
                    tracing::error!("rollout worker failed: {e}");
                    return Next::Fail(Status::internal(format!("rollout worker failed: {e}")));
                }
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
