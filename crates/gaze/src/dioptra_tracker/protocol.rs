//! The dioptra binocular tracker's HID reports (vendor page 0xFF00, usage 0xD1).
//!
//! - Input report 1, 70 bytes: `[0x01][n][postcard(BinocularSample): n bytes][zero pad]`
//!   with n ≤ 68, the largest postcard encoding of a `BinocularSample` (a 10-byte varint
//!   time and 2 x 29 bytes of eye data). The message is postcard alone, not a framed
//!   dioptra-protocol frame: HID already delimits and checks reports.
//! - Feature report 2, 5 bytes: `[0x02][streaming 0|1][rate_hz u16 LE][report version]`.
//!   Writing it with streaming = 1 starts the stream; rate 0 keeps the device's rate.

use dioptra_core::EyeRay;
use dioptra_protocol::{BinocularSample, EyeSample};

use crate::eye_hid::protocol::ReportError;
use crate::hid_descriptor::{ReportDescriptor, ReportKind, Usage};

pub const VENDOR_PAGE: u16 = 0xff00;
pub const APPLICATION_USAGE: Usage = Usage::new(VENDOR_PAGE, 0xd1);
pub const SAMPLE_REPORT_ID: u8 = 1;
pub const SAMPLE_REPORT_LEN: usize = 70;
pub const MAX_PAYLOAD: usize = SAMPLE_REPORT_LEN - 2;
pub const CONTROL_REPORT_ID: u8 = 2;
pub const CONTROL_REPORT_LEN: usize = 5;
pub const REPORT_VERSION: u8 = 1;

/// Checks that a descriptor is the dioptra tracker's: the application usage and both
/// reports at their sizes.
pub fn check_descriptor(d: &ReportDescriptor) -> Result<(), String> {
    if !d.applications.contains(&APPLICATION_USAGE) {
        return Err(format!(
            "not a dioptra tracker: no application collection {APPLICATION_USAGE}"
        ));
    }
    for (kind, id, len) in [
        (ReportKind::Input, SAMPLE_REPORT_ID, SAMPLE_REPORT_LEN),
        (ReportKind::Feature, CONTROL_REPORT_ID, CONTROL_REPORT_LEN),
    ] {
        match d.report_len(kind, id) {
            Some(n) if n >= len => {}
            n => {
                return Err(format!(
                    "{kind:?} report {id} is {n:?} bytes, the dioptra tracker's is {len}"
                ))
            }
        }
    }
    Ok(())
}

/// Decodes input report 1 (report id first).
pub fn decode_sample_report(report: &[u8]) -> Result<BinocularSample, ReportError> {
    let (&id, rest) = report.split_first().ok_or(ReportError::Empty)?;
    if id != SAMPLE_REPORT_ID {
        return Err(ReportError::WrongId {
            expected: SAMPLE_REPORT_ID,
            got: id,
        });
    }
    let (&n, body) = rest.split_first().ok_or(ReportError::Short {
        id,
        needed: 2,
        got: report.len(),
    })?;
    let n = usize::from(n);
    let malformed = |detail: String| ReportError::Malformed { id, detail };
    if n > MAX_PAYLOAD {
        return Err(malformed(format!(
            "payload length {n} exceeds {MAX_PAYLOAD}"
        )));
    }
    let payload = body.get(..n).ok_or(ReportError::Short {
        id,
        needed: 2 + n,
        got: report.len(),
    })?;
    let (sample, extra) = postcard::take_from_bytes::<BinocularSample>(payload)
        .map_err(|e| malformed(format!("BinocularSample does not decode: {e}")))?;
    if !extra.is_empty() {
        return Err(malformed(format!(
            "{} bytes after the BinocularSample",
            extra.len()
        )));
    }
    Ok(sample)
}

/// One eye as core's [`EyeRay`]. A ray that is not finite or has no direction is invalid,
/// whatever the device's flag says.
pub fn eye_ray(e: &EyeSample) -> EyeRay {
    let d = e.direction;
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let finite = e.origin_mm.iter().chain(&d).all(|v| v.is_finite());
    let valid = e.valid && finite && n > 0.5 && n < 1.5;
    let n = if valid { n } else { 1.0 };
    EyeRay {
        origin_mm: e.origin_mm,
        direction: [d[0] / n, d[1] / n, d[2] / n],
        pupil_mm: e.pupil_mm,
        valid,
    }
}

/// The stream-control feature report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamControl {
    pub streaming: bool,
    pub rate_hz: u16,
    pub version: u8,
}

impl StreamControl {
    pub fn encode(&self) -> [u8; CONTROL_REPORT_LEN] {
        let r = self.rate_hz.to_le_bytes();
        [
            CONTROL_REPORT_ID,
            u8::from(self.streaming),
            r[0],
            r[1],
            self.version,
        ]
    }

    pub fn decode(report: &[u8]) -> Result<StreamControl, ReportError> {
        match *report {
            [CONTROL_REPORT_ID, on @ (0 | 1), lo, hi, version, ..] => Ok(StreamControl {
                streaming: on == 1,
                rate_hz: u16::from_le_bytes([lo, hi]),
                version,
            }),
            [CONTROL_REPORT_ID, on, _, _, _, ..] => Err(ReportError::Malformed {
                id: CONTROL_REPORT_ID,
                detail: format!("streaming flag {on}"),
            }),
            [CONTROL_REPORT_ID, ..] => Err(ReportError::Short {
                id: CONTROL_REPORT_ID,
                needed: CONTROL_REPORT_LEN,
                got: report.len(),
            }),
            [id, ..] => Err(ReportError::WrongId {
                expected: CONTROL_REPORT_ID,
                got: id,
            }),
            [] => Err(ReportError::Empty),
        }
    }
}
