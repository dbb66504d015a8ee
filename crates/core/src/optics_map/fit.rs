//! Fitting a lens calibration: measured (command, demand) points -> a smooth monotone curve,
//! its residuals, and a refusal when the measurement is too noisy or the curve not monotone.
//!
//! The curve is a least-squares polynomial in the command, of degree 1 to 5, the degree
//! chosen by the Bayesian information criterion (n ln(RSS/n) + k ln n): a thin-lens layout's
//! map is a smooth rational function that a low-degree polynomial follows to well under the
//! noise of a measurement over a lens's range, and the criterion keeps the degree from
//! chasing that noise. Commands are scaled to -1..1 first so the normal equations stay well
//! conditioned.

use super::table::{CalibrationTable, MAX_GAP_D, MIN_POINTS};

/// Fewest measured points a fit accepts (a cubic and a noise estimate need a few more than
/// the table's minimum).
pub const MIN_FIT_POINTS: usize = MIN_POINTS + 1;
/// Highest polynomial degree tried.
const MAX_DEGREE: usize = 5;

/// How much misfit a calibration may have.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitLimits {
    /// Largest root-mean-square residual, diopters.
    pub max_rms_d: f64,
    /// Largest single residual, diopters (one bad reading).
    pub max_residual_d: f64,
}

impl Default for FitLimits {
    /// 0.05 D rms and 0.15 D at any point: well inside the eye's depth of field (about
    /// ±0.3 D), and wider than a careful autorefractor's or camera sweep's repeatability.
    fn default() -> Self {
        FitLimits {
            max_rms_d: 0.05,
            max_residual_d: 0.15,
        }
    }
}

/// A fitted calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationFit {
    /// Polynomial degree chosen.
    pub degree: usize,
    /// The measured points, commands increasing: (command, measured demand).
    pub measured: Vec<(f64, f64)>,
    /// The fitted demand at each measured command.
    pub fitted: Vec<f64>,
    /// Root-mean-square residual, diopters.
    pub rms_d: f64,
    /// The residual (measured - fitted) largest in size, diopters...
    pub max_residual_d: f64,
    /// ...and the command it is at.
    pub max_residual_at_d: f64,
    /// Coefficients in the scaled command `u = (c - mid) / half`, lowest power first.
    coefficients: Vec<f64>,
    mid: f64,
    half: f64,
}

/// Why a calibration was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    #[error("too few points: {got} measured, a calibration needs at least {MIN_FIT_POINTS} (use a smaller step, or measure the points that were skipped)")]
    TooFewPoints { got: usize },
    #[error("too sparse: commands {from} D and {to} D are {gap:.3} D apart; measure at most {MAX_GAP_D} D apart")]
    TooSparse { from: f64, to: f64, gap: f64 },
    #[error("a measured value is not a number (command {command} D)")]
    NotANumber { command: f64 },
    #[error("command {0} D was measured twice; give one measurement per command")]
    Repeated(f64),
    #[error("not monotonic: the fitted demand {direction} up to about command {at:.3} D and then turns back (measured near there: {near}); a lens's demand must rise or fall steadily with its command: check the measurement, the lens's range and its temperature")]
    NotMonotonic {
        direction: &'static str,
        at: f64,
        near: String,
    },
    #[error("too noisy: {what}; measure again (more carefully, more settle time, or average several readings per point), or allow more with --max-rms-d / --max-residual-d")]
    Noisy { what: String },
}

impl CalibrationFit {
    /// Fits `points` (command, measured demand; any order) and checks the result.
    pub fn fit(points: &[(f64, f64)], limits: FitLimits) -> Result<Self, FitError> {
        if let Some(&(c, _)) = points
            .iter()
            .find(|(c, a)| !(c.is_finite() && a.is_finite()))
        {
            return Err(FitError::NotANumber { command: c });
        }
        if points.len() < MIN_FIT_POINTS {
            return Err(FitError::TooFewPoints { got: points.len() });
        }
        let mut measured = points.to_vec();
        measured.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in measured.windows(2) {
            if w[0].0 == w[1].0 {
                return Err(FitError::Repeated(w[0].0));
            }
            if w[1].0 - w[0].0 > MAX_GAP_D + 1e-9 {
                return Err(FitError::TooSparse {
                    from: w[0].0,
                    to: w[1].0,
                    gap: w[1].0 - w[0].0,
                });
            }
        }
        let n = measured.len();
        let (lo, hi) = (measured[0].0, measured[n - 1].0);
        let (mid, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let u: Vec<f64> = measured.iter().map(|p| (p.0 - mid) / half).collect();
        let y: Vec<f64> = measured.iter().map(|p| p.1).collect();
        // Degrees that leave at least two residual degrees of freedom.
        let mut best: Option<(f64, Vec<f64>)> = None;
        for degree in 1..=MAX_DEGREE.min(n - 3) {
            let Some(coef) = least_squares(&u, &y, degree) else {
                continue;
            };
            let rss: f64 = u
                .iter()
                .zip(&y)
                .map(|(&u, &y)| (poly(&coef, u) - y).powi(2))
                .sum();
            let k = (degree + 1) as f64;
            // A floor on RSS keeps an exact fit (synthetic data) from scoring -infinity.
            let bic = n as f64 * (rss / n as f64).max(1e-24).ln() + k * (n as f64).ln();
            if best.as_ref().is_none_or(|(b, _)| bic < *b) {
                best = Some((bic, coef));
            }
        }
        let Some((_, coefficients)) = best else {
            return Err(FitError::TooFewPoints { got: n });
        };
        let fitted: Vec<f64> = u.iter().map(|&u| poly(&coefficients, u)).collect();
        let residuals: Vec<f64> = fitted.iter().zip(&y).map(|(f, y)| y - f).collect();
        let rms_d = (residuals.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
        let (worst, &max_abs) = residuals
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap_or((0, &0.0));
        let fit = CalibrationFit {
            degree: coefficients.len() - 1,
            max_residual_d: max_abs,
            max_residual_at_d: measured[worst].0,
            measured,
            fitted,
            rms_d,
            coefficients,
            mid,
            half,
        };
        fit.check_monotone()?;
        if max_abs.abs() > limits.max_residual_d {
            return Err(FitError::Noisy {
                what: format!(
                    "the point at command {:.3} D is {:.3} D off the fitted curve, above {} D",
                    fit.max_residual_at_d, max_abs, limits.max_residual_d
                ),
            });
        }
        if rms_d > limits.max_rms_d {
            return Err(FitError::Noisy {
                what: format!(
                    "the residuals' rms is {rms_d:.3} D, above {} D",
                    limits.max_rms_d
                ),
            });
        }
        Ok(fit)
    }

    /// The fitted demand at command `c`.
    pub fn demand_at(&self, c: f64) -> f64 {
        poly(&self.coefficients, (c - self.mid) / self.half)
    }

    /// Residual (measured - fitted) of each measured point.
    pub fn residuals(&self) -> impl Iterator<Item = f64> + '_ {
        self.measured.iter().zip(&self.fitted).map(|(m, f)| m.1 - f)
    }

    /// The table to write: the fitted demand at each measured command.
    pub fn table(&self, name: &str) -> Result<CalibrationTable, super::OpticsError> {
        let points: Vec<(f64, f64)> = self
            .measured
            .iter()
            .zip(&self.fitted)
            .map(|(m, &f)| (m.0, f))
            .collect();
        CalibrationTable::new(name, &points)
    }

    /// The fitted curve's slope must keep one sign over the measured commands (checked on a
    /// fine grid: 50 steps between neighbouring points).
    fn check_monotone(&self) -> Result<(), FitError> {
        let (lo, hi) = (self.measured[0].0, self.measured[self.measured.len() - 1].0);
        let steps = 50 * self.measured.len();
        let rising = self.demand_at(hi) > self.demand_at(lo);
        let mut prev = self.demand_at(lo);
        for i in 1..=steps {
            let c = lo + (hi - lo) * i as f64 / steps as f64;
            let v = self.demand_at(c);
            if (v > prev) != rising || v == prev {
                let near: Vec<String> = self
                    .measured
                    .iter()
                    .filter(|p| (p.0 - c).abs() <= 2.0 * MAX_GAP_D.min(hi - lo))
                    .map(|p| format!("{:.3} D at {:.3}", p.1, p.0))
                    .collect();
                return Err(FitError::NotMonotonic {
                    direction: if rising { "rises" } else { "falls" },
                    at: c,
                    near: near.join(", "),
                });
            }
            prev = v;
        }
        Ok(())
    }
}

pub(crate) fn poly(coef: &[f64], u: f64) -> f64 {
    coef.iter().rev().fold(0.0, |acc, c| acc * u + c)
}

/// Least-squares polynomial of `degree` through (u, y), by the normal equations solved with
/// partial pivoting; `None` if they are singular.
pub(crate) fn least_squares(u: &[f64], y: &[f64], degree: usize) -> Option<Vec<f64>> {
    let m = degree + 1;
    let mut a = vec![vec![0.0f64; m + 1]; m];
    for (&u, &y) in u.iter().zip(y) {
        let mut pow = vec![1.0f64; m];
        for j in 1..m {
            pow[j] = pow[j - 1] * u;
        }
        for r in 0..m {
            for c in 0..m {
                a[r][c] += pow[r] * pow[c];
            }
            a[r][m] += pow[r] * y;
        }
    }
    for col in 0..m {
        let pivot = (col..m).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() < 1e-12 {
            return None;
        }
        a.swap(col, pivot);
        let pivot_row = a[col].clone();
        for (r, row) in a.iter_mut().enumerate() {
            if r != col {
                let f = row[col] / pivot_row[col];
                for (x, p) in row.iter_mut().zip(&pivot_row).skip(col) {
                    *x -= f * p;
                }
            }
        }
    }
    Some((0..m).map(|r| a[r][m] / a[r][r]).collect())
}
