//! The one-euro filter (Casiez, Roussel, Vogel, CHI 2012): a low-pass whose cutoff rises with
//! speed, so fixations are smoothed hard while fast movements pass with little lag.

/// One-euro filter settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OneEuroConfig {
    /// Cutoff at rest, Hz: lower smooths fixations more.
    pub min_cutoff_hz: f64,
    /// Cutoff increase per unit of speed (per degree/s for gaze angles): higher lags less.
    pub beta: f64,
    /// Cutoff of the speed estimate itself, Hz.
    pub derivative_cutoff_hz: f64,
}

impl Default for OneEuroConfig {
    fn default() -> Self {
        // Tuned for gaze angles in degrees at 120-1000 Hz.
        OneEuroConfig {
            min_cutoff_hz: 1.0,
            beta: 0.5,
            derivative_cutoff_hz: 10.0,
        }
    }
}

/// A scalar one-euro filter over irregularly timed samples.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OneEuro {
    cfg: OneEuroConfig,
    /// (last time s, filtered value, filtered derivative)
    state: Option<(f64, f64, f64)>,
}

fn alpha(cutoff_hz: f64, dt: f64) -> f64 {
    let tau = 1.0 / (2.0 * std::f64::consts::PI * cutoff_hz.max(1e-6));
    1.0 / (1.0 + tau / dt)
}

impl OneEuro {
    pub fn new(cfg: OneEuroConfig) -> Self {
        OneEuro { cfg, state: None }
    }

    /// Filters `x` observed at `t_s` seconds. A time that does not move forward, or a
    /// non-finite value, leaves the filter as it was and returns its last output.
    pub fn filter(&mut self, t_s: f64, x: f64) -> f64 {
        if !x.is_finite() || !t_s.is_finite() {
            return self.value().unwrap_or(x);
        }
        let Some((t0, y0, dy0)) = self.state else {
            self.state = Some((t_s, x, 0.0));
            return x;
        };
        let dt = t_s - t0;
        if dt <= 0.0 {
            return y0;
        }
        let dx = (x - y0) / dt;
        let dy = dy0 + alpha(self.cfg.derivative_cutoff_hz, dt) * (dx - dy0);
        let cutoff = self.cfg.min_cutoff_hz + self.cfg.beta * dy.abs();
        let y = y0 + alpha(cutoff, dt) * (x - y0);
        self.state = Some((t_s, y, dy));
        y
    }

    /// Restarts at `x` (after a saccade or blink, so no old value drags the new one).
    pub fn reset_to(&mut self, t_s: f64, x: f64) {
        self.state = Some((t_s, x, 0.0));
    }

    pub fn value(&self) -> Option<f64> {
        self.state.map(|s| s.1)
    }

    /// Filtered rate of change, units per second.
    pub fn derivative(&self) -> Option<f64> {
        self.state.map(|s| s.2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_input_passes_unchanged_and_noise_is_reduced() {
        let mut f = OneEuro::new(OneEuroConfig::default());
        for i in 0..100 {
            assert_eq!(f.filter(i as f64 * 0.002, 3.0), 3.0);
        }
        // Alternating ±0.1 noise around 0 at 500 Hz.
        let mut f = OneEuro::new(OneEuroConfig::default());
        let mut worst: f64 = 0.0;
        for i in 0..500 {
            let x = if i % 2 == 0 { 0.1 } else { -0.1 };
            let y = f.filter(i as f64 * 0.002, x);
            if i > 50 {
                worst = worst.max(y.abs());
            }
        }
        assert!(worst < 0.01, "residual noise {worst}");
    }

    #[test]
    fn fast_ramps_lag_little() {
        // 300 deg/s ramp at 500 Hz: cutoff rises so the lag stays well under a degree.
        let mut f = OneEuro::new(OneEuroConfig::default());
        let mut y = 0.0;
        for i in 0..40 {
            y = f.filter(i as f64 * 0.002, i as f64 * 0.6);
        }
        let lag = 39.0 * 0.6 - y;
        assert!(lag < 1.0, "lag {lag}");
    }

    #[test]
    fn bad_time_and_values_are_ignored() {
        let mut f = OneEuro::new(OneEuroConfig::default());
        assert_eq!(f.filter(1.0, 2.0), 2.0);
        assert_eq!(f.filter(1.0, 5.0), 2.0);
        assert_eq!(f.filter(0.5, 5.0), 2.0);
        assert_eq!(f.filter(2.0, f64::NAN), 2.0);
        assert_eq!(f.value(), Some(2.0));
    }
}
