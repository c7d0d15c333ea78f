//! The two thread pools for CPU-heavy work, and nothing else: the bounded pool of blocking
//! workers ([`CpuPool`]) and the stepping threads of large Steps ([`StepPool`]). The module is
//! named for what it holds, the pools, rather than for the resource they spend.
//!
//! - [`CpuPool`]: Rollout episodes and the Reset, Step, Render, Snapshot and Fork of
//!   planner-labelled sessions. Such work runs on tokio's blocking threads, never on the async
//!   workers that serve Step and Reset, and at most `workers` jobs run at once, so a flood of
//!   heavy requests queues here instead of starving every other client. The server's pool
//!   ([`CpuPool::beside_steps`]) is one per process: the gRPC service and the shared-memory data
//!   plane's threads ([`CpuPool::acquire_blocking`]) take their permits from the same
//!   semaphore, so planner Steps are bounded together whichever transport asked.
//! - [`StepPool`]: the threads that step one large session's environments in chunks at once
//!   ([`Stepping`] says when a Step is large enough). Only chunks of large Steps run there;
//!   small Steps stay on their caller's thread and never queue behind them.
//!
//! # Why the two pools neither deadlock nor oversubscribe
//! A planner-labelled Step runs on a [`CpuPool`] blocking thread; when it is large it hands its
//! chunks to the [`StepPool`] and that thread sleeps until they are done. Chunk work touches
//! only its own environments and Batch rows: it takes no lock, awaits nothing and never submits
//! work to either pool, so a chunk cannot wait on anything its caller holds (the caller holds
//! the session's lock; chunks run under it, on data borrowed from it). The callers of large
//! Steps sleep while their chunks run, so the CPU-busy threads are at most the stepping
//! threads, plus the callers of small Steps (async workers, shared-memory threads, CpuPool
//! workers) that run their own. An async worker that hands a large Step over gives its other
//! tasks to another thread first (`block_in_place`), so small Steps keep being served.

use std::sync::{Arc, OnceLock};

use tokio::sync::{OwnedSemaphorePermit, Semaphore, TryAcquireError};

/// Why a job did not run to completion.
#[derive(Debug, thiserror::Error)]
pub enum CpuError {
    /// The pool's semaphore was closed (nothing closes it today; tokio's API can fail so).
    #[error("the worker pool is closed")]
    Closed,
    /// The job panicked; the panic was caught on its blocking thread.
    #[error("a worker failed: {0}")]
    Failed(String),
}

/// A bounded pool of blocking workers. Cloning is shallow: every clone shares the same permits.
#[derive(Debug, Clone)]
pub struct CpuPool {
    /// One permit per job allowed to run at once.
    permits: Arc<Semaphore>,
    /// The number of permits, for [`CpuPool::workers`].
    max: usize,
}

impl CpuPool {
    /// A pool running at most `workers` jobs at once (at least one).
    pub fn new(workers: usize) -> CpuPool {
        CpuPool {
            permits: Arc::new(Semaphore::new(workers.max(1))),
            max: workers.max(1),
        }
    }

    /// The process's pool, which leaves one core to the async workers serving Step and Reset
    /// (one worker on one or two cores): Rollouts being read must not raise other clients' Step
    /// latency. Every call returns the same pool (the cores are the machine's, not a service's):
    /// the gRPC service and the shared-memory data plane share its permits.
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
        // The permits are never added to or forgotten: the count given to `new`, at least 1.
        self.max
    }

    /// Waits for a free worker from a thread of its own outside the runtime (a shared-memory
    /// planner session's thread), which then runs its job itself while it holds the permit: the
    /// same bound as [`CpuPool::run`], without a hop to another thread. `runtime` drives the wait
    /// when no permit is free at once; it must not be called from an async task.
    pub fn acquire_blocking(
        &self,
        runtime: &tokio::runtime::Handle,
    ) -> Result<OwnedSemaphorePermit, CpuError> {
        match Arc::clone(&self.permits).try_acquire_owned() {
            Ok(permit) => Ok(permit),
            Err(TryAcquireError::Closed) => Err(CpuError::Closed),
            Err(TryAcquireError::NoPermits) => runtime.block_on(self.acquire()),
        }
    }

    /// Waits for a free worker. Holding the permit is what reserves the worker: pass it into
    /// [`CpuPool::run_with`], or keep it across several blocking jobs.
    pub async fn acquire(&self) -> Result<OwnedSemaphorePermit, CpuError> {
        Arc::clone(&self.permits)
            .acquire_owned()
            .await
            .map_err(|_| CpuError::Closed)
    }

    /// Runs `job` on a blocking thread once a worker is free, and returns its result. When the
    /// caller stops waiting (a cancelled request), a job already running finishes and releases
    /// its worker; one still queued never starts.
    pub async fn run<F, R>(&self, job: F) -> Result<R, CpuError>
    where
        F: FnOnce() -> R + Send + 'static,
        R: Send + 'static,
    {
        let permit = self.acquire().await?;
        CpuPool::run_with(permit, job).await
    }

    /// Runs `job` on a blocking thread under a permit already taken from [`CpuPool::acquire`];
    /// the permit is released when the job ends.
    pub async fn run_with<F, R>(permit: OwnedSemaphorePermit, job: F) -> Result<R, CpuError>
    where
        F: FnOnce() -> R + Send + 'static,
        R: Send + 'static,
    {
        tokio::task::spawn_blocking(move || {
            let result = job();
            drop(permit);
            result
        })
        .await
        .map_err(|e| CpuError::Failed(e.to_string()))
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
        // `chunk_envs` when there are enough, at most a few per thread.
        let most = self.threads.saturating_mul(CHUNKS_PER_THREAD);
        (num_envs / chunk_envs).clamp(2, most.max(2)).min(num_envs)
    }
}

/// The stepping threads ([`Stepping::threads`] of them, started on the first parallel Step) and
/// the thresholds. Shared by every session of a store.
#[derive(Debug)]
pub struct StepPool {
    /// When to go parallel, and the pool's size.
    stepping: Stepping,
    /// The threads, once a Step needed them; an error if they could not be started (Steps then
    /// run on their caller's thread).
    pool: OnceLock<Result<rayon::ThreadPool, String>>,
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

    /// The threads, started on the first call.
    fn threads(&self) -> Option<&rayon::ThreadPool> {
        let pool = self.pool.get_or_init(|| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(self.stepping.threads.max(1))
                .thread_name(|i| format!("dinerdash-step-{i}"))
                .build()
                .map_err(|e| {
                    tracing::warn!("cannot start the stepping threads, stepping serially: {e}");
                    e.to_string()
                })
        });
        pool.as_ref().ok()
    }

    /// Runs `work` on every piece, the pieces in parallel on the stepping threads while the
    /// caller sleeps, and returns the first error in the pieces' order (or runs them in order on
    /// the caller's thread, when there is one piece or the threads could not be started). Work
    /// must take no lock and submit nothing to either pool (see the module doc).
    pub fn run<T, E, W>(&self, pieces: Vec<T>, work: W) -> Result<(), E>
    where
        T: Send,
        E: Send,
        W: Fn(T) -> Result<(), E> + Sync + Send,
    {
        let threads = if pieces.len() > 1 {
            self.threads()
        } else {
            None
        };
        let Some(threads) = threads else {
            return pieces.into_iter().try_for_each(work);
        };
        let results: Vec<Result<(), E>> = hand_over(|| {
            use rayon::iter::{IntoParallelIterator, ParallelIterator};
            threads.install(|| pieces.into_par_iter().map(&work).collect())
        });
        results.into_iter().collect()
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

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn never_runs_more_jobs_than_workers() {
        let pool = CpuPool::new(2);
        let running = Arc::new(AtomicUsize::new(0));
        let most = Arc::new(AtomicUsize::new(0));
        let jobs = (0..8).map(|_| {
            let (pool, running, most) = (pool.clone(), running.clone(), most.clone());
            tokio::spawn(async move {
                pool.run(move || {
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
        let held = pool.acquire_blocking(runtime.handle()).unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        let (other, handle) = (pool.clone(), runtime.handle().clone());
        let waiter = std::thread::spawn(move || {
            let permit = other.acquire_blocking(&handle).unwrap();
            tx.send(()).unwrap();
            drop(permit);
        });
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
        assert!(Arc::ptr_eq(&a.permits, &b.permits));
        assert_eq!(a.workers(), b.workers());
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
        let result = pool.run((0..16).collect(), |i: usize| {
            done.fetch_add(1, Ordering::SeqCst);
            if i % 5 == 3 { Err(i) } else { Ok(()) }
        });
        assert_eq!(result, Err(3));
        assert_eq!(done.load(Ordering::SeqCst), 16);
        assert_eq!(pool.run(vec![1, 2], |_: i32| Ok::<(), ()>(())), Ok(()));
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
            tokio::spawn(async move { pool.run(vec![1, 2, 3], |_: i32| Ok::<(), ()>(())) })
        };
        assert_eq!(on_worker.await.unwrap(), Ok(()));
        let blocking = tokio::task::spawn_blocking(move || pool.run(vec![1, 2], |_: i32| Err(7)));
        assert_eq!(blocking.await.unwrap(), Err(7));
    }

    #[tokio::test]
    async fn a_current_thread_runtime_just_waits_for_the_pool() {
        let pool = StepPool::new(Stepping {
            threads: 2,
            min_envs: 2,
            min_planner_envs: 2,
        });
        assert_eq!(pool.run(vec![1, 2], |_: i32| Ok::<(), ()>(())), Ok(()));
    }

    #[tokio::test]
    async fn a_panic_is_an_error_and_frees_its_worker() {
        let pool = CpuPool::new(1);
        assert!(matches!(
            pool.run(|| panic!("boom")).await,
            Err(CpuError::Failed(_))
        ));
        assert_eq!(pool.run(|| 1).await.unwrap(), 1);
    }
}
