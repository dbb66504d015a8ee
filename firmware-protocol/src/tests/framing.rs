//! One-frame encoding and decoding, one test per error kind.

use std::vec::Vec;

use super::{wire, wire_with_payload};
use crate::frame::HEADER_LEN;
use crate::message::MESSAGE_VARIANT_COUNT;
use crate::test_support::largest_messages;
use crate::*;

#[test]
fn frame_crc_is_crc32_iscsi() {
    let algorithm = FRAME_CRC.algorithm;
    assert_eq!(
        (algorithm.width, algorithm.poly, algorithm.init),
        (32, 0x1EDC_6F41, 0xFFFF_FFFF)
    );
    assert!(algorithm.refin && algorithm.refout);
    assert_eq!(algorithm.xorout, 0xFFFF_FFFF);
    assert_eq!(FRAME_CRC.checksum(b"123456789"), 0xE306_9283);
}

#[test]
fn ack_with_request_id_1_matches_hand_computed_bytes() {
    // Body:  02 (version) 01 00 (request id 1, LE) 02 (Ack = discriminant 2, postcard varint)
    // CRC-32/ISCSI of 02 01 00 02 = 0xB37A8ACF, appended LE: CF 8A 7A B3
    // COBS of 02 01 00 02 CF 8A 7A B3: the zero at index 2 ends a 2-byte run -> code 03 02 01;
    // the last run of 5 bytes -> code 06 02 CF 8A 7A B3; then the 00 delimiter.
    let expected = [0x03, 0x02, 0x01, 0x06, 0x02, 0xCF, 0x8A, 0x7A, 0xB3, 0x00];
    assert_eq!(wire(1, &Message::Ack), expected);
    let frame = decode_frame(&expected).expect("the hand-computed frame decodes");
    assert_eq!(
        frame,
        Frame {
            version: 2,
            request_id: 1,
            message: Message::Ack
        }
    );
}

#[test]
fn photodiode_edge_matches_hand_computed_bytes() {
    // Body:  02 (version) 00 00 (event id 0) 12 (discriminant 18)
    //        AC 02 (edge 300) E7 84 91 3B (124011111 us) 01 (rising) A2 90 03 (level 51234)
    // CRC-32/ISCSI of those 15 bytes = 0xC867B5F2 (a bitwise implementation outside this crate),
    // LE: F2 B5 67 C8. COBS: runs 02 | (empty) | the 15 bytes from 12 to C8.
    let expected = [
        0x02, 0x02, 0x01, 0x10, 0x12, 0xAC, 0x02, 0xE7, 0x84, 0x91, 0x3B, 0x01, 0xA2, 0x90, 0x03,
        0xF2, 0xB5, 0x67, 0xC8, 0x00,
    ];
    let edge = Message::PhotodiodeEdge(PhotodiodeEdge {
        edge: 300,
        device_time_us: 124_011_111,
        rising: true,
        level: 51_234,
    });
    assert_eq!(wire(EVENT_REQUEST_ID, &edge), expected);
    assert_eq!(decode_frame(&expected).map(|f| f.message), Ok(edge));
}

#[test]
fn photodiode_config_validation_keeps_both_edges_possible() {
    let config = |threshold, hysteresis| PhotodiodeConfig {
        enabled: true,
        threshold,
        hysteresis,
    };
    assert_eq!(config(32_768, 2_000).validate(), Ok(()));
    assert_eq!(config(1, 0).validate(), Ok(()));
    assert_eq!(config(65_534, 0).validate(), Ok(()));
    for (threshold, hysteresis) in [(0, 0), (2_000, 2_000), (65_535, 0), (60_000, 5_535)] {
        assert_eq!(
            config(threshold, hysteresis).validate(),
            Err(PhotodiodeConfigError::BandOutsideRange {
                threshold,
                hysteresis
            }),
            "{threshold} +/- {hysteresis}"
        );
    }
}

#[test]
fn largest_messages_fit_a_frame() {
    let message_lens: Vec<usize> = largest_messages()
        .iter()
        .map(|message| {
            let frame = wire(u16::MAX, message);
            assert_eq!(
                decode_frame(&frame).map(|f| f.message).as_ref(),
                Ok(message)
            );
            // Bodies under 254 bytes gain exactly one COBS byte, plus the delimiter.
            frame.len() - 2 - HEADER_LEN - CRC_LEN
        })
        .collect();
    // DeviceInfo, Error, TimeSyncPong, PlaneSchedule, SubframeEvent, Fault, BinocularSample,
    // PhotodiodeConfig, PhotodiodeEdge: the maxima PROTOCOL.md quotes. The largest body is
    // 3 + 77 + 4 = 84 bytes.
    assert_eq!(message_lens, [36, 35, 21, 77, 21, 18, 69, 8, 20]);
    assert_eq!(MAX_FRAME_LEN, 259);
}

#[test]
fn encode_reports_a_small_buffer_and_fits_an_exact_one() {
    let message = Message::SetFocalPower {
        diopters: 2.5,
        apply_at_us: 0,
    };
    let frame = wire(9, &message);
    let mut out = std::vec![0u8; frame.len()];
    assert_eq!(
        encode_frame(9, &message, &mut out[..frame.len() - 1]),
        Err(EncodeError::BufferTooSmall {
            needed: frame.len(),
            available: frame.len() - 1
        })
    );
    assert_eq!(encode_frame(9, &message, &mut out), Ok(frame.len()));
    assert_eq!(out, frame);
}

#[test]
fn decode_frame_takes_a_frame_with_or_without_its_delimiter() {
    let frame = wire(42, &Message::GetLimits);
    let without = &frame[..frame.len() - 1];
    assert_eq!(decode_frame(&frame), decode_frame(without));
    assert_eq!(decode_frame(without).map(|f| f.request_id), Ok(42));
}

#[test]
fn nan_payload_bits_survive_the_wire() {
    let odd_nan = f32::from_bits(0x7FC0_1234);
    let frame = decode_frame(&wire(
        3,
        &Message::SetFocalPower {
            diopters: odd_nan,
            apply_at_us: 1,
        },
    ));
    let Ok(Frame {
        message: Message::SetFocalPower { diopters, .. },
        ..
    }) = frame
    else {
        panic!("expected SetFocalPower, got {frame:?}");
    };
    assert_eq!(diopters.to_bits(), odd_nan.to_bits());
}

#[test]
fn request_ids_wrap_past_zero() {
    assert_eq!(next_request_id(EVENT_REQUEST_ID), 1);
    assert_eq!(next_request_id(1), 2);
    assert_eq!(next_request_id(u16::MAX), 1);
}

#[test]
fn too_long_body_is_rejected_and_a_maximal_one_is_not() {
    // A body of MAX_BODY_LEN bytes gets past the size check (and fails later, on its content).
    let mut payload = [0u8; MAX_MESSAGE_LEN];
    payload[0] = 2; // Ack, followed by MAX_MESSAGE_LEN - 1 zero bytes
    assert_eq!(
        decode_frame(&wire_with_payload(PROTOCOL_VERSION, 5, &payload)),
        Err(DecodeError::TrailingBytes {
            count: MAX_MESSAGE_LEN - 1,
            request_id: 5
        })
    );
    // One byte more is too long, whatever it holds.
    let body = [1u8; MAX_BODY_LEN + 1];
    let mut encoded = [0u8; MAX_FRAME_LEN + 1];
    let len = cobs::encode(&body, &mut encoded);
    let error = decode_frame(&encoded[..len]);
    assert_eq!(error, Err(DecodeError::TooLong));
    assert_eq!(DecodeError::TooLong.error_code(), ErrorCode::FrameTooLong);
    assert_eq!(DecodeError::TooLong.request_id(), None);
}

#[test]
fn invalid_cobs_is_rejected() {
    // Code byte 05 promises four data bytes, but the delimiter comes after one.
    assert_eq!(decode_frame(&[0x05, 0x01, 0x00]), Err(DecodeError::Cobs));
    // A 0x00 inside a single frame.
    let mut frame = wire(1, &Message::Ack);
    frame[4] = 0;
    assert_eq!(decode_frame(&frame), Err(DecodeError::Cobs));
    assert_eq!(DecodeError::Cobs.error_code(), ErrorCode::BadCrc);
}

#[test]
fn short_bodies_are_rejected() {
    assert_eq!(decode_frame(&[]), Err(DecodeError::TooShort { len: 0 }));
    assert_eq!(decode_frame(&[0x00]), Err(DecodeError::TooShort { len: 0 }));
    // Header and CRC with no message: 7 bytes.
    let error = decode_frame(&wire_with_payload(PROTOCOL_VERSION, 1, &[]));
    assert_eq!(
        error,
        Err(DecodeError::TooShort {
            len: HEADER_LEN + 4
        })
    );
    assert_eq!(error.unwrap_err().error_code(), ErrorCode::Malformed);
}

#[test]
fn bad_crc_is_rejected_with_both_values() {
    // Ack (02) with request id 1, the discriminant byte changed to 03 on the way.
    let mut frame = wire(1, &Message::Ack);
    assert_eq!(frame[4], 0x02);
    frame[4] = 0x03;
    let error = decode_frame(&frame).unwrap_err();
    assert_eq!(
        error,
        DecodeError::BadCrc {
            received: 0xB37A_8ACF,
            computed: 0x4111_09CC // CRC-32/ISCSI of 02 01 00 03
        }
    );
    assert_eq!(error.request_id(), None);
    assert_eq!(error.error_code(), ErrorCode::BadCrc);
}

#[test]
fn other_protocol_versions_are_reported_not_parsed() {
    // Versions 1 and 3 with a payload that would be a valid v2 Ack: must still not be
    // interpreted (version 1 knows no photodiode messages; a v2 host refuses v1 devices).
    for version in [1, 3] {
        assert_eq!(
            decode_frame(&wire_with_payload(version, 77, &[0x02])),
            Err(DecodeError::UnsupportedVersion {
                version,
                request_id: 77
            })
        );
    }
    let error = decode_frame(&wire_with_payload(3, 77, &[0x02])).unwrap_err();
    assert_eq!(error.request_id(), Some(77));
    assert_eq!(error.error_code(), ErrorCode::UnsupportedVersion);
}

#[test]
fn unknown_discriminants_are_reported_as_unknown_messages() {
    let count = u8::try_from(MESSAGE_VARIANT_COUNT).expect("fewer than 128 variants");
    let error = decode_frame(&wire_with_payload(PROTOCOL_VERSION, 78, &[count])).unwrap_err();
    assert_eq!(
        error,
        DecodeError::UnknownMessage {
            discriminant: MESSAGE_VARIANT_COUNT,
            request_id: 78
        }
    );
    assert_eq!(error.request_id(), Some(78));
    assert_eq!(error.error_code(), ErrorCode::UnknownMessage);
    // A two-byte varint discriminant (128).
    assert_eq!(
        decode_frame(&wire_with_payload(PROTOCOL_VERSION, 79, &[0x80, 0x01])),
        Err(DecodeError::UnknownMessage {
            discriminant: 128,
            request_id: 79
        })
    );
}

#[test]
fn malformed_payloads_are_rejected_with_postcards_reason() {
    let malformed =
        |payload: &[u8]| match decode_frame(&wire_with_payload(PROTOCOL_VERSION, 80, payload)) {
            Err(DecodeError::Malformed { error, request_id }) => {
                assert_eq!(request_id, 80);
                error
            }
            other => panic!("payload {payload:02x?} gave {other:?}"),
        };
    // LensState (8): three f32, then `settled` = 2, which is no bool.
    let mut lens_state = std::vec![8u8];
    lens_state.extend_from_slice(&[0; 12]);
    lens_state.extend_from_slice(&[2, 0]);
    assert_eq!(malformed(&lens_state), postcard::Error::DeserializeBadBool);
    // SetFocalPower (6) with its fields missing.
    assert_eq!(malformed(&[6]), postcard::Error::DeserializeUnexpectedEnd);
    // PhotodiodeEdge (18): edge 0, time 1 us, then `rising` = 7.
    assert_eq!(
        malformed(&[18, 0, 1, 7, 0]),
        postcard::Error::DeserializeBadBool
    );
    // PhotodiodeConfig (17) whose threshold varint overflows a u16.
    assert_eq!(
        malformed(&[17, 1, 0xFF, 0xFF, 0x04, 0]),
        postcard::Error::DeserializeBadVarint
    );
    // Error (3) with code 12, which no ErrorCode has.
    assert_eq!(malformed(&[3, 12, 0]), postcard::Error::SerdeDeCustom);
    // DeviceInfo (1) with a 17-byte serial.
    let mut device_info = std::vec![1u8, 0, 1, 1, 0, 0, 17];
    device_info.extend_from_slice(&[b'A'; 17]);
    device_info.push(0);
    assert_eq!(malformed(&device_info), postcard::Error::SerdeDeCustom);
    // A discriminant varint that never ends.
    assert_eq!(
        malformed(&[0x80, 0x80, 0x80, 0x80, 0x80, 0x80]),
        postcard::Error::DeserializeBadVarint
    );
    let error = decode_frame(&wire_with_payload(PROTOCOL_VERSION, 80, &[6])).unwrap_err();
    assert_eq!(error.error_code(), ErrorCode::Malformed);
    assert_eq!(error.request_id(), Some(80));
}

#[test]
fn bytes_after_the_message_are_rejected() {
    let error = decode_frame(&wire_with_payload(PROTOCOL_VERSION, 81, &[0x02, 0xAA])).unwrap_err();
    assert_eq!(
        error,
        DecodeError::TrailingBytes {
            count: 1,
            request_id: 81
        }
    );
    assert_eq!(error.error_code(), ErrorCode::Malformed);
}

#[test]
fn the_wire_carries_invalid_schedules_for_the_device_to_refuse() {
    let empty = PlaneSchedule {
        plane_powers_d: heapless::Vec::new(),
        subframe_period_us: 4_166,
        settle_allowance_us: 0,
        trigger_rising: true,
    };
    let frame = decode_frame(&wire(6, &Message::PlaneSchedule(empty))).expect("decodes");
    let Message::PlaneSchedule(schedule) = frame.message else {
        panic!("expected PlaneSchedule, got {:?}", frame.message);
    };
    assert_eq!(
        schedule.validate(),
        Err(ScheduleError::PlaneCount { count: 0 })
    );
}
