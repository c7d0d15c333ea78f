//! Who may call: the bearer tokens and the tenants they stand for (`--auth-token`,
//! `--auth-tokens-file` and its parsing), the constant-time comparison of a sent token, and the
//! [`RequestGate`] in front of every RPC but health checks, which also turns calls away while
//! the server drains or when their connection is over the connection limit.

use std::sync::Arc;

use tonic::{Request, Status};

use crate::budget::{Share, Tenant};
use crate::connections::conn_info;
use crate::shutdown::{self, Shutdown};

/// A token clients may send, and the tenant it stands for.
#[derive(Debug, Clone)]
pub struct Token {
    /// The secret, sent as `authorization: Bearer <token>`.
    pub token: String,
    /// Whose share its requests count against; `None`: each connection's own (`--auth-token`).
    pub tenant: Option<Arc<Tenant>>,
}

/// One line of `--auth-tokens-file`: a tenant, its token and its share.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TenantLine {
    /// The tenant's name, for messages and logs.
    pub name: String,
    /// Its bearer token.
    pub token: String,
    /// What it may hold.
    pub share: Share,
}

/// Reads `--auth-tokens-file`: one tenant a line, `NAME TOKEN [envs=N] [sessions=N]
/// [rollouts=N]`; what a line does not give is `default`'s. Blank lines and `#` comments are
/// skipped. Names and tokens must be unique.
pub fn parse_tenants(text: &str, default: Share) -> Result<Vec<TenantLine>, String> {
    let mut tenants: Vec<TenantLine> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or_default().trim();
        if line.is_empty() {
            continue;
        }
        let at = |msg: String| format!("line {}: {msg}", i + 1);
        let mut words = line.split_whitespace();
        let (Some(name), Some(token)) = (words.next(), words.next()) else {
            return Err(at(
                "expected `NAME TOKEN [envs=N] [sessions=N] [rollouts=N]`".into(),
            ));
        };
        let mut share = default;
        for word in words {
            let (key, value) = word
                .split_once('=')
                .ok_or_else(|| at(format!("expected key=value, got {word:?}")))?;
            let value: u64 = value
                .parse()
                .map_err(|_| at(format!("{key} must be a whole number, got {value:?}")))?;
            match key {
                "envs" => share.max_envs = value,
                "sessions" => share.max_sessions = value,
                "rollouts" => share.max_rollouts = value,
                other => {
                    return Err(at(format!(
                        "unknown quota {other:?}: use envs, sessions or rollouts"
                    )));
                }
            }
        }
        if tenants.iter().any(|t| t.name == name || t.token == token) {
            return Err(at(format!("tenant {name:?} or its token is given twice")));
        }
        tenants.push(TenantLine {
            name: name.to_owned(),
            token: token.to_owned(),
            share,
        });
    }
    if tenants.is_empty() {
        return Err("no tenant in the file".into());
    }
    Ok(tenants)
}

/// The tokens of `--auth-tokens-file`'s `text` (see [`parse_tenants`]), each standing for its
/// own tenant, named `tenant NAME`.
pub fn tenant_tokens(text: &str, default: Share) -> Result<Vec<Token>, String> {
    Ok(parse_tenants(text, default)?
        .into_iter()
        .map(|line| Token {
            token: line.token,
            tenant: Some(Arc::new(Tenant::new(
                format!("tenant {}", line.name),
                line.share,
            ))),
        })
        .collect())
}

/// An accepted `authorization` value (`Bearer <token>`) and the tenant it stands for.
type Accepted = (Box<[u8]>, Option<Arc<Tenant>>);

/// The tokens a server accepts, as the `authorization` values that carry them, for the gRPC
/// [`RequestGate`] and the web pages alike. Cloning is shallow.
#[derive(Debug, Clone, Default)]
pub struct Tokens {
    /// Accepted `Bearer <token>` values and their tenants; empty: an open server.
    accepted: Arc<[Accepted]>,
}

impl Tokens {
    /// Accepts `tokens` (none: an open server).
    pub fn new(tokens: &[Token]) -> Tokens {
        let accepted = tokens
            .iter()
            .map(|t| {
                let expected = format!("Bearer {}", t.token)
                    .into_bytes()
                    .into_boxed_slice();
                (expected, t.tenant.clone())
            })
            .collect();
        Tokens { accepted }
    }

    /// Whether the server has no tokens (every request is let in).
    pub fn is_empty(&self) -> bool {
        self.accepted.is_empty()
    }

    /// Which token the `authorization` value `value` carries: `None`, none of this server's;
    /// `Some(tenant)`, a tenant's token, or `Some(None)` the shared `--auth-token`. Every token
    /// is compared, so that the time taken does not reveal which one matched.
    pub fn check(&self, value: &[u8]) -> Option<Option<Arc<Tenant>>> {
        let mut found = None;
        for (expected, tenant) in self.accepted.iter() {
            if same_bytes(value, expected) {
                found = Some(tenant.clone());
            }
        }
        found
    }

    /// Whether one of the tokens stands for `tenant`.
    pub fn stand_for(&self, tenant: &Arc<Tenant>) -> bool {
        self.accepted
            .iter()
            .any(|(_, t)| t.as_ref().is_some_and(|t| Arc::ptr_eq(t, tenant)))
    }
}

/// Stands in front of every RPC but health checks: answers `UNAVAILABLE` once the server drains,
/// `RESOURCE_EXHAUSTED` on a connection over the connection limit, and, when the server has
/// tokens, checks `authorization: Bearer <token>` and tags the request with the token's tenant.
#[derive(Debug, Clone)]
pub struct RequestGate {
    /// The accepted tokens; none lets every request in.
    tokens: Tokens,
    /// Fires when the server drains.
    stopping: Shutdown,
}

impl RequestGate {
    /// A gate accepting `tokens` (none: an open server).
    pub fn new(tokens: Tokens, stopping: Shutdown) -> RequestGate {
        RequestGate { tokens, stopping }
    }
}

/// Compares without returning early, so that the time taken does not reveal the token.
fn same_bytes(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl tonic::service::Interceptor for RequestGate {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if self.stopping.is_stopping() {
            return Err(shutdown::unavailable());
        }
        if let Some(max) = conn_info(&request).and_then(|c| c.over_limit) {
            return Err(Status::resource_exhausted(format!(
                "the server serves its maximum of {max} connections; retry later or raise \
                 --max-connections"
            )));
        }
        if self.tokens.is_empty() {
            return Ok(request);
        }
        let Some(value) = request.metadata().get("authorization") else {
            return Err(Status::unauthenticated(
                "missing authorization metadata: send `authorization: Bearer <token>`",
            ));
        };
        match self.tokens.check(value.as_bytes()) {
            None => Err(Status::unauthenticated("invalid auth token")),
            Some(tenant) => {
                if let Some(tenant) = tenant {
                    request.extensions_mut().insert(tenant);
                }
                Ok(request)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tenants_file_lines() {
        let text = "# trainers\nteam-a s3cret envs=100 rollouts=1\n\nteam-b other # no quota\n";
        let tenants = parse_tenants(text, Share::default()).unwrap();
        assert_eq!(tenants.len(), 2);
        assert_eq!(tenants[0].share.max_envs, 100);
        assert_eq!(tenants[0].share.max_rollouts, 1);
        assert_eq!(tenants[1].share, Share::default());
        assert_eq!(
            parse_tenants("a t envs=x", Share::default()),
            Err("line 1: envs must be a whole number, got \"x\"".into())
        );
        assert!(parse_tenants("a t\nb t", Share::default()).is_err());
        assert!(parse_tenants("lonely", Share::default()).is_err());
    }

    #[test]
    fn same_bytes_compares_whole_values() {
        assert!(same_bytes(b"Bearer abc", b"Bearer abc"));
        assert!(!same_bytes(b"Bearer abc", b"Bearer abd"));
        assert!(!same_bytes(b"Bearer ab", b"Bearer abc"));
        assert!(same_bytes(b"", b""));
    }
}
