//! The `dinerdash-server` command: parses the command line and runs the command it names
//! ([`dinerdash_server::cmd`]). Without a subcommand it serves gRPC; `eval` plays a policy
//! locally; `health` probes a running server (the Docker HEALTHCHECK); `ceiling` measures the
//! server's own rates.

use std::process::ExitCode;

use clap::Parser;
use dinerdash_server::cmd::Cli;

fn main() -> ExitCode {
    Cli::parse().run()
}
