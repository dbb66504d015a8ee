//! The state the loop, the API and the device tasks share ([`RigState`]): the rig's config,
//! its parts' handles, the channel to the loop, the recording in progress; and what the API
//! asks of the loop and why it may refuse ([`ControlError`]).

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use dioptra_core::{lock, Clock, Timestamp};
use serde::Serialize;
use serde_json::json;
use thiserror::Error;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_util::sync::CancellationToken;

use crate::config::RigConfig;
use crate::content::status::ContentHandle;
use crate::devices::status::DevicesHandle;
use crate::display::status::DisplayHandle;
use crate::engine::Control;
use crate::lsl::LslOutlets;
use crate::mode::{Method, Mode};
use crate::optics::status::OpticsHandle;
use crate::problem::Problem;
use crate::recording::{self, Rec, Recorder, RecordingHandle, RecordingStats, StartRec};
use crate::render::status::RenderHandle;

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

/// The loop's own status: the mode and method it runs, the manual focus, what it handled, the
/// multifocal sub-frames and the scheduler's figures. (Each part publishes the rest through
/// its handle.)
#[derive(Debug, Clone, Default, Serialize)]
pub struct LoopStatus {
    pub mode: Option<Mode>,
    pub method: Option<Method>,
    pub manual_focus_d: Option<f32>,
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

/// The rig's clock: what the host timeline counts, and its anchor to the wall clock.
pub struct RigClock {
    pub(crate) clock: Arc<dyn Clock>,
    /// What the host timeline counts.
    pub(crate) source: &'static str,
    /// The wall-clock time (UTC, ns since the Unix epoch) of the host timeline's zero, read
    /// at start; `None` on a simulated clock. Host time `t` happened at `wall_zero_ns + t`.
    pub(crate) wall_zero_ns: Option<u64>,
    /// When the rig started, on the host timeline.
    pub(crate) started: Timestamp,
}

impl RigClock {
    /// Host time now.
    pub fn now(&self) -> Timestamp {
        self.clock.now()
    }
    pub fn clock(&self) -> &Arc<dyn Clock> {
        &self.clock
    }
    /// What the host timeline counts.
    pub fn source(&self) -> &'static str {
        self.source
    }
    /// The wall-clock time (UTC, ns since the Unix epoch) of the host timeline's zero;
    /// `None` on a simulated clock.
    pub fn wall_zero_ns(&self) -> Option<u64> {
        self.wall_zero_ns
    }
    /// `/status`'s `clock`.
    fn status(&self) -> serde_json::Value {
        json!({
            "source": self.source,
            "wall_zero_ns": self.wall_zero_ns,
        })
    }
}

/// State shared by the loop, the API and the device tasks: the rig's config and each part's
/// handle, through which the part publishes its status (`/status` composes them).
pub struct RigState {
    pub(crate) cfg: Arc<RigConfig>,
    pub(crate) devices: DevicesHandle,
    pub(crate) content: ContentHandle,
    pub(crate) render: RenderHandle,
    pub(crate) display: DisplayHandle,
    pub(crate) optics: OpticsHandle,
    pub(crate) recording: RecordingHandle,
    /// Lab Streaming Layer outlets (`[lsl] enabled = true`).
    pub(crate) lsl: Option<LslOutlets>,
    pub(crate) loop_status: Mutex<LoopStatus>,
    pub(crate) clock: RigClock,
    /// JSON text messages for the API's WebSocket (`GET /stream`).
    pub(crate) websocket: broadcast::Sender<Arc<str>>,
    pub(crate) cancel: CancellationToken,
    pub(crate) controls: mpsc::Sender<ControlMsg>,
}

impl RigState {
    /// The rig config it runs.
    pub fn cfg(&self) -> &Arc<RigConfig> {
        &self.cfg
    }
    /// The devices: their links, the device tasks' settings, the simulated devices.
    pub fn devices(&self) -> &DevicesHandle {
        &self.devices
    }
    /// What the rig shows: the content source, each eye's view.
    pub fn content(&self) -> &ContentHandle {
        &self.content
    }
    /// What renders the frames, and how the renders went.
    pub fn render(&self) -> &RenderHandle {
        &self.render
    }
    /// The display: its sink's status, the marker patch's requests.
    pub fn display(&self) -> &DisplayHandle {
        &self.display
    }
    /// Each lens's optics map, and the focus the lenses were commanded and reported.
    pub fn optics(&self) -> &OpticsHandle {
        &self.optics
    }
    /// The recording in progress.
    pub fn recording(&self) -> &RecordingHandle {
        &self.recording
    }
    /// The Lab Streaming Layer outlets (`[lsl] enabled = true`).
    pub fn lsl(&self) -> Option<&LslOutlets> {
        self.lsl.as_ref()
    }
    /// The loop's own status now.
    pub fn loop_status(&self) -> LoopStatus {
        lock(&self.loop_status).clone()
    }
    /// The rig's clock.
    pub fn clock(&self) -> &RigClock {
        &self.clock
    }
    /// The API's WebSocket messages (`GET /stream`): subscribe to hear them.
    pub fn websocket(&self) -> &broadcast::Sender<Arc<str>> {
        &self.websocket
    }
    /// Stops the rig: the loop carries out the scheduler's shutdown, the device tasks stop.
    pub fn cancel(&self) -> &CancellationToken {
        &self.cancel
    }

    /// `GET /status`: each part's status, and `problems`, what is wrong now.
    pub fn status_json(&self) -> serde_json::Value {
        let now = self.clock.now();
        let st = self.loop_status();
        let render = self.render.status_now();
        let mut out = serde_json::Map::new();
        out.insert(
            "uptime_s".into(),
            json!(now.saturating_since(self.clock.started).as_secs_f64()),
        );
        out.insert("host_ns".into(), json!(now.0));
        out.insert("mode".into(), json!(st.mode));
        out.insert(
            "method".into(),
            if self.render.auto() {
                json!("auto")
            } else {
                json!(st.method)
            },
        );
        out.insert("clock".into(), self.clock.status());
        self.optics
            .status(&mut out, st.manual_focus_d, |i| self.devices.lens_link(i));
        self.content.status(&mut out);
        self.render.status(&mut out);
        self.devices.status(&mut out);
        self.display.status(&mut out);
        self.recording.status(&mut out);
        out.insert(
            "lsl".into(),
            json!(self.lsl.as_ref().map(|l| l.status_json())),
        );
        out.insert(
            "counts".into(),
            json!({
                "gaze_samples": st.gaze_samples,
                "lens_commands": st.lens_commands,
                "sync_events": st.sync_events,
                "frames_requested": st.frames_requested,
                "frames_shown": self.display.shown(),
                "render_errors": render.render_errors,
                "fallback_frames": render.fallback_frames,
            }),
        );
        out.insert(
            "subframes".into(),
            json!({
                "started": st.subframes,
                "measured": st.subframes_measured,
                "off_target": st.subframes_off_target,
                "off_target_rate": (st.subframes_measured > 0)
                    .then(|| st.subframes_off_target as f64 / st.subframes_measured as f64),
                "tolerance_d": SUBFRAME_TOLERANCE_D,
                "faults": st.subframe_faults,
                "lens_measured_by": self.devices.subframe_measurement(),
            }),
        );
        out.insert("scheduler".into(), st.scheduler);
        out.insert("problems".into(), json!(self.problems()));
        serde_json::Value::Object(out)
    }

    /// What is wrong now, each part's in turn, each naming its part and the config key to
    /// look at (the details stay in the part's own status).
    pub fn problems(&self) -> Vec<Problem> {
        let mut p = self.devices.problems();
        p.extend(self.content.problems());
        p.extend(self.render.problems());
        p.extend(self.display.problems());
        p.extend(self.optics.problems());
        p.extend(self.recording.problems());
        if let Some(l) = &self.lsl {
            p.extend(l.problems());
        }
        p
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
        self.recording.record(t, rec);
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
                    json!(self.clock.wall_zero_ns.is_some().then(wall_ns)),
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
        if let Some(r) = self.recording.current().as_ref() {
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
        let st = self.loop_status();
        StartRec {
            config: toml::to_string(self.cfg.as_ref()).unwrap_or_default(),
            mode: st.mode.unwrap_or(self.cfg.mode).as_str().into(),
            method: st.method.unwrap_or(self.cfg.method).as_str().into(),
            manual_focus_d: st.manual_focus_d,
            from_start,
            device_tasks: serde_json::to_value(self.devices.settings()).unwrap_or_default(),
            wall_zero_ns: self.clock.wall_zero_ns,
            clock: self.clock.source.into(),
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
            let mut slot = self.recording.current();
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
        let r = self
            .recording
            .current()
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

#[cfg(test)]
mod tests;
