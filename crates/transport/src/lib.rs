//! dioptra-transport: the links device drivers talk through.
//!
//! Drivers are generic over two small async traits, [`ByteLink`] (a byte stream: serial
//! ports, USB bulk endpoints, ptys, in-memory pipes) and [`HidLink`] (HID reports), so the
//! same driver code runs on real hardware, on a pty and on an in-memory link to a simulator.
//! Every failure is a [`LinkError`]; nothing here panics on input from a device or a caller.
//!
//! Backends (Linux):
//! - [`serial::SerialLink`]: a tty (`/dev/ttyACM*`, `/dev/ttyUSB*`, a pty slave) made async
//!   with tokio's `AsyncFd`.
//! - [`usb::UsbBulkLink`]: a pair of USB bulk endpoints through libusb (rusb, explicit context).
//! - [`memory::pair`]: an in-memory duplex pipe with fault injection, for tests and simulators.
//! - [`pty::PtyPair`]: a pseudo-terminal whose master side a simulator serves, while a driver
//!   opens the slave path through [`serial::SerialLink`] as if it were `/dev/ttyACM0`.
//! - [`hid::HidapiLink`]: a HID device through hidapi's hidraw backend;
//!   [`hid::memory::device`]: an in-memory HID device backed by a simulator.
//!
//! [`discovery`] lists the serial ports, USB devices and HID devices present and matches them
//! against the drivers' tables of known devices.

pub mod any;
mod blocking;
pub mod discovery;
mod fdio;
pub mod hid;
mod link;
pub mod memory;
pub mod protocol_client;
pub mod pty;
pub mod serial;
pub mod usb;

pub use any::{AnyByteLink, AnyHidLink};
pub use dioptra_core::LinkError;
pub use hid::HidLink;
pub use link::ByteLink;

/// The [`LinkError::Timeout`] for a wait of `timeout`.
pub(crate) fn timeout_error(timeout: std::time::Duration) -> LinkError {
    LinkError::Timeout {
        ms: u64::try_from(timeout.as_millis()).unwrap_or(u64::MAX),
    }
}
