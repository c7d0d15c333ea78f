//! The two thread pools for CPU-heavy work, and nothing else: the bounded pool of blocking
//! workers ([`CpuPool`]) and the stepping threads of large Steps ([`StepPool`]). The module is
//! named for what it holds, the pools, rather than for the resource they spend.
//!
//! - [`CpuPool`]: Rollout episodes (in chunks of [`crate::rollout::ROLLOUT_CHUNK`]) and the
//!   Reset, Step, Render, Snapshot and Fork of planner-labelled sessions (a large Step's only
//!   until it hands its chunks to the stepping threads). Such work runs on
//!   tokio's blocking threads, never on the async workers that serve Step and Reset, and at most
//!   `workers` jobs run at once, so a flood of heavy requests queues here instead of starving
//!   every other client. Waiting jobs queue per tenant ([`Turn`]) and a freed worker goes to the
//!   tenants in turn (round robin), so one tenant's many jobs delay another's by about one job
//!   each, not by all of them. The server's pool ([`CpuPool::beside_steps`]) is one per process:
//!   the gRPC service and the shared-memory data plane's threads ([`CpuPool::acquire_blocking`])
//!   take their workers from the same queue, so planner Steps are bounded together whichever
//!   transport asked.
//! - [`StepPool`]: the threads that step one large session's environments in chunks at once
//!   ([`Stepping`] says when a Step is large enough). Only chunks of large Steps run there;
//!   small Steps stay on their caller's thread and never queue behind them. A planner Step's
//!   chunk runs under a slot, one a thread, taken in its tenant's turn from a queue like the
//!   CpuPool's, and a thread that has run a chunk gives its slot to another tenant waiting for
//!   one: another tenant's large planner Step waits about a chunk (planner chunks are small:
//!   `MAX_PLANNER_CHUNK_ENVS`), not for the Steps already there. Plain Steps' chunks
//!   (microseconds each) go first come, first served ([`StepPool::run_first_come`]).
//!
//! # Why the two pools neither deadlock nor oversubscribe
//! A planner-labelled Step runs on a [`CpuPool`] blocking thread; when it is large it hands its
//! chunks to the [`StepPool`] and that thread sleeps until they are done. Chunk work touches
//! only its own environments and Batch rows: it takes no lock, awaits nothing and never submits
//! work to either pool, so a chunk cannot wait on anything its caller holds (the caller holds
//! the session's lock; chunks run under it, on data borrowed from it). The caller waits for
//! stepping slots with that lock held, but a slot is held only by a running chunk, which ends
//! whatever else waits: the order in which tenants' chunks run cannot deadlock. The callers of
//! large Steps sleep while their chunks run, so the CPU-busy threads are at most the stepping
//! threads, plus the callers of small Steps (async workers, shared-memory threads, CpuPool
//! workers) that run their own. An async worker that hands a large Step over gives its other
//! tasks to another thread first (`block_in_place`), so small Steps keep being served.
//!
//! A CpuPool job that hands a large Step's chunks over gives its worker back before it sleeps
//! ([`CpuPermit::hold_while`]): the chunks' CPU is the stepping threads', so another tenant's
//! planner Step takes the worker meanwhile instead of waiting for the whole large Step. The job
//! then ends without a worker (what is left of its Step is the session's bookkeeping, no planner
//! decision). Giving the worker back cannot deadlock: the job waits only for its chunks. Taking
//! one again under the session's lock could: a Render of the same session may hold the freed
//! worker while it waits for that lock. So the workers bound the planner decisions made on
//! callers' threads, the stepping threads those of large Steps, and each sleeping caller holds
//! a blocking thread and its session's lock, nothing of either pool. The service's calls on a
//! planner session wait for the one before them ([`crate::session::FoundSession::queue`])
//! before they ask for a worker, so a worker does not wait for that lock either.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, PoisonError};

use tokio::sync::oneshot;

use crate::budget::Tenant;

/// Why a job did not run to completion.
#[derive(Debug, thiserror::Error)]
pub enum CpuError {
    /// The pool was dropped while the job waited (nothing drops the server's pool).
    #[error("the worker pool is closed")]
    Closed,
    /// The job panicked; the panic was caught on its blocking thread.
    #[error("a worker failed: {0}")]
    Failed(String),
}

/// A bounded pool of blocking workers that serves tenants in turn. Cloning is shallow: every
/// clone shares the same workers.
#[derive(Debug, Clone)]
pub struct CpuPool {
    /// The workers and the jobs waiting for one.
    queue: Arc<Queue>,
    /// The number of workers, for [`CpuPool::workers`].
    max: usize,
}

impl CpuPool {
    /// A pool running at most `workers` jobs at once (at least one).
    pub fn new(workers: usize) -> CpuPool {
        let max = workers.max(1);
        CpuPool {
            queue: Queue::of(max),
            max,
        }
    }

    /// The process's pool, which leaves one core to the async workers serving Step and Reset
    /// (one worker on one or two cores): Rollouts being read must not raise other clients' Step
    /// latency. Every call returns the same pool (the cores are the machine's, not a service's):
    /// the gRPC service and the shared-memory data plane share its workers.
    pub fn beside_steps() -> CpuPool {
        static POOL: OnceLock<CpuPool> = OnceLock::new();
        POOL.get_or_init(|| {
            let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
            CpuPool::new(cores.saturating_sub(1))
        })
        .clone()
    }

    /// How many jobs may run at once.
    pub fn workers(&self) -> usize {
        self.max
    }

    /// Waits for a free worker for `turn` from a thread of its own outside the runtime (a
    /// shared-memory planner session's thread), which then runs its job itself while it holds
    /// the permit: the same bound and the same turns as [`CpuPool::run`], without a hop to
    /// another thread. `runtime` drives the wait when no worker is free at once; it must not be
    /// called from an async task.
    pub fn acquire_blocking(
        &self,
        turn: Turn,
        runtime: &tokio::runtime::Handle,
    ) -> Result<CpuPermit, CpuError> {
        match self.queue.enter(turn) {
            Ok(permit) => Ok(permit),
            Err(handed) => runtime.block_on(handed).map_err(|_| CpuError::Closed),
        }
    }

    /// Waits for a worker for `turn`: at once when one is free, else when the tenants with jobs
    /// waiting before it have had theirs (each tenant's own jobs in their order of arrival).
    /// Holding the permit is what reserves the worker: pass it into [`CpuPool::run_with`].
    pub async fn acquire(&self, turn: Turn) -> Result<CpuPermit, CpuError> {
        match self.queue.enter(turn) {
            Ok(permit) => Ok(permit),
            Err(handed) => handed.await.map_err(|_| CpuError::Closed),
        }
    }

    /// Runs `job` on a blocking thread once a worker is free for `turn`, and returns its result.
    /// When the caller stops waiting (a cancelled request), a job already running finishes and
    /// releases its worker; one still queued never starts.
    pub async fn run<F, R>(&self, turn: Turn, job: F) -> Result<R, CpuError>
    where
        F: FnOnce() -> R + Send + 'static,
        R: Send + 'static,
    {
        let permit = self.acquire(turn).await?;
        CpuPool::run_with(permit, job).await
    }

    /// Runs `job` on a blocking thread under a permit already taken from [`CpuPool::acquire`];
    /// the permit is released when the job ends.
    pub async fn run_with<F, R>(permit: CpuPermit, job: F) -> Result<R, CpuError>
    where
        F: FnOnce() -> R + Send + 'static,
        R: Send + 'static,
    {
        tokio::task::spawn_blocking(move || permit.hold_while(job))
            .await
            .map_err(|e| CpuError::Failed(e.to_string()))
    }
}

/// Which tenant a job of the [`CpuPool`] or a Step's chunks on the [`StepPool`] are run for:
/// the pools serve tenants in turn, not jobs in order of arrival. Made from the tenant a
/// session or a Rollout is charged to; the default is nobody's (one tenant's, in tests).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash)]
pub struct Turn(usize);

impl Turn {
    /// The turn of `tenant` (one per tenant: its address while it lives).
    pub fn of(tenant: &Arc<Tenant>) -> Turn {
        Turn(Arc::as_ptr(tenant) as usize)
    }
}

/// A worker of the [`CpuPool`], held while its job runs; dropping it hands the worker to the
/// next tenant's first waiting job (or frees it).
#[derive(Debug)]
#[must_use = "the worker is free again as soon as its permit is dropped"]
pub struct CpuPermit {
    /// The pool it is given back to (none once handed on).
    queue: Option<Arc<Queue>>,
}

impl CpuPermit {
    /// Runs `job` on this thread under the permit, which is released when the job ends, or
    /// earlier: when the job hands a large Step's chunks to the [`StepPool`] and sleeps until
    /// they are done, it gives the worker back meanwhile (the chunks' CPU is the stepping
    /// threads'), and ends without it (see the module doc).
    pub fn hold_while<R>(self, job: impl FnOnce() -> R) -> R {
        /// Puts back what the thread held before, releasing the permit if still held, also
        /// when the job panics.
        struct Ends(Option<CpuPermit>);
        impl Drop for Ends {
            fn drop(&mut self) {
                drop(HELD.replace(self.0.take()));
            }
        }
        let _ends = Ends(HELD.replace(Some(self)));
        job()
    }
}

thread_local! {
    /// The permit of the [`CpuPool`] job running on this thread ([`CpuPermit::hold_while`]).
    static HELD: std::cell::Cell<Option<CpuPermit>> = const { std::cell::Cell::new(None) };
}

/// Gives back the worker of the [`CpuPool`] job running on this thread, if it holds one: the
/// job is about to sleep until the stepping threads have run its chunks.
fn give_back_held_worker() {
    drop(HELD.take());
}

/// Waits on this thread for `future` (a permit's hand-over), parked between its wake-ups: from
/// a thread outside any runtime, an async worker inside `block_in_place`, or a current-thread
/// runtime's own thread alike (which a runtime's `block_on` refuses).
fn park_until<F: std::future::Future>(future: F) -> F::Output {
    use std::task::{Context, Poll, Wake, Waker};
    /// Wakes the parked thread.
    struct Unpark(std::thread::Thread);
    impl Wake for Unpark {
        fn wake(self: Arc<Self>) {
            self.0.unpark();
        }
    }
    let waker = Waker::from(Arc::new(Unpark(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    let mut future = std::pin::pin!(future);
    loop {
        if let Poll::Ready(output) = future.as_mut().poll(&mut cx) {
            return output;
        }
        std::thread::park();
    }
}

impl Drop for CpuPermit {
    fn drop(&mut self) {
        if let Some(queue) = self.queue.take() {
            queue.release();
        }
    }
}

/// The pool's workers and its waiting jobs, one queue per tenant.
#[derive(Debug)]
struct Queue {
    state: Mutex<Waiting>,
}

/// What a [`Queue`] holds under its lock.
#[derive(Debug, Default)]
struct Waiting {
    /// Workers not held. Jobs wait only while this is zero.
    free: usize,
    /// The tenants with waiting jobs, each once, in the order they are served: a tenant served
    /// goes to the back if it has more waiting.
    turns: VecDeque<Turn>,
    /// Each tenant's waiting jobs, first come first: the senders their permits are handed
    /// through (a job whose caller stopped waiting has dropped its receiver and is skipped).
    jobs: HashMap<Turn, VecDeque<oneshot::Sender<CpuPermit>>>,
}

impl Waiting {
    /// The next waiting job, the tenants served in turn.
    fn next(&mut self) -> Option<oneshot::Sender<CpuPermit>> {
        let turn = self.turns.pop_front()?;
        let jobs = self.jobs.get_mut(&turn)?;
        let next = jobs.pop_front();
        if jobs.is_empty() {
            self.jobs.remove(&turn);
        } else {
            self.turns.push_back(turn);
        }
        next
    }
}

impl Queue {
    /// `free` workers, none held.
    fn of(free: usize) -> Arc<Queue> {
        Arc::new(Queue {
            state: Mutex::new(Waiting {
                free,
                ..Waiting::default()
            }),
        })
    }

    /// A worker for `turn`, waited for on this thread (parked, whatever runtime it is in). The
    /// queue is the stepping slots', which live as long as the threads that borrow them, so a
    /// waiting job's sender is never dropped unanswered.
    fn enter_blocking(self: &Arc<Self>, turn: Turn) -> CpuPermit {
        match self.enter(turn) {
            Ok(permit) => permit,
            Err(handed) => park_until(handed).expect("the stepping slots' queue is never closed"),
        }
    }

    /// A worker if one is free now (no job waits then, so taking it jumps no queue).
    fn try_enter(self: &Arc<Self>) -> Option<CpuPermit> {
        let mut waiting = self.lock();
        (waiting.free > 0).then(|| {
            waiting.free -= 1;
            CpuPermit {
                queue: Some(Arc::clone(self)),
            }
        })
    }

    /// Whether a tenant other than `turn`'s waits for a worker.
    fn others_wait(&self, turn: Turn) -> bool {
        self.lock().turns.iter().any(|&t| t != turn)
    }

    /// A worker for `turn` at once, or the receiver its permit will come through.
    fn enter(self: &Arc<Self>, turn: Turn) -> Result<CpuPermit, oneshot::Receiver<CpuPermit>> {
        let mut guard = self.lock();
        let waiting = &mut *guard;
        if waiting.free > 0 {
            waiting.free -= 1;
            return Ok(CpuPermit {
                queue: Some(Arc::clone(self)),
            });
        }
        let (tx, rx) = oneshot::channel();
        let jobs = waiting.jobs.entry(turn).or_default();
        if jobs.is_empty() {
            waiting.turns.push_back(turn);
        }
        jobs.push_back(tx);
        Err(rx)
    }

    /// A worker given back: handed to the next tenant's waiting job, or freed.
    fn release(self: &Arc<Self>) {
        loop {
            let Some(next) = ({
                let mut waiting = self.lock();
                let next = waiting.next();
                if next.is_none() {
                    waiting.free += 1;
                }
                next
            }) else {
                return;
            };
            let permit = CpuPermit {
                queue: Some(Arc::clone(self)),
            };
            match next.send(permit) {
                Ok(()) => return,
                // Its caller stopped waiting: the worker goes to the next one, without a drop
                // that would release it again.
                Err(mut unsent) => unsent.queue = None,
            }
        }
    }

    fn lock(&self) -> MutexGuard<'_, Waiting> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Default `--parallel-min-envs`.
pub const DEFAULT_PARALLEL_MIN_ENVS: usize = 512;
/// Default `--parallel-min-planner-envs`: a planner decision costs as much as a few hundred
/// plain steps, so even a few planner-labelled environments are worth a second thread.
pub const DEFAULT_PARALLEL_MIN_PLANNER_ENVS: usize = 4;
/// Fewest environments in one chunk of a parallel Step without planner labels: below this the
/// hand-over to another thread costs about what the chunk saves.
const MIN_CHUNK_ENVS: usize = 128;
/// Chunks per stepping thread: planner decisions vary in cost, so more, smaller chunks even the
/// threads out (the pool's idle threads steal the ones left).
const CHUNKS_PER_THREAD: usize = 4;
/// Most planner-labelled environments in one chunk: another tenant's chunk waits for one chunk
/// at most, a few milliseconds of planner decisions, however large the session.
const MAX_PLANNER_CHUNK_ENVS: usize = 128;

/// When a session's Reset or Step is spread over threads, and over how many.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stepping {
    /// Threads of the stepping pool (`--step-threads`); 1 steps every session on its caller's
    /// thread.
    pub threads: usize,
    /// Sessions of at least this many environments step in parallel (`--parallel-min-envs`).
    pub min_envs: usize,
    /// Planner-labelled sessions step in parallel from this many environments
    /// (`--parallel-min-planner-envs`).
    pub min_planner_envs: usize,
}

impl Default for Stepping {
    /// One thread per core, and the default thresholds.
    fn default() -> Self {
        Stepping {
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            min_envs: DEFAULT_PARALLEL_MIN_ENVS,
            min_planner_envs: DEFAULT_PARALLEL_MIN_PLANNER_ENVS,
        }
    }
}

impl Stepping {
    /// Every session on its caller's thread.
    pub const SERIAL: Stepping = Stepping {
        threads: 1,
        min_envs: usize::MAX,
        min_planner_envs: usize::MAX,
    };

    /// Into how many chunks a Reset or Step of `num_envs` environments is cut (1: stepped on the
    /// caller's thread), `planner` when its expert actions come from the planner.
    pub fn chunks(&self, num_envs: usize, planner: bool) -> usize {
        if self.threads <= 1 {
            return 1;
        }
        let (min_envs, chunk_envs) = if planner {
            (self.min_planner_envs, 1)
        } else {
            (self.min_envs, MIN_CHUNK_ENVS)
        };
        if num_envs < min_envs.max(2) {
            return 1;
        }
        // At least two chunks (the threshold asked for parallel), each of at least
        // `chunk_envs` when there are enough, at most a few per thread; planner chunks of at
        // most MAX_PLANNER_CHUNK_ENVS.
        let most = self.threads.saturating_mul(CHUNKS_PER_THREAD);
        let chunks = (num_envs / chunk_envs).clamp(2, most.max(2)).min(num_envs);
        if planner {
            chunks.max(num_envs.div_ceil(MAX_PLANNER_CHUNK_ENVS))
        } else {
            chunks
        }
    }
}

/// The stepping threads ([`Stepping::threads`] of them, started on the first parallel Step) and
/// the thresholds. Shared by every session of a store.
#[derive(Debug)]
pub struct StepPool {
    /// When to go parallel, and the pool's size.
    stepping: Stepping,
    /// The threads and their slots, once a Step needed them; an error if they could not be
    /// started (Steps then run on their caller's thread).
    pool: OnceLock<Result<Threads, String>>,
}

/// The stepping threads, and one slot for each, which the Steps' callers take in their
/// tenants' turns: a chunk runs only under a slot.
#[derive(Debug)]
struct Threads {
    /// The threads.
    pool: rayon::ThreadPool,
    /// Their slots: a [`Queue`] of as many workers.
    slots: Arc<Queue>,
}

/// A pool that steps every session on its caller's thread (and never starts one).
pub static SERIAL: StepPool = StepPool::new(Stepping::SERIAL);

impl StepPool {
    /// A pool of `stepping.threads` threads, started when first needed.
    pub const fn new(stepping: Stepping) -> StepPool {
        StepPool {
            stepping,
            pool: OnceLock::new(),
        }
    }

    /// The thresholds and size.
    pub fn stepping(&self) -> &Stepping {
        &self.stepping
    }

    /// Into how many chunks a Step of `num_envs` is cut; see [`Stepping::chunks`].
    pub fn chunks(&self, num_envs: usize, planner: bool) -> usize {
        self.stepping.chunks(num_envs, planner)
    }

    /// The threads for `pieces` pieces, if more than one and the threads could be started, with
    /// the caller's [`CpuPool`] worker given back (it sleeps while they run).
    fn parallel(&self, pieces: usize) -> Option<&Threads> {
        let threads = if pieces > 1 { self.threads() } else { None };
        if threads.is_some() {
            give_back_held_worker();
        }
        threads
    }

    /// The threads, started on the first call.
    fn threads(&self) -> Option<&Threads> {
        let pool = self.pool.get_or_init(|| {
            let threads = self.stepping.threads.max(1);
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(|i| format!("dinerdash-step-{i}"))
                .build()
                .map(|pool| Threads {
                    pool,
                    slots: Queue::of(threads),
                })
                .map_err(|e| {
                    tracing::warn!("cannot start the stepping threads, stepping serially: {e}");
                    e.to_string()
                })
        });
        pool.as_ref().ok()
    }

    /// [`StepPool::run`] without turns, for Steps and Resets without planner labels: their
    /// pieces take microseconds (a whole Step of the largest session, a few ms), so they go to
    /// the threads first come, first served, without the slots' bookkeeping, which cost a
    /// quarter of a 1,024-environment Step's rate (docs/benchmarks.md).
    pub fn run_first_come<T, E, W>(&self, pieces: Vec<T>, work: W) -> Result<(), E>
    where
        T: Send,
        E: Send,
        W: Fn(T) -> Result<(), E> + Sync + Send,
    {
        let Some(threads) = self.parallel(pieces.len()) else {
            return pieces.into_iter().try_for_each(work);
        };
        let results: Vec<Result<(), E>> = hand_over(|| {
            use rayon::iter::{IntoParallelIterator, ParallelIterator};
            threads
                .pool
                .install(|| pieces.into_par_iter().map(&work).collect())
        });
        results.into_iter().collect()
    }

    /// Runs `work` on every piece, the pieces in parallel on the stepping threads while the
    /// caller sleeps (giving back its [`CpuPool`] worker if it holds one), and returns the
    /// first error in the pieces' order (or runs them in order on the caller's thread, when
    /// there is one piece or the threads could not be started). Work must take no lock and
    /// submit nothing to either pool (see the module doc).
    ///
    /// The threads serve tenants in turn: each runs the pieces of a Step under a slot taken in
    /// `turn`, and gives the slot back after a piece when another tenant waits for one.
    pub fn run<T, E, W>(&self, turn: Turn, pieces: Vec<T>, work: W) -> Result<(), E>
    where
        T: Send,
        E: Send,
        W: Fn(T) -> Result<(), E> + Sync + Send,
    {
        let Some(threads) = self.parallel(pieces.len()) else {
            return pieces.into_iter().try_for_each(work);
        };
        let left = Mutex::new(pieces.into_iter().enumerate().peekable());
        let first_error: Mutex<Option<(usize, E)>> = Mutex::new(None);
        let lock = || left.lock().unwrap_or_else(PoisonError::into_inner);
        let next = || lock().next();
        let (work, next, first) = (&work, &next, &first_error);
        let slots = &threads.slots;
        // Each round takes a slot in `turn` (waiting behind other tenants), then whatever slots
        // are free, one runner each; the runners run pieces until none is left, or until
        // another tenant waits for a slot. Pieces left by runners that gave way wait for the
        // next round, in turn again.
        hand_over(|| {
            while lock().peek().is_some() {
                let slot = slots.enter_blocking(turn);
                threads.pool.in_place_scope(|scope| {
                    let mut slot = Some(slot);
                    while let Some(held) = slot.take().or_else(|| slots.try_enter()) {
                        let Some(piece) = next() else { break };
                        scope.spawn(move |_| {
                            let _slot = held;
                            let mut piece = Some(piece);
                            while let Some((i, p)) = piece.take().or_else(next) {
                                if let Err(e) = work(p) {
                                    let mut first =
                                        first.lock().unwrap_or_else(PoisonError::into_inner);
                                    if first.as_ref().is_none_or(|(j, _)| i < *j) {
                                        *first = Some((i, e));
                                    }
                                }
                                if slots.others_wait(turn) {
                                    break;
                                }
                            }
                        });
                    }
                });
            }
        });
        match first_error
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner)
        {
            Some((_, e)) => Err(e),
            None => Ok(()),
        }
    }
}

/// Runs `f`, which sleeps until other threads finish, from any thread: an async worker of a
/// multi-threaded runtime first gives its other tasks to another thread (`block_in_place`), so
/// that the requests queued behind it are served meanwhile. (A current-thread runtime cannot
/// give them away: it just waits, as for any Step it serves.)
fn hand_over<R>(f: impl FnOnce() -> R) -> R {
    use tokio::runtime::{Handle, RuntimeFlavor};
    match Handle::try_current() {
        Ok(handle) if handle.runtime_flavor() == RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(f)
        }
        _ => f(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Tenant 1's job asking `pool` for a worker from a thread of its own: `rx` says when it got
    /// one (it gives it back at once).
    fn other_tenant_waits(
        pool: &CpuPool,
        handle: &tokio::runtime::Handle,
    ) -> (std::sync::mpsc::Receiver<()>, std::thread::JoinHandle<()>) {
        let (tx, rx) = std::sync::mpsc::channel();
        let (other, handle) = (pool.clone(), handle.clone());
        let waiter = std::thread::spawn(move || {
            let permit = other.acquire_blocking(Turn(1), &handle).unwrap();
            tx.send(()).unwrap();
            drop(permit);
        });
        (rx, waiter)
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn never_runs_more_jobs_than_workers() {
        let pool = CpuPool::new(2);
        let running = Arc::new(AtomicUsize::new(0));
        let most = Arc::new(AtomicUsize::new(0));
        let jobs = (0..8).map(|_| {
            let (pool, running, most) = (pool.clone(), running.clone(), most.clone());
            tokio::spawn(async move {
                pool.run(Turn(0), move || {
                    let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                    most.fetch_max(now, Ordering::SeqCst);
                    std::thread::sleep(std::time::Duration::from_millis(5));
                    running.fetch_sub(1, Ordering::SeqCst);
                })
                .await
            })
        });
        for job in jobs.collect::<Vec<_>>() {
            job.await.unwrap().unwrap();
        }
        assert!(most.load(Ordering::SeqCst) <= 2);
    }

    #[test]
    fn a_blocking_acquire_waits_for_a_free_worker_and_the_process_has_one_pool() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let pool = CpuPool::new(1);
        let held = pool.acquire_blocking(Turn(0), runtime.handle()).unwrap();
        let (rx, waiter) = other_tenant_waits(&pool, runtime.handle());
        // Not while the only worker is held (however long this side waits)...
        assert!(
            rx.recv_timeout(std::time::Duration::from_millis(50))
                .is_err()
        );
        drop(held);
        // ...and at once when it is free.
        rx.recv_timeout(std::time::Duration::from_secs(60)).unwrap();
        waiter.join().unwrap();
        let (a, b) = (CpuPool::beside_steps(), CpuPool::beside_steps());
        assert!(Arc::ptr_eq(&a.queue, &b.queue));
        assert_eq!(a.workers(), b.workers());
    }

    #[tokio::test]
    async fn a_freed_worker_goes_to_the_tenants_in_turn() {
        let pool = CpuPool::new(1);
        let held = pool.acquire(Turn(0)).await.unwrap();
        // Tenant 1 queues three jobs, then tenant 2 one, and one of tenant 1's callers leaves.
        let order = Arc::new(std::sync::Mutex::new(Vec::new()));
        let mut waiters = Vec::new();
        for (turn, name) in [(1, "a1"), (1, "gone"), (1, "a2"), (1, "a3"), (2, "b1")] {
            let handed = match pool.queue.enter(Turn(turn)) {
                Err(handed) => handed,
                Ok(_) => panic!("a worker was free"),
            };
            waiters.push((name, handed));
        }
        waiters.retain(|(name, _)| *name != "gone");
        let tasks: Vec<_> = waiters
            .into_iter()
            .map(|(name, handed)| {
                let order = Arc::clone(&order);
                tokio::spawn(async move {
                    let permit = handed.await.unwrap();
                    order.lock().unwrap().push(name);
                    tokio::task::yield_now().await;
                    drop(permit);
                })
            })
            .collect();
        drop(held);
        for task in tasks {
            task.await.unwrap();
        }
        // Tenant 2's one job runs after tenant 1's first, not after all of them.
        assert_eq!(*order.lock().unwrap(), ["a1", "b1", "a2", "a3"]);
        // Every worker is free again.
        let state = pool.queue.lock();
        assert_eq!(state.free, 1);
        assert!(state.turns.is_empty() && state.jobs.is_empty());
    }

    #[test]
    fn small_sessions_step_on_their_callers_thread() {
        let two = Stepping {
            threads: 2,
            ..Stepping::default()
        };
        let min = DEFAULT_PARALLEL_MIN_ENVS;
        assert_eq!(two.chunks(1, false), 1);
        assert_eq!(two.chunks(min - 1, false), 1);
        assert_eq!(two.chunks(DEFAULT_PARALLEL_MIN_PLANNER_ENVS - 1, true), 1);
        // One thread, or the serial settings: never parallel.
        let one = Stepping { threads: 1, ..two };
        assert_eq!(one.chunks(16_384, false), 1);
        assert_eq!(one.chunks(16_384, true), 1);
        assert_eq!(Stepping::SERIAL.chunks(usize::MAX, true), 1);
    }

    #[test]
    fn large_sessions_are_cut_into_chunks_of_at_least_a_minimum() {
        let two = Stepping {
            threads: 2,
            ..Stepping::default()
        };
        // From the threshold on, at least two chunks of at least MIN_CHUNK_ENVS when there are
        // enough, at most CHUNKS_PER_THREAD a thread.
        assert_eq!(two.chunks(DEFAULT_PARALLEL_MIN_ENVS, false), 4);
        assert_eq!(two.chunks(4096, false), 8);
        assert_eq!(two.chunks(16_384, false), 8);
        let low = Stepping { min_envs: 3, ..two };
        assert_eq!(low.chunks(3, false), 2);
        assert_eq!(low.chunks(300, false), 2);
        // Planner labels: from their own threshold, chunks of one environment and up.
        assert_eq!(two.chunks(DEFAULT_PARALLEL_MIN_PLANNER_ENVS, true), 4);
        assert_eq!(two.chunks(256, true), 8);
        let many = Stepping { threads: 16, ..two };
        assert_eq!(many.chunks(256, true), 64);
        // Planner chunks of at most MAX_PLANNER_CHUNK_ENVS however large the session.
        assert_eq!(two.chunks(16_384, true), 16_384 / MAX_PLANNER_CHUNK_ENVS);
        assert_eq!(
            two.chunks(16_385, true),
            16_384 / MAX_PLANNER_CHUNK_ENVS + 1
        );
        assert_eq!(many.chunks(4096, false), 32);
    }

    #[test]
    fn the_pool_returns_the_first_error_in_order_and_runs_every_piece() {
        let pool = StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        });
        let done = AtomicUsize::new(0);
        let result = pool.run(Turn(0), (0..16).collect(), |i: usize| {
            done.fetch_add(1, Ordering::SeqCst);
            if i % 5 == 3 { Err(i) } else { Ok(()) }
        });
        assert_eq!(result, Err(3));
        assert_eq!(done.load(Ordering::SeqCst), 16);
        assert_eq!(
            pool.run(Turn(0), vec![1, 2], |_: i32| Ok::<(), ()>(())),
            Ok(())
        );
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_async_worker_hands_its_tasks_over_while_the_pool_steps() {
        let pool = Arc::new(StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        }));
        // On a worker of a multi-threaded runtime and on a blocking thread alike.
        let on_worker = {
            let pool = Arc::clone(&pool);
            tokio::spawn(async move { pool.run(Turn(0), vec![1, 2, 3], |_: i32| Ok::<(), ()>(())) })
        };
        assert_eq!(on_worker.await.unwrap(), Ok(()));
        let blocking =
            tokio::task::spawn_blocking(move || pool.run(Turn(0), vec![1, 2], |_: i32| Err(7)));
        assert_eq!(blocking.await.unwrap(), Err(7));
    }

    #[tokio::test]
    async fn a_current_thread_runtime_just_waits_for_the_pool() {
        let pool = StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        });
        assert_eq!(
            pool.run(Turn(0), vec![1, 2], |_: i32| Ok::<(), ()>(())),
            Ok(())
        );
    }

    #[test]
    fn a_job_sleeping_on_the_stepping_threads_gives_its_worker_back_for_good() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let cpu = CpuPool::new(1);
        let steps = StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        });
        let permit = cpu.acquire_blocking(Turn(0), runtime.handle()).unwrap();
        // Another tenant's job waits for the one worker...
        let (rx, waiter) = other_tenant_waits(&cpu, runtime.handle());
        // ...and gets it while the job holding it sleeps until its chunks are done: a chunk
        // waits for the other job's start.
        let rx = Mutex::new(rx);
        let stepped = permit.hold_while(|| {
            steps.run(Turn(0), vec![0, 1], |i: usize| match i {
                0 => rx
                    .lock()
                    .unwrap()
                    .recv_timeout(std::time::Duration::from_secs(60))
                    .map_err(|_| "the worker was held while the chunks ran"),
                _ => Ok(()),
            })
        });
        assert_eq!(stepped, Ok(()));
        waiter.join().unwrap();
        // The job ended without taking a worker again: the one worker is free, once.
        assert_eq!(cpu.queue.lock().free, 1);
        // A job of one chunk runs on its caller's thread and keeps its worker to its end.
        let permit = cpu.acquire_blocking(Turn(0), runtime.handle()).unwrap();
        permit.hold_while(|| {
            assert_eq!(
                steps.run(Turn(0), vec![0], |_: i32| Ok::<(), ()>(())),
                Ok(())
            );
            assert_eq!(cpu.queue.lock().free, 0);
        });
        assert_eq!(cpu.queue.lock().free, 1);
    }

    #[test]
    fn the_stepping_threads_serve_tenants_in_turn() {
        let pool = StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        });
        let started = Mutex::new(Vec::new());
        let (a_began, b_may_start) = std::sync::mpsc::channel();
        let a_began = Mutex::new(Some(a_began));
        std::thread::scope(|s| {
            // Tenant A's Step of 40 pieces of 5 ms each...
            s.spawn(|| {
                pool.run(Turn(1), (0..40).collect(), |i: usize| {
                    started.lock().unwrap().push(('a', i));
                    if let Some(began) = a_began.lock().unwrap().take() {
                        began.send(()).unwrap();
                    }
                    std::thread::sleep(std::time::Duration::from_millis(5));
                    Ok::<(), ()>(())
                })
            });
            // ...then tenant B's of two pieces: they start within a few of A's, not after all.
            b_may_start.recv().unwrap();
            let b_from = started.lock().unwrap().len();
            pool.run(Turn(2), vec![0, 1], |i: usize| {
                started.lock().unwrap().push(('b', i));
                Ok::<(), ()>(())
            })
            .unwrap();
            let order = started.lock().unwrap().clone();
            let b_last = order.iter().rposition(|(t, _)| *t == 'b').unwrap();
            assert!(
                b_last - b_from <= 6,
                "B's pieces waited for {} of A's: {order:?}",
                b_last - b_from - 1
            );
        });
        let order = started.into_inner().unwrap();
        assert_eq!(order.len(), 42, "every piece ran once");
    }

    #[tokio::test]
    async fn a_panic_is_an_error_and_frees_its_worker() {
        let pool = CpuPool::new(1);
        assert!(matches!(
            pool.run(Turn(0), || panic!("boom")).await,
            Err(CpuError::Failed(_))
        ));
        assert_eq!(pool.run(Turn(0), || 1).await.unwrap(), 1);
    }
}
