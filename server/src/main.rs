//! The `dinerdash-server` command: parses the command line and hands over to the library.

use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use dinerdash_server::eval::{PolicyKind, evaluate};
use dinerdash_server::sim::Config;

/// DinerDash Gym environment server.
#[derive(Debug, Parser)]
#[command(version, about, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Plays a policy locally for many episodes and prints mean ± sd of score and length.
    Eval(EvalArgs),
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PolicyArg {
    Expert,
    Random,
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
    };
    let threads = args.threads.unwrap_or_else(|| {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    });
    let result = match evaluate(kind, Config::default(), args.seed, args.episodes, args.max_steps, threads) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(2);
        }
    };
    let score = result.score();
    let length = result.length();
    let secs = result.elapsed.as_secs_f64().max(1e-9);
    println!(
        "policy {:?}: {} episodes (seeds {}..={})",
        args.policy,
        result.episodes.len(),
        args.seed,
        args.seed.wrapping_add(u64::from(args.episodes.saturating_sub(1)))
    );
    println!(
        "score  {:.1} ± {:.1} (sample sd {:.1})",
        score.mean, score.std, score.sample_std
    );
    println!("length {:.1} ± {:.1} steps", length.mean, length.std);
    println!(
        "{} steps in {:.3} s on {} threads: {:.0} steps/s",
        result.total_steps(),
        secs,
        threads,
        result.total_steps() as f64 / secs
    );
    ExitCode::SUCCESS
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Eval(args)) => run_eval(&args),
        None => {
            eprintln!("the server is not built yet");
            ExitCode::FAILURE
        }
    }
}
