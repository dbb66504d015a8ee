//! Gaze signal processing, sans-IO: feed [`GazeSample`]s in time order, read back the eye's
//! phase (fixation, pursuit, saccade, blink), smoothed gaze, fused vergence depth, and a
//! prediction of gaze at a future time. Deterministic: the sample's `host_time` is the only
//! clock.
//!
//! ```
//! use dioptra_sched::processing::{GazeProcessor, ProcessorConfig};
//! # let samples: Vec<dioptra_core::GazeSample> = vec![];
//! let mut p = GazeProcessor::new(ProcessorConfig::default());
//! for s in &samples {
//!     let state = p.push(s);
//!     let _ = (state.phase, state.fixation, state.vergence);
//!     // Gaze 20 ms ahead, to compensate the display's latency.
//!     let _ahead = p.predict(s.host_time + std::time::Duration::from_millis(20));
//! }
//! ```

pub mod filters;
pub mod prediction;
pub mod saccades;
pub mod vergence;

use dioptra_core::{GazeSample, Timestamp};

use filters::{OneEuro, OneEuroConfig};
use glam::DVec3;
pub use prediction::PredictedGaze;
use saccades::{SaccadeConfig, SaccadeDetector, SaccadeEvent};
use vergence::{to_f64, unit, Vergence, V3};

/// Horizontal and vertical gaze angles, degrees: yaw positive to the right, pitch up.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Angles {
    pub yaw_deg: f64,
    pub pitch_deg: f64,
}

impl Angles {
    /// Angles of a direction in the head frame (+z forward, +x right, +y up).
    pub fn from_direction(d: V3) -> Angles {
        Angles {
            yaw_deg: d[0].atan2(d[2]).to_degrees(),
            pitch_deg: d[1].atan2(d[0].hypot(d[2])).to_degrees(),
        }
    }
    pub fn direction(&self) -> V3 {
        let (y, p) = (self.yaw_deg.to_radians(), self.pitch_deg.to_radians());
        [p.cos() * y.sin(), p.sin(), p.cos() * y.cos()]
    }
    /// Great-circle angle to `other`, degrees.
    pub fn distance_deg(&self, other: &Angles) -> f64 {
        let (a, b) = (
            DVec3::from(self.direction()),
            DVec3::from(other.direction()),
        );
        let c = a.dot(b).clamp(-1.0, 1.0);
        a.cross(b).length().atan2(c).to_degrees()
    }
}

/// What the eyes are doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum EyePhase {
    /// No valid sample yet.
    #[default]
    Unknown,
    Fixation,
    /// Slow following movement (between `pursuit_dps` and the saccade onset speed).
    Pursuit,
    Saccade,
    /// Both eyes invalid for less than `max_blink_us`.
    Blink,
    /// Both eyes invalid for longer: tracking lost.
    Lost,
}

impl EyePhase {
    pub fn as_str(self) -> &'static str {
        match self {
            EyePhase::Unknown => "unknown",
            EyePhase::Fixation => "fixation",
            EyePhase::Pursuit => "pursuit",
            EyePhase::Saccade => "saccade",
            EyePhase::Blink => "blink",
            EyePhase::Lost => "lost",
        }
    }
}

/// The current fixation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Fixation {
    pub start: Timestamp,
    /// Mean gaze direction over the fixation so far.
    pub centre: Angles,
    pub samples: u32,
}

/// Processor settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProcessorConfig {
    pub saccade: SaccadeConfig,
    pub smoothing: OneEuroConfig,
    /// Per-eye angular noise of the tracker, degrees (1 sd): sets vergence uncertainty.
    pub tracker_noise_deg: f64,
    /// Speed over the pursuit window above which a non-saccadic movement is pursuit, deg/s.
    pub pursuit_dps: f64,
    /// Window for the pursuit speed, µs (long, to average tracker noise away; split in
    /// thirds that must all move, so microsaccades are not pursuit).
    pub pursuit_window_us: u64,
    /// Both eyes lost for longer than this is tracking loss, not a blink, µs.
    pub max_blink_us: u64,
    /// Memory of the fused vergence estimate, µs. Vergence settles with a time constant of
    /// ~150 ms; a memory much shorter than that keeps the estimate from lagging it.
    pub vergence_time_constant_us: u64,
    /// Predictions further ahead than this are held at it, µs.
    pub max_prediction_us: u64,
}

impl Default for ProcessorConfig {
    fn default() -> Self {
        ProcessorConfig {
            saccade: SaccadeConfig::default(),
            smoothing: OneEuroConfig::default(),
            tracker_noise_deg: 0.5,
            pursuit_dps: 4.0,
            pursuit_window_us: 90_000,
            max_blink_us: 500_000,
            vergence_time_constant_us: 50_000,
            max_prediction_us: 100_000,
        }
    }
}

/// Everything the processor knows after the latest sample.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct GazeState {
    /// Host time of the latest sample.
    pub time: Timestamp,
    pub phase: EyePhase,
    pub phase_since: Timestamp,
    /// Cyclopean gaze of the latest valid sample, unfiltered.
    pub raw: Option<Angles>,
    /// Cyclopean gaze smoothed during fixations and passed through during saccades.
    pub smoothed: Option<Angles>,
    /// Instantaneous angular speed, deg/s.
    pub speed_dps: f64,
    /// Angular velocity over the pursuit window, deg/s (yaw, pitch).
    pub window_velocity_dps: (f64, f64),
    pub fixation: Option<Fixation>,
    /// Vergence of the latest sample with both eyes valid.
    pub vergence_raw: Option<Vergence>,
    /// Inverse-variance fused vergence over the current fixation.
    pub vergence: Option<Vergence>,
    pub saccades: u64,
    pub blinks: u64,
    /// Samples ignored because their time did not move forward.
    pub rejected: u64,
}

/// The sans-IO gaze processor.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct GazeProcessor {
    cfg: ProcessorConfig,
    state: GazeState,
    detector: SaccadeDetector,
    yaw_f: OneEuro,
    pitch_f: OneEuro,
    /// Recent (device time, angles) of valid samples, oldest first.
    history: Vec<(Timestamp, Angles)>,
    /// Last time at least one eye was valid.
    last_valid: Option<Timestamp>,
    /// Fused vergence accumulators: (sum of w x, sum of w, time of the last update).
    fuse: Option<(f64, f64, Timestamp)>,
    /// Where the current saccade began, and how far it had gone at its peak speed.
    saccade_start: Option<(Angles, f64)>,
    /// (yaw, pitch) from each eye's direction to the cyclopean one, both eyes last seen.
    eye_offsets: [Option<(f64, f64)>; 2],
}

const HISTORY_LEN: usize = 64;

fn valid_dir(e: &dioptra_core::EyeRay) -> Option<V3> {
    (e.valid && to_f64(e.origin_mm).is_finite())
        .then(|| unit(to_f64(e.direction)))
        .flatten()
        .map(|d| d.to_array())
}

impl GazeProcessor {
    pub fn new(cfg: ProcessorConfig) -> Self {
        GazeProcessor {
            cfg,
            state: GazeState::default(),
            detector: SaccadeDetector::new(cfg.saccade),
            yaw_f: OneEuro::new(cfg.smoothing),
            pitch_f: OneEuro::new(cfg.smoothing),
            history: Vec::with_capacity(HISTORY_LEN),
            last_valid: None,
            fuse: None,
            saccade_start: None,
            eye_offsets: [None, None],
        }
    }

    pub fn config(&self) -> &ProcessorConfig {
        &self.cfg
    }

    pub fn state(&self) -> &GazeState {
        &self.state
    }

    /// Peak angular speed so far of the running saccade, deg/s; `None` outside saccades.
    /// Speed below the peak means the saccade is decelerating towards its landing point.
    pub fn saccade_peak_dps(&self) -> Option<f64> {
        self.detector.active().map(|(_, peak)| peak)
    }

    fn set_phase(&mut self, phase: EyePhase, t: Timestamp) {
        if self.state.phase != phase {
            self.state.phase = phase;
            self.state.phase_since = t;
        }
    }

    /// Feeds one sample and returns the updated state. The state is on the host timeline
    /// (`host_time`); speeds and filters use `device_time` differences, since the device
    /// clock times intervals better than a clock mapping that is still settling (a burst of
    /// queued reports arrives microseconds apart). Samples whose host time does not move
    /// forward are counted in `rejected` and change nothing else.
    pub fn push(&mut self, s: &GazeSample) -> &GazeState {
        let t = s.host_time;
        let ts = s.device_time;
        if self.state.phase != EyePhase::Unknown && t <= self.state.time {
            self.state.rejected += 1;
            return &self.state;
        }
        self.state.time = t;
        let Some(dir) = self.cyclopean(s) else {
            self.invalid_sample(t);
            return &self.state;
        };
        let a = Angles::from_direction(dir);
        // A device clock that stops or steps back (a reboot) also breaks the history.
        let clock_restart = self.history.last().is_some_and(|h| ts <= h.0);
        let resumed = clock_restart
            || matches!(
                self.state.phase,
                EyePhase::Unknown | EyePhase::Blink | EyePhase::Lost
            );
        if resumed {
            // Never filter or differentiate across a gap.
            self.history.clear();
            self.detector.reset();
            self.fuse = None;
            self.start_fixation(t, ts, a);
        }
        self.last_valid = Some(t);
        let speed = self.instant_speed(ts, &a);
        if self.history.len() == HISTORY_LEN {
            self.history.remove(0);
        }
        self.history.push((ts, a));
        self.state.raw = Some(a);
        self.state.speed_dps = speed;
        self.state.window_velocity_dps = self.window_velocity(ts);

        match self.detector.update(ts, speed) {
            SaccadeEvent::Onset => {
                self.state.saccades += 1;
                // The saccade began at the previous sample, the last one still at rest.
                let start = self.history.iter().rev().nth(1).map_or(a, |h| h.1);
                self.saccade_start = Some((start, a.distance_deg(&start)));
                self.state.fixation = None;
                self.fuse = None;
                self.set_phase(EyePhase::Saccade, t);
            }
            SaccadeEvent::End { spurious } => {
                if spurious {
                    self.state.saccades = self.state.saccades.saturating_sub(1);
                }
                self.saccade_start = None;
                self.start_fixation(t, ts, a);
            }
            SaccadeEvent::None => {}
        }
        if let (Some((start, at_peak)), Some((_, peak))) =
            (&mut self.saccade_start, self.detector.active())
        {
            if speed >= peak {
                *at_peak = a.distance_deg(start);
            }
        }

        let t_s = ts.as_secs_f64();
        if self.state.phase == EyePhase::Saccade {
            // Pass saccades through unfiltered: smoothing must not lag them.
            self.yaw_f.reset_to(t_s, a.yaw_deg);
            self.pitch_f.reset_to(t_s, a.pitch_deg);
            self.state.smoothed = Some(a);
        } else {
            self.state.smoothed = Some(Angles {
                yaw_deg: self.yaw_f.filter(t_s, a.yaw_deg),
                pitch_deg: self.pitch_f.filter(t_s, a.pitch_deg),
            });
            let (vy, vp) = self.state.window_velocity_dps;
            let phase = if vy.hypot(vp) >= self.cfg.pursuit_dps {
                EyePhase::Pursuit
            } else {
                EyePhase::Fixation
            };
            self.set_phase(phase, t);
            if let Some(f) = &mut self.state.fixation {
                let n = f64::from(f.samples);
                f.centre.yaw_deg = (f.centre.yaw_deg * n + a.yaw_deg) / (n + 1.0);
                f.centre.pitch_deg = (f.centre.pitch_deg * n + a.pitch_deg) / (n + 1.0);
                f.samples = f.samples.saturating_add(1);
            }
        }

        self.state.vergence_raw = vergence::vergence(&s.left, &s.right, self.cfg.tracker_noise_deg);
        if self.state.phase != EyePhase::Saccade {
            if let Some(v) = self.state.vergence_raw {
                self.fuse_vergence(ts, v);
            }
        }
        &self.state
    }

    /// The gaze direction from between the eyes. With one eye, that eye's direction plus
    /// its offset from the cyclopean direction when both were last seen, so losing an eye
    /// does not jump the gaze by half the vergence angle.
    fn cyclopean(&mut self, s: &GazeSample) -> Option<V3> {
        match (valid_dir(&s.left), valid_dir(&s.right)) {
            (Some(l), Some(r)) => {
                let c = unit(DVec3::from(l) + DVec3::from(r))?.to_array();
                let ca = Angles::from_direction(c);
                let off = |d: V3| {
                    let a = Angles::from_direction(d);
                    (ca.yaw_deg - a.yaw_deg, ca.pitch_deg - a.pitch_deg)
                };
                self.eye_offsets = [Some(off(l)), Some(off(r))];
                Some(c)
            }
            (Some(d), None) | (None, Some(d)) => {
                let which = usize::from(valid_dir(&s.left).is_none());
                let Some((dy, dp)) = self.eye_offsets[which] else {
                    return Some(d);
                };
                let a = Angles::from_direction(d);
                Some(
                    Angles {
                        yaw_deg: a.yaw_deg + dy,
                        pitch_deg: a.pitch_deg + dp,
                    }
                    .direction(),
                )
            }
            (None, None) => None,
        }
    }

    /// `t` host time (reported), `ts` device time (for the filters).
    fn start_fixation(&mut self, t: Timestamp, ts: Timestamp, a: Angles) {
        self.state.fixation = Some(Fixation {
            start: t,
            centre: a,
            samples: 0,
        });
        let t_s = ts.as_secs_f64();
        self.yaw_f.reset_to(t_s, a.yaw_deg);
        self.pitch_f.reset_to(t_s, a.pitch_deg);
        self.set_phase(EyePhase::Fixation, t);
    }

    fn invalid_sample(&mut self, t: Timestamp) {
        self.detector.reset();
        self.saccade_start = None;
        let since = self.last_valid.map_or(u64::MAX, |v| {
            t.saturating_since(v).as_micros().min(u128::from(u64::MAX)) as u64
        });
        let phase = if since > self.cfg.max_blink_us {
            EyePhase::Lost
        } else {
            EyePhase::Blink
        };
        if phase == EyePhase::Blink && self.state.phase != EyePhase::Blink {
            self.state.blinks += 1;
        }
        self.set_phase(phase, t);
        self.state.fixation = None;
        self.state.vergence_raw = None;
        self.state.speed_dps = 0.0;
    }

    /// Speed over the last two sample intervals: one interval doubles the noise's share.
    fn instant_speed(&self, t: Timestamp, a: &Angles) -> f64 {
        let back = self.history.len().min(2);
        let Some(&(t0, a0)) = self
            .history
            .len()
            .checked_sub(back)
            .and_then(|i| self.history.get(i))
        else {
            return 0.0;
        };
        let dt = t.saturating_since(t0).as_secs_f64();
        if back == 0 || dt <= 0.0 {
            return 0.0;
        }
        a.distance_deg(&a0) / dt
    }

    /// Velocity over the pursuit window, or zero unless each third of the window moves
    /// faster than `pursuit_dps`: a microsaccade fills at most two thirds, pursuit all three.
    fn window_velocity(&self, t: Timestamp) -> (f64, f64) {
        let w = self.cfg.pursuit_window_us;
        let at = |back_us: u64| {
            let since = t.saturating_sub(std::time::Duration::from_micros(back_us));
            self.history.iter().find(|h| h.0 >= since).copied()
        };
        let marks = [
            at(w),
            at(w * 2 / 3),
            at(w / 3),
            self.history.last().copied(),
        ];
        let [Some(a), Some(b), Some(c), Some(d)] = marks else {
            return (0.0, 0.0);
        };
        let vel = |p: (Timestamp, Angles), q: (Timestamp, Angles)| {
            let dt = q.0.saturating_since(p.0).as_secs_f64();
            if dt <= 0.0 {
                return None;
            }
            Some((
                (q.1.yaw_deg - p.1.yaw_deg) / dt,
                (q.1.pitch_deg - p.1.pitch_deg) / dt,
            ))
        };
        // Less than most of a window is too little to call pursuit.
        if (d.0.saturating_since(a.0).as_micros() as f64) < 0.8 * w as f64 {
            return (0.0, 0.0);
        }
        let thirds = [vel(a, b), vel(b, c), vel(c, d)];
        let all_fast = thirds
            .iter()
            .all(|v| v.is_some_and(|(y, p)| y.hypot(p) >= self.cfg.pursuit_dps));
        match (all_fast, vel(a, d)) {
            (true, Some(v)) => v,
            _ => (0.0, 0.0),
        }
    }

    fn fuse_vergence(&mut self, t: Timestamp, v: Vergence) {
        if !v.diopters.is_finite() || v.sigma_d.is_nan() || v.sigma_d <= 0.0 {
            return;
        }
        let w = 1.0 / (v.sigma_d * v.sigma_d);
        let (mut swx, mut sw) = (0.0, 0.0);
        if let Some((sx, s, t0)) = self.fuse {
            let dt = t.saturating_since(t0).as_micros() as f64;
            let keep = (-dt / self.cfg.vergence_time_constant_us.max(1) as f64).exp();
            swx = sx * keep;
            sw = s * keep;
        }
        swx += w * v.diopters;
        sw += w;
        self.fuse = Some((swx, sw, t));
        self.state.vergence = Some(Vergence {
            diopters: swx / sw,
            sigma_d: 1.0 / sw.sqrt(),
            point_mm: v.point_mm,
            miss_mm: v.miss_mm,
        });
    }
}

#[cfg(test)]
mod tests;
