//! Who is asking: the bearer token of an HTTP request, checked against the server's tokens, and
//! the identity ([`Owner`]) whose sessions that viewer may see, the same one its gRPC calls
//! have: the pages look sessions up through the store's owner check like every RPC.
//!
//! A server without tokens serves its pages only on a local address (the command line refuses
//! anything else) and shows every session (all are the shared identity's). With tokens, every
//! feed and `/metrics` need one: a tenant token (`--auth-tokens-file`) sees its tenant's
//! sessions; the shared `--auth-token` sees the sessions that no tenant token created.

use std::sync::Arc;

use crate::auth::Tokens;
use crate::budget::Tenant;
use crate::session::Owner;

/// Who a request comes from.
#[derive(Debug, Clone)]
pub enum Viewer {
    /// The server has no tokens: everyone sees everything.
    Anyone,
    /// The shared `--auth-token`.
    SharedToken,
    /// A tenant's token.
    Tenant(Arc<Tenant>),
}

impl Viewer {
    /// The identity whose sessions the viewer sees: a tenant's, else the shared one (which, on
    /// a server without tokens, owns every session).
    pub fn owner(&self) -> Owner {
        match self {
            Viewer::Anyone | Viewer::SharedToken => Owner::Shared,
            Viewer::Tenant(tenant) => Owner::Tenant(Arc::clone(tenant)),
        }
    }
}

/// Why a request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Refused {
    /// No `Authorization` header, and the server needs one.
    #[error("this server needs a token: send `Authorization: Bearer <token>`")]
    Missing,
    /// The header names no token of this server.
    #[error("invalid token")]
    Invalid,
}

/// The server's tokens, as the pages check them.
#[derive(Debug, Clone, Default)]
pub struct Access {
    /// The accepted tokens; none: an open (local-only) endpoint.
    tokens: Tokens,
}

impl Access {
    /// Accepts `tokens`; none: an open (local-only) endpoint.
    pub fn new(tokens: Tokens) -> Access {
        Access { tokens }
    }

    /// Whether requests need a token.
    pub fn needs_token(&self) -> bool {
        !self.tokens.is_empty()
    }

    /// Who sends `authorization` (the header's value, if any).
    pub fn viewer(&self, authorization: Option<&[u8]>) -> Result<Viewer, Refused> {
        if self.tokens.is_empty() {
            return Ok(Viewer::Anyone);
        }
        let value = authorization.ok_or(Refused::Missing)?.trim_ascii();
        match self.tokens.check(value) {
            None => Err(Refused::Invalid),
            Some(None) => Ok(Viewer::SharedToken),
            Some(Some(tenant)) => Ok(Viewer::Tenant(tenant)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auth::Token;
    use crate::budget::Share;

    #[test]
    fn tokens_choose_what_a_viewer_sees() {
        let a = Arc::new(Tenant::new("tenant a".into(), Share::default()));
        let b = Arc::new(Tenant::new("tenant b".into(), Share::default()));
        let token = |token: &str, tenant: Option<&Arc<Tenant>>| Token {
            token: token.into(),
            tenant: tenant.cloned(),
        };
        let access = Access::new(Tokens::new(&[
            token("aaa", Some(&a)),
            token("bbb", Some(&b)),
            token("shared", None),
        ]));
        assert_eq!(access.viewer(None).unwrap_err(), Refused::Missing);
        assert_eq!(
            access.viewer(Some(b"Bearer nope")).unwrap_err(),
            Refused::Invalid
        );
        let viewer_a = access.viewer(Some(b"Bearer aaa")).unwrap().owner();
        assert!(viewer_a.is(&Owner::Tenant(Arc::clone(&a))));
        assert!(!viewer_a.is(&Owner::Tenant(b)));
        assert!(!viewer_a.is(&Owner::Shared));
        let shared = access.viewer(Some(b" Bearer shared ")).unwrap().owner();
        assert!(shared.is(&Owner::Shared));
        assert!(!shared.is(&Owner::Tenant(a)));
        let open = Access::default();
        assert!(!open.needs_token());
        assert!(open.viewer(None).unwrap().owner().is(&Owner::Shared));
    }
}
