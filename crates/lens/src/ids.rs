//! USB identities of the lens drivers' devices; discovery and the udev rules come from here.

use dioptra_transport::discovery::{Interface, KnownDevice};

/// dioptra's own USB devices use the pid.codes open-hardware vendor id.
/// The product ids below are dioptra's choice and are not yet registered with pid.codes.
pub const DIOPTRA_VID: u16 = 0x1209;
pub const DIOPTRA_LENS_PID: u16 = 0xd107;

pub const OPTOTUNE_VID: u16 = 0x03eb;
pub const OPTOTUNE_LENS_DRIVER_4_PID: u16 = 0x2018;

pub const KNOWN_DEVICES: &[KnownDevice] = &[
    KnownDevice::usb(
        "optotune",
        "Optotune Lens Driver 4",
        OPTOTUNE_VID,
        OPTOTUNE_LENS_DRIVER_4_PID,
        Interface::Serial,
    ),
    KnownDevice::usb(
        "lens",
        "dioptra lens controller (CDC-ACM)",
        DIOPTRA_VID,
        DIOPTRA_LENS_PID,
        Interface::Serial,
    ),
    KnownDevice::usb(
        "lens",
        "dioptra lens controller (USB bulk)",
        DIOPTRA_VID,
        DIOPTRA_LENS_PID,
        Interface::UsbBulk,
    ),
];
