//! Puts the server together: the `DinerDash` service behind the auth interceptor, the standard
//! `grpc.health.v1` service, server reflection, optional TLS, the idle-session sweeper and the
//! metrics endpoint, all served on a listener the caller bound until a shutdown future completes.
//!
//! The binary passes a listener on `--host:--port` and [`crate::shutdown::signal`]; tests pass
//! `127.0.0.1:0` and a oneshot.

use std::future::Future;
use std::sync::Arc;

use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Identity, Server, ServerTlsConfig};

use crate::budget::Share;
use crate::connections::{self, KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT, MAX_STREAMS_PER_CONNECTION};
use crate::metrics::{self, Metrics};
use crate::pb;
use crate::pb::diner_dash_server::DinerDashServer;
use crate::service::{AuthInterceptor, DinerDashService, MAX_MESSAGE_BYTES, Token};
use crate::session::{Limits, Store};
use crate::shutdown;

/// A PEM certificate chain and its private key.
#[derive(Debug, Clone)]
pub struct TlsPem {
    /// The certificate chain, PEM.
    pub cert: Vec<u8>,
    /// The private key, PEM.
    pub key: Vec<u8>,
}

/// Everything [`run`] needs besides the listener.
#[derive(Debug, Default)]
pub struct ServerConfig {
    /// Session limits and the idle TTL.
    pub limits: Limits,
    /// The bearer token clients must send; `None` serves everyone (unless `tenants` is given).
    /// Each connection is then its own tenant.
    pub auth_token: Option<String>,
    /// Tenant tokens (`--auth-tokens-file`): each token's requests count against its tenant's
    /// share. Given with `auth_token`, either token is accepted.
    pub tenants: Vec<Token>,
    /// What each connection may hold when its requests carry no tenant token.
    pub connection_share: Share,
    /// Connection limit and idle timeout.
    pub connections: connections::Limits,
    /// Serve TLS with this identity; `None` serves plaintext.
    pub tls: Option<TlsPem>,
    /// Serve Prometheus metrics on this listener (asking for the same tokens as the RPCs);
    /// `None` serves none.
    pub metrics_listener: Option<TcpListener>,
}

/// Why the server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The gRPC transport (TLS configuration, accepting connections).
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// The reflection service could not read the descriptors.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
}

/// Serves on `listener` until `shutdown` completes, then stops accepting connections, lets the
/// RPCs in flight finish, and returns.
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServerError> {
    let metrics = Arc::new(Metrics::default());
    let store = Store::new(config.limits, Arc::clone(&metrics));
    let (trigger, stopping) = shutdown::channel();

    let sweeper = tokio::spawn(store.clone().sweep_until(stopping.clone()));
    let (health, health_service) = tonic_health::server::health_reporter();
    health
        .set_serving::<DinerDashServer<DinerDashService>>()
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let mut tokens = config.tenants.clone();
    if let Some(token) = &config.auth_token {
        tokens.push(Token {
            token: token.clone(),
            tenant: None,
        });
    }
    let auth = AuthInterceptor::new(&tokens, stopping.clone());
    // The metrics ask for the same tokens as the RPCs, so that a server that needs a token
    // does not publish its load to whoever reaches the metrics port.
    let metrics_task = config.metrics_listener.map(|l| {
        if let Ok(addr) = l.local_addr() {
            tracing::info!("metrics on http://{addr}/metrics");
        }
        let serve = metrics::serve(
            l,
            Arc::clone(&metrics),
            auth.bearer_values(),
            stopping.clone(),
        );
        tokio::spawn(serve)
    });
    let service = DinerDashService::new(
        store,
        Arc::clone(&metrics),
        config.connection_share,
        stopping.clone(),
    );
    let dinerdash = DinerDashServer::new(service)
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);

    // Live clients answer the keepalive pings, which keeps their connections out of the idle
    // timeout; dead ones do not, and are closed.
    let mut builder = Server::builder()
        .layer(connections::InFlightLayer)
        .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    if let Some(tls) = &config.tls {
        builder = builder
            .tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert, &tls.key)))?;
    }
    // The accept loop stops (and closes the port) when the trigger fires.
    let incoming = connections::accept(
        listener,
        config.connections,
        config.connection_share,
        Arc::clone(&metrics),
        stopping.clone(),
    );
    let served = builder
        // Health stays open without the token, so that orchestrators can probe it.
        .add_service(health_service)
        .add_service(InterceptedService::new(reflection, auth.clone()))
        .add_service(InterceptedService::new(dinerdash, auth))
        .serve_with_incoming_shutdown(incoming, async {
            shutdown.await;
            // First of all: close the port and answer new calls UNAVAILABLE.
            trigger.fire();
            tracing::info!("shutting down: finishing the RPCs in flight");
            health
                .set_not_serving::<DinerDashServer<DinerDashService>>()
                .await;
            health
                .set_service_status("", tonic_health::ServingStatus::NotServing)
                .await;
        })
        .await;

    // The trigger fired, or was dropped with the shutdown future if serving failed: either way
    // the sweeper and the metrics responder are stopping.
    let _ = sweeper.await;
    if let Some(task) = metrics_task {
        let _ = task.await;
    }
    served?;
    tracing::info!("server stopped");
    Ok(())
}
