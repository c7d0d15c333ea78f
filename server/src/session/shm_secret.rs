//! A session's shared-memory credential: the secret the doorbell's hello must carry
//! (docs/shm.md). Drawn from the operating system's random source when the session is created,
//! forked or restored, told only in the reply to the caller that made it, compared in constant
//! time, and never written by `Debug` (nor by anything else of the server: no log, no page).

/// Bytes of a secret: 256 random bits.
pub const SHM_SECRET_BYTES: usize = 32;

/// A session's shared-memory secret. `Debug` prints no byte of it; `==` takes the same time
/// whichever bytes differ.
#[derive(Clone, Copy)]
pub struct ShmSecret([u8; SHM_SECRET_BYTES]);

impl ShmSecret {
    /// A fresh secret from the operating system's random source.
    pub(super) fn random() -> Result<ShmSecret, super::SessionError> {
        use rand::TryRngCore;
        let mut bytes = [0u8; SHM_SECRET_BYTES];
        rand::rngs::OsRng.try_fill_bytes(&mut bytes).map_err(|e| {
            super::SessionError::Internal(format!("no system randomness for a session secret: {e}"))
        })?;
        Ok(ShmSecret(bytes))
    }

    /// The bytes, for the one reply that tells them to the session's creator.
    pub fn expose(&self) -> &[u8; SHM_SECRET_BYTES] {
        &self.0
    }

    /// Whether `given` is this secret, in time that depends only on `given`'s length (which is
    /// public: always [`SHM_SECRET_BYTES`] for a well-formed hello).
    pub fn matches(&self, given: &[u8]) -> bool {
        if given.len() != SHM_SECRET_BYTES {
            return false;
        }
        let diff = self
            .0
            .iter()
            .zip(given)
            .fold(0u8, |acc, (a, b)| acc | (a ^ b));
        // Keeps the compiler from turning the fold into an early exit.
        std::hint::black_box(diff) == 0
    }
}

impl PartialEq for ShmSecret {
    fn eq(&self, other: &ShmSecret) -> bool {
        self.matches(&other.0)
    }
}

impl Eq for ShmSecret {}

impl std::fmt::Debug for ShmSecret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ShmSecret(<redacted>)")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_only_itself_and_debug_shows_no_byte() {
        let a = ShmSecret::random().unwrap();
        let b = ShmSecret::random().unwrap();
        assert!(a.matches(a.expose()));
        assert!(!a.matches(b.expose()));
        assert!(!a.matches(&a.expose()[..31]));
        assert!(!a.matches(&[]));
        let mut flipped = *a.expose();
        flipped[31] ^= 1;
        assert!(!a.matches(&flipped));
        assert_eq!(a, a);
        assert_ne!(a, b);
        let shown = format!("{a:?} {:?}", Some(a));
        assert_eq!(shown, "ShmSecret(<redacted>) Some(ShmSecret(<redacted>))");
        let hex: String = a.expose().iter().map(|b| format!("{b:02x}")).collect();
        assert!(!shown.contains(&hex[..8]));
    }
}
