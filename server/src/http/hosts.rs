//! Which `Host` a request to the web endpoint may name: the defence against DNS rebinding, where
//! a page on an attacker's domain has the domain re-resolve to this machine (or a host on its
//! network) and then reads the endpoint from the victim's browser. The browser still sends the
//! attacker's name as `Host`, so a request is served only when its host (the port aside) is
//!
//! - an IP literal (`10.0.0.7`, `[::1]`): no DNS name is involved, so nothing was rebound;
//! - `localhost` (or a name under `.localhost`), when the endpoint listens on a loopback or a
//!   wildcard address;
//! - a name the TLS certificate is valid for, when the endpoint serves TLS;
//! - a name given with `--http-allowed-host` (compared case-insensitively, a trailing dot and
//!   any port ignored).
//!
//! Any other host, or none, is answered 421 Misdirected Request, naming the flag.

use std::net::{IpAddr, SocketAddr};

use super::tls::HttpTls;

/// The names the endpoint answers to.
#[derive(Debug, Clone)]
pub struct Hosts {
    /// `localhost` is allowed: the endpoint listens on a loopback or a wildcard address.
    localhost: bool,
    /// `--http-allowed-host`, lowercased, without ports and trailing dots.
    allowed: Vec<String>,
    /// The certificate whose names are allowed, when the endpoint serves TLS.
    tls: Option<HttpTls>,
}

impl Hosts {
    /// The names an endpoint bound to `bound` answers to: its own, `allowed`, and `tls`'s.
    pub fn new(bound: SocketAddr, allowed: &[String], tls: Option<HttpTls>) -> Hosts {
        let ip = bound.ip();
        Hosts {
            localhost: ip.is_loopback() || ip.is_unspecified(),
            // A port given with a name is not compared, as for requests.
            allowed: allowed.iter().map(|name| normal(name_of(name))).collect(),
            tls,
        }
    }

    /// Whether a request whose `Host` (or absolute URI's authority) is `host` is served.
    pub fn allows(&self, host: &str) -> bool {
        let name = normal(name_of(host));
        if name.is_empty() {
            return false;
        }
        if name.parse::<IpAddr>().is_ok() {
            return true;
        }
        if self.localhost && (name == "localhost" || name.ends_with(".localhost")) {
            return true;
        }
        self.allowed.contains(&name) || self.tls.as_ref().is_some_and(|tls| tls.certifies(&name))
    }
}

/// `host` without its port and IPv6 brackets: `[::1]:8080` is `::1`, `gpu-box:9090` `gpu-box`.
fn name_of(host: &str) -> &str {
    let host = host.trim();
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split_once(']').map_or(rest, |(ip, _)| ip);
    }
    match host.rsplit_once(':') {
        // One colon: a port. More: an IPv6 address without brackets (not valid, but harmless).
        Some((name, _)) if !name.contains(':') => name,
        _ => host,
    }
}

/// `name` lowercased, without a trailing dot (`Example.COM.` is `example.com`).
fn normal(name: &str) -> String {
    name.trim().trim_end_matches('.').to_ascii_lowercase()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hosts(bound: &str, allowed: &[&str]) -> Hosts {
        let allowed: Vec<String> = allowed.iter().map(|s| (*s).to_owned()).collect();
        Hosts::new(bound.parse().unwrap(), &allowed, None)
    }

    #[test]
    fn ip_literals_and_localhost_on_loopback_are_served() {
        let local = hosts("127.0.0.1:8080", &[]);
        for ok in [
            "localhost",
            "LOCALHOST:8080",
            "127.0.0.1:8080",
            "[::1]:8080",
            "10.0.0.7",
        ] {
            assert!(local.allows(ok), "{ok}");
        }
        for refused in ["evil.example.com", "evil.example.com:8080", "", ":8080"] {
            assert!(!local.allows(refused), "{refused:?}");
        }
        let wildcard = hosts("0.0.0.0:8080", &["Dinerdash.Example.com.", "gpu-box:8080"]);
        assert!(wildcard.allows("gpu-box"));
        assert!(wildcard.allows("localhost:8080"));
        assert!(wildcard.allows("dinerdash.example.com:8080"));
        assert!(wildcard.allows("DINERDASH.example.com."));
        assert!(!wildcard.allows("example.com"));
        // Bound to one public address, localhost is not this endpoint.
        let public = hosts("10.0.0.7:8080", &["gpu-box"]);
        assert!(!public.allows("localhost"));
        assert!(public.allows("gpu-box:8080") && public.allows("10.0.0.7:8080"));
    }

    #[test]
    fn names_without_their_port() {
        assert_eq!(name_of("[::1]:80"), "::1");
        assert_eq!(name_of("[::1]"), "::1");
        assert_eq!(name_of("a.b:80"), "a.b");
        assert_eq!(name_of("a.b"), "a.b");
        assert_eq!(name_of("::1"), "::1");
    }
}
