//! Tests that exercise the crate as a whole: framing, stream decoding, properties, golden vectors.

mod framing;
mod properties;
mod stream;
mod vectors;

use std::vec::Vec;

use crate::frame::{seal_frame, HEADER_LEN, MAX_BODY_LEN};
use crate::{encode_frame, Message, MAX_FRAME_LEN};

/// `message` framed under `request_id`, as the bytes on the wire.
fn wire(request_id: u16, message: &Message) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME_LEN];
    let len = encode_frame(request_id, message, &mut out).expect("every message fits a frame");
    out[..len].to_vec()
}

/// A frame around a hand-made body (`version`, `request_id`, then `payload`), with a valid CRC:
/// for frames that must get past the CRC and fail later.
fn wire_with_payload(version: u8, request_id: u16, payload: &[u8]) -> Vec<u8> {
    let mut body = [0u8; MAX_BODY_LEN];
    let [id_low, id_high] = request_id.to_le_bytes();
    body[..HEADER_LEN].copy_from_slice(&[version, id_low, id_high]);
    body[HEADER_LEN..HEADER_LEN + payload.len()].copy_from_slice(payload);
    let mut out = [0u8; MAX_FRAME_LEN];
    let len = seal_frame(&mut body, HEADER_LEN + payload.len(), &mut out)
        .expect("test payloads fit a frame");
    out[..len].to_vec()
}
