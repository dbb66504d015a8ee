//! Recordings: MCAP files with one channel per topic. Messages are JSON (message encoding
//! `json`) described by a JSON Schema per topic (schema encoding `jsonschema`), so Foxglove
//! and the `mcap` CLI show them as they are. Times are host nanoseconds on the daemon's clock;
//! each message's `log_time` is the time the daemon handled it, and its MCAP sequence number
//! is its place in the order the loop handled it (which replay follows).
//!
//! Topics: `/gaze`, `/lens/state`, `/lens/wire`, `/sync/event`, `/frame` (frame timing),
//! `/control` (API commands) are what went into the scheduler; `/lens/command` and `/render`
//! are what came out.
//!
//! Writing happens on a blocking thread fed through a bounded channel: the loop never waits
//! for the disk. Messages that do not fit the channel are counted as dropped.
//!
//! Crash safety: a chunk holds at most [`CHUNK_SPAN`] of messages and is flushed to the file
//! when it closes, so a process killed mid-recording (SIGKILL, a power cut) loses at most the
//! open chunk; [`recover`] rewrites such a file into a complete one.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use dioptra_core::{
    Diopters, EyeRay, GazeSample, LensState, LightEdge, LightEvent, SequencerEvent, SequencerFault,
    Timestamp,
};
use serde::{Deserialize, Serialize};

use dioptra_core::{lock, Side};
use thiserror::Error;
use tokio::sync::mpsc;

use crate::problem::Problem;

pub mod config;

/// An eye (`left`/`right`) in serialized records: core's [`Side`], which has no serde.
pub mod side_serde {
    use dioptra_core::Side;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(side: &Option<Side>, s: S) -> Result<S::Ok, S::Error> {
        side.map(Side::as_str).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Side>, D::Error> {
        match Option::<String>::deserialize(d)? {
            None => Ok(None),
            Some(s) => Side::parse(&s).map(Some).ok_or_else(|| {
                serde::de::Error::custom(format!("{s:?}: expected \"left\" or \"right\""))
            }),
        }
    }
}

#[derive(Debug, Error)]
pub enum RecordingError {
    #[error("cannot create the recording {path}: {source}; check that recording.dir exists and is writable")]
    Create {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write the recording {path}: {detail}")]
    Write { path: PathBuf, detail: String },
    #[error("cannot read the recording {path}: {detail}")]
    Read { path: PathBuf, detail: String },
    #[error("the recording thread for {0} stopped unexpectedly")]
    Thread(PathBuf),
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EyeRec {
    pub origin_mm: [f32; 3],
    pub direction: [f32; 3],
    pub pupil_mm: f32,
    pub valid: bool,
}

impl From<EyeRay> for EyeRec {
    fn from(e: EyeRay) -> Self {
        EyeRec {
            origin_mm: e.origin_mm,
            direction: e.direction,
            pupil_mm: e.pupil_mm,
            valid: e.valid,
        }
    }
}
impl From<EyeRec> for EyeRay {
    fn from(e: EyeRec) -> Self {
        EyeRay {
            origin_mm: e.origin_mm,
            direction: e.direction,
            pupil_mm: e.pupil_mm,
            valid: e.valid,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GazeRec {
    pub device_ns: u64,
    pub host_receive_ns: u64,
    pub host_ns: u64,
    pub left: EyeRec,
    pub right: EyeRec,
}

impl From<&GazeSample> for GazeRec {
    fn from(s: &GazeSample) -> Self {
        GazeRec {
            device_ns: s.device_time.0,
            host_receive_ns: s.host_receive_time.0,
            host_ns: s.host_time.0,
            left: s.left.into(),
            right: s.right.into(),
        }
    }
}
impl From<&GazeRec> for GazeSample {
    fn from(r: &GazeRec) -> Self {
        GazeSample {
            device_time: Timestamp(r.device_ns),
            host_receive_time: Timestamp(r.host_receive_ns),
            host_time: Timestamp(r.host_ns),
            left: r.left.into(),
            right: r.right.into(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LensStateRec {
    pub power_d: f32,
    pub current_ma: Option<f32>,
    pub temperature_c: Option<f32>,
    pub settled: Option<bool>,
    pub host_ns: u64,
    /// With a lens per eye, the eye whose lens it is (its topics are `/lens/left/...` and
    /// `/lens/right/...`); absent for a rig's one lens.
    #[serde(default, skip_serializing_if = "Option::is_none", with = "side_serde")]
    pub eye: Option<Side>,
}

impl From<&LensState> for LensStateRec {
    fn from(s: &LensState) -> Self {
        LensStateRec {
            power_d: s.power.0,
            current_ma: s.current_ma,
            temperature_c: s.temperature_c,
            settled: s.settled,
            host_ns: s.host_time.0,
            eye: None,
        }
    }
}
impl From<&LensStateRec> for LensState {
    fn from(r: &LensStateRec) -> Self {
        LensState {
            power: Diopters(r.power_d),
            current_ma: r.current_ma,
            temperature_c: r.temperature_c,
            settled: r.settled,
            host_time: Timestamp(r.host_ns),
        }
    }
}

/// Light on the photodiode: an edge, or edges the device could not report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LightRec {
    Edge {
        device_ns: u64,
        host_receive_ns: u64,
        host_ns: u64,
        rising: bool,
        level: Option<f32>,
    },
    Lost {
        count: u64,
        host_ns: u64,
    },
}

impl From<&LightEvent> for LightRec {
    fn from(e: &LightEvent) -> Self {
        match *e {
            LightEvent::Edge(e) => LightRec::Edge {
                device_ns: e.device_time.0,
                host_receive_ns: e.host_receive_time.0,
                host_ns: e.host_time.0,
                rising: e.rising,
                level: e.level,
            },
            LightEvent::Lost { count, host_time } => LightRec::Lost {
                count,
                host_ns: host_time.0,
            },
        }
    }
}

impl From<&LightRec> for LightEvent {
    fn from(r: &LightRec) -> Self {
        match *r {
            LightRec::Edge {
                device_ns,
                host_receive_ns,
                host_ns,
                rising,
                level,
            } => LightEvent::Edge(LightEdge {
                device_time: Timestamp(device_ns),
                host_receive_time: Timestamp(host_receive_ns),
                host_time: Timestamp(host_ns),
                rising,
                level,
            }),
            LightRec::Lost { count, host_ns } => LightEvent::Lost {
                count,
                host_time: Timestamp(host_ns),
            },
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SyncRec {
    Subframe {
        frame: u32,
        plane_index: u8,
        device_ns: u64,
        host_ns: u64,
        lens_power_d: Option<f32>,
    },
    Fault {
        fault: String,
        code: u16,
        frame: u32,
        plane_index: u8,
        host_ns: u64,
    },
}

impl From<&SequencerEvent> for SyncRec {
    fn from(e: &SequencerEvent) -> Self {
        match *e {
            SequencerEvent::SubframeStart {
                frame,
                plane_index,
                device_time,
                host_time,
                lens_power,
            } => SyncRec::Subframe {
                frame,
                plane_index,
                device_ns: device_time.0,
                host_ns: host_time.0,
                lens_power_d: lens_power.map(|p| p.0),
            },
            SequencerEvent::Fault {
                fault,
                frame,
                plane_index,
                host_time,
            } => {
                let (name, code) = match fault {
                    SequencerFault::MissedVsync => ("missed_vsync", 0),
                    SequencerFault::LateSettle => ("late_settle", 0),
                    SequencerFault::Other(c) => ("other", c),
                };
                SyncRec::Fault {
                    fault: name.into(),
                    code,
                    frame,
                    plane_index,
                    host_ns: host_time.0,
                }
            }
        }
    }
}
impl From<&SyncRec> for SequencerEvent {
    fn from(r: &SyncRec) -> Self {
        match r {
            SyncRec::Subframe {
                frame,
                plane_index,
                device_ns,
                host_ns,
                lens_power_d,
            } => SequencerEvent::SubframeStart {
                frame: *frame,
                plane_index: *plane_index,
                device_time: Timestamp(*device_ns),
                host_time: Timestamp(*host_ns),
                lens_power: lens_power_d.map(Diopters),
            },
            SyncRec::Fault {
                fault,
                code,
                frame,
                plane_index,
                host_ns,
            } => SequencerEvent::Fault {
                fault: match fault.as_str() {
                    "missed_vsync" => SequencerFault::MissedVsync,
                    "late_settle" => SequencerFault::LateSettle,
                    _ => SequencerFault::Other(*code),
                },
                frame: *frame,
                plane_index: *plane_index,
                host_time: Timestamp(*host_ns),
            },
        }
    }
}

/// A render finished: the scheduler's input, with the render time it was given.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRec {
    pub frame: u64,
    pub method: String,
    pub render_ns: u64,
    /// When the render was asked for.
    pub requested_ns: u64,
    /// The focus it was rendered for (varifocal).
    pub focus_d: Option<f32>,
}

/// The content's depth was given to the scheduler.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct DepthRec {
    /// The animated scene's time of the frame (a replay renders its depth from it); `None`
    /// for other content, and in recordings of the still scene.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_ns: Option<u64>,
}

/// The content frame of the latest depth: when it arrived and was ready (host ns).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ContentRec {
    pub arrived_ns: u64,
    pub ready_ns: u64,
}

/// A command from the API.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ControlRec {
    Mode {
        mode: String,
    },
    Method {
        method: String,
    },
    /// `None` returns focus to gaze.
    ManualFocus {
        diopters: Option<f32>,
    },
}

/// A lens command went on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LensWireRec {
    pub id: u64,
    pub requested_d: f32,
    pub wire_ns: u64,
    /// With a lens per eye, the eye (see [`LensStateRec::eye`]).
    #[serde(default, skip_serializing_if = "Option::is_none", with = "side_serde")]
    pub eye: Option<Side>,
}

/// The lens link went down or came back.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LensLinkRec {
    pub up: bool,
    /// With a lens per eye, the eye (see [`LensStateRec::eye`]).
    #[serde(default, skip_serializing_if = "Option::is_none", with = "side_serde")]
    pub eye: Option<Side>,
}

/// A lens power the scheduler commanded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LensCommandRec {
    pub id: u64,
    pub power_d: f32,
    pub apply_at_ns: u64,
    pub reason: String,
    /// The focus the command gives through the rig's optics map (absent in older recordings).
    #[serde(default)]
    pub focus_d: Option<f32>,
    /// With a lens per eye, the eye (see [`LensStateRec::eye`]).
    #[serde(default, skip_serializing_if = "Option::is_none", with = "side_serde")]
    pub eye: Option<Side>,
}

/// A frame the scheduler asked the renderer for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderRec {
    pub frame: u64,
    pub mode: String,
    pub method: String,
    pub focus_d: Option<f32>,
    pub display_ns: u64,
}

/// A frame (or, in multifocal mode, one layer of it) the scheduler had shown.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PresentRec {
    pub frame: u64,
    /// Multifocal: the layer, shown in the sub-frame that started at `at_ns`.
    pub layer: Option<u8>,
    /// The vsync (or sub-frame start) it is shown from.
    pub at_ns: u64,
    /// The frame already on screen, shown again (a missed deadline).
    pub repeat: bool,
}

/// A marker: nothing but the time it happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Marker {}

/// A lab's marker (`POST /marker`): its text or JSON object, as the experiment sent it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerRec {
    pub marker: serde_json::Value,
}

/// What a replay needs to rebuild the scheduler.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StartRec {
    /// The rig config, TOML.
    pub config: String,
    pub mode: String,
    pub method: String,
    pub manual_focus_d: Option<f32>,
    /// Whether the recording began with the daemon (a replay then starts from the same state).
    pub from_start: bool,
    /// The device tasks' settings (`devices::DeviceSettings`); absent in older
    /// recordings.
    #[serde(default)]
    pub device_tasks: serde_json::Value,
    /// Wall-clock time (UTC, ns since the Unix epoch) of host time 0: host time `t` happened
    /// at `wall_zero_ns + t`. `None` on a simulated clock, and in older recordings.
    #[serde(default)]
    pub wall_zero_ns: Option<u64>,
    /// What the host times count.
    #[serde(default)]
    pub clock: String,
    /// The calibration tables the run read (path as the config gives it -> the file's text),
    /// so a replay uses them as they were.
    #[serde(default)]
    pub calibration_tables: std::collections::BTreeMap<String, String>,
    /// The experiment's names for this recording (`POST /recording/start`).
    #[serde(default)]
    pub name: Option<String>,
    #[serde(default)]
    pub subject: Option<String>,
    #[serde(default)]
    pub trial: Option<String>,
    /// A recording started mid-run (through the API): the scheduler's state when it began
    /// ([`dioptra_sched::Scheduler::state`]), so a replay starts there. `None` from the start,
    /// and in older recordings.
    #[serde(default)]
    pub scheduler_state: Option<Box<serde_json::Value>>,
    /// With it: the scene time of the frame whose depth the scheduler had (`None` for content
    /// without one).
    #[serde(default)]
    pub depth_scene_ns: Option<u64>,
}

/// One recorded message. Inputs (what the scheduler was given): Start, Gaze, LensState,
/// LensWire, LensLink, Sync, Frame, Control, Depth, Content, Tick, Shutdown. Outputs (what it
/// commanded): LensCommand, Render, Present, StopSequencer. And the lab's markers (Marker).
#[derive(Debug, Clone, PartialEq)]
pub enum Rec {
    Start(StartRec),
    Gaze(GazeRec),
    LensState(LensStateRec),
    LensWire(LensWireRec),
    LensLink(LensLinkRec),
    Sync(SyncRec),
    Light(LightRec),
    Frame(FrameRec),
    Control(ControlRec),
    Depth(DepthRec),
    Content(ContentRec),
    Tick(Marker),
    Shutdown(Marker),
    LensCommand(LensCommandRec),
    Render(RenderRec),
    Present(PresentRec),
    StopSequencer(Marker),
    /// Not an input of the scheduler: replay passes it over.
    Marker(MarkerRec),
}

/// Declares, for each variant, its topic, schema name and JSON Schema properties.
macro_rules! topics {
    ($( $variant:ident => $topic:literal, $name:literal, $props:expr; )*) => {
        impl Rec {
            /// The topic of the message's kind, before a lens's eye is added.
            fn kind_topic(&self) -> &'static str {
                match self { $( Rec::$variant(_) => $topic, )* }
            }
            fn to_json(&self) -> Result<Vec<u8>, serde_json::Error> {
                match self { $( Rec::$variant(r) => serde_json::to_vec(r), )* }
            }
            /// Decodes a message of `topic`; `None` for a topic this version does not know.
            pub fn from_json(topic: &str, data: &[u8]) -> Option<Result<Rec, serde_json::Error>> {
                let topic = kind_of_topic(topic);
                match topic {
                    $( $topic => Some(serde_json::from_slice(data).map(Rec::$variant)), )*
                    _ => None,
                }
            }
        }
        /// (topic, schema name, JSON Schema) for every topic (the lens topics once, without
        /// an eye).
        fn topics() -> Vec<(&'static str, &'static str, String)> {
            vec![ $( ($topic, $name, format!(r#"{{"type":"object","properties":{{{}}}}}"#, $props)), )* ]
        }
    };
}

const N: &str = r#"{"type":"number"}"#;
const ON: &str = r#"{"type":["number","null"]}"#;
const S: &str = r#"{"type":"string"}"#;
const OS: &str = r#"{"type":["string","null"]}"#;
const B: &str = r#"{"type":"boolean"}"#;
const EYE_SCHEMA: &str = r#"{"type":"object","properties":{"origin_mm":{"type":"array","items":{"type":"number"}},"direction":{"type":"array","items":{"type":"number"}},"pupil_mm":{"type":"number"},"valid":{"type":"boolean"}}}"#;

topics! {
    Start => "/start", "dioptra.Start",
        format!(r#""config":{S},"mode":{S},"method":{S},"manual_focus_d":{ON},"from_start":{B},"wall_zero_ns":{ON},"clock":{S},"calibration_tables":{{"type":"object"}},"name":{OS},"subject":{OS},"trial":{OS},"scheduler_state":{{"type":["object","null"]}},"depth_scene_ns":{ON}"#);
    Gaze => "/gaze", "dioptra.Gaze",
        format!(r#""device_ns":{N},"host_receive_ns":{N},"host_ns":{N},"left":{EYE_SCHEMA},"right":{EYE_SCHEMA}"#);
    LensState => "/lens/state", "dioptra.LensState",
        format!(r#""power_d":{N},"current_ma":{ON},"temperature_c":{ON},"settled":{{"type":["boolean","null"]}},"host_ns":{N}"#);
    LensWire => "/lens/wire", "dioptra.LensWire",
        format!(r#""id":{N},"requested_d":{N},"wire_ns":{N}"#);
    LensLink => "/lens/link", "dioptra.LensLink", format!(r#""up":{B}"#);
    Sync => "/sync/event", "dioptra.SyncEvent",
        format!(r#""kind":{{"enum":["subframe","fault"]}},"frame":{N},"plane_index":{N},"device_ns":{N},"host_ns":{N},"lens_power_d":{ON},"fault":{S},"code":{N}"#);
    Light => "/photodiode", "dioptra.LightEdge",
        format!(r#""kind":{{"enum":["edge","lost"]}},"device_ns":{N},"host_receive_ns":{N},"host_ns":{N},"rising":{B},"level":{ON},"count":{N}"#);
    Frame => "/frame", "dioptra.FrameRendered",
        format!(r#""frame":{N},"method":{S},"render_ns":{N},"requested_ns":{N},"focus_d":{ON}"#);
    Control => "/control", "dioptra.Control",
        format!(r#""kind":{{"enum":["mode","method","manual_focus"]}},"mode":{S},"method":{S},"diopters":{ON}"#);
    Depth => "/depth", "dioptra.DepthGiven", format!(r#""scene_ns":{N}"#);
    Content => "/content", "dioptra.ContentArrival",
        format!(r#""arrived_ns":{N},"ready_ns":{N}"#);
    Tick => "/tick", "dioptra.Tick", "";
    Shutdown => "/shutdown", "dioptra.Shutdown", "";
    LensCommand => "/lens/command", "dioptra.LensCommand",
        format!(r#""id":{N},"power_d":{N},"apply_at_ns":{N},"reason":{S},"focus_d":{ON}"#);
    Render => "/render", "dioptra.RenderRequest",
        format!(r#""frame":{N},"mode":{S},"method":{S},"focus_d":{ON},"display_ns":{N}"#);
    Present => "/present", "dioptra.Present",
        format!(r#""frame":{N},"layer":{ON},"at_ns":{N},"repeat":{B}"#);
    StopSequencer => "/sync/stop", "dioptra.StopSequencer", "";
    Marker => "/marker", "dioptra.Marker",
        r#""marker":{"type":["string","object"]}"#;
}

/// The lens topics of each eye, on a rig with a lens per eye: `(kind topic, left, right)`.
const EYE_TOPICS: [(&str, &str, &str); 4] = [
    ("/lens/state", "/lens/left/state", "/lens/right/state"),
    ("/lens/wire", "/lens/left/wire", "/lens/right/wire"),
    ("/lens/link", "/lens/left/link", "/lens/right/link"),
    ("/lens/command", "/lens/left/command", "/lens/right/command"),
];

/// The message kind's topic of `topic` (an eye's lens topic is its kind's).
fn kind_of_topic(topic: &str) -> &str {
    EYE_TOPICS
        .iter()
        .find(|(_, l, r)| *l == topic || *r == topic)
        .map_or(topic, |(k, _, _)| k)
}

impl Rec {
    /// The message's topic: its kind's, or with a lens per eye, its eye's
    /// (`/lens/left/state`, `/lens/right/command`, ...).
    pub fn topic(&self) -> &'static str {
        let eye = match self {
            Rec::LensState(r) => r.eye,
            Rec::LensWire(r) => r.eye,
            Rec::LensLink(r) => r.eye,
            Rec::LensCommand(r) => r.eye,
            _ => None,
        };
        let kind = self.kind_topic();
        match eye {
            None => kind,
            Some(e) => EYE_TOPICS
                .iter()
                .find(|(k, _, _)| *k == kind)
                .map_or(kind, |(_, l, r)| match e {
                    Side::Left => l,
                    Side::Right => r,
                }),
        }
    }
}

/// What a finished recording holds./// What a finished recording holds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RecordingStats {
    pub path: PathBuf,
    pub messages: u64,
    /// Messages the writer could not keep up with.
    pub dropped: u64,
}

/// Messages the channel holds before the loop starts dropping them.
const QUEUE: usize = 16_384;

/// The most host time one chunk spans: what a killed recording can lose.
pub const CHUNK_SPAN: std::time::Duration = std::time::Duration::from_secs(1);

/// A recording in progress. [`Recorder::finish`] writes the summary and closes the file.
pub struct Recorder {
    path: PathBuf,
    tx: mpsc::Sender<(u64, Rec)>,
    dropped: Arc<AtomicU64>,
    /// The writer thread's result: messages written.
    thread: tokio::sync::oneshot::Receiver<Result<u64, RecordingError>>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.path)
            .finish()
    }
}

impl Recorder {
    /// Creates the file and starts its writer thread; `lens_per_eye`: the lens topics are
    /// each eye's (`/lens/left/...`, `/lens/right/...`).
    pub fn start(path: &Path, lens_per_eye: bool) -> Result<Recorder, RecordingError> {
        let file = File::create(path).map_err(|source| RecordingError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        let werr = |e: mcap::McapError| RecordingError::Write {
            path: path.to_path_buf(),
            detail: e.to_string(),
        };
        let mut w = mcap::WriteOptions::new()
            .compression(None)
            .profile("")
            .library(concat!("dioptra ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(werr)?;
        let mut channels = BTreeMap::new();
        for (topic, name, schema) in topics() {
            let sid = w
                .add_schema(name, "jsonschema", schema.as_bytes())
                .map_err(werr)?;
            let eyes = EYE_TOPICS.iter().find(|(k, _, _)| *k == topic);
            let each: Vec<&'static str> = match (eyes, lens_per_eye) {
                (Some((_, l, r)), true) => vec![l, r],
                _ => vec![topic],
            };
            for t in each {
                let cid = w
                    .add_channel(sid, t, "json", &BTreeMap::new())
                    .map_err(werr)?;
                channels.insert(t, cid);
            }
        }
        let (tx, mut rx) = mpsc::channel::<(u64, Rec)>(QUEUE);
        let p = path.to_path_buf();
        let (done, thread) = tokio::sync::oneshot::channel();
        // A thread of its own, not tokio's blocking pool: a blocking task that lives as long as
        // the recording would stop a paused (simulated) clock from advancing.
        let mut write = move || {
            let werr = |e: String| RecordingError::Write {
                path: p.clone(),
                detail: e,
            };
            let mut seq: u32 = 0;
            let mut first_error = None;
            let span = CHUNK_SPAN.as_nanos() as u64;
            let mut chunk_start: Option<u64> = None;
            while let Some((t, rec)) = rx.blocking_recv() {
                if first_error.is_some() {
                    continue;
                }
                let Some(&channel_id) = channels.get(rec.topic()) else {
                    continue;
                };
                let r = rec.to_json().map_err(|e| e.to_string()).and_then(|data| {
                    w.write_to_known_channel(
                        &mcap::records::MessageHeader {
                            channel_id,
                            sequence: seq,
                            log_time: t,
                            publish_time: t,
                        },
                        &data,
                    )
                    .map_err(|e| e.to_string())
                });
                match r {
                    Ok(()) => seq = seq.wrapping_add(1),
                    Err(e) => first_error = Some(werr(e)),
                }
                // Close and flush the chunk once it spans CHUNK_SPAN.
                let start = *chunk_start.get_or_insert(t);
                if t.saturating_sub(start) >= span {
                    chunk_start = None;
                    if let Err(e) = w.flush() {
                        first_error.get_or_insert(werr(e.to_string()));
                    }
                }
            }
            let finished = w.finish().map_err(|e| werr(e.to_string()));
            if let Some(e) = first_error {
                return Err(e);
            }
            finished?;
            Ok(u64::from(seq))
        };
        std::thread::Builder::new()
            .name("dioptra-recorder".into())
            .spawn(move || {
                let _ = done.send(write());
            })
            .map_err(|source| RecordingError::Create {
                path: path.to_path_buf(),
                source,
            })?;
        tracing::info!(path = %path.display(), "recording");
        Ok(Recorder {
            path: path.to_path_buf(),
            tx,
            dropped: Arc::new(AtomicU64::new(0)),
            thread,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Messages dropped so far (the channel to the writer was full).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Queues one message; never waits.
    pub fn record(&self, t: Timestamp, rec: Rec) {
        if self.tx.try_send((t.0, rec)).is_err() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Writes the rest, the summary and the footer, and closes the file.
    pub async fn finish(self) -> Result<RecordingStats, RecordingError> {
        let Recorder {
            path,
            tx,
            dropped,
            thread,
        } = self;
        drop(tx);
        let messages = thread
            .await
            .map_err(|_| RecordingError::Thread(path.clone()))??;
        Ok(RecordingStats {
            path,
            messages,
            dropped: dropped.load(Ordering::Relaxed),
        })
    }
}

/// What the recording part publishes: the recording in progress, if any; `/status`'s
/// `recording` (its path), and messages it dropped.
#[derive(Default)]
pub struct RecordingHandle(Mutex<Option<Recorder>>);

impl RecordingHandle {
    /// The recording in progress (`None`: not recording), locked.
    pub fn current(&self) -> std::sync::MutexGuard<'_, Option<Recorder>> {
        lock(&self.0)
    }

    /// Where the recording in progress goes.
    pub fn path(&self) -> Option<PathBuf> {
        self.current().as_ref().map(|r| r.path().to_path_buf())
    }

    /// Queues `rec` at `t` in the recording in progress (none: nothing).
    pub fn record(&self, t: Timestamp, rec: Rec) {
        if let Some(r) = self.current().as_ref() {
            r.record(t, rec);
        }
    }

    /// `/status`'s `recording`: the path of the recording in progress.
    pub fn status(&self, out: &mut serde_json::Map<String, serde_json::Value>) {
        out.insert(
            "recording".into(),
            serde_json::json!(self.path().map(|p| p.display().to_string())),
        );
    }

    /// The recording in progress dropped messages: the disk did not keep up.
    pub fn problems(&self) -> Vec<Problem> {
        let current = self.current();
        let Some(r) = current.as_ref().filter(|r| r.dropped() > 0) else {
            return Vec::new();
        };
        vec![Problem::new(
            "recording",
            "recording.dir",
            format!(
                "the recording {} dropped {} messages: the disk does not keep up with the rig",
                r.path().display(),
                r.dropped()
            ),
        )]
    }
}

/// A recording read back: messages in the order they were recorded, with their log times.
#[derive(Debug, Clone, PartialEq)]
pub struct Recorded {
    pub messages: Vec<(Timestamp, Rec)>,
    /// Messages on topics this version does not know.
    pub unknown: u64,
    /// Whether the file ends with a summary (it was finished, not cut off).
    pub complete: bool,
    /// Written by [`recover`] from a cut file: complete, but its last inputs' commands may
    /// have been lost with the cut.
    pub recovered: bool,
}

/// What [`recover`] writes as the header's library, after the version.
const RECOVERED_TAG: &str = " (recovered)";

/// Reads a recording. A file cut off mid-write reads up to the cut, with `complete` false.
pub fn read(path: &Path) -> Result<Recorded, RecordingError> {
    let rerr = |detail: String| RecordingError::Read {
        path: path.to_path_buf(),
        detail,
    };
    let bytes = std::fs::read(path).map_err(|e| rerr(e.to_string()))?;
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(rerr(
            "it does not start with the MCAP magic bytes: not an MCAP file".into(),
        ));
    }
    let complete = matches!(mcap::Summary::read(&bytes), Ok(Some(_)));
    let recovered = mcap::read::LinearReader::new_with_options(
        &bytes,
        enumset::enum_set!(mcap::read::Options::IgnoreEndMagic),
    )
    .ok()
    .and_then(|mut r| r.next())
    .is_some_and(
        |h| matches!(h, Ok(mcap::records::Record::Header(h)) if h.library.ends_with(RECOVERED_TAG)),
    );
    let stream = mcap::MessageStream::new(&bytes).map_err(|e| {
        rerr(format!(
            "{e}; is it an MCAP file written by `dioptra serve`?"
        ))
    })?;
    let mut messages = Vec::new();
    let mut unknown = 0;
    for m in stream {
        let m = match m {
            Ok(m) => m,
            Err(e) if !complete => {
                tracing::warn!(error = %e, "recording cut off; reading up to the cut");
                break;
            }
            Err(e) => return Err(rerr(e.to_string())),
        };
        match Rec::from_json(&m.channel.topic, &m.data) {
            Some(Ok(r)) => messages.push((m.sequence, Timestamp(m.log_time), r)),
            Some(Err(e)) => {
                return Err(rerr(format!(
                    "message {} on {}: {e}",
                    m.sequence, m.channel.topic
                )))
            }
            None => unknown += 1,
        }
    }
    messages.sort_by_key(|(seq, _, _)| *seq);
    Ok(Recorded {
        messages: messages.into_iter().map(|(_, t, r)| (t, r)).collect(),
        unknown,
        complete,
        recovered,
    })
}

/// What [`recover`] saved.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Recovered {
    pub output: PathBuf,
    pub messages: u64,
    /// Whether the input was cut off (false: it was complete already, and is copied whole).
    pub was_cut: bool,
    /// Why reading stopped, for a cut file.
    pub cut_at: Option<String>,
}

/// Rewrites the recording `input`, cut off mid-write, into a complete file `output`: every
/// message up to the cut (the chunks closed before it), with the same channels, schemas,
/// sequence numbers and times, and a summary.
pub fn recover(input: &Path, output: &Path) -> Result<Recovered, RecordingError> {
    let rerr = |detail: String| RecordingError::Read {
        path: input.to_path_buf(),
        detail,
    };
    let werr = |detail: String| RecordingError::Write {
        path: output.to_path_buf(),
        detail,
    };
    let bytes = std::fs::read(input).map_err(|e| rerr(e.to_string()))?;
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(rerr(
            "it does not start with the MCAP magic bytes: not an MCAP file".into(),
        ));
    }
    let was_cut = !matches!(mcap::Summary::read(&bytes), Ok(Some(_)));
    let stream = mcap::MessageStream::new_with_options(
        &bytes,
        enumset::enum_set!(mcap::read::Options::IgnoreEndMagic),
    )
    .map_err(|e| rerr(e.to_string()))?;
    if output.exists() {
        return Err(werr("it exists already; give another --out".into()));
    }
    let file = File::create(output).map_err(|source| RecordingError::Create {
        path: output.to_path_buf(),
        source,
    })?;
    let mut w = mcap::WriteOptions::new()
        .compression(None)
        .profile("")
        .library(concat!(
            "dioptra ",
            env!("CARGO_PKG_VERSION"),
            " (recovered)"
        ))
        .create(BufWriter::new(file))
        .map_err(|e| werr(e.to_string()))?;
    let mut messages = 0u64;
    let mut cut_at = None;
    for m in stream {
        match m {
            Ok(m) => {
                w.write(&m).map_err(|e| werr(e.to_string()))?;
                messages += 1;
            }
            Err(e) => {
                cut_at = Some(e.to_string());
                break;
            }
        }
    }
    w.finish().map_err(|e| werr(e.to_string()))?;
    Ok(Recovered {
        output: output.to_path_buf(),
        messages,
        was_cut,
        cut_at,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaze(t: u64) -> GazeSample {
        let eye = EyeRay {
            origin_mm: [31.5, 0.0, 0.0],
            direction: [0.1, -0.05, 0.99],
            pupil_mm: 3.9,
            valid: true,
        };
        GazeSample {
            device_time: Timestamp(t + 7),
            host_receive_time: Timestamp(t + 900),
            host_time: Timestamp(t),
            left: eye,
            right: EyeRay {
                valid: false,
                ..eye
            },
        }
    }

    #[tokio::test]
    async fn chunks_span_at_most_a_second_and_a_cut_file_is_recovered() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        let rec = Recorder::start(&path, false).unwrap();
        // 5 s of gaze at 1 kHz.
        let n = 5000u64;
        for i in 0..n {
            let t = i * 1_000_000;
            rec.record(Timestamp(t), Rec::Gaze(GazeRec::from(&gaze(t))));
            if i % 1000 == 999 {
                tokio::task::yield_now().await;
            }
        }
        let stats = rec.finish().await.unwrap();
        assert_eq!((stats.messages, stats.dropped), (n, 0));
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert!(
            summary.chunk_indexes.len() >= 5,
            "{} chunks",
            summary.chunk_indexes.len()
        );
        for c in &summary.chunk_indexes {
            let span = c.message_end_time - c.message_start_time;
            assert!(
                span <= CHUNK_SPAN.as_nanos() as u64,
                "a chunk spans {span} ns"
            );
        }
        // Cut where a kill would: in the middle of the third chunk.
        let third = &summary.chunk_indexes[2];
        let cut_at = (third.chunk_start_offset + third.chunk_length / 2) as usize;
        let cut = dir.path().join("cut.mcap");
        std::fs::write(&cut, &bytes[..cut_at]).unwrap();
        assert!(!read(&cut).unwrap().complete);
        let out = dir.path().join("fixed.mcap");
        let r = recover(&cut, &out).unwrap();
        assert!(r.was_cut && r.cut_at.is_some(), "{r:?}");
        let fixed = read(&out).unwrap();
        assert!(fixed.complete && fixed.recovered);
        assert!(!read(&path).unwrap().recovered);
        assert_eq!(fixed.messages.len() as u64, r.messages);
        // Every message of the first two chunks (and the whole records of the cut one, an
        // uncompressed chunk reads record by record), in order, none after the cut.
        let in_two: u64 = summary.chunk_indexes[..2]
            .iter()
            .map(|c| c.message_end_time / 1_000_000 - c.message_start_time / 1_000_000 + 1)
            .sum();
        let in_three = in_two + (third.message_end_time - third.message_start_time) / 1_000_000 + 1;
        assert!(
            (in_two..in_three).contains(&r.messages),
            "{} of {in_two}..{in_three}",
            r.messages
        );
        for (i, (t, _)) in fixed.messages.iter().enumerate() {
            assert_eq!(t.0, i as u64 * 1_000_000);
        }
        // A complete file is copied whole; an existing output is not overwritten.
        let again = dir.path().join("again.mcap");
        let r = recover(&path, &again).unwrap();
        assert!(!r.was_cut);
        assert_eq!(r.messages, stats.messages);
        assert!(recover(&cut, &out).is_err());
    }

    #[tokio::test]
    async fn a_recording_reads_back_exactly_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        let rec = Recorder::start(&path, false).unwrap();
        let ev = SequencerEvent::Fault {
            fault: SequencerFault::LateSettle,
            frame: 3,
            plane_index: 1,
            host_time: Timestamp(55),
        };
        let sent = vec![
            (
                Timestamp(0),
                Rec::Start(StartRec {
                    config: "mode = \"varifocal\"".into(),
                    mode: "varifocal".into(),
                    method: "gather".into(),
                    manual_focus_d: None,
                    from_start: true,
                    device_tasks: serde_json::Value::Null,
                    wall_zero_ns: Some(1_764_000_000_000_000_000),
                    clock: "test".into(),
                    calibration_tables: [(
                        "cal.csv".to_string(),
                        "command_d,demand_d\n".to_string(),
                    )]
                    .into(),
                    name: Some("vergence".into()),
                    subject: None,
                    trial: Some("3".into()),
                    scheduler_state: Some(Box::new(serde_json::json!({"commanded": 1.5}))),
                    depth_scene_ns: Some(50_000_000),
                }),
            ),
            (Timestamp(1), Rec::Gaze(GazeRec::from(&gaze(1_000)))),
            (Timestamp(1), Rec::Tick(Marker {})),
            (
                Timestamp(2),
                Rec::LensCommand(LensCommandRec {
                    id: 4,
                    power_d: 1.3,
                    apply_at_ns: 3,
                    reason: "fixation".into(),
                    focus_d: Some(1.25),
                    eye: None,
                }),
            ),
            (Timestamp(2), Rec::Sync(SyncRec::from(&ev))),
            (
                Timestamp(3),
                Rec::Control(ControlRec::ManualFocus {
                    diopters: Some(0.1),
                }),
            ),
            (
                Timestamp(4),
                Rec::Frame(FrameRec {
                    frame: 9,
                    method: "gather".into(),
                    render_ns: 1_250_000,
                    requested_ns: 1,
                    focus_d: Some(2.25),
                }),
            ),
            (
                Timestamp(5),
                Rec::Marker(MarkerRec {
                    marker: serde_json::json!({"event": "stimulus_on", "trial": 3}),
                }),
            ),
            (
                Timestamp(6),
                Rec::Marker(MarkerRec {
                    marker: serde_json::json!("response"),
                }),
            ),
        ];
        for (t, r) in &sent {
            rec.record(*t, r.clone());
        }
        let stats = rec.finish().await.unwrap();
        assert_eq!(stats.messages, sent.len() as u64);
        assert_eq!(stats.dropped, 0);
        let back = read(&path).unwrap();
        assert!(back.complete);
        assert_eq!(back.messages, sent);
        // Conversions back to the core types are exact.
        let Rec::Gaze(g) = &back.messages[1].1 else {
            panic!()
        };
        assert_eq!(GazeSample::from(g), gaze(1_000));
        let Rec::Sync(s) = &back.messages[4].1 else {
            panic!()
        };
        assert_eq!(SequencerEvent::from(s), ev);
        // The summary lists every channel with its schema.
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert_eq!(summary.channels.len(), topics().len());
        assert!(summary
            .channels
            .values()
            .all(|c| c.message_encoding == "json"
                && c.schema
                    .as_ref()
                    .is_some_and(|s| s.encoding == "jsonschema")));
    }

    #[tokio::test]
    async fn a_cut_off_recording_reads_up_to_the_cut_and_says_so() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.mcap");
        let rec = Recorder::start(&path, false).unwrap();
        for i in 0..50 {
            rec.record(
                Timestamp(i),
                Rec::Present(PresentRec {
                    frame: i,
                    layer: None,
                    at_ns: i,
                    repeat: false,
                }),
            );
        }
        rec.finish().await.unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        match read(&path) {
            Ok(r) => assert!(!r.complete),
            Err(e) => assert!(e.to_string().contains("cannot read the recording"), "{e}"),
        }
        std::fs::write(&path, b"not an mcap").unwrap();
        let e = read(&path).unwrap_err();
        assert!(e.to_string().contains("MCAP"), "{e}");
    }

    #[test]
    fn every_schema_is_valid_json() {
        for (topic, _, schema) in topics() {
            let v: serde_json::Value =
                serde_json::from_str(&schema).unwrap_or_else(|e| panic!("{topic}: {e}: {schema}"));
            assert_eq!(v["type"], "object", "{topic}");
        }
    }
}
