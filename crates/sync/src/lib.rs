//! Multifocal sync hardware drivers behind core's [`dioptra_core::PlaneSequencer`]: dioptra's
//! own sync board over dioptra-protocol ([`board`]) and the TI DLPC350 (DLP LightCrafter 4500)
//! over USB HID ([`dlpc350`]).

pub mod board;
pub mod dlpc350;
pub mod ids;
