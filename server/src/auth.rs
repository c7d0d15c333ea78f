//! Who may call: the bearer tokens and the tenants they stand for (`--auth-token`,
//! `--auth-tokens-file` and its parsing), the rules a token must meet ([`check_token`]), the
//! [`Secret`] that keeps a token out of `Debug` output and logs, the constant-time comparison
//! of a sent token, and the [`RequestGate`] in front of every RPC but health checks, which also
//! turns calls away while the server drains or when their connection is over the connection
//! limit.

use std::collections::HashMap;
use std::fmt;
use std::sync::{Arc, Mutex, PoisonError, RwLock};

use tonic::{Request, Status};

use crate::audit::{Audit, AuthFailure, called_method};
pub use crate::budget::SharedShare;
use crate::budget::{Share, Tenant};
use crate::connections::calls::IDENTITY_SHARE;
use crate::connections::conn_info;
use crate::shutdown::{self, Shutdown};

/// Fewest characters a token may have: 16 random characters are out of reach of guessing over
/// the network, and shorter ones are usually words (`s3cret`).
pub const MIN_TOKEN_CHARS: usize = 16;

/// A secret (a bearer token) that never shows in `Debug` output, so that a logged or printed
/// configuration (`{:?}` of [`Token`], [`TenantLine`], `ServeArgs`, `ServerConfig`) holds none.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct Secret(String);

impl Secret {
    /// The secret itself, for comparing it with what a client sends.
    pub fn expose(&self) -> &str {
        &self.0
    }

    /// Whether it is the empty string (an empty `DINERDASH_AUTH_TOKEN` is no token).
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Secret(<redacted>)")
    }
}

impl From<String> for Secret {
    fn from(secret: String) -> Secret {
        Secret(secret)
    }
}

impl From<&str> for Secret {
    fn from(secret: &str) -> Secret {
        Secret(secret.to_owned())
    }
}

/// Why a token is refused at start. The messages never repeat the token.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TokenError {
    /// Fewer than [`MIN_TOKEN_CHARS`] characters.
    #[error(
        "the token has {0} characters, fewer than {MIN_TOKEN_CHARS}: use a random one, e.g. \
         `openssl rand -hex 32`"
    )]
    TooShort(usize),
    /// A `#`, which a tenants file would read as the start of a comment.
    #[error(
        "the token contains `#`, which starts a comment in a tenants file: use a random one, \
         e.g. `openssl rand -hex 32`"
    )]
    Hash,
    /// A space, control or non-ASCII character, which an `authorization` header cannot carry
    /// as it is.
    #[error(
        "the token contains a space, control or non-ASCII character: use visible ASCII only, \
         e.g. `openssl rand -hex 32`"
    )]
    NotVisibleAscii,
}

/// Refuses a token that is short, holds a `#`, or a character other than visible ASCII: it is
/// refused as a whole, never truncated.
pub fn check_token(token: &str) -> Result<(), TokenError> {
    if token.contains('#') {
        return Err(TokenError::Hash);
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(TokenError::NotVisibleAscii);
    }
    if token.len() < MIN_TOKEN_CHARS {
        return Err(TokenError::TooShort(token.len()));
    }
    Ok(())
}

/// A token clients may send, and the tenant it stands for.
#[derive(Debug, Clone)]
pub struct Token {
    /// The secret, sent as `authorization: Bearer <token>`.
    pub token: Secret,
    /// Whose share its requests count against; `None`: each connection's own (`--auth-token`).
    pub tenant: Option<Arc<Tenant>>,
}

/// One line of `--auth-tokens-file`: a tenant, its token and its share.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TenantLine {
    /// The tenant's name, for messages and logs.
    pub name: String,
    /// Its bearer token.
    pub token: Secret,
    /// What it may hold.
    pub share: Share,
}

/// `line` without its comment: a `#` starts one at the start of the line or after whitespace
/// only, so that a `#` inside a token stays in it (and [`check_token`] refuses the token)
/// instead of silently cutting it short.
fn without_comment(line: &str) -> &str {
    let mut previous = None;
    for (at, c) in line.char_indices() {
        if c == '#' && previous.is_none_or(char::is_whitespace) {
            return &line[..at];
        }
        previous = Some(c);
    }
    line
}

/// Reads `--auth-tokens-file`: one tenant a line, `NAME TOKEN [envs=N] [sessions=N]
/// [rollouts=N] [connections=N] [streams=N]`; what a line does not give is `default`'s. Blank lines and comments are
/// skipped: a comment starts with a `#` at the start of a line or after whitespace. Names and
/// tokens must be unique, and every token must pass [`check_token`]. The errors name the line
/// and the tenant, never the token.
pub fn parse_tenants(text: &str, default: Share) -> Result<Vec<TenantLine>, String> {
    let mut tenants: Vec<TenantLine> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = without_comment(line).trim();
        if line.is_empty() {
            continue;
        }
        let at = |msg: String| format!("line {}: {msg}", i + 1);
        let mut words = line.split_whitespace();
        let (Some(name), Some(token)) = (words.next(), words.next()) else {
            return Err(at(
                "expected `NAME TOKEN [envs=N] [sessions=N] [rollouts=N] [connections=N] \
                 [streams=N]`"
                    .into(),
            ));
        };
        check_token(token).map_err(|e| at(format!("tenant {name:?}: {e}")))?;
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
                "connections" => share.max_connections = value,
                "streams" => share.max_streams = value,
                other => {
                    return Err(at(format!(
                        "unknown quota {other:?}: use envs, sessions, rollouts, connections or \
                         streams"
                    )));
                }
            }
        }
        if tenants
            .iter()
            .any(|t| t.name == name || t.token.expose() == token)
        {
            return Err(at(format!("tenant {name:?} or its token is given twice")));
        }
        tenants.push(TenantLine {
            name: name.to_owned(),
            token: token.into(),
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
    Ok(Roster::default().tokens(parse_tenants(text, default)?))
}

/// What each identity may hold of a server-wide limit (`--max-sessions`, `--max-connections`,
/// the calls the intake bound holds) when its line does not say: an equal part of `max` for each
/// of `identities` (the tenants, and the shared token if there is one), at least one, so that no
/// identity can take all of it and every one can always reach its part.
pub fn fair_part(max: u64, identities: usize) -> u64 {
    (max / identities.max(1) as u64).max(1)
}

/// What the tenants of a tokens file may hold when their lines say nothing else, and the shared
/// token their tokens must differ from.
#[derive(Debug, Clone)]
pub struct TenantRules {
    /// `--max-envs-per-tenant` and `--max-rollouts-per-tenant`; its `max_sessions`,
    /// `max_connections` and `max_streams` are ignored: a tenant's default to its fair part
    /// ([`fair_part`]) of the three below.
    pub share: Share,
    /// `--max-sessions`.
    pub max_sessions: u64,
    /// `--max-connections`.
    pub max_connections: u64,
    /// The calls the intake bound holds (`connections::calls::calls_held`); one identity's part
    /// is at most half of them, as [`IDENTITY_SHARE`] says, even alone.
    pub max_calls: u64,
    /// The shared token (`DINERDASH_AUTH_TOKEN` / `--auth-token`), if any: a tenant's token may
    /// not be it, and it counts as one more identity in the fair part of the sessions.
    pub shared_token: Option<Secret>,
}

impl TenantRules {
    /// The tenants of a tokens file's `text` with their shares: `default` with each line's
    /// quotas, the sessions' fair part where a line gives none. Refuses a tenant whose token is
    /// the shared token (which would make the tenant the shared identity).
    pub fn lines(&self, text: &str) -> Result<Vec<TenantLine>, String> {
        // Counted first: the fair part depends on how many identities there are.
        let count = parse_tenants(text, self.share)?.len();
        let identities = count + usize::from(self.shared_token.is_some());
        let default = self.fair_share(identities);
        let lines = parse_tenants(text, default)?;
        if let Some(shared) = &self.shared_token
            && let Some(line) = lines.iter().find(|l| l.token == *shared)
        {
            return Err(format!(
                "tenant {:?}'s token is also the shared token (DINERDASH_AUTH_TOKEN or \
                 --auth-token): give every tenant, and the shared token, a token of its own",
                line.name
            ));
        }
        Ok(lines)
    }

    /// The shared token's share: `share`, its sessions, connections and calls its fair part
    /// among `tenants` tenants and itself.
    pub fn shared_share(&self, tenants: usize) -> Share {
        self.fair_share(tenants + 1)
    }

    /// `share` with its sessions, connections and calls each an equal part for `identities`;
    /// the calls at most 1/[`IDENTITY_SHARE`] of those the intake bound holds.
    fn fair_share(&self, identities: usize) -> Share {
        Share {
            max_sessions: fair_part(self.max_sessions, identities),
            max_connections: fair_part(self.max_connections, identities),
            max_streams: fair_part(self.max_calls, identities.max(IDENTITY_SHARE)),
            ..self.share
        }
    }
}

/// Every tenant the server has known, by name, so that a tenant whose line a reload of the
/// tokens file keeps (or brings back) stays the same tenant: its sessions are still its own,
/// what it holds still counts against its share, and only its token and share change.
#[derive(Debug, Default)]
pub struct Roster {
    /// By [`Tenant::name`].
    known: Mutex<HashMap<String, Arc<Tenant>>>,
}

impl Roster {
    /// A roster knowing the tenants of `tokens`.
    pub fn new(tokens: &[Token]) -> Roster {
        let known = tokens
            .iter()
            .filter_map(|t| t.tenant.as_ref())
            .map(|t| (t.name().to_owned(), Arc::clone(t)))
            .collect();
        Roster {
            known: Mutex::new(known),
        }
    }

    /// The tokens of `lines`, each standing for its tenant (named `tenant NAME`): a tenant known
    /// already is the same [`Tenant`], its share set to the line's.
    pub fn tokens(&self, lines: Vec<TenantLine>) -> Vec<Token> {
        let mut known = self.known.lock().unwrap_or_else(PoisonError::into_inner);
        lines
            .into_iter()
            .map(|line| {
                let name = format!("tenant {}", line.name);
                let tenant = known
                    .entry(name.clone())
                    .or_insert_with(|| Arc::new(Tenant::new(name, line.share)));
                tenant.set_share(line.share);
                Token {
                    token: line.token,
                    tenant: Some(Arc::clone(tenant)),
                }
            })
            .collect()
    }
}

/// An accepted `authorization` value (`Bearer <token>`) and the tenant it stands for.
type Accepted = (Box<[u8]>, Option<Arc<Tenant>>);

/// The tokens a server accepts, as the `authorization` values that carry them, for the gRPC
/// [`RequestGate`] and the web pages alike. Cloning is shallow. Its `Debug` shows how many
/// tokens there are and their tenants, never the tokens.
#[derive(Clone, Default)]
pub struct Tokens {
    /// Accepted `Bearer <token>` values and their tenants; empty: an open server. Replaced as
    /// a whole when the tokens file is read again ([`Tokens::replace`]).
    accepted: Arc<RwLock<Arc<[Accepted]>>>,
    /// What the shared token's requests count against, as one identity (not per connection).
    shared: Option<Arc<Tenant>>,
}

impl fmt::Debug for Tokens {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let accepted = self.current();
        let tenants: Vec<Option<&str>> = accepted
            .iter()
            .map(|(_, tenant)| tenant.as_deref().map(Tenant::name))
            .collect();
        f.debug_struct("Tokens")
            .field("tenants", &tenants)
            .finish_non_exhaustive()
    }
}

impl Tokens {
    /// Accepts `tokens` (none: an open server).
    pub fn new(tokens: &[Token]) -> Tokens {
        Tokens {
            accepted: Arc::new(RwLock::new(accepted(tokens))),
            shared: None,
        }
    }

    /// These tokens, the shared token's requests counting against `share` (one identity).
    pub fn with_shared_share(self, share: Arc<Tenant>) -> Tokens {
        Tokens {
            shared: Some(share),
            ..self
        }
    }

    /// Accepts `tokens` from now on, instead of the ones before (every clone sees them): a
    /// new token works on its next request, a removed one is refused on its next request.
    pub fn replace(&self, tokens: &[Token]) {
        *self
            .accepted
            .write()
            .unwrap_or_else(PoisonError::into_inner) = accepted(tokens);
    }

    /// The tokens accepted now.
    fn current(&self) -> Arc<[Accepted]> {
        Arc::clone(&self.accepted.read().unwrap_or_else(PoisonError::into_inner))
    }

    /// Whether the server has no tokens (every request is let in).
    pub fn is_empty(&self) -> bool {
        self.current().is_empty()
    }

    /// Which token the `authorization` value `value` carries: `None`, none of this server's;
    /// `Some(tenant)`, a tenant's token, or `Some(None)` the shared `--auth-token`. Every token
    /// is compared, so that the time taken does not reveal which one matched.
    pub fn check(&self, value: &[u8]) -> Option<Option<Arc<Tenant>>> {
        let mut found = None;
        for (expected, tenant) in self.current().iter() {
            if same_bytes(value, expected) {
                found = Some(tenant.clone());
            }
        }
        found
    }

    /// Whether one of the tokens stands for `tenant`.
    pub fn stand_for(&self, tenant: &Arc<Tenant>) -> bool {
        self.current()
            .iter()
            .any(|(_, t)| t.as_ref().is_some_and(|t| Arc::ptr_eq(t, tenant)))
    }
}

/// `tokens` as the `authorization` values that carry them.
fn accepted(tokens: &[Token]) -> Arc<[Accepted]> {
    tokens
        .iter()
        .map(|t| {
            let expected = format!("Bearer {}", t.token.expose())
                .into_bytes()
                .into_boxed_slice();
            (expected, t.tenant.clone())
        })
        .collect()
}

/// Stands in front of every RPC but health checks: answers `UNAVAILABLE` once the server drains,
/// `RESOURCE_EXHAUSTED` on a connection over the connection limit, and, when the server has
/// tokens, checks `authorization: Bearer <token>` and tags the request with the token's tenant
/// (or the shared token's [`SharedShare`]). A refused token is reported to the [`Audit`].
#[derive(Debug, Clone)]
pub struct RequestGate {
    /// The accepted tokens; none lets every request in.
    tokens: Tokens,
    /// Fires when the server drains.
    stopping: Shutdown,
    /// Counts and logs the refused tokens.
    audit: Arc<Audit>,
}

impl RequestGate {
    /// A gate accepting `tokens` (none: an open server), reporting refusals to `audit`.
    pub fn new(tokens: Tokens, stopping: Shutdown, audit: Arc<Audit>) -> RequestGate {
        RequestGate {
            tokens,
            stopping,
            audit,
        }
    }

    /// `UNAUTHENTICATED` for `failure`, reported to the audit.
    fn refuse(&self, request: &Request<()>, failure: AuthFailure) -> Status {
        let peer = conn_info(request).and_then(|c| c.remote);
        self.audit
            .auth_failed(peer, called_method(request.extensions()), failure);
        Status::unauthenticated(failure.message())
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
            return Err(self.refuse(&request, AuthFailure::Missing));
        };
        match self.tokens.check(value.as_bytes()) {
            None => Err(self.refuse(&request, AuthFailure::Invalid)),
            Some(Some(tenant)) => {
                request.extensions_mut().insert(tenant);
                Ok(request)
            }
            Some(None) => {
                if let Some(shared) = &self.tokens.shared {
                    request
                        .extensions_mut()
                        .insert(SharedShare(Arc::clone(shared)));
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
        let text = "# trainers\nteam-a 0123456789abcdef envs=100 rollouts=1\n\n\
                    team-b fedcba9876543210fedc # no quota\n";
        let tenants = parse_tenants(text, Share::default()).unwrap();
        assert_eq!(tenants.len(), 2);
        assert_eq!(tenants[0].token.expose(), "0123456789abcdef");
        assert_eq!(tenants[0].share.max_envs, 100);
        assert_eq!(tenants[0].share.max_rollouts, 1);
        assert_eq!(tenants[1].share, Share::default());
        assert_eq!(
            parse_tenants("a 0123456789abcdef envs=x", Share::default()),
            Err("line 1: envs must be a whole number, got \"x\"".into())
        );
        let twice = "a 0123456789abcdef\nb 0123456789abcdef";
        assert!(parse_tenants(twice, Share::default()).is_err());
        assert!(parse_tenants("lonely", Share::default()).is_err());
    }

    #[test]
    fn short_tokens_and_tokens_with_a_hash_are_refused_not_cut() {
        assert_eq!(check_token("0123456789abcdef"), Ok(()));
        assert_eq!(check_token("s3cret"), Err(TokenError::TooShort(6)));
        assert_eq!(check_token("0123456789#abcdef"), Err(TokenError::Hash));
        assert_eq!(
            check_token("0123456789 abcdef"),
            Err(TokenError::NotVisibleAscii)
        );
        assert_eq!(
            check_token("0123456789abcdéf"),
            Err(TokenError::NotVisibleAscii)
        );
        // In a tenants file, a `#` inside a word is part of the token, which is then refused;
        // after whitespace or at the start of a line it starts a comment.
        let hash = parse_tenants("team-a 01234567#89abcdefgh\n", Share::default()).unwrap_err();
        assert!(hash.starts_with("line 1: tenant \"team-a\": "), "{hash}");
        assert!(hash.contains('#') && !hash.contains("01234567"), "{hash}");
        let short = parse_tenants("\nteam-b s3cret # old\n", Share::default()).unwrap_err();
        assert!(short.starts_with("line 2: tenant \"team-b\": "), "{short}");
        assert!(
            !short.contains("s3cret"),
            "the error repeats the token: {short}"
        );
        assert_eq!(without_comment("#all"), "");
        assert_eq!(without_comment("a b\t# c"), "a b\t");
        assert_eq!(without_comment("a b#c # d"), "a b#c ");
    }

    #[test]
    fn debug_output_holds_no_token() {
        let secret = "0123456789abcdef-top";
        let tenants = tenant_tokens(&format!("team-a {secret}\n"), Share::default()).unwrap();
        let lines = parse_tenants(&format!("team-a {secret}\n"), Share::default()).unwrap();
        let tokens = Tokens::new(&tenants);
        for shown in [
            format!("{tenants:?}"),
            format!("{lines:?}"),
            format!("{tokens:?}"),
            format!("{:?}", Secret::from(secret)),
        ] {
            assert!(!shown.contains(secret), "{shown}");
        }
        assert!(format!("{tokens:?}").contains("tenant team-a"));
    }

    #[test]
    fn tenants_get_a_fair_part_of_the_sessions_and_keep_their_identity() {
        let rules = TenantRules {
            share: Share::default(),
            max_sessions: 10,
            max_connections: 7,
            max_calls: 1365,
            shared_token: Some("shared-token-0123456789".into()),
        };
        let text = "a aaaaaaaaaaaaaaaa\nb bbbbbbbbbbbbbbbb sessions=7\n";
        let lines = rules.lines(text).unwrap();
        // Three identities (two tenants and the shared token): 10 / 3 each, unless a line says.
        assert_eq!(lines[0].share.max_sessions, 3);
        assert_eq!(lines[1].share.max_sessions, 7);
        assert_eq!(rules.shared_share(2).max_sessions, 3);
        // Connections and calls too: 7 / 3, and 1365 / 3.
        assert_eq!(lines[0].share.max_connections, 2);
        assert_eq!(lines[0].share.max_streams, 455);
        let alone = rules.shared_share(0);
        // Alone, an identity may have half the calls open (two are needed to fill the bound).
        assert_eq!((alone.max_connections, alone.max_streams), (7, 682));
        assert_eq!(fair_part(1, 5), 1);
        let quotas = "c cccccccccccccccc connections=9 streams=11\n";
        let c = &rules.lines(quotas).unwrap()[0].share;
        assert_eq!((c.max_connections, c.max_streams), (9, 11));
        assert!(
            rules
                .lines("c cccccccccccccccc sockets=9\n")
                .unwrap_err()
                .contains("use envs, sessions, rollouts, connections or streams")
        );
        let twice = rules.lines("a shared-token-0123456789\n").unwrap_err();
        assert!(
            twice.contains("tenant \"a\"'s token is also the shared token"),
            "{twice}"
        );
        assert!(!twice.contains("shared-token-0123456789"), "{twice}");

        let roster = Roster::default();
        let before = roster.tokens(lines);
        let a = Arc::clone(before[0].tenant.as_ref().unwrap());
        let tokens = Tokens::new(&before);
        assert!(tokens.check(b"Bearer aaaaaaaaaaaaaaaa").is_some());
        // A rotated: the same tenant, a new token; b gone.
        let after = roster.tokens(rules.lines("a cccccccccccccccc envs=5\n").unwrap());
        assert!(Arc::ptr_eq(after[0].tenant.as_ref().unwrap(), &a));
        assert_eq!(a.share().max_envs, 5);
        assert_eq!(
            a.share().max_sessions,
            5,
            "10 / (1 tenant + the shared token)"
        );
        tokens.replace(&after);
        assert!(tokens.check(b"Bearer aaaaaaaaaaaaaaaa").is_none());
        assert!(tokens.check(b"Bearer bbbbbbbbbbbbbbbb").is_none());
        assert!(tokens.stand_for(&a));
    }

    #[test]
    fn same_bytes_compares_whole_values() {
        assert!(same_bytes(b"Bearer abc", b"Bearer abc"));
        assert!(!same_bytes(b"Bearer abc", b"Bearer abd"));
        assert!(!same_bytes(b"Bearer ab", b"Bearer abc"));
        assert!(same_bytes(b"", b""));
    }
}
