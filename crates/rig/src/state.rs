//! The state the loop, the API and the device tasks share ([`RigState`]): the rig's config,
//! its parts' handles, the channel to the loop, the recording in progress; and what the API
//! asks of the loop and why it may refuse ([`ControlError`]).

use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

use dioptra_core::{lock, Clock, Timestamp};
use serde::Serialize;
use serde_json::json;
use thiserror::Error;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use crate::config::RigConfig;
use crate::content::source::Content;
use crate::content::stereo::EyeViews;
use crate::devices::config::SyncDriver;
use crate::devices::input::LensId;
use crate::devices::link::DeviceSettings;
use crate::devices::registry::Registry;
use crate::devices::simulators::{SimDevices, SimSlot};
use crate::display::MarkerControl;
use crate::engine::Control;
use crate::lsl::LslOutlets;
use crate::mode::{Method, Mode};
use crate::recording::{self, Rec, Recorder, RecordingStats, StartRec};
use crate::render::job::{Planned, Renderer};

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
    pub planned: Option<Planned>,
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
    pub eye_views: Option<Arc<EyeViews>>,
    /// `method = "auto"` (config or API): the planner chooses each varifocal frame's method.
    pub auto_method: std::sync::atomic::AtomicBool,
    /// Fires when every lens task has parked its lens (or given up) and ended: after this,
    /// exiting the process leaves the lenses safe.
    pub lens_parked: CancellationToken,
    pub clock: Arc<dyn Clock>,
    /// The simulated devices (none on a hardware rig); set once the devices start.
    pub sims: OnceLock<SimDevices>,
    /// Lab Streaming Layer outlets (`[lsl] enabled = true`).
    pub lsl: Option<LslOutlets>,
    /// Focus <-> lens command for the rig's lens (the one lens, or the left eye's): the
    /// scheduler's map (`/status`, recordings, the WebSocket and LSL say what focus a lens
    /// power gives through it). See [`RigState::optics_of`].
    pub optics: dioptra_core::OpticsMap,
    /// The marker patch's requests from outside the loop (an API marker; `dioptra hil`'s hold).
    pub marker: MarkerControl,
    /// The right eye's lens's map, on a rig with a lens per eye.
    pub optics_right: Option<dioptra_core::OpticsMap>,
    pub(crate) controls: mpsc::Sender<ControlMsg>,
    pub(crate) started: Timestamp,
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
        let one = |slot: Option<&SimSlot>| -> serde_json::Value {
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
            SyncDriver::Sync => "the sync board's lens read-back at each sub-frame",
            SyncDriver::Dlpc350 => {
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

/// Nanoseconds since the Unix epoch (UTC) now.
pub(crate) fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}
