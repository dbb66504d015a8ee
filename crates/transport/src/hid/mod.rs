//! HID devices as a [`HidLink`]: input, output and feature reports plus the report
//! descriptor.
//!
//! # Report-id convention
//!
//! Every report buffer, in both directions, starts with the report id; devices that use no
//! report ids take and give `0` there. This is hidapi's convention for writes and feature
//! reports, applied to input reports too: hidapi/hidraw omit the byte on input from devices
//! without report ids, and [`HidapiLink`] puts the `0` back, so a driver parses one layout
//! whatever the device. Lengths returned include that first byte.

use std::future::Future;
use std::time::Duration;

use dioptra_core::LinkError;

mod hidraw;
pub mod memory;

pub(crate) use hidraw::hid_api;
pub use hidraw::HidapiLink;

/// An async HID device. Same conventions as [`crate::ByteLink`]: `&mut self`, `Send`
/// futures, [`LinkError`] for every failure (a device that stalls a request gives
/// [`LinkError::Io`]).
pub trait HidLink: Send {
    /// Waits up to `timeout` for the next input report and copies it (report id first) into
    /// `buf`; returns its length. A report longer than `buf` is truncated, as hidraw does.
    fn read_input_report(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> impl Future<Output = Result<usize, LinkError>> + Send;

    /// Sends an output report; `report[0]` is the report id.
    fn write_output_report(
        &mut self,
        report: &[u8],
    ) -> impl Future<Output = Result<(), LinkError>> + Send;

    /// Reads feature report `report_id` into `buf` (`buf[0]` becomes the report id); returns
    /// the length including that byte. `buf` must hold at least the id byte.
    fn get_feature_report(
        &mut self,
        report_id: u8,
        buf: &mut [u8],
    ) -> impl Future<Output = Result<usize, LinkError>> + Send;

    /// Sends a feature report; `report[0]` is the report id.
    fn send_feature_report(
        &mut self,
        report: &[u8],
    ) -> impl Future<Output = Result<(), LinkError>> + Send;

    /// The device's HID report descriptor: where every field of every report is.
    fn report_descriptor(&mut self) -> impl Future<Output = Result<Vec<u8>, LinkError>> + Send;

    /// What this link is connected to, for logs and error messages.
    fn describe(&self) -> String;
}

/// True when the report descriptor declares any Report ID item, i.e. every report on the
/// wire starts with its id. Stops quietly at a truncated item.
pub(crate) fn descriptor_uses_report_ids(descriptor: &[u8]) -> bool {
    const REPORT_ID_TAG: u8 = 0x84; // global item, tag 8 (HID 1.11, 6.2.2.7)
    let mut i = 0;
    while let Some(&prefix) = descriptor.get(i) {
        if prefix == 0xfe {
            // Long item: size byte, tag byte, data.
            let Some(&size) = descriptor.get(i + 1) else {
                return false;
            };
            i += 3 + usize::from(size);
            continue;
        }
        if prefix & 0xfc == REPORT_ID_TAG {
            return true;
        }
        i += 1 + [0, 1, 2, 4][usize::from(prefix & 0x03)];
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_id_items_are_found_and_truncation_is_harmless() {
        // Usage Page (0x12), Usage (1), Collection (Application), Report ID (1), ...
        let with_ids = [0x05, 0x12, 0x09, 0x01, 0xa1, 0x01, 0x85, 0x01, 0xc0];
        assert!(descriptor_uses_report_ids(&with_ids));
        // The same without the Report ID item; the 0x85 byte inside Usage (0x85) is data.
        let without = [0x05, 0x12, 0x09, 0x85, 0xa1, 0x01, 0xc0];
        assert!(!descriptor_uses_report_ids(&without));
        // A long item whose data holds 0x85, then a truncated 4-byte item.
        let long = [0xfe, 0x02, 0x10, 0x85, 0x85, 0x07, 0x01];
        assert!(!descriptor_uses_report_ids(&long));
        assert!(!descriptor_uses_report_ids(&[0xfe]));
        assert!(!descriptor_uses_report_ids(&[]));
    }
}
