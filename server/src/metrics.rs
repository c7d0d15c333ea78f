//! What the server did, as `prometheus-client` metrics, and their Prometheus text format
//! ([`Metrics::render`]); [`crate::http`] serves them at `/metrics`.
//!
//! Each metric is declared once, in the `metrics!` list below: its field, its type, its
//! Prometheus name and help. The list makes the struct and registers every field's handle with
//! the registry [`Metrics::render`] encodes, in the order listed (the order of `/metrics`). The
//! handles are `prometheus-client`'s own types: [`Counter`], [`Gauge`] and [`Family`]s of
//! counters labelled by gRPC status code ([`CodeLabel`]) and by the limit that refused
//! ([`ReasonLabel`]). Cloning a handle shares its atomic,
//! so what the registry reads is what the server bumped: there is no second copy.
//!
//! Counters and gauges are single atomics bumped on the hot path (relaxed: statistics, not
//! synchronisation); nothing here allocates per step. The memory budget counts with the
//! gauges themselves ([`crate::budget`]): it takes from `live_sessions` and `memory_used_bytes`
//! with compare-and-swap on the gauge's own atomic ([`Gauge::inner`]) and keeps
//! `live_rollouts`, which is why the gauges ([`Level`]) are `u64` over an [`AtomicU64`]; the
//! connections count `open_connections` and `over_limit_connections` the same way.

use std::sync::atomic::AtomicU64;

use prometheus_client::encoding::prometheus_text;
use prometheus_client::encoding::{EncodeLabelSet, EncodeLabelValue, LabelValueEncoder};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

/// The `Content-Type` of [`Metrics::render`]'s text: Prometheus' text format, version 0.0.4.
pub const CONTENT_TYPE: &str = prometheus_text::CONTENT_TYPE;

/// A level that goes up and down, never below zero: what the budget takes from and gives back.
pub type Level = Gauge<u64, AtomicU64>;

/// The label of [`Metrics::rpc_errors`]: `code="NOT_FOUND"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, EncodeLabelSet)]
pub struct CodeLabel {
    /// The gRPC status code the RPC failed with.
    pub code: GrpcCode,
}

/// A gRPC status code as a label value: its name in the gRPC specification (`NOT_FOUND`), as
/// `grpc-status` documents it and clients print it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct GrpcCode(pub tonic::Code);

impl GrpcCode {
    /// The code's name in the gRPC specification. tonic spells its variants in Rust's case; the
    /// match is exhaustive, so a code tonic added would not compile until it is named here.
    pub fn name(self) -> &'static str {
        use tonic::Code;
        match self.0 {
            Code::Ok => "OK",
            Code::Cancelled => "CANCELLED",
            Code::Unknown => "UNKNOWN",
            Code::InvalidArgument => "INVALID_ARGUMENT",
            Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
            Code::NotFound => "NOT_FOUND",
            Code::AlreadyExists => "ALREADY_EXISTS",
            Code::PermissionDenied => "PERMISSION_DENIED",
            Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
            Code::FailedPrecondition => "FAILED_PRECONDITION",
            Code::Aborted => "ABORTED",
            Code::OutOfRange => "OUT_OF_RANGE",
            Code::Unimplemented => "UNIMPLEMENTED",
            Code::Internal => "INTERNAL",
            Code::Unavailable => "UNAVAILABLE",
            Code::DataLoss => "DATA_LOSS",
            Code::Unauthenticated => "UNAUTHENTICATED",
        }
    }
}

impl EncodeLabelValue for GrpcCode {
    fn encode(&self, encoder: &mut LabelValueEncoder) -> Result<(), std::fmt::Error> {
        std::fmt::Write::write_str(encoder, self.name())
    }
}

/// The label of [`Metrics::refusals`]: `reason="streams_quota"`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, EncodeLabelSet)]
pub struct ReasonLabel {
    /// Which limit refused.
    pub reason: Refusal,
}

/// A limit that refused a call or closed a connection, as [`Metrics::refusals`] counts it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Refusal {
    /// A tenant's first call on a connection over its `connections` quota.
    ConnectionsQuota,
    /// A call over its identity's `streams` quota.
    StreamsQuota,
    /// A call over what a server without tokens lets be open at once.
    CallsOpen,
    /// A call whose charge the intake bound could not take.
    Intake,
    /// A call outside the DinerDash service over their caps (in all, or from one address).
    ProbeCalls,
    /// A connection without an authenticated call closed for its address's cap
    /// (`--max-connections-per-address`).
    AddressCap,
}

impl Refusal {
    /// The label value.
    pub fn name(self) -> &'static str {
        match self {
            Refusal::ConnectionsQuota => "connections_quota",
            Refusal::StreamsQuota => "streams_quota",
            Refusal::CallsOpen => "calls_open",
            Refusal::Intake => "intake",
            Refusal::ProbeCalls => "probe_calls",
            Refusal::AddressCap => "address_cap",
        }
    }
}

impl EncodeLabelValue for Refusal {
    fn encode(&self, encoder: &mut LabelValueEncoder) -> Result<(), std::fmt::Error> {
        std::fmt::Write::write_str(encoder, self.name())
    }
}

/// Declares [`Metrics`]: one line per metric, `field: Type = "prometheus_name", "Help"`. The
/// help is also the field's documentation; `prometheus-client` appends the full stop to it, and
/// `_total` to a counter's name.
macro_rules! metrics {
    ($($field:ident: $ty:ty = $name:literal, $help:literal;)*) => {
        /// The server's metrics. Shared by the session store, the budget, the service, the
        /// connections and the HTTP endpoint; each field is a `prometheus-client` handle.
        #[derive(Debug)]
        pub struct Metrics {
            $(
                #[doc = concat!($help, ".")]
                pub $field: $ty,
            )*
            /// Every field's handle, registered under its name, for [`Metrics::render`].
            registry: Registry,
        }

        impl Default for Metrics {
            fn default() -> Metrics {
                let mut registry = Registry::default();
                $(
                    let $field = <$ty>::default();
                    registry.register($name, $help, $field.clone());
                )*
                Metrics { $($field,)* registry }
            }
        }
    };
}

metrics! {
    sessions_created: Counter = "dinerdash_sessions_created",
        "Sessions created by CreateSession, Fork and Restore";
    sessions_closed: Counter = "dinerdash_sessions_closed",
        "Sessions closed by CloseSession";
    sessions_expired: Counter = "dinerdash_sessions_expired",
        "Sessions evicted after being idle longer than the TTL";
    step_calls: Counter = "dinerdash_step_calls",
        "Step RPCs that succeeded";
    env_steps: Counter = "dinerdash_env_steps",
        "Environment steps (a Step of N environments counts N)";
    env_resets: Counter = "dinerdash_env_resets",
        "Environment resets, by Reset and by autoreset";
    rollout_episodes: Counter = "dinerdash_rollout_episodes",
        "Episodes recorded by Rollout";
    connections_shed: Counter = "dinerdash_connections_shed",
        "Connections closed at the connection limit to admit a new one";
    connections_without_preface: Counter = "dinerdash_connections_without_preface",
        "Connections closed for not sending the HTTP/2 preface in time";
    connections_idle_closed: Counter = "dinerdash_connections_idle_closed",
        "Connections closed for being silent longer than --idle-timeout";
    auth_failures: Counter = "dinerdash_auth_failures",
        "Requests refused for a missing or unknown token (gRPC)";
    live_sessions: Level = "dinerdash_live_sessions",
        "Sessions alive now";
    memory_used_bytes: Level = "dinerdash_memory_used_bytes",
        "Bytes sessions and Rollout streams hold now, as the memory budget counts them";
    memory_budget_bytes: Level = "dinerdash_memory_budget_bytes",
        "The memory budget (--max-memory)";
    live_rollouts: Level = "dinerdash_live_rollouts",
        "Rollout streams running now";
    open_connections: Level = "dinerdash_open_connections",
        "Client connections open now";
    over_limit_connections: Level = "dinerdash_over_limit_connections",
        "Connections over the connection limit open now, answered RESOURCE_EXHAUSTED";
    rpc_errors: Family<CodeLabel, Counter> = "dinerdash_rpc_errors",
        "RPCs that failed, by gRPC status code";
    refusals: Family<ReasonLabel, Counter> = "dinerdash_refusals",
        "Calls refused and connections closed at a quota or cap, by the limit";
}

impl Metrics {
    /// Counts one RPC that failed with `code`.
    pub fn count_error(&self, code: tonic::Code) {
        self.rpc_errors
            .get_or_create(&CodeLabel {
                code: GrpcCode(code),
            })
            .inc();
    }

    /// Counts one call refused (or connection closed) by `reason`.
    pub fn count_refusal(&self, reason: Refusal) {
        self.refusals.get_or_create(&ReasonLabel { reason }).inc();
    }

    /// The metrics in Prometheus' text exposition format (version 0.0.4, [`CONTENT_TYPE`]),
    /// encoded by `prometheus-client` from the registry. A code that never failed has no line
    /// of `dinerdash_rpc_errors_total`, and until one has, the family has none at all (the
    /// registry leaves an empty family out, HELP and TYPE included); the codes that failed
    /// come in no particular order.
    pub fn render(&self) -> String {
        let mut out = String::with_capacity(4096);
        // Writing to a String cannot fail.
        let _ = prometheus_text::encode(&mut out, &self.registry);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scrape_keeps_the_names_types_and_labels() {
        let metrics = Metrics::default();
        let fresh = metrics.render();
        assert_eq!(fresh.matches("# TYPE ").count(), 17, "{fresh}");
        assert!(!fresh.contains("dinerdash_rpc_errors_total"), "{fresh}");
        metrics.env_steps.inc_by(7);
        metrics.live_sessions.inc_by(2);
        metrics.count_error(tonic::Code::NotFound);
        metrics.count_error(tonic::Code::NotFound);
        metrics.count_error(tonic::Code::Unknown);
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
        assert_eq!(text.matches("# TYPE ").count(), 18);
        metrics.count_refusal(Refusal::StreamsQuota);
        let text = metrics.render();
        assert!(
            text.lines()
                .any(|l| l == "dinerdash_refusals_total{reason=\"streams_quota\"} 1"),
            "{text}"
        );
    }

    #[test]
    fn every_code_has_its_specification_name() {
        // tonic's codes are numbered as the specification's; the names follow them in order.
        let names: Vec<&str> = (0..17)
            .map(|n| GrpcCode(tonic::Code::from_i32(n)).name())
            .collect();
        assert_eq!(names[0], "OK");
        assert_eq!(names[5], "NOT_FOUND");
        assert_eq!(names[16], "UNAUTHENTICATED");
        let distinct: std::collections::BTreeSet<&str> = names.iter().copied().collect();
        assert_eq!(distinct.len(), 17);
    }
}
