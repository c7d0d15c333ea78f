//! The `health` command's client: one `grpc.health.v1` Check against a running server (the
//! Docker HEALTHCHECK), plaintext or TLS.

use std::time::Duration;

use tonic::transport::{Certificate, ClientTlsConfig, Endpoint};
pub use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

/// What to ask, and of whom.
#[derive(Debug, Clone)]
pub struct Probe {
    /// The server, host:port.
    pub address: String,
    /// Give up after this long.
    pub timeout: Duration,
    /// The service to ask about; empty means the whole server.
    pub service: String,
    /// Connect with TLS, trusting this PEM CA certificate.
    pub tls_ca: Option<Vec<u8>>,
}

/// One Check: the status the server reported, or why there was none.
pub async fn check(probe: &Probe) -> Result<ServingStatus, String> {
    let scheme = if probe.tls_ca.is_some() {
        "https"
    } else {
        "http"
    };
    let mut endpoint = Endpoint::from_shared(format!("{scheme}://{}", probe.address))
        .map_err(|e| format!("bad address {:?}: {e}", probe.address))?
        .connect_timeout(probe.timeout)
        .timeout(probe.timeout);
    if let Some(pem) = &probe.tls_ca {
        endpoint = endpoint
            .tls_config(ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)))
            .map_err(|e| format!("TLS: {e}"))?;
    }
    let ask = async {
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| format!("cannot connect: {e}"))?;
        let reply = HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: probe.service.clone(),
            })
            .await
            .map_err(|s| format!("{:?}: {}", s.code(), s.message()))?;
        Ok(reply.into_inner().status())
    };
    tokio::time::timeout(probe.timeout, ask)
        .await
        .map_err(|_| format!("no answer within {:?}", probe.timeout))?
}
