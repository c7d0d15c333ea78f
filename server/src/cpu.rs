//! The bounded pool for CPU-heavy work: Rollout episodes and planner decisions. Such work runs on
//! tokio's blocking threads, never on the async workers that serve Step and Reset, and at most
//! `workers` jobs run at once, so a flood of heavy requests queues here instead of starving
//! every other client.
//!
//! The server's pool ([`CpuPool::beside_steps`]) is one per process: the gRPC service and the
//! shared-memory data plane's session threads ([`CpuPool::acquire_blocking`]) take their permits
//! from the same semaphore, so planner Steps are bounded together whichever transport asked.

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
    /// session's thread), which then runs its job itself while it holds the permit: the same
    /// bound as [`CpuPool::run`], without a hop to another thread. `runtime` drives the wait
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
