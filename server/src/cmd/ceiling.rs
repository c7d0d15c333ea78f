//! The `ceiling` command: the rates no client of this server can pass, measured on the machine
//! the clients run on, for `python -m dinerdash bench` to print beside them, and how they scale
//! with the stepping threads (`--step-threads`).
//!
//! - **in process**: one session of N environments stepped through the session store, each
//!   Step's Batch built as for a reply, no transport at all (the server's own batch rate);
//! - **Rust gRPC client**: the same over loopback gRPC, a tonic client of a server in this
//!   process, one unary Step after another (what `cargo bench --bench grpc` measures).
//!
//! Both step with uniformly random actions from a fixed stream, as the Python bench does, on a
//! store whose stepping pool has the given number of threads (and the default thresholds), with
//! the given expert labels in every Batch. One line per (N, threads):
//! `N threads labels in_process grpc`, in env-steps/s.

use std::io::Write as _;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::ValueEnum;

use crate::budget::{Share, Tenant};
use crate::config::parse_duration;
use crate::pb;
use crate::pools::Stepping;
use crate::server::{self, Listeners, ServerConfig, ServerError};
use crate::session::{Autoreset, Caller, ExpertActions, Limits, ResetArgs, SessionOptions, Store};
use crate::sim::{Config, NUM_ACTIONS};

/// Which expert actions every Batch of the measured session carries.
// The variants' doc comments would show in `--help`; the flag's own help says enough.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Labels {
    None,
    Expert,
    Planner,
}

impl Labels {
    /// The session option these labels ask for.
    fn expert_actions(self) -> ExpertActions {
        match self {
            Labels::None => ExpertActions::None,
            Labels::Expert => ExpertActions::Reference,
            Labels::Planner => ExpertActions::Planner,
        }
    }

    /// The protocol's `expert_actions` and `expert_policy` of CreateSession.
    fn request(self) -> (bool, i32) {
        match self {
            Labels::None => (false, pb::Policy::Unspecified.into()),
            Labels::Expert => (true, pb::Policy::Expert.into()),
            Labels::Planner => (true, pb::Policy::Planner.into()),
        }
    }

    /// The name printed in each line (the flag's value).
    fn name(self) -> &'static str {
        match self {
            Labels::None => "none",
            Labels::Expert => "expert",
            Labels::Planner => "planner",
        }
    }
}

/// What to measure: the `ceiling` command's flags.
#[derive(Debug, Clone, clap::Args)]
pub struct CeilingArgs {
    /// Environments in the session (one line per value and thread count).
    #[arg(long, default_values_t = [1, 256, 1024])]
    pub num_envs: Vec<usize>,
    /// Stepping threads of the server (`--step-threads`), one line per value; default: one per
    /// core.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub threads: Vec<u32>,
    /// Expert actions in every Batch: none, the reference heuristic's, or the planner's.
    #[arg(long, value_enum, default_value = "none")]
    pub labels: Labels,
    /// How long each measurement lasts (seconds, or with ms, s, m or h).
    #[arg(long, default_value = "2", value_parser = parse_duration)]
    pub time: Duration,
}

/// Why a measurement failed.
#[derive(Debug, thiserror::Error)]
pub enum CeilingError {
    /// The in-process session refused a request.
    #[error("in process: {0}")]
    Session(#[from] crate::session::SessionError),
    /// The server in this process could not start or serve.
    #[error(transparent)]
    Server(#[from] ServerError),
    /// The gRPC client's call failed.
    #[error("gRPC client: {0}")]
    Client(String),
    /// No async runtime for the gRPC measurement.
    #[error("cannot start the async runtime: {0}")]
    Runtime(std::io::Error),
}

/// One measured line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rate {
    /// N.
    pub num_envs: usize,
    /// Stepping threads.
    pub threads: usize,
    /// The labels.
    pub labels: Labels,
    /// Env-steps/s in process.
    pub in_process: f64,
    /// Env-steps/s through the Rust gRPC client.
    pub grpc: f64,
}

impl std::fmt::Display for Rate {
    /// `N threads labels in_process grpc`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} {} {} {:.0} {:.0}",
            self.num_envs,
            self.threads,
            self.labels.name(),
            self.in_process,
            self.grpc
        )
    }
}

/// The `ceiling` command: one line per (N, threads) to stdout as soon as it is measured,
/// `N threads labels in_process grpc` (env-steps/s).
pub(super) fn execute(args: &CeilingArgs) -> ExitCode {
    let printed = run(args, |rate| {
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

/// Measures every (N, threads) of `args`, calling `line` with each as soon as it is measured.
pub fn run(args: &CeilingArgs, mut line: impl FnMut(Rate)) -> Result<(), CeilingError> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(CeilingError::Runtime)?;
    let threads: Vec<usize> = if args.threads.is_empty() {
        vec![Stepping::default().threads]
    } else {
        args.threads.iter().map(|&t| t as usize).collect()
    };
    for &n in &args.num_envs {
        for &t in &threads {
            let stepping = stepping(t);
            let in_process = in_process(n, stepping, args.labels, args.time)?;
            let grpc = rt.block_on(grpc(n, stepping, args.labels, args.time))?;
            line(Rate {
                num_envs: n,
                threads: t,
                labels: args.labels,
                in_process,
                grpc,
            });
        }
    }
    Ok(())
}

/// `threads` stepping threads and the default thresholds.
fn stepping(threads: usize) -> Stepping {
    Stepping {
        threads,
        ..Stepping::default()
    }
}

/// A fixed stream of random actions, packed as a Step carries them (a 64-bit LCG from `seed`);
/// the parallel-stepping tests replay the same streams.
pub struct Actions(pub u64);

impl Actions {
    /// The next Step's actions for `n` environments.
    pub fn next(&mut self, n: usize) -> Vec<u8> {
        (0..n)
            .flat_map(|_| {
                self.0 = self
                    .0
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (((self.0 >> 33) % NUM_ACTIONS as u64) as i32).to_le_bytes()
            })
            .collect()
    }
}

/// The limits of the measuring store or server: room for the session, and `stepping`.
fn limits(num_envs: usize, stepping: Stepping) -> Limits {
    let defaults = Limits::default();
    Limits {
        max_envs_per_session: defaults.max_envs_per_session.max(num_envs),
        stepping,
        ..defaults
    }
}

/// Env-steps/s of one session of `num_envs` with `labels` stepped in process for about `time`,
/// on a store stepping with `stepping`.
pub fn in_process(
    num_envs: usize,
    stepping: Stepping,
    labels: Labels,
    time: Duration,
) -> Result<f64, CeilingError> {
    let store = Store::new(limits(num_envs, stepping), Arc::default());
    let caller = Caller::shared(Arc::new(Tenant::new(
        "ceiling".into(),
        Share {
            max_envs: u64::MAX,
            ..Share::default()
        },
    )));
    let options = SessionOptions {
        autoreset: Autoreset::NextStep,
        action_masks: true,
        expert_actions: labels.expert_actions(),
    };
    let n = u32::try_from(num_envs).unwrap_or(u32::MAX);
    let (id, _) = store.create(&caller, n, Config::default(), options, Some(0))?;
    let session = store.find(&caller.owner, &id.to_string())?;
    session.reset(&ResetArgs::default())?;
    let mut actions = Actions(0);
    let batches: Vec<Vec<u8>> = (0..64).map(|_| actions.next(num_envs)).collect();
    // One Step first: the stepping threads start on the first parallel one.
    session.step(&batches[0])?;
    let start = Instant::now();
    let mut steps = 0u64;
    'timed: while start.elapsed() < time {
        for a in &batches {
            std::hint::black_box(session.step(a)?);
            steps += 1;
            if start.elapsed() >= time {
                break 'timed;
            }
        }
    }
    Ok(steps as f64 * num_envs as f64 / start.elapsed().as_secs_f64())
}

/// Env-steps/s of one tonic client stepping a session of `num_envs` with `labels` on a server
/// in this process stepping with `stepping`, over loopback, for about `time`.
pub async fn grpc(
    num_envs: usize,
    stepping: Stepping,
    labels: Labels,
    time: Duration,
) -> Result<f64, CeilingError> {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|source| ServerError::Listen {
            addr: "127.0.0.1:0".into(),
            purpose: "",
            source,
        })?;
    let addr = listener.local_addr().map_err(ServerError::LocalAddr)?;
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let config = ServerConfig {
        limits: limits(num_envs, stepping),
        connection_share: Share {
            max_envs: u64::MAX,
            ..Share::default()
        },
        ..ServerConfig::default()
    };
    let serving = tokio::spawn(server::run(Listeners::grpc(listener), config, async {
        let _ = stopped.await;
    }));
    let client_error = |e: &dyn std::fmt::Display| CeilingError::Client(e.to_string());
    let rate = async {
        let mut client = pb::diner_dash_client::DinerDashClient::connect(format!("http://{addr}"))
            .await
            .map_err(|e| client_error(&e))?
            .max_decoding_message_size(usize::MAX)
            .max_encoding_message_size(usize::MAX);
        let (expert_actions, expert_policy) = labels.request();
        let created = client
            .create_session(pb::CreateSessionRequest {
                num_envs: u32::try_from(num_envs).unwrap_or(u32::MAX),
                seed: Some(0),
                autoreset_mode: pb::AutoresetMode::NextStep.into(),
                action_masks: true,
                expert_actions,
                expert_policy,
                ..Default::default()
            })
            .await
            .map_err(|e| client_error(&e))?
            .into_inner();
        let id = created.session_id;
        client
            .reset(pb::ResetRequest {
                session_id: id.clone(),
                ..Default::default()
            })
            .await
            .map_err(|e| client_error(&e))?;
        let mut actions = Actions(0);
        let step = |actions: Vec<u8>| {
            let mut client = client.clone();
            let request = pb::StepRequest {
                session_id: id.clone(),
                actions,
            };
            async move { client.step(request).await.map_err(|e| client_error(&e)) }
        };
        // One Step first: the stepping threads start on the first parallel one.
        step(actions.next(num_envs)).await?;
        let start = Instant::now();
        let mut steps = 0u64;
        while start.elapsed() < time {
            step(actions.next(num_envs)).await?;
            steps += 1;
        }
        Ok::<f64, CeilingError>(steps as f64 * num_envs as f64 / start.elapsed().as_secs_f64())
    }
    .await;
    let _ = stop.send(());
    let _ = serving.await;
    rate
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_names_n_threads_and_labels_then_both_rates() {
        let rate = Rate {
            num_envs: 256,
            threads: 2,
            labels: Labels::Planner,
            in_process: 12345.6,
            grpc: 999.4,
        };
        assert_eq!(rate.to_string(), "256 2 planner 12346 999");
    }

    #[test]
    fn every_pair_of_n_and_threads_is_measured() {
        let args = CeilingArgs {
            num_envs: vec![1, 600],
            threads: vec![1, 2],
            labels: Labels::Expert,
            time: Duration::from_millis(20),
        };
        let mut lines = Vec::new();
        run(&args, |rate| lines.push(rate)).unwrap();
        let pairs: Vec<(usize, usize)> = lines.iter().map(|r| (r.num_envs, r.threads)).collect();
        assert_eq!(pairs, [(1, 1), (1, 2), (600, 1), (600, 2)]);
        assert!(lines.iter().all(|r| r.in_process > 0.0 && r.grpc > 0.0));
    }
}
