//! The `dinerdash-server` binary's commands, one file each (as mini-redis's `cmd/`): the
//! command line ([`Cli`]) and its dispatch live here, so that `main.rs` only parses and calls
//! [`Cli::run`].
//!
//! - [`serve`]: no subcommand; serves gRPC with the flags of [`crate::config::ServeArgs`]
//!   ([`crate::server::serve`]).
//! - [`eval`]: plays a policy locally for many episodes and summarises them.
//! - [`health`]: the grpc.health.v1 client that probes a running server (the Docker
//!   HEALTHCHECK).
//! - [`ceiling`]: the server's own batch rate, in process and through a Rust gRPC client, that
//!   `python -m dinerdash bench` prints beside the Python client's.
//!
//! Commands sit above every library layer: they may use any module, and no module uses them
//! (`tests/module_graph.rs`).

pub mod ceiling;
pub mod eval;
pub mod health;
pub mod serve;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::config::ServeArgs;

/// DinerDash Gym environment server.
#[derive(Debug, Parser)]
#[command(version, about, args_conflicts_with_subcommands = true)]
pub struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    serve: ServeArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Plays a policy locally for many episodes and prints mean ± sd of score and length.
    Eval(eval::EvalArgs),
    /// Asks a running server's grpc.health.v1 service; exits 0 if it is SERVING.
    Health(health::HealthArgs),
    /// Prints the server's own rates for a session of N on each number of stepping threads
    /// (env-steps/s, in process and through a Rust gRPC client): the ceiling of any client, for
    /// `python -m dinerdash bench`.
    Ceiling(ceiling::CeilingArgs),
}

impl Cli {
    /// Runs the command the line asked for; its exit code.
    pub fn run(self) -> ExitCode {
        match self.command {
            Some(Command::Eval(args)) => eval::execute(&args),
            Some(Command::Health(args)) => health::execute(&args),
            Some(Command::Ceiling(args)) => ceiling::execute(&args),
            None => serve::execute(&self.serve),
        }
    }
}

/// The multi-threaded tokio runtime the async commands run on.
fn runtime() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
}
