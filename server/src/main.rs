//! The `dinerdash-server` command: parses the command line and hands over to the library.
//! Without a subcommand it serves gRPC ([`dinerdash_server::server::run`]); `eval` plays a
//! policy locally; `health` probes a running server (the Docker HEALTHCHECK).

use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use dinerdash_server::eval::evaluate;
use dinerdash_server::expert::PolicyKind;
use dinerdash_server::server::{self, ServerConfig, TlsPem};
use dinerdash_server::session::{DEFAULT_MAX_ENVS_PER_SESSION, DEFAULT_MAX_SESSIONS, Limits};
use dinerdash_server::shutdown;
use dinerdash_server::sim::Config;
use tokio_rustls::rustls::client::WebPkiServerVerifier;
use tokio_rustls::rustls::client::danger::{
    HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier,
};
use tokio_rustls::rustls::pki_types::{CertificateDer, ServerName, UnixTime, pem::PemObject};
use tokio_rustls::rustls::{self, DigitallySignedStruct, RootCertStore, SignatureScheme};

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
    /// Serve Prometheus metrics over HTTP on this port of --host.
    #[arg(long)]
    metrics_port: Option<u16>,
    /// Require `authorization: Bearer <token>` on every RPC (health checks excepted).
    #[arg(long, env = "DINERDASH_AUTH_TOKEN", hide_env_values = true)]
    auth_token: Option<String>,
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

/// "300", "300s", "500ms", "5m", "1h" as a non-zero duration.
fn parse_duration(text: &str) -> Result<Duration, String> {
    let text = text.trim();
    let split = text
        .find(|c: char| !c.is_ascii_digit())
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let n: u64 = number
        .parse()
        .map_err(|_| format!("expected a number of seconds or e.g. 5m, got {text:?}"))?;
    let duration = match unit.trim() {
        "" | "s" => Duration::from_secs(n),
        "ms" => Duration::from_millis(n),
        "m" => Duration::from_secs(n.saturating_mul(60)),
        "h" => Duration::from_secs(n.saturating_mul(3600)),
        other => return Err(format!("unknown unit {other:?}: use ms, s, m or h")),
    };
    if duration.is_zero() {
        return Err("must be greater than zero".into());
    }
    Ok(duration)
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
    let listener = tokio::net::TcpListener::bind((args.host.as_str(), args.port))
        .await
        .map_err(|e| format!("cannot listen on {}:{}: {e}", args.host, args.port))?;
    let metrics_listener = match args.metrics_port {
        Some(port) => Some(
            tokio::net::TcpListener::bind((args.host.as_str(), port))
                .await
                .map_err(|e| format!("cannot listen on {}:{port} for metrics: {e}", args.host))?,
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
        },
        auth_token: args.auth_token.filter(|t| !t.is_empty()),
        tls,
        metrics_listener,
    };
    tracing::info!(
        %addr,
        tls = config.tls.is_some(),
        auth = config.auth_token.is_some(),
        max_sessions = config.limits.max_sessions,
        max_envs_per_session = config.limits.max_envs_per_session,
        session_ttl_s = config.limits.session_ttl.as_secs_f64(),
        "serving"
    );
    // The one line on stdout: clients that started this process read the port from it.
    let mut stdout = std::io::stdout().lock();
    let _ = writeln!(stdout, "dinerdash-server listening on {addr}");
    let _ = stdout.flush();
    drop(stdout);

    let (signalled, drain) = tokio::sync::oneshot::channel();
    let stop = async move {
        shutdown::signal().await;
        let _ = signalled.send(());
    };
    let deadline = async move {
        if drain.await.is_ok() {
            tokio::time::sleep(shutdown::DRAIN_DEADLINE).await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        served = server::run(listener, config, stop) => served.map_err(|e| e.to_string()),
        () = deadline => {
            tracing::warn!(
                "RPCs still running {} s after the signal; exiting anyway",
                shutdown::DRAIN_DEADLINE.as_secs()
            );
            Ok(())
        }
    }
}

/// One grpc.health.v1 Check; Ok(true) when SERVING.
async fn check_health(args: &HealthArgs) -> Result<bool, String> {
    use tonic::transport::Endpoint;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

    // With --tls-ca the TLS is ours (see `tls_connector`) and tonic speaks HTTP/2 over it.
    let endpoint = Endpoint::from_shared(format!("http://{}", args.address))
        .map_err(|e| format!("bad address {:?}: {e}", args.address))?
        .connect_timeout(args.timeout)
        .timeout(args.timeout);
    let check = async {
        let channel = match &args.tls_ca {
            Some(ca) => {
                let connector = tls_connector(&args.address, ca)?;
                endpoint.connect_with_connector(connector).await
            }
            None => endpoint.connect().await,
        }
        .map_err(|e| format!("cannot connect: {}", error_chain(&e)))?;
        let reply = HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: args.service.clone(),
            })
            .await
            .map_err(|s| format!("{:?}: {}", s.code(), s.message()))?;
        let status = reply.into_inner().status();
        println!("{}", status.as_str_name());
        Ok(status == tonic_health::pb::health_check_response::ServingStatus::Serving)
    };
    tokio::time::timeout(args.timeout, check)
        .await
        .map_err(|_| format!("no answer within {:?}", args.timeout))?
}

/// An error and its sources, so that "transport error" says which TLS check failed.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(&format!(": {s}"));
        source = s.source();
    }
    text
}

/// Opens TCP to `address` and TLS over it, trusting the PEM certificates of `ca`, for tonic's
/// `connect_with_connector`.
fn tls_connector(
    address: &str,
    ca: &std::path::Path,
) -> Result<
    impl tower::Service<
        tonic::codegen::http::Uri,
        Response = hyper_util::rt::TokioIo<tokio_rustls::client::TlsStream<tokio::net::TcpStream>>,
        Error = std::io::Error,
        Future = impl Send,
    > + Clone
    + Send
    + 'static,
    String,
> {
    let pem = std::fs::read(ca).map_err(|e| format!("cannot read {}: {e}", ca.display()))?;
    let verifier = SelfSignedOrCa::new(&pem).map_err(|e| format!("{}: {e}", ca.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| format!("TLS: {e}"))?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(verifier))
        .with_no_client_auth();
    config.alpn_protocols = vec![b"h2".to_vec()];
    let host = address
        .rsplit_once(':')
        .map_or(address, |(host, _)| host)
        .trim_start_matches('[')
        .trim_end_matches(']');
    let name = ServerName::try_from(host.to_owned())
        .map_err(|e| format!("bad host name {host:?}: {e}"))?;
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    let address = address.to_owned();
    Ok(tower::service_fn(move |_: tonic::codegen::http::Uri| {
        let (connector, name, address) = (connector.clone(), name.clone(), address.clone());
        async move {
            let tcp = tokio::net::TcpStream::connect(&address).await?;
            let tls = connector.connect(name, tcp).await?;
            Ok(hyper_util::rt::TokioIo::new(tls))
        }
    }))
}

/// The usual WebPKI checks against the --tls-ca certificates, plus one exception: a server
/// certificate that is byte for byte one of them is trusted as is. webpki refuses a CA
/// certificate as a server's own ("CaUsedAsEndEntity"), yet a self-signed certificate made with
/// `openssl req -x509` is exactly that, and the operator who names it as the CA trusts it.
#[derive(Debug)]
struct SelfSignedOrCa {
    webpki: Arc<WebPkiServerVerifier>,
    pinned: Vec<CertificateDer<'static>>,
}

impl SelfSignedOrCa {
    fn new(pem: &[u8]) -> Result<SelfSignedOrCa, String> {
        let pinned = CertificateDer::pem_slice_iter(pem)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| format!("not PEM certificates: {e}"))?;
        if pinned.is_empty() {
            return Err("no PEM certificate in it".into());
        }
        let mut roots = RootCertStore::empty();
        for cert in &pinned {
            roots
                .add(cert.clone())
                .map_err(|e| format!("unusable certificate: {e}"))?;
        }
        let webpki = WebPkiServerVerifier::builder_with_provider(
            Arc::new(roots),
            Arc::new(rustls::crypto::ring::default_provider()),
        )
        .build()
        .map_err(|e| format!("unusable certificates: {e}"))?;
        Ok(SelfSignedOrCa { webpki, pinned })
    }
}

impl ServerCertVerifier for SelfSignedOrCa {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        server_name: &ServerName<'_>,
        ocsp_response: &[u8],
        now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        match self.webpki.verify_server_cert(
            end_entity,
            intermediates,
            server_name,
            ocsp_response,
            now,
        ) {
            Ok(verified) => Ok(verified),
            Err(_)
                if self
                    .pinned
                    .iter()
                    .any(|c| c.as_ref() == end_entity.as_ref()) =>
            {
                Ok(ServerCertVerified::assertion())
            }
            Err(e) => Err(e),
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.webpki.verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.webpki.verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.webpki.supported_verify_schemes()
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Some(Command::Eval(args)) => run_eval(&args),
        Some(Command::Health(args)) => {
            let result = runtime()
                .map_err(|e| e.to_string())
                .and_then(|rt| rt.block_on(check_health(&args)));
            match result {
                Ok(true) => ExitCode::SUCCESS,
                Ok(false) => ExitCode::FAILURE,
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
