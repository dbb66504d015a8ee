//! `dioptra replay FILE`: drives a fresh scheduler from a recording made by `dioptra serve`
//! and compares what it commands with what was recorded.
//!
//! The recording's `/start` message holds the rig config and the scheduler's state when it
//! began; every input the loop gave the scheduler (gaze, lens state and wire times, sync
//! events, finished frames, frame ticks, API commands) is fed again at its recorded time and in
//! its recorded order. The scheduler is deterministic, so a recording that began with the
//! daemon replays to the same lens commands and render requests.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use dioptra_core::{DepthMap, Diopters, Timestamp};
use serde::Serialize;

use dioptra_core::Side;
use dioptra_rig::config::{ContentSource, Lenses, Method, Mode, RigConfig};
use dioptra_rig::content::scene::{self, AnimatedScene, Pacing};
use dioptra_rig::devices::{DeviceInput, LensId};
use dioptra_rig::engine::{Command, Engine, Input};
use dioptra_rig::recording::{self, ControlRec, Rec, Recorded};
use dioptra_rig::Control;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// An MCAP recording written by `dioptra serve`.
    pub file: PathBuf,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// One command, as recorded or as replayed, with the time the loop handled it.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Cmd {
    Lens {
        t_ns: u64,
        id: u64,
        power_d: f32,
        reason: String,
        /// With a lens per eye, the eye's lens.
        #[serde(
            skip_serializing_if = "Option::is_none",
            serialize_with = "dioptra_rig::recording::side_serde::serialize"
        )]
        eye: Option<Side>,
    },
    Render {
        t_ns: u64,
        frame: u64,
        method: String,
        focus_d: Option<f32>,
    },
    Present {
        t_ns: u64,
        frame: u64,
        layer: Option<u8>,
        at_ns: u64,
        repeat: bool,
    },
    StopSequencer {
        t_ns: u64,
    },
}

impl Cmd {
    /// A recorded command, or `None` for an input.
    fn recorded(t: Timestamp, r: &Rec) -> Option<Cmd> {
        Some(match r {
            Rec::LensCommand(c) => Cmd::Lens {
                t_ns: t.0,
                id: c.id,
                power_d: c.power_d,
                reason: c.reason.clone(),
                eye: c.eye,
            },
            Rec::Render(c) => Cmd::Render {
                t_ns: t.0,
                frame: c.frame,
                method: c.method.clone(),
                focus_d: c.focus_d,
            },
            Rec::Present(c) => Cmd::Present {
                t_ns: t.0,
                frame: c.frame,
                layer: c.layer,
                at_ns: c.at_ns,
                repeat: c.repeat,
            },
            Rec::StopSequencer(_) => Cmd::StopSequencer { t_ns: t.0 },
            _ => return None,
        })
    }

    /// A command the replayed scheduler gave, in the form the daemon records it (`lenses`:
    /// the rig's, which name each lens's eye).
    fn replayed(t: Timestamp, c: &Command, lenses: &Lenses) -> Option<Cmd> {
        Some(match *c {
            Command::SetLensPower {
                lens,
                id,
                power,
                reason,
                ..
            } => Cmd::Lens {
                t_ns: t.0,
                id: id.0,
                power_d: power.0,
                reason: dioptra_rig::engine::reason_name(reason),
                eye: lenses.side(lens.index()),
            },
            Command::RenderFrame(req) => Cmd::Render {
                t_ns: t.0,
                frame: req.frame.0,
                method: req.method.as_str().into(),
                focus_d: req.focus.map(|d| d.0),
            },
            Command::Present {
                frame,
                vsync,
                repeat,
                ..
            } => Cmd::Present {
                t_ns: t.0,
                frame: frame.0,
                layer: None,
                at_ns: vsync.0,
                repeat,
            },
            Command::PresentLayer {
                frame,
                layer,
                start,
                repeat,
                ..
            } => Cmd::Present {
                t_ns: t.0,
                frame: frame.0,
                layer: Some(layer),
                at_ns: start.0,
                repeat,
            },
            Command::StopSequencer => Cmd::StopSequencer { t_ns: t.0 },
            _ => return None,
        })
    }

    fn is_lens(&self) -> bool {
        matches!(self, Cmd::Lens { .. })
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub file: PathBuf,
    pub complete: bool,
    /// Rewritten by `dioptra recording recover` from a cut file.
    pub recovered: bool,
    pub from_start: bool,
    /// Started mid-run with the scheduler's state (through the API): the replay starts there.
    pub restored: bool,
    pub mode: String,
    pub method: String,
    /// Seconds from the first to the last message.
    pub duration_s: f64,
    /// Messages per topic.
    pub topics: BTreeMap<String, u64>,
    pub recorded: Vec<Cmd>,
    pub replayed: Vec<Cmd>,
    /// Commands equal in both, position by position, before the first difference.
    pub matching_prefix: usize,
    pub first_difference: Option<(Option<Cmd>, Option<Cmd>)>,
    pub scheduler: serde_json::Value,
}

impl ReplayReport {
    /// Same commands in the same order. A file cut off mid-write may lack the commands of its
    /// last inputs (they were in the lost chunk): replayed commands beyond the recorded ones
    /// then count as the cut, not a difference.
    pub fn identical(&self) -> bool {
        match &self.first_difference {
            None => true,
            Some((None, Some(_))) => !self.complete || self.recovered,
            Some(_) => false,
        }
    }

    pub fn verdict(&self) -> Verdict {
        if !self.from_start && !self.restored {
            Verdict::CannotCompare
        } else if self.identical() {
            Verdict::Identical
        } else {
            Verdict::Differs
        }
    }
}

pub fn run(args: Args) -> Result<()> {
    let report = replay_file(&args.file)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_summary(&report);
    }
    match report.verdict() {
        Verdict::Identical => Ok(()),
        Verdict::Differs => Err(crate::common::Exit::new(
            1,
            format!(
                "the replayed scheduler differs from the recording after {} matching commands",
                report.matching_prefix
            ),
        )
        .into()),
        Verdict::CannotCompare => Err(crate::common::Exit::new(
            2,
            "the recording began mid-run without the scheduler's state (it was started by a \
             daemon older than this one, or not through the API), so the replay (from a fresh \
             scheduler) cannot be compared command by command; record through POST \
             /recording/start or from daemon start (recording.start = true) to compare",
        )
        .into()),
    }
}

/// What a replay shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Identical,
    Differs,
    /// A recording started mid-run: nothing to compare against.
    CannotCompare,
}

fn print_summary(r: &ReplayReport) {
    println!("recording {}", r.file.display());
    println!(
        "  {:.2} s, mode {}, method {}, {}{}",
        r.duration_s,
        r.mode,
        r.method,
        if r.recovered {
            "recovered from a cut recording"
        } else if r.complete {
            "complete"
        } else {
            "cut off (read up to the cut)"
        },
        if r.from_start {
            ", recorded from daemon start"
        } else if r.restored {
            ", started mid-run (replayed from the scheduler's recorded state)"
        } else {
            ", started mid-run (the scheduler's history before it is unknown)"
        }
    );
    for (topic, n) in &r.topics {
        println!("  {topic:<14} {n}");
    }
    let lens = |v: &[Cmd]| v.iter().filter(|c| c.is_lens()).count();
    println!(
        "commands: recorded {} ({} lens), replayed {} ({} lens)",
        r.recorded.len(),
        lens(&r.recorded),
        r.replayed.len(),
        lens(&r.replayed),
    );
    if !r.from_start && !r.restored {
        println!(
            "not compared: the recording began mid-run, so a fresh scheduler cannot reproduce \
             its commands ({} replayed commands are in --json)",
            r.replayed.len()
        );
        return;
    }
    match &r.first_difference {
        None => println!("replay identical to the recording"),
        Some((None, Some(_))) if !r.complete || r.recovered => println!(
            "replay identical to the recording up to its cut ({} matching commands; the \
             replay's last {} fell in the lost part)",
            r.matching_prefix,
            r.replayed.len() - r.matching_prefix
        ),
        Some((a, b)) => println!(
            "first difference after {} matching commands: recorded {a:?}, replayed {b:?}",
            r.matching_prefix
        ),
    }
}

pub fn replay_file(path: &Path) -> Result<ReplayReport> {
    let rec = recording::read(path)?;
    let mut r = replay(&rec)?;
    r.file = path.to_path_buf();
    Ok(r)
}

/// The lens a recorded message's eye names: the right eye's is the second lens; the left
/// eye's, or a rig's one lens (no eye), the first.
fn lens_of(eye: Option<Side>) -> LensId {
    match eye {
        Some(Side::Right) => LensId(1),
        _ => LensId::FIRST,
    }
}

/// Replays a recording through a fresh scheduler.
pub fn replay(rec: &Recorded) -> Result<ReplayReport> {
    let Some((t0, Rec::Start(start))) = rec.messages.first() else {
        bail!("the recording does not begin with a /start message; was it written by `dioptra serve`?");
    };
    // With the calibration tables the run read, as they were then.
    let tables = start
        .calibration_tables
        .iter()
        .map(|(p, t)| (std::path::PathBuf::from(p), t.clone()))
        .collect();
    let mut cfg = RigConfig::parse_with_tables(&start.config, tables)
        .context("the rig config in the recording")?;
    cfg.mode = Mode::parse(&start.mode)
        .with_context(|| format!("unknown mode {:?} in the recording", start.mode))?;
    cfg.method = Method::parse(&start.method)
        .with_context(|| format!("unknown method {:?} in the recording", start.method))?;
    // Streamed content is replayed from its recorded depths: no shared-memory ring (one at the
    // recorded path could be a running daemon's).
    if cfg.content.source == ContentSource::Stream {
        cfg.content.ring = Some(PathBuf::from("none"));
    }
    // A recording without scene times is of a still scene (made before the scene moved, or
    // with content.animate = false).
    let animated = rec
        .messages
        .iter()
        .any(|(_, m)| matches!(m, Rec::Depth(d) if d.scene_ns.is_some()));
    if !animated && cfg.content.source == ContentSource::Scene {
        cfg.content.animate = Some(false);
    }
    // The procedural scene renders the depth of any scene time a /depth message names.
    let scene = match cfg.content.source {
        ContentSource::Scene => Some(
            AnimatedScene::start(
                cfg.display.scene_seed,
                scene::camera(&cfg.eye, &cfg.display)
                    .context("the recorded rig's eye and display")?,
                cfg.content.animate.unwrap_or(true),
                Pacing::Simulated,
            )
            .context("cannot render the recorded rig's scene")?,
        ),
        _ => None,
    };
    // The depth the daemon gave at its start: what a /depth message without a scene time
    // stands for (a still frame).
    let depth = match &scene {
        Some(s) => {
            let frame = s.frame_at(*t0).map_or_else(|| s.current().0, |(f, _)| f);
            Arc::new(frame.depth.clone())
        }
        None => dioptra_rig::content::open(
            &cfg.content,
            &cfg.display,
            &cfg.eye,
            &cfg.api,
            Pacing::Simulated,
        )
        .context("cannot open the recorded rig's content")?
        .poll(*t0)
        .context("the recorded rig's content has no frame")?
        .depth(),
    };
    let depth_at = |scene_ns: Option<u64>| -> Result<Arc<DepthMap>> {
        let Some(t) = scene_ns else {
            return Ok(depth.clone());
        };
        match &scene {
            Some(s) => Ok(Arc::new(
                s.render_at(Timestamp(t))
                    .with_context(|| format!("cannot render the scene at {} ms", t / 1_000_000))?
                    .depth,
            )),
            None => bail!("the recording has scene times, and its config's content is not the procedural scene"),
        }
    };
    let restored = start.scheduler_state.is_some();
    let mut engine = match &start.scheduler_state {
        // Started mid-run through the API: where the scheduler was, with the depth it had.
        Some(state) => Engine::restore(
            &cfg,
            cfg.mode,
            cfg.method,
            depth_at(start.depth_scene_ns)?,
            state,
        )
        .map_err(anyhow::Error::msg)
        .context("cannot restore the scheduler's state recorded in /start")?,
        None => Engine::new(&cfg)
            .map_err(anyhow::Error::msg)
            .context("cannot start the scheduler")?,
    };
    if !start.from_start && !restored {
        // The daemon gave the scene's depth at its start, before this recording began.
        let _ = engine.step(*t0, Input::Depth(depth.clone()));
    }
    if let Some(d) = start.manual_focus_d.filter(|_| !restored) {
        // Set before the recording began: its commands are not in the file.
        let _ = engine.step(*t0, Input::Control(Control::ManualFocus(Some(d))));
    }
    let mut topics = BTreeMap::new();
    let mut recorded = Vec::new();
    let mut replayed = Vec::new();
    let last = rec.messages.last().map_or(*t0, |(t, _)| *t);
    for (t, m) in &rec.messages {
        *topics.entry(m.topic().to_string()).or_insert(0u64) += 1;
        if let Some(c) = Cmd::recorded(*t, m) {
            recorded.push(c);
            continue;
        }
        let input = match m {
            Rec::Gaze(g) => Input::Device(DeviceInput::Gaze(g.into(), std::time::Instant::now())),
            Rec::LensState(s) => Input::Device(DeviceInput::LensState(lens_of(s.eye), s.into())),
            Rec::LensWire(w) => Input::Device(DeviceInput::LensWire {
                lens: lens_of(w.eye),
                id: w.id,
                requested: Diopters(w.requested_d),
                wire_time: Timestamp(w.wire_ns),
                host_path: None,
            }),
            Rec::LensLink(l) => Input::Device(DeviceInput::LensLink(lens_of(l.eye), l.up)),
            Rec::Sync(e) => Input::Device(DeviceInput::Sync(e.into())),
            Rec::Light(e) => Input::Device(DeviceInput::Light(e.into())),
            Rec::Frame(f) => Input::RenderFinished {
                frame: f.frame,
                method: Method::parse(&f.method)
                    .with_context(|| format!("unknown method {:?} in /frame", f.method))?,
                render_time: Duration::from_nanos(f.render_ns),
            },
            Rec::Depth(d) => Input::Depth(depth_at(d.scene_ns)?),
            Rec::Content(c) => Input::Content(dioptra_rig::content::Arrival {
                arrived: Timestamp(c.arrived_ns),
                ready: Timestamp(c.ready_ns),
            }),
            Rec::Tick(_) => Input::Tick,
            Rec::Shutdown(_) => Input::Shutdown,
            Rec::Control(c) => Input::Control(match c {
                ControlRec::Mode { mode } => Control::Mode(
                    Mode::parse(mode).with_context(|| format!("unknown mode {mode:?}"))?,
                ),
                ControlRec::Method { method } => Control::Method(
                    Method::parse(method).with_context(|| format!("unknown method {method:?}"))?,
                ),
                ControlRec::ManualFocus { diopters } => Control::ManualFocus(*diopters),
            }),
            // Start is first and handled above; commands were taken by Cmd::recorded.
            _ => continue,
        };
        // An input the scheduler refused produced no commands in the run either.
        let Ok(cmds) = engine.step(*t, input) else {
            continue;
        };
        replayed.extend(
            cmds.iter()
                .filter_map(|c| Cmd::replayed(*t, c, &cfg.devices.lens)),
        );
    }
    let matching_prefix = recorded
        .iter()
        .zip(&replayed)
        .take_while(|(a, b)| a == b)
        .count();
    let first_difference = (matching_prefix < recorded.len().max(replayed.len())).then(|| {
        (
            recorded.get(matching_prefix).cloned(),
            replayed.get(matching_prefix).cloned(),
        )
    });
    Ok(ReplayReport {
        file: PathBuf::new(),
        complete: rec.complete,
        recovered: rec.recovered,
        from_start: start.from_start,
        restored,
        mode: start.mode.clone(),
        method: start.method.clone(),
        duration_s: last.saturating_since(*t0).as_secs_f64(),
        topics,
        recorded,
        replayed,
        matching_prefix,
        first_difference,
        scheduler: engine.status(),
    })
}
