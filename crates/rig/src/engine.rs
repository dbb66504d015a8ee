//! The adapter between the daemon and [`dioptra_sched::Scheduler`]: the rig config becomes a
//! [`SchedulerConfig`], the daemon's inputs become scheduler events, and API commands the
//! scheduler would ignore (a method that does not suit the mode) are refused here with a
//! reason, so the API can say why. The daemon loop and `dioptra replay` both drive the
//! scheduler through this one adapter, so a replay sees exactly what the run saw.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{DepthMap, Diopters, PlaneSchedule, PowerRange, Side, Timestamp};
use dioptra_sched::{
    CommandId, DisplayTiming, Event, FrameId, LensDynamics, LinkStatus, RenderMethod, RightLens,
    Scheduler, SchedulerConfig,
};
use serde_json::json;

pub use dioptra_sched::Command;

use crate::config::RigConfig;
use crate::content::frame::Arrival;
use crate::devices::config::{LensDevice, Lenses};
use crate::devices::input::DeviceInput;
use crate::mode::{Method, Mode};
use crate::recording::ControlRec;

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

/// What the daemon gives the scheduler.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    Device(DeviceInput),
    Control(Control),
    /// The depth map of the content being shown (diopters), read at the gaze point.
    Depth(Arc<DepthMap>),
    /// The content frame of the latest depth arrived and was ready then.
    Content(Arrival),
    RenderFinished {
        frame: u64,
        method: Method,
        render_time: Duration,
    },
    /// A timer the scheduler asked for ([`Engine::next_wakeup`]).
    Tick,
    Shutdown,
}

/// `FixationOnset` -> `fixation_onset`: how recordings and the stream name a focus reason.
pub fn reason_name(r: dioptra_sched::FocusReason) -> String {
    let mut out = String::new();
    for (i, ch) in format!("{r:?}").chars().enumerate() {
        if ch.is_ascii_uppercase() && i > 0 {
            out.push('_');
        }
        out.push(ch.to_ascii_lowercase());
    }
    out
}

/// The scheduler, configured from a rig config.
pub struct Engine {
    sched: Scheduler,
    /// Modes the network cannot render in, and why (its weights did not load).
    network_missing: Vec<(Mode, RenderMethod, String)>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Engine").finish_non_exhaustive()
    }
}

/// The scheduler's settings for a rig.
pub fn sched_config(cfg: &RigConfig) -> Result<SchedulerConfig, String> {
    let mut s = SchedulerConfig::new(cfg.mode.sched());
    s.method = cfg.method.0;
    s.eye = cfg.eye_model();
    let r = cfg.optics.lens_range;
    s.lens_range = PowerRange::new(Diopters(r.min), Diopters(r.max))
        .ok_or("optics.lens_range: min must be below max")?;
    let dynamics = |l: &LensDevice| LensDynamics {
        settle_time: Duration::from_secs_f64(l.model_settle_ms() / 1000.0),
        ..LensDynamics::default()
    };
    let first = cfg.devices.lens.first();
    s.lens = dynamics(first);
    s.park_power = Diopters(first.park_power);
    let map = |side| cfg.optics_map(side).map_err(|e| e.to_string());
    match &cfg.devices.lens {
        // One map for the rig's one lens.
        Lenses::One(_) => s.optics = map(None)?,
        // A lens per eye: both follow the one fixation estimate, each through its own eye's
        // optics map and its own model.
        Lenses::PerEye { right, .. } => {
            s.optics = map(Some(Side::Left))?;
            s.right_lens = Some(RightLens {
                lens: dynamics(right),
                optics: map(Some(Side::Right))?,
                park_power: Diopters(right.park_power),
            });
        }
    }
    let period = Duration::from_secs_f64(1.0 / cfg.display.frame_hz);
    s.display = DisplayTiming {
        frame_period: period,
        render_lead: period,
        ..DisplayTiming::default()
    };
    // Always given, so that the API can switch to multifocal mode.
    s.planes = Some(
        PlaneSchedule::new(
            cfg.optics.planes.iter().copied().map(Diopters).collect(),
            Duration::from_secs_f64(1.0 / cfg.optics.subframe_hz),
            Duration::from_secs_f64(0.25 / cfg.optics.subframe_hz),
        )
        .map_err(|e| format!("optics.planes: {e}"))?,
    );
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
}

impl Engine {
    /// A scheduler for `cfg`.
    pub fn new(cfg: &RigConfig) -> Result<Engine, String> {
        Self::with_config(sched_config(cfg)?)
    }

    /// The scheduler of `cfg` in the `state` a recording started mid-run holds
    /// ([`dioptra_sched::Scheduler::state`]), in `mode` with `method`, the content's `depth`
    /// map as it had it: where a replay of that recording starts.
    pub fn restore(
        cfg: &RigConfig,
        mode: Mode,
        method: Method,
        depth: Arc<DepthMap>,
        state: &serde_json::Value,
    ) -> Result<Engine, String> {
        let sched = Scheduler::restore(
            sched_config(cfg)?,
            mode.sched(),
            method.0,
            Some(depth),
            state,
        )
        .map_err(|e| e.to_string())?;
        Ok(Engine {
            sched,
            network_missing: Vec::new(),
        })
    }

    /// A scheduler with settings of its own (the simulated-rig builder tunes them).
    pub fn with_config(cfg: SchedulerConfig) -> Result<Engine, String> {
        let sched = Scheduler::new(cfg).map_err(|e| e.to_string())?;
        Ok(Engine {
            sched,
            network_missing: Vec::new(),
        })
    }

    /// Tells the engine in which modes a net's method cannot render (from
    /// [`crate::render::Renderer::network_missing`]), so that the API refuses to switch to it.
    pub fn set_network_missing(&mut self, missing: Vec<(Mode, RenderMethod, String)>) {
        self.network_missing = missing;
    }

    fn network_missing(&self, mode: Mode, method: Method) -> Option<String> {
        self.network_missing
            .iter()
            .find(|(m, r, _)| *m == mode && *r == method.0)
            .map(|(_, _, why)| why.clone())
    }

    pub fn mode(&self) -> Mode {
        Mode::from_sched(self.sched.config().mode)
    }
    pub fn method(&self) -> Method {
        Method(self.sched.config().method)
    }
    pub fn next_wakeup(&self) -> Option<Timestamp> {
        self.sched.next_wakeup()
    }
    pub fn scheduler(&self) -> &Scheduler {
        &self.sched
    }

    /// Steps the scheduler. API commands it would ignore are refused with the reason.
    pub fn step(&mut self, now: Timestamp, input: Input) -> Result<Vec<Command>, String> {
        let mut then_method = None;
        let event = match input {
            Input::Device(d) => match d {
                DeviceInput::Gaze(g, _) => Event::Gaze(g),
                DeviceInput::LensState(lens, s) => Event::LensState(lens, s),
                DeviceInput::LensWire {
                    lens,
                    id,
                    wire_time,
                    ..
                } => Event::LensCommandWritten {
                    lens,
                    id: CommandId(id),
                    wire_time,
                },
                DeviceInput::LensLink(lens, up) => Event::LensLink(
                    lens,
                    if up {
                        LinkStatus::Connected
                    } else {
                        LinkStatus::Lost
                    },
                ),
                DeviceInput::Sync(e) => Event::Sequencer(e),
                // The scheduler does not use the light: hooks (`dioptra hil`) do.
                DeviceInput::Light(_) => Event::Tick,
            },
            Input::Control(c) => match c {
                Control::ManualFocus(d) => Event::ManualFocus(d.map(Diopters)),
                Control::Method(m) => {
                    if !m.fits(self.mode()) {
                        return Err(format!(
                            "{} does not make {} frames; use {}, or change the mode first \
                             (POST /mode)",
                            m.as_str(),
                            self.mode().as_str(),
                            Method::for_mode(self.mode())
                        ));
                    }
                    if let Some(why) = m
                        .unavailable(self.mode())
                        .or_else(|| self.network_missing(self.mode(), m))
                    {
                        return Err(why);
                    }
                    Event::SetMethod(m.0)
                }
                Control::Mode(m) => {
                    // The current method if the new mode renders it, else the mode's default
                    // (from multifocal with the network, lightfield mode shows views: C5 is
                    // not rendered by the daemon). Missing weights refuse the switch.
                    let current = self.method();
                    let method = if current.fits(m) && current.unavailable(m).is_none() {
                        current
                    } else {
                        Method(RenderMethod::default_for(m.sched()))
                    };
                    if let Some(why) = method
                        .unavailable(m)
                        .or_else(|| self.network_missing(m, method))
                    {
                        return Err(format!(
                            "{} mode would render with {}, and {why}",
                            m.as_str(),
                            method.as_str()
                        ));
                    }
                    // The scheduler keeps a method that suits the mode: say the switch.
                    if method != current && current.fits(m) {
                        then_method = Some(method.0);
                    }
                    Event::SetMode(m.sched())
                }
            },
            Input::Depth(d) => Event::Depth(d),
            Input::Content(a) => Event::Content {
                arrived: a.arrived,
                ready: a.ready,
            },
            Input::RenderFinished {
                frame,
                method,
                render_time,
            } => Event::RenderFinished {
                frame: FrameId(frame),
                method: method.0,
                render_time,
            },
            Input::Tick => Event::Tick,
            Input::Shutdown => Event::Shutdown,
        };
        let mut out = Vec::new();
        self.sched.step(now, event, &mut out);
        if let Some(m) = then_method {
            self.sched.step(now, Event::SetMethod(m), &mut out);
        }
        Ok(out)
    }

    /// The scheduler's status and latency figures, for `GET /status` and replay reports.
    pub fn status(&self) -> serde_json::Value {
        let s = self.sched.status();
        let c = s.counters;
        let lat = self.sched.latency();
        let stages: serde_json::Map<String, serde_json::Value> = dioptra_sched::Stage::ALL
            .iter()
            .filter_map(|&st| {
                let h = lat.stage(st);
                (!h.is_empty()).then(|| {
                    (
                        st.as_str().to_string(),
                        json!({
                            "count": h.len(),
                            "p50_us": h.value_at_quantile(0.5),
                            "p99_us": h.value_at_quantile(0.99),
                            "max_us": h.max(),
                        }),
                    )
                })
            })
            .collect();
        json!({
            "mode": Mode::from_sched(s.mode).as_str(),
            "method": s.method.as_str(),
            "phase": format!("{:?}", s.phase).to_lowercase(),
            "vergence_d": s.vergence_d,
            "fixation_depth_d": s.fixation_depth.map(|d| d.0),
            "commanded_d": s.commanded_power.map(|d| d.0),
            "commanded_focus_d": s
                .commanded_power
                .map(|p| self.sched.config().optics.focus_of(p).0),
            "lens_link": format!("{:?}", s.lens_link).to_lowercase(),
            "last_settle_ms": s.last_settle.map(|d| d.as_secs_f64() * 1e3),
            "shown_frame": s.shown_frame.map(|f| f.0),
            "counters": {
                "gaze_samples": c.gaze_samples,
                "saccades": c.saccades,
                "blinks": c.blinks,
                "lens_commands": c.lens_commands,
                "lens_commands_held": c.lens_commands_held,
                "lens_readbacks": c.lens_readbacks,
                "lens_link_losses": c.lens_link_losses,
                "frames_requested": c.frames_requested,
                "frames_rendered": c.frames_rendered,
                "frames_presented": c.frames_presented,
                "misses": c.misses,
                "late_frames": c.late_frames,
                "renders_skipped": c.renders_skipped,
                "sequencer_faults": c.sequencer_faults,
                "ignored_events": c.ignored_events,
            },
            "latency_us": stages,
        })
    }
}
