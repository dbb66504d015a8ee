//! A measured calibration table: lens command -> accommodation demand at the eye, read
//! through a monotone cubic (PCHIP, Fritsch & Carlson 1980, with the shape-preserving end
//! slopes of Fritsch & Butland as SciPy's `PchipInterpolator` uses), so that the map is
//! monotone between the points whatever their spacing, and inverted exactly (the inverse
//! solves the same cubic, so a focus turned into a command and back comes back).
//!
//! The file is CSV: `#` lines are comments (the provenance `dioptra lens calibrate` writes),
//! the first other line names the columns, and the columns `command_d` and `demand_d` are
//! read; any others (readback, temperature, the raw measurement) are kept for people.

use super::OpticsError;
use crate::table_csv::TableColumns;

/// The file's columns.
const COLUMNS: TableColumns = TableColumns {
    names: ["command_d", "demand_d"],
    row: "point",
    meaning: "command_d and demand_d (the lens command and the accommodation demand measured \
              at the eye, diopters)",
    number: "a number of diopters",
};

/// Fewest points a table may have.
pub const MIN_POINTS: usize = 4;
/// Widest gap between neighbouring commands, diopters: between points the table is an
/// interpolation, and a lens's curve is not known over wider gaps.
pub const MAX_GAP_D: f64 = 1.0;
/// Slack when checking that a table covers the lens range, diopters (0.005 D is the
/// Lens Driver 4's resolution; commands written with three decimals round within this).
const COVER_SLACK_D: f64 = 0.005;

/// A monotone table of (lens command, demand) points, commands increasing.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationTable {
    /// Where it came from, for messages (a file name).
    name: String,
    commands: Vec<f64>,
    demands: Vec<f64>,
    /// The file's line of each point (0 where the points did not come from a file).
    lines: Vec<usize>,
    /// PCHIP derivative at each point.
    slopes: Vec<f64>,
}

/// " (line N)" for a point from a file, "" otherwise.
fn on_line(line: usize) -> String {
    match line {
        0 => String::new(),
        l => format!(" (line {l})"),
    }
}

fn point(c: f64, a: f64) -> String {
    format!("(command {c} D, demand {a} D)")
}

impl CalibrationTable {
    /// A table of `(command_d, demand_d)` points (any order). Refused, naming `name` and the
    /// points: fewer than [`MIN_POINTS`], a repeated command, a value that is not a number, or
    /// a demand that is not strictly monotone in the command.
    pub fn new(name: &str, points: &[(f64, f64)]) -> Result<Self, OpticsError> {
        let lines = vec![0; points.len()];
        Self::with_lines(name, points, &lines)
    }

    fn with_lines(name: &str, points: &[(f64, f64)], lines: &[usize]) -> Result<Self, OpticsError> {
        let err = |message: String| OpticsError::Table {
            file: name.to_string(),
            message,
        };
        if points.len() < MIN_POINTS {
            return Err(err(format!(
                "{} points; a table needs at least {MIN_POINTS}, at most {MAX_GAP_D} D apart",
                points.len()
            )));
        }
        if let Some(i) = points
            .iter()
            .position(|(c, a)| !(c.is_finite() && a.is_finite()))
        {
            let (c, a) = points[i];
            return Err(err(format!(
                "{} is not a pair of numbers{}",
                point(c, a),
                on_line(lines[i])
            )));
        }
        let mut order: Vec<usize> = (0..points.len()).collect();
        order.sort_by(|&i, &j| points[i].0.total_cmp(&points[j].0));
        let commands: Vec<f64> = order.iter().map(|&i| points[i].0).collect();
        let demands: Vec<f64> = order.iter().map(|&i| points[i].1).collect();
        let lines: Vec<usize> = order.iter().map(|&i| lines[i]).collect();
        let at = |k: usize| on_line(lines[k]);
        for k in 1..commands.len() {
            if commands[k] == commands[k - 1] {
                return Err(err(format!(
                    "command {} D appears twice{}{}: give one demand per command",
                    commands[k],
                    at(k - 1),
                    at(k)
                )));
            }
        }
        let rising = demands[commands.len() - 1] > demands[0];
        for k in 1..commands.len() {
            let step = demands[k] - demands[k - 1];
            if step == 0.0 || (step > 0.0) != rising {
                return Err(err(format!(
                    "not monotonic: the demand {} overall with the command, but {}{} -> {}{} {}; \
                     measure these points again (a table must rise or fall strictly)",
                    if rising { "rises" } else { "falls" },
                    point(commands[k - 1], demands[k - 1]),
                    at(k - 1),
                    point(commands[k], demands[k]),
                    at(k),
                    if step == 0.0 {
                        "stays level"
                    } else if rising {
                        "falls"
                    } else {
                        "rises"
                    },
                )));
            }
        }
        let slopes = pchip_slopes(&commands, &demands);
        Ok(CalibrationTable {
            name: name.to_string(),
            commands,
            demands,
            lines,
            slopes,
        })
    }

    /// Parses the CSV text of a table (see the module's notes); `name` is the file, for messages.
    pub fn parse_csv(name: &str, text: &str) -> Result<Self, OpticsError> {
        let rows = COLUMNS.read(text).map_err(|message| OpticsError::Table {
            file: name.to_string(),
            message,
        })?;
        let points: Vec<(f64, f64)> = rows.iter().map(|(_, [c, a])| (*c, *a)).collect();
        let lines: Vec<usize> = rows.iter().map(|(line, _)| *line).collect();
        Self::with_lines(name, &points, &lines)
    }

    /// Writes the table as CSV: `comments` as `#` lines (provenance), then the points, with any
    /// extra columns (`extra_names` and one row of values per point).
    pub fn to_csv(
        &self,
        comments: &[String],
        extra_names: &[&str],
        extra: &[Vec<String>],
    ) -> String {
        let points = self.points().map(|(c, a)| format!("{c:.4},{a:.4}"));
        COLUMNS.write(comments, points, extra_names, extra)
    }

    /// The file (or other name) the table came from.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The points, commands increasing.
    pub fn points(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.commands
            .iter()
            .copied()
            .zip(self.demands.iter().copied())
    }

    pub fn len(&self) -> usize {
        self.commands.len()
    }

    pub fn is_empty(&self) -> bool {
        self.commands.is_empty()
    }

    /// The commands the table spans.
    pub fn command_span(&self) -> (f64, f64) {
        (self.commands[0], self.commands[self.commands.len() - 1])
    }

    /// Refuses a table that does not cover the lens range `lo..=hi`, or has a gap wider than
    /// [`MAX_GAP_D`] inside it, naming the points.
    pub fn check_covers(&self, lo: f64, hi: f64) -> Result<(), OpticsError> {
        let err = |message: String| OpticsError::Table {
            file: self.name.clone(),
            message,
        };
        let (first, last) = self.command_span();
        if first > lo + COVER_SLACK_D || last < hi - COVER_SLACK_D {
            return Err(err(format!(
                "its commands span {first}..{last} D, but optics.lens_range is {lo}..{hi} D: \
                 calibrate over the whole range (or narrow the range)"
            )));
        }
        for k in 1..self.commands.len() {
            let (a, b) = (self.commands[k - 1], self.commands[k]);
            if b - a > MAX_GAP_D + 1e-9 && b > lo && a < hi {
                return Err(err(format!(
                    "too sparse for the lens range: no point between {} and {}, {:.3} D apart \
                     (at most {MAX_GAP_D} D); measure more points there",
                    point(a, self.demands[k - 1]),
                    point(b, self.demands[k]),
                    b - a
                )));
            }
        }
        Ok(())
    }

    /// The segment holding command `c` (clamped to the table), and its parameters.
    fn segment(&self, c: f64) -> usize {
        let n = self.commands.len();
        match self.commands.partition_point(|&x| x <= c) {
            0 => 0,
            k if k >= n => n - 2,
            k => k - 1,
        }
    }

    /// The Hermite cubic of segment `k` at `t` in 0..=1.
    fn hermite(&self, k: usize, t: f64) -> f64 {
        let h = self.commands[k + 1] - self.commands[k];
        let (y0, y1) = (self.demands[k], self.demands[k + 1]);
        let (m0, m1) = (self.slopes[k] * h, self.slopes[k + 1] * h);
        let (t2, t3) = (t * t, t * t * t);
        (2.0 * t3 - 3.0 * t2 + 1.0) * y0
            + (t3 - 2.0 * t2 + t) * m0
            + (-2.0 * t3 + 3.0 * t2) * y1
            + (t3 - t2) * m1
    }

    /// Demand at lens command `c`; outside the table, the demand at its nearer end.
    pub fn demand_at(&self, c: f64) -> f64 {
        let (first, last) = self.command_span();
        let c = c.clamp(first, last);
        let k = self.segment(c);
        let h = self.commands[k + 1] - self.commands[k];
        self.hermite(k, (c - self.commands[k]) / h)
    }

    /// The lens command giving demand `a` (the inverse of [`CalibrationTable::demand_at`]);
    /// outside the table's demands, the command at its nearer end.
    pub fn command_for(&self, a: f64) -> f64 {
        let n = self.commands.len();
        let rising = self.demands[n - 1] > self.demands[0];
        // Work on a rising sequence: negate a falling one.
        let sign = if rising { 1.0 } else { -1.0 };
        let target = sign * a;
        if target <= sign * self.demands[0] {
            return self.commands[0];
        }
        if target >= sign * self.demands[n - 1] {
            return self.commands[n - 1];
        }
        let k = self.demands.partition_point(|&y| sign * y <= target) - 1;
        let k = k.min(n - 2);
        // The cubic is monotone on its segment: bisect for t (60 halvings reach f64's
        // resolution of 0..1).
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if sign * self.hermite(k, mid) < target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let h = self.commands[k + 1] - self.commands[k];
        self.commands[k] + 0.5 * (lo + hi) * h
    }

    /// Where each point came from in its file (0: not from a file).
    pub fn lines(&self) -> &[usize] {
        &self.lines
    }
}

/// PCHIP derivatives (Fritsch & Carlson's weighted harmonic mean inside; Fritsch & Butland's
/// shape-preserving three-point formula at the ends), as SciPy's `PchipInterpolator`.
pub(crate) fn pchip_slopes(x: &[f64], y: &[f64]) -> Vec<f64> {
    let n = x.len();
    let h: Vec<f64> = (0..n - 1).map(|k| x[k + 1] - x[k]).collect();
    let delta: Vec<f64> = (0..n - 1).map(|k| (y[k + 1] - y[k]) / h[k]).collect();
    if n == 2 {
        return vec![delta[0]; 2];
    }
    let mut d = vec![0.0; n];
    for k in 1..n - 1 {
        let (a, b) = (delta[k - 1], delta[k]);
        if a == 0.0 || b == 0.0 || (a > 0.0) != (b > 0.0) {
            d[k] = 0.0;
        } else {
            let w1 = 2.0 * h[k] + h[k - 1];
            let w2 = h[k] + 2.0 * h[k - 1];
            d[k] = (w1 + w2) / (w1 / a + w2 / b);
        }
    }
    let end = |h0: f64, h1: f64, m0: f64, m1: f64| {
        let d = ((2.0 * h0 + h1) * m0 - h0 * m1) / (h0 + h1);
        if d.signum() != m0.signum() {
            0.0
        } else if m0.signum() != m1.signum() && d.abs() > 3.0 * m0.abs() {
            3.0 * m0
        } else {
            d
        }
    };
    d[0] = end(h[0], h[1], delta[0], delta[1]);
    d[n - 1] = end(h[n - 2], h[n - 3], delta[n - 2], delta[n - 3]);
    d
}
