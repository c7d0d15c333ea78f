//! The session store: unguessable session IDs, the limits, idle expiry, and one lock per
//! session.
//!
//! There is no global lock on the step path. Sessions live in [`SHARDS`] hash maps, each behind
//! its own std `Mutex` that is held only to look up, insert or remove an `Arc<Session>`; the
//! work of a Reset or Step happens under the session's own std `Mutex`, so the steps of one
//! session are serialized and different sessions run in parallel. std rather than tokio mutexes:
//! no critical section ever awaits, and they are several times cheaper.
//!
//! Every session belongs to the identity that created it (its [`Owner`]), and every lookup by
//! ID names the caller's identity: another identity's session is answered exactly as an unknown
//! ID ([`SessionError::NotFound`], the same message), by the same code path, without marking it
//! used. The ID is not the access check; with tenants (`--auth-tokens-file`) each tenant is its
//! own identity, otherwise every caller is the one shared identity.
//!
//! - [`envs`]: the environments of one session and what Reset and Step do to them.
//! - [`watch`]: each session's running summary and watched environments, read by the web pages.

pub mod envs;
mod shm_secret;
pub mod watch;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

pub use envs::{Autoreset, Batch, Envs, ExpertActions, ResetArgs, SessionOptions};
pub use shm_secret::{SHM_SECRET_BYTES, ShmSecret};

use crate::budget::{Budget, BudgetError, Charge, DEFAULT_MAX_MEMORY, Tenant};
use crate::metrics::Metrics;
use crate::pools::{StepPool, Stepping, Turn};
use crate::shutdown::Shutdown;
use crate::sim::Config;

/// Number of shards of the session map: enough that two cores never wait on each other's
/// lookups, few enough that a sweep over all of them is cheap.
const SHARDS: usize = 64;
/// Longest prefix of a bad session ID echoed back in an error message.
const MAX_ECHOED_ID: usize = 64;

/// Why a session operation was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SessionError {
    /// No session has this ID: never created, closed, or expired.
    #[error("session {0} not found (closed or expired)")]
    NotFound(String),
    /// The request is malformed; the message starts with the field's path (`seeds`,
    /// `arrivals[0].groups[2].size`) and gives its allowed range: the service reports that
    /// leading path as the `BadRequest` field.
    #[error("{0}")]
    InvalidArgument(String),
    /// Environment `env` of a Step was given an action outside the game's actions.
    #[error("actions[{env}] must be in 0..={max}, got {action}", max = crate::sim::NUM_ACTIONS - 1)]
    ActionOutOfRange {
        /// Index of the environment in the session.
        env: usize,
        /// The action given.
        action: i32,
    },
    /// A partial Reset would keep environment `i`, which has never been reset.
    #[error("environment {0} has never been reset: include it in reset_mask")]
    KeptNeverReset(usize),
    /// The server holds its maximum number of sessions.
    #[error("the server holds its maximum of {0} sessions; close one or raise --max-sessions")]
    TooManySessions(usize),
    /// Step or Render before the first Reset.
    #[error("the session was never reset; call reset")]
    NotReset,
    /// A single-environment autoreset DISABLED session stepped after its episode ended.
    #[error("episode is over; call reset")]
    EpisodeOver,
    /// Environment i of an autoreset DISABLED session stepped after its episode ended.
    #[error("environment {0}: episode is over; call reset")]
    EnvEpisodeOver(usize),
    /// The memory budget or the tenant's share would be passed.
    #[error(transparent)]
    OverBudget(BudgetError),
    /// A state the checks rule out.
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<BudgetError> for SessionError {
    fn from(e: BudgetError) -> SessionError {
        match e {
            BudgetError::Sessions(max) => {
                SessionError::TooManySessions(usize::try_from(max).unwrap_or(usize::MAX))
            }
            other => SessionError::OverBudget(other),
        }
    }
}

/// Default most live sessions: an idle single-environment session costs ~3.5 KB, so 100,000
/// fit in well under 1 GiB.
pub const DEFAULT_MAX_SESSIONS: u32 = 100_000;
/// Default most environments in one session: one trainer feeding an accelerator wants thousands
/// (~3.5 KB each, so 16,384 hold ~57 MB of the memory budget).
pub const DEFAULT_MAX_ENVS_PER_SESSION: u32 = 16_384;
/// Default idle time after which a session is closed.
pub const DEFAULT_SESSION_TTL: Duration = Duration::from_secs(300);
/// What a session costs besides its environments: the `Session`, its `Arc`, its map entry.
const SESSION_OVERHEAD_BYTES: u64 = 256;

/// Digits of a session ID that info-level logs show: enough to match a line with the sessions
/// page (which shows as many), far from enough to name the session. The full ID, a capability
/// without tenants, is logged at debug level only.
pub const LOGGED_ID: usize = 8;

/// The first [`LOGGED_ID`] characters of a session ID as a request gave it.
pub fn short_id(id: &str) -> &str {
    id.char_indices()
        .nth(LOGGED_ID)
        .map_or(id, |(i, _)| &id[..i])
}

/// The bytes the memory budget charges a session of `num_envs` environments.
pub fn session_bytes(num_envs: usize) -> u64 {
    (num_envs as u64).saturating_mul(Envs::BYTES_PER_ENV) + SESSION_OVERHEAD_BYTES
}

/// The limits a server enforces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most live sessions; CreateSession, Fork and Restore beyond it are refused.
    pub max_sessions: usize,
    /// Most environments in one session.
    pub max_envs_per_session: usize,
    /// A session unused for this long is closed.
    pub session_ttl: Duration,
    /// Bytes sessions and Rollout streams may hold (the memory budget).
    pub max_memory: u64,
    /// When a large session's Reset and Step run in chunks on several threads, and on how many.
    pub stepping: Stepping,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_sessions: DEFAULT_MAX_SESSIONS as usize,
            max_envs_per_session: DEFAULT_MAX_ENVS_PER_SESSION as usize,
            session_ttl: DEFAULT_SESSION_TTL,
            max_memory: DEFAULT_MAX_MEMORY,
            stepping: Stepping::default(),
        }
    }
}

/// A session ID: 128 random bits, written as 32 lowercase hex digits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SessionId(u128);

impl SessionId {
    /// A fresh ID from the operating system's random source.
    fn random() -> Result<SessionId, SessionError> {
        use rand::TryRngCore;
        let mut bytes = [0u8; 16];
        rand::rngs::OsRng.try_fill_bytes(&mut bytes).map_err(|e| {
            SessionError::Internal(format!("no system randomness for a session ID: {e}"))
        })?;
        Ok(SessionId(u128::from_le_bytes(bytes)))
    }

    /// The ID written as `text`, or the NOT_FOUND error for it.
    pub fn parse(text: &str) -> Result<SessionId, SessionError> {
        let valid = text.len() == 32 && text.bytes().all(|b| b.is_ascii_hexdigit());
        match valid.then(|| u128::from_str_radix(text, 16)) {
            Some(Ok(id)) => Ok(SessionId(id)),
            _ => {
                let shown: String = text.chars().take(MAX_ECHOED_ID).collect();
                Err(SessionError::NotFound(shown))
            }
        }
    }

    /// Which shard holds this ID (the low bits are as random as any).
    fn shard(self) -> usize {
        (self.0 as usize) % SHARDS
    }
}

impl std::fmt::Display for SessionId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:032x}", self.0)
    }
}

/// Whose a session is: the identity every lookup by ID must name. Compared by identity
/// ([`Owner::is`]), never by name.
#[derive(Debug, Clone)]
pub enum Owner {
    /// Everyone who is not a tenant: the shared `--auth-token`, or a server without tokens (one
    /// that serves only its own host).
    Shared,
    /// The tenant a token of `--auth-tokens-file` stands for (the `Arc` the request gate puts
    /// in the request's extensions).
    Tenant(Arc<Tenant>),
}

impl Owner {
    /// The identity of a request that came with `tenant`'s token, or with no tenant's.
    pub fn of(tenant: Option<&Arc<Tenant>>) -> Owner {
        tenant.map_or(Owner::Shared, |t| Owner::Tenant(Arc::clone(t)))
    }

    /// Whether `self` and `other` are the same identity.
    pub fn is(&self, other: &Owner) -> bool {
        match (self, other) {
            (Owner::Shared, Owner::Shared) => true,
            (Owner::Tenant(a), Owner::Tenant(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

/// Who makes a request that creates a session: whose the session will be, and whose share it
/// counts against. They differ without tenants: the identity is the shared one, the share the
/// connection's (see [`crate::connections`]), which a reconnect changes while the owner stays.
#[derive(Debug, Clone)]
pub struct Caller {
    /// The identity the new session belongs to.
    pub owner: Owner,
    /// Whose share the new session counts against.
    pub tenant: Arc<Tenant>,
}

impl Caller {
    /// A tenant calling with its own token: it is both the owner and the share.
    pub fn tenant(tenant: Arc<Tenant>) -> Caller {
        Caller {
            owner: Owner::Tenant(Arc::clone(&tenant)),
            tenant,
        }
    }

    /// A caller of the shared identity whose requests count against `share`'s share.
    pub fn shared(share: Arc<Tenant>) -> Caller {
        Caller {
            owner: Owner::Shared,
            tenant: share,
        }
    }
}

/// What a client needs to know about a session it created (the protocol's `Spec`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionSpec {
    /// N.
    pub num_envs: usize,
    /// The options, autoreset as it is in effect.
    pub options: SessionOptions,
    /// The configuration of the next reset.
    pub config: Config,
    /// The credential of the session's shared-memory hello, told only to its creator.
    pub shm_secret: ShmSecret,
}

/// One session: its environments behind their own lock, and when it was last used.
#[derive(Debug)]
pub struct Session {
    /// Its bytes in the memory budget and its slot in its tenant's share, given back when the
    /// last reference goes (closed or expired, and no request still using it).
    _charge: Charge,
    /// Whose it is: every lookup by ID names an identity, and only this one finds it.
    owner: Owner,
    /// Milliseconds since the store's epoch at the last lookup; the sweeper reads it.
    last_used_ms: AtomicU64,
    /// The environments. Locked for the whole of one Reset or Step.
    envs: Mutex<Envs>,
    /// N, fixed at creation (the sessions page reads it without the lock).
    num_envs: usize,
    /// The options (which expert fills its expert actions, autoreset): fixed at creation, so
    /// read without the lock.
    options: SessionOptions,
    /// Milliseconds since the store's epoch at creation.
    created_ms: u64,
    /// Steps, episodes and recent scores, for the sessions page.
    tally: watch::Tally,
    /// The environments someone watches.
    watch: watch::Watch,
    /// What the shared-memory hello must carry for this session ([`Store::find_shm`]).
    shm_secret: ShmSecret,
    /// Where the calls that run on the CPU pool wait for the one before them, without a worker
    /// ([`FoundSession::queue`]).
    queue: Arc<tokio::sync::Semaphore>,
}

impl Session {
    /// The environments, locked. A panic under the lock cannot leave a half-stepped
    /// environment visible to clients any worse than the error it raised, so poisoning is
    /// ignored rather than turning one failure into a dead session.
    fn lock(&self) -> MutexGuard<'_, Envs> {
        self.envs.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// What a client needs to know about this session.
    fn spec(&self) -> SessionSpec {
        let envs = self.lock();
        SessionSpec {
            num_envs: envs.len(),
            options: *envs.options(),
            config: envs.config(),
            shm_secret: self.shm_secret,
        }
    }
}

/// A session [`Store::find`] looked up: its Reset or Step then takes its lock once, with no
/// second lookup. It keeps the session alive while held, even if closed meanwhile.
#[derive(Debug, Clone)]
pub struct FoundSession {
    /// The session.
    session: Arc<Session>,
    /// The store's counters.
    metrics: Arc<Metrics>,
    /// The threads that step large sessions in chunks.
    pool: Arc<StepPool>,
}

impl FoundSession {
    /// Which expert fills the session's expert actions (no lock: fixed at creation).
    pub fn expert_actions(&self) -> ExpertActions {
        self.session.options.expert_actions
    }

    /// N (no lock: fixed at creation).
    pub fn num_envs(&self) -> usize {
        self.session.num_envs
    }

    /// The session's turn among the calls on the CPU pool that lock it: a caller waits here,
    /// holding no worker, until the call before it ends, and holds the returned permit until
    /// its own ends. So a worker never waits for the lock of a session whose large Step gave its
    /// worker back (see [`crate::pools`]).
    pub async fn queue(&self) -> tokio::sync::OwnedSemaphorePermit {
        Arc::clone(&self.session.queue)
            .acquire_owned()
            .await
            .expect("a session's queue is never closed")
    }

    /// Whose share the session counts against.
    pub fn tenant(&self) -> &Arc<Tenant> {
        self.session._charge.tenant()
    }

    /// Whose the session is (a fork or restore of it belongs to whoever makes it).
    pub fn owner(&self) -> &Owner {
        &self.session.owner
    }

    /// A copy of environment `index`'s state, once it has been reset (the play page reads its
    /// mask and the reference expert's choice from it).
    pub fn restaurant(&self, index: usize) -> Option<crate::sim::Restaurant> {
        self.session.lock().restaurant(index).copied()
    }

    /// The session as versioned bytes.
    pub fn snapshot(&self) -> Vec<u8> {
        self.session.lock().snapshot()
    }

    /// Environments `start..start + count` of the session (`count` 0: to the end) as the
    /// versioned bytes of a session of their own.
    pub fn snapshot_range(&self, start: u32, count: u32) -> Result<Vec<u8>, SessionError> {
        self.session.lock().snapshot_range(start, count)
    }

    /// One environment of the session drawn as text.
    pub fn render(&self, env_index: u32, color: bool) -> Result<String, SessionError> {
        self.session.lock().render(env_index, color)
    }

    /// Resets every environment of the session.
    pub fn reset(&self, args: &ResetArgs) -> Result<Batch, SessionError> {
        let mut envs = self.session.lock();
        let batch = envs.reset_on(args, &self.pool, Turn::of(self.tenant()))?;
        self.session.was_reset(&envs, &batch);
        drop(envs);
        let m = &self.metrics;
        m.env_resets.inc_by(u64::from(batch.num_envs));
        Ok(batch)
    }

    /// Steps every environment of the session.
    pub fn step(&self, actions: &[u8]) -> Result<Batch, SessionError> {
        let mut envs = self.session.lock();
        let batch = envs.step_on(actions, &self.pool, Turn::of(self.tenant()))?;
        self.session.stepped(&envs, actions, &batch);
        drop(envs);
        let m = &self.metrics;
        m.step_calls.inc();
        m.env_steps.inc_by(u64::from(batch.num_envs));
        let resets = batch.resets();
        if resets > 0 {
            m.env_resets.inc_by(resets);
        }
        Ok(batch)
    }
}

/// The sessions of one server. Cloning `Store` is shallow: clones share the sessions.
#[derive(Debug, Clone)]
pub struct Store {
    /// Everything the clones share.
    shared: Arc<Shared>,
}

#[derive(Debug)]
struct Shared {
    /// Session maps, by [`SessionId::shard`].
    shards: Vec<Mutex<HashMap<SessionId, Arc<Session>>>>,
    /// The memory budget and the live-session count (checked without locking every shard).
    budget: Arc<Budget>,
    /// The limits.
    limits: Limits,
    /// Zero of `Session::last_used_ms`.
    epoch: Instant,
    /// Counters for the metrics endpoint.
    metrics: Arc<Metrics>,
    /// The threads that step large sessions in chunks (`limits.stepping`).
    pool: Arc<StepPool>,
}

impl Store {
    /// An empty store.
    pub fn new(limits: Limits, metrics: Arc<Metrics>) -> Store {
        Store {
            shared: Arc::new(Shared {
                shards: (0..SHARDS).map(|_| Mutex::new(HashMap::new())).collect(),
                budget: Arc::new(Budget::new(
                    limits.max_memory,
                    limits.max_sessions as u64,
                    Arc::clone(&metrics),
                )),
                limits,
                epoch: Instant::now(),
                metrics,
                pool: Arc::new(StepPool::new(limits.stepping)),
            }),
        }
    }

    /// The limits this store enforces.
    pub fn limits(&self) -> &Limits {
        &self.shared.limits
    }

    /// Live sessions.
    pub fn live(&self) -> usize {
        self.shared.budget.live_sessions() as usize
    }

    /// The memory budget, which Rollout streams are charged to as well.
    pub fn budget(&self) -> &Arc<Budget> {
        &self.shared.budget
    }

    fn now_ms(&self) -> u64 {
        self.shared.epoch.elapsed().as_millis() as u64
    }

    fn shard(&self, id: SessionId) -> MutexGuard<'_, HashMap<SessionId, Arc<Session>>> {
        self.shared.shards[id.shard()]
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// The session with this ID if `owner` owns it, not marked as used. The one lookup every
    /// access by ID goes through: a session of another owner is refused inside the same shard
    /// lookup, with the error of an unknown ID, before anything about it is touched.
    fn lookup(&self, owner: &Owner, id: &str) -> Result<Arc<Session>, SessionError> {
        let key = SessionId::parse(id)?;
        self.shard(key)
            .get(&key)
            .filter(|s| s.owner.is(owner))
            .cloned()
            .ok_or_else(|| SessionError::NotFound(id.to_owned()))
    }

    /// The session with this ID if `owner` owns it, marked as used now.
    fn get(&self, owner: &Owner, id: &str) -> Result<Arc<Session>, SessionError> {
        let session = self.lookup(owner, id)?;
        session.last_used_ms.store(self.now_ms(), Ordering::Relaxed);
        Ok(session)
    }

    /// Whether session `id` is live, without marking it used (the shared-memory thread serving it
    /// asks, to let it go).
    pub fn contains(&self, id: &str) -> bool {
        SessionId::parse(id).is_ok_and(|key| self.shard(key).contains_key(&key))
    }

    /// Charges a session of `num_envs` environments to `tenant`, before they are allocated.
    fn charge(&self, tenant: &Arc<Tenant>, num_envs: usize) -> Result<Charge, SessionError> {
        Ok(self
            .shared
            .budget
            .charge_session(tenant, num_envs as u64, session_bytes(num_envs))?)
    }

    /// Adds a session already charged, owned by `owner`, and returns its ID and spec.
    fn insert(
        &self,
        owner: &Owner,
        envs: Envs,
        charge: Charge,
    ) -> Result<(SessionId, SessionSpec), SessionError> {
        let now = self.now_ms();
        let session = Arc::new(Session {
            _charge: charge,
            owner: owner.clone(),
            last_used_ms: AtomicU64::new(now),
            num_envs: envs.len(),
            options: *envs.options(),
            envs: Mutex::new(envs),
            created_ms: now,
            tally: watch::Tally::default(),
            watch: watch::Watch::default(),
            shm_secret: ShmSecret::random()?,
            queue: Arc::new(tokio::sync::Semaphore::new(1)),
        });
        let spec = session.spec();
        let id = loop {
            // On an error the session is dropped, and its charge with it.
            let id = SessionId::random()?;
            let mut shard = self.shard(id);
            // 128 random bits do not collide, but a collision must not replace a session.
            if let std::collections::hash_map::Entry::Vacant(slot) = shard.entry(id) {
                slot.insert(Arc::clone(&session));
                break id;
            }
        };
        self.shared.metrics.sessions_created.inc();
        tracing::debug!(session = %id, num_envs = spec.num_envs, "session created");
        Ok((id, spec))
    }

    /// Creates a session of `num_envs` environments, not reset yet, owned by `caller`.
    pub fn create(
        &self,
        caller: &Caller,
        num_envs: u32,
        config: Config,
        options: SessionOptions,
        seed: Option<u64>,
    ) -> Result<(SessionId, SessionSpec), SessionError> {
        let max = self.shared.limits.max_envs_per_session;
        let n = usize::try_from(num_envs).unwrap_or(usize::MAX);
        if !(1..=max).contains(&n) {
            return Err(SessionError::InvalidArgument(format!(
                "num_envs must be in 1..={max}, got {num_envs}"
            )));
        }
        config
            .validate()
            .map_err(|e| SessionError::InvalidArgument(e.to_string()))?;
        let charge = self.charge(&caller.tenant, n)?;
        self.insert(&caller.owner, Envs::new(n, config, options, seed)?, charge)
    }

    /// Closes a session of `owner`'s.
    pub fn close(&self, owner: &Owner, id: &str) -> Result<(), SessionError> {
        let key = SessionId::parse(id)?;
        let mut shard = self.shard(key);
        // The owner check and the removal under one shard lock: another owner's session is
        // neither removed nor told apart from an unknown ID.
        let mine = shard.get(&key).is_some_and(|s| s.owner.is(owner));
        let removed = mine.then(|| shard.remove(&key)).flatten();
        drop(shard);
        // Freed (if no request still holds it) outside the shard lock.
        removed.ok_or_else(|| SessionError::NotFound(id.to_owned()))?;
        self.shared.metrics.sessions_closed.inc();
        tracing::debug!(session = %key, "session closed");
        Ok(())
    }

    /// Session `id` of `owner`'s, looked up once for a Reset or Step (or Render, Snapshot, Fork)
    /// that may run elsewhere (the service runs those of sessions whose expert actions come from
    /// the planner on its CPU pool).
    pub fn find(&self, owner: &Owner, id: &str) -> Result<FoundSession, SessionError> {
        Ok(FoundSession {
            session: self.get(owner, id)?,
            metrics: Arc::clone(&self.shared.metrics),
            pool: Arc::clone(&self.shared.pool),
        })
    }

    /// The session with this ID if `secret` is its shared-memory secret, for the doorbell's
    /// hello and each of its Steps. A wrong secret gets exactly the answer of an unknown ID
    /// (the same error, the same message), compared in constant time, and does not mark the
    /// session used.
    pub fn find_shm(&self, id: &str, secret: &[u8]) -> Result<FoundSession, SessionError> {
        let key = SessionId::parse(id)?;
        let session = self
            .shard(key)
            .get(&key)
            .filter(|s| s.shm_secret.matches(secret))
            .cloned()
            .ok_or_else(|| SessionError::NotFound(id.to_owned()))?;
        session.last_used_ms.store(self.now_ms(), Ordering::Relaxed);
        Ok(FoundSession {
            session,
            metrics: Arc::clone(&self.shared.metrics),
            pool: Arc::clone(&self.shared.pool),
        })
    }

    /// The counters (the shared-memory data plane counts its refusals there as gRPC does).
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.shared.metrics
    }

    /// Resets every environment of a session of `owner`'s.
    pub fn reset(&self, owner: &Owner, id: &str, args: &ResetArgs) -> Result<Batch, SessionError> {
        self.find(owner, id)?.reset(args)
    }

    /// Steps every environment of a session of `owner`'s.
    pub fn step(&self, owner: &Owner, id: &str, actions: &[u8]) -> Result<Batch, SessionError> {
        self.find(owner, id)?.step(actions)
    }

    /// A new session of `caller`'s identical to `found`, random streams included.
    pub fn fork(
        &self,
        caller: &Caller,
        found: &FoundSession,
    ) -> Result<(SessionId, SessionSpec), SessionError> {
        let envs = found.session.lock();
        // Charged before the copy is made: a refused Fork allocates nothing.
        let charge = self.charge(&caller.tenant, envs.len())?;
        let copy = envs.clone();
        drop(envs);
        self.insert(&caller.owner, copy, charge)
    }

    /// A new session of `caller`'s from snapshot bytes.
    pub fn restore(
        &self,
        caller: &Caller,
        bytes: &[u8],
    ) -> Result<(SessionId, SessionSpec), SessionError> {
        // The tenant's share and the memory budget are charged for the environments the header
        // counts before any is decoded: a snapshot over either is refused without allocating
        // them, and the decoded ones are within the charge (given back if they do not decode).
        let max_envs = self.shared.limits.max_envs_per_session;
        let charge = self.charge(&caller.tenant, Envs::count(bytes, max_envs)?)?;
        let envs = Envs::restore(bytes, max_envs)?;
        self.insert(&caller.owner, envs, charge)
    }

    /// Closes every session idle for longer than the TTL; returns how many.
    pub fn sweep(&self) -> usize {
        let ttl = self.shared.limits.session_ttl.as_millis() as u64;
        let now = self.now_ms();
        let mut evicted = 0;
        for shard in &self.shared.shards {
            let mut shard = shard.lock().unwrap_or_else(PoisonError::into_inner);
            shard.retain(|id, session| {
                let idle = now.saturating_sub(session.last_used_ms.load(Ordering::Relaxed));
                let keep = idle <= ttl;
                if !keep {
                    let full = id.to_string();
                    let tenant = session._charge.tenant().name();
                    let session = short_id(&full);
                    tracing::info!(session, tenant, idle_ms = idle, "session expired");
                    tracing::debug!(session = %full, "session expired: full ID");
                    evicted += 1;
                }
                keep
            });
        }
        if evicted > 0 {
            self.shared.metrics.sessions_expired.inc_by(evicted as u64);
            tracing::info!(evicted, "closed idle sessions");
        }
        evicted
    }

    /// Sweeps idle sessions every quarter TTL (10 ms to 30 s) until `shutdown` fires.
    pub async fn sweep_until(self, mut shutdown: Shutdown) {
        let period = (self.shared.limits.session_ttl / 4)
            .clamp(Duration::from_millis(10), Duration::from_secs(30));
        let mut ticker = tokio::time::interval(period);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                () = shutdown.wait() => return,
                _ = ticker.tick() => {
                    // A sweep of 100,000 sessions takes milliseconds: run it off the workers.
                    let store = self.clone();
                    let _ = tokio::task::spawn_blocking(move || store.sweep()).await;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tenant() -> Arc<Tenant> {
        Arc::new(Tenant::new("test".into(), crate::budget::Share::default()))
    }

    /// A caller of the shared identity, on a connection of its own.
    fn caller() -> Caller {
        Caller::shared(tenant())
    }

    fn options() -> SessionOptions {
        SessionOptions {
            autoreset: Autoreset::NextStep,
            action_masks: false,
            expert_actions: ExpertActions::None,
        }
    }

    #[test]
    fn ids_are_32_hex_digits_and_parse_back() {
        let id = SessionId::random().unwrap();
        let text = id.to_string();
        assert_eq!(text.len(), 32);
        assert_eq!(SessionId::parse(&text), Ok(id));
        assert!(SessionId::parse("xyz").is_err());
        assert!(SessionId::parse(&format!("+{}", &text[1..])).is_err());
    }

    #[test]
    fn a_restore_over_the_share_is_refused_from_the_header_before_decoding() {
        let store = Store::new(Limits::default(), Arc::default());
        let (id, _) = store
            .create(&caller(), 3, Config::default(), options(), None)
            .unwrap();
        let bytes = store
            .find(&Owner::Shared, &id.to_string())
            .unwrap()
            .snapshot();
        let two = crate::budget::Share {
            max_envs: 2,
            ..crate::budget::Share::default()
        };
        let small = Caller::shared(Arc::new(Tenant::new("small".into(), two)));
        // Its environments cut off: refused for the share, not as undecodable (never decoded).
        let header_only = &bytes[..8];
        assert!(matches!(
            store.restore(&small, header_only),
            Err(SessionError::OverBudget(BudgetError::TenantEnvs {
                needed: 3,
                ..
            }))
        ));
        assert_eq!(small.tenant.envs(), 0);
        // Within a share, the same bytes are refused as undecodable, and nothing stays charged.
        let big = caller();
        assert!(matches!(
            store.restore(&big, header_only),
            Err(SessionError::InvalidArgument(_))
        ));
        assert_eq!(big.tenant.envs(), 0);
        assert_eq!(store.live(), 1);
        store.restore(&big, &bytes).unwrap();
        assert_eq!(big.tenant.envs(), 3);
    }

    #[test]
    fn limits_and_close() {
        let limits = Limits {
            max_sessions: 2,
            ..Limits::default()
        };
        let store = Store::new(limits, Arc::default());
        let (a, _) = store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
        store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
        assert_eq!(
            store.create(&caller(), 1, Config::default(), options(), None),
            Err(SessionError::TooManySessions(2))
        );
        store.close(&Owner::Shared, &a.to_string()).unwrap();
        assert_eq!(store.live(), 1);
        assert!(store.close(&Owner::Shared, &a.to_string()).is_err());
        store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
    }

    #[test]
    fn a_found_session_steps_without_a_second_lookup() {
        let metrics = Arc::new(Metrics::default());
        let store = Store::new(Limits::default(), Arc::clone(&metrics));
        let planner = SessionOptions {
            expert_actions: ExpertActions::Planner,
            ..options()
        };
        let (id, _) = store
            .create(&caller(), 2, Config::default(), planner, None)
            .unwrap();
        let found = store.find(&Owner::Shared, &id.to_string()).unwrap();
        assert_eq!(found.expert_actions(), ExpertActions::Planner);
        let args = ResetArgs {
            seed: Some(1),
            ..ResetArgs::default()
        };
        assert_eq!(found.reset(&args).unwrap().num_envs, 2);
        // Closed meanwhile: the request that found it still finishes its step.
        store.close(&Owner::Shared, &id.to_string()).unwrap();
        let batch = found.step(&[0; 8]).unwrap();
        assert_eq!(batch.expert_actions.len(), 2);
        assert_eq!(metrics.step_calls.get(), 1);
        assert_eq!(metrics.env_steps.get(), 2);
        assert!(matches!(
            store.find(&Owner::Shared, &id.to_string()),
            Err(SessionError::NotFound(_))
        ));
    }

    #[test]
    fn a_wrong_shm_secret_is_an_unknown_session() {
        let store = Store::new(Limits::default(), Arc::default());
        let (id, spec) = store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
        let found = store.find(&Owner::Shared, &id.to_string()).unwrap();
        let (fork, forked) = store.fork(&caller(), &found).unwrap();
        assert_ne!(
            spec.shm_secret, forked.shm_secret,
            "a fork draws its own secret"
        );
        let id = id.to_string();
        assert!(store.find_shm(&id, spec.shm_secret.expose()).is_ok());
        let refused = |id: &str, secret: &[u8]| store.find_shm(id, secret).err().unwrap();
        // Another session's secret, a wrong one, none: as an unknown ID.
        let unknown = "0".repeat(32);
        let expected = SessionError::NotFound(id.clone());
        assert_eq!(refused(&id, forked.shm_secret.expose()), expected);
        assert_eq!(refused(&id, &[0; SHM_SECRET_BYTES]), expected);
        assert_eq!(refused(&id, &[]), expected);
        assert_eq!(
            refused(&unknown, spec.shm_secret.expose()),
            SessionError::NotFound(unknown.clone())
        );
        assert!(
            store
                .find_shm(&fork.to_string(), forked.shm_secret.expose())
                .is_ok()
        );
    }

    #[test]
    fn sweep_evicts_only_idle_sessions() {
        let limits = Limits {
            session_ttl: Duration::ZERO,
            ..Limits::default()
        };
        let store = Store::new(limits, Arc::default());
        let (id, _) = store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(store.sweep(), 1);
        assert_eq!(store.live(), 0);
        assert!(matches!(
            store.step(&Owner::Shared, &id.to_string(), &[0; 4]),
            Err(SessionError::NotFound(_))
        ));
    }

    /// A session of another owner is found, closed, forked, stepped and snapshotted exactly as
    /// an unknown ID is (the same error, message included), and is left as it was.
    #[test]
    fn another_owners_session_is_an_unknown_id() {
        let store = Store::new(Limits::default(), Arc::default());
        let a = Caller::tenant(tenant());
        let b = Caller::tenant(tenant());
        let (id, _) = store
            .create(&a, 2, Config::default(), options(), Some(9))
            .unwrap();
        let (twin, _) = store
            .create(&a, 2, Config::default(), options(), Some(9))
            .unwrap();
        let (id, twin) = (id.to_string(), twin.to_string());
        let args = ResetArgs::default();
        store.reset(&a.owner, &id, &args).unwrap();
        store.reset(&a.owner, &twin, &args).unwrap();
        let key = SessionId::parse(&id).unwrap();
        let session = Arc::clone(&store.shard(key)[&key]);
        session.last_used_ms.store(0, Ordering::Relaxed);
        let unknown = "0123456789abcdef0123456789abcdef";
        for asked in [id.as_str(), unknown] {
            let not_found = Err(SessionError::NotFound(asked.to_owned()));
            assert_eq!(store.reset(&b.owner, asked, &args).map(|_| ()), not_found);
            assert_eq!(store.step(&b.owner, asked, &[0; 8]).map(|_| ()), not_found);
            assert_eq!(store.find(&b.owner, asked).map(|_| ()), not_found);
            assert_eq!(store.close(&b.owner, asked), not_found);
            assert_eq!(store.find(&Owner::Shared, asked).map(|_| ()), not_found);
            assert_eq!(store.watch(&b.owner, asked, 0).map(|_| ()), not_found);
        }
        assert_eq!(store.live(), 2);
        // Nothing about it was touched: not even when it was last used.
        assert_eq!(session.last_used_ms.load(Ordering::Relaxed), 0);
        drop(session);
        assert_eq!(store.summaries(&a.owner, 10).rows.len(), 2);
        assert!(store.summaries(&b.owner, 10).rows.is_empty());
        // Still the owner's, and exactly as its twin.
        let stepped = store.step(&a.owner, &id, &[0; 8]).unwrap();
        let twin_stepped = store.step(&a.owner, &twin, &[0; 8]).unwrap();
        assert_eq!(stepped.observations, twin_stepped.observations);
        assert_eq!(stepped.rewards, twin_stepped.rewards);
        // Forks and restores belong to whoever makes them.
        let found = store.find(&a.owner, &id).unwrap();
        let (fork, _) = store.fork(&b, &found).unwrap();
        let (restored, _) = store.restore(&b, &found.snapshot()).unwrap();
        for made in [fork.to_string(), restored.to_string()] {
            assert!(store.find(&b.owner, &made).is_ok());
            assert_eq!(
                store.find(&a.owner, &made).map(|_| ()),
                Err(SessionError::NotFound(made.clone()))
            );
        }
        assert_eq!(store.summaries(&b.owner, 10).rows.len(), 2);
        // The shared identity is one identity, whatever share its sessions count against.
        let (shared, _) = store
            .create(&caller(), 1, Config::default(), options(), None)
            .unwrap();
        let other_connection = Caller::shared(tenant());
        assert!(
            store
                .find(&other_connection.owner, &shared.to_string())
                .is_ok()
        );
        assert!(store.find(&a.owner, &shared.to_string()).is_err());
        store.close(&Owner::Shared, &shared.to_string()).unwrap();
    }
}
