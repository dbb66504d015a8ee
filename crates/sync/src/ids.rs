//! USB identities of the multifocal sync hardware.

use dioptra_transport::discovery::{Interface, KnownDevice};

/// dioptra's own USB devices use the pid.codes open-hardware vendor id; the product id is
/// dioptra's choice and not yet registered with pid.codes.
pub const DIOPTRA_VID: u16 = 0x1209;
pub const DIOPTRA_SYNC_PID: u16 = 0xd108;

pub const TI_VID: u16 = 0x0451;
pub const DLPC350_PID: u16 = 0x6401;

pub const KNOWN_DEVICES: &[KnownDevice] = &[
    KnownDevice::usb(
        "sync",
        "dioptra multifocal sync board",
        DIOPTRA_VID,
        DIOPTRA_SYNC_PID,
        Interface::Serial,
    ),
    KnownDevice::usb(
        "dlpc350",
        "TI DLPC350 (DLP LightCrafter 4500)",
        TI_VID,
        DLPC350_PID,
        Interface::Hid,
    ),
];
