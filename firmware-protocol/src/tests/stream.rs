//! The stream decoder on hand-picked byte sequences.

use std::vec::Vec;

use super::wire;
use crate::*;

fn frame(request_id: u16, message: Message) -> Frame {
    Frame {
        version: PROTOCOL_VERSION,
        request_id,
        message,
    }
}

fn decode_all(decoder: &mut FrameDecoder, bytes: &[u8]) -> Vec<Result<Frame, DecodeError>> {
    decoder.push(bytes).collect()
}

#[test]
fn frames_in_one_push_come_out_in_order() {
    let mut bytes = wire(1, &Message::GetLensState);
    bytes.extend(wire(2, &Message::GetLimits));
    let mut decoder = FrameDecoder::new();
    assert_eq!(
        decode_all(&mut decoder, &bytes),
        [
            Ok(frame(1, Message::GetLensState)),
            Ok(frame(2, Message::GetLimits))
        ]
    );
}

#[test]
fn a_frame_fed_byte_by_byte_completes_on_its_delimiter() {
    let bytes = wire(3, &Message::Start);
    let (last, rest) = bytes.split_last().expect("frames are not empty");
    let mut decoder = FrameDecoder::new();
    assert!(rest.iter().all(|&byte| decoder.push_byte(byte).is_none()));
    assert_eq!(decoder.push_byte(*last), Some(Ok(frame(3, Message::Start))));
}

#[test]
fn idle_delimiters_are_skipped() {
    let mut bytes = std::vec![0, 0, 0];
    bytes.extend(wire(4, &Message::Stop));
    bytes.extend([0, 0]);
    let mut decoder = FrameDecoder::new();
    assert_eq!(
        decode_all(&mut decoder, &bytes),
        [Ok(frame(4, Message::Stop))]
    );
}

#[test]
fn an_oversized_run_is_reported_once_and_skipped_to_the_next_delimiter() {
    // 0x01 bytes decode to zeros: 1000 of them make a body far over the limit.
    let mut bytes = std::vec![0x01; 1000];
    bytes.push(0);
    bytes.extend(wire(5, &Message::Ack));
    let mut decoder = FrameDecoder::new();
    assert_eq!(
        decode_all(&mut decoder, &bytes),
        [Err(DecodeError::TooLong), Ok(frame(5, Message::Ack))]
    );
}

#[test]
fn a_garbled_frame_does_not_spoil_the_next() {
    let mut bytes = wire(6, &Message::Ack);
    bytes[5] ^= 0x40; // a CRC byte: COBS structure intact
    bytes.extend(wire(7, &Message::Ack));
    let mut decoder = FrameDecoder::new();
    let results = decode_all(&mut decoder, &bytes);
    assert!(
        matches!(results[0], Err(DecodeError::BadCrc { .. })),
        "{results:?}"
    );
    assert_eq!(results[1..], [Ok(frame(7, Message::Ack))]);
}

#[test]
fn dropping_the_iterator_early_keeps_the_stream_in_step() {
    let mut bytes = wire(8, &Message::GetLensState);
    bytes.extend(wire(9, &Message::GetLimits));
    let third = wire(10, &Message::Stop);
    bytes.extend(&third[..4]);
    let mut decoder = FrameDecoder::new();
    let first = decoder.push(&bytes).next();
    assert_eq!(first, Some(Ok(frame(8, Message::GetLensState))));
    // Frame 9 was completed while the iterator was dropped and is gone; frame 10's start is kept.
    assert_eq!(
        decode_all(&mut decoder, &third[4..]),
        [Ok(frame(10, Message::Stop))]
    );
}

#[test]
fn reset_drops_a_partial_frame() {
    let bytes = wire(11, &Message::Start);
    let mut decoder = FrameDecoder::new();
    assert!(decode_all(&mut decoder, &bytes[..5]).is_empty());
    decoder.reset();
    assert_eq!(
        decode_all(&mut decoder, &bytes),
        [Ok(frame(11, Message::Start))]
    );
}
