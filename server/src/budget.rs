//! What clients may hold: the server's memory budget (`--max-memory`) and each tenant's share of
//! it. A tenant is one line of `--auth-tokens-file`, the shared token (all its connections
//! together), or, on a server without any token, one connection, so that a single buggy worker
//! cannot take every session slot or every byte.
//!
//! Everything is charged before it is allocated: a session its environments' bytes, a Rollout
//! stream the episodes it may buffer; and, against a bound of their own beside `--max-memory`
//! (a quarter of it, at least 64 MiB), a large request the bytes it costs while it is received
//! and decoded (`codec::intake`). A [`Charge`] gives its bytes and slots back when it is
//! dropped (the session closed or expired, the stream ended), so the counters can never drift
//! from what is held. The live-session and memory counters are the metrics' gauges themselves:
//! one counter each, not a copy kept in lockstep.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use crate::metrics::Metrics;

/// Default `--max-memory`: what sessions and Rollout streams may hold. Measured RSS is about
/// 1.1x the accounted bytes plus ~20 MiB of runtime (docs/operations.md, "Memory budget"), so
/// one server stays under ~2 GiB whatever clients do.
pub const DEFAULT_MAX_MEMORY: u64 = 1 << 30;
/// Requests being received and decoded may hold `--max-memory / INTAKE_SHARE` bytes besides
/// `--max-memory` (`codec::intake`), and at least [`MIN_INTAKE_BYTES`].
pub const INTAKE_SHARE: u64 = 4;
/// Least bytes requests being received may hold: room for a few of the largest legitimate
/// requests (a Restore of 1024 environments is charged ~34 MiB) whatever `--max-memory` is.
pub const MIN_INTAKE_BYTES: u64 = 64 << 20;
/// Default share of one tenant (or connection): environments it may hold at once.
pub const DEFAULT_TENANT_ENVS: u64 = 65_536;
/// Default share of one tenant (or connection): Rollout streams it may run at once.
pub const DEFAULT_TENANT_ROLLOUTS: u64 = 4;

/// What one tenant may hold at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Share {
    /// Environments over all its sessions.
    pub max_envs: u64,
    /// Sessions.
    pub max_sessions: u64,
    /// Rollout streams running at once.
    pub max_rollouts: u64,
    /// Connections it may hold at once: a connection is its from its first authenticated call
    /// (`connections::calls`).
    pub max_connections: u64,
    /// Calls it may have open at once (unary calls and streams, over all its connections).
    pub max_streams: u64,
}

impl Default for Share {
    fn default() -> Self {
        Share {
            max_envs: DEFAULT_TENANT_ENVS,
            max_sessions: u64::MAX,
            max_rollouts: DEFAULT_TENANT_ROLLOUTS,
            max_connections: u64::MAX,
            max_streams: u64::MAX,
        }
    }
}

/// Why a request was refused for want of room. Every variant is `RESOURCE_EXHAUSTED`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BudgetError {
    /// The server holds its maximum number of sessions.
    #[error("the server holds its maximum of {0} sessions; close one or raise --max-sessions")]
    Sessions(u64),
    /// The memory budget would be passed.
    #[error(
        "the server's memory budget is spent: this needs {needed} bytes and {used} of {max} are \
         held; close sessions or raise --max-memory"
    )]
    Memory {
        /// Bytes the request needs.
        needed: u64,
        /// Bytes held now.
        used: u64,
        /// The budget.
        max: u64,
    },
    /// The tenant (or connection) would pass its share of environments.
    #[error(
        "{tenant} holds {held} environments and may hold {max}; this needs {needed} more: close \
         sessions"
    )]
    TenantEnvs {
        /// Who.
        tenant: String,
        /// Environments held now.
        held: u64,
        /// The share.
        max: u64,
        /// Environments the request needs.
        needed: u64,
    },
    /// The tenant (or connection) holds its share of sessions.
    #[error("{tenant} holds its maximum of {max} sessions; close one")]
    TenantSessions {
        /// Who.
        tenant: String,
        /// The share.
        max: u64,
    },
    /// The tenant (or connection) runs its share of Rollout streams.
    #[error("{tenant} already runs its maximum of {max} Rollout streams; read or cancel one")]
    TenantRollouts {
        /// Who.
        tenant: String,
        /// The share.
        max: u64,
    },
}

/// One tenant: a name for messages and logs, its share, and what it holds now.
#[derive(Debug)]
pub struct Tenant {
    /// "tenant NAME" or "connection ADDRESS".
    name: String,
    /// What it may hold: a tenants file read again (SIGHUP) may change it.
    share: Mutex<Share>,
    /// Environments held.
    envs: AtomicU64,
    /// Sessions held.
    sessions: AtomicU64,
    /// Rollout streams running.
    rollouts: AtomicU64,
    /// Connections it holds.
    connections: AtomicU64,
    /// Calls it has open.
    streams: AtomicU64,
    /// Its share's `max_streams`, read without the share's lock on every call.
    max_streams: AtomicU64,
}

impl Tenant {
    /// A tenant holding nothing yet. `name` is how messages refer to it.
    pub fn new(name: String, share: Share) -> Tenant {
        Tenant {
            name,
            share: Mutex::new(share),
            envs: AtomicU64::new(0),
            sessions: AtomicU64::new(0),
            rollouts: AtomicU64::new(0),
            connections: AtomicU64::new(0),
            streams: AtomicU64::new(0),
            max_streams: AtomicU64::new(share.max_streams),
        }
    }

    /// How messages refer to it.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// What it may hold now.
    pub fn share(&self) -> Share {
        *self.share.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Changes what it may hold from now on (what it holds stays held).
    pub fn set_share(&self, share: Share) {
        let mut held = self.share.lock().unwrap_or_else(PoisonError::into_inner);
        *held = share;
        self.max_streams.store(share.max_streams, Ordering::Relaxed);
    }

    /// Sessions it holds now.
    pub fn sessions(&self) -> u64 {
        self.sessions.load(Ordering::Relaxed)
    }

    /// Environments it holds now.
    pub fn envs(&self) -> u64 {
        self.envs.load(Ordering::Relaxed)
    }

    /// Counts one more connection of its, unless it holds its `max_connections`; refused, says
    /// how many it holds and may hold.
    pub fn take_connection(self: &Arc<Self>) -> Result<Held, (u64, u64)> {
        let max = self.share().max_connections;
        take(&self.connections, 1, max).map_err(|held| (held, max))?;
        Ok(Held {
            tenant: Arc::clone(self),
            what: HeldKind::Connection,
        })
    }

    /// Counts one more open call of its, unless it has its `max_streams` open; refused, says
    /// how many it has open and may have.
    pub fn take_stream(self: &Arc<Self>) -> Result<Held, (u64, u64)> {
        let max = self.max_streams.load(Ordering::Relaxed);
        take(&self.streams, 1, max).map_err(|held| (held, max))?;
        Ok(Held {
            tenant: Arc::clone(self),
            what: HeldKind::Stream,
        })
    }

    /// Connections it holds now.
    pub fn connections(&self) -> u64 {
        self.connections.load(Ordering::Relaxed)
    }

    /// Calls it has open now.
    pub fn streams(&self) -> u64 {
        self.streams.load(Ordering::Relaxed)
    }
}

/// The share the shared token's requests count against (a request extension the request gate,
/// `auth::RequestGate`, adds): one for all its connections.
#[derive(Debug, Clone)]
pub struct SharedShare(pub Arc<Tenant>);

/// Which counter a [`Held`] counts in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HeldKind {
    /// [`Tenant::take_connection`].
    Connection,
    /// [`Tenant::take_stream`].
    Stream,
}

/// A connection or an open call counted against a tenant's share; given back when dropped.
#[derive(Debug)]
pub struct Held {
    /// Whose.
    tenant: Arc<Tenant>,
    /// Which counter.
    what: HeldKind,
}

impl Held {
    /// Whose share it counts against.
    pub fn tenant(&self) -> &Arc<Tenant> {
        &self.tenant
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        let counter = match self.what {
            HeldKind::Connection => &self.tenant.connections,
            HeldKind::Stream => &self.tenant.streams,
        };
        give(counter, 1);
    }
}

/// The intake bound of a server of `--max-memory` `max_bytes`: a quarter of it, at least
/// [`MIN_INTAKE_BYTES`].
pub fn intake_bound(max_bytes: u64) -> u64 {
    (max_bytes / INTAKE_SHARE).max(MIN_INTAKE_BYTES)
}

/// Adds `n` to `counter` unless that passes `max`; on refusal returns what it holds.
fn take(counter: &AtomicU64, n: u64, max: u64) -> Result<(), u64> {
    counter
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
            held.checked_add(n).filter(|&after| after <= max)
        })
        .map(drop)
}

fn give(counter: &AtomicU64, n: u64) {
    counter.fetch_sub(n, Ordering::AcqRel);
}

/// The server-wide limits and the gauges that count against them.
#[derive(Debug)]
pub struct Budget {
    /// `--max-memory`.
    max_bytes: u64,
    /// `--max-sessions`.
    max_sessions: u64,
    /// Holds the live-session and memory gauges this budget counts with.
    metrics: Arc<Metrics>,
    /// Bytes held by requests being received and decoded: a bound of their own beside
    /// `--max-memory` ([`Budget::max_intake_bytes`]), so that a burst of large requests never
    /// refuses a session and a full budget never refuses a legitimate large request.
    intake_used: AtomicU64,
}

/// What a [`Charge`] holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Holding {
    /// A session of this many environments.
    Session { envs: u64 },
    /// A Rollout stream.
    Rollout,
    /// A shared-memory region (bytes only).
    Region,
}

/// Bytes and slots held for a session or a Rollout stream; given back when dropped.
#[derive(Debug)]
pub struct Charge {
    /// Where the bytes are counted.
    budget: Arc<Budget>,
    /// Whose share it counts against.
    tenant: Arc<Tenant>,
    /// What it holds.
    holding: Holding,
    /// Bytes counted in the budget.
    bytes: u64,
}

impl Charge {
    /// Whose share it counts against.
    pub fn tenant(&self) -> &Arc<Tenant> {
        &self.tenant
    }
}

impl Drop for Charge {
    fn drop(&mut self) {
        let m = &self.budget.metrics;
        give(m.memory_used_bytes.inner(), self.bytes);
        match self.holding {
            Holding::Session { envs } => {
                give(m.live_sessions.inner(), 1);
                give(&self.tenant.sessions, 1);
                give(&self.tenant.envs, envs);
            }
            Holding::Rollout => {
                give(m.live_rollouts.inner(), 1);
                give(&self.tenant.rollouts, 1);
            }
            Holding::Region => {}
        }
    }
}

impl Budget {
    /// A budget of `max_bytes` and `max_sessions`, counted in `metrics`' gauges.
    pub fn new(max_bytes: u64, max_sessions: u64, metrics: Arc<Metrics>) -> Budget {
        metrics.memory_budget_bytes.set(max_bytes);
        Budget {
            max_bytes,
            max_sessions,
            metrics,
            intake_used: AtomicU64::new(0),
        }
    }

    /// `--max-memory`.
    pub fn max_bytes(&self) -> u64 {
        self.max_bytes
    }

    /// Bytes held now.
    pub fn used_bytes(&self) -> u64 {
        self.metrics.memory_used_bytes.get()
    }

    /// The metrics its gauges are.
    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// Live sessions.
    pub fn live_sessions(&self) -> u64 {
        self.metrics.live_sessions.get()
    }

    fn take_bytes(&self, bytes: u64) -> Result<(), BudgetError> {
        take(
            self.metrics.memory_used_bytes.inner(),
            bytes,
            self.max_bytes,
        )
        .map_err(|used| BudgetError::Memory {
            needed: bytes,
            used,
            max: self.max_bytes,
        })
    }

    /// Charges a session of `envs` environments of `bytes` to `tenant`, or refuses it.
    pub fn charge_session(
        self: &Arc<Self>,
        tenant: &Arc<Tenant>,
        envs: u64,
        bytes: u64,
    ) -> Result<Charge, BudgetError> {
        let (share, m) = (tenant.share(), &self.metrics);
        take(m.live_sessions.inner(), 1, self.max_sessions)
            .map_err(|_| BudgetError::Sessions(self.max_sessions))?;
        if take(&tenant.sessions, 1, share.max_sessions).is_err() {
            give(m.live_sessions.inner(), 1);
            return Err(BudgetError::TenantSessions {
                tenant: tenant.name.clone(),
                max: share.max_sessions,
            });
        }
        if let Err(held) = take(&tenant.envs, envs, share.max_envs) {
            give(m.live_sessions.inner(), 1);
            give(&tenant.sessions, 1);
            return Err(BudgetError::TenantEnvs {
                tenant: tenant.name.clone(),
                held,
                max: share.max_envs,
                needed: envs,
            });
        }
        if let Err(e) = self.take_bytes(bytes) {
            give(m.live_sessions.inner(), 1);
            give(&tenant.sessions, 1);
            give(&tenant.envs, envs);
            return Err(e);
        }
        Ok(Charge {
            budget: Arc::clone(self),
            tenant: Arc::clone(tenant),
            holding: Holding::Session { envs },
            bytes,
        })
    }

    /// Charges a session's shared-memory region of `bytes` to `tenant`, or refuses it.
    pub fn charge_region(
        self: &Arc<Self>,
        tenant: &Arc<Tenant>,
        bytes: u64,
    ) -> Result<Charge, BudgetError> {
        self.take_bytes(bytes)?;
        Ok(Charge {
            budget: Arc::clone(self),
            tenant: Arc::clone(tenant),
            holding: Holding::Region,
            bytes,
        })
    }

    /// Charges a Rollout stream that may buffer `bytes` to `tenant`, or refuses it.
    pub fn charge_rollout(
        self: &Arc<Self>,
        tenant: &Arc<Tenant>,
        bytes: u64,
    ) -> Result<Charge, BudgetError> {
        let max = tenant.share().max_rollouts;
        take(&tenant.rollouts, 1, max).map_err(|_| BudgetError::TenantRollouts {
            tenant: tenant.name.clone(),
            max,
        })?;
        if let Err(e) = self.take_bytes(bytes) {
            give(&tenant.rollouts, 1);
            return Err(e);
        }
        self.metrics
            .live_rollouts
            .inner()
            .fetch_add(1, Ordering::AcqRel);
        Ok(Charge {
            budget: Arc::clone(self),
            tenant: Arc::clone(tenant),
            holding: Holding::Rollout,
            bytes,
        })
    }
}

/// Bytes held for one message being received and handled (`codec::intake`); given back when
/// dropped.
#[derive(Debug)]
pub struct IntakeCharge {
    /// Where the bytes are counted.
    budget: Arc<Budget>,
    /// Bytes counted.
    bytes: u64,
}

impl Drop for IntakeCharge {
    fn drop(&mut self) {
        give(&self.budget.intake_used, self.bytes);
    }
}

/// A message refused because the requests being received already hold their bound.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "requests being received hold {used} of the {max} bytes they may (a quarter of --max-memory, \
     at least 64 MiB), and this one needs {needed}: retry later, send smaller requests or raise \
     --max-memory"
)]
pub struct IntakeRefused {
    /// Bytes the message needs.
    pub needed: u64,
    /// Bytes held by requests being received now.
    pub used: u64,
    /// Their bound.
    pub max: u64,
}

impl Budget {
    /// Bytes requests being received and decoded may hold: a quarter of `--max-memory`, at
    /// least [`MIN_INTAKE_BYTES`].
    pub fn max_intake_bytes(&self) -> u64 {
        intake_bound(self.max_bytes)
    }

    /// Bytes requests being received and decoded hold now.
    pub fn intake_bytes(&self) -> u64 {
        self.intake_used.load(Ordering::Relaxed)
    }

    /// Charges a message being received and handled with `bytes`, or refuses it.
    pub fn charge_intake(self: &Arc<Self>, bytes: u64) -> Result<IntakeCharge, IntakeRefused> {
        let max = self.max_intake_bytes();
        take(&self.intake_used, bytes, max).map_err(|used| IntakeRefused {
            needed: bytes,
            used,
            max,
        })?;
        Ok(IntakeCharge {
            budget: Arc::clone(self),
            bytes,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charges_are_refused_before_a_limit_and_given_back_on_drop() {
        let metrics = Arc::new(Metrics::default());
        let budget = Arc::new(Budget::new(1000, 3, Arc::clone(&metrics)));
        let share = Share {
            max_envs: 10,
            max_sessions: 2,
            max_rollouts: 1,
            ..Share::default()
        };
        let tenant = Arc::new(Tenant::new("connection a".into(), share));
        let a = budget.charge_session(&tenant, 4, 400).unwrap();
        assert_eq!(
            budget.charge_session(&tenant, 7, 10).unwrap_err(),
            BudgetError::TenantEnvs {
                tenant: "connection a".into(),
                held: 4,
                max: 10,
                needed: 7
            }
        );
        assert!(matches!(
            budget.charge_session(&tenant, 1, 700),
            Err(BudgetError::Memory {
                needed: 700,
                used: 400,
                max: 1000
            })
        ));
        let b = budget.charge_session(&tenant, 6, 600).unwrap();
        assert_eq!(budget.used_bytes(), 1000);
        let other = Arc::new(Tenant::new("connection b".into(), share));
        assert!(matches!(
            budget.charge_rollout(&other, 1),
            Err(BudgetError::Memory { .. })
        ));
        drop(b);
        assert!(matches!(
            budget.charge_session(&tenant, 1, 1).map(drop),
            Ok(())
        ));
        let r = budget.charge_rollout(&other, 100).unwrap();
        assert!(matches!(
            budget.charge_rollout(&other, 1),
            Err(BudgetError::TenantRollouts { max: 1, .. })
        ));
        drop((a, r));
        assert_eq!((budget.used_bytes(), budget.live_sessions()), (0, 0));
        assert_eq!(tenant.envs(), 0);
        assert_eq!(metrics.live_rollouts.get(), 0);
    }
}
