//! What the `serve` command's flags decide, before anything is bound: [`ServeArgs`] (the flags
//! themselves, parsed by the binary), and [`ServerConfig::from_args`], which reads the TLS and
//! tenants files, turns the tenants into tokens, and refuses what the server must not start
//! with ([`ServeArgs::validate`]): a token too weak to be one, or a port open beyond this
//! machine without a token (gRPC and the web endpoint) or without TLS (the web endpoint) unless
//! `--insecure` says the network is trusted. Library users (tests, embeddings) build a
//! [`ServerConfig`] directly. No `Debug` output of these types holds a token or a private key.

use std::fmt;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use clap::ValueEnum;

use crate::auth::{Roster, Secret, TenantRules, Token, TokenError, check_token};
use crate::budget::{DEFAULT_MAX_MEMORY, DEFAULT_TENANT_ENVS, DEFAULT_TENANT_ROLLOUTS, Share};
use crate::connections::calls::calls_held;
use crate::connections::{self, DEFAULT_MAX_CONNECTIONS};
use crate::pools::{DEFAULT_PARALLEL_MIN_ENVS, DEFAULT_PARALLEL_MIN_PLANNER_ENVS, Stepping};
use crate::rollout::{self, MAX_ROLLOUT_WORK_STEPS};
use crate::session::{DEFAULT_MAX_ENVS_PER_SESSION, DEFAULT_MAX_SESSIONS, Limits};

/// Default `--max-shm-sessions`: each holds a region (~240 bytes an environment), stepped by
/// its client process's thread.
pub const DEFAULT_MAX_SHM_SESSIONS: u32 = 64;

/// How log lines are written (to stderr).
// The variants' doc comments would show in `--help`; the flag's own help says enough.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    Text,
    Json,
}

/// The server's flags (used when no subcommand is given).
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on. Any other than a loopback one (127.0.0.1, ::1, localhost) needs a
    /// token (DINERDASH_AUTH_TOKEN or --auth-tokens-file), or --insecure.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    /// Port to listen on; 0 picks a free one (printed on stdout).
    #[arg(long, default_value_t = 50051)]
    pub port: u16,
    /// Most live sessions.
    #[arg(long, default_value_t = DEFAULT_MAX_SESSIONS, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_sessions: u32,
    /// Most environments in one session.
    #[arg(long, default_value_t = DEFAULT_MAX_ENVS_PER_SESSION, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub max_envs_per_session: u32,
    /// Close sessions idle this long: seconds, or a number with ms, s, m or h ("5m").
    #[arg(long, default_value = "300", value_parser = parse_duration)]
    pub session_ttl: Duration,
    /// Log line format on stderr (the level comes from RUST_LOG, default info).
    #[arg(long, value_enum, default_value = "text")]
    pub log_format: LogFormat,
    /// Most bytes sessions and Rollout streams may hold: bytes, or with KiB, MiB, GiB ("2GiB").
    /// Requests that would pass it are refused with RESOURCE_EXHAUSTED.
    #[arg(long, default_value_t = DEFAULT_MAX_MEMORY, value_parser = parse_bytes)]
    pub max_memory: u64,
    /// Most environments one tenant may hold: a tenant of --auth-tokens-file (unless its line
    /// says otherwise), the shared token (all its connections together), or, without any
    /// token, one connection.
    #[arg(long, default_value_t = DEFAULT_TENANT_ENVS)]
    pub max_envs_per_tenant: u64,
    /// Most steps one Rollout request may record over all its episodes.
    #[arg(long, default_value_t = MAX_ROLLOUT_WORK_STEPS, value_parser = clap::value_parser!(u64).range(1..))]
    pub max_rollout_work_steps: u64,
    /// Most Rollout streams one tenant (as for --max-envs-per-tenant) may run at once.
    #[arg(long, default_value_t = DEFAULT_TENANT_ROLLOUTS)]
    pub max_rollouts_per_tenant: u64,
    /// Most client connections, capped below the open-file limit. At the limit the longest-idle
    /// connection with no call in flight is closed to admit a new one; when every connection has
    /// a call in flight, new ones are answered RESOURCE_EXHAUSTED and closed.
    #[arg(long, default_value_t = DEFAULT_MAX_CONNECTIONS as u32, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_connections: u32,
    /// Most connections from one peer address that have made no authenticated call (default:
    /// a quarter of --max-connections): at it, a new one from that address closes the longest
    /// idle of them. A tenant's connections (from its first call with a token) do not count.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_connections_per_address: Option<u32>,
    /// Close connections silent this long (live clients answer keepalive pings every 30 s).
    #[arg(long, default_value = "120", value_parser = parse_duration)]
    pub idle_timeout: Duration,
    /// Serve web pages over HTTP on this port of --http-host: the live sessions at `/`, any
    /// environment playing at `/watch/{session_id}?env=K`, and Prometheus metrics at `/metrics`
    /// (--metrics-port is the same flag).
    #[arg(long, alias = "metrics-port")]
    pub http_port: Option<u16>,
    /// Address of the HTTP endpoint: local only by default, whatever --host is. Any other
    /// address needs a token (DINERDASH_AUTH_TOKEN or --auth-tokens-file), whose tokens the
    /// pages then ask for, and --tls-cert/--tls-key (the endpoint serves HTTPS with them), or
    /// --insecure (--metrics-host is the same flag).
    #[arg(long, alias = "metrics-host", default_value = "127.0.0.1")]
    pub http_host: String,
    /// A host name the web endpoint answers to besides its own address, IP literals,
    /// localhost (when it listens on loopback or on every address) and the TLS certificate's
    /// names; repeatable. Requests naming any other `Host` are refused 421 (DNS rebinding).
    #[arg(long = "http-allowed-host", value_name = "NAME")]
    pub http_allowed_hosts: Vec<String>,
    /// Serve grpc.health.v1, and only it, on this port of --host, plaintext and without a token,
    /// for orchestrators' probes; 0 picks a free one (printed on stdout after the gRPC port).
    /// The gRPC port then serves health only to callers with a token, like any call.
    #[arg(long)]
    pub probe_port: Option<u16>,
    /// Require `authorization: Bearer <token>` on every RPC (health checks excepted): at least
    /// 16 visible ASCII characters, no `#`. Prefer the environment variable: flags show in `ps`.
    #[arg(long, env = "DINERDASH_AUTH_TOKEN", hide_env_values = true)]
    pub auth_token: Option<Secret>,
    /// Tenants, one a line: `NAME TOKEN [envs=N] [sessions=N] [rollouts=N] [connections=N]
    /// [streams=N]`; `#` starts a comment at the start of a line or after whitespace. Each
    /// token is accepted like --auth-token (and follows its rules), and its requests count
    /// against its tenant's share: by default an equal part of --max-sessions, of
    /// --max-connections and of the calls open at once for each tenant (and the shared token,
    /// if given, which must differ from every tenant's). Read again on SIGHUP.
    #[arg(long)]
    pub auth_tokens_file: Option<PathBuf>,
    /// Start even where a port is open beyond this machine without a token (--host), or the
    /// web endpoint without a token or TLS (--http-host): say so only on a trusted network.
    #[arg(long)]
    pub insecure: bool,
    /// PEM certificate chain: serve TLS (needs --tls-key).
    #[arg(long, requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// On SIGTERM/SIGINT, serve the sessions left for this long at most (seconds, or with ms,
    /// s, m or h) while refusing new ones, then stop; 0 stops at once. A second signal stops at
    /// once. Give orchestrators a longer grace period (terminationGracePeriodSeconds).
    #[arg(long, default_value = "30", value_parser = parse_drain_timeout)]
    pub drain_timeout: Duration,
    /// Most sessions stepped through shared memory at once (clients on this host, running as
    /// this user; Linux): each holds a region counted in --max-memory, stepped by one thread per
    /// client process. 0 offers none: every client steps over gRPC.
    #[arg(long, default_value_t = DEFAULT_MAX_SHM_SESSIONS)]
    pub max_shm_sessions: u32,
    /// Threads that step one large session's environments in chunks at once (default: one per
    /// core); 1 steps every session on the thread serving it.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub step_threads: Option<u32>,
    /// Sessions of at least this many environments are stepped (and reset) in parallel on the
    /// --step-threads; smaller ones on the thread serving them.
    #[arg(long, default_value_t = DEFAULT_PARALLEL_MIN_ENVS as u32, value_parser = clap::value_parser!(u32).range(1..))]
    pub parallel_min_envs: u32,
    /// Sessions with planner expert actions are stepped in parallel from this many
    /// environments (a planner decision costs as much as hundreds of plain steps).
    #[arg(long, default_value_t = DEFAULT_PARALLEL_MIN_PLANNER_ENVS as u32, value_parser = clap::value_parser!(u32).range(1..))]
    pub parallel_min_planner_envs: u32,
}

/// Why the flags describe no server that may start.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// A file named by a flag could not be read.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The tenants file is not UTF-8.
    #[error("{} is not UTF-8", .0.display())]
    NotUtf8(PathBuf),
    /// A line of the tenants file is malformed.
    #[error("{}: {message}", path.display())]
    Tenants {
        /// The file.
        path: PathBuf,
        /// Which line, and what is wrong with it.
        message: String,
    },
    /// `--http-host` is not local and no token protects the pages and metrics.
    #[error(
        "--http-host {0} publishes the sessions and metrics beyond this machine: give a token \
         too, DINERDASH_AUTH_TOKEN=$(openssl rand -hex 32) in the environment (or \
         --auth-token) or --auth-tokens-file (the pages then ask for it, and scrapers send it \
         as a bearer token), or pass --insecure if the network is trusted"
    )]
    PublicHttp(String),
    /// `--http-host` is not local and the endpoint would send its tokens in plain HTTP.
    #[error(
        "--http-host {0} serves the web pages and metrics beyond this machine in plain HTTP, \
         where their bearer tokens would cross the network in clear: give --tls-cert and \
         --tls-key (the endpoint then serves HTTPS with the certificate of gRPC), or pass \
         --insecure if the network is trusted"
    )]
    PlaintextHttp(String),
    /// `--host` is not local and no token says who may call.
    #[error(
        "--host {0} serves gRPC beyond this machine, where anyone who reaches the port could \
         use it: give a token, DINERDASH_AUTH_TOKEN=$(openssl rand -hex 32) in the environment \
         (clients send the same variable; --auth-token works too but shows in `ps`), or \
         --auth-tokens-file with a token per tenant; or pass --insecure if the network is \
         trusted"
    )]
    PublicGrpc(String),
    /// `--auth-token` (or `DINERDASH_AUTH_TOKEN`) breaks a token rule.
    #[error("--auth-token (or DINERDASH_AUTH_TOKEN): {0}")]
    AuthToken(TokenError),
}

/// Whether `host` names this machine only: `localhost`, or a loopback address (`127.0.0.0/8`,
/// `::1`, bracketed or not). Any other name, even one that resolves to a loopback address, and
/// the wildcards `0.0.0.0` and `::`, count as beyond this machine.
pub fn is_loopback(host: &str) -> bool {
    let bare = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    bare.eq_ignore_ascii_case("localhost")
        || bare.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

impl ServeArgs {
    /// Refuses flags the server must not start with:
    ///
    /// - an `--auth-token` that breaks the token rules ([`check_token`]; an empty one is no
    ///   token);
    /// - gRPC served beyond this machine (a `--host` that is not [`is_loopback`]) without a
    ///   token;
    /// - pages and metrics served beyond this machine (`--http-host`) without a token, whose
    ///   tokens the endpoint would ask for, or without TLS, which would carry them in clear.
    ///
    /// `--insecure` lifts the last two. (A tokens file counts as a token:
    /// [`ServerConfig::from_args`] refuses one without a tenant, or with a bad token.)
    pub fn validate(&self) -> Result<(), ConfigError> {
        if let Some(token) = self.auth_token.as_ref().filter(|t| !t.is_empty()) {
            check_token(token.expose()).map_err(ConfigError::AuthToken)?;
        }
        match self.exposures().into_iter().next() {
            Some(exposed) if !self.insecure => Err(exposed),
            _ => Ok(()),
        }
    }

    /// What this server would serve beyond this machine unprotected (the refusals `--insecure`
    /// lifts), in the order [`ServeArgs::validate`] reports them; empty when nothing is.
    pub fn exposures(&self) -> Vec<ConfigError> {
        let has_token = self.auth_token.as_ref().is_some_and(|t| !t.is_empty())
            || self.auth_tokens_file.is_some();
        let mut exposed = Vec::new();
        if !is_loopback(&self.host) && !has_token {
            exposed.push(ConfigError::PublicGrpc(self.host.clone()));
        }
        if self.http_port.is_some() && !is_loopback(&self.http_host) {
            if !has_token {
                exposed.push(ConfigError::PublicHttp(self.http_host.clone()));
            }
            if self.tls_cert.is_none() {
                exposed.push(ConfigError::PlaintextHttp(self.http_host.clone()));
            }
        }
        exposed
    }

    /// What each tenant (or connection) may hold: `--max-envs-per-tenant`,
    /// `--max-rollouts-per-tenant`, any number of sessions (a tenant's and the shared token's
    /// sessions are then cut to their fair part: [`crate::auth::TenantRules`]).
    pub fn share(&self) -> Share {
        Share {
            max_envs: self.max_envs_per_tenant,
            max_sessions: u64::MAX,
            max_rollouts: self.max_rollouts_per_tenant,
            max_connections: u64::MAX,
            max_streams: u64::MAX,
        }
    }

    /// When and on how many threads large sessions step in parallel: `--step-threads`,
    /// `--parallel-min-envs`, `--parallel-min-planner-envs`.
    pub fn stepping(&self) -> Stepping {
        let default = Stepping::default();
        Stepping {
            threads: self.step_threads.map_or(default.threads, |t| t as usize),
            min_envs: self.parallel_min_envs as usize,
            min_planner_envs: self.parallel_min_planner_envs as usize,
        }
    }
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
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    const MS: &[(&str, u64)] = &[
        ("", 1000),
        ("s", 1000),
        ("ms", 1),
        ("m", 60_000),
        ("h", 3_600_000),
    ];
    parse_scaled(text, MS, "seconds", "5m").map(Duration::from_millis)
}

/// A duration as [`parse_duration`] reads it, or zero ("0", "0s").
pub fn parse_drain_timeout(text: &str) -> Result<Duration, String> {
    let number = ["ms", "s", "m", "h"]
        .iter()
        .find_map(|unit| text.trim().strip_suffix(unit))
        .unwrap_or(text)
        .trim();
    if number.parse::<u64>() == Ok(0) {
        return Ok(Duration::ZERO);
    }
    parse_duration(text)
}

/// "1073741824", "512MiB", "2GiB", "64KiB" (also KB, MB, GB as powers of 1000) as bytes.
pub fn parse_bytes(text: &str) -> Result<u64, String> {
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

/// A PEM certificate chain and its private key. Its `Debug` shows neither (the key is a
/// secret, the chain only long).
#[derive(Clone)]
pub struct TlsPem {
    /// The certificate chain, PEM.
    pub cert: Vec<u8>,
    /// The private key, PEM.
    pub key: Vec<u8>,
}

impl fmt::Debug for TlsPem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("TlsPem")
            .field("cert_bytes", &self.cert.len())
            .field("key", &"<redacted>")
            .finish()
    }
}

/// Everything the server (`server::run`) needs besides its listeners: values only, no socket.
#[derive(Debug, Default)]
pub struct ServerConfig {
    /// Session limits and the idle TTL.
    pub limits: Limits,
    /// The shared bearer token; `None` serves everyone (unless `tenants` is given), each
    /// connection then its own tenant. Its holders are one identity with one share.
    pub auth_token: Option<Secret>,
    /// Tenant tokens (`--auth-tokens-file`): each token's requests count against its tenant's
    /// share. Given with `auth_token`, either token is accepted.
    pub tenants: Vec<Token>,
    /// The file `tenants` came from: read again on SIGHUP ([`crate::reload`]); `None`: the
    /// tokens never change.
    pub tenants_file: Option<PathBuf>,
    /// What each connection may hold when the server has no token; what the shared token
    /// (`auth_token`) may hold, as one identity, with its sessions its fair part of
    /// `limits.max_sessions` ([`ServerConfig::tenant_rules`]); what a tenant of `tenants_file`
    /// may hold when its line says nothing else.
    pub connection_share: Share,
    /// How long the sessions left are served once the shutdown future completes, while new
    /// ones are refused (`--drain-timeout`); zero (the default here) stops at once.
    pub drain_timeout: Duration,
    /// Connection limit and idle timeout.
    pub connections: connections::Limits,
    /// What one Rollout request may do.
    pub rollout: rollout::Limits,
    /// Serve TLS with this identity, gRPC and the web endpoint alike; `None` serves plaintext.
    pub tls: Option<TlsPem>,
    /// Host names the web endpoint answers to besides its own address, IP literals, localhost
    /// (on a loopback or wildcard address) and the certificate's names (`--http-allowed-host`):
    /// a request naming another `Host` is refused, so that a DNS name rebound to this machine
    /// cannot reach the pages from a browser.
    pub http_allowed_hosts: Vec<String>,
    /// Most sessions stepped through shared memory at once; 0 (the default of a library
    /// embedding; the binary's is [`DEFAULT_MAX_SHM_SESSIONS`]) offers none.
    pub max_shm_sessions: usize,
}

fn read(path: &Path) -> Result<Vec<u8>, ConfigError> {
    std::fs::read(path).map_err(|source| ConfigError::Read {
        path: path.to_owned(),
        source,
    })
}

/// The tenants of the tokens file at `path`, by `rules` ([`TenantRules::lines`]).
pub fn read_tenants(
    path: &Path,
    rules: &TenantRules,
) -> Result<Vec<crate::auth::TenantLine>, ConfigError> {
    let text = String::from_utf8(read(path)?).map_err(|_| ConfigError::NotUtf8(path.to_owned()))?;
    rules.lines(&text).map_err(|message| ConfigError::Tenants {
        path: path.to_owned(),
        message,
    })
}

impl ServerConfig {
    /// What the tenants of a tokens file may hold unless their lines say otherwise, and the
    /// shared token their tokens must differ from.
    pub fn tenant_rules(&self) -> TenantRules {
        TenantRules {
            share: self.connection_share,
            max_sessions: self.limits.max_sessions as u64,
            max_connections: self.connections.max_connections as u64,
            max_calls: calls_held(self.limits.max_memory),
            shared_token: self.auth_token.clone(),
        }
    }

    /// The configuration `args` describe: the TLS files read, the tenants file's tenants as
    /// tokens, the limits; refused unless [`ServeArgs::validate`] passes. Nothing is bound: the
    /// caller binds the listeners and hands them to `server::run`.
    pub fn from_args(args: &ServeArgs) -> Result<ServerConfig, ConfigError> {
        let tls = match (&args.tls_cert, &args.tls_key) {
            (Some(cert), Some(key)) => Some(TlsPem {
                cert: read(cert)?,
                key: read(key)?,
            }),
            _ => None,
        };
        let share = args.share();
        let auth_token = args.auth_token.clone().filter(|t| !t.is_empty());
        let rules = TenantRules {
            share,
            max_sessions: u64::from(args.max_sessions),
            max_connections: u64::from(args.max_connections),
            max_calls: calls_held(args.max_memory),
            shared_token: auth_token.clone(),
        };
        let tenants = match &args.auth_tokens_file {
            Some(path) => Roster::default().tokens(read_tenants(path, &rules)?),
            None => Vec::new(),
        };
        args.validate()?;
        Ok(ServerConfig {
            limits: Limits {
                max_sessions: args.max_sessions as usize,
                max_envs_per_session: args.max_envs_per_session as usize,
                session_ttl: args.session_ttl,
                max_memory: args.max_memory,
                stepping: args.stepping(),
            },
            rollout: rollout::Limits {
                max_work_steps: args.max_rollout_work_steps,
            },
            auth_token,
            tenants,
            tenants_file: args.auth_tokens_file.clone(),
            connection_share: share,
            drain_timeout: args.drain_timeout,
            connections: connections::Limits {
                max_connections: args.max_connections as usize,
                idle_timeout: args.idle_timeout,
                max_connections_per_address: args.max_connections_per_address.map(|n| n as usize),
                ..connections::Limits::default()
            },
            tls,
            http_allowed_hosts: args.http_allowed_hosts.clone(),
            max_shm_sessions: args.max_shm_sessions as usize,
        })
    }

    /// Every token the server accepts: the tenants' and `auth_token` (which stands for no
    /// tenant: its requests are the shared identity's, counted against the shared token's share).
    pub fn tokens(&self) -> Vec<Token> {
        let mut tokens = self.tenants.clone();
        if let Some(token) = &self.auth_token {
            tokens.push(Token {
                token: token.clone(),
                tenant: None,
            });
        }
        tokens
    }

    /// Whether the server asks for a token.
    pub fn has_tokens(&self) -> bool {
        self.auth_token.is_some() || !self.tenants.is_empty()
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
        assert_eq!(parse_drain_timeout("0"), Ok(Duration::ZERO));
        assert_eq!(parse_drain_timeout("0s"), Ok(Duration::ZERO));
        assert_eq!(parse_drain_timeout("45"), Ok(Duration::from_secs(45)));
        assert!(parse_drain_timeout("-1").is_err());
        assert!(parse_bytes("1TiB").unwrap_err().contains("unknown unit"));
        assert!(parse_bytes("x").unwrap_err().contains("number of bytes"));
        assert!(
            parse_bytes("99999999999GiB")
                .unwrap_err()
                .contains("too large")
        );
    }

    #[derive(Debug, clap::Parser)]
    struct Flags {
        #[command(flatten)]
        serve: ServeArgs,
    }

    fn flags(args: &[&str]) -> ServeArgs {
        use clap::Parser as _;
        Flags::parse_from(std::iter::once("dinerdash-server").chain(args.iter().copied())).serve
    }

    #[test]
    fn the_drain_timeout_defaults_to_the_documented_one() {
        assert_eq!(
            flags(&[]).drain_timeout,
            crate::shutdown::DEFAULT_DRAIN_TIMEOUT
        );
        assert_eq!(
            flags(&["--drain-timeout", "0"]).drain_timeout,
            Duration::ZERO
        );
    }

    #[test]
    fn stepping_flags_reach_the_limits() {
        let defaults = ServerConfig::from_args(&flags(&[]))
            .unwrap()
            .limits
            .stepping;
        assert_eq!(defaults, Stepping::default());
        let args = [
            "--step-threads",
            "3",
            "--parallel-min-envs",
            "100",
            "--parallel-min-planner-envs",
            "2",
        ];
        let stepping = ServerConfig::from_args(&flags(&args))
            .unwrap()
            .limits
            .stepping;
        let expected = Stepping {
            threads: 3,
            min_envs: 100,
            min_planner_envs: 2,
        };
        assert_eq!(stepping, expected);
    }

    #[test]
    fn metrics_beyond_this_machine_need_a_token() {
        let public = ["--metrics-port", "9000", "--metrics-host", "0.0.0.0"];
        let refused = ServerConfig::from_args(&flags(&public)).unwrap_err();
        assert!(matches!(&refused, ConfigError::PublicHttp(host) if host == "0.0.0.0"));
        assert!(
            refused.to_string().contains("--auth-tokens-file"),
            "{refused}"
        );
        let token = ["--auth-token", "0123456789abcdef"];
        let with_token = [&public[..], &token].concat();
        let plaintext = ServerConfig::from_args(&flags(&with_token)).unwrap_err();
        assert!(matches!(&plaintext, ConfigError::PlaintextHttp(host) if host == "0.0.0.0"));
        assert!(plaintext.to_string().contains("--tls-cert"), "{plaintext}");
        let trusted = [&with_token[..], &["--insecure"]].concat();
        let config = ServerConfig::from_args(&flags(&trusted)).unwrap();
        assert!(config.has_tokens());
        assert_eq!(config.tokens().len(), 1);
        let local = ["--metrics-port", "9000", "--metrics-host", "localhost"];
        assert!(
            !ServerConfig::from_args(&flags(&local))
                .unwrap()
                .has_tokens()
        );
        // An empty --auth-token is no token.
        let empty = [&public[..], &["--auth-token", ""]].concat();
        assert!(flags(&empty).validate().is_err());
    }

    #[test]
    fn the_tenants_file_becomes_tokens() {
        let dir = std::env::temp_dir().join(format!("dinerdash-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("tenants");
        std::fs::write(
            &file,
            "team-a aaaaaaaaaaaaaaaa envs=8\nteam-b bbbbbbbbbbbbbbbb\n",
        )
        .unwrap();
        let path = file.to_str().unwrap();
        let config =
            ServerConfig::from_args(&flags(&["--auth-tokens-file", path, "--max-sessions", "7"]))
                .unwrap();
        assert_eq!(config.limits.max_sessions, 7);
        let tokens = config.tokens();
        assert_eq!(tokens.len(), 2);
        let team_a = tokens[0].tenant.as_ref().unwrap();
        assert_eq!(
            (tokens[0].token.expose(), team_a.name()),
            ("aaaaaaaaaaaaaaaa", "tenant team-a")
        );
        std::fs::write(&file, "team-a\n").unwrap();
        let bad = ServerConfig::from_args(&flags(&["--auth-tokens-file", path])).unwrap_err();
        assert!(
            bad.to_string().starts_with(&format!("{path}: line 1: ")),
            "{bad}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
        let missing = ServerConfig::from_args(&flags(&["--auth-tokens-file", path])).unwrap_err();
        assert!(matches!(missing, ConfigError::Read { .. }), "{missing}");
    }

    #[test]
    fn grpc_beyond_this_machine_needs_a_token_or_insecure() {
        for local in [
            "127.0.0.1",
            "127.0.0.2",
            "::1",
            "[::1]",
            "localhost",
            "LocalHost",
        ] {
            assert!(is_loopback(local), "{local}");
            flags(&["--host", local]).validate().unwrap();
        }
        for public in [
            "0.0.0.0",
            "::",
            "10.0.0.7",
            "gpu-box",
            "localhost.example.com",
        ] {
            assert!(!is_loopback(public), "{public}");
            let refused = flags(&["--host", public]).validate().unwrap_err();
            assert!(matches!(&refused, ConfigError::PublicGrpc(h) if h == public));
            let message = refused.to_string();
            for hint in ["DINERDASH_AUTH_TOKEN", "--auth-tokens-file", "--insecure"] {
                assert!(message.contains(hint), "{message}");
            }
            flags(&["--host", public, "--insecure"]).validate().unwrap();
            let token = ["--auth-token", "0123456789abcdef"];
            flags(&[&["--host", public][..], &token].concat())
                .validate()
                .unwrap();
            assert!(
                flags(&["--host", public, "--auth-tokens-file", "t"])
                    .exposures()
                    .is_empty()
            );
        }
        // An empty token is no token.
        let empty = flags(&["--host", "0.0.0.0", "--auth-token", ""]);
        assert!(matches!(empty.validate(), Err(ConfigError::PublicGrpc(_))));
    }

    #[test]
    fn weak_tokens_are_refused_at_start() {
        for (token, why) in [
            ("s3cret", "fewer than 16"),
            ("0123456789#abcdef", "`#`"),
            ("0123456789 abcdef", "space"),
        ] {
            let refused = flags(&["--auth-token", token]).validate().unwrap_err();
            let message = refused.to_string();
            assert!(matches!(refused, ConfigError::AuthToken(_)), "{message}");
            assert!(message.contains(why), "{message}");
            assert!(
                !message.contains(token),
                "the error repeats the token: {message}"
            );
        }
        flags(&["--auth-token", "0123456789abcdef"])
            .validate()
            .unwrap();
    }

    #[test]
    fn debug_of_the_config_holds_no_secret() {
        let secret = "0123456789abcdef-very-secret";
        let dir = std::env::temp_dir().join(format!("dinerdash-debug-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("tenants");
        std::fs::write(&file, format!("team-a {secret}-a\n")).unwrap();
        let args = flags(&[
            "--auth-token",
            secret,
            "--auth-tokens-file",
            file.to_str().unwrap(),
        ]);
        let mut config = ServerConfig::from_args(&args).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        config.tls = Some(TlsPem {
            cert: b"CERT".to_vec(),
            key: b"-----BEGIN PRIVATE KEY----- key-bytes".to_vec(),
        });
        assert_eq!(config.tokens().len(), 2);
        for shown in [
            format!("{args:?}"),
            format!("{args:#?}"),
            format!("{config:?}"),
            format!("{:?}", config.tokens()),
            format!("{:?}", crate::auth::Tokens::new(&config.tokens())),
        ] {
            assert!(!shown.contains(secret), "{shown}");
            assert!(!shown.contains("key-bytes"), "{shown}");
        }
    }
}
