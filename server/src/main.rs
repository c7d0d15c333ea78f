//! The `dinerdash-server` command: parses the command line and hands over to the library.
//! Without a subcommand it serves gRPC ([`dinerdash_server::server::run`]); `eval` plays a
//! policy locally; `health` probes a running server (the Docker HEALTHCHECK).

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use dinerdash_server::budget::{
    DEFAULT_MAX_MEMORY, DEFAULT_TENANT_ENVS, DEFAULT_TENANT_ROLLOUTS, Share, Tenant, parse_tenants,
};
use dinerdash_server::connections::{self, DEFAULT_MAX_CONNECTIONS};
use dinerdash_server::eval::evaluate;
use dinerdash_server::expert::PolicyKind;
use dinerdash_server::health::{self, Probe};
use dinerdash_server::rollout::MAX_ROLLOUT_WORK_STEPS;
use dinerdash_server::server::{self, ServerConfig, TlsPem};
use dinerdash_server::service::Token;
use dinerdash_server::session::{DEFAULT_MAX_ENVS_PER_SESSION, DEFAULT_MAX_SESSIONS, Limits};
use dinerdash_server::shutdown;
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
}

/// How log lines are written (to stderr).
#[derive(Debug, Clone, Copy, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

/// The server's flags (used when no subcommand is given).
#[derive(Debug, clap::Args)]
struct ServeArgs {
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1")]
    host: String,
    /// Port to listen on; 0 picks a free one (printed on stdout).
    #[arg(long, default_value_t = 50051)]
    port: u16,
    /// Most live sessions.
    #[arg(long, default_value_t = DEFAULT_MAX_SESSIONS, value_parser = clap::value_parser!(u32).range(1..))]
    max_sessions: u32,
    /// Most environments in one session.
    #[arg(long, default_value_t = DEFAULT_MAX_ENVS_PER_SESSION, value_parser = clap::value_parser!(u32).range(1..=65536))]
    max_envs_per_session: u32,
    /// Close sessions idle this long: seconds, or a number with ms, s, m or h ("5m").
    #[arg(long, default_value = "300", value_parser = parse_duration)]
    session_ttl: Duration,
    /// Log line format on stderr (the level comes from RUST_LOG, default info).
    #[arg(long, value_enum, default_value = "text")]
    log_format: LogFormat,
    /// Most bytes sessions and Rollout streams may hold: bytes, or with KiB, MiB, GiB ("2GiB").
    /// Requests that would pass it are refused with RESOURCE_EXHAUSTED.
    #[arg(long, default_value_t = DEFAULT_MAX_MEMORY, value_parser = parse_bytes)]
    max_memory: u64,
    /// Most environments one tenant may hold: a token of --auth-tokens-file (unless its line
    /// says otherwise), or else one connection.
    #[arg(long, default_value_t = DEFAULT_TENANT_ENVS)]
    max_envs_per_tenant: u64,
    /// Most steps one Rollout request may record over all its episodes.
    #[arg(long, default_value_t = MAX_ROLLOUT_WORK_STEPS, value_parser = clap::value_parser!(u64).range(1..))]
    max_rollout_work_steps: u64,
    /// Most Rollout streams one tenant (or connection) may run at once.
    #[arg(long, default_value_t = DEFAULT_TENANT_ROLLOUTS)]
    max_rollouts_per_tenant: u64,
    /// Most client connections, capped below the open-file limit. At the limit the longest-idle
    /// connection with no call in flight is closed to admit a new one; when every connection has
    /// a call in flight, new ones are answered RESOURCE_EXHAUSTED and closed.
    #[arg(long, default_value_t = DEFAULT_MAX_CONNECTIONS as u32, value_parser = clap::value_parser!(u32).range(1..))]
    max_connections: u32,
    /// Close connections silent this long (live clients answer keepalive pings every 30 s).
    #[arg(long, default_value = "120", value_parser = parse_duration)]
    idle_timeout: Duration,
    /// Serve Prometheus metrics over HTTP on this port of --metrics-host.
    #[arg(long)]
    metrics_port: Option<u16>,
    /// Address of the metrics endpoint: local only by default, whatever --host is. Any other
    /// address needs --auth-token or --auth-tokens-file, whose tokens the endpoint then asks for.
    #[arg(long, default_value = "127.0.0.1")]
    metrics_host: String,
    /// Require `authorization: Bearer <token>` on every RPC (health checks excepted).
    #[arg(long, env = "DINERDASH_AUTH_TOKEN", hide_env_values = true)]
    auth_token: Option<String>,
    /// Tenants, one a line: `NAME TOKEN [envs=N] [sessions=N] [rollouts=N]`. Each token is
    /// accepted like --auth-token, and its requests count against its tenant's share.
    #[arg(long)]
    auth_tokens_file: Option<PathBuf>,
    /// PEM certificate chain: serve TLS (needs --tls-key).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
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

/// A non-zero whole number followed by one of `units` (name, scale); `what` and `example` word
/// the errors.
fn parse_scaled(
    text: &str,
    units: &[(&str, u64)],
    what: &str,
    example: &str,
) -> Result<u64, String> {
    let text = text.trim();
    let split = text
        .find(|c: char| !c.is_ascii_digit())
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let n: u64 = number
        .parse()
        .map_err(|_| format!("expected a number of {what} or e.g. {example}, got {text:?}"))?;
    let unit = unit.trim();
    let scale = units
        .iter()
        .find_map(|&(name, scale)| (name == unit).then_some(scale))
        .ok_or_else(|| {
            let names: Vec<&str> = units
                .iter()
                .map(|&(name, _)| name)
                .filter(|n| !n.is_empty())
                .collect();
            format!("unknown unit {unit:?}: use {}", names.join(", "))
        })?;
    let value = n
        .checked_mul(scale)
        .ok_or_else(|| format!("{text} is too large"))?;
    if value == 0 {
        return Err("must be greater than zero".into());
    }
    Ok(value)
}

/// "300", "300s", "500ms", "5m", "1h" as a non-zero duration.
fn parse_duration(text: &str) -> Result<Duration, String> {
    const MS: &[(&str, u64)] = &[
        ("", 1000),
        ("s", 1000),
        ("ms", 1),
        ("m", 60_000),
        ("h", 3_600_000),
    ];
    parse_scaled(text, MS, "seconds", "5m").map(Duration::from_millis)
}

/// "1073741824", "512MiB", "2GiB", "64KiB" (also KB, MB, GB as powers of 1000) as bytes.
fn parse_bytes(text: &str) -> Result<u64, String> {
    const UNITS: &[(&str, u64)] = &[
        ("", 1),
        ("B", 1),
        ("KiB", 1 << 10),
        ("MiB", 1 << 20),
        ("GiB", 1 << 30),
        ("KB", 1_000),
        ("MB", 1_000_000),
        ("GB", 1_000_000_000),
    ];
    parse_scaled(text, UNITS, "bytes", "2GiB")
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
    let score = result.score();
    let length = result.length();
    let lost: u64 = result.episodes.iter().map(|e| u64::from(e.lost)).sum();
    let ended = result.episodes.iter().filter(|e| e.terminated).count();
    let secs = result.elapsed.as_secs_f64().max(1e-9);
    let report = format!(
        "policy {:?}: {} episodes (seeds {}..={})\n\
         score  {:.1} ± {:.1} (sample sd {:.1})\n\
         length {:.1} ± {:.1} steps\n\
         lost   {} groups, {:.2} per 1000 steps; {} of {} episodes ended by losing groups\n\
         {} steps in {:.3} s on {} threads: {:.0} steps/s\n",
        args.policy,
        result.episodes.len(),
        args.seed,
        args.seed
            .wrapping_add(u64::from(args.episodes.saturating_sub(1))),
        score.mean,
        score.std,
        score.sample_std,
        length.mean,
        length.std,
        lost,
        1000.0 * lost as f64 / result.total_steps().max(1) as f64,
        ended,
        result.episodes.len(),
        result.total_steps(),
        secs,
        threads,
        result.total_steps() as f64 / secs
    );
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

/// Binds, prints the listening line, and serves until SIGINT/SIGTERM.
async fn serve(args: ServeArgs) -> Result<(), String> {
    let read = |path: &PathBuf| {
        std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
    };
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(cert), Some(key)) => Some(TlsPem {
            cert: read(cert)?,
            key: read(key)?,
        }),
        _ => None,
    };
    let share = Share {
        max_envs: args.max_envs_per_tenant,
        max_sessions: u64::MAX,
        max_rollouts: args.max_rollouts_per_tenant,
    };
    let tenants = match &args.auth_tokens_file {
        Some(path) => {
            let text = String::from_utf8(read(path)?)
                .map_err(|_| format!("{} is not UTF-8", path.display()))?;
            parse_tenants(&text, share)
                .map_err(|e| format!("{}: {e}", path.display()))?
                .into_iter()
                .map(|line| Token {
                    token: line.token,
                    tenant: Some(Arc::new(Tenant::new(
                        format!("tenant {}", line.name),
                        line.share,
                    ))),
                })
                .collect()
        }
        None => Vec::new(),
    };
    let has_token = args.auth_token.as_ref().is_some_and(|t| !t.is_empty()) || !tenants.is_empty();
    let local_metrics = matches!(
        args.metrics_host.as_str(),
        "127.0.0.1" | "::1" | "localhost"
    );
    if args.metrics_port.is_some() && !local_metrics && !has_token {
        return Err(format!(
            "--metrics-host {} publishes the metrics beyond this machine: give --auth-token or \
             --auth-tokens-file too (scrapers then send the token as a bearer token)",
            args.metrics_host
        ));
    }
    // Room for connections: the accept loop caps --max-connections below this limit.
    dinerdash_server::fd_limit::raise();
    let listener = connections::bind(&args.host, args.port)
        .await
        .map_err(|e| format!("cannot listen on {}:{}: {e}", args.host, args.port))?;
    let metrics_listener = match args.metrics_port {
        Some(port) => Some(
            tokio::net::TcpListener::bind((args.metrics_host.as_str(), port))
                .await
                .map_err(|e| {
                    format!(
                        "cannot listen on {}:{port} for metrics: {e}",
                        args.metrics_host
                    )
                })?,
        ),
        None => None,
    };
    let addr = listener
        .local_addr()
        .map_err(|e| format!("cannot read the bound address: {e}"))?;
    let config = ServerConfig {
        limits: Limits {
            max_sessions: args.max_sessions as usize,
            max_envs_per_session: args.max_envs_per_session as usize,
            session_ttl: args.session_ttl,
            max_memory: args.max_memory,
            max_rollout_work_steps: args.max_rollout_work_steps,
        },
        auth_token: args.auth_token.filter(|t| !t.is_empty()),
        tenants,
        connection_share: share,
        connections: connections::Limits {
            max_connections: args.max_connections as usize,
            idle_timeout: args.idle_timeout,
            ..connections::Limits::default()
        },
        tls,
        metrics_listener,
    };
    tracing::info!(
        %addr,
        tls = config.tls.is_some(),
        auth = config.auth_token.is_some() || !config.tenants.is_empty(),
        tenants = config.tenants.len(),
        max_sessions = config.limits.max_sessions,
        max_envs_per_session = config.limits.max_envs_per_session,
        max_memory = config.limits.max_memory,
        max_connections = config.connections.max_connections,
        session_ttl_s = config.limits.session_ttl.as_secs_f64(),
        "serving"
    );
    // The one line on stdout: clients that started this process read the port from it.
    let mut stdout = std::io::stdout().lock();
    let _ = writeln!(stdout, "dinerdash-server listening on {addr}");
    let _ = stdout.flush();
    drop(stdout);

    shutdown::serve_until_signal(|stop| server::run(listener, config, stop))
        .await
        .map_err(|e| e.to_string())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Eval(args)) => run_eval(&args),
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
            let result = runtime()
                .map_err(|e| e.to_string())
                .and_then(|rt| rt.block_on(serve(cli.serve)));
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_and_sizes_parse_with_their_units() {
        assert_eq!(parse_duration("300"), Ok(Duration::from_secs(300)));
        assert_eq!(parse_duration("500ms"), Ok(Duration::from_millis(500)));
        assert_eq!(parse_duration(" 5m "), Ok(Duration::from_secs(300)));
        assert_eq!(parse_duration("1h"), Ok(Duration::from_secs(3600)));
        assert_eq!(parse_bytes("2GiB"), Ok(2 << 30));
        assert_eq!(parse_bytes("64KB"), Ok(64_000));
        assert_eq!(parse_bytes("1048576"), Ok(1 << 20));
        assert!(
            parse_duration("0s")
                .unwrap_err()
                .contains("greater than zero")
        );
        assert!(
            parse_duration("5d")
                .unwrap_err()
                .contains("use s, ms, m, h")
        );
        assert!(parse_bytes("1TiB").unwrap_err().contains("unknown unit"));
        assert!(parse_bytes("x").unwrap_err().contains("number of bytes"));
        assert!(
            parse_bytes("99999999999GiB")
                .unwrap_err()
                .contains("too large")
        );
    }
}
