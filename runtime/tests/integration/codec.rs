//! Round trips for every message, and a table of corruptions every decoder
//! must reject with a typed error (never a panic, never a huge allocation).

use crate::{common, for_each_sample};

use std::fmt::Debug;

use offworld_runtime::codec::{decode, decode_borrowed, encode, encode_into, CDR_LE_HEADER};
use offworld_runtime::msg::*;
use offworld_runtime::DecodeError;
use serde::{de::DeserializeOwned, Serialize};

fn round_trips<T: Serialize + DeserializeOwned + PartialEq + Debug>(name: &str, msg: T) {
    let bytes = encode(&msg).expect(name);
    assert_eq!(bytes[..4], CDR_LE_HEADER, "{name}: header");
    let back: T = decode(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(back, msg, "{name}");
}

#[test]
fn every_message_round_trips() {
    for_each_sample!(round_trips);
}

#[test]
fn known_sizes_match_the_ros_layouts() {
    // Sizes checked against rosbags in ../shared/reference/ros2-interop.md.
    assert_eq!(encode(&common::twist()).expect("twist").len(), 52);
    assert_eq!(encode(&common::pose_stamped()).expect("pose").len(), 84);
    // header 4 + stamp 8 + frame_id (4 + 26 chars + NUL) + pad 1 + h, w 8
    // + "rgb8" (4 + 5) + is_bigendian 1 + pad 2 + step 4 + data (4 + 18).
    let image = common::image_rgb();
    assert_eq!(image.header.frame_id.len(), 26);
    assert_eq!(
        encode(&image).expect("image").len(),
        4 + 8 + 4 + 27 + 1 + 8 + 4 + 5 + 1 + 2 + 4 + 4 + 18
    );
}

#[test]
fn a_motion_fault_has_its_documented_bytes() {
    let fault = MotionFault {
        seq: 7,
        reason: "no".into(),
    };
    // header, seq u64 LE, reason: u32 length with NUL, bytes, NUL.
    let expected = [
        0x00, 0x01, 0x00, 0x00, 7, 0, 0, 0, 0, 0, 0, 0, 3, 0, 0, 0, b'n', b'o', 0,
    ];
    assert_eq!(encode(&fault).expect("fault"), expected);
}

#[test]
fn an_episode_event_has_its_documented_bytes() {
    // CDR aligns each primitive to its size, counted after the 4-byte
    // header; the offsets are the body's.
    let mut expected: Vec<u8> = Vec::new();
    let mut row = |bytes: &[u8]| expected.extend_from_slice(bytes);
    row(&[0x00, 0x01, 0x00, 0x00]); // header
    row(&[10, 0, 0, 0]); // 0: experiment, its length with the NUL
    row(b"dqn-depth\0"); // 4
    row(&[0, 0]); // 14: pad
    row(&[4, 0, 0, 0, 0, 0, 0, 0]); // 16: episode_id
    row(&[17, 0, 0, 0]); // 24: step
    row(&[0, 0, 0, 0]); // 28: pad
    row(&[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]); // 32: reward 1.0
    row(&[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]); // 40: episode_return 1.0
    row(&[1, 0, 1]); // 48: terminated, truncated, success
    row(&[0]); // 51: pad
    row(&[17, 0, 0, 0]); // 52: end_reason, its length with the NUL
    row(b"reached monolith\0"); // 56
    row(&[0, 0, 0, 0, 0, 0, 0]); // 73: pad
    row(&[3, 0, 0, 0, 0, 0, 0, 0]); // 80: experiment_id
    row(&[35, 0, 0, 0, 0, 0, 0, 0]); // 88: command_seq
    assert_eq!(expected.len(), 4 + 96);
    assert_eq!(encode(&common::episode_event()).expect("event"), expected);
}

#[test]
fn encode_into_reuses_the_buffer() {
    let frame = common::camera_frame();
    let mut buf = Vec::with_capacity(4096);
    let capacity = buf.capacity();
    encode_into(&frame, &mut buf).expect("encode");
    let first = buf.clone();
    encode_into(&frame, &mut buf).expect("encode again");
    assert_eq!(buf, first, "re-encoding into a used buffer must not append");
    assert_eq!(
        buf.capacity(),
        capacity,
        "no reallocation for a fitting frame"
    );
}

#[test]
fn frame_views_read_in_place_and_keep_the_wire_bytes() {
    let frame = common::camera_frame();
    let bytes = encode(&frame).expect("frame");
    let view: CameraFrameView = decode_borrowed(&bytes).expect("view");
    assert_eq!(view, frame.view());
    // The pixels are the payload's own bytes, not a copy.
    let range = bytes.as_ptr_range();
    assert!(range.contains(&view.color.data.as_ptr()));
    assert!(range.contains(&view.depth.data.as_ptr()));
    assert_eq!(encode(&view).expect("view encodes"), bytes);
    assert_eq!(view.color.validate(), frame.color.validate());
    for len in [0, 3, 4, bytes.len() / 2, bytes.len() - 1] {
        assert!(decode_borrowed::<CameraFrameView>(&bytes[..len]).is_err());
    }
}

/// Every strict prefix is truncated; every byte flip either fails or decodes
/// to a message that re-encodes to exactly the flipped bytes.
fn survives_corruption<T: Serialize + DeserializeOwned + PartialEq + Debug>(name: &str, msg: T) {
    let bytes = encode(&msg).expect(name);
    for len in 0..bytes.len() {
        let err = decode::<T>(&bytes[..len]).expect_err(&format!("{name}: prefix {len} decoded"));
        match (len, err) {
            (0..=3, DecodeError::TooShort(n)) => assert_eq!(n, len),
            (4.., DecodeError::Truncated { .. } | DecodeError::Invalid(_)) => {}
            (len, err) => panic!("{name}: prefix {len} gave {err:?}"),
        }
    }
    for i in 0..bytes.len() {
        for flip in [0x01u8, 0x80, 0xff] {
            let mut bad = bytes.clone();
            bad[i] ^= flip;
            match decode::<T>(&bad) {
                Ok(decoded) => {
                    let again = encode(&decoded).expect("re-encode");
                    // Decoding saw exactly the flipped bytes, except those the
                    // format ignores: header options and alignment padding
                    // (which the encoder writes as zeros).
                    let faithful = again.len() == bad.len()
                        && again[..2] == bad[..2]
                        && again[4..]
                            .iter()
                            .zip(&bad[4..])
                            .all(|(a, b)| a == b || *a == 0);
                    assert!(faithful, "{name}: byte {i} ^ {flip:#x} misread");
                }
                Err(DecodeError::BadHeader(h)) => assert!(i < 2, "{name}: {h:?} at {i}"),
                Err(_) => {}
            }
        }
    }
    let mut trailing = bytes.clone();
    trailing.extend_from_slice(&[0, 0, 0, 0]);
    assert_eq!(
        decode::<T>(&trailing),
        Err(DecodeError::TrailingBytes(4)),
        "{name}: trailing"
    );
    let mut garbage = bytes.clone();
    garbage.push(7);
    assert_eq!(
        decode::<T>(&garbage),
        Err(DecodeError::TrailingBytes(1)),
        "{name}: garbage"
    );
    let mut padded = bytes.clone();
    padded.extend_from_slice(&[0, 0, 0]);
    assert_eq!(
        decode::<T>(&padded).as_ref().ok(),
        Some(&msg),
        "{name}: alignment padding"
    );
    let mut big_endian = bytes;
    big_endian[1] = 0x00;
    assert_eq!(
        decode::<T>(&big_endian),
        Err(DecodeError::BadHeader([0, 0, 0, 0])),
        "{name}: big-endian CDR"
    );
}

#[test]
fn every_decoder_rejects_corruption() {
    for_each_sample!(survives_corruption);
}

#[test]
fn hostile_length_prefixes_fail_without_allocating() {
    // A string/byte/sequence length of u32::MAX must be refused from the
    // length alone (the `cdr` crate would allocate 4 GiB first).
    let mut bytes = CDR_LE_HEADER.to_vec();
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        decode::<String>(&bytes),
        Err(DecodeError::Truncated { .. })
    ));
    assert!(matches!(
        decode::<Vec<f64>>(&bytes),
        Err(DecodeError::Truncated { .. })
    ));
    let mut image = encode(&common::image_rgb()).expect("image");
    let data_len_at = image.len() - 18 - 4;
    image[data_len_at..data_len_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        decode::<Image>(&image),
        Err(DecodeError::Truncated { .. })
    ));
}

#[test]
fn invalid_values_are_typed() {
    let mut bytes = encode(&EStop::new(true, "x")).expect("estop");
    bytes[4] = 2; // bool must be 0 or 1
    assert!(matches!(
        decode::<EStop>(&bytes),
        Err(DecodeError::Invalid(_))
    ));
    let mut action = encode(&Action::Discrete(1)).expect("action");
    action[4] = 9; // no such variant
    assert!(matches!(
        decode::<Action>(&action),
        Err(DecodeError::Invalid(_))
    ));
    let mut text = encode(&"ok".to_owned()).expect("string");
    text[8] = 0xff; // not UTF-8
    assert!(matches!(
        decode::<String>(&text),
        Err(DecodeError::Invalid(_))
    ));
    let mut code = encode(&common::wire_error()).expect("error");
    code[4..6].copy_from_slice(&777u16.to_le_bytes()); // unknown error code
    assert!(matches!(
        decode::<offworld_runtime::WireError>(&code),
        Err(DecodeError::Invalid(_))
    ));
    assert_eq!(decode::<Twist>(&[]), Err(DecodeError::TooShort(0)));
    assert_eq!(decode::<Twist>(&[0, 1, 0]), Err(DecodeError::TooShort(3)));
}

#[test]
fn image_geometry_is_validated() {
    assert_eq!(common::image_rgb().validate(), Ok(PixelEncoding::Rgb8));
    assert_eq!(
        common::image_depth().validate(),
        Ok(PixelEncoding::Depth32FC1)
    );
    let mut short = common::image_rgb();
    short.data.pop();
    assert!(matches!(
        short.validate(),
        Err(ImageError::BadGeometry { .. })
    ));
    let mut odd = common::image_rgb();
    odd.encoding = "yuv422".into();
    assert_eq!(
        odd.validate(),
        Err(ImageError::UnsupportedEncoding("yuv422".into()))
    );
}

/// `encode_with_tail` keeps the observation apart from the head; the payload
/// must be exactly the plain encoding, for every data length (padding
/// differs), joined or as Zenoh sends it.
#[test]
fn observations_kept_apart_equal_the_plain_encoding() {
    use offworld_runtime::codec::encode_with_tail;
    for len in 0..9usize {
        let data: Vec<u8> = (0..len as u8).map(|i| i * 7 + 1).collect();
        let obs = ObsArray {
            height: 1,
            width: len as u32,
            channels: 1,
            dtype: DType::U8,
            data: data.clone(),
        };
        let step = StepReply {
            observation: obs.clone(),
            ..common::step_reply()
        };
        let reset = ResetReply {
            observation: obs,
            ..common::reset_reply()
        };
        let mut head = step.clone();
        head.observation.data.clear();
        let apart = encode_with_tail(&head, data.clone()).expect("step reply");
        assert_same_payload(&apart.to_vec(), &step, len);
        assert_eq!(apart.decode().expect("decodes"), step);
        let payload = apart.into_payload();
        assert_eq!(
            payload.slices().count(),
            if len == 0 { 1 } else { 2 },
            "not joined"
        );
        assert_same_payload(&payload.to_bytes(), &step, len);
        let mut head = reset.clone();
        head.observation.data.clear();
        let apart = encode_with_tail(&head, data.clone()).expect("reset reply");
        assert_same_payload(&apart.to_vec(), &reset, len);
    }
    // Only a message ending in an empty byte sequence can take a tail.
    let refused = encode_with_tail(&common::step_request(), vec![1, 2, 3, 4]);
    assert!(refused.is_err());
    let mut full = common::step_reply();
    full.observation.data = vec![9];
    assert!(encode_with_tail(&full, vec![1]).is_err());
}

fn assert_same_payload<T: Serialize>(in_place: &[u8], full: &T, len: usize) {
    assert_eq!(
        in_place,
        encode(full).expect("encode"),
        "tail of {len} bytes"
    );
}

/// A payload as Zenoh hands over a reassembled reply: in fragments.
fn fragmented(bytes: &[u8], cuts: &[usize]) -> zenoh::bytes::ZBytes {
    let mut writer = zenoh::bytes::ZBytes::writer();
    let mut start = 0;
    for &cut in cuts.iter().chain([&bytes.len()]) {
        writer.append(bytes[start..cut].to_vec().into());
        start = cut;
    }
    writer.finish()
}

/// The receiving mirror of `encode_with_tail`: a fragmented reply decodes
/// to the very message, wherever the fragments are cut, and whatever is
/// broken fails exactly as the plain decode fails.
#[test]
fn fragmented_observations_decode_as_the_plain_payload() {
    use offworld_runtime::codec::{
        decode_payload, decode_payload_tail, decode_payload_tail_into, decode_payload_tail_to,
    };
    let data: Vec<u8> = (0..40u8).map(|i| i.wrapping_mul(13)).collect();
    let step = StepReply {
        observation: ObsArray {
            height: 4,
            width: 10,
            channels: 1,
            dtype: DType::U8,
            data,
        },
        ..common::step_reply()
    };
    let bytes = encode(&step).expect("encode");
    for cut in 1..bytes.len() {
        for cuts in [vec![cut], vec![cut / 2, cut]] {
            let payload = fragmented(&bytes, &cuts);
            assert!(payload.slices().count() >= 2);
            let decoded: StepReply = decode_payload_tail(&payload).expect("decodes");
            assert_eq!(decoded, step, "cut at {cuts:?}");
        }
    }
    // Whole or fragmented, into a recycled buffer holding an older frame:
    // the same message, in that buffer's memory.
    for cuts in [vec![], vec![bytes.len() - 20]] {
        let recycled = vec![0xEE; 64];
        let address = recycled.as_ptr();
        let decoded: StepReply =
            decode_payload_tail_into(&fragmented(&bytes, &cuts), recycled).expect("decodes");
        assert_eq!(decoded, step, "cut at {cuts:?}");
        assert_eq!(
            decoded.observation.data.as_ptr(),
            address,
            "no new allocation, cut at {cuts:?}"
        );
    }
    // Or into a slot of a batch: the message without its pixels, the
    // pixels in the slot; a slot of another size is a typed error.
    for cuts in [vec![], vec![bytes.len() - 20], vec![9, 30]] {
        let payload = fragmented(&bytes, &cuts);
        let mut slot = [0xEE; 40];
        let decoded: StepReply = decode_payload_tail_to(&payload, &mut slot).expect("decodes");
        assert_eq!(slot.as_slice(), step.observation.data, "cut at {cuts:?}");
        assert!(decoded.observation.data.is_empty());
        let mut whole = decoded;
        whole.observation.data = slot.to_vec();
        assert_eq!(whole, step);
        let short = decode_payload_tail_to::<StepReply>(&payload, &mut [0; 39]);
        assert_eq!(
            short.map_err(|e| e.to_string()),
            Err("invalid value: a byte sequence of 40 bytes where 39 were expected".into())
        );
    }
    let reset = ResetReply {
        observation: step.observation.clone(),
        ..common::reset_reply()
    };
    let bytes = encode(&reset).expect("encode");
    let decoded: ResetReply = decode_payload_tail(&fragmented(&bytes, &[9, 30])).expect("decodes");
    assert_eq!(decoded, reset);
    // Truncated, padded with garbage, a lying length, a bad header.
    let bytes = encode(&step).expect("encode");
    let mut lying = bytes.clone();
    let count_at = bytes.len() - 44;
    lying[count_at..count_at + 4].copy_from_slice(&41u32.to_le_bytes());
    let mut bad_header = bytes.clone();
    bad_header[0] = 1;
    for broken in [
        bytes[..bytes.len() - 1].to_vec(),
        [bytes.as_slice(), &[9, 9, 9, 9]].concat(),
        lying,
        bad_header,
    ] {
        let payload = fragmented(&broken, &[broken.len() - 20]);
        let tail = decode_payload_tail::<StepReply>(&payload).map_err(|e| e.to_string());
        let plain = decode_payload::<StepReply>(&payload).map_err(|e| e.to_string());
        assert!(plain.is_err());
        assert_eq!(tail, plain);
        let whole = fragmented(&broken, &[]);
        let into = decode_payload_tail_into::<StepReply>(&whole, vec![1; 8]);
        assert_eq!(into.map_err(|e| e.to_string()), plain, "in one piece");
    }
}
