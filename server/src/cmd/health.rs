//! The `health` command's client: one `grpc.health.v1` Check against a running server (the
//! Docker HEALTHCHECK), plaintext or TLS. With TLS it trusts the given CA certificates, or a
//! self-signed server certificate named as its own CA.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use tokio_rustls::rustls::client::WebPkiServerVerifier;
use tokio_rustls::rustls::client::danger::{
    HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier,
};
use tokio_rustls::rustls::pki_types::{CertificateDer, ServerName, UnixTime, pem::PemObject};
use tokio_rustls::rustls::{self, DigitallySignedStruct, RootCertStore, SignatureScheme};
use tonic::transport::Endpoint;
pub use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

use crate::config::parse_duration;

/// What to ask, and of whom.
#[derive(Debug, Clone)]
pub struct Probe {
    /// The server, host:port.
    pub address: String,
    /// Give up after this long.
    pub timeout: Duration,
    /// The service to ask about; empty means the whole server.
    pub service: String,
    /// Connect with TLS, trusting this PEM CA certificate (or a self-signed server certificate
    /// itself).
    pub tls_ca: Option<Vec<u8>>,
    /// Sent as `authorization: Bearer <token>`: a server with a `--probe-port` serves health on
    /// its gRPC port only to callers with a token.
    pub token: Option<String>,
}

#[derive(Debug, clap::Args)]
pub(super) struct HealthArgs {
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
    /// The token to send (a server with --probe-port asks for one on its gRPC port; its probe
    /// port does not).
    #[arg(long, env = "DINERDASH_AUTH_TOKEN", hide_env_values = true)]
    auth_token: Option<String>,
}

/// The `health` command: prints the status the server reported; success if it is SERVING.
pub(super) fn execute(args: &HealthArgs) -> ExitCode {
    let probe = |tls_ca: Option<Vec<u8>>| Probe {
        address: args.address.clone(),
        timeout: args.timeout,
        service: args.service.clone(),
        tls_ca,
        token: args.auth_token.clone().filter(|t| !t.is_empty()),
    };
    let result = args
        .tls_ca
        .as_ref()
        .map(|ca| std::fs::read(ca).map_err(|e| format!("cannot read {}: {e}", ca.display())))
        .transpose()
        .and_then(|ca| {
            let rt = super::runtime().map_err(|e| e.to_string())?;
            rt.block_on(check(&probe(ca)))
        });
    match result {
        Ok(status) => {
            println!("{}", status.as_str_name());
            if status == ServingStatus::Serving {
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

/// One Check: the status the server reported, or why there was none.
pub async fn check(probe: &Probe) -> Result<ServingStatus, String> {
    // With a CA the TLS is ours (see `tls_connector`) and tonic speaks HTTP/2 over it.
    let endpoint = Endpoint::from_shared(format!("http://{}", probe.address))
        .map_err(|e| format!("bad address {:?}: {e}", probe.address))?
        .connect_timeout(probe.timeout)
        .timeout(probe.timeout);
    let ask = async {
        let channel = match &probe.tls_ca {
            Some(pem) => {
                let connector = tls_connector(&probe.address, pem)?;
                endpoint.connect_with_connector(connector).await
            }
            None => endpoint.connect().await,
        }
        .map_err(|e| format!("cannot connect: {}", error_chain(&e)))?;
        let mut request = tonic::Request::new(HealthCheckRequest {
            service: probe.service.clone(),
        });
        if let Some(token) = &probe.token {
            let value = format!("Bearer {token}")
                .parse()
                .map_err(|_| "the token cannot be sent in a header".to_owned())?;
            request.metadata_mut().insert("authorization", value);
        }
        let reply = HealthClient::new(channel)
            .check(request)
            .await
            .map_err(|s| format!("{:?}: {}", s.code(), s.message()))?;
        Ok(reply.into_inner().status())
    };
    tokio::time::timeout(probe.timeout, ask)
        .await
        .map_err(|_| format!("no answer within {:?}", probe.timeout))?
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

/// Opens TCP to `address` and TLS over it, trusting the PEM certificates `ca_pem`, for tonic's
/// `connect_with_connector`.
fn tls_connector(
    address: &str,
    ca_pem: &[u8],
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
    let verifier = SelfSignedOrCa::new(ca_pem).map_err(|e| format!("the TLS CA: {e}"))?;
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
