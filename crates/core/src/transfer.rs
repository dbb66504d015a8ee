//! The panel's transfer function: code value (the fraction of full scale a pixel is driven
//! with, 0 to 1) to the light it emits, and its inverse, which the renderer's linear light
//! goes through before it reaches the panel.
//!
//! "Linear" means linear above the panel's black: linear value `v` (0 to 1) must give
//! luminance `L(0) + v (L(1) - L(0))`. Light from two layers then adds as the values do
//! (every multifocal plane is shown each frame, so each contributes its black once whatever
//! the split), which is what linear blending needs. [`Transfer::decode`] is the normalised
//! response `n(c) = (L(c) - L(0)) / (L(1) - L(0))`; [`Transfer::encode`] its inverse.
//!
//! - [`Transfer::Srgb`]: IEC 61966-2-1's curve (what the renderer wrote before).
//! - [`Transfer::Gamma`]: ITU-R BT.1886's form, `L = a max(c + b, 0)^γ` with `a` and `b`
//!   set by the black level `β = L(0) / L(1)`; β = 0 is a pure power law. The encoding is
//!   `c = ((β + v (1 - β))^(1/γ) - β^(1/γ)) / (1 - β^(1/γ))`. (A black that is light added
//!   on top, backlight bleed or flare, `L = L0 + k c^γ`, needs no black here: it leaves the
//!   normalised response `c^γ`.) γ = 1, β = 0 is a linear panel (a DLP in a pattern mode).
//! - [`Transfer::Table`]: a measured table ([`TransferTable`], the file `dioptra display
//!   calibrate` writes), read through a monotone cubic.

use crate::optics_map::{least_squares, pchip_slopes, poly};
use crate::table_csv::TableColumns;

/// A table file's columns.
const COLUMNS: TableColumns = TableColumns {
    names: ["level", "luminance_cd_m2"],
    row: "level",
    meaning: "level (the code value, 0 to 1) and luminance_cd_m2",
    number: "a number",
};

/// A transfer function or table the rig cannot use, naming the key or the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransferError {
    #[error("{key}: {message}")]
    Invalid { key: &'static str, message: String },
    #[error("transfer table {file}: {message}")]
    Table { file: String, message: String },
}

/// Fewest levels a table (and a calibration) may have.
pub const MIN_LEVELS: usize = 6;

#[derive(Debug, Clone, PartialEq)]
pub enum Transfer {
    Srgb,
    /// BT.1886 with exponent `gamma` and black level `black` (L(0) / L(1), 0 to 0.5).
    Gamma {
        gamma: f64,
        black: f64,
    },
    Table(TransferTable),
}

impl Transfer {
    /// A gamma transfer, checked (keys as rig.toml's `display.transfer` spells them).
    pub fn gamma(gamma: f64, black: f64) -> Result<Self, TransferError> {
        if !(gamma.is_finite() && (0.2..=5.0).contains(&gamma)) {
            return Err(TransferError::Invalid {
                key: "display.transfer.gamma",
                message: format!("{gamma}: expected an exponent from 0.2 to 5 (e.g. 2.2 or 2.4; 1 for a linear panel)"),
            });
        }
        if !(black.is_finite() && (0.0..=0.5).contains(&black)) {
            return Err(TransferError::Invalid {
                key: "display.transfer.black",
                message: format!(
                    "{black}: expected the black level as a fraction of white's luminance, 0 to 0.5 (e.g. 0.001)"
                ),
            });
        }
        Ok(Transfer::Gamma { gamma, black })
    }

    /// A linear panel (`display.transfer = "linear"`).
    pub fn linear() -> Self {
        Transfer::Gamma {
            gamma: 1.0,
            black: 0.0,
        }
    }

    /// Normalised light above black for code value `c` (clamped to 0..1).
    pub fn decode(&self, c: f64) -> f64 {
        let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
        match self {
            Transfer::Srgb => {
                if c <= 0.04045 {
                    c / 12.92
                } else {
                    ((c + 0.055) / 1.055).powf(2.4)
                }
            }
            Transfer::Gamma { gamma, black } => {
                if *black == 0.0 {
                    return c.powf(*gamma);
                }
                let (lb, g) = (black.powf(1.0 / gamma), *gamma);
                // L / L(1) = (c (1 - lb) + lb)^γ, then normalised above black.
                ((c * (1.0 - lb) + lb).powf(g) - black) / (1.0 - black)
            }
            Transfer::Table(t) => t.normalised_at(c),
        }
    }

    /// The code value that gives normalised light `v` (clamped to 0..1; NaN gives 0).
    pub fn encode(&self, v: f64) -> f64 {
        let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
        match self {
            Transfer::Srgb => {
                if v <= 0.003_130_8 {
                    12.92 * v
                } else {
                    1.055 * v.powf(1.0 / 2.4) - 0.055
                }
            }
            Transfer::Gamma { gamma, black } => {
                if *black == 0.0 {
                    return v.powf(1.0 / gamma);
                }
                let lb = black.powf(1.0 / gamma);
                ((black + v * (1.0 - black)).powf(1.0 / gamma) - lb) / (1.0 - lb)
            }
            Transfer::Table(t) => t.level_for(v),
        }
    }

    /// One line for people.
    pub fn describe(&self) -> String {
        match self {
            Transfer::Srgb => "sRGB".into(),
            Transfer::Gamma { gamma, black } if *black == 0.0 && *gamma == 1.0 => "linear".into(),
            Transfer::Gamma { gamma, black } => format!("gamma {gamma} (BT.1886), black {black}"),
            Transfer::Table(t) => format!("measured table {} ({} levels)", t.name, t.len()),
        }
    }
}

/// A measured response: (code value, luminance) at levels from 0 to 1, luminance rising,
/// read through a monotone cubic (PCHIP, as the lens calibration table).
///
/// The file is CSV: `#` lines are comments (the provenance), the first other line names the
/// columns, and `level` (the code value as a fraction of full scale, 0 to 1: 8-bit code 128
/// is 128/255) and `luminance_cd_m2` are read; others are kept for people. Levels 0 and 1
/// must be there (black and white set the normalisation).
#[derive(Debug, Clone, PartialEq)]
pub struct TransferTable {
    name: String,
    levels: Vec<f64>,
    luminance: Vec<f64>,
    /// (L - L(0)) / (L(1) - L(0)).
    normalised: Vec<f64>,
    slopes: Vec<f64>,
}

impl TransferTable {
    /// A table of (level, luminance) points, any order; refused (naming `name`) with fewer
    /// than [`MIN_LEVELS`], levels outside 0..1 or repeated, no level 0 or 1, or luminance
    /// that does not rise strictly with the level.
    pub fn new(name: &str, points: &[(f64, f64)]) -> Result<Self, TransferError> {
        let err = |message: String| TransferError::Table {
            file: name.to_string(),
            message,
        };
        if points.len() < MIN_LEVELS {
            return Err(err(format!(
                "{} levels; a table needs at least {MIN_LEVELS}, from 0 (black) to 1 (white)",
                points.len()
            )));
        }
        if let Some((l, y)) = points
            .iter()
            .find(|(l, y)| !(l.is_finite() && y.is_finite()))
        {
            return Err(err(format!(
                "(level {l}, luminance {y}) is not a pair of numbers"
            )));
        }
        if let Some((l, _)) = points.iter().find(|(l, _)| !(0.0..=1.0).contains(l)) {
            return Err(err(format!(
                "level {l} is outside 0..1 (levels are fractions of full scale: 8-bit code 128 is {:.6})",
                128.0 / 255.0
            )));
        }
        let mut p = points.to_vec();
        p.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in p.windows(2) {
            if w[0].0 == w[1].0 {
                return Err(err(format!("level {} appears twice", w[0].0)));
            }
        }
        if p[0].0 != 0.0 || p[p.len() - 1].0 != 1.0 {
            return Err(err(format!(
                "its levels span {}..{}: black (level 0) and white (level 1) must be measured",
                p[0].0,
                p[p.len() - 1].0
            )));
        }
        for w in p.windows(2) {
            if w[1].1 <= w[0].1 {
                return Err(err(format!(
                    "not rising: luminance {} at level {} then {} at level {}; a panel's light \
                     must rise with its code value: measure these levels again",
                    w[0].1, w[0].0, w[1].1, w[1].0
                )));
            }
        }
        let levels: Vec<f64> = p.iter().map(|x| x.0).collect();
        let luminance: Vec<f64> = p.iter().map(|x| x.1).collect();
        let (lo, hi) = (luminance[0], luminance[luminance.len() - 1]);
        let normalised: Vec<f64> = luminance.iter().map(|l| (l - lo) / (hi - lo)).collect();
        let slopes = pchip_slopes(&levels, &normalised);
        Ok(TransferTable {
            name: name.to_string(),
            levels,
            luminance,
            normalised,
            slopes,
        })
    }

    /// Parses a table's CSV text; `name` (the file) is for messages.
    pub fn parse_csv(name: &str, text: &str) -> Result<Self, TransferError> {
        let rows = COLUMNS.read(text).map_err(|message| TransferError::Table {
            file: name.to_string(),
            message,
        })?;
        let points: Vec<(f64, f64)> = rows.iter().map(|(_, [l, y])| (*l, *y)).collect();
        Self::new(name, &points)
    }

    /// The table as CSV: `comments` as `#` lines, then `level,luminance_cd_m2` and any extra
    /// columns (one row of values per level).
    pub fn to_csv(
        &self,
        comments: &[String],
        extra_names: &[&str],
        extra: &[Vec<String>],
    ) -> String {
        let points = self
            .levels
            .iter()
            .zip(&self.luminance)
            .map(|(l, y)| format!("{l:.6},{y:.6}"));
        COLUMNS.write(comments, points, extra_names, extra)
    }

    pub fn name(&self) -> &str {
        &self.name
    }
    pub fn len(&self) -> usize {
        self.levels.len()
    }
    pub fn is_empty(&self) -> bool {
        self.levels.is_empty()
    }
    /// (level, luminance) points, levels rising.
    pub fn points(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.levels
            .iter()
            .copied()
            .zip(self.luminance.iter().copied())
    }
    /// Black's and white's luminance, cd/m².
    pub fn black_white(&self) -> (f64, f64) {
        (self.luminance[0], self.luminance[self.luminance.len() - 1])
    }

    fn hermite(&self, k: usize, t: f64) -> f64 {
        let h = self.levels[k + 1] - self.levels[k];
        let (y0, y1) = (self.normalised[k], self.normalised[k + 1]);
        let (m0, m1) = (self.slopes[k] * h, self.slopes[k + 1] * h);
        let (t2, t3) = (t * t, t * t * t);
        (2.0 * t3 - 3.0 * t2 + 1.0) * y0
            + (t3 - 2.0 * t2 + t) * m0
            + (-2.0 * t3 + 3.0 * t2) * y1
            + (t3 - t2) * m1
    }

    /// Normalised light at level `c` in 0..1.
    fn normalised_at(&self, c: f64) -> f64 {
        let n = self.levels.len();
        let k = self.levels.partition_point(|&x| x <= c).clamp(1, n - 1) - 1;
        let h = self.levels[k + 1] - self.levels[k];
        self.hermite(k, (c - self.levels[k]) / h)
    }

    /// The level giving normalised light `v` in 0..1 (the cubic is monotone on each segment:
    /// bisected to f64's resolution).
    fn level_for(&self, v: f64) -> f64 {
        if v <= 0.0 {
            return 0.0;
        }
        if v >= 1.0 {
            return 1.0;
        }
        let n = self.levels.len();
        let k = self.normalised.partition_point(|&y| y <= v).clamp(1, n - 1) - 1;
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if self.hermite(k, mid) < v {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let h = self.levels[k + 1] - self.levels[k];
        self.levels[k] + 0.5 * (lo + hi) * h
    }
}

/// How much misfit a panel calibration may have, as fractions of the luminance range
/// (white minus black).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransferFitLimits {
    pub max_rms: f64,
    pub max_residual: f64,
}

impl Default for TransferFitLimits {
    /// 0.5 % rms and 2 % at any level: a spot photometer (or a calibrated camera) repeats to
    /// a few tenths of a percent of white; more misfit is a reading taken before the panel
    /// settled, room light, or a patch the sensor does not cover.
    fn default() -> Self {
        TransferFitLimits {
            max_rms: 0.005,
            max_residual: 0.02,
        }
    }
}

/// Why a panel calibration was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransferFitError {
    #[error("too few levels: {got} measured, a calibration needs at least {MIN_LEVELS} from black to white (use more --levels)")]
    TooFewLevels { got: usize },
    #[error("level {level} has a reading that is not a number ({value})")]
    NotANumber { level: f64, value: f64 },
    #[error("level {0} is outside 0..1")]
    OutOfRange(f64),
    #[error("level {0} was measured twice")]
    Repeated(f64),
    #[error("black (level 0) and white (level 1) must both be measured")]
    NoEnds,
    #[error("white ({white} cd/m²) is not brighter than black ({black} cd/m²): is the photometer on the patch, the panel on, the measure command reading the right device?")]
    NoRange { black: f64, white: f64 },
    #[error("not monotonic: the fitted luminance stops rising near level {at:.3} (measured near there: {near}); a panel's light must rise with its code value: check the readings there (a saturating or clipping photometer range, the panel's dynamic contrast or auto-brightness switched on)")]
    NotMonotonic { at: f64, near: String },
    #[error("too noisy: {what}; measure again (let the photometer settle, darken the room, average several readings per level), or allow more with --max-rms / --max-residual")]
    Noisy { what: String },
}

/// A fitted panel response.
#[derive(Debug, Clone, PartialEq)]
pub struct TransferFit {
    /// The exponent of the power law the curve is fitted in (`t = level^γ`).
    pub gamma: f64,
    /// Polynomial degree in `t` chosen (by the Bayesian information criterion).
    pub degree: usize,
    /// (level, luminance) measured, levels rising.
    pub measured: Vec<(f64, f64)>,
    pub fitted: Vec<f64>,
    /// Residuals' rms and the largest, as fractions of the fitted luminance range.
    pub rms: f64,
    pub max_residual: f64,
    pub max_residual_at: f64,
    coefficients: Vec<f64>,
}

impl TransferFit {
    /// Fits measured (level, luminance) readings: a power law's exponent first (log-log, on
    /// the levels between black and white), then a least-squares polynomial of degree 1 to 3
    /// in `level^γ` (a power law is degree 1; a panel that departs from one, an sRGB-like toe
    /// or an S-curve, takes more), the degree chosen by the Bayesian information criterion.
    /// Refused when too few levels, not monotone, or noisier than `limits`.
    pub fn fit(points: &[(f64, f64)], limits: TransferFitLimits) -> Result<Self, TransferFitError> {
        if let Some(&(level, value)) = points
            .iter()
            .find(|(l, y)| !(l.is_finite() && y.is_finite()))
        {
            return Err(TransferFitError::NotANumber { level, value });
        }
        if let Some(&(l, _)) = points.iter().find(|(l, _)| !(0.0..=1.0).contains(l)) {
            return Err(TransferFitError::OutOfRange(l));
        }
        if points.len() < MIN_LEVELS {
            return Err(TransferFitError::TooFewLevels { got: points.len() });
        }
        let mut measured = points.to_vec();
        measured.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in measured.windows(2) {
            if w[0].0 == w[1].0 {
                return Err(TransferFitError::Repeated(w[0].0));
            }
        }
        let n = measured.len();
        if measured[0].0 != 0.0 || measured[n - 1].0 != 1.0 {
            return Err(TransferFitError::NoEnds);
        }
        let (black, white) = (measured[0].1, measured[n - 1].1);
        if white <= black {
            return Err(TransferFitError::NoRange { black, white });
        }
        let range = white - black;
        // Exponent: ln n = γ ln c through the origin, on levels well above black's noise.
        let (mut sxy, mut sxx) = (0.0, 0.0);
        for &(c, y) in &measured[1..n - 1] {
            let v = (y - black) / range;
            if v > 0.01 && v < 0.99 {
                sxy += v.ln() * c.ln();
                sxx += c.ln() * c.ln();
            }
        }
        let gamma = if sxx > 0.0 {
            (sxy / sxx).clamp(0.3, 5.0)
        } else {
            1.0
        };
        let t: Vec<f64> = measured.iter().map(|p| p.0.powf(gamma)).collect();
        let y: Vec<f64> = measured.iter().map(|p| p.1).collect();
        let mut best: Option<(f64, Vec<f64>)> = None;
        for degree in 1..=3.min(n - 3) {
            let Some(coef) = least_squares(&t, &y, degree) else {
                continue;
            };
            let rss: f64 = t
                .iter()
                .zip(&y)
                .map(|(&t, &y)| (poly(&coef, t) - y).powi(2))
                .sum();
            let k = (degree + 1) as f64;
            // A floor (relative to the range) keeps an exact fit from scoring -infinity.
            let floor = (1e-12 * range).powi(2);
            let bic = n as f64 * (rss / n as f64).max(floor).ln() + k * (n as f64).ln();
            if best.as_ref().is_none_or(|(b, _)| bic < *b) {
                best = Some((bic, coef));
            }
        }
        let Some((_, coefficients)) = best else {
            return Err(TransferFitError::TooFewLevels { got: n });
        };
        let fitted: Vec<f64> = t.iter().map(|&t| poly(&coefficients, t)).collect();
        let fitted_range = fitted[n - 1] - fitted[0];
        let residuals: Vec<f64> = fitted
            .iter()
            .zip(&y)
            .map(|(f, y)| (y - f) / fitted_range)
            .collect();
        let rms = (residuals.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
        let (worst, &max_residual) = residuals
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap_or((0, &0.0));
        let fit = TransferFit {
            gamma,
            degree: coefficients.len() - 1,
            max_residual_at: measured[worst].0,
            measured,
            fitted,
            rms,
            max_residual,
            coefficients,
        };
        // Noise first: a curve bent by noisy readings is a noise problem.
        if max_residual.abs() > limits.max_residual {
            return Err(TransferFitError::Noisy {
                what: format!(
                    "the reading at level {:.4} is {:.2} % of the luminance range off the fitted curve, above {} %",
                    fit.max_residual_at,
                    100.0 * max_residual.abs(),
                    100.0 * limits.max_residual
                ),
            });
        }
        if rms > limits.max_rms {
            return Err(TransferFitError::Noisy {
                what: format!(
                    "the residuals' rms is {:.2} % of the luminance range, above {} %",
                    100.0 * rms,
                    100.0 * limits.max_rms
                ),
            });
        }
        fit.check_monotone()?;
        Ok(fit)
    }

    /// The fitted luminance at level `c`, cd/m² (or the readings' unit).
    pub fn luminance_at(&self, c: f64) -> f64 {
        poly(&self.coefficients, c.clamp(0.0, 1.0).powf(self.gamma))
    }

    /// Residual of each reading as a fraction of the fitted range.
    pub fn residuals(&self) -> impl Iterator<Item = f64> + '_ {
        let range = self.fitted[self.fitted.len() - 1] - self.fitted[0];
        self.measured
            .iter()
            .zip(&self.fitted)
            .map(move |(m, f)| (m.1 - f) / range)
    }

    /// The table to write: the fitted curve at `steps + 1` evenly spaced levels (255 steps:
    /// every 8-bit code), so that reading it back follows the fit, not a cubic between
    /// readings.
    pub fn table(&self, name: &str, steps: usize) -> Result<TransferTable, TransferError> {
        let steps = steps.max(MIN_LEVELS - 1);
        let points: Vec<(f64, f64)> = (0..=steps)
            .map(|k| {
                let c = k as f64 / steps as f64;
                (c, self.luminance_at(c))
            })
            .collect();
        TransferTable::new(name, &points)
    }

    /// The fit must rise over 0..1 (checked at 4096 levels).
    fn check_monotone(&self) -> Result<(), TransferFitError> {
        const STEPS: usize = 4096;
        let mut prev = self.luminance_at(0.0);
        for i in 1..=STEPS {
            let c = i as f64 / STEPS as f64;
            let v = self.luminance_at(c);
            if v <= prev {
                let near: Vec<String> = self
                    .measured
                    .iter()
                    .filter(|p| (p.0 - c).abs() <= 0.15)
                    .map(|p| format!("{:.4} at {:.3}", p.1, p.0))
                    .collect();
                return Err(TransferFitError::NotMonotonic {
                    at: c,
                    near: near.join(", "),
                });
            }
            prev = v;
        }
        Ok(())
    }
}

/// `display.transfer` as rig.toml spells it: `"srgb"`, `"linear"`, `{ gamma = G, black = B }`
/// or `{ table = "FILE" }` (relative to the config file).
#[cfg(feature = "serde")]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(untagged)]
pub enum TransferSetting {
    Named(TransferName),
    Gamma {
        gamma: f64,
        #[serde(default)]
        black: f64,
    },
    Table {
        table: std::path::PathBuf,
    },
}

#[cfg(feature = "serde")]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TransferName {
    Srgb,
    Linear,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_curve_round_trips_and_hits_its_ends() {
        let table: Vec<(f64, f64)> = (0..=8)
            .map(|k| {
                let c = k as f64 / 8.0;
                (c, 0.4 + 150.0 * c.powf(2.2))
            })
            .collect();
        for t in [
            Transfer::Srgb,
            Transfer::linear(),
            Transfer::gamma(2.4, 0.0).unwrap(),
            Transfer::gamma(2.4, 0.002).unwrap(),
            Transfer::Table(TransferTable::new("t", &table).unwrap()),
        ] {
            assert!(
                t.encode(0.0).abs() < 1e-12 && (t.encode(1.0) - 1.0).abs() < 1e-12,
                "{t:?}"
            );
            assert!(
                t.decode(0.0).abs() < 1e-12 && (t.decode(1.0) - 1.0).abs() < 1e-12,
                "{t:?}"
            );
            for i in 0..=200 {
                let v = i as f64 / 200.0;
                let back = t.decode(t.encode(v));
                assert!((back - v).abs() < 1e-9, "{} at {v}: {back}", t.describe());
            }
            assert_eq!(t.encode(f64::NAN), 0.0);
            assert_eq!(t.encode(-3.0), 0.0);
            assert_eq!(t.encode(7.0), t.encode(1.0));
        }
    }

    #[test]
    fn bt1886_by_hand() {
        // γ 2.4, β 0.01: lb = 0.01^(1/2.4) = 0.146779926762207; code 0.5 gives
        // (0.5 (1 - lb) + lb)^2.4 = 0.573389963381^2.4 = 0.262889... of white; above black,
        // (0.262889 - 0.01) / 0.99.
        let t = Transfer::gamma(2.4, 0.01).unwrap();
        let lb: f64 = 0.146_779_926_762_207;
        let l = (0.5 * (1.0 - lb) + lb).powf(2.4);
        assert!((t.decode(0.5) - (l - 0.01) / 0.99).abs() < 1e-12);
        assert!((0.01f64.powf(1.0 / 2.4) - lb).abs() < 1e-12);
    }

    #[test]
    fn a_csv_table_reads_and_bad_ones_say_why() {
        let text = "# dioptra display calibration\nlevel,luminance_cd_m2,measured_cd_m2\n\
                    0,0.5,0.5\n0.2,3,3\n0.4,14,14\n0.6,35,35\n0.8,66,66\n1,110,110\n";
        let t = TransferTable::parse_csv("p.csv", text).unwrap();
        assert_eq!(t.len(), 6);
        assert_eq!(t.black_white(), (0.5, 110.0));
        let again = TransferTable::parse_csv("p.csv", &t.to_csv(&["x".into()], &[], &[])).unwrap();
        assert_eq!(
            again.points().collect::<Vec<_>>(),
            t.points().collect::<Vec<_>>()
        );
        for (bad, says) in [
            ("level,luminance_cd_m2\n0,1\n0.5,2\n1,3\n", "at least 6"),
            ("code,luminance\n0,1\n", "no level column"),
            (
                "level,luminance_cd_m2\n0,1\n0.2,2\n0.4,3\n0.6,3\n0.8,5\n1,6\n",
                "not rising",
            ),
            (
                "level,luminance_cd_m2\n0.1,1\n0.2,2\n0.4,3\n0.6,4\n0.8,5\n1,6\n",
                "black (level 0)",
            ),
            ("level,luminance_cd_m2\n0,1\n0.2,x\n", "line 3"),
            (
                "level,luminance_cd_m2\n0,1\n0.2,2\n0.4,3\n0.6,4\n0.8,5\n255,6\n",
                "outside 0..1",
            ),
        ] {
            let e = TransferTable::parse_csv("p.csv", bad)
                .unwrap_err()
                .to_string();
            assert!(e.contains(says) && e.contains("p.csv"), "{bad:?}: {e}");
        }
    }

    fn gamma_panel(levels: usize, noise: impl Fn(usize) -> f64) -> Vec<(f64, f64)> {
        (0..levels)
            .map(|k| {
                let c = k as f64 / (levels - 1) as f64;
                (c, 0.3 + 120.0 * c.powf(2.4) + noise(k))
            })
            .collect()
    }

    #[test]
    fn a_gamma_panel_fits_to_its_curve_and_a_bad_one_is_refused() {
        let fit = TransferFit::fit(&gamma_panel(9, |_| 0.0), Default::default()).unwrap();
        assert!((fit.gamma - 2.4).abs() < 1e-6, "{}", fit.gamma);
        assert_eq!(fit.degree, 1);
        let table = Transfer::Table(fit.table("t", 255).unwrap());
        let exact = Transfer::gamma(2.4, 0.0).unwrap();
        for i in 1..=100 {
            let v = i as f64 / 100.0;
            let rel = (exact.decode(table.encode(v)) - v) / v;
            assert!(rel.abs() < 2e-3, "at {v}: {rel}");
        }
        // Too few, a non-monotone reading, noise beyond the limit, no range.
        assert!(matches!(
            TransferFit::fit(&gamma_panel(5, |_| 0.0), Default::default()),
            Err(TransferFitError::TooFewLevels { got: 5 })
        ));
        let e = TransferFit::fit(
            &gamma_panel(9, |k| if k == 6 { -30.0 } else { 0.0 }),
            Default::default(),
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                TransferFitError::NotMonotonic { .. } | TransferFitError::Noisy { .. }
            ),
            "{e}"
        );
        let e = TransferFit::fit(
            &gamma_panel(17, |k| if k % 2 == 0 { 2.0 } else { -2.0 }),
            Default::default(),
        )
        .unwrap_err();
        assert!(matches!(e, TransferFitError::Noisy { .. }), "{e}");
        assert!(e.to_string().contains("--max-rms"), "{e}");
        let flat: Vec<(f64, f64)> = (0..9).map(|k| (k as f64 / 8.0, 5.0)).collect();
        assert!(matches!(
            TransferFit::fit(&flat, Default::default()),
            Err(TransferFitError::NoRange { .. })
        ));
        // Small noise passes.
        let ok = TransferFit::fit(
            &gamma_panel(17, |k| 0.2 * ((k * 7919) % 13) as f64 / 13.0 - 0.1),
            Default::default(),
        )
        .unwrap();
        assert!(ok.rms < 0.002, "{}", ok.rms);
    }

    #[test]
    fn a_panel_whose_light_turns_down_is_refused_as_not_monotonic() {
        // Smooth readings that peak at 92 % of full scale and fall 3 % by white (a panel's
        // dynamic contrast, or a photometer clipping): the fit follows them closely, and the
        // refusal says where the light stops rising.
        let points: Vec<(f64, f64)> = (0..=16)
            .map(|k| {
                let c = k as f64 / 16.0;
                (
                    c,
                    0.5 + 100.0 * (1.15 * std::f64::consts::FRAC_PI_2 * c.powf(2.4)).sin(),
                )
            })
            .collect();
        match TransferFit::fit(&points, Default::default()) {
            Err(TransferFitError::NotMonotonic { at, .. }) => assert!(at > 0.85, "{at}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_panel_that_is_not_a_power_law_fits_too() {
        // sRGB's own curve (a linear toe under a 2.4 power): within 0.3 % of white (0.26 % at
        // black, where the toe is).
        let points: Vec<(f64, f64)> = (0..=16)
            .map(|k| {
                let c = k as f64 / 16.0;
                (c, 100.0 * Transfer::Srgb.decode(c))
            })
            .collect();
        let fit = TransferFit::fit(&points, Default::default()).unwrap();
        for i in 0..=64 {
            let c = i as f64 / 64.0;
            let e = fit.luminance_at(c) / 100.0 - Transfer::Srgb.decode(c);
            assert!(e.abs() < 3e-3, "at {c}: {e}");
        }
    }
}
