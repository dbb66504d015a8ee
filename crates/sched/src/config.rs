//! Scheduler settings. [`SchedulerConfig::validate`] names the field and the expected form of
//! anything wrong, so a rig config file's errors can say which key to fix.

use std::str::FromStr;
use std::time::Duration;

use dioptra_core::{Diopters, EyeModel, OpticsMap, PlaneSchedule, PowerRange};
use thiserror::Error;

use crate::depth::DepthWindow;
use crate::lens::LensDynamics;
use crate::processing::ProcessorConfig;

/// What kind of display the loop drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Mode {
    /// One image per frame; gaze drives a focus-tunable lens.
    Varifocal,
    /// One layer per sub-frame, in lockstep with the sync hardware's plane schedule.
    Multifocal,
    /// One panel image per frame (elemental images behind a lenslet array); the lens holds.
    LightField,
}

impl Mode {
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Varifocal => "varifocal",
            Mode::Multifocal => "multifocal",
            Mode::LightField => "lightfield",
        }
    }
}

impl FromStr for Mode {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "varifocal" => Ok(Mode::Varifocal),
            "multifocal" => Ok(Mode::Multifocal),
            "lightfield" | "light-field" => Ok(Mode::LightField),
            _ => Err(ConfigError::invalid(
                "mode",
                format!("{s:?}: expected varifocal, multifocal or lightfield"),
            )),
        }
    }
}

/// How a frame is made. The scheduler only passes it through to the renderer and keeps render
/// times per method; which methods suit which mode is [`RenderMethod::suits`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RenderMethod {
    /// Defocus by gathering (varifocal).
    Gather,
    /// Gather's sums with large blurs spread at the resolution they leave: work per pixel
    /// bounded whatever the blur (varifocal); foveated around the gaze where the rig says.
    Pyramid,
    /// Defocus through a dynamic light field, Yu et al. 2010 (varifocal).
    LightFieldDefocus,
    /// The DeepFocus-family network (any mode it was trained for).
    Network,
    /// Linear blending of RGB-D into layers (multifocal).
    Linear,
    /// Optimized blending into layers (multifocal).
    Optimized,
    /// The spectral decomposition into layers: the least squares solved per spatial frequency
    /// (multifocal).
    Spectral,
    /// The gaze-contingent hybrid (after Yu et al. 2019): spectral layers around the gaze where
    /// a blurred depth step reaches it, linear blending elsewhere (multifocal).
    Hybrid,
    /// Light-field views resampled into elemental images (light field).
    Views,
    /// A classical result corrected by a refinement net (varifocal: C1R on its classical
    /// render; multifocal: C4R on linear blending).
    Refine,
}

impl RenderMethod {
    pub const ALL: [RenderMethod; 10] = [
        RenderMethod::Gather,
        RenderMethod::Pyramid,
        RenderMethod::LightFieldDefocus,
        RenderMethod::Network,
        RenderMethod::Linear,
        RenderMethod::Optimized,
        RenderMethod::Spectral,
        RenderMethod::Hybrid,
        RenderMethod::Views,
        RenderMethod::Refine,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            RenderMethod::Gather => "gather",
            RenderMethod::Pyramid => "pyramid",
            RenderMethod::LightFieldDefocus => "lightfield-defocus",
            RenderMethod::Network => "network",
            RenderMethod::Linear => "linear",
            RenderMethod::Optimized => "optimized",
            RenderMethod::Spectral => "spectral",
            RenderMethod::Hybrid => "hybrid",
            RenderMethod::Views => "views",
            RenderMethod::Refine => "refine",
        }
    }

    /// Whether this method makes what `mode` displays.
    pub fn suits(self, mode: Mode) -> bool {
        use RenderMethod::*;
        match mode {
            Mode::Varifocal => {
                matches!(
                    self,
                    Gather | Pyramid | LightFieldDefocus | Network | Refine
                )
            }
            Mode::Multifocal => matches!(
                self,
                Linear | Optimized | Spectral | Hybrid | Network | Refine
            ),
            Mode::LightField => matches!(self, Views | Network | Refine),
        }
    }

    /// The method a mode uses unless told otherwise.
    pub fn default_for(mode: Mode) -> RenderMethod {
        match mode {
            Mode::Varifocal => RenderMethod::Gather,
            Mode::Multifocal => RenderMethod::Linear,
            Mode::LightField => RenderMethod::Views,
        }
    }
}

impl FromStr for RenderMethod {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        RenderMethod::ALL
            .into_iter()
            .find(|m| m.as_str() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = RenderMethod::ALL.iter().map(|m| m.as_str()).collect();
                ConfigError::invalid("method", format!("{s:?}: expected one of {names:?}"))
            })
    }
}

/// How gaze turns into lens commands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FocusPolicy {
    /// A new focus target within this of the commanded one is not sent, diopters (the eye's
    /// depth of field is about ±0.3 D: smaller changes are not seen, only chased).
    pub deadband_d: f32,
    /// During a fixation, a target outside the deadband must hold this long before it is sent
    /// (at fixation onset it is sent at once).
    pub confirm: Duration,
    /// During a fixation, at most one command per this interval.
    pub min_interval: Duration,
    /// Command the lens to the depth at the predicted saccade landing point once the saccade
    /// decelerates, so the lens moves during saccadic suppression.
    pub predict_landing: bool,
    /// Window around the gaze point the depth is read from.
    pub window: DepthWindow,
    /// Without a depth map, vergence alone sets focus when its 1-sd uncertainty is below this.
    pub vergence_only_max_sigma_d: f64,
    /// A "saccade" smaller than this, degrees, is tracker noise or a microsaccade: the
    /// fixation goes on (no onset command, no landing prediction).
    pub min_saccade_deg: f64,
}

impl Default for FocusPolicy {
    fn default() -> Self {
        FocusPolicy {
            deadband_d: 0.15,
            confirm: Duration::from_millis(60),
            min_interval: Duration::from_millis(150),
            predict_landing: true,
            window: DepthWindow::default(),
            vergence_only_max_sigma_d: 0.3,
            min_saccade_deg: 1.0,
        }
    }
}

/// The right eye's lens on a rig with a lens per eye: its own step response, optics map and
/// park power (each lens is built and calibrated on its own).
#[derive(Debug, Clone, PartialEq)]
pub struct RightLens {
    pub lens: LensDynamics,
    /// Made for `lens_range`, like [`SchedulerConfig::optics`].
    pub optics: OpticsMap,
    pub park_power: Diopters,
}

/// Display timing for whole-frame modes (varifocal, light field). Multifocal frames follow the
/// sync hardware's events instead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DisplayTiming {
    pub frame_period: Duration,
    /// From a frame's vsync to its light reaching the eye (scan-out, persistence midpoint).
    pub latency: Duration,
    /// A frame is requested this long before its vsync (the render budget).
    pub render_lead: Duration,
}

impl Default for DisplayTiming {
    fn default() -> Self {
        DisplayTiming {
            frame_period: Duration::from_nanos(16_666_667),
            latency: Duration::from_millis(4),
            render_lead: Duration::from_nanos(16_666_667),
        }
    }
}

/// Everything the scheduler needs to know about the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct SchedulerConfig {
    pub mode: Mode,
    pub method: RenderMethod,
    /// The eye, and the field the depth maps span (`fov_horizontal_deg`).
    pub eye: EyeModel,
    /// The lens powers the scheduler may command (drivers enforce their own limits too).
    pub lens_range: PowerRange,
    pub lens: LensDynamics,
    /// Focus (the accommodation demand the content asks of the eye) <-> lens command: the
    /// rig's optics and the viewer's prescription. Made for `lens_range`; the identity by
    /// default (the lens's power is the image's vergence, as in the simulated rig).
    pub optics: OpticsMap,
    /// The lens is left here on shutdown.
    pub park_power: Diopters,
    /// The right eye's lens, on a rig with a lens per eye (`lens`, `optics` and
    /// `park_power` are then the left eye's). One fixation estimate drives both.
    pub right_lens: Option<RightLens>,
    pub focus: FocusPolicy,
    pub gaze: ProcessorConfig,
    pub display: DisplayTiming,
    /// The multifocal plane schedule (required in multifocal mode).
    pub planes: Option<PlaneSchedule>,
    /// A readback within this of the model's prediction leaves the model alone, diopters.
    pub readback_tolerance_d: f32,
    /// Settled means within this of the commanded power, diopters.
    pub settled_tolerance_d: f32,
}

impl SchedulerConfig {
    /// How many lenses the scheduler drives: 1, or 2 (a lens per eye).
    pub fn lens_count(&self) -> usize {
        1 + usize::from(self.right_lens.is_some())
    }

    /// The optics map of `lens`: focus <-> that lens's command.
    pub fn optics_of(&self, lens: crate::LensId) -> &OpticsMap {
        match (lens.0, &self.right_lens) {
            (1, Some(r)) => &r.optics,
            _ => &self.optics,
        }
    }

    /// `lens`'s step response.
    pub fn dynamics_of(&self, lens: crate::LensId) -> LensDynamics {
        match (lens.0, &self.right_lens) {
            (1, Some(r)) => r.lens,
            _ => self.lens,
        }
    }

    /// Where `lens` is left on shutdown.
    pub fn park_power_of(&self, lens: crate::LensId) -> Diopters {
        match (lens.0, &self.right_lens) {
            (1, Some(r)) => r.park_power,
            _ => self.park_power,
        }
    }

    /// Defaults for `mode`: DeepFocus's eye, a 0-4 D lens, 60 Hz frames, and in multifocal
    /// mode DeepFocus's planes (0.2, 0.8, 1.4, 2.0 D) at 240 sub-frames per second.
    pub fn new(mode: Mode) -> Self {
        let planes = (mode == Mode::Multifocal)
            .then(|| {
                PlaneSchedule::new(
                    [0.2, 0.8, 1.4, 2.0].map(Diopters).to_vec(),
                    Duration::from_nanos(4_166_667),
                    Duration::from_micros(1_500),
                )
                .ok()
            })
            .flatten();
        let lens_range = PowerRange {
            min: Diopters(0.0),
            max: Diopters(4.0),
        };
        SchedulerConfig {
            mode,
            method: RenderMethod::default_for(mode),
            eye: EyeModel::default(),
            lens_range,
            lens: LensDynamics::default(),
            optics: OpticsMap::identity(lens_range),
            park_power: Diopters(0.0),
            right_lens: None,
            focus: FocusPolicy::default(),
            gaze: ProcessorConfig::default(),
            display: DisplayTiming::default(),
            planes,
            readback_tolerance_d: 0.05,
            settled_tolerance_d: 0.03,
        }
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.eye
            .validated()
            .map_err(|e| ConfigError::invalid("eye", e.to_string()))?;
        if !self.method.suits(self.mode) {
            return Err(ConfigError::invalid(
                "method",
                format!(
                    "{} does not make {} frames; use {}",
                    self.method.as_str(),
                    self.mode.as_str(),
                    RenderMethod::default_for(self.mode).as_str()
                ),
            ));
        }
        if PowerRange::new(self.lens_range.min, self.lens_range.max).is_none() {
            return Err(ConfigError::invalid(
                "lens_range",
                format!(
                    "{}..{} D: expected finite min <= max",
                    self.lens_range.min.0, self.lens_range.max.0
                ),
            ));
        }
        if !self.lens_range.contains(self.park_power) {
            return Err(ConfigError::invalid(
                "park_power",
                format!(
                    "{} D is outside the lens range {}..{} D",
                    self.park_power.0, self.lens_range.min.0, self.lens_range.max.0
                ),
            ));
        }
        let right = self.right_lens.as_ref();
        for (key, d) in [
            ("lens", Some(&self.lens)),
            ("right_lens.lens", right.map(|r| &r.lens)),
        ] {
            let Some(d) = d else { continue };
            if d.settle_time.is_zero() || d.damping.is_nan() || d.damping <= 0.0 {
                return Err(ConfigError::invalid(
                    key,
                    "settle_time must be > 0 and damping > 0 (e.g. 15 ms, 0.7)",
                ));
            }
        }
        for (key, o) in [
            ("optics", Some(&self.optics)),
            ("right_lens.optics", right.map(|r| &r.optics)),
        ] {
            let Some(o) = o else { continue };
            if o.range() != self.lens_range {
                let r = o.range();
                return Err(ConfigError::invalid(
                    key,
                    format!(
                        "the optics map was made for a lens range of {}..{} D, and lens_range is \
                         {}..{} D: make the map for the range the scheduler drives",
                        r.min.0, r.max.0, self.lens_range.min.0, self.lens_range.max.0
                    ),
                ));
            }
        }
        if let Some(r) = right {
            if !self.lens_range.contains(r.park_power) {
                return Err(ConfigError::invalid(
                    "right_lens.park_power",
                    format!(
                        "{} D is outside the lens range {}..{} D",
                        r.park_power.0, self.lens_range.min.0, self.lens_range.max.0
                    ),
                ));
            }
        }
        let f = &self.focus;
        if !(f.deadband_d.is_finite() && f.deadband_d >= 0.0) {
            return Err(ConfigError::invalid(
                "focus.deadband_d",
                "expected a finite number >= 0 D, e.g. 0.15",
            ));
        }
        if !(f.window.radius_deg.is_finite()
            && f.window.radius_deg > 0.0
            && f.window.bin_d.is_finite()
            && f.window.bin_d > 0.0)
        {
            return Err(ConfigError::invalid(
                "focus.window",
                "radius_deg and bin_d must be > 0, e.g. 0.75 deg and 0.05 D",
            ));
        }
        if self.display.frame_period.is_zero() {
            return Err(ConfigError::invalid(
                "display.frame_period",
                "must be > 0, e.g. 16.7 ms for 60 Hz",
            ));
        }
        if self.mode == Mode::Multifocal && self.planes.is_none() {
            return Err(ConfigError::invalid(
                "planes",
                "multifocal mode needs a plane schedule, e.g. 0.2, 0.8, 1.4, 2.0 D",
            ));
        }
        if !(self.readback_tolerance_d > 0.0 && self.settled_tolerance_d > 0.0) {
            return Err(ConfigError::invalid(
                "readback_tolerance_d",
                "tolerances must be > 0 D",
            ));
        }
        Ok(())
    }
}

/// A setting the scheduler cannot run with.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ConfigError {
    #[error("scheduler setting `{key}` is invalid: {problem}")]
    Invalid { key: &'static str, problem: String },
    #[error("cannot make the latency histograms: {0}")]
    Histogram(String),
}

impl ConfigError {
    pub fn invalid(key: &'static str, problem: impl Into<String>) -> Self {
        ConfigError::Invalid {
            key,
            problem: problem.into(),
        }
    }
}
