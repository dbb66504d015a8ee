//! Eye-tracker drivers (HID usage page 0x12; the dioptra binocular tracker) and gaze signal processing. Filled by the eye-tracking issue; today it holds the devices' match table (ids.rs).

pub mod ids;
