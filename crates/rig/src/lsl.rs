//! Lab Streaming Layer outlets (`[lsl] enabled = true`): the rig's gaze, lens and events as
//! three LSL streams, for LabRecorder, pylsl and MATLAB beside a lab's other instruments.
//!
//! The loop hands each sample to [`LslOutlets`] as it handles it (a bounded channel: a stalled
//! LSL thread costs samples, counted in `/status`, never the loop's time); one thread owns the
//! liblsl outlets and pushes them. Every sample is stamped on LSL's clock with the time it
//! happened (a gaze sample's mapped device time, a lens command's time on the wire, a frame's
//! time on screen), not when it was pushed.
//!
//! What the streams hold is described by [`stream_specs`] (also `dioptra lsl --list`). liblsl
//! itself comes in with the `lsl` cargo feature; without it, starting a rig with LSL enabled
//! says how to build it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};

use dioptra_core::{lock, Clock, Diopters, GazeSample, LensState, OpticsMap, Timestamp};
use serde::Serialize;
use serde_json::{json, Value};

use crate::devices::config::{Devices, Port};
use crate::devices::LensId;
use crate::problem::Problem;

pub mod config;
pub use config::LslConfig;

/// Whether this build links liblsl.
pub const BUILT_WITH_LSL: bool = cfg!(feature = "lsl");

/// How to get a build with LSL.
pub const HOW_TO_BUILD: &str = "this dioptra was built without Lab Streaming Layer support: \
     rebuild with `cargo build --release --features lsl` (it builds liblsl from source, which \
     needs cmake and a C++ compiler: `apt install cmake g++`)";

/// A channel's description, following the XDF meta-data conventions (for `Gaze` streams:
/// <https://github.com/sccn/xdf/wiki/Gaze-Meta-Data>).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChannelSpec {
    pub label: &'static str,
    /// `left`, `right` or `both` (gaze channels only).
    #[serde(skip_serializing_if = "str::is_empty")]
    pub eye: &'static str,
    #[serde(rename = "type")]
    pub kind: &'static str,
    pub unit: &'static str,
}

/// A stream's sample format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Double64,
    String,
}

/// One outlet's declaration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StreamSpec {
    pub name: String,
    /// LSL's content type.
    #[serde(rename = "type")]
    pub kind: &'static str,
    /// Nominal rate, Hz; 0 for an irregular stream.
    pub rate_hz: f64,
    pub format: Format,
    pub source_id: String,
    pub channels: Vec<ChannelSpec>,
    /// What each sample's LSL timestamp is.
    pub timestamps: &'static str,
}

const fn ch(
    label: &'static str,
    eye: &'static str,
    kind: &'static str,
    unit: &'static str,
) -> ChannelSpec {
    ChannelSpec {
        label,
        eye,
        kind,
        unit,
    }
}

/// The gaze stream's channels, in sample order (see [`gaze_values`]).
pub const GAZE_CHANNELS: [ChannelSpec; 24] = [
    ch("left_direction_x", "left", "DirectionX", "normalized"),
    ch("left_direction_y", "left", "DirectionY", "normalized"),
    ch("left_direction_z", "left", "DirectionZ", "normalized"),
    ch("left_position_x", "left", "PositionX", "mm"),
    ch("left_position_y", "left", "PositionY", "mm"),
    ch("left_position_z", "left", "PositionZ", "mm"),
    ch("left_pupil_diameter", "left", "Diameter", "mm"),
    ch("left_valid", "left", "Confidence", "normalized"),
    ch("right_direction_x", "right", "DirectionX", "normalized"),
    ch("right_direction_y", "right", "DirectionY", "normalized"),
    ch("right_direction_z", "right", "DirectionZ", "normalized"),
    ch("right_position_x", "right", "PositionX", "mm"),
    ch("right_position_y", "right", "PositionY", "mm"),
    ch("right_position_z", "right", "PositionZ", "mm"),
    ch("right_pupil_diameter", "right", "Diameter", "mm"),
    ch("right_valid", "right", "Confidence", "normalized"),
    ch("cyclopean_direction_x", "both", "DirectionX", "normalized"),
    ch("cyclopean_direction_y", "both", "DirectionY", "normalized"),
    ch("cyclopean_direction_z", "both", "DirectionZ", "normalized"),
    ch("cyclopean_valid", "both", "Confidence", "normalized"),
    ch("vergence_depth", "both", "VergenceDepth", "diopters"),
    ch("eye_phase", "both", "EyePhase", "code"),
    ch("device_time", "both", "DeviceTime", "s"),
    ch("host_time", "both", "HostTime", "s"),
];

/// The lens stream's channels (see [`LslOutlets::lens_wire`] and [`LslOutlets::lens_state`]):
/// lens powers, and the focus each gives through the rig's optics map.
pub const LENS_CHANNELS: [ChannelSpec; 6] = [
    ch("event", "", "Event", "code"),
    ch("commanded_power", "", "Power", "diopters"),
    ch("actual_power", "", "Power", "diopters"),
    ch("settled", "", "Flag", "boolean"),
    ch("commanded_focus", "", "Focus", "diopters"),
    ch("actual_focus", "", "Focus", "diopters"),
];

/// Lens stream `event` codes.
pub const LENS_EVENT_COMMANDED: f64 = 1.0;
pub const LENS_EVENT_READ_BACK: f64 = 2.0;

/// The codes of the gaze stream's `eye_phase` channel, in code order.
pub const EYE_PHASES: [&str; 6] = ["unknown", "fixation", "pursuit", "saccade", "blink", "lost"];

/// The outlets a rig with `[lsl]` and `devices` makes, whether or not LSL is enabled in it.
pub fn stream_specs(lsl: &LslConfig, devices: &Devices) -> Vec<StreamSpec> {
    let name = &lsl.name;
    vec![StreamSpec {
        name: format!("{name}-gaze"),
        kind: "Gaze",
        // A real tracker's rate is known only once it is connected: irregular.
        rate_hz: if devices.gaze.port == Port::Sim {
            devices.gaze.sim_rate_hz
        } else {
            0.0
        },
        format: Format::Double64,
        source_id: format!("{name}-gaze"),
        channels: GAZE_CHANNELS.to_vec(),
        timestamps: "the sample's device time mapped to the host timeline (the tracker \
                         driver's clock-offset estimate), on LSL's clock",
    }]
    .into_iter()
    // A lens outlet per lens: `<name>-lens`, or `<name>-lens-left` and `<name>-lens-right`.
    .chain((0..devices.lens.count()).map(|i| {
        let stream = match devices.lens.side(i) {
            None => format!("{name}-lens"),
            Some(eye) => format!("{name}-lens-{}", eye.as_str()),
        };
        StreamSpec {
            name: stream.clone(),
            kind: "Lens",
            rate_hz: 0.0,
            format: Format::Double64,
            source_id: stream,
            channels: LENS_CHANNELS.to_vec(),
            timestamps: "event 1 (commanded): when the command was on the wire; event 2 \
                         (read back): when the lens's reply arrived; on LSL's clock",
        }
    }))
    .chain([StreamSpec {
        name: format!("{name}-markers"),
        kind: "Markers",
        rate_hz: 0.0,
        format: Format::String,
        source_id: format!("{name}-markers"),
        channels: vec![ch("event", "", "Marker", "json")],
        timestamps: "when the event happened: a frame's time on screen, a sub-frame's \
                         start as the sync hardware reports it, a control's or recording's \
                         time of taking effect; on LSL's clock",
    }])
    .collect()
}

/// A sample on its way to an outlet; `t` is on the host timeline.
#[derive(Debug, Clone, PartialEq)]
pub enum LslSample {
    Gaze {
        t: Timestamp,
        values: Vec<f64>,
    },
    /// `lens`: which lens outlet (the lens's index: the one lens, or left then right).
    Lens {
        lens: usize,
        t: Timestamp,
        values: Vec<f64>,
    },
    Marker {
        t: Timestamp,
        text: String,
    },
}

/// Counters for `/status`.
#[derive(Debug, Default)]
struct Counts {
    queued: AtomicU64,
    dropped: AtomicU64,
}

/// What the LSL thread reports.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PushStatus {
    pub pushed: u64,
    /// Outlets with at least one consumer, the last time it looked.
    pub with_consumers: Vec<String>,
    pub last_error: Option<String>,
    /// The newest look at the pushes found an error (the next without one clears it).
    #[serde(skip)]
    pub failing: bool,
}

/// The loop's end of the outlets.
pub struct LslOutlets {
    tx: SyncSender<LslSample>,
    counts: Counts,
    names: Vec<String>,
    pushed: Arc<Mutex<PushStatus>>,
}

/// Samples that may wait for the LSL thread: a few seconds of 1 kHz gaze.
const QUEUE: usize = 8192;

impl LslOutlets {
    /// Starts the outlets `[lsl]` and `devices` declare on an LSL thread of their own.
    pub fn start(
        lsl: &LslConfig,
        devices: &Devices,
        clock: Arc<dyn Clock>,
    ) -> Result<LslOutlets, String> {
        let specs = stream_specs(lsl, devices);
        let (tx, rx) = sync_channel(QUEUE);
        let pushed = Arc::new(Mutex::new(PushStatus::default()));
        outlet_thread(specs.clone(), rx, clock, pushed.clone())?;
        Ok(LslOutlets {
            tx,
            counts: Counts::default(),
            names: specs.into_iter().map(|s| s.name).collect(),
            pushed,
        })
    }

    /// Outlets whose samples go to `rx` instead of liblsl (tests).
    pub fn to_channel(lsl: &LslConfig, devices: &Devices) -> (LslOutlets, Receiver<LslSample>) {
        let (tx, rx) = sync_channel(QUEUE);
        let outlets = LslOutlets {
            tx,
            counts: Counts::default(),
            names: stream_specs(lsl, devices)
                .into_iter()
                .map(|s| s.name)
                .collect(),
            pushed: Arc::default(),
        };
        (outlets, rx)
    }

    fn send(&self, s: LslSample) {
        match self.tx.try_send(s) {
            Ok(()) => {
                self.counts.queued.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                self.counts.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// A gaze sample, with the scheduler's eye phase and fused vergence after it.
    pub fn gaze(&self, g: &GazeSample, phase: &str, vergence_d: Option<f64>) {
        self.send(LslSample::Gaze {
            t: g.host_time,
            values: gaze_values(g, phase, vergence_d),
        });
    }

    /// A command to `lens` on the wire at `wire_time`.
    pub fn lens_wire(
        &self,
        lens: LensId,
        wire_time: Timestamp,
        commanded: Diopters,
        optics: &OpticsMap,
    ) {
        self.send(LslSample::Lens {
            lens: lens.index(),
            t: wire_time,
            values: vec![
                LENS_EVENT_COMMANDED,
                f64::from(commanded.0),
                f64::NAN,
                f64::NAN,
                f64::from(optics.focus_of(commanded).0),
                f64::NAN,
            ],
        });
    }

    /// A read-back of `lens`, with the power last commanded to it.
    pub fn lens_state(
        &self,
        lens: LensId,
        s: &LensState,
        commanded: Option<Diopters>,
        optics: &OpticsMap,
    ) {
        let focus = |p: Diopters| f64::from(optics.focus_of(p).0);
        self.send(LslSample::Lens {
            lens: lens.index(),
            t: s.host_time,
            values: vec![
                LENS_EVENT_READ_BACK,
                commanded.map_or(f64::NAN, |c| f64::from(c.0)),
                f64::from(s.power.0),
                s.settled.map_or(f64::NAN, |b| f64::from(u8::from(b))),
                commanded.map_or(f64::NAN, focus),
                focus(s.power),
            ],
        });
    }

    /// An event marker: `event` names it, `fields` (a JSON object) says the rest.
    pub fn marker(&self, t: Timestamp, event: &str, fields: Value) {
        let mut m = json!({ "event": event });
        if let (Some(o), Value::Object(f)) = (m.as_object_mut(), fields) {
            o.extend(f);
        }
        self.send(LslSample::Marker {
            t,
            text: m.to_string(),
        });
    }

    /// `/status`'s `lsl`.
    pub fn status_json(&self) -> Value {
        let p = lock(&self.pushed).clone();
        json!({
            "streams": self.names,
            "queued": self.counts.queued.load(Ordering::Relaxed),
            "pushed": p.pushed,
            "dropped": self.counts.dropped.load(Ordering::Relaxed),
            "with_consumers": p.with_consumers,
            "last_error": p.last_error,
        })
    }

    /// Pushing to liblsl fails now.
    pub fn problems(&self) -> Vec<Problem> {
        let p = lock(&self.pushed);
        match (p.failing, &p.last_error) {
            (true, Some(e)) => vec![Problem::new(
                "lsl",
                "lsl.enabled",
                format!("pushing samples to the LSL outlets fails: {e}"),
            )],
            _ => Vec::new(),
        }
    }
}

/// The gaze stream's sample for `g` (channels as [`GAZE_CHANNELS`]); values of an invalid eye
/// are NaN.
pub fn gaze_values(g: &GazeSample, phase: &str, vergence_d: Option<f64>) -> Vec<f64> {
    let mut v = Vec::with_capacity(GAZE_CHANNELS.len());
    for eye in [&g.left, &g.right] {
        let ok = |x: f32| if eye.valid { f64::from(x) } else { f64::NAN };
        v.extend(eye.direction.iter().map(|&x| ok(x)));
        v.extend(eye.origin_mm.iter().map(|&x| ok(x)));
        v.push(ok(eye.pupil_mm));
        v.push(f64::from(u8::from(eye.valid)));
    }
    // Cyclopean: the mean direction of the valid eyes.
    let valid: Vec<_> = [&g.left, &g.right]
        .into_iter()
        .filter(|e| e.valid)
        .collect();
    let mut c = [0f64; 3];
    for e in &valid {
        for (ci, d) in c.iter_mut().zip(e.direction) {
            *ci += f64::from(d);
        }
    }
    let norm = c.iter().map(|x| x * x).sum::<f64>().sqrt();
    if valid.is_empty() || norm == 0.0 || !norm.is_finite() {
        v.extend([f64::NAN; 3]);
        v.push(0.0);
    } else {
        v.extend(c.iter().map(|x| x / norm));
        v.push(1.0);
    }
    v.push(vergence_d.unwrap_or(f64::NAN));
    v.push(
        EYE_PHASES
            .iter()
            .position(|p| *p == phase)
            .map_or(0.0, |i| i as f64),
    );
    v.push(g.device_time.0 as f64 * 1e-9);
    v.push(g.host_time.0 as f64 * 1e-9);
    v
}

/// The host timeline on LSL's clock: `lsl = host + offset`. Both count the machine's monotonic
/// clock, so one estimate holds; it is taken from the tightest of a few paired readings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockMap {
    pub offset_s: f64,
}

impl ClockMap {
    /// Pairs `host()` before and after `lsl()` `n` times and keeps the tightest pair's midpoint.
    pub fn estimate(n: usize, mut host: impl FnMut() -> f64, mut lsl: impl FnMut() -> f64) -> Self {
        let mut best = (f64::INFINITY, 0.0);
        for _ in 0..n.max(1) {
            let a = host();
            let l = lsl();
            let b = host();
            if b - a < best.0 {
                best = (b - a, l - (a + b) / 2.0);
            }
        }
        ClockMap { offset_s: best.1 }
    }
    pub fn lsl_time(&self, t: Timestamp) -> f64 {
        t.0 as f64 * 1e-9 + self.offset_s
    }
}

#[cfg(not(feature = "lsl"))]
fn outlet_thread(
    _specs: Vec<StreamSpec>,
    _rx: Receiver<LslSample>,
    _clock: Arc<dyn Clock>,
    _pushed: Arc<Mutex<PushStatus>>,
) -> Result<(), String> {
    Err(HOW_TO_BUILD.into())
}

/// Starts the thread that owns the liblsl outlets; returns once they exist (or could not be
/// made).
#[cfg(feature = "lsl")]
fn outlet_thread(
    specs: Vec<StreamSpec>,
    rx: Receiver<LslSample>,
    clock: Arc<dyn Clock>,
    pushed: Arc<Mutex<PushStatus>>,
) -> Result<(), String> {
    let (ready_tx, ready_rx) = sync_channel(1);
    std::thread::Builder::new()
        .name("dioptra-lsl".into())
        .spawn(move || {
            let outlets = match liblsl::outlets(&specs) {
                Ok(o) => {
                    let _ = ready_tx.send(Ok(()));
                    o
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
            };
            let map = ClockMap::estimate(16, || clock.now().0 as f64 * 1e-9, lsl::local_clock);
            liblsl::push_all(&outlets, &specs, rx, map, &pushed);
        })
        .map_err(|e| format!("cannot start the LSL thread: {e}"))?;
    ready_rx
        .recv()
        .map_err(|_| "the LSL thread ended before making its outlets".to_string())?
}

#[cfg(feature = "lsl")]
mod liblsl {
    use super::*;
    use lsl::ExPushable;

    pub(super) fn outlets(specs: &[StreamSpec]) -> Result<Vec<lsl::StreamOutlet>, String> {
        specs
            .iter()
            .map(|s| {
                let format = match s.format {
                    Format::Double64 => lsl::ChannelFormat::Double64,
                    Format::String => lsl::ChannelFormat::String,
                };
                let mut info = lsl::StreamInfo::new(
                    &s.name,
                    s.kind,
                    s.channels.len() as u32,
                    s.rate_hz,
                    format,
                    &s.source_id,
                )
                .map_err(|e| format!("LSL stream {}: {e:?}", s.name))?;
                let mut desc = info.desc();
                desc.append_child_value("manufacturer", "dioptra");
                desc.append_child_value("timestamps", s.timestamps);
                let mut channels = desc.append_child("channels");
                for c in &s.channels {
                    let mut e = channels.append_child("channel");
                    e.append_child_value("label", c.label);
                    if !c.eye.is_empty() {
                        e.append_child_value("eye", c.eye);
                    }
                    e.append_child_value("type", c.kind);
                    e.append_child_value("unit", c.unit);
                }
                if s.kind == "Gaze" {
                    let mut codes = desc.append_child("eye_phase_codes");
                    for (i, p) in EYE_PHASES.iter().enumerate() {
                        codes.append_child_value(p, &i.to_string());
                    }
                    desc.append_child_value(
                        "coordinate_system",
                        "head frame: +x right, +y up, +z forward; eye positions in mm",
                    );
                }
                lsl::StreamOutlet::new(&info, 0, 360)
                    .map_err(|e| format!("LSL outlet {}: {e:?}", s.name))
            })
            .collect()
    }

    pub(super) fn push_all(
        outlets: &[lsl::StreamOutlet],
        specs: &[StreamSpec],
        rx: Receiver<LslSample>,
        map: ClockMap,
        pushed: &Mutex<PushStatus>,
    ) {
        // Gaze first, markers last, the lens outlets (one per lens) between.
        let (Some(gaze), Some(markers)) = (outlets.first(), outlets.last()) else {
            return;
        };
        let lenses = outlets
            .get(1..outlets.len().saturating_sub(1))
            .unwrap_or(&[]);
        let mut n = 0u64;
        let mut last_look = std::time::Instant::now();
        // Ends when the rig drops its end.
        for s in rx {
            let r = match &s {
                LslSample::Gaze { t, values } => {
                    gaze.push_sample_ex(values, map.lsl_time(*t), true)
                }
                LslSample::Lens { lens, t, values } => match lenses.get(*lens) {
                    Some(o) => o.push_sample_ex(values, map.lsl_time(*t), true),
                    None => continue,
                },
                LslSample::Marker { t, text } => {
                    markers.push_sample_ex(&vec![text.clone()], map.lsl_time(*t), true)
                }
            };
            n += 1;
            let error = r.err().map(|e| format!("{e:?}"));
            if error.is_some() || last_look.elapsed().as_millis() >= 500 {
                last_look = std::time::Instant::now();
                let mut p = lock(pushed);
                p.pushed = n;
                p.failing = error.is_some();
                if error.is_some() {
                    p.last_error = error;
                }
                p.with_consumers = outlets
                    .iter()
                    .zip(specs)
                    .filter(|(o, _)| o.have_consumers())
                    .map(|(_, s)| s.name.clone())
                    .collect();
            }
        }
    }
}

#[cfg(test)]
mod tests;
