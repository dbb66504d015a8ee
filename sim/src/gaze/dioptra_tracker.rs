//! The dioptra binocular tracker, simulated: a vendor-defined HID device whose input report
//! carries one postcard-encoded `BinocularSample`.
//!
//! Report layout (the firmware's side; the driver is `dioptra_gaze::dioptra_tracker`):
//! - input report 1, 70 bytes: `[0x01][n][postcard(BinocularSample): n bytes][zero pad]`,
//!   n ≤ 68 (the largest postcard encoding: 10-byte varint time + 2 x 29 bytes).
//! - feature report 2, 5 bytes: `[0x02][streaming 0|1][rate_hz u16 LE][protocol version]`.
//!   Writing it starts or stops the stream; a rate other than the running one is refused.

use std::sync::{Arc, Mutex};

use dioptra_protocol::BinocularSample;
use dioptra_transport::hid::memory::{self, HidBehaviour, HidRefusal, MemoryHidLink};

use super::{lock, spawn_serve, SampleSource, SimTracker, Streaming};

pub const SAMPLE_REPORT_ID: u8 = 1;
pub const SAMPLE_REPORT_LEN: usize = 70;
pub const MAX_PAYLOAD: usize = SAMPLE_REPORT_LEN - 2;
pub const CONTROL_REPORT_ID: u8 = 2;
pub const CONTROL_REPORT_LEN: usize = 5;
pub const REPORT_VERSION: u8 = 1;

/// The device's report descriptor: vendor page 0xFF00, usage 0xD1.
#[rustfmt::skip]
pub const DESCRIPTOR: &[u8] = &[
    0x06, 0x00, 0xff,       // Usage Page (vendor 0xFF00)
    0x09, 0xd1,             // Usage (0xD1: dioptra binocular tracker)
    0xa1, 0x01,             // Collection (Application)
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08, // bytes 0..=255
    0x85, 0x01, 0x09, 0x01, 0x95, 0x45, 0x81, 0x02, // Report 1: 69 bytes in
    0x85, 0x02, 0x09, 0x02, 0x95, 0x04, 0xb1, 0x02, // Report 2: 4 bytes feature
    0xc0,
];

/// Encodes one sample as input report 1; `None` if it does not fit (it always does).
pub fn encode_sample_report(s: &BinocularSample) -> Option<[u8; SAMPLE_REPORT_LEN]> {
    let mut r = [0u8; SAMPLE_REPORT_LEN];
    r[0] = SAMPLE_REPORT_ID;
    let n = postcard::to_slice(s, &mut r[2..]).ok()?.len();
    r[1] = n as u8;
    Some(r)
}

/// The device side of the feature report.
#[derive(Debug)]
pub struct TrackerState {
    pub streaming: bool,
    pub rate_hz: u16,
}

struct Behaviour(Arc<Mutex<Streaming<TrackerState>>>);

impl HidBehaviour for Behaviour {
    fn get_feature(&mut self, id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
        if id != CONTROL_REPORT_ID || buf.len() < CONTROL_REPORT_LEN {
            return Err(HidRefusal::new(format!(
                "no feature report {id} of that size"
            )));
        }
        let st = lock(&self.0);
        buf[1] = u8::from(st.device.streaming);
        buf[2..4].copy_from_slice(&st.device.rate_hz.to_le_bytes());
        buf[4] = REPORT_VERSION;
        Ok(CONTROL_REPORT_LEN)
    }

    fn set_feature(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
        let [CONTROL_REPORT_ID, on @ (0 | 1), lo, hi, ..] = *report else {
            return Err(HidRefusal::new("malformed stream-control report"));
        };
        let mut st = lock(&self.0);
        let rate = u16::from_le_bytes([lo, hi]);
        if rate != 0 && rate != st.device.rate_hz {
            return Err(HidRefusal::new(format!(
                "rate {rate} Hz: this tracker runs at {} Hz",
                st.device.rate_hz
            )));
        }
        st.device.streaming = on == 1;
        Ok(())
    }
}

/// Starts a simulated dioptra tracker serving `source`; the host gets the link. Needs a
/// tokio runtime.
pub fn spawn(source: Box<dyn SampleSource>) -> (MemoryHidLink, SimTracker<TrackerState>) {
    let rate_hz = source.rate_hz().round().clamp(0.0, 65_535.0) as u16;
    let shared = Arc::new(Mutex::new(Streaming {
        device: TrackerState {
            streaming: false,
            rate_hz,
        },
        faults: Default::default(),
        sent: 0,
    }));
    let (link, device) = memory::device(DESCRIPTOR.to_vec(), Behaviour(shared.clone()), 64);
    let task = spawn_serve(device.clone(), source, shared.clone(), |st, s| {
        st.streaming
            .then(|| encode_sample_report(s).map(|r| r.to_vec()))
            .flatten()
    });
    (
        link.named("simulated dioptra tracker"),
        SimTracker {
            shared,
            device,
            task,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_protocol::EyeSample;

    #[test]
    fn the_largest_sample_fits_the_report() {
        let eye = EyeSample {
            origin_mm: [f32::MAX; 3],
            direction: [-1.0; 3],
            pupil_mm: f32::NAN,
            valid: true,
        };
        let s = BinocularSample {
            device_time_us: u64::MAX,
            left: eye,
            right: eye,
        };
        let r = encode_sample_report(&s).unwrap();
        assert_eq!(usize::from(r[1]), MAX_PAYLOAD);
        let back: BinocularSample = postcard::from_bytes(&r[2..]).unwrap();
        assert_eq!(back.device_time_us, u64::MAX);
    }
}
