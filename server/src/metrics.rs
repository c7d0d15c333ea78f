//! Counters of what the server did, and their Prometheus text format ([`Metrics::render`]);
//! [`crate::http`] serves them at `/metrics`.
//!
//! Counters are plain atomics bumped on the hot path (relaxed: they are statistics, not
//! synchronisation); nothing here allocates per step.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};

/// gRPC status code names, indexed by code number, for the error counter's label.
const CODE_NAMES: [&str; 17] = [
    "OK",
    "CANCELLED",
    "UNKNOWN",
    "INVALID_ARGUMENT",
    "DEADLINE_EXCEEDED",
    "NOT_FOUND",
    "ALREADY_EXISTS",
    "PERMISSION_DENIED",
    "RESOURCE_EXHAUSTED",
    "FAILED_PRECONDITION",
    "ABORTED",
    "OUT_OF_RANGE",
    "UNIMPLEMENTED",
    "INTERNAL",
    "UNAVAILABLE",
    "DATA_LOSS",
    "UNAUTHENTICATED",
];

/// The server's counters. Shared by the session store, the service and the responder.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Sessions created by CreateSession, Fork and Restore.
    pub sessions_created: AtomicU64,
    /// Sessions closed by CloseSession.
    pub sessions_closed: AtomicU64,
    /// Sessions evicted for being idle longer than the TTL.
    pub sessions_expired: AtomicU64,
    /// Live sessions right now: the one counter the session limit is checked against
    /// (the memory budget keeps it).
    pub live_sessions: AtomicU64,
    /// Bytes sessions and Rollout streams hold now, as the memory budget counts them.
    pub memory_used_bytes: AtomicU64,
    /// The memory budget, `--max-memory`.
    pub memory_budget_bytes: AtomicU64,
    /// Rollout streams running now.
    pub live_rollouts: AtomicU64,
    /// Connections open now.
    pub open_connections: AtomicU64,
    /// Connections accepted over the connection limit, open now (answered RESOURCE_EXHAUSTED).
    pub over_limit_connections: AtomicU64,
    /// Connections closed at the connection limit to admit a new one (shed).
    pub connections_shed: AtomicU64,
    /// Connections closed for not sending the HTTP/2 preface in time.
    pub connections_without_preface: AtomicU64,
    /// Connections closed for being silent longer than `--idle-timeout`.
    pub connections_idle_closed: AtomicU64,
    /// Step RPCs that succeeded.
    pub step_calls: AtomicU64,
    /// Environment steps: a Step of N environments counts N.
    pub env_steps: AtomicU64,
    /// Environment resets, by Reset and by autoreset.
    pub env_resets: AtomicU64,
    /// Episodes recorded by Rollout.
    pub rollout_episodes: AtomicU64,
    /// RPCs that failed, by gRPC status code.
    pub rpc_errors: [AtomicU64; 17],
}

impl Metrics {
    /// Counts one failed RPC with gRPC status code `code` (0..=16; others count as UNKNOWN).
    pub fn count_error(&self, code: usize) {
        let code = if code < CODE_NAMES.len() { code } else { 2 };
        self.rpc_errors[code].fetch_add(1, Ordering::Relaxed);
    }

    /// The counters in Prometheus' text exposition format.
    pub fn render(&self) -> String {
        let mut out = String::with_capacity(2048);
        let counters: [(&str, &str, &AtomicU64); 10] = [
            (
                "dinerdash_sessions_created_total",
                "Sessions created by CreateSession, Fork and Restore.",
                &self.sessions_created,
            ),
            (
                "dinerdash_sessions_closed_total",
                "Sessions closed by CloseSession.",
                &self.sessions_closed,
            ),
            (
                "dinerdash_sessions_expired_total",
                "Sessions evicted after being idle longer than the TTL.",
                &self.sessions_expired,
            ),
            (
                "dinerdash_step_calls_total",
                "Step RPCs that succeeded.",
                &self.step_calls,
            ),
            (
                "dinerdash_env_steps_total",
                "Environment steps (a Step of N environments counts N).",
                &self.env_steps,
            ),
            (
                "dinerdash_env_resets_total",
                "Environment resets, by Reset and by autoreset.",
                &self.env_resets,
            ),
            (
                "dinerdash_rollout_episodes_total",
                "Episodes recorded by Rollout.",
                &self.rollout_episodes,
            ),
            (
                "dinerdash_connections_shed_total",
                "Connections closed at the connection limit to admit a new one.",
                &self.connections_shed,
            ),
            (
                "dinerdash_connections_without_preface_total",
                "Connections closed for not sending the HTTP/2 preface in time.",
                &self.connections_without_preface,
            ),
            (
                "dinerdash_connections_idle_closed_total",
                "Connections closed for being silent longer than --idle-timeout.",
                &self.connections_idle_closed,
            ),
        ];
        for (name, help, value) in counters {
            let _ = writeln!(out, "# HELP {name} {help}");
            let _ = writeln!(out, "# TYPE {name} counter");
            let _ = writeln!(out, "{name} {}", value.load(Ordering::Relaxed));
        }
        let gauges: [(&str, &str, &AtomicU64); 6] = [
            (
                "dinerdash_live_sessions",
                "Sessions alive now.",
                &self.live_sessions,
            ),
            (
                "dinerdash_memory_used_bytes",
                "Bytes sessions and Rollout streams hold now, as the memory budget counts them.",
                &self.memory_used_bytes,
            ),
            (
                "dinerdash_memory_budget_bytes",
                "The memory budget (--max-memory).",
                &self.memory_budget_bytes,
            ),
            (
                "dinerdash_live_rollouts",
                "Rollout streams running now.",
                &self.live_rollouts,
            ),
            (
                "dinerdash_open_connections",
                "Client connections open now.",
                &self.open_connections,
            ),
            (
                "dinerdash_over_limit_connections",
                "Connections over the connection limit open now, answered RESOURCE_EXHAUSTED.",
                &self.over_limit_connections,
            ),
        ];
        for (name, help, value) in gauges {
            let _ = writeln!(out, "# HELP {name} {help}");
            let _ = writeln!(out, "# TYPE {name} gauge");
            let _ = writeln!(out, "{name} {}", value.load(Ordering::Relaxed));
        }
        let _ = writeln!(
            out,
            "# HELP dinerdash_rpc_errors_total RPCs that failed, by gRPC status code."
        );
        let _ = writeln!(out, "# TYPE dinerdash_rpc_errors_total counter");
        for (name, value) in CODE_NAMES.iter().zip(&self.rpc_errors) {
            let value = value.load(Ordering::Relaxed);
            if value > 0 {
                let _ = writeln!(out, "dinerdash_rpc_errors_total{{code=\"{name}\"}} {value}");
            }
        }
        out
    }
}
