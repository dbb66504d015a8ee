//! Arbitrary bytes through the decoders. Nothing may panic, and every frame they accept must
//! re-encode to bytes that decode to the same message again; the checks a device runs on a
//! received schedule or photodiode config must not panic either. Seeds: `fuzz/seeds/
//! stream_decoder/`, one golden frame per message (vectors/vectors.txt) behind a chunk byte.
#![no_main]

use dioptra_protocol::{
    decode_frame, encode_frame, Frame, FrameDecoder, Message, CRC_LEN, FRAME_CRC, MAX_BODY_LEN,
    MAX_FRAME_LEN,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // The first byte picks the chunk size (1..=256), the rest is the stream.
    let Some((&chunk_choice, stream)) = data.split_first() else {
        return;
    };
    let chunk_len = usize::from(chunk_choice) + 1;
    let mut decoder = FrameDecoder::new();
    for chunk in stream.chunks(chunk_len) {
        decoder
            .push(chunk)
            .flatten()
            .for_each(|frame| check_round_trip(&frame));
    }

    // Random bytes almost never pass the CRC, so also frame the stream as a body with a valid
    // CRC: that lets coverage reach the version check and the message parser.
    let body_len = stream.len().min(MAX_BODY_LEN - CRC_LEN);
    let mut body = [0u8; MAX_BODY_LEN];
    body[..body_len].copy_from_slice(&stream[..body_len]);
    let crc = FRAME_CRC.checksum(&body[..body_len]).to_le_bytes();
    body[body_len..body_len + CRC_LEN].copy_from_slice(&crc);
    let mut wire = [0u8; MAX_FRAME_LEN];
    let len = cobs::encode(&body[..body_len + CRC_LEN], &mut wire);
    if let Ok(frame) = decode_frame(&wire[..len]) {
        check_round_trip(&frame);
    }
});

fn check_round_trip(frame: &Frame) {
    // What a device checks on every received config must not panic on any decoded value.
    match &frame.message {
        Message::PlaneSchedule(s) => {
            let _ = s.validate();
        }
        Message::PhotodiodeConfig(c) => {
            if c.validate().is_ok() {
                assert!(
                    c.hysteresis < c.threshold && c.threshold.checked_add(c.hysteresis).is_some()
                );
            }
        }
        _ => {}
    }
    let mut wire = [0u8; MAX_FRAME_LEN];
    let len = encode_frame(frame.request_id, &frame.message, &mut wire)
        .expect("a decoded message re-encodes");
    let again = decode_frame(&wire[..len]).expect("a re-encoded frame decodes");
    assert_eq!(again.request_id, frame.request_id);
    // Compare encodings rather than messages, so that NaN fields count as equal.
    let mut wire_again = [0u8; MAX_FRAME_LEN];
    let len_again = encode_frame(again.request_id, &again.message, &mut wire_again)
        .expect("a decoded message re-encodes");
    assert_eq!(wire[..len], wire_again[..len_again]);
}
