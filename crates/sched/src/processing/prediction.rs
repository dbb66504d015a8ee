//! Gaze prediction at a future time, for latency compensation: hold during fixation,
//! extrapolate pursuit linearly, and during a saccade extrapolate towards the landing point
//! the main sequence gives for the peak speed seen so far.

use dioptra_core::Timestamp;

use super::saccades::main_sequence_amplitude_deg;
use super::{Angles, EyePhase, GazeProcessor};

/// Predicted gaze at a requested time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PredictedGaze {
    /// The time asked for.
    pub at: Timestamp,
    /// How far ahead of the latest sample, µs (after clamping to `max_prediction_us`).
    pub horizon_us: u64,
    pub angles: Angles,
    /// Unit direction of `angles`, head frame.
    pub direction: [f64; 3],
    /// Fused vergence depth (held: vergence is slow against prediction horizons).
    pub diopters: Option<f64>,
    /// The phase the prediction was made in.
    pub phase: EyePhase,
}

impl GazeProcessor {
    /// Gaze predicted at `at` (host time). `None` before any valid sample. Times before the
    /// latest sample give the latest smoothed gaze.
    pub fn predict(&self, at: Timestamp) -> Option<PredictedGaze> {
        let st = &self.state;
        let base = st.smoothed?;
        let horizon_us = (at
            .saturating_since(st.time)
            .as_micros()
            .min(u128::from(u64::MAX)) as u64)
            .min(self.cfg.max_prediction_us);
        let h = horizon_us as f64 * 1e-6;
        let angles = match st.phase {
            EyePhase::Pursuit => {
                let (vy, vp) = st.window_velocity_dps;
                Angles {
                    yaw_deg: base.yaw_deg + vy * h,
                    pitch_deg: base.pitch_deg + vp * h,
                }
            }
            EyePhase::Saccade => self.predict_saccade(base, h),
            _ => base,
        };
        Some(PredictedGaze {
            at,
            horizon_us,
            angles,
            direction: angles.direction(),
            diopters: st.vergence.map(|v| v.diopters),
            phase: st.phase,
        })
    }

    fn predict_saccade(&self, now: Angles, h: f64) -> Angles {
        // Direction of travel from the last two samples.
        let n = self.history.len();
        let (Some(&(t0, a0)), Some(&(t1, a1))) = (
            n.checked_sub(2).and_then(|i| self.history.get(i)),
            self.history.last(),
        ) else {
            return now;
        };
        let dt = t1.saturating_since(t0).as_secs_f64();
        if dt <= 0.0 {
            return now;
        }
        let (vy, vp) = (
            (a1.yaw_deg - a0.yaw_deg) / dt,
            (a1.pitch_deg - a0.pitch_deg) / dt,
        );
        let linear = Angles {
            yaw_deg: now.yaw_deg + vy * h,
            pitch_deg: now.pitch_deg + vp * h,
        };
        let (Some((start, at_peak)), Some((_, peak))) =
            (self.saccade_start, self.detector.active())
        else {
            return linear;
        };
        let speed = vy.hypot(vp);
        let (dy, dp) = (now.yaw_deg - start.yaw_deg, now.pitch_deg - start.pitch_deg);
        let travelled = dy.hypot(dp);
        if travelled <= 0.0 || speed <= 0.0 {
            return linear;
        }
        // Saccades are near-symmetric: the peak comes about halfway. Before the peak both
        // that and the main sequence only bound the amplitude below; after it, average them.
        let from_peak = main_sequence_amplitude_deg(peak);
        let amplitude = if speed >= peak {
            from_peak.max(2.0 * travelled)
        } else {
            (0.5 * (from_peak + 2.0 * at_peak)).max(travelled)
        };
        let landing = Angles {
            yaw_deg: start.yaw_deg + dy / travelled * amplitude,
            pitch_deg: start.pitch_deg + dp / travelled * amplitude,
        };
        // Go linearly, but not past the landing point.
        let to_landing = now.distance_deg(&landing);
        if speed * h >= to_landing {
            landing
        } else {
            linear
        }
    }
}
