//! Typed put/get/reply over Zenoh: CDR payloads labelled
//! `application/cdr`, error replies as [`WireError`], timeouts as errors.

use std::time::{Duration, Instant};

use serde::{de::DeserializeOwned, Serialize};
use zenoh::bytes::{Encoding, ZBytes};
use zenoh::pubsub::{Publisher, PublisherBuilder};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::{Query, QueryTarget};
use zenoh::Session;
use zenoh::Wait;

use crate::codec;
use crate::error::{DecodeError, EncodeError, WireError};
use crate::msg::{ClientTag, SeqTag};
use crate::seal::Sealer;

/// Why a request got no usable answer.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    /// The server answered with a typed error.
    #[error(transparent)]
    Remote(#[from] WireError),
    /// Nobody serves this key (no queryable matched).
    #[error("nothing answers on `{0}`")]
    NoResponder(String),
    /// A responder exists but did not answer in time.
    #[error("no reply on `{key}` within {timeout:?}")]
    Timeout {
        /// The key queried.
        key: String,
        /// The deadline used.
        timeout: Duration,
    },
    /// The reply (or error reply) was not a valid message.
    #[error("undecodable reply: {0}")]
    Decode(#[from] DecodeError),
    /// The request could not be encoded.
    #[error(transparent)]
    Encode(#[from] EncodeError),
    /// Zenoh refused the operation.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

impl RequestError {
    /// The error as a client sees it: every failure becomes a typed code.
    pub fn into_wire(self) -> WireError {
        match self {
            RequestError::Remote(e) => e,
            RequestError::NoResponder(key) => {
                WireError::not_found(format!("no env is serving `{key}`"))
            }
            e @ RequestError::Timeout { .. } => WireError::timeout(e.to_string()),
            e => WireError::internal(e.to_string()),
        }
    }
}

/// Puts one message on `key` (labelled as CDR) with [`Delivery::Latest`].
pub async fn put<T: Serialize>(session: &Session, key: &str, msg: &T) -> Result<(), RequestError> {
    put_at(session, key, msg, Priority::Data, None).await
}

/// The Zenoh priority of what keeps a robot safe and moving: commands,
/// controller heartbeats and e-stops. Zenoh queues each priority apart on
/// every link and sends the higher first, so a camera stream filling a
/// link (~11 MB/s at 30 Hz) can never hold back the heartbeat whose
/// absence brakes the robot.
pub const CONTROL_PRIORITY: Priority = Priority::RealTime;

/// Puts a control message (a heartbeat) on `key` at [`CONTROL_PRIORITY`],
/// with [`Delivery::Latest`]: the next beat supersedes it.
pub async fn put_control<T: Serialize>(
    session: &Session,
    key: &str,
    msg: &T,
) -> Result<(), RequestError> {
    put_at(session, key, msg, CONTROL_PRIORITY, None).await
}

async fn put_at<T: Serialize>(
    session: &Session,
    key: &str,
    msg: &T,
    priority: Priority,
    sealer: Option<&Sealer>,
) -> Result<(), RequestError> {
    let bytes = codec::encode(msg)?;
    let seal = sealer.map(|s| s.seal(key, &bytes, &[]));
    session
        .put(key, bytes)
        .encoding(Encoding::APPLICATION_CDR)
        .priority(priority)
        .attachment(seal.map(ZBytes::from))
        .await
        .map_err(|e| RequestError::Zenoh(e.to_string()))
}

/// What a congested link does with a publication.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// A stream whose next sample supersedes this one (heartbeats, status,
    /// tracker poses, camera topics): dropped when the link stays congested
    /// (after [`crate::session::PATIENT_DROP_US`]; a fragmented message
    /// after Zenoh's 50 ms), so a slow reader never stalls the publisher.
    Latest,
    /// A message a step cannot do without (a command, the frame and pose
    /// answering it): the publisher waits for room instead. A frame is
    /// several fragments and one stall of the reader over 50 ms would
    /// otherwise lose it, failing the step after its whole answer timeout.
    Every,
}

impl Delivery {
    /// Zenoh's congestion control for this delivery.
    pub fn congestion_control(self) -> CongestionControl {
        match self {
            Delivery::Latest => CongestionControl::Drop,
            Delivery::Every => CongestionControl::Block,
        }
    }
}

/// A publisher of CDR messages on `key` for keys put on every step (the key
/// is resolved once instead of at each put); `.await` or `.wait()` it.
pub fn publisher(
    session: &Session,
    key: String,
    delivery: Delivery,
) -> PublisherBuilder<'_, 'static> {
    session
        .declare_publisher(key)
        .encoding(Encoding::APPLICATION_CDR)
        .congestion_control(delivery.congestion_control())
}

/// Publishes one message through a [`publisher`]. Zenoh's put is synchronous
/// whether awaited or not (an [`Delivery::Every`] put holds the caller while
/// it waits for room), so this one is plainly blocking.
pub fn publish<T: Serialize>(publisher: &Publisher<'_>, msg: &T) -> Result<(), RequestError> {
    publisher
        .put(codec::encode(msg)?)
        .wait()
        .map_err(|e| RequestError::Zenoh(e.to_string()))
}

/// [`put`], sealed by `sealer` when there is one ([`crate::seal`]).
pub async fn put_sealed<T: Serialize>(
    session: &Session,
    key: &str,
    msg: &T,
    sealer: Option<&Sealer>,
) -> Result<(), RequestError> {
    put_at(session, key, msg, Priority::Data, sealer).await
}

/// [`put_control`], sealed by `sealer` when there is one.
pub async fn put_control_sealed<T: Serialize>(
    session: &Session,
    key: &str,
    msg: &T,
    sealer: Option<&Sealer>,
) -> Result<(), RequestError> {
    put_at(session, key, msg, CONTROL_PRIORITY, sealer).await
}

/// Publishes one message tagged with the command it answers (a
/// [`SeqTag`] attachment).
pub fn publish_tagged<T: Serialize>(
    publisher: &Publisher<'_>,
    msg: &T,
    tag: SeqTag,
) -> Result<(), RequestError> {
    let bytes = codec::encode(msg)?;
    let attachment = codec::encode(&tag)?;
    publisher
        .put(bytes)
        .attachment(attachment)
        .wait()
        .map_err(|e| RequestError::Zenoh(e.to_string()))
}

/// Sends a request to the queryable on `key` and waits for its first reply.
pub async fn request<Req: Serialize, Rep: DeserializeOwned>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
) -> Result<Rep, RequestError> {
    let payload = codec::encode(req)?;
    request_raw(session, key, payload, timeout).await
}

/// [`request`] saying who asks: `tag` travels as the query's attachment
/// (the controller's per-client quotas are keyed on it).
pub async fn request_as<Req: Serialize, Rep: DeserializeOwned>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
    tag: &ClientTag,
) -> Result<Rep, RequestError> {
    request_decoded_as(session, key, req, timeout, tag, codec::decode_payload).await
}

/// [`request_tail`] saying who asks (see [`request_as`]), its pixels
/// copied into `tail` (see [`codec::decode_payload_tail_into`]; a fresh
/// buffer is `Vec::new()`).
pub async fn request_tail_as<Req: Serialize, Rep: DeserializeOwned + codec::ByteTail>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
    tag: &ClientTag,
    tail: Vec<u8>,
) -> Result<Rep, RequestError> {
    request_decoded_as(session, key, req, timeout, tag, |reply| {
        codec::decode_payload_tail_into(reply, tail)
    })
    .await
}

/// [`request_as`] with the reply read by `decode` (such as
/// [`codec::decode_payload_tail_to`], into a slot of a caller's buffer).
pub async fn request_decoded_as<Req: Serialize, Rep>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
    tag: &ClientTag,
    decode: impl FnOnce(&ZBytes) -> Result<Rep, DecodeError>,
) -> Result<Rep, RequestError> {
    let payload = codec::encode(req)?;
    let tag = codec::encode(tag)?;
    request_decoded(session, key, payload, Some(tag), timeout, decode).await
}

/// [`request`] for a reply whose last field is an observation: its pixels
/// are copied once out of the received fragments ([`codec::decode_payload_tail`]).
pub async fn request_tail<Req: Serialize, Rep: DeserializeOwned + codec::ByteTail>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
) -> Result<Rep, RequestError> {
    let payload = codec::encode(req)?;
    request_decoded(
        session,
        key,
        payload,
        None,
        timeout,
        codec::decode_payload_tail,
    )
    .await
}

/// [`request`], sealed by `sealer` when there is one ([`crate::seal`]).
pub async fn request_sealed<Req: Serialize, Rep: DeserializeOwned>(
    session: &Session,
    key: &str,
    req: &Req,
    timeout: Duration,
    sealer: Option<&Sealer>,
) -> Result<Rep, RequestError> {
    let payload = codec::encode(req)?;
    let seal = sealer.map(|s| s.seal(key, &payload, &[]));
    request_decoded(session, key, payload, seal, timeout, codec::decode_payload).await
}

/// Like [`request`] with an already encoded payload (empty for `spec`).
pub async fn request_raw<Rep: DeserializeOwned>(
    session: &Session,
    key: &str,
    payload: Vec<u8>,
    timeout: Duration,
) -> Result<Rep, RequestError> {
    request_decoded(session, key, payload, None, timeout, codec::decode_payload).await
}

async fn request_decoded<Rep>(
    session: &Session,
    key: &str,
    payload: Vec<u8>,
    attachment: Option<Vec<u8>>,
    timeout: Duration,
    decode: impl FnOnce(&ZBytes) -> Result<Rep, DecodeError>,
) -> Result<Rep, RequestError> {
    let started = Instant::now();
    let replies = session
        .get(key)
        .payload(payload)
        .encoding(Encoding::APPLICATION_CDR)
        .attachment(attachment.map(ZBytes::from))
        .target(QueryTarget::BestMatching)
        .timeout(timeout)
        .await
        .map_err(|e| RequestError::Zenoh(e.to_string()))?;
    match replies.recv_async().await {
        Ok(reply) => match reply.result() {
            Ok(sample) => Ok(decode(sample.payload())?),
            // Our servers label typed errors as CDR; anything else comes
            // from Zenoh itself (its query timeout replies "Timeout").
            Err(err) if err.encoding() == &Encoding::APPLICATION_CDR => {
                Err(RequestError::Remote(codec::decode_payload(err.payload())?))
            }
            Err(err) => {
                let text = String::from_utf8_lossy(&err.payload().to_bytes()).into_owned();
                if text == "Timeout" {
                    Err(RequestError::Timeout {
                        key: key.to_owned(),
                        timeout,
                    })
                } else {
                    Err(RequestError::Zenoh(text))
                }
            }
        },
        // The reply channel closed empty: either nobody matched (immediately)
        // or the deadline passed.
        Err(_) if started.elapsed() >= timeout => Err(RequestError::Timeout {
            key: key.to_owned(),
            timeout,
        }),
        Err(_) => Err(RequestError::NoResponder(key.to_owned())),
    }
}

/// Decodes a query's payload; an absent payload decodes as `T` from no bytes
/// (which fails for every non-unit type).
pub fn decode_query<T: DeserializeOwned>(query: &Query) -> Result<T, WireError> {
    let bytes = query.payload().map(ZBytes::to_bytes).unwrap_or_default();
    codec::decode(&bytes).map_err(|e| WireError::bad_request(format!("undecodable request: {e}")))
}

/// Answers a query with a message or a typed error.
pub async fn reply<T: Serialize>(
    query: &Query,
    result: Result<&T, WireError>,
) -> Result<(), RequestError> {
    reply_now(query, result)
}

/// [`reply`] from a thread that is not async (a Zenoh callback, a
/// simulation thread). Zenoh sends a reply synchronously either way.
pub fn reply_now<T: Serialize>(
    query: &Query,
    result: Result<&T, WireError>,
) -> Result<(), RequestError> {
    let encoded = match result.map(codec::encode) {
        Ok(Ok(bytes)) => Ok(bytes.into()),
        Ok(Err(e)) => Err(WireError::internal(e.to_string())),
        Err(err) => Err(err),
    };
    reply_payload(query, encoded)
}

/// Like [`reply`] with a message already encoded (see
/// [`codec::encode_with_tail`]).
pub async fn reply_encoded<T>(
    query: &Query,
    result: Result<codec::Encoded<T>, WireError>,
) -> Result<(), RequestError> {
    reply_encoded_now(query, result)
}

/// [`reply_encoded`] from a thread that is not async (a Zenoh callback).
pub fn reply_encoded_now<T>(
    query: &Query,
    result: Result<codec::Encoded<T>, WireError>,
) -> Result<(), RequestError> {
    reply_payload(query, result.map(codec::Encoded::into_payload))
}

fn reply_payload(query: &Query, result: Result<ZBytes, WireError>) -> Result<(), RequestError> {
    let outcome = match result {
        Ok(payload) => query
            .reply(query.key_expr().clone(), payload)
            .encoding(Encoding::APPLICATION_CDR)
            .wait(),
        Err(err) => query
            .reply_err(codec::encode(&err)?)
            .encoding(Encoding::APPLICATION_CDR)
            .wait(),
    };
    outcome.map_err(|e| RequestError::Zenoh(e.to_string()))
}

/// Decodes a sample's CDR attachment, if any (without its seal, if sealed).
pub fn decode_attachment<T: DeserializeOwned>(sample: &zenoh::sample::Sample) -> Option<T> {
    sample
        .attachment()
        .and_then(|a| codec::decode(crate::seal::inner(&a.to_bytes())).ok())
}
