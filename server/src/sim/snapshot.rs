//! The versioned binary snapshot format: a 4-byte kind tag, a little-endian `u16` format
//! version, then the value in postcard's serde encoding.
//!
//! A value whose first field is a sequence (a session's environments) starts its payload with
//! the sequence's length, a varint: [`leading_count`] reads it without decoding anything else,
//! so that a reader can refuse too many elements before it allocates them.

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

/// The payload of bytes written by [`encode`] with the same kind tag, once the tag and the
/// version are checked.
fn payload(kind: [u8; 4], bytes: &[u8]) -> Result<&[u8], SnapshotError> {
    if bytes.len() < 6 || bytes[..4] != kind {
        return Err(SnapshotError::Kind {
            expected: String::from_utf8_lossy(&kind).into_owned(),
        });
    }
    let found = u16::from_le_bytes([bytes[4], bytes[5]]);
    if found != SNAPSHOT_VERSION {
        return Err(SnapshotError::Version { found });
    }
    Ok(&bytes[6..])
}

/// The length of the sequence that starts the value of bytes written by [`encode`] with the
/// same kind tag (postcard writes it first, as a varint), read without decoding the value.
pub fn leading_count(kind: [u8; 4], bytes: &[u8]) -> Result<u64, SnapshotError> {
    let mut count = 0u64;
    for (i, &b) in payload(kind, bytes)?.iter().enumerate().take(10) {
        count |= u64::from(b & 0x7f) << (7 * i);
        if b < 0x80 {
            return Ok(count);
        }
    }
    Err(SnapshotError::Corrupt("no sequence length".into()))
}

/// Decodes bytes written by [`encode`] with the same kind tag.
pub fn decode<T: DeserializeOwned>(kind: [u8; 4], bytes: &[u8]) -> Result<T, SnapshotError> {
    let (value, rest) = postcard::take_from_bytes(payload(kind, bytes)?)
        .map_err(|e| SnapshotError::Corrupt(e.to_string()))?;
    if !rest.is_empty() {
        return Err(SnapshotError::Corrupt(format!(
            "{} trailing bytes",
            rest.len()
        )));
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_leading_count_is_read_without_decoding() {
        let bytes = encode(*b"test", &(vec![7u8; 300], 1u32));
        assert_eq!(leading_count(*b"test", &bytes), Ok(300));
        assert!(matches!(
            leading_count(*b"othr", &bytes),
            Err(SnapshotError::Kind { .. })
        ));
        // A claim of 2^63 elements followed by nothing: refused by the reader's bound, and the
        // decoder refuses it without allocating them.
        let mut huge = bytes[..6].to_vec();
        huge.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f]);
        assert_eq!(leading_count(*b"test", &huge), Ok(u64::MAX >> 1));
        assert!(decode::<(Vec<u8>, u32)>(*b"test", &huge).is_err());
        assert!(leading_count(*b"test", &bytes[..6]).is_err());
    }
}
