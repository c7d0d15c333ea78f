//! DinerDash Gym server: the Diner Dash benchmark's game, its reference expert, and the gRPC
//! environment service that hosts many sessions of it.
//!
//! # Layout
//! Each module uses only modules listed above it (`tests/module_graph.rs` keeps it so).
//! - [`sim`]: the game itself, pure and synchronous (docs/rules.md).
//! - [`policy`]: [`policy::Policy`] and [`policy::PolicyKind`], the names that choose one; the
//!   reference heuristic ([`policy::expert`]), random actions ([`policy::random`]), and the
//!   look-ahead planner over sampled futures, which never reads what arrives next
//!   ([`policy::planner`]); one episode of a policy from a seed ([`policy::run_episode`]).
//! - [`pb`]: the generated protocol types, client and server of `dinerdash.v1`.
//! - [`metrics`]: every metric, one entry each, as `prometheus-client` counters, gauges and a
//!   family labelled by gRPC code, and their Prometheus text.
//! - [`audit`]: failed authentications counted and logged (peer, method; rate-limited), and
//!   the tower layer that tags each request with its method.
//! - [`shutdown`]: SIGINT/SIGTERM, the drain of a planned restart (its phases, its refusal of
//!   new sessions, the time left), the deadlines, the shutdown handles, and the `UNAVAILABLE` a
//!   stopping server answers.
//! - [`budget`]: the memory budget and each tenant's share of it (sessions, environments,
//!   Rollouts).
//! - [`pools`]: the two thread pools for CPU-heavy work: [`pools::CpuPool`], the bounded
//!   blocking workers that run Rollout episodes (in chunks) and every planner-labelled session's
//!   Reset, Step, Render, Snapshot and Fork, serving tenants in turn (one per process, shared by
//!   gRPC and shared memory), and
//!   [`pools::StepPool`], the threads that step one large Step's environments in chunks.
//! - [`rollout`]: the Rollout RPC's rules (what a request may ask, what its stream is charged)
//!   and the recording of whole episodes of a server-side policy.
//! - [`codec`]: protobuf decoding that measures each request on the wire before decoding it
//!   and answers undecodable or oversized ones `INVALID_ARGUMENT`; `codec::intake`, the tower
//!   layer that charges large messages while they are received and decoded.
//! - [`session`]: the session store: IDs, limits, idle expiry, per-session locks, and what Reset,
//!   Step, Fork and Snapshot do to a session's environments (autoreset included).
//! - [`connections`]: a folder, one job a file: the accept loop (backoff, limit), the table of
//!   connections and shedding, the connection wrapper with its preface and idle timers, the
//!   calls' admission and counting (`connections::calls`), and the open-file limit
//!   (`connections::fd_limit`).
//! - [`auth`]: bearer tokens and the tenants they stand for (the tenants file), the
//!   constant-time compare, and the [`auth::RequestGate`] in front of every RPC: draining,
//!   over the connection limit, token.
//! - [`http`]: the HTTP endpoint on hyper and axum: the sessions page and the watch page, their
//!   JSON and event feeds, the play page and its games' recordings, and the metrics.
//! - [`service`]: tonic glue: decode a request, call the session store, encode the reply; the
//!   only place errors become `tonic::Status` ([`service::status`](mod@service::status));
//!   StepStream and Rollout streams.
//! - [`shm`]: the same-host data plane (Linux): a session's Steps through a shared-memory region
//!   and a doorbell socket, for clients on the server's host running as its user.
//! - [`config`]: the `serve` flags and what they decide ([`config::ServerConfig::from_args`]).
//! - [`reload`]: the tokens file read again on SIGHUP, its tenants and their sessions kept.
//! - [`server`]: [`server::run`] puts the service, health, reflection, TLS and HTTP together
//!   on a listener until a shutdown future completes; [`server::serve`] is the binary's.
//! - [`cmd`]: the binary's commands, one file each, and the command line that dispatches to
//!   them: `serve` (the default), `eval`, `health` (the grpc.health.v1 client) and `ceiling`
//!   (the server's own batch rate). The top layer: it may use every module above, none uses it.

pub mod audit;
pub mod auth;
pub mod budget;
pub mod cmd;
pub mod codec;
pub mod config;
pub mod connections;
pub mod http;
pub mod metrics;
pub mod policy;
pub mod pools;
pub mod reload;
pub mod rollout;
pub mod server;
pub mod service;
pub mod session;
#[cfg(target_os = "linux")]
pub mod shm;
pub mod shutdown;
pub mod sim;

/// The generated `dinerdash.v1` protocol: messages, the `DinerDash` client and server.
#[allow(missing_docs, clippy::all)]
pub mod pb {
    tonic::include_proto!("dinerdash.v1");

    /// The encoded descriptor set of `dinerdash.proto`, served by gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/dinerdash_descriptor.bin"));

    impl GameConfig {
        /// `config` with every field present.
        pub fn of(c: &crate::sim::Config) -> GameConfig {
            GameConfig {
                arrival_interval: Some(c.arrival_interval),
                patience_type1: Some(c.patience[0]),
                patience_type2: Some(c.patience[1]),
                decay_type1: Some(c.decay[0]),
                decay_type2: Some(c.decay[1]),
                reading_ticks: Some(c.reading_ticks),
                cooking_ticks: Some(c.cooking_ticks),
                eating_ticks: Some(c.eating_ticks),
                lives: Some(c.lives),
                time_limit: Some(c.time_limit),
            }
        }

        /// The game configuration this message asks for: absent fields keep ruleset `v0`'s (not
        /// yet validated). The gRPC service and the web endpoint's games both read it so.
        pub fn config(&self) -> crate::sim::Config {
            let d = crate::sim::Config::default();
            crate::sim::Config {
                arrival_interval: self.arrival_interval.unwrap_or(d.arrival_interval),
                patience: [
                    self.patience_type1.unwrap_or(d.patience[0]),
                    self.patience_type2.unwrap_or(d.patience[1]),
                ],
                decay: [
                    self.decay_type1.unwrap_or(d.decay[0]),
                    self.decay_type2.unwrap_or(d.decay[1]),
                ],
                reading_ticks: self.reading_ticks.unwrap_or(d.reading_ticks),
                cooking_ticks: self.cooking_ticks.unwrap_or(d.cooking_ticks),
                eating_ticks: self.eating_ticks.unwrap_or(d.eating_ticks),
                lives: self.lives.unwrap_or(d.lives),
                time_limit: self.time_limit.unwrap_or(d.time_limit),
            }
        }
    }
}

/// This server's version, reported in `Spec` and `ServerInfo`.
pub const SERVER_VERSION: &str = env!("CARGO_PKG_VERSION");
