//! A simulated HID "Eye and Head Trackers" (usage page 0x12) device: a screen-mounted
//! tracker with a real report descriptor, Capabilities / Configuration / Status / Control
//! feature reports, and Tracking Data input reports built from the generator's rays. It
//! serves one of two descriptors ([`SimLayout`]): one built like Microsoft's reference
//! trackers, and one laid out differently, so the driver is tested on both. Reports are
//! written at the byte offsets each descriptor implies, not through the driver's parser.
//!
//! Frame: µm from the screen's top-left corner, y down, z the distance in front of the
//! screen. The gaze point is where the cyclopean ray meets the screen plane.

use std::sync::{Arc, Mutex};

use dioptra_protocol::BinocularSample;
use dioptra_transport::hid::memory::{self, HidBehaviour, HidRefusal, MemoryHidLink};

use super::{lock, spawn_serve, SampleSource, SimTracker, Streaming};

/// Which report descriptor the simulated tracker serves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SimLayout {
    /// Built like Microsoft's reference trackers (GazeHid, DMF VirtualEyeGaze): report ids
    /// 0x10-0x14, i32 positions in cm with exponent -4 (µm), a µs timestamp, Constant flags
    /// on the gaze point, eye positions and every Capabilities / Configuration field, tracker
    /// quality 0..1 (1 = fine gaze), Configuration with the display id fields.
    #[default]
    Reference,
    /// Another vendor's choice: report ids 1-5, i16 positions in 0.1 mm (cm, exponent -2),
    /// head direction in 0.01 degree, 16-bit Capabilities, Data flags everywhere.
    Compact,
}

impl SimLayout {
    /// (Tracking Data, Capabilities, Configuration, Status, Control) report ids.
    pub const fn report_ids(self) -> [u8; 5] {
        match self {
            SimLayout::Reference => [0x10, 0x11, 0x12, 0x13, 0x14],
            SimLayout::Compact => [1, 2, 3, 4, 5],
        }
    }
    pub fn descriptor(self) -> &'static [u8] {
        match self {
            SimLayout::Reference => DESCRIPTOR,
            SimLayout::Compact => COMPACT_DESCRIPTOR,
        }
    }
    /// Bytes of one position value and of the Tracking Data report (id included).
    const fn position_bytes(self) -> usize {
        match self {
            SimLayout::Reference => 4,
            SimLayout::Compact => 2,
        }
    }
    pub const fn tracking_len(self) -> usize {
        1 + 8 + 14 * self.position_bytes()
    }
    /// A length in µm as the layout's raw value.
    fn length(self, um: f64) -> i64 {
        match self {
            SimLayout::Reference => clamp_raw(um, i64::from(i32::MIN), i64::from(i32::MAX)),
            SimLayout::Compact => clamp_raw(um / 100.0, i64::from(i16::MIN), i64::from(i16::MAX)),
        }
    }
    /// An angle in degrees as the layout's raw value.
    fn angle(self, deg: f64) -> i64 {
        match self {
            SimLayout::Reference => clamp_raw(deg * 1e6, i64::from(i32::MIN), i64::from(i32::MAX)),
            SimLayout::Compact => clamp_raw(deg * 100.0, i64::from(i16::MIN), i64::from(i16::MAX)),
        }
    }
}

fn clamp_raw(v: f64, min: i64, max: i64) -> i64 {
    (v.round() as i64).clamp(min, max)
}

/// [`SimLayout::Reference`]'s report descriptor.
#[rustfmt::skip]
pub const DESCRIPTOR: &[u8] = &[
    0x05, 0x12, 0x09, 0x01, 0xa1, 0x01,             // Eye Tracker, Application
    // Tracking Data, input report 0x10 (Logical collection with the report's usage).
    0x09, 0x10, 0xa1, 0x02, 0x85, 0x10,
    0x15, 0x00, 0x26, 0xff, 0x00, 0x75, 0x08,       //   logical 0..255, 8 bits
    0x09, 0x20, 0x66, 0x01, 0x10, 0x55, 0x0a,       //   Timestamp: SI s, exponent -6 (µs)
    0x95, 0x08, 0x81, 0x02,                         //     8 x 8 bits, one little-endian u64
    0x95, 0x01, 0x75, 0x20, 0x65, 0x11, 0x55, 0x0c, //   32 bits, cm, exponent -4 (µm)
    0x17, 0x80, 0x7b, 0xe1, 0xff,                   //   logical -2 000 000 ..
    0x27, 0x80, 0x84, 0x1e, 0x00,                   //     2 000 000 µm
    0x09, 0x24, 0xa1, 0x00, 0x95, 0x02, 0x09, 0x21, 0x09, 0x22, 0x81, 0x03, 0xc0,
    0x09, 0x25, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x03, 0xc0,
    0x09, 0x26, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x03, 0xc0,
    0x09, 0x27, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x03, 0xc0,
    0x65, 0x14, 0x55, 0x0a,                         //   degrees, exponent -6
    0x17, 0x00, 0x00, 0x00, 0x80, 0x27, 0xff, 0xff, 0xff, 0x7f,
    0x09, 0x28, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x29, 0x09, 0x2a, 0x09, 0x2b, 0x81, 0x03, 0xc0,
    0xc0,
    // Capabilities, feature report 0x11.
    0x09, 0x11, 0xa1, 0x02, 0x85, 0x11,
    0x75, 0x08, 0x95, 0x01, 0x0a, 0x00, 0x01,       //   Tracker Quality, 0..1
    0x15, 0x00, 0x25, 0x01, 0x65, 0x00, 0x55, 0x00, 0xb1, 0x03,
    0xa1, 0x00, 0x95, 0x05, 0x75, 0x20,             //   distances, max screen: i32 µm
    0x17, 0x80, 0x7b, 0xe1, 0xff, 0x27, 0x80, 0x84, 0x1e, 0x00, 0x65, 0x11, 0x55, 0x0c,
    0x0a, 0x01, 0x01, 0x0a, 0x02, 0x01, 0x0a, 0x03, 0x01, 0x0a, 0x04, 0x01, 0x0a, 0x05, 0x01,
    0xb1, 0x03, 0xc0,
    0xc0,
    // Configuration, feature report 0x12.
    0x09, 0x12, 0xa1, 0x02, 0x85, 0x12,
    0x75, 0x10, 0x95, 0x01, 0x15, 0x00, 0x27, 0xff, 0xff, 0x00, 0x00, 0x65, 0x00, 0x55, 0x00,
    0x0a, 0x00, 0x02, 0xb1, 0x03, 0x0a, 0x01, 0x02, 0xb1, 0x03, // display manufacturer, product
    0x75, 0x20, 0x27, 0xff, 0xff, 0xff, 0x7f, 0x0a, 0x02, 0x02, 0xb1, 0x03, // serial
    0x75, 0x10, 0x27, 0xff, 0xff, 0x00, 0x00, 0x0a, 0x03, 0x02, 0xb1, 0x03, // date
    0xa1, 0x00, 0x65, 0x11, 0x55, 0x0c, 0x27, 0xff, 0xff, 0xff, 0x7f, 0x75, 0x20,
    0x0a, 0x04, 0x02, 0xb1, 0x03, 0x0a, 0x05, 0x02, 0xb1, 0x03, 0xc0, // calibrated screen, µm
    0xc0,
    // Status, feature report 0x13.
    0x09, 0x13, 0xa1, 0x02, 0x85, 0x13,
    0x75, 0x08, 0x65, 0x00, 0x55, 0x00, 0x15, 0x00, 0x25, 0x04,
    0x0a, 0x01, 0x03, 0xb1, 0x02,                   //   Configuration Status, 0..4
    0x75, 0x10, 0x27, 0xff, 0xff, 0x00, 0x00, 0x66, 0x01, 0xf0,
    0x0a, 0x00, 0x03, 0xb1, 0x02,                   //   Sampling Frequency, Hz
    0xc0,
    // Control, feature report 0x14.
    0x09, 0x14, 0xa1, 0x02, 0x85, 0x14,
    0x75, 0x08, 0x15, 0x00, 0x25, 0x07, 0x65, 0x00, 0x55, 0x00,
    0x0a, 0x00, 0x04, 0xb1, 0x02,                   //   Mode Request bits
    0xc0,
    0xc0,
];

/// [`SimLayout::Compact`]'s report descriptor.
#[rustfmt::skip]
pub const COMPACT_DESCRIPTOR: &[u8] = &[
    0x05, 0x12, 0x09, 0x01, 0xa1, 0x01,
    0x09, 0x10, 0xa1, 0x02, 0x85, 0x01,             // Tracking Data, input report 1
    0x15, 0x00, 0x27, 0xff, 0xff, 0xff, 0x7f, 0x75, 0x40, 0x95, 0x01,
    0x66, 0x01, 0x10, 0x55, 0x0a, 0x09, 0x20, 0x81, 0x02, //   Timestamp u64, µs
    0x16, 0x00, 0x80, 0x26, 0xff, 0x7f, 0x75, 0x10, //   i16
    0x65, 0x11, 0x55, 0x0e,                         //   cm, exponent -2 (0.1 mm)
    0x09, 0x24, 0xa1, 0x00, 0x95, 0x02, 0x09, 0x21, 0x09, 0x22, 0x81, 0x02, 0xc0,
    0x09, 0x25, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x02, 0xc0,
    0x09, 0x26, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x02, 0xc0,
    0x09, 0x27, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x21, 0x09, 0x22, 0x09, 0x23, 0x81, 0x02, 0xc0,
    0x65, 0x14, 0x55, 0x0e,                         //   degrees, exponent -2
    0x09, 0x28, 0xa1, 0x00, 0x95, 0x03, 0x09, 0x29, 0x09, 0x2a, 0x09, 0x2b, 0x81, 0x02, 0xc0,
    0xc0,
    0x09, 0x11, 0xa1, 0x02, 0x85, 0x02,             // Capabilities, feature report 2
    0x75, 0x08, 0x95, 0x01, 0x15, 0x00, 0x25, 0x01, 0x65, 0x00, 0x55, 0x00,
    0x0a, 0x00, 0x01, 0xb1, 0x02,
    0x75, 0x10, 0x95, 0x05, 0x27, 0xff, 0xff, 0x00, 0x00, 0x65, 0x11, 0x55, 0x0e,
    0x0a, 0x01, 0x01, 0x0a, 0x02, 0x01, 0x0a, 0x03, 0x01, 0x0a, 0x04, 0x01, 0x0a, 0x05, 0x01,
    0xb1, 0x02,                                     //   u16, 0.1 mm
    0xc0,
    0x09, 0x12, 0xa1, 0x02, 0x85, 0x03,             // Configuration, feature report 3
    0x75, 0x10, 0x95, 0x02, 0x0a, 0x04, 0x02, 0x0a, 0x05, 0x02, 0xb1, 0x02,
    0xc0,
    0x09, 0x13, 0xa1, 0x02, 0x85, 0x04,             // Status, feature report 4
    0x75, 0x08, 0x95, 0x01, 0x65, 0x00, 0x55, 0x00, 0x15, 0x00, 0x25, 0x04,
    0x0a, 0x01, 0x03, 0xb1, 0x02,
    0x75, 0x10, 0x27, 0xff, 0xff, 0x00, 0x00, 0x0a, 0x00, 0x03, 0xb1, 0x02,
    0xc0,
    0x09, 0x14, 0xa1, 0x02, 0x85, 0x05,             // Control, feature report 5
    0x75, 0x08, 0x15, 0x00, 0x25, 0x07, 0x0a, 0x00, 0x04, 0xb1, 0x02,
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
    pub layout: SimLayout,
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
            layout: SimLayout::Reference,
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

/// Writes `v` as a little-endian integer of `n` bytes at `at`.
fn put(r: &mut [u8], at: usize, n: usize, v: i64) {
    r[at..at + n].copy_from_slice(&v.to_le_bytes()[..n]);
}

/// Tracking Data report for one sample.
pub fn encode_tracking_report(setup: &HidTrackerSetup, mode: u8, s: &BinocularSample) -> Vec<u8> {
    let layout = setup.layout;
    let (w, h, dist) = (
        setup.screen_width_mm,
        setup.screen_height_mm,
        setup.viewing_distance_mm,
    );
    let n = layout.position_bytes();
    let mut r = vec![0u8; layout.tracking_len()];
    r[0] = layout.report_ids()[0];
    r[1..9].copy_from_slice(&s.device_time_us.to_le_bytes());
    // Value i of the 14 after the timestamp: gaze x, y; left, right, head xyz; head direction.
    let mut pos = |i: usize, mm: f64| put(&mut r, 9 + n * i, n, layout.length(mm * 1000.0));
    let f = |a: [f32; 3]| a.map(f64::from);
    let eyes: Vec<([f64; 3], [f64; 3])> = [&s.left, &s.right]
        .into_iter()
        .filter(|e| e.valid)
        .map(|e| (f(e.origin_mm), f(e.direction)))
        .collect();
    if !eyes.is_empty() {
        let k = eyes.len() as f64;
        let mid: Vec<f64> = (0..3)
            .map(|c| eyes.iter().map(|e| e.0[c]).sum::<f64>() / k)
            .collect();
        let dir: Vec<f64> = (0..3)
            .map(|c| eyes.iter().map(|e| e.1[c]).sum::<f64>() / k)
            .collect();
        if dir[2] > 1e-6 && mode & 1 != 0 {
            // Meet the screen plane, `dist` ahead of the eyes.
            let t = (dist - mid[2]) / dir[2];
            pos(0, w / 2.0 + mid[0] + dir[0] * t);
            pos(1, h / 2.0 - (mid[1] + dir[1] * t));
        }
    }
    for (k, e) in [&s.left, &s.right].into_iter().enumerate() {
        if e.valid && mode & 2 != 0 {
            let o = f(e.origin_mm);
            pos(2 + 3 * k, w / 2.0 + o[0]);
            pos(3 + 3 * k, h / 2.0 - o[1]);
            pos(4 + 3 * k, dist - o[2]);
        }
    }
    if mode & 4 != 0 {
        pos(8, w / 2.0);
        pos(9, h / 2.0);
        pos(10, dist);
        // Head turned 1.5 degrees about y.
        put(&mut r, 9 + n * 12, n, layout.angle(1.5));
    }
    r
}

struct Behaviour(Arc<Mutex<Streaming<TrackerState>>>);

impl HidBehaviour for Behaviour {
    fn get_feature(&mut self, id: u8, buf: &mut [u8]) -> Result<usize, HidRefusal> {
        let mut st = lock(&self.0);
        let d = &mut st.device;
        let s = d.setup;
        let layout = s.layout;
        let [_, caps, config, status, control] = layout.report_ids();
        let um = |mm: f64| layout.length(mm * 1000.0);
        // Capabilities and Configuration values are as wide as the layout's positions.
        let n = layout.position_bytes();
        let mut out: Vec<u8> = vec![id];
        let push = |out: &mut Vec<u8>, n: usize, v: i64| out.extend(&v.to_le_bytes()[..n]);
        if id == caps {
            push(&mut out, 1, 1); // tracker quality: 1 = fine gaze (HUTRR74)
            for v in [
                400.0,
                s.viewing_distance_mm,
                900.0,
                s.screen_width_mm,
                s.screen_height_mm,
            ] {
                push(&mut out, n, um(v));
            }
        } else if id == config && !s.configuration_readable {
            return Err(HidRefusal::new("no screen configured"));
        } else if id == config {
            if layout == SimLayout::Reference {
                // Display manufacturer id, product id, serial number, manufacture date.
                push(&mut out, 2, 0x4453);
                push(&mut out, 2, 0x0001);
                push(&mut out, 4, 1);
                push(&mut out, 2, 0);
            }
            push(&mut out, n, um(s.screen_width_mm));
            push(&mut out, n, um(s.screen_height_mm));
        } else if id == status {
            out.push(d.status());
            out.extend(d.rate_hz.to_le_bytes());
            d.polls_left = d.polls_left.saturating_sub(1);
        } else if id == control {
            out.push(d.mode);
        } else {
            return Err(HidRefusal::new(format!("no feature report {id}")));
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
        let mut st = lock(&self.0);
        let control = st.device.setup.layout.report_ids()[4];
        match *report {
            [id, mode, ..] if id == control && mode <= 7 => {
                let d = &mut st.device;
                if mode != d.mode {
                    d.polls_left = d.setup.configuring_polls;
                }
                d.mode = mode;
                Ok(())
            }
            [id, ..] if id == control => Err(HidRefusal::new("unknown mode request bits")),
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
    let descriptor = setup.layout.descriptor().to_vec();
    let (link, device) = memory::device(descriptor, Behaviour(shared.clone()), 64);
    let task = spawn_serve(device.clone(), source, shared.clone(), |st, s| {
        st.streaming()
            .then(|| encode_tracking_report(&st.setup, st.mode, s))
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
