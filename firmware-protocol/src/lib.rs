//! dioptra-protocol: the wire protocol between the dioptra host and dioptra's own device
//! firmware (lens controller, multifocal sync board, binocular eye tracker).
//!
//! `no_std`, no allocation: the host and the firmware share this crate. A frame is
//! `COBS([version u8][request_id u16 LE][postcard(Message)][CRC-32/ISCSI LE]) 0x00`;
//! PROTOCOL.md beside this crate is the byte-level specification.
//!
//! ```
//! use dioptra_protocol::{decode_frame, encode_frame, Message, MAX_FRAME_LEN};
//!
//! let mut wire = [0u8; MAX_FRAME_LEN];
//! let request = Message::SetFocalPower { diopters: 1.5, apply_at_us: 0 };
//! let len = encode_frame(7, &request, &mut wire)?;
//! let frame = decode_frame(&wire[..len])?;
//! assert_eq!((frame.request_id, frame.message), (7, request));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

#[cfg(test)]
extern crate std;

mod frame;
mod message;
mod stream;

#[cfg(test)]
mod test_support;
#[cfg(test)]
mod tests;

pub use frame::{
    decode_frame, encode_frame, next_request_id, CrcTable, DecodeError, EncodeError, Frame,
    CRC_LEN, EVENT_REQUEST_ID, FRAME_CRC, HEADER_LEN, MAX_BODY_LEN, MAX_FRAME_LEN, MAX_MESSAGE_LEN,
    MIN_BODY_LEN, PROTOCOL_VERSION,
};
pub use message::{
    truncated, BinocularSample, Capabilities, DeviceInfo, DeviceKind, ErrorCode, ErrorDetail,
    EyeSample, Fault, FaultKind, FirmwareVersion, LensState, Limits, Message, PhotodiodeConfig,
    PhotodiodeConfigError, PhotodiodeEdge, PlaneSchedule, ScheduleError, Serial, SubframeEvent,
    UnknownErrorCode, ERROR_DETAIL_LEN, MAX_APPLY_AHEAD_US, MAX_PLANES, SERIAL_LEN,
};
pub use stream::{FrameDecoder, Frames};
