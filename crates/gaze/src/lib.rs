//! Eye-tracker drivers (HID usage page 0x12; the dioptra binocular tracker). Gaze signal
//! processing lives in `dioptra_sched::processing`, so the scheduler uses it without linking
//! a HID library.

pub mod dioptra_tracker;
pub mod eye_hid;
pub mod hid_descriptor;
pub mod ids;
pub mod pupil;
mod timing;
