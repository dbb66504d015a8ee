//! dioptra-photodiode: light sensors for latency measurement behind core's
//! [`dioptra_core::Photodiode`]. A photodiode taped over the display's marker patch reports
//! the moment light leaves the panel; `dioptra hil` measures up to that moment.
//!
//! - [`serial_line`]: the common lab build, a microcontroller with a photodiode and a
//!   comparator speaking a small line protocol over USB serial ([`protocol`]; specification
//!   and the Arduino sketch in firmware-protocol/photodiode/), with [`ids`].
//! - The dioptra sync board's photodiode input is in `dioptra_sync::board` (it shares the
//!   board's link with its sub-frame events).

pub mod ids;
pub mod protocol;
pub mod serial_line;

pub use serial_line::{PhotodiodeStatus, SerialPhotodiode, SerialPhotodiodeConfig};
