//! The versioned binary snapshot format: a 4-byte kind tag, a little-endian `u16` format
//! version, then the value in postcard's serde encoding.

use serde::{Serialize, de::DeserializeOwned};

use super::restaurant::StateError;

/// The snapshot format version this build writes and reads.
pub const SNAPSHOT_VERSION: u16 = 1;
/// Kind tag of a single [`super::Game`].
pub const GAME: [u8; 4] = *b"DDgm";

/// Why snapshot bytes could not be restored.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SnapshotError {
    /// The bytes do not start with the expected kind tag.
    #[error("not a {expected} snapshot")]
    Kind {
        /// The kind that was expected.
        expected: String,
    },
    /// Written by a different format version.
    #[error(
        "snapshot version {found} is not supported (this server reads version {SNAPSHOT_VERSION})"
    )]
    Version {
        /// The version in the bytes.
        found: u16,
    },
    /// The payload does not decode.
    #[error("corrupt snapshot: {0}")]
    Corrupt(String),
    /// The payload decodes to a state the game cannot reach.
    #[error(transparent)]
    State(#[from] StateError),
}

/// Encodes `value` under the given kind tag.
pub fn encode<T: Serialize>(kind: [u8; 4], value: &T) -> Vec<u8> {
    let mut out = Vec::with_capacity(4096);
    out.extend_from_slice(&kind);
    out.extend_from_slice(&SNAPSHOT_VERSION.to_le_bytes());
    // Plain data (no maps, no unsized sequences) always serialises into a growable Vec.
    postcard::to_extend(value, out).expect("postcard serialisation into a Vec")
}

/// Decodes bytes written by [`encode`] with the same kind tag.
pub fn decode<T: DeserializeOwned>(kind: [u8; 4], bytes: &[u8]) -> Result<T, SnapshotError> {
    if bytes.len() < 6 || bytes[..4] != kind {
        return Err(SnapshotError::Kind {
            expected: String::from_utf8_lossy(&kind).into_owned(),
        });
    }
    let found = u16::from_le_bytes([bytes[4], bytes[5]]);
    if found != SNAPSHOT_VERSION {
        return Err(SnapshotError::Version { found });
    }
    let (value, rest) = postcard::take_from_bytes(&bytes[6..])
        .map_err(|e| SnapshotError::Corrupt(e.to_string()))?;
    if !rest.is_empty() {
        return Err(SnapshotError::Corrupt(format!(
            "{} trailing bytes",
            rest.len()
        )));
    }
    Ok(value)
}
