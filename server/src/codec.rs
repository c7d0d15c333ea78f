//! The protobuf codec of `dinerdash.v1`: prost's, except that
//! - bytes which do not decode are the client's fault (`INVALID_ARGUMENT`), not the server's
//!   (`INTERNAL`, prost's choice);
//! - a request is measured on the wire before prost decodes it ([`WireBounds`]): a repeated
//!   field holding more elements than any session could use (Reset's arrival lists and seeds,
//!   Rollout's seeds), an arrival list of more groups than an episode has, a byte field longer
//!   than any session's actions or mask, or an arrival group too short to name its customers is
//!   refused `INVALID_ARGUMENT` before prost allocates a vector for it. Prost turns a 2-byte empty submessage into a 24-byte struct in
//!   a vector that doubles as it grows, so 16 MiB of empty arrival lists used to become ~380 MiB
//!   before anything was checked; past these bounds a decoded request is at most a few times
//!   its size, which [`intake`] charges while it is received and decoded.
//!
//! The bounds here are the server's ceilings (a session has at most [`MAX_ENVS`] environments,
//! whatever `--max-envs-per-session` says); each request is then checked against its session's
//! own number of environments before it is converted (`service::convert`).

pub mod intake;

use tonic::Status;
use tonic::codec::{BufferSettings, Codec, DecodeBuf, Decoder};
use tonic_prost::{ProstCodec, ProstDecoder, ProstEncoder};

use crate::pb;
use crate::rollout::MAX_ROLLOUT_EPISODES;
use crate::sim::MAX_ARRIVALS;

/// Most environments any session may have: the largest `--max-envs-per-session`.
pub const MAX_ENVS: usize = 65_536;
/// Shortest encoding of an arrival group the game accepts: both fields are at least 1, so both
/// are on the wire, a tag and a one-byte varint each.
const MIN_GROUP_BYTES: usize = 4;

/// Why a request's wire bytes were refused before decoding. Every variant is
/// `INVALID_ARGUMENT`; each message starts with the field it is about.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// The bytes are not protobuf (a truncated field, a bad varint, a group).
    #[error("undecodable message: {0}")]
    Malformed(&'static str),
    /// A repeated field holds more elements than its bound.
    #[error("{field} must hold at most {max} {what}, got more ({why})")]
    TooMany {
        /// The field.
        field: String,
        /// Its bound.
        max: usize,
        /// What it counts.
        what: &'static str,
        /// Where the bound comes from.
        why: &'static str,
    },
    /// An arrival list without a group, or a group without its customers.
    #[error("{0}")]
    Shape(String),
}

impl From<WireError> for Status {
    fn from(e: WireError) -> Status {
        Status::invalid_argument(e.to_string())
    }
}

/// One field of a message on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Value<'a> {
    /// Wire type 0, and its value.
    Varint(u64),
    /// Wire types 1 and 5.
    Fixed,
    /// Wire type 2: bytes, a string, a submessage or a packed repeated field.
    Delimited(&'a [u8]),
}

/// Reads a varint at the start of `bytes`: its value and its length.
fn varint(bytes: &[u8]) -> Result<(u64, usize), WireError> {
    let mut value = 0u64;
    for (i, &b) in bytes.iter().enumerate().take(10) {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b < 0x80 {
            return Ok((value, i + 1));
        }
    }
    Err(WireError::Malformed("a varint runs past its field"))
}

/// The fields of one message's bytes, in order: `(field number, value)`. Reads no more than
/// the bytes hold and allocates nothing.
struct Fields<'a>(&'a [u8]);

impl<'a> Iterator for Fields<'a> {
    type Item = Result<(u64, Value<'a>), WireError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.0.is_empty() {
            return None;
        }
        Some(self.field())
    }
}

impl<'a> Fields<'a> {
    fn field(&mut self) -> Result<(u64, Value<'a>), WireError> {
        let truncated = WireError::Malformed("a field runs past the message");
        let (key, n) = varint(self.0)?;
        let rest = &self.0[n..];
        let (value, used) = match key & 7 {
            0 => {
                let (v, n) = varint(rest)?;
                (Value::Varint(v), n)
            }
            1 => (Value::Fixed, 8),
            5 => (Value::Fixed, 4),
            2 => {
                let (len, n) = varint(rest)?;
                let len = usize::try_from(len).map_err(|_| truncated.clone())?;
                let end = n.checked_add(len).ok_or_else(|| truncated.clone())?;
                (
                    Value::Delimited(rest.get(n..end).ok_or(truncated.clone())?),
                    end,
                )
            }
            _ => return Err(WireError::Malformed("groups are not part of dinerdash.v1")),
        };
        self.0 = rest.get(used..).ok_or(truncated)?;
        Ok((key >> 3, value))
    }
}

/// Elements of a repeated varint field's occurrence: one unpacked, or as many as the packed
/// bytes end varints.
fn varints(value: Value<'_>) -> usize {
    match value {
        Value::Delimited(packed) => packed.iter().filter(|&&b| b < 0x80).count(),
        Value::Varint(_) | Value::Fixed => 1,
    }
}

/// Length of a bytes or string field (0 for a field of another wire type, which prost refuses).
fn length(value: Value<'_>) -> usize {
    match value {
        Value::Delimited(bytes) => bytes.len(),
        Value::Varint(_) | Value::Fixed => 0,
    }
}

/// Refuses `count` elements of `field` over `max`.
fn at_most(
    count: usize,
    field: &str,
    max: usize,
    what: &'static str,
    why: &'static str,
) -> Result<(), WireError> {
    if count > max {
        return Err(WireError::TooMany {
            field: field.into(),
            max,
            what,
            why,
        });
    }
    Ok(())
}

/// What a message's wire bytes may hold, checked before prost decodes them: a message with
/// repeated fields says how many elements each may have; the others accept any bytes (their
/// decoded size does not depend on the input beyond its length).
pub trait WireBounds {
    /// Refuses `bytes` when the message they encode would pass a bound. By default nothing is
    /// checked (no pass over the bytes: replies the Rust client decodes stay as fast as prost);
    /// prost refuses malformed bytes itself.
    fn check_wire(_bytes: &[u8]) -> Result<(), WireError> {
        Ok(())
    }
}

impl WireBounds for pb::ResetRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), WireError> {
        const WHY: &str = "a session has at most 65536 environments";
        let (mut seeds, mut lists) = (0usize, 0usize);
        for field in Fields(bytes) {
            let (number, value) = field?;
            match number {
                3 => {
                    seeds += varints(value);
                    at_most(seeds, "seeds", MAX_ENVS, "seeds", WHY)?;
                }
                4 => {
                    at_most(lists + 1, "arrivals", MAX_ENVS, "lists", WHY)?;
                    check_arrival_list(lists, value)?;
                    lists += 1;
                }
                6 => at_most(length(value), "reset_mask", MAX_ENVS, "flags", WHY)?,
                _ => {}
            }
        }
        Ok(())
    }
}

/// Arrival list `i` on the wire: 1..=[`MAX_ARRIVALS`] groups, each long enough to give both its
/// customer type and its size (the game's rules for a list, checked again once decoded, with
/// the same messages).
fn check_arrival_list(i: usize, value: Value<'_>) -> Result<(), WireError> {
    let Value::Delimited(list) = value else {
        return Ok(());
    };
    let mut groups = 0usize;
    for field in Fields(list) {
        let (number, value) = field?;
        if number != 1 {
            continue;
        }
        if let Value::Delimited(group) = value {
            if group.len() < MIN_GROUP_BYTES {
                return Err(WireError::Shape(short_group(i, groups, group)?));
            }
        }
        groups += 1;
    }
    if !(1..=MAX_ARRIVALS).contains(&groups) {
        return Err(WireError::Shape(format!(
            "arrivals[{i}] must hold 1..={MAX_ARRIVALS} groups, got {groups}"
        )));
    }
    Ok(())
}

/// Why group `g` of arrival list `i`, shorter than both its fields, is refused: one of them is
/// absent, so 0, which the game refuses with this message.
fn short_group(i: usize, g: usize, group: &[u8]) -> Result<String, WireError> {
    let (mut customer_type, mut size) = (0, 0);
    for field in Fields(group) {
        match field? {
            (1, Value::Varint(v)) => customer_type = v,
            (2, Value::Varint(v)) => size = v,
            _ => {}
        }
    }
    Ok(if (1..=2).contains(&customer_type) {
        format!("arrivals[{i}].groups[{g}].size must be in 1..=6, got {size}")
    } else {
        format!("arrivals[{i}].groups[{g}].customer_type must be in 1..=2, got {customer_type}")
    })
}

impl WireBounds for pb::StepRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), WireError> {
        for field in Fields(bytes) {
            let (number, value) = field?;
            if number == 2 {
                at_most(
                    length(value),
                    "actions",
                    4 * MAX_ENVS,
                    "bytes",
                    "4 bytes for each of at most 65536 environments",
                )?;
            }
        }
        Ok(())
    }
}

impl WireBounds for pb::RolloutRequest {
    fn check_wire(bytes: &[u8]) -> Result<(), WireError> {
        let mut seeds = 0usize;
        for field in Fields(bytes) {
            let (number, value) = field?;
            if number == 2 {
                seeds += varints(value);
                at_most(
                    seeds,
                    "seeds",
                    MAX_ROLLOUT_EPISODES as usize,
                    "seeds",
                    "the most episodes of one Rollout",
                )?;
            }
        }
        Ok(())
    }
}

/// Messages with no repeated field (prost skips unknown fields without keeping them), and the
/// replies the Rust client decodes.
macro_rules! unbounded {
    ($($message:ty),* $(,)?) => {$( impl WireBounds for $message {} )*};
}

unbounded!(
    // A session ID is bounded by the method's largest message (`intake`).
    pb::CloseSessionRequest,
    pb::ForkRequest,
    pb::SnapshotRequest,
    pb::RenderRequest,
    // A snapshot is one byte field; its environment count is checked before its environments
    // are decoded (`Envs::restore`).
    pb::RestoreRequest,
    pb::CreateSessionRequest,
    pb::ServerInfoRequest,
    pb::CreateSessionResponse,
    pb::CloseSessionResponse,
    pb::Batch,
    pb::SnapshotResponse,
    pb::RenderResponse,
    pb::Episode,
    pb::ServerInfoResponse,
);

/// [`ProstCodec`] with requests measured before they are decoded ([`WireBounds`]) and decode
/// errors answered `INVALID_ARGUMENT`; the generated code uses it.
#[derive(Debug, Clone, Copy)]
pub struct StrictCodec<T, U>(std::marker::PhantomData<(T, U)>);

impl<T, U> Default for StrictCodec<T, U> {
    fn default() -> Self {
        StrictCodec(std::marker::PhantomData)
    }
}

impl<T, U> Codec for StrictCodec<T, U>
where
    T: prost::Message + Send + 'static,
    U: prost::Message + WireBounds + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = StrictDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstCodec::<T, U>::default().encoder()
    }

    fn decoder(&mut self) -> Self::Decoder {
        StrictDecoder(ProstCodec::<T, U>::default().decoder())
    }
}

/// Measures the message ([`WireBounds`]), then decodes like prost; a malformed message is
/// `INVALID_ARGUMENT`.
#[derive(Debug, Clone, Default)]
pub struct StrictDecoder<U>(ProstDecoder<U>);

impl<U: prost::Message + WireBounds + Default> Decoder for StrictDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        use prost::bytes::Buf as _;
        // The message is one contiguous buffer (tonic gathers it before decoding); should it
        // ever come in pieces, prost's own limits still hold and only this check is skipped.
        let bytes = buf.chunk();
        if bytes.len() == buf.remaining() {
            U::check_wire(bytes)?;
        }
        self.0
            .decode(buf)
            .map_err(|s| Status::invalid_argument(format!("undecodable message: {}", s.message())))
    }

    fn buffer_settings(&self) -> BufferSettings {
        self.0.buffer_settings()
    }
}

#[cfg(test)]
mod tests {
    use prost::Message as _;

    use super::*;

    fn reset(r: pb::ResetRequest) -> Result<(), WireError> {
        pb::ResetRequest::check_wire(&r.encode_to_vec())
    }

    fn list(groups: usize) -> pb::ArrivalList {
        pb::ArrivalList {
            groups: vec![
                pb::Arrival {
                    customer_type: 1,
                    size: 2
                };
                groups
            ],
        }
    }

    #[test]
    fn legitimate_requests_pass_and_their_bounds_are_exact() {
        let full = pb::ResetRequest {
            seeds: vec![u64::MAX; MAX_ENVS],
            arrivals: vec![list(MAX_ARRIVALS); 16],
            reset_mask: vec![1; MAX_ENVS],
            ..Default::default()
        };
        assert_eq!(reset(full.clone()), Ok(()));
        let more_seeds = pb::ResetRequest {
            seeds: vec![0; MAX_ENVS + 1],
            ..full.clone()
        };
        assert!(matches!(
            reset(more_seeds),
            Err(WireError::TooMany { max: MAX_ENVS, .. })
        ));
        let more_groups = pb::ResetRequest {
            arrivals: vec![list(1), list(MAX_ARRIVALS + 1)],
            ..Default::default()
        };
        let e = reset(more_groups).unwrap_err().to_string();
        assert_eq!(e, "arrivals[1] must hold 1..=200 groups, got 201");
        let step = pb::StepRequest {
            session_id: "x".into(),
            actions: vec![0; 4 * MAX_ENVS],
        };
        assert_eq!(pb::StepRequest::check_wire(&step.encode_to_vec()), Ok(()));
        let rollout = pb::RolloutRequest {
            seeds: (0..u64::from(MAX_ROLLOUT_EPISODES) + 1).collect(),
            ..Default::default()
        };
        assert!(pb::RolloutRequest::check_wire(&rollout.encode_to_vec()).is_err());
    }

    #[test]
    fn empty_submessages_are_refused_before_decoding() {
        let empty_lists = pb::ResetRequest {
            arrivals: vec![pb::ArrivalList::default(); 3],
            ..Default::default()
        };
        assert_eq!(
            reset(empty_lists).unwrap_err().to_string(),
            "arrivals[0] must hold 1..=200 groups, got 0"
        );
        let empty_group = pb::ResetRequest {
            arrivals: vec![pb::ArrivalList {
                groups: vec![pb::Arrival::default()],
            }],
            ..Default::default()
        };
        assert_eq!(
            reset(empty_group).unwrap_err().to_string(),
            "arrivals[0].groups[0].customer_type must be in 1..=2, got 0"
        );
        let no_size = pb::ResetRequest {
            arrivals: vec![pb::ArrivalList {
                groups: vec![pb::Arrival {
                    customer_type: 2,
                    size: 0,
                }],
            }],
            ..Default::default()
        };
        assert_eq!(
            reset(no_size).unwrap_err().to_string(),
            "arrivals[0].groups[0].size must be in 1..=6, got 0"
        );
        // Many lists, even well-formed ones, past the most environments of a session.
        let mut lists = Vec::new();
        for _ in 0..=MAX_ENVS {
            lists.extend_from_slice(&[0x22, 0x06, 0x0a, 0x04, 0x08, 0x01, 0x10, 0x01]);
        }
        let e = pb::ResetRequest::check_wire(&lists).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("arrivals must hold at most 65536 lists"),
            "{e}"
        );
    }

    #[test]
    fn malformed_bytes_are_refused_without_reading_past_them() {
        for bytes in [
            &[0x22, 0x05, 0x0a][..],
            &[
                0x1a, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01,
            ],
            &[0x0b],
            &[0x09, 0x00],
            &[0x80],
        ] {
            assert!(
                matches!(
                    pb::ResetRequest::check_wire(bytes),
                    Err(WireError::Malformed(_))
                ),
                "{bytes:?}"
            );
        }
    }
}
