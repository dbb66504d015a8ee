//! Framing: `COBS([version][request_id LE][postcard(Message)][CRC-32/ISCSI LE]) 0x00`.

use crate::message::{ErrorCode, Message, MESSAGE_VARIANT_COUNT};
use crate::stream::FrameDecoder;

/// Version of this protocol, sent in every frame's first body byte and in `Hello`/`DeviceInfo`.
/// Version 2 added the photodiode messages (PROTOCOL.md, section 5).
pub const PROTOCOL_VERSION: u8 = 2;

/// Bytes before the message: version (1) and request id (2, little-endian).
pub const HEADER_LEN: usize = 3;
/// Bytes of the CRC trailer.
pub const CRC_LEN: usize = 4;
/// Largest frame body (header + message + CRC) before COBS encoding.
pub const MAX_BODY_LEN: usize = 256;
/// Largest postcard-encoded message.
pub const MAX_MESSAGE_LEN: usize = MAX_BODY_LEN - HEADER_LEN - CRC_LEN;
/// Smallest valid body: header, a one-byte message (a unit variant) and the CRC.
pub const MIN_BODY_LEN: usize = HEADER_LEN + 1 + CRC_LEN;
/// Largest frame on the wire: COBS-encoded maximum body plus the 0x00 delimiter. A buffer of this
/// size always holds an encoded frame.
pub const MAX_FRAME_LEN: usize = cobs::max_encoding_length(MAX_BODY_LEN) + 1;
/// Request id of unsolicited events (device -> host). Requests use 1..=65535.
pub const EVENT_REQUEST_ID: u16 = 0;

/// CRC-32/ISCSI (Castagnoli): width 32, poly 0x1EDC6F41, init 0xFFFFFFFF, reflected in and out,
/// xorout 0xFFFFFFFF, check 0xE3069283. Chosen over CRC-32/ISO-HDLC for its larger Hamming
/// distance at short lengths; many MCUs and every x86-64 have it in hardware.
pub const FRAME_CRC: crc::Crc<u32, CrcTable> = crc::Crc::<u32, CrcTable>::new(&crc::CRC_32_ISCSI);

/// Bare-metal firmware gets the 1 KiB byte-wise table; hosts the 16 KiB slice-by-16 table, which
/// is several times faster. Both compute the same CRC.
#[cfg(target_os = "none")]
pub type CrcTable = crc::Table<1>;
/// Bare-metal firmware gets the 1 KiB byte-wise table; hosts the 16 KiB slice-by-16 table, which
/// is several times faster. Both compute the same CRC.
#[cfg(not(target_os = "none"))]
pub type CrcTable = crc::Table<16>;

/// A decoded frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// The body's version byte (always [`PROTOCOL_VERSION`] once decoded).
    pub version: u8,
    /// Id that pairs a reply with its request; [`EVENT_REQUEST_ID`] for events.
    pub request_id: u16,
    /// The message.
    pub message: Message,
}

/// Why a message could not be framed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// `out` cannot hold the frame; [`MAX_FRAME_LEN`] always suffices.
    #[error("output buffer holds {available} bytes, the frame needs {needed}")]
    BufferTooSmall {
        /// Bytes the frame needs.
        needed: usize,
        /// Bytes `out` has.
        available: usize,
    },
    /// postcard could not serialise the message into [`MAX_MESSAGE_LEN`] bytes. No message of
    /// this version is that large; kept so that encoding never panics.
    #[error("message does not serialise into {MAX_MESSAGE_LEN} bytes: {0}")]
    Serialize(postcard::Error),
}

/// Why bytes did not decode to a frame. Variants that carry `request_id` passed the CRC, so the
/// id is trustworthy and a reply can be addressed to it.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// More than [`MAX_BODY_LEN`] decoded bytes without a delimiter; the stream decoder skipped
    /// to the next 0x00.
    #[error("frame longer than {MAX_BODY_LEN} bytes, discarded up to the next delimiter")]
    TooLong,
    /// The bytes are not valid COBS (a code byte points past the delimiter, or a 0x00 inside).
    #[error("invalid COBS encoding")]
    Cobs,
    /// The body is shorter than header + one message byte + CRC.
    #[error("frame body of {len} bytes is shorter than the {MIN_BODY_LEN}-byte minimum")]
    TooShort {
        /// Decoded body length.
        len: usize,
    },
    /// The CRC trailer does not match the body.
    #[error("CRC mismatch: frame says {received:#010x}, body gives {computed:#010x}")]
    BadCrc {
        /// CRC carried by the frame.
        received: u32,
        /// CRC computed over the body.
        computed: u32,
    },
    /// The sender speaks another protocol version; the message was not interpreted.
    #[error("peer speaks protocol version {version}, this side speaks {PROTOCOL_VERSION}")]
    UnsupportedVersion {
        /// The frame's version byte.
        version: u8,
        /// The frame's request id.
        request_id: u16,
    },
    /// The message discriminant is not one this version knows.
    #[error("unknown message discriminant {discriminant}")]
    UnknownMessage {
        /// The discriminant read.
        discriminant: u32,
        /// The frame's request id.
        request_id: u16,
    },
    /// The message's fields did not parse (bad bool, string too long, unknown enum value, ...).
    #[error("malformed message: {error}")]
    Malformed {
        /// postcard's reason.
        error: postcard::Error,
        /// The frame's request id.
        request_id: u16,
    },
    /// The message parsed but bytes remained before the CRC.
    #[error("{count} unexpected bytes after the message")]
    TrailingBytes {
        /// Bytes left over.
        count: usize,
        /// The frame's request id.
        request_id: u16,
    },
}

impl DecodeError {
    /// The request id, when the CRC vouched for it. A device answers these errors with an
    /// `Error` reply to that id, and the others with an `Error` event (id 0).
    pub fn request_id(&self) -> Option<u16> {
        match *self {
            DecodeError::UnsupportedVersion { request_id, .. }
            | DecodeError::UnknownMessage { request_id, .. }
            | DecodeError::Malformed { request_id, .. }
            | DecodeError::TrailingBytes { request_id, .. } => Some(request_id),
            DecodeError::TooLong
            | DecodeError::Cobs
            | DecodeError::TooShort { .. }
            | DecodeError::BadCrc { .. } => None,
        }
    }

    /// The code a device reports for this error.
    pub fn error_code(&self) -> ErrorCode {
        match self {
            DecodeError::TooLong => ErrorCode::FrameTooLong,
            DecodeError::Cobs | DecodeError::BadCrc { .. } => ErrorCode::BadCrc,
            DecodeError::UnsupportedVersion { .. } => ErrorCode::UnsupportedVersion,
            DecodeError::UnknownMessage { .. } => ErrorCode::UnknownMessage,
            DecodeError::TooShort { .. }
            | DecodeError::Malformed { .. }
            | DecodeError::TrailingBytes { .. } => ErrorCode::Malformed,
        }
    }
}

/// The request id after `id`: counts 1..=65535 and wraps, skipping [`EVENT_REQUEST_ID`].
pub const fn next_request_id(id: u16) -> u16 {
    match id.wrapping_add(1) {
        EVENT_REQUEST_ID => 1,
        next => next,
    }
}

/// Writes `message` as one wire frame, delimiter included, to `out`; returns the bytes written.
pub fn encode_frame(
    request_id: u16,
    message: &Message,
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    let mut body = [0u8; MAX_BODY_LEN];
    let [id_low, id_high] = request_id.to_le_bytes();
    body[..HEADER_LEN].copy_from_slice(&[PROTOCOL_VERSION, id_low, id_high]);
    let message_space = &mut body[HEADER_LEN..HEADER_LEN + MAX_MESSAGE_LEN];
    let message_len = postcard::to_slice(message, message_space)
        .map_err(EncodeError::Serialize)?
        .len();
    seal_frame(&mut body, HEADER_LEN + message_len, out)
}

/// Appends the CRC to `body[..len]` and writes the COBS-encoded, delimited frame to `out`.
/// Separate from [`encode_frame`] so tests can frame hand-made (invalid) bodies.
pub(crate) fn seal_frame(
    body: &mut [u8; MAX_BODY_LEN],
    len: usize,
    out: &mut [u8],
) -> Result<usize, EncodeError> {
    let body_len = len.saturating_add(CRC_LEN);
    let body = body
        .get_mut(..body_len)
        .ok_or(EncodeError::Serialize(postcard::Error::SerializeBufferFull))?;
    let (covered, crc_slot) = body.split_at_mut(len);
    crc_slot.copy_from_slice(&FRAME_CRC.checksum(covered).to_le_bytes());

    // COBS adds one byte per started 254-byte run: exact for bodies under 254 bytes.
    let needed = cobs::max_encoding_length(body_len) + 1;
    let too_small = EncodeError::BufferTooSmall {
        needed,
        available: out.len(),
    };
    if out.len() < needed {
        return Err(too_small);
    }
    let encoded_len = cobs::try_encode(body, out).map_err(|_| too_small.clone())?;
    *out.get_mut(encoded_len).ok_or(too_small)? = 0;
    Ok(encoded_len + 1)
}

/// Decodes one frame: its COBS bytes, with or without the trailing 0x00 delimiter.
pub fn decode_frame(encoded: &[u8]) -> Result<Frame, DecodeError> {
    let encoded = encoded.strip_suffix(&[0]).unwrap_or(encoded);
    if encoded.contains(&0) {
        return Err(DecodeError::Cobs);
    }
    // One implementation of decoding: run the bytes through a fresh stream decoder.
    let mut decoder = FrameDecoder::new();
    if let Some(result) = decoder.push(encoded).next() {
        // Without a 0x00, the only thing the stream decoder reports early is an oversized run.
        return result;
    }
    decoder
        .push_byte(0)
        .unwrap_or(Err(DecodeError::TooShort { len: 0 }))
}

/// Decodes a COBS-decoded body: checks length, CRC and version, then parses the message.
pub(crate) fn decode_body(body: &[u8]) -> Result<Frame, DecodeError> {
    let too_short = DecodeError::TooShort { len: body.len() };
    if body.len() < MIN_BODY_LEN {
        return Err(too_short);
    }
    let (covered, crc_bytes) = body
        .split_last_chunk::<CRC_LEN>()
        .ok_or(too_short.clone())?;
    let received = u32::from_le_bytes(*crc_bytes);
    let computed = FRAME_CRC.checksum(covered);
    if received != computed {
        return Err(DecodeError::BadCrc { received, computed });
    }

    let (&[version, id_low, id_high], payload) =
        covered.split_first_chunk::<HEADER_LEN>().ok_or(too_short)?;
    let request_id = u16::from_le_bytes([id_low, id_high]);
    if version != PROTOCOL_VERSION {
        return Err(DecodeError::UnsupportedVersion {
            version,
            request_id,
        });
    }

    // Read the discriminant first so an unknown message is told apart from a malformed one.
    let malformed = |error| DecodeError::Malformed { error, request_id };
    let (discriminant, _) = postcard::take_from_bytes::<u32>(payload).map_err(malformed)?;
    if discriminant >= MESSAGE_VARIANT_COUNT {
        return Err(DecodeError::UnknownMessage {
            discriminant,
            request_id,
        });
    }
    let (message, rest) = postcard::take_from_bytes::<Message>(payload).map_err(malformed)?;
    if !rest.is_empty() {
        return Err(DecodeError::TrailingBytes {
            count: rest.len(),
            request_id,
        });
    }
    Ok(Frame {
        version,
        request_id,
        message,
    })
}
