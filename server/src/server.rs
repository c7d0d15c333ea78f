//! Puts the server together: the `DinerDash` service behind the request gate, the standard
//! `grpc.health.v1` service, server reflection, optional TLS (for gRPC and the HTTP endpoint
//! alike), the idle-session sweeper and the HTTP endpoint (pages, feeds, metrics), served on the
//! [`Listeners`] the caller bound until a shutdown future completes ([`run`]).
//!
//! With a probe listener (`--probe-port`), `grpc.health.v1` alone is also served there,
//! plaintext and without a token, for orchestrators' probes, under caps of its own
//! ([`serve_probes`]); the gRPC port then serves health only behind the token check.
//!
//! The binary calls [`serve`], which binds `--host:--port` (and `--http-host:--http-port`,
//! `--host:--probe-port`) and runs it under [`crate::shutdown::serve_until_signal`] (the first
//! SIGINT/SIGTERM starts the drain); tests bind `127.0.0.1:0` and pass a oneshot to [`run`].

use std::future::Future;
use std::io::Write as _;
use std::sync::Arc;

use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Identity, Server, ServerTlsConfig};

pub use crate::config::{ServerConfig, TlsPem};

use crate::audit::{Audit, MethodLayer};
use crate::auth::{RequestGate, Roster, Tokens};
use crate::budget::{Budget, Share, Tenant};
use crate::codec::intake::IntakeLayer;
use crate::config::{ConfigError, ServeArgs};
use crate::connections::calls::{Admit, Admitted, ProbeLayer};
use crate::connections::{self, KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT, MAX_STREAMS_PER_CONNECTION};
use crate::http::{self, Access, Exposure, HttpTls, Site, TlsError};
use crate::metrics::Metrics;
use crate::pb;
use crate::pb::diner_dash_server::DinerDashServer;
use crate::reload::{Hangups, Reloader};
use crate::service::{DinerDashService, MAX_MESSAGE_BYTES};
use crate::session::Store;
use crate::shutdown;

/// The grpc.health.v1 service name that stays SERVING while the server drains, for liveness
/// probes (a draining server is alive; it only takes no new sessions).
pub const LIVENESS_SERVICE: &str = "liveness";

/// Most connections the probe listener serves at once; at the limit it sheds the longest-idle
/// one, as the gRPC port does. Probes open a connection each (the kubelet's) or keep one.
pub const PROBE_MAX_CONNECTIONS: usize = 64;

/// Why the server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The gRPC transport (TLS configuration, accepting connections).
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// The reflection service could not read the descriptors.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The flags describe no server that may start.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The TLS certificate or key cannot serve the HTTP endpoint.
    #[error(transparent)]
    HttpTls(#[from] TlsError),
    /// A listener could not be bound.
    #[error("cannot listen on {addr}{purpose}: {source}")]
    Listen {
        /// `host:port`.
        addr: String,
        /// Empty for gRPC, " for the web pages" for the HTTP endpoint, " for the health probes"
        /// for the probe listener.
        purpose: &'static str,
        /// Why.
        source: std::io::Error,
    },
    /// The bound listener's address could not be read.
    #[error("cannot read the bound address: {0}")]
    LocalAddr(std::io::Error),
}

/// The `dinerdash-server` command: the configuration `args` describe
/// ([`ServerConfig::from_args`]), served on `--host:--port` (and the web pages and metrics on
/// `--http-host:--http-port`) until SIGINT/SIGTERM, with the drain deadline of
/// [`shutdown::serve_until_signal`]. Once bound, prints `dinerdash-server listening on ADDR`,
/// the one line on stdout: clients that started this process read the port from it.
pub async fn serve(args: &ServeArgs) -> Result<(), ServerError> {
    async fn bind(
        host: &str,
        port: u16,
        purpose: &'static str,
    ) -> Result<TcpListener, ServerError> {
        connections::bind(host, port)
            .await
            .map_err(|source| ServerError::Listen {
                addr: format!("{host}:{port}"),
                purpose,
                source,
            })
    }
    let config = ServerConfig::from_args(args)?;
    // What --insecure let through: said once, loudly, before anything is bound.
    for exposed in args.exposures() {
        tracing::warn!("--insecure: starting anyway, although {exposed}");
    }
    // Room for connections: the accept loop caps --max-connections below this limit.
    connections::fd_limit::raise();
    let listeners = Listeners {
        grpc: bind(&args.host, args.port, "").await?,
        http: match args.http_port {
            Some(port) => Some(bind(&args.http_host, port, " for the web pages").await?),
            None => None,
        },
        probe: match args.probe_port {
            Some(port) => Some(bind(&args.host, port, " for the health probes").await?),
            None => None,
        },
    };
    let addr = listeners
        .grpc
        .local_addr()
        .map_err(ServerError::LocalAddr)?;
    let probe_addr = listeners
        .probe
        .as_ref()
        .map(TcpListener::local_addr)
        .transpose()
        .map_err(ServerError::LocalAddr)?;
    tracing::info!(
        %addr,
        tls = config.tls.is_some(),
        auth = config.has_tokens(),
        tenants = config.tenants.len(),
        max_sessions = config.limits.max_sessions,
        max_envs_per_session = config.limits.max_envs_per_session,
        max_memory = config.limits.max_memory,
        max_connections = config.connections.max_connections,
        probe_addr = probe_addr.map(tracing::field::display),
        session_ttl_s = config.limits.session_ttl.as_secs_f64(),
        "serving"
    );
    // Both signals are listened for before the line below says the server is up, so that a
    // SIGTERM sent as soon as it is read drains the server rather than killing it.
    let signals = shutdown::Signals::new();
    // SIGHUP reads the tokens file again; without one it keeps its default (the process ends).
    let hangups = match &config.tenants_file {
        Some(_) => Hangups::listen(),
        None => Hangups::default(),
    };
    // The first line on stdout: clients that started this process read the port from it; the
    // probe port, if any, on the second.
    let mut stdout = std::io::stdout().lock();
    let _ = writeln!(stdout, "dinerdash-server listening on {addr}");
    if let Some(probe_addr) = probe_addr {
        let _ = writeln!(stdout, "dinerdash-server probes on {probe_addr}");
    }
    let _ = stdout.flush();
    drop(stdout);

    shutdown::serve_until_signal(signals, config.drain_timeout, |stop| {
        run_with_hangups(listeners, config, stop, hangups)
    })
    .await
}

/// Starts the shared-memory doorbell ([`crate::shm`]) for up to `max` sessions and returns its
/// name; empty when there is none (`max` is 0, not Linux, or the socket could not be made: the
/// clients then step over gRPC).
fn start_doorbell(store: &Store, max: usize, stopping: &shutdown::Shutdown) -> String {
    #[cfg(target_os = "linux")]
    if max > 0 {
        match crate::shm::Doorbell::start(store.clone(), max, stopping.clone()) {
            Ok(doorbell) => return doorbell.name().to_owned(),
            Err(e) => tracing::warn!(error = %e, "no shared-memory data plane"),
        }
    }
    let _ = (store, max, stopping);
    String::new()
}

/// The sockets a server serves, bound by its caller: [`serve`] binds them from the flags, tests
/// on `127.0.0.1:0`.
#[derive(Debug)]
pub struct Listeners {
    /// The gRPC services.
    pub grpc: TcpListener,
    /// The HTTP endpoint: the sessions and watch pages, their feeds, and Prometheus metrics,
    /// asking for the same tokens as the RPCs; `None` serves none.
    pub http: Option<TcpListener>,
    /// `grpc.health.v1` alone, plaintext, without a token, for orchestrators' probes; the gRPC
    /// listener then serves health behind the token check. `None`: health is served on the
    /// gRPC listener without a token.
    pub probe: Option<TcpListener>,
}

impl Listeners {
    /// gRPC on `grpc`, no HTTP endpoint.
    pub fn grpc(grpc: TcpListener) -> Listeners {
        Listeners {
            grpc,
            http: None,
            probe: None,
        }
    }
}

/// Serves `health` alone on `listener` until `stopping` fires (the server stops), plaintext and
/// without a token, so that an orchestrator's probes (the kubelet's gRPC probe speaks no TLS)
/// are not answered from the caps that the gRPC port's callers fill: the same bounds as the
/// gRPC port's calls outside the DinerDash service (a 1 KiB message, arriving within 10 s:
/// [`IntakeLayer`]), caps of its own ([`ProbeLayer`]: 256 calls, 32 a peer address; Watches
/// 64, 4 a peer address) and at most [`PROBE_MAX_CONNECTIONS`] connections. Any other path is
/// answered `UNIMPLEMENTED`.
async fn serve_probes<H: tonic_health::pb::health_server::Health>(
    listener: TcpListener,
    health: tonic_health::pb::health_server::HealthServer<H>,
    budget: Arc<Budget>,
    (limits, share): (connections::Limits, Share),
    metrics: Arc<Metrics>,
    stopping: shutdown::Shutdown,
) -> Result<(), tonic::transport::Error> {
    let limits = connections::Limits {
        max_connections: PROBE_MAX_CONNECTIONS,
        ..limits
    };
    let probe_layer = ProbeLayer::new(Arc::clone(&metrics));
    let incoming = connections::accept(listener, limits, share, metrics, stopping.clone());
    let mut stopped = stopping;
    Server::builder()
        .layer(probe_layer)
        .layer(IntakeLayer::new(budget))
        .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT))
        .add_service(health)
        .serve_with_incoming_shutdown(incoming, async move { stopped.wait().await })
        .await
}

/// Serves on `listeners` until `shutdown` completes, then drains (for `config.drain_timeout` at
/// most: see [`shutdown`]), stops accepting connections, lets the RPCs in flight finish, and
/// returns. With a `config.tenants_file`, SIGHUPs from now on read it again.
pub async fn run(
    listeners: Listeners,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServerError> {
    let hangups = match &config.tenants_file {
        Some(_) => Hangups::listen(),
        None => Hangups::default(),
    };
    run_with_hangups(listeners, config, shutdown, hangups).await
}

/// [`run`], the tokens file read again on each of `hangups` (listened for by the caller).
pub async fn run_with_hangups(
    listeners: Listeners,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send,
    hangups: Hangups,
) -> Result<(), ServerError> {
    // With a certificate, the endpoint speaks HTTPS only, with the same certificate as gRPC;
    // made first, so that a certificate it cannot use stops the server before anything runs.
    let exposure = Exposure {
        tls: match (&config.tls, &listeners.http) {
            (Some(tls), Some(_)) => Some(HttpTls::new(&tls.cert, &tls.key)?),
            _ => None,
        },
        allowed_hosts: config.http_allowed_hosts.clone(),
    };
    let metrics = Arc::new(Metrics::default());
    let store = Store::new(config.limits, Arc::clone(&metrics));
    let (trigger, stopping) = shutdown::channel();

    let sweeper = tokio::spawn(store.clone().sweep_until(stopping.clone()));
    let (sessions, drain_timeout) = (store.clone(), config.drain_timeout);
    let doorbell = start_doorbell(&store, config.max_shm_sessions, &stopping);
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<DinerDashServer<DinerDashService>>()
        .await;
    // Says whether the process is alive, for liveness probes: SERVING while draining too, when
    // the whole server ("") and DinerDash already say NOT_SERVING to readiness probes.
    health
        .set_service_status(LIVENESS_SERVICE, tonic_health::ServingStatus::Serving)
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    // The shared token is one identity: its connections share one share.
    let rules = config.tenant_rules();
    let shared = config.auth_token.as_ref().map(|_| {
        let share = rules.shared_share(config.tenants.len());
        Arc::new(Tenant::new("the shared token".into(), share))
    });
    let mut tokens = Tokens::new(&config.tokens());
    if let Some(shared) = &shared {
        tokens = tokens.with_shared_share(Arc::clone(shared));
    }
    let audit = Arc::new(Audit::new(Arc::clone(&metrics)));
    let gate = RequestGate::new(tokens.clone(), stopping.clone(), audit);
    let reloader = config.tenants_file.clone().map(|path| Reloader {
        path,
        rules,
        roster: Roster::new(&config.tenants),
        tokens: tokens.clone(),
        shared,
    });
    let reload_task = reloader.map(|r| tokio::spawn(r.on_hangups(hangups, stopping.clone())));
    // The pages' feeds and the metrics ask for the same tokens as the RPCs, so that a server
    // that needs a token shows its sessions and load only to its token holders.
    let http_addr = listeners.http.as_ref().and_then(|l| l.local_addr().ok());
    let http_task = listeners.http.map(|l| {
        if let Some(addr) = http_addr {
            let scheme = if exposure.tls.is_some() {
                "https"
            } else {
                "http"
            };
            tracing::info!(
                "sessions page on {scheme}://{addr}/, metrics on {scheme}://{addr}/metrics"
            );
        }
        let site = Site::new(store.clone(), Arc::clone(&metrics), Access::new(tokens));
        tokio::spawn(http::serve_exposed(
            l,
            Arc::new(site),
            stopping.clone(),
            exposure,
        ))
    });
    let budget = Arc::clone(store.budget());
    // The probe listener serves the same statuses: the drain below sets both at once.
    let probes = listeners.probe.map(|listener| {
        tokio::spawn(serve_probes(
            listener,
            health_service.clone(),
            Arc::clone(&budget),
            (config.connections, config.connection_share),
            Arc::clone(&metrics),
            stopping.clone(),
        ))
    });
    let service = DinerDashService::new(
        store,
        Arc::clone(&metrics),
        config.connection_share,
        stopping.clone(),
    )
    .with_http_addr(http_addr)
    .with_rollout_limits(config.rollout)
    .with_shm_doorbell(&doorbell);
    let dinerdash = DinerDashServer::new(service)
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    // Behind the token check: each call counted by identity and charged while it is open.
    let dinerdash = Admit::new(dinerdash, Admitted::new(Arc::clone(&budget)));

    // Live clients answer the keepalive pings, which keeps their connections out of the idle
    // timeout; dead ones do not, and are closed.
    let mut builder = Server::builder()
        // Health checks and reflection, open without a token, are few at once.
        .layer(ProbeLayer::new(Arc::clone(&metrics)))
        // The method of each request, for the audit of refused tokens.
        .layer(MethodLayer)
        // Large messages count against --max-memory while they are received and decoded.
        .layer(IntakeLayer::new(Arc::clone(&budget)))
        .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    if let Some(tls) = &config.tls {
        builder = builder
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert, &tls.key)))?;
    }
    // Health stays open without the token, so that orchestrators can probe it, unless they
    // probe the probe listener: then it is a call like any other, behind the token check.
    let router = if probes.is_some() {
        builder.add_service(InterceptedService::new(health_service, gate.clone()))
    } else {
        builder.add_service(health_service)
    };
    // The accept loop stops (and closes the port) when the trigger fires.
    let incoming = connections::accept(
        listeners.grpc,
        config.connections,
        config.connection_share,
        Arc::clone(&metrics),
        stopping.clone(),
    );
    let served = router
        .add_service(InterceptedService::new(reflection, gate.clone()))
        .add_service(InterceptedService::new(dinerdash, gate))
        .serve_with_incoming_shutdown(incoming, async {
            shutdown.await;
            // First of all: refuse new sessions, and tell the probes.
            let until = trigger.drain(drain_timeout);
            health
                .set_not_serving::<DinerDashServer<DinerDashService>>()
                .await;
            health
                .set_service_status("", tonic_health::ServingStatus::NotServing)
                .await;
            shutdown::drained(until, || sessions.live()).await;
            // Then close the port and answer new calls UNAVAILABLE.
            trigger.fire();
            tracing::info!("shutting down: finishing the RPCs in flight");
        })
        .await;

    // The trigger fired, or was dropped with the shutdown future if serving failed: either way
    // the sweeper and the HTTP endpoint are stopping.
    let _ = sweeper.await;
    if let Some(task) = reload_task {
        let _ = task.await;
    }
    if let Some(task) = http_task {
        let _ = task.await;
    }
    let probes_served = match probes {
        Some(task) => task.await.unwrap_or(Ok(())),
        None => Ok(()),
    };
    served?;
    probes_served?;
    tracing::info!("server stopped");
    Ok(())
}
