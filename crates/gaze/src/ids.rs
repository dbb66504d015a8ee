//! Identities of the eye trackers the gaze drivers handle.

use dioptra_transport::discovery::{Interface, KnownDevice};

/// HID usage page "Eye and Head Trackers" (HUTRR74) and its Eye Tracker collection.
pub const EYE_HEAD_TRACKER_PAGE: u16 = 0x12;
pub const EYE_TRACKER_USAGE: u16 = 0x01;

/// dioptra's own USB devices use the pid.codes open-hardware vendor id; the product id is
/// dioptra's choice and not yet registered with pid.codes.
pub const DIOPTRA_VID: u16 = 0x1209;
pub const DIOPTRA_TRACKER_PID: u16 = 0xd109;

pub const KNOWN_DEVICES: &[KnownDevice] = &[
    KnownDevice::usb(
        "dioptra-tracker",
        "dioptra binocular eye tracker",
        DIOPTRA_VID,
        DIOPTRA_TRACKER_PID,
        Interface::Hid,
    ),
    KnownDevice::hid_usage(
        "hid",
        "eye tracker (HID usage page 0x12)",
        EYE_HEAD_TRACKER_PAGE,
        Some(EYE_TRACKER_USAGE),
    ),
];
