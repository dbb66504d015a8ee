//! Saccade detection: a velocity threshold with hysteresis (enter above `onset_dps`, leave
//! after `offset_samples` consecutive samples below `offset_dps`), and the fixation that
//! follows each saccade.

use dioptra_core::Timestamp;

/// Saccade detector settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SaccadeConfig {
    /// Angular speed that starts a saccade, degrees/s.
    pub onset_dps: f64,
    /// Speed below which a saccade may end, degrees/s (below `onset_dps`: the hysteresis).
    pub offset_dps: f64,
    /// Consecutive samples below `offset_dps` that end a saccade.
    pub offset_samples: u32,
    /// A movement above `onset_dps` shorter than this is not a saccade (a spike), µs; the
    /// saccade is still reported at onset, and retracted when it ends this early.
    pub min_duration_us: u64,
}

impl Default for SaccadeConfig {
    fn default() -> Self {
        // 70 deg/s onset sits above tracker noise and microsaccades (< 1 deg, < 60 deg/s)
        // and below the peak of a 2 deg saccade (~150 deg/s).
        SaccadeConfig {
            onset_dps: 70.0,
            offset_dps: 30.0,
            offset_samples: 2,
            min_duration_us: 0,
        }
    }
}

/// What the detector concluded from one speed sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SaccadeEvent {
    None,
    Onset,
    /// The saccade ended; `spurious` when it was shorter than `min_duration_us`.
    End {
        spurious: bool,
    },
}

/// The hysteresis state machine on angular speed.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SaccadeDetector {
    cfg: SaccadeConfig,
    /// Onset time and peak speed while a saccade runs.
    active: Option<(Timestamp, f64)>,
    below: u32,
}

impl SaccadeDetector {
    pub fn new(cfg: SaccadeConfig) -> Self {
        SaccadeDetector {
            cfg,
            active: None,
            below: 0,
        }
    }

    pub fn config(&self) -> &SaccadeConfig {
        &self.cfg
    }

    /// Feeds the angular speed at `t`.
    pub fn update(&mut self, t: Timestamp, speed_dps: f64) -> SaccadeEvent {
        let speed = if speed_dps.is_finite() {
            speed_dps
        } else {
            0.0
        };
        match &mut self.active {
            None if speed >= self.cfg.onset_dps => {
                self.active = Some((t, speed));
                self.below = 0;
                SaccadeEvent::Onset
            }
            None => SaccadeEvent::None,
            Some((start, peak)) => {
                *peak = peak.max(speed);
                if speed < self.cfg.offset_dps {
                    self.below += 1;
                } else {
                    self.below = 0;
                }
                if self.below >= self.cfg.offset_samples.max(1) {
                    let spurious = t.saturating_since(*start).as_micros()
                        < u128::from(self.cfg.min_duration_us);
                    self.active = None;
                    SaccadeEvent::End { spurious }
                } else {
                    SaccadeEvent::None
                }
            }
        }
    }

    /// Onset time and peak speed so far of the running saccade.
    pub fn active(&self) -> Option<(Timestamp, f64)> {
        self.active
    }

    /// Forgets a running saccade (tracking lost).
    pub fn reset(&mut self) {
        self.active = None;
        self.below = 0;
    }
}

/// Saccade duration predicted by the main sequence, ms (Carpenter 1988: 2.2 ms/deg + 21 ms).
pub fn main_sequence_duration_ms(amplitude_deg: f64) -> f64 {
    2.2 * amplitude_deg.abs() + 21.0
}

/// Peak speed of a minimum-jerk saccade that follows the main-sequence duration, deg/s.
pub fn main_sequence_peak_dps(amplitude_deg: f64) -> f64 {
    1875.0 * amplitude_deg.abs() / main_sequence_duration_ms(amplitude_deg)
}

/// Inverse of [`main_sequence_peak_dps`]: amplitude of a saccade with this peak speed.
/// Saturates at 90 degrees (the peak speed's asymptote is 852 deg/s).
pub fn main_sequence_amplitude_deg(peak_dps: f64) -> f64 {
    let v = peak_dps.max(0.0);
    let denom = 1875.0 - 2.2 * v;
    if denom <= 21.0 * v / 90.0 {
        return 90.0;
    }
    (21.0 * v / denom).min(90.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hysteresis_keeps_a_saccade_through_a_dip_and_ends_after_quiet_samples() {
        let mut d = SaccadeDetector::new(SaccadeConfig::default());
        let t = |i: u64| Timestamp::from_millis(i * 2);
        assert_eq!(d.update(t(0), 20.0), SaccadeEvent::None);
        assert_eq!(d.update(t(1), 69.0), SaccadeEvent::None);
        assert_eq!(d.update(t(2), 80.0), SaccadeEvent::Onset);
        assert_eq!(d.update(t(3), 50.0), SaccadeEvent::None); // above offset: still in
        assert_eq!(d.update(t(4), 400.0), SaccadeEvent::None);
        assert_eq!(d.update(t(5), 20.0), SaccadeEvent::None);
        assert_eq!(d.update(t(6), 35.0), SaccadeEvent::None); // resets the quiet count
        assert_eq!(d.update(t(7), 10.0), SaccadeEvent::None);
        assert_eq!(d.active(), Some((t(2), 400.0)));
        assert_eq!(d.update(t(8), 10.0), SaccadeEvent::End { spurious: false });
        assert_eq!(d.active(), None);
        assert_eq!(d.update(t(9), f64::NAN), SaccadeEvent::None);
    }

    #[test]
    fn short_spikes_are_marked_spurious() {
        let mut d = SaccadeDetector::new(SaccadeConfig {
            min_duration_us: 10_000,
            ..SaccadeConfig::default()
        });
        let t = |i: u64| Timestamp::from_millis(i * 2);
        assert_eq!(d.update(t(0), 500.0), SaccadeEvent::Onset);
        d.update(t(1), 0.0);
        assert_eq!(d.update(t(2), 0.0), SaccadeEvent::End { spurious: true });
    }

    #[test]
    fn main_sequence_round_trips() {
        assert!((main_sequence_duration_ms(10.0) - 43.0).abs() < 1e-9);
        for a in [0.5, 2.0, 10.0, 30.0] {
            let v = main_sequence_peak_dps(a);
            assert!((main_sequence_amplitude_deg(v) - a).abs() < 1e-6);
        }
        assert_eq!(main_sequence_amplitude_deg(5000.0), 90.0);
        assert_eq!(main_sequence_amplitude_deg(-1.0), 0.0);
    }
}
