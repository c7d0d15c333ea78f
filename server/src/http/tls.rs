//! The web endpoint's TLS: the certificate and key gRPC serves (`--tls-cert`, `--tls-key`) made
//! into a rustls acceptor for HTTP/1.1, so that the bearer tokens the pages and scrapers send
//! never cross the network in clear; and the DNS names that certificate is valid for, which
//! the Host check accepts ([`super::hosts`]).

use std::sync::Arc;

use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName, pem::PemObject};
use tokio_rustls::rustls::{self, ServerConfig};

/// Why the certificate or key cannot serve the web endpoint.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// `--tls-cert` holds no usable PEM certificate.
    #[error("the TLS certificate (--tls-cert): {0}")]
    Cert(String),
    /// `--tls-key` holds no usable PEM private key.
    #[error("the TLS key (--tls-key): {0}")]
    Key(String),
    /// rustls refused the pair (a key that is not the certificate's, an unsupported algorithm).
    #[error("the web endpoint's TLS: {0}")]
    Config(#[from] rustls::Error),
}

/// The web endpoint's TLS identity: the acceptor every connection's handshake runs through, and
/// the leaf certificate whose names a `Host` header may give.
#[derive(Clone)]
pub struct HttpTls {
    /// Handshakes a connection (HTTP/1.1 over ALPN, TLS 1.2 and 1.3, ring's algorithms).
    pub acceptor: TlsAcceptor,
    /// The first certificate of the chain: the one a browser checks the address against.
    leaf: CertificateDer<'static>,
}

impl std::fmt::Debug for HttpTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HttpTls").finish_non_exhaustive()
    }
}

impl HttpTls {
    /// The identity of the PEM certificate chain `cert` and private key `key`.
    pub fn new(cert: &[u8], key: &[u8]) -> Result<HttpTls, TlsError> {
        let chain = CertificateDer::pem_slice_iter(cert)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| TlsError::Cert(format!("not PEM certificates: {e}")))?;
        let leaf = chain
            .first()
            .cloned()
            .ok_or_else(|| TlsError::Cert("no PEM certificate in it".into()))?;
        let key = PrivateKeyDer::from_pem_slice(key)
            .map_err(|e| TlsError::Key(format!("no PEM private key: {e}")))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut config = ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()?
            .with_no_client_auth()
            .with_single_cert(chain, key)?;
        config.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(HttpTls {
            acceptor: TlsAcceptor::from(Arc::new(config)),
            leaf,
        })
    }

    /// Whether the certificate is valid for the DNS name `name` (its subject alternative
    /// names, wildcards included, as a browser would check them).
    pub fn certifies(&self, name: &str) -> bool {
        let Ok(server_name) = ServerName::try_from(name) else {
            return false;
        };
        webpki::EndEntityCert::try_from(&self.leaf)
            .is_ok_and(|cert| cert.verify_is_valid_for_subject_name(&server_name).is_ok())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_certificate_names_its_hosts() {
        let names = vec!["dinerdash.example.com".into(), "*.pods.example.com".into()];
        let made = rcgen::generate_simple_self_signed(names).unwrap();
        let tls = HttpTls::new(
            made.cert.pem().as_bytes(),
            made.signing_key.serialize_pem().as_bytes(),
        )
        .unwrap();
        assert!(tls.certifies("dinerdash.example.com"));
        assert!(tls.certifies("a.pods.example.com"));
        assert!(!tls.certifies("evil.example.net"));
        assert!(!tls.certifies("not a name"));
        let refused = HttpTls::new(b"junk", b"junk").unwrap_err();
        assert!(matches!(refused, TlsError::Cert(_)), "{refused}");
    }
}
