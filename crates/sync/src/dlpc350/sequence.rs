//! Mapping a plane schedule onto a DLPC350 pattern sequence. Pure.
//!
//! The rig streams one 24-bit video frame per display frame over the video port; the DLPC350
//! splits it into one pattern per focal plane (plane `i` is pattern number `i` at the deepest
//! bit depth that fits all planes in 24 bits), shows them at the sub-frame period after each
//! VSYNC, pulses TRIG_OUT_1 at every pattern (lens steps) and TRIG_OUT_2 at the first pattern
//! of each frame (lens sweep starts). The settle allowance is dark time after each exposure,
//! filled with black as TI's SDK fills it (`LCr4500::CreateSendStartSequenceLut`: insert black
//! when the exposure is shorter than the period, and on the entry before an externally
//! triggered one), or the controller's validation fails bit 3.

use std::time::Duration;

use dioptra_core::{DeviceError, PlaneSchedule};

use super::protocol::{
    exposure_fits_period, min_exposure_us, patterns_per_image, LutEntry, SetExposure,
    SetPatternConfig, SetTrigOut1, SetTrigOut2, TriggerType, MAX_LUT_ENTRIES, MIN_DARK_US,
    TRIG_DELAY_ZERO,
};

/// How the projector is wired into the rig.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dlpc350Config {
    /// Video-port frame rate: each VSYNC starts one frame's patterns.
    pub vsync_hz: f64,
    /// LED enables for every pattern: bit 0 red, 1 green, 2 blue.
    pub leds: u8,
    pub trig_out1: SetTrigOut1,
    pub trig_out2: SetTrigOut2,
}

impl Default for Dlpc350Config {
    fn default() -> Self {
        Dlpc350Config {
            vsync_hz: 60.0,
            leds: 0b111,
            trig_out1: SetTrigOut1 {
                invert: false,
                rising_delay: TRIG_DELAY_ZERO,
                falling_delay: TRIG_DELAY_ZERO,
            },
            trig_out2: SetTrigOut2 {
                invert: false,
                rising_delay: TRIG_DELAY_ZERO,
            },
        }
    }
}

/// Everything the driver programs for one schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct PatternSequence {
    pub exposure: SetExposure,
    pub config: SetPatternConfig,
    pub entries: Vec<LutEntry>,
    pub trig_out1: SetTrigOut1,
    pub trig_out2: SetTrigOut2,
    /// The video frame period the patterns must fit in, µs.
    pub frame_period_us: u32,
    /// The same, exactly: each frame's first pattern starts at a VSYNC.
    pub frame_period: Duration,
}

fn invalid(msg: String) -> DeviceError {
    DeviceError::Invalid(msg)
}

impl PatternSequence {
    /// The sequence for `schedule`, or a clear error when the DLPC350 cannot run it.
    pub fn for_schedule(
        schedule: &PlaneSchedule,
        cfg: &Dlpc350Config,
    ) -> Result<PatternSequence, DeviceError> {
        let n = schedule.planes().len();
        let period_us = u32::try_from(schedule.subframe_period().as_micros())
            .map_err(|_| invalid("sub-frame period is too long for the DLPC350".into()))?;
        let settle_us = u32::try_from(schedule.settle_allowance().as_micros()).unwrap_or(u32::MAX);
        if settle_us > 0 && settle_us < MIN_DARK_US {
            return Err(invalid(format!(
                "settle allowance {settle_us} us: the DLPC350 can only go dark between patterns \
                 for 0 or at least {MIN_DARK_US} us"
            )));
        }
        let frame_period = Duration::try_from_secs_f64(1.0 / cfg.vsync_hz)
            .ok()
            .filter(|f| cfg.vsync_hz.is_finite() && !f.is_zero())
            .ok_or_else(|| invalid(format!("video rate {} Hz is not usable", cfg.vsync_hz)))?;
        // Deepest bit depth that fits every plane into one 24-bit frame and whose shortest
        // exposure the sub-frame allows: fewer grey levels rather than no multifocal mode.
        // When none does, the shallowest is kept, so `check` names the shortest exposure there is.
        let exposure_us = period_us.saturating_sub(settle_us);
        let fitting = (1..=8u8)
            .rev()
            .filter(|d| usize::from(patterns_per_image(*d)) >= n);
        let bit_depth = fitting
            .clone()
            .find(|d| min_exposure_us(*d).is_some_and(|min| exposure_us >= min))
            .or_else(|| fitting.clone().min())
            .ok_or_else(|| invalid(format!("{n} planes do not fit one 24-bit video frame")))?;
        let black_fill = exposure_us < period_us;
        let entries = (0..n)
            .map(|i| LutEntry {
                // The first pattern waits for VSYNC and takes the new frame's buffer
                // (pycrafter4500 marks it external-positive too); the rest follow on.
                trigger: if i == 0 {
                    TriggerType::ExternalPositive
                } else {
                    TriggerType::Continue
                },
                pattern: i as u8,
                bit_depth,
                leds: cfg.leds & 0x07,
                invert: false,
                // Entry 0 waits for VSYNC, so the last entry (before it, as the sequence
                // repeats) clears the DMD after its exposure too.
                insert_black: black_fill || i + 1 == n,
                buffer_swap: i == 0,
                trig_out_prev: false,
            })
            .collect();
        let seq = PatternSequence {
            exposure: SetExposure {
                exposure_us,
                period_us,
            },
            config: SetPatternConfig {
                lut_entries: n as u8,
                repeat: true,
                trig_out2_every: n as u16,
                images: 1,
            },
            entries,
            trig_out1: cfg.trig_out1,
            trig_out2: cfg.trig_out2,
            frame_period_us: u32::try_from(frame_period.as_micros()).unwrap_or(u32::MAX),
            frame_period,
        };
        seq.check()?;
        Ok(seq)
    }

    /// The controller's rules, checked before anything is sent.
    pub fn check(&self) -> Result<(), DeviceError> {
        let SetExposure {
            exposure_us,
            period_us,
        } = self.exposure;
        if !exposure_fits_period(exposure_us, period_us) {
            return Err(invalid(format!(
                "exposure {exposure_us} us must equal the pattern period {period_us} us or be at \
                 least {MIN_DARK_US} us shorter"
            )));
        }
        let n = self.entries.len();
        if n == 0 || n > MAX_LUT_ENTRIES || usize::from(self.config.lut_entries) != n {
            return Err(invalid(format!(
                "{n} LUT entries with a configured count of {}",
                self.config.lut_entries
            )));
        }
        for (i, e) in self.entries.iter().enumerate() {
            let Some(min) = min_exposure_us(e.bit_depth) else {
                return Err(invalid(format!(
                    "entry {i}: bit depth {} is reserved",
                    e.bit_depth
                )));
            };
            if e.pattern >= patterns_per_image(e.bit_depth) {
                return Err(invalid(format!(
                    "entry {i}: pattern {} does not exist at {} bits",
                    e.pattern, e.bit_depth
                )));
            }
            if exposure_us < min {
                return Err(invalid(format!(
                    "exposure {exposure_us} us is shorter than the {min} us a {}-bit pattern \
                     needs: use fewer planes or a lower rate",
                    e.bit_depth
                )));
            }
        }
        let frame_us = u64::from(period_us) * n as u64;
        if frame_us > u64::from(self.frame_period_us) {
            return Err(invalid(format!(
                "{n} patterns x {period_us} us = {frame_us} us do not fit the {} us video frame",
                self.frame_period_us
            )));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::Diopters;

    fn schedule(n: usize, period_us: u64, settle_us: u64) -> PlaneSchedule {
        PlaneSchedule::new(
            (0..n).map(|i| Diopters(0.2 + 0.6 * i as f32)).collect(),
            Duration::from_micros(period_us),
            Duration::from_micros(settle_us),
        )
        .unwrap()
    }

    #[test]
    fn four_planes_at_240_hz_become_four_six_bit_patterns() {
        let s = PatternSequence::for_schedule(&schedule(4, 4166, 1000), &Dlpc350Config::default())
            .unwrap();
        assert_eq!(
            s.exposure,
            SetExposure {
                exposure_us: 3166,
                period_us: 4166
            }
        );
        assert_eq!(s.config.trig_out2_every, 4);
        assert_eq!(s.entries.len(), 4);
        assert!(s.entries.iter().all(|e| e.bit_depth == 6));
        assert_eq!(
            s.entries.iter().map(|e| e.pattern).collect::<Vec<_>>(),
            vec![0, 1, 2, 3]
        );
        assert_eq!(s.entries[0].trigger, TriggerType::ExternalPositive);
        assert!(s.entries[1..]
            .iter()
            .all(|e| e.trigger == TriggerType::Continue));
        // 1000 us of settle time is dark: black fill on every entry (TI's SDK rule).
        assert!(s.entries.iter().all(|e| e.insert_black));
        // Exposure equal to the period: black only before the VSYNC-triggered first entry.
        let s = PatternSequence::for_schedule(&schedule(4, 4000, 0), &Dlpc350Config::default())
            .unwrap();
        let black: Vec<bool> = s.entries.iter().map(|e| e.insert_black).collect();
        assert_eq!(black, vec![false, false, false, true]);
    }

    #[test]
    fn depth_follows_the_plane_count() {
        let cfg = Dlpc350Config {
            vsync_hz: 30.0,
            ..Default::default()
        };
        let depth = |n| {
            PatternSequence::for_schedule(&schedule(n, 2000, 0), &cfg)
                .map(|s| s.entries[0].bit_depth)
        };
        // Three planes fit at 8 bits, but a 2 ms exposure allows 5 at most (6 needs 2500 us).
        assert_eq!(depth(3).unwrap(), 5);
        assert_eq!(depth(5).unwrap(), 4);
        assert_eq!(depth(16).unwrap(), 1);
        assert_eq!(depth(12).unwrap(), 2);
        // A 4 ms exposure is too short for 7 bits (4500 us) but allows 6.
        let three = PatternSequence::for_schedule(&schedule(3, 4000, 0), &cfg).unwrap();
        assert!(three.entries.iter().all(|e| e.bit_depth == 6));
    }

    #[test]
    fn impossible_schedules_are_refused_with_the_reason() {
        let cfg = Dlpc350Config::default();
        let e = |n, p, s| {
            PatternSequence::for_schedule(&schedule(n, p, s), &cfg)
                .unwrap_err()
                .to_string()
        };
        assert!(e(4, 4166, 100).contains("230 us"));
        assert!(e(4, 5000, 0).contains("video frame"));
        assert!(e(3, 200, 0).contains("1-bit"));
        assert!(e(16, 1000, 900).contains("1-bit"));
    }
}
