//! dioptra-rig: the running rig. One implementation that `dioptra serve`, `dioptra hil`, the
//! demo, `dioptra eval --suite loop` and the whole-loop tests all run, so the figures they
//! publish describe the code that drives a rig.
//!
//! - [`config`]: the rig config (`rig.toml`) and its validation.
//! - [`devices`]: one task per device (lens, gaze, sync), opened through the drivers' table
//!   ([`devices::open`]), with one policy for lost links and backoff.
//! - [`executor`]: the loop that steps the scheduler ([`engine`]) and carries out its commands;
//!   [`executor::LoopHook`]s see what it does: the recording, `/status`, the WebSocket and LSL
//!   among them ([`observers`]).
//! - [`content`]: what the rig shows ([`content::Content`]: the procedural scene, a lab's
//!   files, a stream), apart from how it is rendered; the loop hears of each frame when it
//!   arrives.
//! - [`render`]: the render worker's [`render::Renderer`], which renders a job from a content
//!   frame ([`render::rgbd::RgbdRenderer`], the rig's own).
//! - [`display`]: where frames go ([`display::DisplaySink`]; headless here, the window in the
//!   binary), and the marker patch a photodiode watches.
//! - [`photons`]: latency measured in photons (`dioptra hil`): a photodiode's edges matched to
//!   the presents that toggled the marker patch.
//! - [`recording`]: MCAP recordings.
//! - [`devices::simulators`]: the simulated devices of `port = "sim"`; [`simulated_rig`]
//!   (feature `simulated`): a whole rig on simulated devices and tokio's paused clock,
//!   recording ground truth.
//!
//! Everything stops through one [`CancellationToken`] ([`RigState::cancel`]): the loop carries
//! out the scheduler's shutdown (its park command), then the device tasks stop (the lens task
//! parks the lens and waits for it, the sync task stops the sequence), and [`Rig::wait`]
//! finishes the recording.

pub mod api;
pub mod config;
pub mod content;
pub mod devices;
pub mod display;
pub mod engine;
pub mod executor;
pub mod lsl;
pub mod mode;
pub mod observers;
pub mod optics;
pub mod photons;
pub mod recording;
pub mod render;
#[cfg(feature = "simulated")]
pub mod simulated_rig;

use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

use dioptra_core::{lock, Clock, Timestamp};
use dioptra_sched::SchedulerConfig;
use serde::Serialize;
use serde_json::json;
use thiserror::Error;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use config::{ConfigError, Method, Mode, RigConfig};
use content::Content;
use devices::simulators::{SimDevices, SimSpec};
use devices::{DeviceInput, DeviceSettings, LensId, ParkReport, Registry};
use display::{DisplaySink, HeadlessSink};
use engine::Engine;
use executor::LoopHook;
use recording::{ControlRec, Rec, Recorder, RecordingStats, StartRec};
use render::Renderer;

/// Why a rig did not start.
#[derive(Debug, Error)]
pub enum RigError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Content(#[from] content::ContentError),
    #[error("cannot start the renderer: {0}")]
    Renderer(#[source] dioptra_render::RenderError),
    #[error("cannot start the scheduler: {0}")]
    Scheduler(String),
    #[error("method = \"{method}\" in {mode} mode: {why}")]
    NetworkMissing {
        method: &'static str,
        mode: &'static str,
        why: String,
    },
    #[error("cannot start the devices: {0}")]
    Devices(#[source] dioptra_core::DeviceError),
    #[error("the display: {0}")]
    Display(#[source] display::DisplayError),
    #[error("cannot start recording: {0}")]
    Recording(#[source] ControlError),
    #[error("display.kind = \"window\": the window is opened on the main thread by the binary and its sink handed to the rig")]
    WindowSinkNeeded,
    #[error("a rig task failed to start: {0}")]
    Task(String),
    #[error("[lsl] enabled = true: {0}")]
    Lsl(String),
}

/// Why an API command was not carried out.
#[derive(Debug, Error)]
pub enum ControlError {
    /// It conflicts with the rig's state or config (a method that does not fit the mode, no
    /// recording dir, already recording).
    #[error("{0}")]
    Conflict(String),
    #[error("the rig is shutting down; the command was not applied")]
    ShuttingDown,
    /// Something failed on this machine (a file could not be written).
    #[error("{what}: {source}")]
    Failed {
        what: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// A command for the loop (from the API, or a script of the simulated rig).
#[derive(Debug, Clone, PartialEq)]
pub enum Control {
    Mode(Mode),
    Method(Method),
    ManualFocus(Option<f32>),
}

impl Control {
    pub(crate) fn rec(&self) -> ControlRec {
        match self {
            Control::Mode(m) => ControlRec::Mode {
                mode: m.as_str().into(),
            },
            Control::Method(m) => ControlRec::Method {
                method: m.as_str().into(),
            },
            Control::ManualFocus(d) => ControlRec::ManualFocus { diopters: *d },
        }
    }
}

pub(crate) struct ControlMsg {
    pub cmd: LoopCmd,
    pub reply: oneshot::Sender<Result<(), String>>,
}

/// What the API asks of the loop.
pub(crate) enum LoopCmd {
    Control(Control),
    /// Start this recording between two steps, with the scheduler's state then.
    StartRecording(Box<PendingRecording>),
}

/// A recording file made, its `/start` not yet written.
pub(crate) struct PendingRecording {
    pub recorder: Recorder,
    pub start: StartRec,
    pub path: PathBuf,
    pub meta: RecordingMeta,
}

/// What the loop publishes for `GET /status`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoopStatus {
    pub mode: Option<Mode>,
    pub method: Option<Method>,
    pub manual_focus_d: Option<f32>,
    /// The newest lens power the scheduler commanded (the one lens, or the left eye's).
    pub commanded_power_d: Option<f32>,
    /// The newest lens power the lens reported (the one lens, or the left eye's).
    pub lens_power_d: Option<f32>,
    /// Each lens's newest commanded and reported power, by lens id (a lens per eye: left,
    /// right).
    pub commanded_by_lens: [Option<f32>; 2],
    pub reported_by_lens: [Option<f32>; 2],
    /// Whether that read-back had the lens settled at the power commanded.
    pub lens_settled: Option<bool>,
    pub gaze_samples: u64,
    pub lens_commands: u64,
    pub sync_events: u64,
    /// Edges from the photodiode over the marker patch, and edges it reported lost.
    pub light_edges: u64,
    pub light_edges_lost: u64,
    /// Sub-frames the sync hardware started, those with a measured lens power, those whose
    /// power was off its plane by more than [`SUBFRAME_TOLERANCE_D`], and its fault reports.
    pub subframes: u64,
    pub subframes_measured: u64,
    pub subframes_off_target: u64,
    pub subframe_faults: u64,
    pub frames_requested: u64,
    pub frames_shown: u64,
    pub render_errors: u64,
    /// Render errors per method (`gather`, `network`, ...).
    pub render_errors_by_method: std::collections::BTreeMap<String, u64>,
    /// The newest render error.
    pub last_render_error: Option<RenderErrorNote>,
    /// Frames shown unblurred because their render failed.
    pub fallback_frames: u64,
    pub last_render_ms: Option<f64>,
    /// `method = "auto"`: the planner's choice for the newest frame.
    pub planned: Option<render::Planned>,
    pub display: serde_json::Value,
    pub scheduler: serde_json::Value,
}

/// What an experiment calls a recording (`POST /recording/start` body): each part at most
/// 64 characters of letters, digits, `-`, `_` and `.`, so that it can go into a file name.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingMeta {
    pub name: Option<String>,
    pub subject: Option<String>,
    /// A number or a label.
    #[serde(default, deserialize_with = "number_or_text")]
    pub trial: Option<String>,
}

/// A trial: a whole number (0 or more) or a label; anything else is refused saying so.
fn number_or_text<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<String>, D::Error> {
    struct Trial;
    impl<'de> serde::de::Visitor<'de> for Trial {
        type Value = Option<String>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a trial number (a whole number, 0 or more) or a label such as \"3b\"")
        }
        fn visit_u64<E: serde::de::Error>(self, n: u64) -> Result<Self::Value, E> {
            Ok(Some(n.to_string()))
        }
        fn visit_i64<E: serde::de::Error>(self, n: i64) -> Result<Self::Value, E> {
            u64::try_from(n)
                .map(|n| Some(n.to_string()))
                .map_err(|_| E::invalid_value(serde::de::Unexpected::Signed(n), &self))
        }
        fn visit_f64<E: serde::de::Error>(self, n: f64) -> Result<Self::Value, E> {
            Err(E::invalid_value(serde::de::Unexpected::Float(n), &self))
        }
        fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<Self::Value, E> {
            Ok(Some(s.to_string()))
        }
        fn visit_none<E: serde::de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }
        fn visit_unit<E: serde::de::Error>(self) -> Result<Self::Value, E> {
            Ok(None)
        }
        fn visit_some<D2: serde::Deserializer<'de>>(self, d: D2) -> Result<Self::Value, D2::Error> {
            d.deserialize_any(Trial)
        }
    }
    d.deserialize_option(Trial)
}

impl RecordingMeta {
    /// The first part that cannot go into a file name: (key, why).
    pub fn invalid(&self) -> Option<(&'static str, String)> {
        let parts = [
            ("name", &self.name),
            ("subject", &self.subject),
            ("trial", &self.trial),
        ];
        parts.into_iter().find_map(|(key, v)| {
            let v = v.as_deref()?;
            let ok = !v.is_empty()
                && v.len() <= 64
                && !v.starts_with('.')
                && v.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b));
            (!ok).then(|| {
                (
                    key,
                    format!("{v:?}: use 1 to 64 letters, digits, '-', '_' or '.' (not first)"),
                )
            })
        })
    }

    fn file_suffix(&self) -> String {
        let mut s = String::new();
        for (tag, v) in [
            ("", &self.name),
            ("sub-", &self.subject),
            ("trial-", &self.trial),
        ] {
            if let Some(v) = v {
                s += &format!("-{tag}{v}");
            }
        }
        s
    }
}

/// Whether a read-back `s` shows the lens settled at `target_d`, within `tolerance_d` (the
/// scheduler's `settled_tolerance_d`, with which it times settling): `None` without a target;
/// not settled while the lens says it is moving (lenses that do not say, such as the Lens
/// Driver 4, are judged by their power alone).
pub fn lens_settled(
    s: &dioptra_core::LensState,
    target_d: Option<f32>,
    tolerance_d: f32,
) -> Option<bool> {
    let target = target_d?;
    Some(s.settled != Some(false) && (s.power.0 - target).abs() <= tolerance_d)
}

/// A sub-frame's lens power off its plane by more than this is off target (the dioptra sync
/// board's own settle tolerance).
pub const SUBFRAME_TOLERANCE_D: f32 = 0.02;

/// The newest render error, as `/status` shows it.
#[derive(Debug, Clone, Serialize)]
pub struct RenderErrorNote {
    pub frame: u64,
    pub method: String,
    pub kind: &'static str,
    pub error: String,
    pub focus_d: f32,
}

/// State shared by the loop, the API and the device tasks.
pub struct RigState {
    pub cfg: Arc<RigConfig>,
    pub registry: Arc<Registry>,
    pub settings: DeviceSettings,
    pub status: Mutex<LoopStatus>,
    /// JSON text messages for the API's WebSocket (`GET /stream`).
    pub websocket: broadcast::Sender<Arc<str>>,
    pub recording: Mutex<Option<Recorder>>,
    pub cancel: CancellationToken,
    /// The wall-clock time (UTC, ns since the Unix epoch) of the host timeline's zero, read
    /// at start; `None` on a simulated clock. Host time `t` happened at `wall_zero_ns + t`.
    pub wall_zero_ns: Option<u64>,
    /// What the host timeline counts.
    pub clock_source: &'static str,
    /// What the rig shows (`/status`'s `content`; the API's frame endpoints).
    pub content: Arc<dyn Content>,
    /// What renders the frames (`/status`'s `render`).
    pub renderer: Arc<dyn Renderer>,
    /// A stereo layout: each eye's view of the content (`/status`'s `eye_views`).
    pub eye_views: Option<Arc<content::stereo::EyeViews>>,
    /// `method = "auto"` (config or API): the planner chooses each varifocal frame's method.
    pub auto_method: std::sync::atomic::AtomicBool,
    /// Fires when every lens task has parked its lens (or given up) and ended: after this,
    /// exiting the process leaves the lenses safe.
    pub lens_parked: CancellationToken,
    pub clock: Arc<dyn Clock>,
    /// The simulated devices (none on a hardware rig); set once the devices start.
    pub sims: OnceLock<SimDevices>,
    /// Lab Streaming Layer outlets (`[lsl] enabled = true`).
    pub lsl: Option<lsl::LslOutlets>,
    /// Focus <-> lens command for the rig's lens (the one lens, or the left eye's): the
    /// scheduler's map (`/status`, recordings, the WebSocket and LSL say what focus a lens
    /// power gives through it). See [`RigState::optics_of`].
    pub optics: dioptra_core::OpticsMap,
    /// The marker patch's requests from outside the loop (an API marker; `dioptra hil`'s hold).
    pub marker: display::MarkerControl,
    /// The right eye's lens's map, on a rig with a lens per eye.
    pub optics_right: Option<dioptra_core::OpticsMap>,
    controls: mpsc::Sender<ControlMsg>,
    started: Timestamp,
}

impl RigState {
    /// The focus range each lens's range gives its eye through its optics map, nearest last:
    /// the one lens's, or the left's then the right's.
    pub fn focus_ranges_d(&self) -> Vec<[f32; 2]> {
        std::iter::once(&self.optics)
            .chain(self.optics_right.as_ref())
            .map(|o| {
                let r = o.range();
                let (a, b) = (o.focus_of(r.min).0, o.focus_of(r.max).0);
                [a.min(b), a.max(b)]
            })
            .collect()
    }

    /// The focus range the lens range gives through the optics map, nearest last; with a lens
    /// per eye, the range both eyes' lenses reach (`None`: they reach no focus in common, as
    /// with prescriptions further apart than the lens range).
    pub fn focus_range_d(&self) -> Option<[f32; 2]> {
        let r = self
            .focus_ranges_d()
            .into_iter()
            .fold([f32::MIN, f32::MAX], |acc, r| {
                [acc[0].max(r[0]), acc[1].min(r[1])]
            });
        (r[0] <= r[1]).then_some(r)
    }

    pub fn status_json(&self) -> serde_json::Value {
        let now = self.clock.now();
        let status = lock(&self.status).clone();
        let recording = lock(&self.recording)
            .as_ref()
            .map(|r| r.path().display().to_string());
        json!({
            "uptime_s": now.saturating_since(self.started).as_secs_f64(),
            "host_ns": now.0,
            "mode": status.mode,
            "method": if self.auto_method.load(std::sync::atomic::Ordering::Relaxed) {
                json!("auto")
            } else {
                json!(status.method)
            },
            "planned": status.planned.as_ref().map(|p| json!({
                "method": p.choice,
                "predicted_fovea_psnr_db": p.predicted_psnr_db,
                "why": p.why,
            })),
            "focus": self.focus_json(&status),
            "optics": self.optics_json(&status),
            "content": self.content.status(),
            "render": self.renderer.backend_status(),
            "eye_views": self.eye_views.as_ref().map(|v| v.status()),
            "clock": {
                "source": self.clock_source,
                "wall_zero_ns": self.wall_zero_ns,
            },
            "devices": self.registry.snapshot(),
            "device_tasks": self.settings,
            "counts": {
                "gaze_samples": status.gaze_samples,
                "lens_commands": status.lens_commands,
                "sync_events": status.sync_events,
                "frames_requested": status.frames_requested,
                "frames_shown": status.frames_shown,
                "render_errors": status.render_errors,
                "fallback_frames": status.fallback_frames,
            },
            "subframes": {
                "started": status.subframes,
                "measured": status.subframes_measured,
                "off_target": status.subframes_off_target,
                "off_target_rate": (status.subframes_measured > 0)
                    .then(|| status.subframes_off_target as f64 / status.subframes_measured as f64),
                "tolerance_d": SUBFRAME_TOLERANCE_D,
                "faults": status.subframe_faults,
                "lens_measured_by": self.subframe_measurement(),
            },
            "render_errors": {
                "by_method": status.render_errors_by_method,
                "last": status.last_render_error,
            },
            "last_render_ms": status.last_render_ms,
            "display": status.display,
            "scheduler": status.scheduler,
            "recording": recording,
            "lsl": self.lsl.as_ref().map(|l| l.status_json()),
            "sim_lens": self.sim_lens_json(),
        })
    }

    /// `/status`'s `focus`: the one lens's, or the left eye's; with a lens per eye, each
    /// eye's under `left` and `right` (commanded and reported power, the focus each gives
    /// through that eye's optics map, and the lens's link).
    fn focus_json(&self, status: &LoopStatus) -> serde_json::Value {
        let focus_of = |lens: LensId, p: Option<f32>| {
            p.map(|p| self.optics_of(lens).focus_of(dioptra_core::Diopters(p)).0)
        };
        let mut focus = json!({
            "manual_d": status.manual_focus_d,
            "commanded_d": status.commanded_power_d,
            "commanded_focus_d": focus_of(LensId::FIRST, status.commanded_power_d),
            "lens_d": status.lens_power_d,
            "lens_focus_d": focus_of(LensId::FIRST, status.lens_power_d),
            "lens_settled": status.lens_settled,
            "lens_range_d": [self.cfg.optics.lens_range.min, self.cfg.optics.lens_range.max],
            "focus_range_d": self.focus_range_d(),
        });
        let lenses = &self.cfg.devices.lens;
        if lenses.count() > 1 {
            let devices = self.registry.snapshot();
            for i in 0..lenses.count() {
                let Some(side) = lenses.side(i) else { continue };
                let lens = LensId(i as u8);
                let link = devices.get(&lenses.name(i)).map(|d| d.state);
                focus[side.as_str()] = json!({
                    "commanded_d": status.commanded_by_lens[i],
                    "commanded_focus_d": focus_of(lens, status.commanded_by_lens[i]),
                    "lens_d": status.reported_by_lens[i],
                    "lens_focus_d": focus_of(lens, status.reported_by_lens[i]),
                    "link": link,
                });
            }
        }
        focus
    }

    /// `/status`'s `optics`: the map of the one lens, or each eye's.
    fn optics_json(&self, status: &LoopStatus) -> serde_json::Value {
        let one = |lens: LensId, power: Option<f32>| {
            let o = self.optics_of(lens);
            json!({
                "source": o.source_name(),
                "map": o.describe(),
                "magnification": power.and_then(|p| o.magnification(dioptra_core::Diopters(p))),
            })
        };
        let lenses = &self.cfg.devices.lens;
        if lenses.count() == 1 {
            let mut v = one(LensId::FIRST, status.lens_power_d);
            v["eyes"] = json!("one map: this rig has one lens ([devices.lens])");
            return v;
        }
        let mut v = json!({ "eyes": "a map per eye: this rig has a lens per eye" });
        for i in 0..lenses.count() {
            if let Some(side) = lenses.side(i) {
                v[side.as_str()] = one(LensId(i as u8), status.reported_by_lens[i]);
            }
        }
        v
    }

    /// The optics map of `lens` (the one lens, or an eye's).
    pub fn optics_of(&self, lens: LensId) -> &dioptra_core::OpticsMap {
        match (lens.0, &self.optics_right) {
            (1, Some(o)) => o,
            _ => &self.optics,
        }
    }

    /// `/status`'s `sim_lens`: where each simulated lens really is.
    fn sim_lens_json(&self) -> serde_json::Value {
        let Some(sims) = self.sims.get() else {
            return serde_json::Value::Null;
        };
        let one = |slot: Option<&devices::simulators::SimSlot>| -> serde_json::Value {
            let Some(slot) = slot else {
                return serde_json::Value::Null;
            };
            let Some(lens) = slot.lens.as_ref() else {
                return serde_json::Value::Null;
            };
            let m = lens.model();
            json!({
                "power_d": m.power().0,
                "target_d": m.target_power().0,
                "settled": m.settled(),
                "plugged": slot.plug.is_plugged(),
            })
        };
        let lenses = &self.cfg.devices.lens;
        if lenses.count() == 1 {
            return one(sims.lenses.first().and_then(Option::as_ref));
        }
        let mut out = json!({});
        for i in 0..lenses.count() {
            if let Some(side) = lenses.side(i) {
                out[side.as_str()] = one(sims.lenses.get(i).and_then(Option::as_ref));
            }
        }
        out
    }

    /// What measures the multifocal lens at each sub-frame (`/status` `subframes`): the
    /// dioptra sync board reads it back; a DLPC350 only sequences, so nothing confirms the
    /// planes were reached and `measured` stays 0.
    fn subframe_measurement(&self) -> Option<&'static str> {
        let sync = self.cfg.devices.sync.as_ref()?;
        Some(match sync.driver {
            config::SyncDriver::Sync => "the sync board's lens read-back at each sub-frame",
            config::SyncDriver::Dlpc350 => {
                "nothing: the DLPC350 sequences the planes but reports no lens power, so \
                 measured stays 0; a photodiode or the lens's own read-back is needed to \
                 confirm the planes were reached"
            }
        })
    }

    /// Hands a command to the loop and waits for its answer.
    pub async fn control(&self, cmd: Control) -> Result<(), ControlError> {
        let (reply, rx) = oneshot::channel();
        self.controls
            .send(ControlMsg {
                cmd: LoopCmd::Control(cmd),
                reply,
            })
            .await
            .map_err(|_| ControlError::ShuttingDown)?;
        rx.await
            .map_err(|_| ControlError::ShuttingDown)?
            .map_err(ControlError::Conflict)
    }

    pub(crate) fn record(&self, t: Timestamp, rec: Rec) {
        if let Some(r) = lock(&self.recording).as_ref() {
            r.record(t, rec);
        }
    }

    /// Sends a `/stream` message, made only when someone listens. Its `host_ns` is when the
    /// event happened (the message's own, else now); `wall_ns` the wall clock (UTC) when it
    /// was sent (none on a simulated clock).
    pub(crate) fn publish(&self, msg: impl FnOnce() -> serde_json::Value) {
        if self.websocket.receiver_count() > 0 {
            let mut m = msg();
            if let Some(o) = m.as_object_mut() {
                o.entry("host_ns").or_insert(json!(self.clock.now().0));
                o.insert(
                    "wall_ns".into(),
                    json!(self.wall_zero_ns.is_some().then(wall_ns)),
                );
            }
            let _ = self.websocket.send(Arc::from(m.to_string()));
        }
    }

    /// A lab's marker (`POST /marker`: a trial's onset, a response): recorded (`/marker`),
    /// sent on `/stream` and to LSL's marker outlet, stamped with the host time now, which it
    /// returns.
    pub fn lab_marker(&self, marker: serde_json::Value) -> Timestamp {
        let t = self.clock.now();
        if let Some(l) = &self.lsl {
            l.marker(t, "marker", json!({ "marker": marker }));
        }
        self.publish(|| json!({ "type": "marker", "host_ns": t.0, "marker": marker.clone() }));
        self.record(t, Rec::Marker(recording::MarkerRec { marker }));
        t
    }

    /// Starts a recording in `recording.dir` now, from this thread; returns its path. The
    /// scheduler's state is not in it: for a recording started mid-run, use
    /// [`RigState::start_recording_mid_run`], which a replay can check.
    pub fn start_recording(&self, from_start: bool) -> Result<PathBuf, ControlError> {
        self.start_recording_with(from_start, &RecordingMeta::default())
    }

    /// [`RigState::start_recording`] with the experiment's names, which go into the file
    /// name and the `/start` message.
    pub fn start_recording_with(
        &self,
        from_start: bool,
        meta: &RecordingMeta,
    ) -> Result<PathBuf, ControlError> {
        let (r, path) = self.open_recording(meta)?;
        let start = self.start_rec(from_start, meta);
        self.install_recording(r, start, &path, meta, self.clock.now())?;
        Ok(path)
    }

    /// Starts a recording while the rig runs (`POST /recording/start`): the loop writes its
    /// `/start` between two steps, with the scheduler's state and the depth it has then, and
    /// records every input after it, so `dioptra replay` starts where the run was and can
    /// compare every command.
    pub async fn start_recording_mid_run(
        &self,
        meta: &RecordingMeta,
    ) -> Result<PathBuf, ControlError> {
        let (recorder, path) = self.open_recording(meta)?;
        let start = self.start_rec(false, meta);
        let (reply, rx) = oneshot::channel();
        let pending = PendingRecording {
            recorder,
            start,
            path: path.clone(),
            meta: meta.clone(),
        };
        let sent = self
            .controls
            .send(ControlMsg {
                cmd: LoopCmd::StartRecording(Box::new(pending)),
                reply,
            })
            .await;
        let answer = match sent {
            Ok(()) => rx.await.map_err(|_| ControlError::ShuttingDown),
            Err(_) => Err(ControlError::ShuttingDown),
        };
        match answer {
            Ok(Ok(())) => Ok(path),
            Ok(Err(why)) => {
                let _ = std::fs::remove_file(&path);
                Err(ControlError::Conflict(why))
            }
            Err(e) => {
                let _ = std::fs::remove_file(&path);
                Err(e)
            }
        }
    }

    /// A new recording file in `recording.dir`, named after `meta`.
    fn open_recording(&self, meta: &RecordingMeta) -> Result<(Recorder, PathBuf), ControlError> {
        let Some(rc) = &self.cfg.recording else {
            return Err(ControlError::Conflict(
                "the rig config has no [recording] section with a dir; add one to record".into(),
            ));
        };
        if let Some(r) = lock(&self.recording).as_ref() {
            return Err(ControlError::Conflict(format!(
                "already recording to {}",
                r.path().display()
            )));
        }
        std::fs::create_dir_all(&rc.dir).map_err(|e| ControlError::Failed {
            what: format!("cannot create {}", rc.dir.display()),
            source: Box::new(e),
        })?;
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        let stem = format!("dioptra-{}{}", stamp.as_secs(), meta.file_suffix());
        let mut path = rc.dir.join(format!("{stem}.mcap"));
        let mut n = 1;
        while path.exists() {
            path = rc.dir.join(format!("{stem}-{n}.mcap"));
            n += 1;
        }
        let r = Recorder::start(&path, self.cfg.devices.lens.count() > 1).map_err(|e| {
            ControlError::Failed {
                what: "cannot start the recording".into(),
                source: Box::new(e),
            }
        })?;
        Ok((r, path))
    }

    /// The `/start` message: the rig config and what the rig is doing.
    fn start_rec(&self, from_start: bool, meta: &RecordingMeta) -> StartRec {
        let st = lock(&self.status).clone();
        StartRec {
            config: toml::to_string(self.cfg.as_ref()).unwrap_or_default(),
            mode: st.mode.unwrap_or(self.cfg.mode).as_str().into(),
            method: st.method.unwrap_or(self.cfg.method).as_str().into(),
            manual_focus_d: st.manual_focus_d,
            from_start,
            device_tasks: serde_json::to_value(self.settings).unwrap_or_default(),
            wall_zero_ns: self.wall_zero_ns,
            clock: self.clock_source.into(),
            calibration_tables: self
                .cfg
                .calibration_tables
                .iter()
                .map(|(p, t)| (p.display().to_string(), t.clone()))
                .collect(),
            name: meta.name.clone(),
            subject: meta.subject.clone(),
            trial: meta.trial.clone(),
            scheduler_state: None,
            depth_scene_ns: None,
        }
    }

    /// Writes `/start` at `t` and makes `r` the recording every message goes to.
    pub(crate) fn install_recording(
        &self,
        r: Recorder,
        start: StartRec,
        path: &std::path::Path,
        meta: &RecordingMeta,
        t: Timestamp,
    ) -> Result<(), ControlError> {
        {
            let mut slot = lock(&self.recording);
            if let Some(other) = slot.as_ref() {
                let why = format!("already recording to {}", other.path().display());
                drop(r);
                let _ = std::fs::remove_file(path);
                return Err(ControlError::Conflict(why));
            }
            r.record(t, Rec::Start(start));
            *slot = Some(r);
        }
        self.publish(|| {
            json!({
                "type": "recording",
                "event": "start",
                "path": path.display().to_string(),
                "name": meta.name,
                "subject": meta.subject,
                "trial": meta.trial,
            })
        });
        if let Some(l) = &self.lsl {
            l.marker(
                t,
                "recording_start",
                json!({
                    "path": path.display().to_string(),
                    "name": meta.name,
                    "subject": meta.subject,
                    "trial": meta.trial,
                }),
            );
        }
        Ok(())
    }

    /// Finishes the recording in progress.
    pub async fn stop_recording(&self) -> Result<RecordingStats, ControlError> {
        let r = lock(&self.recording)
            .take()
            .ok_or_else(|| ControlError::Conflict("not recording".into()))?;
        let path = r.path().display().to_string();
        self.publish(|| json!({ "type": "recording", "event": "stop", "path": path }));
        if let Some(l) = &self.lsl {
            l.marker(self.clock.now(), "recording_stop", json!({ "path": path }));
        }
        r.finish().await.map_err(|e| ControlError::Failed {
            what: "cannot finish the recording".into(),
            source: Box::new(e),
        })
    }
}

/// What a rig is made of. [`RigSetup::new`] is a rig as its config describes it (what `dioptra
/// serve` runs); the simulated-rig builder and `dioptra hil` change only what they name.
pub struct RigSetup {
    pub cfg: RigConfig,
    /// The rig's clock (default tokio's: wall time, or simulated time under a paused runtime).
    pub clock: Option<Arc<dyn Clock>>,
    /// Default: the content `[content]` describes (the procedural scene of
    /// `display.scene_seed` without one).
    pub content: Option<Arc<dyn Content>>,
    /// Default: [`render::rgbd::RgbdRenderer`] of the config.
    pub renderer: Option<Arc<dyn Renderer>>,
    /// Default: the headless sink (`display.kind = "window"` needs the binary's window sink).
    pub sink: Option<Box<dyn DisplaySink>>,
    /// Default: [`SimSpec::from_config`].
    pub sim: Option<SimSpec>,
    /// Default: [`engine::sched_config`] of the config.
    pub scheduler: Option<SchedulerConfig>,
    pub hooks: Vec<Box<dyn LoopHook>>,
    /// The clock is simulated (a paused runtime): its times have no wall-clock anchor.
    pub simulated_time: bool,
    /// Default: liblsl's outlets when `[lsl] enabled = true` (tests hand in
    /// [`lsl::LslOutlets::to_channel`]).
    pub lsl: Option<lsl::LslOutlets>,
}

impl RigSetup {
    pub fn new(cfg: RigConfig) -> RigSetup {
        RigSetup {
            cfg,
            clock: None,
            content: None,
            renderer: None,
            sink: None,
            sim: None,
            scheduler: None,
            hooks: Vec::new(),
            simulated_time: false,
            lsl: None,
        }
    }
}

/// Nanoseconds since the Unix epoch (UTC) now.
fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// How the rig stopped.
#[derive(Debug, Clone, Serialize)]
pub struct ShutdownReport {
    /// The one lens, or the left eye's.
    pub park: Option<ParkReport>,
    /// The right eye's lens, on a rig with a lens per eye.
    pub park_right: Option<ParkReport>,
    /// Whether the rig has a lens per eye (then `park_right` must report too).
    pub lens_per_eye: bool,
    pub recording: Option<Result<RecordingStats, String>>,
    pub task_errors: Vec<String>,
}

impl ShutdownReport {
    pub fn problems(&self) -> Vec<String> {
        let mut p = self.task_errors.clone();
        for (name, park) in self.parks() {
            match park {
                Some(ParkReport { error: Some(e), .. }) => p.push(format!("{name}: {e}")),
                None => p.push(format!("the {name} task did not report")),
                _ => {}
            }
        }
        if let Some(Err(e)) = &self.recording {
            p.push(e.clone());
        }
        p
    }
    pub fn ok(&self) -> bool {
        self.problems().is_empty()
    }
    /// Each lens's park report, by name (`lens`, or `left lens` and `right lens`).
    fn parks(&self) -> Vec<(&'static str, &Option<ParkReport>)> {
        if self.lens_per_eye {
            vec![("left lens", &self.park), ("right lens", &self.park_right)]
        } else {
            vec![("lens", &self.park)]
        }
    }

    pub fn summary(&self) -> String {
        let parks: Vec<String> = self
            .parks()
            .into_iter()
            .map(|(name, park)| match park {
                Some(ParkReport {
                    park_power,
                    reported_power: Some(r),
                    error: None,
                }) => format!("{name} parked at {park_power} D (reports {r:.3} D)"),
                Some(ParkReport { error: Some(e), .. }) => format!("{name}: {e}"),
                _ => format!("{name}: no report"),
            })
            .collect();
        let mut s = parks.join("; ");
        match &self.recording {
            Some(Ok(r)) => {
                s += &format!(
                    "; recording {} finished ({} messages, {} dropped)",
                    r.path.display(),
                    r.messages,
                    r.dropped
                )
            }
            Some(Err(e)) => s += &format!("; recording failed: {e}"),
            None => {}
        }
        s
    }
}

/// A running rig.
pub struct Rig {
    state: Arc<RigState>,
    /// Each lens task's park report, in lens order.
    lens: tokio::task::JoinHandle<Vec<Result<ParkReport, tokio::task::JoinError>>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    looper: tokio::task::JoinHandle<()>,
    devices_stop: CancellationToken,
}

/// Device inputs the loop has not taken yet; beyond this a gaze task waits.
const INPUT_QUEUE: usize = 4096;

impl Rig {
    /// Validates the config, makes the renderer (in a blocking thread: the scene is ray cast),
    /// and starts the device tasks and the loop. Needs a tokio runtime.
    pub async fn start(setup: RigSetup) -> Result<Rig, RigError> {
        let RigSetup {
            cfg,
            clock,
            content,
            renderer,
            sink,
            sim,
            scheduler,
            hooks,
            simulated_time,
            lsl,
        } = setup;
        cfg.validate()?;
        let cfg = Arc::new(cfg);
        let clock: Arc<dyn Clock> =
            clock.unwrap_or_else(|| Arc::new(dioptra_sim::tokio_clock::TokioClock::new()));
        let lsl = match lsl {
            Some(l) => Some(l),
            None if cfg.lsl.enabled && simulated_time => {
                return Err(RigError::Lsl(
                    "this run is on simulated time, which LSL's clock cannot follow; LSL \
                     outlets run with `dioptra serve`"
                        .into(),
                ))
            }
            None if cfg.lsl.enabled => Some(
                lsl::LslOutlets::start(&cfg.lsl, &cfg.devices, clock.clone())
                    .map_err(RigError::Lsl)?,
            ),
            None => None,
        };
        let content: Arc<dyn Content> = match content {
            Some(c) => c,
            None => {
                let c = cfg.clone();
                let pacing = if simulated_time {
                    content::scene::Pacing::Simulated
                } else {
                    content::scene::Pacing::RealTime
                };
                tokio::task::spawn_blocking(move || {
                    content::open(&c.content, &c.display, &c.eye, &c.api, pacing)
                })
                .await
                .map_err(|e| RigError::Task(e.to_string()))??
            }
        };
        let renderer: Arc<dyn Renderer> = match renderer {
            Some(r) => r,
            None => {
                let c = cfg.clone();
                let r = tokio::task::spawn_blocking(move || {
                    render::rgbd::RgbdRenderer::new(&c.render, &c.eye, &c.display, &c.optics)
                })
                .await
                .map_err(|e| RigError::Task(e.to_string()))?
                .map_err(RigError::Renderer)?;
                Arc::new(r)
            }
        };
        let mut engine = match scheduler {
            Some(s) => Engine::with_config(s),
            None => Engine::new(&cfg),
        }
        .map_err(RigError::Scheduler)?;
        let network_missing = renderer.network_missing();
        if let Some((_, _, why)) = network_missing
            .iter()
            .find(|(m, r, _)| *m == cfg.mode && *r == cfg.method.0)
        {
            return Err(RigError::NetworkMissing {
                method: cfg.method.as_str(),
                mode: cfg.mode.as_str(),
                why: why.clone(),
            });
        }
        engine.set_network_missing(network_missing);
        let sink: Box<dyn DisplaySink> = match (sink, cfg.display.kind) {
            (Some(s), _) => s,
            (None, config::SinkKind::Headless) => {
                Box::new(HeadlessSink::for_display(&cfg.display).map_err(RigError::Display)?)
            }
            (None, config::SinkKind::Window) => return Err(RigError::WindowSinkNeeded),
        };
        let spec = match sim {
            Some(s) => s,
            None => SimSpec::from_config(&cfg, engine.scheduler().config().display.latency)?,
        };
        let settings = DeviceSettings::from_config(&cfg.devices);
        let (controls_tx, controls_rx) = mpsc::channel(64);
        let (websocket, _) = broadcast::channel(1024);
        let registry = Arc::new(Registry::default());
        let state = Arc::new(RigState {
            optics: engine.scheduler().config().optics.clone(),
            optics_right: engine
                .scheduler()
                .config()
                .right_lens
                .as_ref()
                .map(|r| r.optics.clone()),
            registry: registry.clone(),
            settings,
            status: Mutex::new(LoopStatus {
                display: sink.status(),
                ..Default::default()
            }),
            sims: OnceLock::new(),
            lsl,
            websocket,
            recording: Mutex::new(None),
            cancel: CancellationToken::new(),
            lens_parked: CancellationToken::new(),
            auto_method: std::sync::atomic::AtomicBool::new(cfg.auto_method),
            content: content.clone(),
            renderer: renderer.clone(),
            eye_views: match cfg.display.stereo() {
                true => Some(Arc::new(
                    content::stereo::EyeViews::new(&cfg.eye, &cfg.display)
                        .map_err(RigError::Renderer)?,
                )),
                false => None,
            },
            wall_zero_ns: (!simulated_time).then(|| wall_ns().saturating_sub(clock.now().0)),
            clock_source: if simulated_time {
                "simulated time (tokio's paused clock), from the run's start"
            } else {
                "the host's monotonic clock (CLOCK_MONOTONIC, through tokio), from daemon start"
            },
            clock: clock.clone(),
            marker: display::MarkerControl::default(),
            controls: controls_tx,
            started: clock.now(),
            cfg: cfg.clone(),
        });
        if cfg.recording.as_ref().is_some_and(|r| r.start) {
            state.start_recording(true).map_err(RigError::Recording)?;
        }
        let (dev_tx, dev_rx) = mpsc::channel::<DeviceInput>(INPUT_QUEUE);
        let devices_stop = CancellationToken::new();
        let (sims, links, dtasks) = devices::spawn_devices(
            &cfg,
            &spec,
            settings,
            &registry,
            clock,
            dev_tx,
            &devices_stop,
        )
        .map_err(RigError::Devices)?;
        let _ = state.sims.set(sims);
        let panel_feed = spec
            .panel
            .clone()
            .map(|p| Box::new(observers::PanelFeed(p)) as Box<dyn LoopHook>);
        let looper = tokio::spawn(executor::run_loop(executor::LoopParts {
            state: state.clone(),
            engine,
            content,
            renderer,
            sink,
            links,
            inputs: dev_rx,
            controls: controls_rx,
            hooks: observers::standard(&state)
                .into_iter()
                .chain(panel_feed)
                .chain(hooks)
                .collect(),
            devices_stop: devices_stop.clone(),
        }));
        let (lens_tasks, parked) = (dtasks.lenses, state.lens_parked.clone());
        let lens = tokio::spawn(async move {
            let mut reports = Vec::new();
            for t in lens_tasks {
                reports.push(t.await);
            }
            parked.cancel();
            reports
        });
        Ok(Rig {
            state,
            lens,
            tasks: dtasks.others,
            looper,
            devices_stop,
        })
    }

    pub fn state(&self) -> &Arc<RigState> {
        &self.state
    }

    /// Waits until the rig is told to stop ([`RigState::cancel`]), then lets the loop carry
    /// out the scheduler's shutdown, parks the lens, stops every device task and finishes
    /// the recording.
    pub async fn wait(self) -> ShutdownReport {
        let Rig {
            state,
            lens,
            tasks,
            looper,
            devices_stop,
        } = self;
        state.cancel.cancelled().await;
        let mut task_errors = Vec::new();
        if let Err(e) = looper.await {
            task_errors.push(format!("the loop task failed: {e}"));
        }
        // Normally the loop did this after its shutdown step.
        devices_stop.cancel();
        let mut parks = match lens.await {
            Ok(reports) => reports
                .into_iter()
                .map(|r| {
                    r.map_err(|e| task_errors.push(format!("a lens task failed: {e}")))
                        .ok()
                })
                .collect(),
            Err(e) => {
                task_errors.push(format!("the lens tasks failed: {e}"));
                Vec::new()
            }
        }
        .into_iter();
        let park = parks.next().flatten();
        let park_right = parks.next().flatten();
        for t in tasks {
            if let Err(e) = t.await {
                task_errors.push(format!("a device task failed: {e}"));
            }
        }
        let rec = lock(&state.recording).take();
        let recording = match rec {
            Some(r) => Some(r.finish().await.map_err(|e| e.to_string())),
            None => None,
        };
        ShutdownReport {
            park,
            park_right,
            lens_per_eye: state.cfg.devices.lens.count() > 1,
            recording,
            task_errors,
        }
    }
}

/// Waits on `clock` until `t` (tokio's timer; simulated under a paused runtime).
pub async fn sleep_until(clock: &dyn Clock, t: Timestamp) {
    tokio::time::sleep(t.saturating_since(clock.now())).await;
}
