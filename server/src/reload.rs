//! The tokens file (`--auth-tokens-file`) read again on SIGHUP, so that tokens can be added,
//! rotated and removed without a restart (which would lose every session):
//!
//! - a new token works from its next request, a removed one is refused from its next request
//!   ([`crate::auth::Tokens::replace`]);
//! - a tenant whose line stays (or comes back) is the same tenant ([`Roster`]): its sessions
//!   stay its own and what it holds still counts; its share becomes its line's;
//! - a file that cannot be read, or with a bad line (the same rules as at start, the shared
//!   token included), changes nothing: the tokens before stay, and the log says why.
//!
//! The binary listens for SIGHUP ([`Hangups::listen`]) before it says it is listening, so that
//! a SIGHUP sent as soon as the line is read is never lost (nor kills the process).

use std::path::PathBuf;
use std::sync::Arc;

use crate::auth::{Roster, TenantRules, Token, Tokens};
use crate::budget::Tenant;
use crate::config::{ConfigError, read_tenants};
use crate::shutdown::Shutdown;

/// SIGHUPs, listened for from creation on (Unix); none elsewhere or when not asked for.
#[derive(Debug, Default)]
pub struct Hangups {
    /// The listener.
    #[cfg(unix)]
    signal: Option<tokio::signal::unix::Signal>,
}

impl Hangups {
    /// Starts listening for SIGHUP (inside a tokio runtime): the signal no longer ends the
    /// process.
    pub fn listen() -> Hangups {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{SignalKind, signal};
            Hangups {
                signal: signal(SignalKind::hangup())
                    .map_err(|e| tracing::warn!("cannot listen for SIGHUP ({e})"))
                    .ok(),
            }
        }
        #[cfg(not(unix))]
        Hangups {}
    }

    /// Completes on the next SIGHUP; never without a listener.
    async fn recv(&mut self) {
        #[cfg(unix)]
        if let Some(signal) = self.signal.as_mut()
            && signal.recv().await.is_some()
        {
            return;
        }
        std::future::pending().await
    }
}

/// Reads the tokens file again and hands its tokens to the server's [`Tokens`].
#[derive(Debug)]
pub struct Reloader {
    /// `--auth-tokens-file`.
    pub path: PathBuf,
    /// The shares' defaults and the shared token.
    pub rules: TenantRules,
    /// Every tenant known so far.
    pub roster: Roster,
    /// The tokens the request gate and the web endpoint check.
    pub tokens: Tokens,
    /// The shared token's share, whose fair part of the sessions follows the tenants' count.
    pub shared: Option<Arc<Tenant>>,
}

impl Reloader {
    /// Reads the file and, if it is valid, accepts its tokens (and the shared token) instead of
    /// the ones before; returns the tenants' names. On an error nothing changes.
    pub fn reload(&self) -> Result<Vec<String>, ConfigError> {
        let lines = read_tenants(&self.path, &self.rules)?;
        let names = lines.iter().map(|l| l.name.clone()).collect();
        if let Some(shared) = &self.shared {
            shared.set_share(self.rules.shared_share(lines.len()));
        }
        let mut tokens = self.roster.tokens(lines);
        if let Some(token) = &self.rules.shared_token {
            tokens.push(Token {
                token: token.clone(),
                tenant: None,
            });
        }
        self.tokens.replace(&tokens);
        Ok(names)
    }

    /// Reads the file again on every SIGHUP of `hangups` until `stopping` fires.
    pub async fn on_hangups(self, mut hangups: Hangups, mut stopping: Shutdown) {
        loop {
            tokio::select! {
                () = stopping.wait() => return,
                () = hangups.recv() => match self.reload() {
                    Ok(names) => tracing::info!(
                        file = %self.path.display(),
                        tenants = names.join(","),
                        "SIGHUP: tokens file read again"
                    ),
                    Err(e) => tracing::warn!(
                        "SIGHUP: the tokens file is refused, the tokens before stay: {e}"
                    ),
                },
            }
        }
    }
}
