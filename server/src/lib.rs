//! DinerDash Gym server: the Diner Dash benchmark's game, its reference expert, and the gRPC
//! environment service that hosts many sessions of it.
//!
//! # Layout
//! - [`sim`]: the game itself, pure and synchronous (docs/rules.md).
//! - [`expert`]: policies that read the game: the reference heuristic, random, and
//!   [`expert::PolicyKind`], the names that choose a policy.
//! - [`planner`]: the look-ahead planner over sampled futures, which never reads what arrives next.
//! - [`eval`]: runs a policy over many episodes and summarises scores (the `eval` command).
//! - [`pb`]: the generated protocol types, client and server of `dinerdash.v1`.
//! - [`session`]: the session store: IDs, limits, idle expiry, per-session locks, and what Reset,
//!   Step, Fork and Snapshot do to a session's environments (autoreset included).
//! - [`budget`]: the memory budget and each tenant's share of it (sessions, environments, Rollouts).
//! - [`connections`]: the accept loop (backoff, limit, idle timeout, shedding) and each
//!   connection's info.
//! - [`fd_limit`]: the open-file limit: raised at start, and the connections it has room for.
//! - [`codec`]: protobuf decoding that answers undecodable requests `INVALID_ARGUMENT`.
//! - [`cpu`]: the bounded pool of blocking workers for CPU-heavy work (Rollout, planners).
//! - [`rollout`]: records whole episodes of a server-side policy (the Rollout RPC).
//! - [`service`]: tonic glue: decode a request, call the session store, encode the reply; the
//!   only place errors become `tonic::Status`; the auth interceptor.
//! - [`server`]: [`server::run`] puts the service, health, reflection, TLS and metrics together
//!   on a listener until a shutdown future completes.
//! - [`shutdown`]: SIGINT/SIGTERM, the drain deadlines and the shutdown handles.
//! - [`health`]: the `health` command's grpc.health.v1 client.
//! - [`metrics`]: counters and the Prometheus text endpoint.

pub mod budget;
pub mod codec;
pub mod connections;
pub mod cpu;
pub mod eval;
pub mod expert;
pub mod fd_limit;
pub mod health;
pub mod metrics;
pub mod planner;
pub mod rollout;
pub mod server;
pub mod service;
pub mod session;
pub mod shutdown;
pub mod sim;

/// The generated `dinerdash.v1` protocol: messages, the `DinerDash` client and server.
#[allow(missing_docs, clippy::all)]
pub mod pb {
    tonic::include_proto!("dinerdash.v1");

    /// The encoded descriptor set of `dinerdash.proto`, served by gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/dinerdash_descriptor.bin"));
}

/// This server's version, reported in `Spec` and `ServerInfo`.
pub const SERVER_VERSION: &str = env!("CARGO_PKG_VERSION");
