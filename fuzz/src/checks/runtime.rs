//! Invariants of the decoders in `offworld-runtime` that read network
//! input: every CDR message (`codec`), camera frames read in place
//! (`CameraFrameView`), e-stops as obeying components read them, rmw_zenoh
//! attachments, and the key space (env ids out of keys, ROS names).
//!
//! Shared, word for word, by the fuzz targets (`fuzz/fuzz_targets/`) and the
//! corpus replay test `runtime/tests/integration/fuzz_corpus.rs` (included there with
//! `#[path]`): a check panics exactly when an invariant breaks.
//!
//! CDR inputs are framed `[kind, cut, cut, payload…]`: `kind` picks the
//! message type (modulo the family's count), the two `cut` bytes split the
//! payload into up to three Zenoh fragments (as a reassembled sample
//! arrives), and `payload` is the CDR bytes.

use std::fmt::Debug;

use offworld_runtime::codec::{self, ByteTail, CDR_LE_HEADER};
use offworld_runtime::estop;
use offworld_runtime::keys::{EnvId, Realm, Topic};
use offworld_runtime::msg::*;
use offworld_runtime::ros2::{KeyStyle, RmwAttachment, RosGraph, RosType, RMW_ATTACHMENT_LEN};
use offworld_runtime::{DecodeError, ErrorCode, WireError};
use serde::{de::DeserializeOwned, Serialize};
use zenoh::bytes::ZBytes;
use zenoh::key_expr::KeyExpr;

/// A framed CDR input.
struct Framed<'a> {
    kind: u8,
    cuts: [u8; 2],
    payload: &'a [u8],
}

impl<'a> Framed<'a> {
    fn parse(data: &'a [u8]) -> Option<Self> {
        let (&[kind, a, b], payload) = data.split_first_chunk::<3>()?;
        Some(Self {
            kind,
            cuts: [a, b],
            payload,
        })
    }

    /// The payload as Zenoh delivers a fragmented sample: up to three slices.
    fn fragmented(&self) -> ZBytes {
        let len = self.payload.len();
        let mut at = self.cuts.map(|c| usize::from(c) * len / 255);
        at.sort_unstable();
        let mut writer = ZBytes::writer();
        for part in [
            &self.payload[..at[0]],
            &self.payload[at[0]..at[1]],
            &self.payload[at[1]..],
        ] {
            if !part.is_empty() {
                writer.append(ZBytes::from(part.to_vec()));
            }
        }
        writer.finish()
    }
}

/// Frames `msg` as a seed of kind `kind`.
fn seed<T: Serialize>(kind: u8, msg: &T) -> Vec<u8> {
    let mut out = vec![kind, 85, 170];
    out.extend(codec::encode(msg).expect("seed messages encode"));
    out
}

/// The encoding of a message that decoded: it must always encode.
fn canonical<T: Serialize + Debug>(name: &str, msg: &T) -> Vec<u8> {
    codec::encode(msg)
        .unwrap_or_else(|e| panic!("{name}: a decoded message does not encode ({e}): {msg:?}"))
}

/// Two decode results are the same: equal errors, or values with equal
/// encodings (compared as bytes, so a NaN equals itself).
fn same<T: Serialize + Debug>(
    name: &str,
    a: &Result<T, DecodeError>,
    b: &Result<T, DecodeError>,
) -> bool {
    match (a, b) {
        (Ok(x), Ok(y)) => canonical(name, x) == canonical(name, y),
        (Err(x), Err(y)) => x == y,
        _ => false,
    }
}

/// What every CDR decoder guarantees, for messages of type `T`:
///
/// - fragmentation changes nothing (`decode_payload` of the fragments is
///   `decode` of the joined bytes, and `contiguous` joins them exactly);
/// - a decoded message encodes, its encoding decodes, and re-encoding that
///   gives the same bytes (the canonical form is a fixed point);
/// - the canonical form with its last byte cut off is rejected;
/// - up to 3 trailing zero bytes are padding, a 4th is `TrailingBytes(4)`.
///
/// Returns the decoded message, if any.
fn message<T: Serialize + DeserializeOwned + Debug>(name: &str, input: &Framed) -> Option<T> {
    let decoded = codec::decode::<T>(input.payload);
    let payload = input.fragmented();
    assert_eq!(
        codec::contiguous(&payload).to_bytes().as_ref(),
        input.payload,
        "{name}: joining fragments changed the bytes"
    );
    let via_payload = codec::decode_payload::<T>(&payload);
    assert!(
        same(name, &decoded, &via_payload),
        "{name}: decode {decoded:?} but decode_payload of the fragments {via_payload:?}"
    );
    let msg = decoded.ok()?;
    let bytes = canonical(name, &msg);
    assert_eq!(bytes[..4], CDR_LE_HEADER, "{name}: encoded header");
    let again = codec::decode::<T>(&bytes)
        .unwrap_or_else(|e| panic!("{name}: its own encoding does not decode ({e}): {msg:?}"));
    assert_eq!(
        canonical(name, &again),
        bytes,
        "{name}: re-encoding a decoded message changed its bytes"
    );
    assert!(
        codec::decode::<T>(&bytes[..bytes.len() - 1]).is_err(),
        "{name}: a truncated message decoded: {msg:?}"
    );
    let mut padded = bytes.clone();
    padded.extend([0; 3]);
    assert!(
        same(name, &Ok(again), &codec::decode::<T>(&padded)),
        "{name}: 3 bytes of trailing padding were not ignored"
    );
    padded.push(0);
    assert_eq!(
        codec::decode::<T>(&padded).err(),
        Some(DecodeError::TrailingBytes(4)),
        "{name}: 4 trailing bytes"
    );
    Some(msg)
}

/// A reply whose pixels are its last field: the fragment-aware decoder
/// gives the same result as the plain one, and the zero-copy encoder
/// (`encode_with_tail`) the same bytes as the plain encoder.
fn byte_tail<T>(name: &str, input: &Framed)
where
    T: Serialize + DeserializeOwned + ByteTail + Clone + Debug,
{
    let whole = codec::decode::<T>(input.payload);
    let tail = codec::decode_payload_tail::<T>(&input.fragmented());
    assert!(
        same(name, &whole, &tail),
        "{name}: decode {whole:?} but decode_payload_tail {tail:?}"
    );
    // In one piece, into a recycled buffer still holding older bytes.
    let one_piece = ZBytes::from(input.payload.to_vec());
    let recycled = codec::decode_payload_tail_into::<T>(&one_piece, vec![0xEE; 16]);
    assert!(
        same(name, &whole, &recycled),
        "{name}: decode {whole:?} but decode_payload_tail_into {recycled:?}"
    );
    // Into a slot of the tail's size: the message without its tail, the
    // tail in the slot; whatever the plain decode refuses, refused alike.
    let mut head = whole.clone();
    let pixels = head.as_mut().ok().map(|m| std::mem::take(m.tail_mut()));
    let mut slot = vec![0xEE; pixels.as_ref().map_or(0, Vec::len)];
    for payload in [&one_piece, &input.fragmented()] {
        let into_slot = codec::decode_payload_tail_to::<T>(payload, &mut slot);
        assert!(
            same(name, &head, &into_slot),
            "{name}: decode {head:?} but decode_payload_tail_to {into_slot:?}"
        );
        if let Some(pixels) = &pixels {
            assert_eq!(&slot, pixels, "{name}: the slot holds the tail");
        }
    }
    if let Some(msg) = message::<T>(name, input) {
        let mut head = msg.clone();
        let pixels = std::mem::take(head.tail_mut());
        let encoded = codec::encode_with_tail(&head, pixels)
            .unwrap_or_else(|e| panic!("{name}: encode_with_tail failed ({e})"));
        assert_eq!(
            encoded.to_vec(),
            canonical(name, &msg),
            "{name}: encode_with_tail and encode differ"
        );
    }
}

/// A valid image's geometry really fits its data.
fn image(name: &str, img: &Image) {
    let result = img.validate();
    assert_eq!(
        img.view().validate(),
        result,
        "{name}: view validates apart"
    );
    if let Ok(encoding) = result {
        assert_eq!(encoding.as_str(), img.encoding, "{name}: encoding");
        assert_eq!(img.is_bigendian, 0, "{name}: big-endian accepted");
        let row = u128::from(img.width) * u128::from(encoding.bytes_per_pixel());
        assert!(u128::from(img.step) >= row, "{name}: step below a row");
        assert_eq!(
            u128::from(img.step) * u128::from(img.height),
            img.data.len() as u128,
            "{name}: step x height is not the data length"
        );
    }
}

/// An e-stop state as merged on start: merging with itself changes
/// nothing, and motion is refused exactly when a latch is engaged.
fn estop_state(name: &str, state: &EStopState) {
    let mut merged = state.clone();
    assert!(!merged.merge(state), "{name}: merging with itself changed");
    assert_eq!(&merged, state, "{name}: merging with itself changed it");
    assert_eq!(
        state.refusal().is_some(),
        state.engaged(),
        "{name}: refusal disagrees with engaged"
    );
}

/// Number of message types of [`cdr_gym`].
pub const GYM_KINDS: u8 = 19;

/// The gym protocol: requests the controller decodes from clients, the
/// replies and publications clients decode, and the typed error.
pub fn cdr_gym(data: &[u8]) {
    let Some(input) = Framed::parse(data) else {
        return;
    };
    match input.kind % GYM_KINDS {
        0 => {
            message::<OpenRequest>("OpenRequest", &input);
        }
        1 => {
            message::<OpenReply>("OpenReply", &input);
        }
        2 => {
            message::<ResetRequest>("ResetRequest", &input);
        }
        3 => byte_tail::<ResetReply>("ResetReply", &input),
        4 => {
            message::<StepRequest>("StepRequest", &input);
        }
        5 => byte_tail::<StepReply>("StepReply", &input),
        6 => {
            message::<CloseRequest>("CloseRequest", &input);
        }
        7 => {
            message::<CloseReply>("CloseReply", &input);
        }
        8 => {
            message::<EnvSpec>("EnvSpec", &input);
        }
        9 => {
            if let Some(status) = message::<EnvStatus>("EnvStatus", &input) {
                estop_state("EnvStatus", &status.estop);
            }
        }
        10 => {
            message::<AdminRequest>("AdminRequest", &input);
        }
        11 => {
            message::<Leaderboard>("Leaderboard", &input);
        }
        12 => {
            message::<BookingRequest>("BookingRequest", &input);
        }
        13 => {
            message::<Bookings>("Bookings", &input);
        }
        14 => {
            message::<EpisodeEvent>("EpisodeEvent", &input);
        }
        15 => {
            message::<ClientTag>("ClientTag", &input);
        }
        16 => {
            message::<ExperimentsRequest>("ExperimentsRequest", &input);
        }
        17 => {
            message::<Experiments>("Experiments", &input);
        }
        _ => {
            if let Some(error) = message::<WireError>("WireError", &input) {
                assert!(ErrorCode::ALL.contains(&error.code), "unknown code decoded");
                let text = error.to_string();
                assert!(text.contains(&error.message), "WireError display");
            }
        }
    }
}

/// Number of message types of [`cdr_robot`].
pub const ROBOT_KINDS: u8 = 11;

/// Controller ↔ robot messages (commands, faults, goto, heartbeats,
/// e-stops and their acknowledgements, tracking status, the `SeqTag`
/// attachment) and rmw_zenoh's 33-byte attachment.
pub fn cdr_robot(data: &[u8]) {
    let Some(input) = Framed::parse(data) else {
        return;
    };
    match input.kind % ROBOT_KINDS {
        0 => {
            message::<MotionCommand>("MotionCommand", &input);
        }
        1 => {
            message::<MotionFault>("MotionFault", &input);
        }
        2 => {
            message::<GotoRequest>("GotoRequest", &input);
        }
        3 => {
            message::<GotoReply>("GotoReply", &input);
        }
        4 => {
            message::<Heartbeat>("Heartbeat", &input);
        }
        5 => {
            // What obeying components act on: the decoded e-stop, or an
            // engage when it does not decode (fail safe).
            let decoded = message::<EStop>("EStop", &input);
            let obeyed = estop::decode(&input.fragmented());
            match decoded {
                Some(stop) => assert_eq!(obeyed, stop, "estop::decode"),
                None => assert!(
                    obeyed.engaged && obeyed.reason.starts_with("malformed e-stop"),
                    "a malformed e-stop did not engage: {obeyed:?}"
                ),
            }
        }
        6 => {
            if let Some(state) = message::<EStopState>("EStopState", &input) {
                estop_state("EStopState", &state);
            }
        }
        7 => {
            if let Some(ack) = message::<EStopAck>("EStopAck", &input) {
                estop_state("EStopAck", &ack.state);
            }
        }
        8 => {
            message::<TrackingStatus>("TrackingStatus", &input);
        }
        9 => {
            message::<SeqTag>("SeqTag", &input);
        }
        _ => {
            let parsed = RmwAttachment::from_bytes(input.payload);
            assert_eq!(
                parsed.is_ok(),
                input.payload.len() == RMW_ATTACHMENT_LEN && input.payload[16] == 16,
                "rmw_zenoh attachment acceptance"
            );
            if let Ok(attachment) = parsed {
                assert_eq!(
                    attachment.to_bytes(),
                    input.payload,
                    "attachment round trip"
                );
            }
        }
    }
}

/// Number of message types of [`cdr_ros`].
pub const ROS_KINDS: u8 = 4;

/// The ROS 2 types read from a robot: images (also read in place), wheel
/// odometry, poses and velocity commands.
pub fn cdr_ros(data: &[u8]) {
    let Some(input) = Framed::parse(data) else {
        return;
    };
    match input.kind % ROS_KINDS {
        0 => {
            let view = codec::decode_borrowed::<ImageView>(input.payload);
            let owned = message::<Image>("Image", &input);
            match (&owned, &view) {
                (Some(img), Ok(view)) => {
                    assert_eq!(view, &img.view(), "Image: view and owned differ");
                    image("Image", img);
                }
                (None, Err(_)) => {}
                _ => panic!("Image: owned {owned:?} but view {view:?}"),
            }
        }
        1 => {
            message::<Odometry>("Odometry", &input);
        }
        2 => {
            message::<PoseStamped>("PoseStamped", &input);
        }
        _ => {
            message::<Twist>("Twist", &input);
        }
    }
}

/// Camera frames (`obs`), as the controller reads them in place
/// (`CameraFrameView`) and as monitors decode them (`CameraFrame`): both
/// accept the same payloads, read the same values, encode the same bytes.
pub fn camera_frame(data: &[u8]) {
    let Some(input) = Framed::parse(data) else {
        return;
    };
    let view = codec::decode_borrowed::<CameraFrameView>(input.payload);
    let owned = message::<CameraFrame>("CameraFrame", &input);
    match (&owned, &view) {
        (Some(frame), Ok(view)) => {
            assert_eq!(view, &frame.view(), "CameraFrame: view and owned differ");
            assert_eq!(
                codec::encode(view).ok(),
                codec::encode(frame).ok(),
                "CameraFrame: view and owned encode apart"
            );
            image("CameraFrame.color", &frame.color);
            image("CameraFrame.depth", &frame.depth);
        }
        (None, Err(_)) => {}
        _ => panic!("CameraFrame: owned {owned:?} but view {view:?}"),
    }
}

/// The key space: env ids parsed out of received keys and from
/// configuration, and ROS 2 names and keys of the robot's graph.
///
/// Input: `[style, text…]`; `text` is UTF-8, split at its first newline
/// into a namespace and a topic for the ROS checks.
pub fn keys(data: &[u8]) {
    let Some((&style, text)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(text) else {
        return;
    };
    if let Ok(env) = EnvId::from_key(text) {
        let prefix = env.prefix();
        assert!(
            text == prefix || text.starts_with(&format!("{prefix}/")),
            "{text:?} parsed as {env} outside its prefix"
        );
        let key = env.key(Topic::Obs);
        assert!(
            KeyExpr::try_from(key.as_str()).is_ok(),
            "{key:?} is no key expression"
        );
        assert_eq!(EnvId::from_key(&key).ok(), Some(env.clone()));
        assert_eq!(env.to_string().parse::<EnvId>().ok(), Some(env.clone()));
    }
    if let Ok(env) = text.parse::<EnvId>() {
        assert_eq!(env.to_string(), text, "env id round trip");
        assert_eq!(
            env.realm().as_str().parse::<Realm>().ok(),
            Some(env.realm())
        );
        assert_eq!(EnvId::new(env.realm(), env.name()).ok(), Some(env.clone()));
    }
    let (namespace, topic) = text.split_once('\n').unwrap_or((text, "cmd_vel"));
    let key_style = if style % 2 == 0 {
        KeyStyle::RmwZenoh {
            domain_id: u32::from(style / 2),
        }
    } else {
        KeyStyle::Bridge {
            prefix: (style % 4 == 3).then(|| topic.to_owned()),
        }
    };
    let Ok(graph) = RosGraph::new(key_style, namespace) else {
        return;
    };
    let Ok(qualified) = graph.qualify(topic) else {
        assert!(
            graph.publication_key(topic, RosType::Twist).is_err(),
            "a key for an invalid topic {topic:?}"
        );
        return;
    };
    assert!(
        !qualified.is_empty() && !qualified.starts_with('/') && !qualified.contains("//"),
        "qualified {topic:?} as {qualified:?}"
    );
    // The qualified name is absolute: qualifying it again changes nothing.
    assert_eq!(
        graph.qualify(&format!("/{qualified}")).ok().as_deref(),
        Some(qualified.as_str()),
        "qualifying is not idempotent"
    );
    for ty in [
        RosType::Twist,
        RosType::Image,
        RosType::Odometry,
        RosType::PoseStamped,
    ] {
        let publication = graph.publication_key(topic, ty);
        let subscription = graph.subscription_key(topic, ty);
        let (Ok(publication), Ok(subscription)) = (publication, subscription) else {
            panic!("{topic:?} qualifies but has no keys");
        };
        for key in [publication, subscription] {
            assert!(
                KeyExpr::try_from(key.as_str()).is_ok(),
                "{graph}: {topic:?} gives {key:?}, not a Zenoh key expression"
            );
        }
    }
}

fn header(frame: &str) -> Header {
    Header::new(
        Time {
            sec: 1_700_000_123,
            nanosec: 456_789,
        },
        frame,
    )
}

fn obs_array() -> ObsArray {
    ObsArray {
        height: 2,
        width: 3,
        channels: 1,
        dtype: DType::U8,
        data: vec![0, 10, 20, 30, 40, 255],
    }
}

fn estop_sample() -> EStopState {
    EStopState {
        site: LatchState {
            engaged: true,
            reason: "fire alarm".into(),
            changed: header("").stamp,
        },
        env: LatchState::default(),
    }
}

fn spec() -> EnvSpec {
    EnvSpec {
        env_id: "sim/monolith-0".into(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        action_space: ActionSpace::Discrete {
            n: 2,
            names: vec!["LEFT".into(), "FORWARD".into()],
        },
        native_height: 240,
        native_width: 320,
        depth_max_m: 5.0,
        max_episode_steps: 100,
    }
}

fn experiment() -> ExperimentInfo {
    ExperimentInfo {
        id: 3,
        name: "dqn-depth".into(),
        episodes: 12,
        steps: 840,
    }
}

/// Seeds of [`cdr_gym`]: one message of every type, plus variants.
pub fn cdr_gym_seeds() -> Vec<Vec<u8>> {
    let info = StepInfo {
        episode_id: 4,
        step: 17,
        is_success: true,
        end_reason: "success".into(),
        pose_shared: true,
        x: 0.25,
        y: -0.5,
        yaw: 1.5,
        distance_to_goal: 0.125,
    };
    vec![
        seed(
            0,
            &OpenRequest {
                token: "secret-token".into(),
                client_id: "client-1".into(),
                experiment_name: "dqn-depth".into(),
                resume_experiment: true,
                learning_type: LearningType::SimToReal,
                algorithm_mode: AlgorithmMode::Test,
                obs: ObsOptions {
                    channels: Channels::Rgbd,
                    height: 84,
                    width: 84,
                    depth_format: DepthFormat::Meters,
                },
            },
        ),
        seed(0, &OpenRequest::anonymous(ObsOptions::default())),
        seed(
            1,
            &OpenReply {
                session_id: "s-1".into(),
                lease_until_unix_ms: 1_700_000_999_000,
                spec: spec(),
                experiment: experiment(),
            },
        ),
        seed(
            2,
            &ResetRequest {
                session_id: "s-1".into(),
                seed: Seed::Fixed(1234),
            },
        ),
        seed(
            2,
            &ResetRequest {
                session_id: String::new(),
                seed: Seed::Continue,
            },
        ),
        seed(
            3,
            &ResetReply {
                info: info.clone(),
                observation: obs_array(),
            },
        ),
        seed(
            4,
            &StepRequest {
                session_id: "s-1".into(),
                seq: 9,
                action: Action::Continuous(vec![0.5, -1.0]),
            },
        ),
        seed(
            4,
            &StepRequest {
                session_id: "s-1".into(),
                seq: 10,
                action: Action::Discrete(2),
            },
        ),
        seed(
            5,
            &StepReply {
                seq: 9,
                reward: 1.0,
                terminated: true,
                truncated: false,
                info,
                observation: obs_array(),
            },
        ),
        seed(
            6,
            &CloseRequest {
                session_id: "s-1".into(),
            },
        ),
        seed(
            7,
            &CloseReply {
                experiment: experiment(),
            },
        ),
        seed(8, &spec()),
        seed(
            8,
            &EnvSpec {
                action_space: ActionSpace::Box {
                    low: vec![-1.0, -1.0],
                    high: vec![1.0, 1.0],
                },
                ..spec()
            },
        ),
        seed(
            9,
            &EnvStatus {
                env_id: "real/enclosure-a".into(),
                state: EnvState::Leased {
                    until_unix_ms: 1_700_000_999_000,
                    holder: "ada".into(),
                },
                estop: estop_sample(),
                last_reset: ResetAccuracy::default(),
            },
        ),
        seed(
            9,
            &EnvStatus {
                env_id: "sim/monolith-0".into(),
                state: EnvState::Maintenance {
                    message: "wheel swap".into(),
                    by: "ops".into(),
                    back_unix_ms: 1_700_000_999_000,
                },
                estop: EStopState::default(),
                last_reset: ResetAccuracy::default(),
            },
        ),
        seed(
            10,
            &AdminRequest::SetMaintenance {
                token: "op".into(),
                message: "wheel swap".into(),
                back_unix_ms: 0,
            },
        ),
        seed(10, &AdminRequest::ClearMaintenance { token: "op".into() }),
        seed(
            10,
            &AdminRequest::RevokeLease {
                token: "op".into(),
                reason: "demo".into(),
            },
        ),
        seed(
            10,
            &AdminRequest::Identify {
                token: "ada".into(),
            },
        ),
        seed(
            11,
            &Leaderboard {
                env_id: "sim/monolith-0".into(),
                entries: vec![LeaderboardEntry {
                    experiment: "dqn".into(),
                    user: "ada".into(),
                    learning_type: "end2end".into(),
                    episodes: 10,
                    success_rate: 0.5,
                    mean_return: 0.25,
                }],
            },
        ),
        seed(
            12,
            &BookingRequest::Make {
                token: "t".into(),
                start_unix_ms: 1_000,
                end_unix_ms: 2_000,
            },
        ),
        seed(12, &BookingRequest::List { from_unix_ms: 5 }),
        seed(
            12,
            &BookingRequest::Cancel {
                token: "t".into(),
                id: 3,
            },
        ),
        seed(
            13,
            &Bookings {
                bookings: vec![Booking {
                    id: 1,
                    env_id: "real/enclosure-a".into(),
                    user: "ada".into(),
                    start_unix_ms: 1_000,
                    end_unix_ms: 2_000,
                }],
            },
        ),
        seed(
            14,
            &EpisodeEvent {
                experiment: "dqn-depth".into(),
                episode_id: 4,
                step: 17,
                reward: 1.0,
                episode_return: 1.0,
                terminated: true,
                truncated: false,
                success: true,
                end_reason: "reached monolith".into(),
                experiment_id: 3,
                command_seq: 35,
            },
        ),
        seed(
            15,
            &ClientTag {
                client_id: "3fa9c0d1e2b4a567".into(),
            },
        ),
        seed(16, &ExperimentsRequest::List { token: "t".into() }),
        seed(
            16,
            &ExperimentsRequest::Show {
                token: "t".into(),
                experiment_id: 3,
                from_episode: 1000,
            },
        ),
        seed(
            17,
            &Experiments {
                experiments: vec![ExperimentRecord {
                    id: 3,
                    user: "ada".into(),
                    env_id: "sim/monolith-0".into(),
                    task: "MonolithDiscrete".into(),
                    name: "dqn".into(),
                    learning_type: "end2end".into(),
                    algorithm_mode: "train".into(),
                    episodes: 2,
                    steps: 40,
                    created_unix_ms: 1_000,
                    updated_unix_ms: 2_000,
                }],
                episodes: vec![EpisodeRecordEntry {
                    index: 0,
                    seeded: true,
                    seed: 7,
                    steps: 20,
                    episode_return: 1.0,
                    success: true,
                    end_reason: "success".into(),
                    started_unix_ms: 1_000,
                    ended_unix_ms: 1_500,
                    reset: ResetAccuracy::measure(
                        Pose2D {
                            x: -1.0,
                            y: 0.5,
                            yaw: 0.0,
                        },
                        Pose2D {
                            x: -1.0,
                            y: 0.5,
                            yaw: 0.0,
                        },
                        0.001,
                        1_000,
                    ),
                    recordings: vec![RecordingFile {
                        path: "sim/monolith-0/exp-000003/ep-000000.mcap".into(),
                        bytes: 123_456,
                        complete: true,
                    }],
                }],
                more: false,
            },
        ),
        seed(18, &WireError::busy("leased until 12:00 UTC")),
    ]
}

/// Seeds of [`cdr_robot`].
pub fn cdr_robot_seeds() -> Vec<Vec<u8>> {
    let attachment = RmwAttachment {
        sequence: 7,
        source_timestamp_ns: 1_700_000_000_000_000_000,
        gid: [3; 16],
    };
    let mut rmw = vec![10, 85, 170];
    rmw.extend(attachment.to_bytes());
    vec![
        seed(
            0,
            &MotionCommand {
                seq: 42,
                linear_x: 0.07,
                angular_z: 1.25,
                duration_s: 1.2,
            },
        ),
        seed(
            1,
            &MotionFault {
                seq: MotionFault::ANY_COMMAND,
                reason: "no camera frames".into(),
            },
        ),
        seed(
            2,
            &GotoRequest {
                seq: 7,
                target: Pose2D {
                    x: 1.0,
                    y: -0.5,
                    yaw: 3.0,
                },
                timeout_s: 30.0,
            },
        ),
        seed(
            3,
            &GotoReply {
                seq: 7,
                achieved: Pose2D {
                    x: 0.98,
                    y: -0.51,
                    yaw: 2.95,
                },
                elapsed_s: 12.5,
            },
        ),
        seed(
            4,
            &Heartbeat {
                stamp: header("").stamp,
                counter: 99,
            },
        ),
        seed(
            5,
            &EStop {
                engaged: true,
                reason: "operator".into(),
                press_id: 0x1234_5678_9abc,
            },
        ),
        seed(5, &EStop::new(false, "")),
        seed(6, &estop_sample()),
        seed(
            7,
            &EStopAck {
                press_id: 7,
                component: "robot_agent".into(),
                env: "real/enclosure-a".into(),
                state: estop_sample(),
            },
        ),
        seed(
            8,
            &TrackingStatus {
                tracking: false,
                last_pose_age_s: 0.75,
                reason: "no poses".into(),
            },
        ),
        seed(9, &SeqTag { seq: 5 }),
        rmw,
    ]
}

fn image_rgb() -> Image {
    Image::packed(
        header("camera_color_optical_frame"),
        3,
        2,
        PixelEncoding::Rgb8,
        (0u8..18).collect(),
    )
}

fn image_depth() -> Image {
    Image::packed(
        header("camera_depth_optical_frame"),
        3,
        2,
        PixelEncoding::Depth32FC1,
        [0.5f32, 1.25, f32::NAN, 4.0, 0.0, -1.0]
            .iter()
            .flat_map(|d| d.to_le_bytes())
            .collect(),
    )
}

fn image_depth_mm() -> Image {
    Image::packed(
        header("camera_depth_optical_frame"),
        3,
        2,
        PixelEncoding::Depth16UC1,
        [1500u16, 0, 65535, 1, 2, 3]
            .iter()
            .flat_map(|d| d.to_le_bytes())
            .collect(),
    )
}

/// Seeds of [`cdr_ros`].
pub fn cdr_ros_seeds() -> Vec<Vec<u8>> {
    let mut padded = image_rgb();
    padded.step = 10;
    padded.data = vec![7; 20];
    padded.encoding = "bgr8".into();
    let pose = Pose {
        position: Point {
            x: 0.0109,
            y: -0.2034,
            z: 0.2838,
        },
        orientation: Quaternion::from_yaw(0.7),
    };
    let twist = Twist::planar(0.25, -1.5);
    vec![
        seed(0, &image_rgb()),
        seed(0, &image_depth()),
        seed(0, &image_depth_mm()),
        seed(0, &padded),
        seed(
            1,
            &Odometry {
                header: header("odom"),
                child_frame_id: "base_link".into(),
                pose: PoseWithCovariance {
                    pose,
                    covariance: [0.5; 36],
                },
                twist: TwistWithCovariance {
                    twist,
                    covariance: [-0.5; 36],
                },
            },
        ),
        seed(
            2,
            &PoseStamped {
                header: header("world"),
                pose,
            },
        ),
        seed(3, &twist),
    ]
}

/// Seeds of [`camera_frame`].
pub fn camera_frame_seeds() -> Vec<Vec<u8>> {
    let mut bgr = image_rgb();
    bgr.encoding = "bgr8".into();
    vec![
        seed(
            0,
            &CameraFrame {
                seq: 42,
                color: image_rgb(),
                depth: image_depth(),
            },
        ),
        seed(
            0,
            &CameraFrame {
                seq: 43,
                color: bgr,
                depth: image_depth_mm(),
            },
        ),
        seed(0, &CameraFrame::default()),
    ]
}

/// Seeds of [`keys`].
pub fn keys_seeds() -> Vec<Vec<u8>> {
    [
        (0u8, "offworld/@v1/sim/monolith-0/obs"),
        (1, "offworld/@v1/real/enclosure-a/alive/client/abc"),
        (2, "real/enclosure-a"),
        (3, "/rosbot\ncamera/color/image_raw"),
        (4, "\n/odom"),
        (7, "robot_1\ncmd_vel"),
    ]
    .iter()
    .map(|(style, text)| {
        let mut out = vec![*style];
        out.extend(text.as_bytes());
        out
    })
    .collect()
}
