//! Counters of what the server did, and their Prometheus text format ([`Metrics::render`]);
//! [`crate::http`] serves them at `/metrics`.
//!
//! Counters are plain atomics bumped on the hot path (relaxed: they are statistics, not
//! synchronisation); nothing here allocates per step. Some double as the memory budget's
//! accounting, which takes from them with compare-and-swap ([`crate::budget`]), so they stay
//! atomics of our own: at a scrape, one reading of them is handed to a `prometheus-client`
//! registry as a collector, and the crate writes the exposition format.

use std::sync::atomic::{AtomicU64, Ordering};

use prometheus_client::collector::Collector;
use prometheus_client::encoding::prometheus_text;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;

/// The `Content-Type` of [`Metrics::render`]'s text: Prometheus' text format, version 0.0.4.
pub const CONTENT_TYPE: &str = prometheus_text::CONTENT_TYPE;

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

    /// The counters in Prometheus' text exposition format (version 0.0.4, [`CONTENT_TYPE`]),
    /// encoded by `prometheus-client` from one reading of every counter.
    pub fn render(&self) -> String {
        let mut registry = Registry::default();
        registry.register_collector(Box::new(self.reading()));
        let mut out = String::with_capacity(4096);
        // Writing to a String cannot fail.
        let _ = prometheus_text::encode(&mut out, &registry);
        out
    }

    /// Every counter's value now.
    fn reading(&self) -> Reading {
        let read = |(name, help, value): (&'static str, &'static str, &AtomicU64)| {
            (name, help, value.load(Ordering::Relaxed))
        };
        let counters = [
            (
                "dinerdash_sessions_created",
                "Sessions created by CreateSession, Fork and Restore.",
                &self.sessions_created,
            ),
            (
                "dinerdash_sessions_closed",
                "Sessions closed by CloseSession.",
                &self.sessions_closed,
            ),
            (
                "dinerdash_sessions_expired",
                "Sessions evicted after being idle longer than the TTL.",
                &self.sessions_expired,
            ),
            (
                "dinerdash_step_calls",
                "Step RPCs that succeeded.",
                &self.step_calls,
            ),
            (
                "dinerdash_env_steps",
                "Environment steps (a Step of N environments counts N).",
                &self.env_steps,
            ),
            (
                "dinerdash_env_resets",
                "Environment resets, by Reset and by autoreset.",
                &self.env_resets,
            ),
            (
                "dinerdash_rollout_episodes",
                "Episodes recorded by Rollout.",
                &self.rollout_episodes,
            ),
            (
                "dinerdash_connections_shed",
                "Connections closed at the connection limit to admit a new one.",
                &self.connections_shed,
            ),
            (
                "dinerdash_connections_without_preface",
                "Connections closed for not sending the HTTP/2 preface in time.",
                &self.connections_without_preface,
            ),
            (
                "dinerdash_connections_idle_closed",
                "Connections closed for being silent longer than --idle-timeout.",
                &self.connections_idle_closed,
            ),
        ]
        .map(read);
        let gauges = [
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
        ]
        .map(read);
        Reading {
            counters,
            gauges,
            rpc_errors: std::array::from_fn(|code| self.rpc_errors[code].load(Ordering::Relaxed)),
        }
    }
}

/// One reading of every counter: name (counters without their `_total`, which the encoder
/// adds), help, value. What the registry encodes at a scrape.
#[derive(Debug)]
struct Reading {
    /// The counters.
    counters: [(&'static str, &'static str, u64); 10],
    /// The gauges.
    gauges: [(&'static str, &'static str, u64); 6],
    /// Failed RPCs by status code.
    rpc_errors: [u64; 17],
}

impl Collector for Reading {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        for &(name, help, value) in &self.counters {
            let metric = encoder.encode_descriptor(name, help, None, MetricType::Counter)?;
            ConstCounter::new(value).encode(metric)?;
        }
        for &(name, help, value) in &self.gauges {
            let metric = encoder.encode_descriptor(name, help, None, MetricType::Gauge)?;
            ConstGauge::new(value).encode(metric)?;
        }
        let mut family = encoder.encode_descriptor(
            "dinerdash_rpc_errors",
            "RPCs that failed, by gRPC status code.",
            None,
            MetricType::Counter,
        )?;
        // Codes that never failed are left out, as a labelled counter that was never touched.
        for (name, &value) in CODE_NAMES.iter().zip(&self.rpc_errors) {
            if value > 0 {
                let labels = [("code", *name)];
                ConstCounter::new(value).encode(family.encode_family(&labels)?)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scrape_keeps_the_names_types_and_labels() {
        let metrics = Metrics::default();
        metrics.env_steps.fetch_add(7, Ordering::Relaxed);
        metrics.live_sessions.fetch_add(2, Ordering::Relaxed);
        metrics.count_error(5);
        metrics.count_error(5);
        metrics.count_error(99);
        let text = metrics.render();
        for line in [
            "# HELP dinerdash_env_steps_total Environment steps (a Step of N environments counts N).",
            "# TYPE dinerdash_env_steps_total counter",
            "dinerdash_env_steps_total 7",
            "# TYPE dinerdash_live_sessions gauge",
            "dinerdash_live_sessions 2",
            "# HELP dinerdash_rpc_errors_total RPCs that failed, by gRPC status code.",
            "# TYPE dinerdash_rpc_errors_total counter",
            "dinerdash_rpc_errors_total{code=\"NOT_FOUND\"} 2",
            "dinerdash_rpc_errors_total{code=\"UNKNOWN\"} 1",
        ] {
            assert!(text.lines().any(|l| l == line), "no {line:?} in\n{text}");
        }
        assert!(!text.contains("code=\"OK\""), "{text}");
        assert_eq!(text.matches("# TYPE ").count(), 17);
    }
}
