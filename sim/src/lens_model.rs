//! Physical model of an electrically tunable lens (Optotune EL-10-30-like), shared by every
//! simulator that moves a lens: the Optotune Lens Driver 4, the dioptra lens controller and the
//! sync board.
//!
//! - Optics: the static power for drive current `I` at temperature `T` is
//!   `p0 + gain * I - drift * (T - T_ref)`; the lens reaches it through a second-order
//!   response (natural frequency and damping), so a step settles in about `settle_time`.
//! - Heat: the lens warms towards `ambient + heating * I^2` with time constant `thermal_tau`.
//! - Focal-power mode recomputes the current from the temperature, as the Lens Driver 4's own
//!   compensation does; current mode does not, so its power drifts as the lens warms.
//! - The reachable power range is the static power at 0 and at maximum current: it moves with
//!   temperature.

use std::time::Duration;

use dioptra_core::{Diopters, PowerRange};

/// Parameters of [`LensModel`]. `Default` is an EL-10-30 with an offset lens, roughly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensModelConfig {
    /// Time for a step to settle within 2 % of its size.
    pub settle_time: Duration,
    /// Damping ratio of the step response (1 = critically damped).
    pub damping: f32,
    /// Static power at zero current and the reference temperature, diopters.
    pub power_at_zero_current_d: f32,
    /// Diopters per milliampere.
    pub gain_d_per_ma: f32,
    /// The driver's maximum output current, mA (Lens Driver 4: 292.84 mA).
    pub max_current_ma: f32,
    /// Static power lost per degree above the reference temperature, diopters.
    pub drift_d_per_c: f32,
    pub reference_temperature_c: f32,
    pub ambient_c: f32,
    /// Steady-state temperature rise per mA², degrees.
    pub heating_c_per_ma2: f32,
    pub thermal_tau: Duration,
}

impl Default for LensModelConfig {
    fn default() -> Self {
        LensModelConfig {
            settle_time: Duration::from_millis(15),
            damping: 0.7,
            power_at_zero_current_d: -2.0,
            gain_d_per_ma: 0.03,
            max_current_ma: 292.84,
            drift_d_per_c: 0.02,
            reference_temperature_c: 25.0,
            ambient_c: 25.0,
            heating_c_per_ma2: 2.4e-4,
            thermal_tau: Duration::from_secs(60),
        }
    }
}

/// How the lens is being driven.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DriveMode {
    /// A fixed current, mA.
    Current(f32),
    /// A target power, diopters; the current follows the temperature.
    FocalPower(f32),
}

/// The simulated lens state. Advance it with [`LensModel::advance`]; it never reads a clock.
#[derive(Debug, Clone)]
pub struct LensModel {
    cfg: LensModelConfig,
    mode: DriveMode,
    power: f32,
    velocity: f32,
    current_ma: f32,
    temperature_c: f32,
}

/// Largest integration step: small against 1/ω for any settle time the model allows.
const MAX_STEP_S: f64 = 20e-6;
/// Tolerance for "settled", diopters.
pub const SETTLED_TOLERANCE_D: f32 = 0.02;

impl LensModel {
    /// A lens at rest, at zero current and ambient temperature.
    pub fn new(cfg: LensModelConfig) -> Self {
        let mut m = LensModel {
            cfg,
            mode: DriveMode::Current(0.0),
            power: 0.0,
            velocity: 0.0,
            current_ma: 0.0,
            temperature_c: cfg.ambient_c,
        };
        m.power = m.static_power();
        m
    }

    pub fn config(&self) -> &LensModelConfig {
        &self.cfg
    }
    pub fn mode(&self) -> DriveMode {
        self.mode
    }
    pub fn power(&self) -> Diopters {
        Diopters(self.power)
    }
    pub fn current_ma(&self) -> f32 {
        self.current_ma
    }
    pub fn temperature_c(&self) -> f32 {
        self.temperature_c
    }

    /// Sets a drive current (clamped to 0..=max) and leaves focal-power mode.
    pub fn set_current_ma(&mut self, ma: f32) {
        let ma = if ma.is_finite() { ma } else { 0.0 };
        self.mode = DriveMode::Current(ma.clamp(0.0, self.cfg.max_current_ma));
        self.update_current();
    }

    /// Targets a focal power. Returns the power the lens will actually settle at: the target
    /// clamped to what the current range reaches at this temperature.
    pub fn set_focal_power(&mut self, d: Diopters) -> Diopters {
        let d = if d.0.is_finite() { d.0 } else { self.power };
        self.mode = DriveMode::FocalPower(d);
        self.update_current();
        Diopters(self.static_power())
    }

    /// Powers reachable at the present temperature.
    pub fn power_range(&self) -> PowerRange {
        let lo = self.static_power_for(0.0);
        let hi = self.static_power_for(self.cfg.max_current_ma);
        PowerRange {
            min: Diopters(lo.min(hi)),
            max: Diopters(lo.max(hi)),
        }
    }

    /// The power the lens is moving towards.
    pub fn target_power(&self) -> Diopters {
        Diopters(self.static_power())
    }

    /// Within [`SETTLED_TOLERANCE_D`] of its target and nearly still.
    pub fn settled(&self) -> bool {
        (self.power - self.static_power()).abs() < SETTLED_TOLERANCE_D
            && self.velocity.abs() < SETTLED_TOLERANCE_D * self.omega()
    }

    /// Moves the model forward by `dt`.
    pub fn advance(&mut self, dt: Duration) {
        // Heat moves on a timescale of seconds: one exact exponential step per call (per-substep
        // increments would vanish in f32 rounding).
        let tau = self.cfg.thermal_tau.as_secs_f64().max(1e-3);
        let t_ss =
            self.cfg.ambient_c + self.cfg.heating_c_per_ma2 * self.current_ma * self.current_ma;
        let k = 1.0 - (-dt.as_secs_f64() / tau).exp();
        self.temperature_c += (t_ss - self.temperature_c) * k as f32;
        self.update_current();
        let mut left = dt.as_secs_f64();
        while left > 0.0 {
            let h = left.min(MAX_STEP_S);
            self.step(h as f32);
            left -= h;
        }
    }

    fn omega(&self) -> f32 {
        // 2 % settling of a second-order system: t_s ≈ 4 / (ζ ω).
        let ts = self.cfg.settle_time.as_secs_f32().max(1e-4);
        4.0 / (self.cfg.damping.max(0.05) * ts)
    }

    fn step(&mut self, h: f32) {
        // Semi-implicit Euler: stable for ω h << 1, which MAX_STEP_S guarantees.
        let w = self.omega();
        let accel =
            w * w * (self.static_power() - self.power) - 2.0 * self.cfg.damping * w * self.velocity;
        self.velocity += accel * h;
        self.power += self.velocity * h;
    }

    fn update_current(&mut self) {
        self.current_ma = match self.mode {
            DriveMode::Current(ma) => ma,
            DriveMode::FocalPower(d) => {
                let offset = self.static_power_for(0.0);
                ((d - offset) / self.cfg.gain_d_per_ma).clamp(0.0, self.cfg.max_current_ma)
            }
        };
    }

    fn static_power_for(&self, current_ma: f32) -> f32 {
        self.cfg.power_at_zero_current_d + self.cfg.gain_d_per_ma * current_ma
            - self.cfg.drift_d_per_c * (self.temperature_c - self.cfg.reference_temperature_c)
    }

    fn static_power(&self) -> f32 {
        self.static_power_for(self.current_ma)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    #[test]
    fn step_settles_within_settle_time_with_bounded_overshoot() {
        let mut lens = LensModel::new(LensModelConfig::default());
        lens.set_focal_power(Diopters(0.0));
        lens.advance(ms(200));
        assert!(lens.settled());
        lens.set_focal_power(Diopters(3.0));
        let mut peak = f32::MIN;
        let mut settled_at = None;
        for i in 1..=40u64 {
            lens.advance(ms(1));
            peak = peak.max(lens.power().0);
            let within = (lens.power().0 - 3.0).abs() <= 0.02 * 3.0;
            match (within, settled_at) {
                (true, None) => settled_at = Some(i),
                (false, Some(_)) => settled_at = None,
                _ => {}
            }
        }
        let t = settled_at.expect("never settled");
        assert!(
            (10..=18).contains(&t),
            "settled after {t} ms, configured 15 ms"
        );
        // ζ = 0.7 overshoots by about 4.6 %.
        assert!(peak > 3.05 && peak < 3.2, "peak {peak}");
        assert!(lens.settled());
    }

    #[test]
    fn slower_lens_settles_later() {
        let cfg = LensModelConfig {
            settle_time: ms(40),
            ..Default::default()
        };
        let mut lens = LensModel::new(cfg);
        lens.set_focal_power(Diopters(2.0));
        lens.advance(ms(20));
        assert!(!lens.settled());
        lens.advance(ms(40));
        assert!(lens.settled());
    }

    #[test]
    fn current_heats_the_lens_and_shifts_the_reachable_range() {
        let mut lens = LensModel::new(LensModelConfig::default());
        let cold = lens.power_range();
        lens.set_current_ma(250.0);
        lens.advance(Duration::from_secs(300));
        // steady state: 25 + 2.4e-4 * 250² = 40 °C
        assert!(
            (lens.temperature_c() - 40.0).abs() < 0.5,
            "{}",
            lens.temperature_c()
        );
        let warm = lens.power_range();
        assert!(warm.max.0 < cold.max.0 - 0.25, "{warm:?} vs {cold:?}");
    }

    #[test]
    fn focal_power_mode_compensates_drift_and_current_mode_does_not() {
        let mut fp = LensModel::new(LensModelConfig::default());
        fp.set_focal_power(Diopters(4.0));
        let mut cur = LensModel::new(LensModelConfig::default());
        cur.set_current_ma(fp.current_ma());
        fp.advance(Duration::from_secs(120));
        cur.advance(Duration::from_secs(120));
        assert!(
            (fp.power().0 - 4.0).abs() < 0.02,
            "focal-power mode {}",
            fp.power()
        );
        assert!(
            cur.power().0 < 3.85,
            "current mode should drift, got {}",
            cur.power()
        );
    }

    #[test]
    fn out_of_range_targets_and_bad_numbers_are_clamped() {
        let mut lens = LensModel::new(LensModelConfig::default());
        let reached = lens.set_focal_power(Diopters(50.0));
        assert!((reached.0 - lens.power_range().max.0).abs() < 1e-4);
        lens.set_current_ma(f32::NAN);
        assert_eq!(lens.current_ma(), 0.0);
        lens.set_focal_power(Diopters(f32::INFINITY));
        lens.advance(ms(5));
        assert!(lens.power().0.is_finite());
    }
}
