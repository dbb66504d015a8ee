//! The device side of dioptra-protocol, sans-IO, for simulators of dioptra's own firmware.
//!
//! Feed it the bytes the host sent; it hands back the requests that decoded, and answers
//! frames that did not as PROTOCOL.md says a device must (an `Error` reply to a frame whose
//! CRC passed, an `Error` event for one that did not, rate-limited). The simulator answers
//! requests with [`ProtocolDevice::reply`] and emits events with [`ProtocolDevice::event`].

use dioptra_protocol::{
    encode_frame, DecodeError, ErrorCode, FrameDecoder, Message, EVENT_REQUEST_ID, MAX_FRAME_LEN,
};

/// Decoder state and the error-reply policy of one simulated device.
#[derive(Debug, Default)]
pub struct ProtocolDevice {
    decoder: FrameDecoder,
    /// Device time (µs) of the last unaddressed error event, for rate limiting.
    last_error_event_us: Option<u64>,
}

/// At most one unaddressed error event per this many microseconds (PROTOCOL.md).
const ERROR_EVENT_INTERVAL_US: u64 = 10_000;

impl ProtocolDevice {
    pub fn new() -> Self {
        Self::default()
    }

    /// Decodes `bytes` received at device time `now_us`. Returns the requests (id, message);
    /// error answers for garbled frames are appended to `out` as wire bytes.
    pub fn receive(&mut self, bytes: &[u8], now_us: u64, out: &mut Vec<u8>) -> Vec<(u16, Message)> {
        let results: Vec<Result<_, DecodeError>> = self.decoder.push(bytes).collect();
        let mut requests = Vec::new();
        for r in results {
            match r {
                Ok(frame) => requests.push((frame.request_id, frame.message)),
                Err(e) => match e.request_id() {
                    Some(id) => {
                        Self::reply(out, id, &Message::error(e.error_code(), &e.to_string()))
                    }
                    None => {
                        let due = self
                            .last_error_event_us
                            .is_none_or(|t| now_us.saturating_sub(t) >= ERROR_EVENT_INTERVAL_US);
                        if due {
                            self.last_error_event_us = Some(now_us);
                            Self::event(out, &Message::error(e.error_code(), &e.to_string()));
                        }
                    }
                },
            }
        }
        requests
    }

    /// Appends the reply to request `request_id`.
    pub fn reply(out: &mut Vec<u8>, request_id: u16, message: &Message) {
        let mut buf = [0u8; MAX_FRAME_LEN];
        // Every message of this protocol version fits MAX_FRAME_LEN; a failure would be a bug
        // in the simulator's own message, so answer with an Internal error instead of panicking.
        let n = encode_frame(request_id, message, &mut buf).unwrap_or_else(|_| {
            encode_frame(
                request_id,
                &Message::error(ErrorCode::Internal, "encode"),
                &mut buf,
            )
            .unwrap_or(0)
        });
        out.extend_from_slice(&buf[..n]);
    }

    /// Appends an unsolicited event (request id 0).
    pub fn event(out: &mut Vec<u8>, message: &Message) {
        Self::reply(out, EVENT_REQUEST_ID, message)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_protocol::{decode_frame, FrameDecoder};

    fn frames(bytes: &[u8]) -> Vec<(u16, Message)> {
        let mut d = FrameDecoder::new();
        d.push(bytes)
            .map(|f| f.map(|f| (f.request_id, f.message)).unwrap())
            .collect()
    }

    #[test]
    fn decodes_requests_in_chunks_and_answers_garbage() {
        let mut dev = ProtocolDevice::new();
        let mut wire = Vec::new();
        ProtocolDevice::reply(&mut wire, 9, &Message::GetLimits);
        let mut out = Vec::new();
        let (a, b) = wire.split_at(3);
        assert!(dev.receive(a, 0, &mut out).is_empty());
        assert_eq!(dev.receive(b, 0, &mut out), vec![(9, Message::GetLimits)]);
        assert!(out.is_empty());

        // Corrupt the CRC: an unaddressed error event, rate-limited.
        let mut bad = wire.clone();
        bad[4] ^= 0x40;
        dev.receive(&bad, 100, &mut out);
        dev.receive(&bad, 200, &mut out);
        let got = frames(&out);
        assert_eq!(got.len(), 1);
        assert!(matches!(
            got[0],
            (
                0,
                Message::Error {
                    code: ErrorCode::BadCrc,
                    ..
                }
            )
        ));
        out.clear();
        dev.receive(&bad, 100 + ERROR_EVENT_INTERVAL_US, &mut out);
        assert_eq!(frames(&out).len(), 1);
    }

    #[test]
    fn unknown_message_is_answered_to_its_request_id() {
        // A frame whose CRC passes but whose discriminant is unknown gets an addressed error.
        let mut body = vec![dioptra_protocol::PROTOCOL_VERSION, 5, 0, 99];
        let crc = dioptra_protocol::FRAME_CRC.checksum(&body);
        body.extend_from_slice(&crc.to_le_bytes());
        let mut wire = vec![0u8; body.len() + 2];
        let n = cobs::encode(&body, &mut wire);
        wire.truncate(n);
        wire.push(0);
        assert!(decode_frame(&wire).is_err());
        let mut dev = ProtocolDevice::new();
        let mut out = Vec::new();
        assert!(dev.receive(&wire, 0, &mut out).is_empty());
        assert!(matches!(
            frames(&out)[..],
            [(
                5,
                Message::Error {
                    code: ErrorCode::UnknownMessage,
                    ..
                }
            )]
        ));
    }
}
