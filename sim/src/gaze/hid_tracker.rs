//! A simulated HID "Eye and Head Trackers" (usage page 0x12) device: a screen-mounted
//! tracker with a real report descriptor, Capabilities / Configuration / Status / Control
//! feature reports, and Tracking Data input reports built from the generator's rays.
//!
//! Frame: µm from the screen's top-left corner, y down, z the distance in front of the
//! screen. The gaze point is where the cyclopean ray meets the screen plane.

use std::sync::{Arc, Mutex};

use dioptra_protocol::BinocularSample;
use dioptra_transport::hid::memory::{self, HidBehaviour, HidRefusal, MemoryHidLink};

use super::{lock, spawn_serve, SampleSource, SimTracker, Streaming};

pub const TRACKING_ID: u8 = 1;
pub const CAPABILITIES_ID: u8 = 2;
pub const CONFIGURATION_ID: u8 = 3;
pub const STATUS_ID: u8 = 4;
pub const CONTROL_ID: u8 = 5;
/// id + u64 timestamp + 2 + 4 x 3 i32.
pub const TRACKING_LEN: usize = 1 + 8 + 14 * 4;

/// The report descriptor, laid out like Microsoft's GazeHid sample.
#[rustfmt::skip]
pub const DESCRIPTOR: &[u8] = &[
    0x05, 0x12, 0x09, 0x01, 0xa1, 0x01,             // Eye Tracker, Application
    // Tracking Data, input report 1.
    0x85, TRACKING_ID, 0x09, 0x10, 0xa1, 0x02,
    0x15, 0x00, 0x27, 0xff, 0xff, 0xff, 0x7f,       //   logical 0..i32::MAX
    0x09, 0x20, 0x75, 0x40, 0x95, 0x01, 0x81, 0x02, //   Timestamp, 64 bits (µs)
    0x17, 0x00, 0x00, 0x00, 0x80,                   //   logical i32::MIN..
    0x75, 0x20,                                     //   32-bit fields (µm)
    0x09, 0x24, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x95, 0x02, 0x81, 0x02, 0xc0,
    0x09, 0x25, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x95, 0x03, 0x81, 0x02, 0xc0,
    0x09, 0x26, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x95, 0x03, 0x81, 0x02, 0xc0,
    0x09, 0x27, 0xa1, 0x00, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x95, 0x03, 0x81, 0x02, 0xc0,
    0x55, 0x0a, 0x65, 0x14,                         //   micro-degrees
    0x09, 0x28, 0xa1, 0x00, 0x09, 0x29, 0x09, 0x2a, 0x09, 0x2b, 0x95, 0x03, 0x81, 0x02, 0xc0,
    0x55, 0x00, 0x65, 0x00,
    0xc0,
    // Capabilities, feature report 2.
    0x85, CAPABILITIES_ID, 0x09, 0x11, 0xa1, 0x02,
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08, 0x95, 0x01,
    0x0a, 0x00, 0x01, 0xb1, 0x02,                   //   Tracker Quality u8
    0x27, 0xff, 0xff, 0xff, 0x7f, 0x75, 0x20, 0x95, 0x05,
    0x0a, 0x01, 0x01, 0x0a, 0x02, 0x01, 0x0a, 0x03, 0x01, 0x0a, 0x04, 0x01, 0x0a, 0x05, 0x01,
    0xb1, 0x02,                                     //   distances, max screen (µm)
    0xc0,
    // Configuration, feature report 3.
    0x85, CONFIGURATION_ID, 0x09, 0x12, 0xa1, 0x02,
    0x0a, 0x04, 0x02, 0x0a, 0x05, 0x02, 0x75, 0x20, 0x95, 0x02, 0xb1, 0x02,
    0xc0,
    // Status, feature report 4.
    0x85, STATUS_ID, 0x09, 0x13, 0xa1, 0x02,
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08, 0x95, 0x01, 0x0a, 0x01, 0x03, 0xb1, 0x02,
    0x27, 0xff, 0xff, 0x00, 0x00, 0x75, 0x10, 0x0a, 0x00, 0x03, 0xb1, 0x02,
    0xc0,
    // Control, feature report 5.
    0x85, CONTROL_ID, 0x09, 0x14, 0xa1, 0x02,
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08, 0x95, 0x01, 0x0a, 0x00, 0x04, 0xb1, 0x02,
    0xc0,
    0xc0,
];

/// The simulated tracker's setup.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HidTrackerSetup {
    pub screen_width_mm: f64,
    pub screen_height_mm: f64,
    /// Eyes' distance in front of the screen.
    pub viewing_distance_mm: f64,
    /// Status reads that say "configuring" after a mode request.
    pub configuring_polls: u32,
    /// Status before any mode request and after configuring (1 ready, 3 screen setup
    /// needed, 4 user calibration needed).
    pub status_when_done: u8,
    /// False: reading the Configuration report stalls, as on trackers without one set up.
    pub configuration_readable: bool,
}

impl Default for HidTrackerSetup {
    fn default() -> Self {
        HidTrackerSetup {
            screen_width_mm: 600.0,
            screen_height_mm: 340.0,
            viewing_distance_mm: 600.0,
            configuring_polls: 3,
            status_when_done: 1,
            configuration_readable: true,
        }
    }
}

/// The device side of the feature reports.
#[derive(Debug)]
pub struct TrackerState {
    pub setup: HidTrackerSetup,
    pub mode: u8,
    pub polls_left: u32,
    pub rate_hz: u16,
}

impl TrackerState {
    fn status(&self) -> u8 {
        if self.mode != 0 && self.polls_left > 0 {
            2
        } else {
            self.setup.status_when_done
        }
    }
    fn streaming(&self) -> bool {
        self.mode != 0 && self.polls_left == 0 && self.setup.status_when_done == 1
    }
}

fn um(mm: f64) -> i32 {
    (mm * 1000.0)
        .round()
        .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
}

/// Tracking Data report for one sample.
pub fn encode_tracking_report(
    setup: &HidTrackerSetup,
    mode: u8,
    s: &BinocularSample,
) -> [u8; TRACKING_LEN] {
    let (w, h, dist) = (
        setup.screen_width_mm,
        setup.screen_height_mm,
        setup.viewing_distance_mm,
    );
    let mut r = [0u8; TRACKING_LEN];
    r[0] = TRACKING_ID;
    r[1..9].copy_from_slice(&s.device_time_us.to_le_bytes());
    let mut put = |i: usize, v: i32| r[9 + 4 * i..13 + 4 * i].copy_from_slice(&v.to_le_bytes());
    let f = |a: [f32; 3]| a.map(f64::from);
    let eyes: Vec<([f64; 3], [f64; 3])> = [&s.left, &s.right]
        .into_iter()
        .filter(|e| e.valid)
        .map(|e| (f(e.origin_mm), f(e.direction)))
        .collect();
    if !eyes.is_empty() {
        let n = eyes.len() as f64;
        let mid: Vec<f64> = (0..3)
            .map(|k| eyes.iter().map(|e| e.0[k]).sum::<f64>() / n)
            .collect();
        let dir: Vec<f64> = (0..3)
            .map(|k| eyes.iter().map(|e| e.1[k]).sum::<f64>() / n)
            .collect();
        if dir[2] > 1e-6 {
            // Meet the screen plane, `dist` ahead of the eyes.
            let t = (dist - mid[2]) / dir[2];
            let (x, y) = (mid[0] + dir[0] * t, mid[1] + dir[1] * t);
            if mode & 1 != 0 {
                put(0, um(w / 2.0 + x));
                put(1, um(h / 2.0 - y));
            }
        }
    }
    for (k, e) in [&s.left, &s.right].into_iter().enumerate() {
        if e.valid && mode & 2 != 0 {
            let o = f(e.origin_mm);
            put(2 + 3 * k, um(w / 2.0 + o[0]));
            put(3 + 3 * k, um(h / 2.0 - o[1]));
            put(4 + 3 * k, um(dist - o[2]));
        }
    }
    if mode & 4 != 0 {
        put(8, um(w / 2.0));
        put(9, um(h / 2.0));
        put(10, um(dist));
        put(12, 1_500_000); // head turned 1.5 degrees about y
    }
    r
}

struct Behaviour(Arc<Mutex<Streaming<TrackerState>>>);

impl HidBehaviour for Behaviour {
    fn get_feature(&mut self, id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
        let mut st = lock(&self.0);
        let d = &mut st.device;
        let s = d.setup;
        let mut out: Vec<u8> = vec![id];
        match id {
            CAPABILITIES_ID => {
                out.push(2); // quality: fine
                for v in [
                    400.0,
                    s.viewing_distance_mm,
                    900.0,
                    s.screen_width_mm,
                    s.screen_height_mm,
                ] {
                    out.extend(um(v).to_le_bytes());
                }
            }
            CONFIGURATION_ID if !s.configuration_readable => {
                return Err(HidRefusal::new("no screen configured"));
            }
            CONFIGURATION_ID => {
                out.extend(um(s.screen_width_mm).to_le_bytes());
                out.extend(um(s.screen_height_mm).to_le_bytes());
            }
            STATUS_ID => {
                out.push(d.status());
                out.extend(d.rate_hz.to_le_bytes());
                d.polls_left = d.polls_left.saturating_sub(1);
            }
            CONTROL_ID => out.push(d.mode),
            _ => return Err(HidRefusal::new(format!("no feature report {id}"))),
        }
        if buf.len() < out.len() {
            return Err(HidRefusal::new(format!(
                "feature report {id} needs {} bytes",
                out.len()
            )));
        }
        buf[..out.len()].copy_from_slice(&out);
        Ok(out.len())
    }

    fn set_feature(&mut self, report: &[u8]) -> Result<(), HidRefusal> {
        match *report {
            [CONTROL_ID, mode, ..] if mode <= 7 => {
                let mut st = lock(&self.0);
                let d = &mut st.device;
                if mode != d.mode {
                    d.polls_left = d.setup.configuring_polls;
                }
                d.mode = mode;
                Ok(())
            }
            [CONTROL_ID, ..] => Err(HidRefusal::new("unknown mode request bits")),
            _ => Err(HidRefusal::new(
                "only the Control feature report is writable",
            )),
        }
    }
}

/// Starts a simulated page 0x12 tracker serving `source`. Needs a tokio runtime.
pub fn spawn(
    source: Box<dyn SampleSource>,
    setup: HidTrackerSetup,
) -> (MemoryHidLink, SimTracker<TrackerState>) {
    let rate_hz = source.rate_hz().round().clamp(0.0, 65_535.0) as u16;
    let shared = Arc::new(Mutex::new(Streaming {
        device: TrackerState {
            setup,
            mode: 0,
            polls_left: 0,
            rate_hz,
        },
        faults: Default::default(),
        sent: 0,
    }));
    let (link, device) = memory::device(DESCRIPTOR.to_vec(), Behaviour(shared.clone()), 64);
    let task = spawn_serve(device.clone(), source, shared.clone(), |st, s| {
        st.streaming()
            .then(|| encode_tracking_report(&st.setup, st.mode, s).to_vec())
    });
    (
        link.named("simulated HID eye tracker (page 0x12)"),
        SimTracker {
            shared,
            device,
            task,
        },
    )
}
