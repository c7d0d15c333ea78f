//! The `dinerdash-server` command: parses the command line and hands over to the library.
//! Without a subcommand it serves gRPC ([`dinerdash_server::server::serve`], with the flags of
//! [`dinerdash_server::config::ServeArgs`]); `eval` plays a policy locally
//! ([`dinerdash_server::eval`]); `health` probes a running server (the Docker HEALTHCHECK).

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use dinerdash_server::ceiling::CeilingArgs;
use dinerdash_server::config::{LogFormat, ServeArgs, parse_duration};
use dinerdash_server::eval::evaluate;
use dinerdash_server::health::{self, Probe};
use dinerdash_server::policy::PolicyKind;
use dinerdash_server::server;
use dinerdash_server::sim::Config;

/// DinerDash Gym environment server.
#[derive(Debug, Parser)]
#[command(version, about, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    serve: ServeArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Plays a policy locally for many episodes and prints mean ± sd of score and length.
    Eval(EvalArgs),
    /// Asks a running server's grpc.health.v1 service; exits 0 if it is SERVING.
    Health(HealthArgs),
    /// Prints the server's own rates for a session of N on each number of stepping threads
    /// (env-steps/s, in process and through a Rust gRPC client): the ceiling of any client, for
    /// `python -m dinerdash bench`.
    Ceiling(CeilingArgs),
}

/// One line per (N, threads): `N threads labels in_process grpc` (env-steps/s).
fn run_ceiling(args: &CeilingArgs) -> ExitCode {
    let printed = dinerdash_server::ceiling::run(args, |rate| {
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "{rate}").and_then(|()| out.flush());
    });
    match printed {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

#[derive(Debug, clap::Args)]
struct HealthArgs {
    /// The server, host:port.
    #[arg(long, default_value = "127.0.0.1:50051")]
    address: String,
    /// Give up after this long (seconds, or with ms, s, m or h).
    #[arg(long, default_value = "5", value_parser = parse_duration)]
    timeout: Duration,
    /// The service to ask about; empty means the whole server.
    #[arg(long, default_value = "")]
    service: String,
    /// Connect with TLS, trusting this PEM CA certificate (or a self-signed server certificate
    /// itself).
    #[arg(long)]
    tls_ca: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PolicyArg {
    /// The reference heuristic.
    Expert,
    /// Uniformly random actions.
    Random,
    /// The look-ahead planner over sampled futures (about a millisecond a decision).
    Planner,
}

#[derive(Debug, clap::Args)]
struct EvalArgs {
    /// The policy to play.
    #[arg(long, value_enum, default_value = "expert")]
    policy: PolicyArg,
    /// Number of episodes; episode i is reset with seed `seed + i`.
    #[arg(long, default_value_t = 100)]
    episodes: u32,
    /// Seed of the first episode.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Truncate an episode after this many steps.
    #[arg(long, default_value_t = 100_000)]
    max_steps: u32,
    /// Worker threads (default: one per core).
    #[arg(long)]
    threads: Option<usize>,
}

fn run_eval(args: &EvalArgs) -> ExitCode {
    let kind = match args.policy {
        PolicyArg::Expert => PolicyKind::Expert,
        PolicyArg::Random => PolicyKind::Random,
        PolicyArg::Planner => PolicyKind::Planner,
    };
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let result = match evaluate(
        kind,
        Config::default(),
        args.seed,
        args.episodes,
        args.max_steps,
        threads,
    ) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let report = result.report(kind, args.seed, args.episodes, threads);
    // A reader that went away (`| head`) is not an error worth a panic.
    let _ = std::io::stdout().lock().write_all(report.as_bytes());
    ExitCode::SUCCESS
}

fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}

fn runtime() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Eval(args)) => run_eval(&args),
        Some(Command::Ceiling(args)) => run_ceiling(&args),
        Some(Command::Health(args)) => {
            let probe = |tls_ca: Option<Vec<u8>>| Probe {
                address: args.address.clone(),
                timeout: args.timeout,
                service: args.service.clone(),
                tls_ca,
            };
            let result = args
                .tls_ca
                .as_ref()
                .map(|ca| {
                    std::fs::read(ca).map_err(|e| format!("cannot read {}: {e}", ca.display()))
                })
                .transpose()
                .and_then(|ca| {
                    let rt = runtime().map_err(|e| e.to_string())?;
                    rt.block_on(health::check(&probe(ca)))
                });
            match result {
                Ok(status) => {
                    println!("{}", status.as_str_name());
                    if status == health::ServingStatus::Serving {
                        ExitCode::SUCCESS
                    } else {
                        ExitCode::FAILURE
                    }
                }
                Err(e) => {
                    eprintln!("error: {e}");
                    ExitCode::FAILURE
                }
            }
        }
        None => {
            init_logging(cli.serve.log_format);
            let result = runtime().map_err(|e| e.to_string()).and_then(|rt| {
                rt.block_on(server::serve(&cli.serve))
                    .map_err(|e| e.to_string())
            });
            match result {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    tracing::error!("{e}");
                    eprintln!("error: {e}");
                    ExitCode::FAILURE
                }
            }
        }
    }
}
