//! The one encode/decode seam: every payload on the wire is little-endian
//! CDR (XCDR1) with the 4-byte encapsulation header `00 01 00 00`, the
//! encoding ROS 2 uses, so ROS types are byte-compatible with ROS 2 peers.
//! Call sites never name the codec.

mod reader;

use serde::{de::DeserializeOwned, Deserialize, Serialize};
use zenoh::bytes::ZBytes;

use crate::error::{DecodeError, EncodeError};

/// Encapsulation header of little-endian plain CDR.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Encodes a message into a fresh buffer of exactly the needed capacity
/// (an image is copied once, never through a growing buffer).
pub fn encode<T: Serialize + ?Sized>(msg: &T) -> Result<Vec<u8>, EncodeError> {
    let mut buf = Vec::with_capacity(cdr::calc_serialized_size(msg) as usize);
    encode_into(msg, &mut buf)?;
    Ok(buf)
}

/// A message already encoded, e.g. by [`encode_with_tail`]: replied as is.
/// A big last byte sequence (an observation's pixels) is kept apart from the
/// head and sent as its own slices, never copied into it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Encoded<T> {
    head: Vec<u8>,
    tail: ZBytes,
    of: std::marker::PhantomData<fn() -> T>,
}

impl<T: Serialize> Encoded<T> {
    /// Encodes `msg`.
    pub fn new(msg: &T) -> Result<Self, EncodeError> {
        Ok(Self::from_parts(encode(msg)?, ZBytes::default()))
    }
}

impl<T> Encoded<T> {
    fn from_parts(head: Vec<u8>, tail: ZBytes) -> Self {
        Self {
            head,
            tail,
            of: std::marker::PhantomData,
        }
    }

    /// The payload as Zenoh sends it: the head, then the tail's slices.
    pub fn into_payload(self) -> ZBytes {
        if self.tail.is_empty() {
            return self.head.into();
        }
        let mut writer = ZBytes::writer();
        writer.append(self.head.into());
        writer.append(self.tail);
        writer.finish()
    }

    /// The payload in one buffer (a copy: for tests and tools).
    pub fn to_vec(&self) -> Vec<u8> {
        [self.head.as_slice(), &self.tail.to_bytes()].concat()
    }
}

impl<T: DeserializeOwned> Encoded<T> {
    /// Decodes the message back.
    pub fn decode(&self) -> Result<T, DecodeError> {
        decode(&self.to_vec())
    }
}

/// Encodes `msg`, whose last field is an empty byte sequence, as if that
/// field held `tail`: the bytes are those of the plain encoding, but `tail`
/// is not copied (see [`Encoded::into_payload`]).
pub fn encode_with_tail<T: Serialize>(
    msg: &T,
    tail: impl Into<ZBytes>,
) -> Result<Encoded<T>, EncodeError> {
    let tail = tail.into();
    Ok(Encoded::from_parts(
        encode_open_tail(msg, tail.len())?,
        tail,
    ))
}

/// Encodes `msg`, whose last field is an empty byte sequence, as if that
/// field held `len` bytes, leaving them out: the caller writes them right
/// after the returned bytes (CDR puts no padding before them).
pub fn encode_open_tail<T: Serialize>(msg: &T, len: usize) -> Result<Vec<u8>, EncodeError> {
    let mut head = encode(msg)?;
    let count = u32::try_from(len)
        .map_err(|_| EncodeError(format!("a byte sequence of {len} bytes is too long")))?;
    // CDR writes a sequence as its u32 count, then its elements: the empty
    // last field is the count 0 at the very end.
    match head.last_chunk_mut::<4>() {
        Some(last) if *last == [0; 4] => *last = count.to_le_bytes(),
        _ => {
            return Err(EncodeError(
                "the message does not end with an empty byte sequence".into(),
            ))
        }
    }
    Ok(head)
}

/// Encodes a message into `buf`, replacing its contents but keeping its
/// capacity: big frames reuse one allocation from step to step.
pub fn encode_into<T: Serialize + ?Sized>(msg: &T, buf: &mut Vec<u8>) -> Result<(), EncodeError> {
    buf.clear();
    cdr::serialize_into::<_, _, _, cdr::CdrLe>(&mut *buf, msg, cdr::Infinite)
        .map_err(|e| EncodeError(e.to_string()))
}

/// Decodes a message, borrowing byte and string payloads from `bytes` where
/// the type allows it.
///
/// Rejects a wrong header, truncation, invalid values and more than 3
/// trailing bytes (alignment padding some writers add). Never panics and
/// never allocates more than the input can justify.
pub fn decode_borrowed<'de, T: Deserialize<'de>>(bytes: &'de [u8]) -> Result<T, DecodeError> {
    let (header, body) = bytes
        .split_first_chunk::<4>()
        .ok_or(DecodeError::TooShort(bytes.len()))?;
    // Bytes 2..4 are options (padding bits) that we ignore, as ROS 2 does.
    if header[..2] != CDR_LE_HEADER[..2] {
        return Err(DecodeError::BadHeader(*header));
    }
    let mut reader = reader::CdrReader::new(body);
    let value = T::deserialize(&mut reader)?;
    let trailing = reader.remaining();
    if trailing.len() > 3 || trailing.iter().any(|b| *b != 0) {
        return Err(DecodeError::TrailingBytes(trailing.len()));
    }
    Ok(value)
}

/// Decodes an owned message (see [`decode_borrowed`]).
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, DecodeError> {
    decode_borrowed(bytes)
}

/// A payload in one slice, so borrowed decodes read it in place. Payloads
/// reassembled from fragments are copied together once, here.
pub fn contiguous(payload: &zenoh::bytes::ZBytes) -> zenoh::bytes::ZBytes {
    match payload.to_bytes() {
        std::borrow::Cow::Borrowed(_) => payload.clone(),
        std::borrow::Cow::Owned(joined) => joined.into(),
    }
}

/// Decodes a Zenoh payload; contiguous payloads are read in place.
pub fn decode_payload<T: DeserializeOwned>(
    payload: &zenoh::bytes::ZBytes,
) -> Result<T, DecodeError> {
    decode(&payload.to_bytes())
}

/// A message whose last field is a big byte sequence (an observation's
/// pixels), the mirror of [`encode_with_tail`] on the receiving side.
pub trait ByteTail {
    /// The last field.
    fn tail_mut(&mut self) -> &mut Vec<u8>;
}

/// [`decode_payload`] for a [`ByteTail`] message: the tail is copied once,
/// straight from the payload's fragments, instead of being joined first and
/// copied again. Same result, same errors.
pub fn decode_payload_tail<T: DeserializeOwned + ByteTail>(
    payload: &zenoh::bytes::ZBytes,
) -> Result<T, DecodeError> {
    decode_payload_tail_into(payload, Vec::new())
}

/// [`decode_payload_tail`] copying the tail into `tail`, whose bytes are
/// dropped and whose capacity is reused: a receiver recycling its buffers
/// (`crate::pool::BufferPool`) decodes big observations without allocating.
pub fn decode_payload_tail_into<T: DeserializeOwned + ByteTail>(
    payload: &zenoh::bytes::ZBytes,
    mut tail: Vec<u8>,
) -> Result<T, DecodeError> {
    let Some((mut msg, tail_at)) = decode_open_tail::<T>(payload) else {
        return decode_payload(payload);
    };
    tail.clear();
    tail.reserve_exact(payload.len() - tail_at);
    for_each_tail_slice(payload, tail_at, |bytes| tail.extend_from_slice(bytes));
    *msg.tail_mut() = tail;
    Ok(msg)
}

/// [`decode_payload_tail`] copying the tail into `out`, which it must fill
/// exactly; the message's own tail is left empty. A vector env writes each
/// env's observation straight into its slot of one batch this way.
pub fn decode_payload_tail_to<T: DeserializeOwned + ByteTail>(
    payload: &zenoh::bytes::ZBytes,
    out: &mut [u8],
) -> Result<T, DecodeError> {
    let unfitting = |len: usize| {
        DecodeError::Invalid(format!(
            "a byte sequence of {len} bytes where {} were expected",
            out.len()
        ))
    };
    let Some((msg, tail_at)) = decode_open_tail::<T>(payload) else {
        let mut msg: T = decode_payload(payload)?;
        let tail = std::mem::take(msg.tail_mut());
        if tail.len() != out.len() {
            return Err(unfitting(tail.len()));
        }
        out.copy_from_slice(&tail);
        return Ok(msg);
    };
    if payload.len() - tail_at != out.len() {
        return Err(unfitting(payload.len() - tail_at));
    }
    let mut at = 0;
    for_each_tail_slice(payload, tail_at, |bytes| {
        out[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    });
    Ok(msg)
}

/// The message read up to its tail (left empty) and the tail's offset in
/// the payload, when the tail is the message's last field and nothing but
/// its bytes follows; `None` for anything else (the general path decides).
fn decode_open_tail<T: DeserializeOwned + ByteTail>(
    payload: &zenoh::bytes::ZBytes,
) -> Option<(T, usize)> {
    let first = payload.slices().next()?;
    let (header, head) = first.split_first_chunk::<4>()?;
    if header[..2] != CDR_LE_HEADER[..2] {
        return None;
    }
    let mut reader = reader::CdrReader::with_open_tail(head, payload.len() - 4);
    let msg = T::deserialize(&mut reader).ok()?;
    Some((msg, reader.tail_at()? + 4))
}

/// Hands `f` the payload's bytes from `tail_at` on, fragment by fragment
/// (`tail_at` lies in the first).
fn for_each_tail_slice(payload: &zenoh::bytes::ZBytes, tail_at: usize, mut f: impl FnMut(&[u8])) {
    let mut slices = payload.slices();
    if let Some(first) = slices.next() {
        f(&first[tail_at..]);
    }
    slices.for_each(f);
}
