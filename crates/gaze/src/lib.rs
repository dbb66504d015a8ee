//! Eye-tracker drivers (HID usage page 0x12; the dioptra binocular tracker) and gaze signal
//! processing.

pub mod dioptra_tracker;
pub mod eye_hid;
pub mod hid_descriptor;
pub mod ids;
pub mod processing;
mod timing;
