//! The `eval` command: runs a policy for many episodes ([`crate::policy::run_episode`]) and
//! summarises them, the numbers a researcher compares with the published benchmark.

use std::io::Write as _;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::ValueEnum;

use crate::policy::{EpisodeSummary, PolicyKind, run_episode};
use crate::sim::Config;

/// Mean and standard deviation (population and sample).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    /// Arithmetic mean.
    pub mean: f64,
    /// Population standard deviation (divides by n), as numpy's `std` reports it.
    pub std: f64,
    /// Sample standard deviation (divides by n - 1).
    pub sample_std: f64,
}

impl Stats {
    /// Summarises `values` (all zero for none).
    pub fn of(values: impl Iterator<Item = f64> + Clone) -> Stats {
        let n = values.clone().count() as f64;
        if n == 0.0 {
            return Stats {
                mean: 0.0,
                std: 0.0,
                sample_std: 0.0,
            };
        }
        let mean = values.clone().sum::<f64>() / n;
        let ss: f64 = values.map(|v| (v - mean).powi(2)).sum();
        Stats {
            mean,
            std: (ss / n).sqrt(),
            sample_std: if n > 1.0 {
                (ss / (n - 1.0)).sqrt()
            } else {
                0.0
            },
        }
    }
}

/// The result of an evaluation.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Every episode, in seed order.
    pub episodes: Vec<EpisodeSummary>,
    /// Wall-clock time of the whole run.
    pub elapsed: Duration,
}

impl Evaluation {
    /// Score statistics.
    pub fn score(&self) -> Stats {
        Stats::of(self.episodes.iter().map(|e| e.score as f64))
    }

    /// Episode length statistics.
    pub fn length(&self) -> Stats {
        Stats::of(self.episodes.iter().map(|e| f64::from(e.steps)))
    }

    /// Steps taken in all.
    pub fn total_steps(&self) -> u64 {
        self.episodes.iter().map(|e| u64::from(e.steps)).sum()
    }

    /// What the `eval` command prints: score, length and lost groups over the episodes of
    /// `kind` from seeds `seed..seed + episodes`, and the speed on `threads` threads.
    pub fn report(&self, kind: PolicyKind, seed: u64, episodes: u32, threads: usize) -> String {
        let score = self.score();
        let length = self.length();
        let lost: u64 = self.episodes.iter().map(|e| u64::from(e.lost)).sum();
        let ended = self.episodes.iter().filter(|e| e.terminated).count();
        let secs = self.elapsed.as_secs_f64().max(1e-9);
        format!(
            "policy {:?}: {} episodes (seeds {}..={})\n\
             score  {:.1} ± {:.1} (sample sd {:.1})\n\
             length {:.1} ± {:.1} steps\n\
             lost   {} groups, {:.2} per 1000 steps; {} of {} episodes ended by losing groups\n\
             {} steps in {:.3} s on {} threads: {:.0} steps/s\n",
            kind,
            self.episodes.len(),
            seed,
            seed.wrapping_add(u64::from(episodes.saturating_sub(1))),
            score.mean,
            score.std,
            score.sample_std,
            length.mean,
            length.std,
            lost,
            1000.0 * lost as f64 / self.total_steps().max(1) as f64,
            ended,
            self.episodes.len(),
            self.total_steps(),
            secs,
            threads,
            self.total_steps() as f64 / secs
        )
    }
}

/// Runs `episodes` episodes with seeds `seed, seed + 1, ...` on `threads` threads.
pub fn evaluate(
    kind: PolicyKind,
    config: Config,
    seed: u64,
    episodes: u32,
    max_steps: u32,
    threads: usize,
) -> Result<Evaluation, crate::sim::ConfigError> {
    config.validate()?;
    let start = Instant::now();
    let seeds: Vec<u64> = (0..u64::from(episodes))
        .map(|i| seed.wrapping_add(i))
        .collect();
    let threads = threads.clamp(1, seeds.len().max(1));
    let chunk = seeds.len().div_ceil(threads).max(1);
    let mut results: Vec<EpisodeSummary> = std::thread::scope(|scope| {
        let handles: Vec<_> = seeds
            .chunks(chunk)
            .map(|part| {
                scope.spawn(move || {
                    part.iter()
                        .filter_map(|&s| run_episode(kind, config, s, max_steps).ok())
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    });
    results.sort_by_key(|e| e.seed.wrapping_sub(seed));
    Ok(Evaluation {
        episodes: results,
        elapsed: start.elapsed(),
    })
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub(super) enum PolicyArg {
    /// The reference heuristic.
    Expert,
    /// Uniformly random actions.
    Random,
    /// The look-ahead planner over sampled futures (about a millisecond a decision).
    Planner,
}

#[derive(Debug, clap::Args)]
pub(super) struct EvalArgs {
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

/// The `eval` command: evaluates and prints [`Evaluation::report`] to stdout.
pub(super) fn execute(args: &EvalArgs) -> ExitCode {
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
