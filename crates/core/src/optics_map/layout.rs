//! The thin-lens layout of one eye's optics: display, tunable lens (with any fixed lens at
//! the same place), eye.
//!
//! Sign conventions (vergence, diopters): light travels from the display towards the eye; a
//! vergence is 1 / (the signed distance from the reference plane to the point the light
//! diverges from or converges to), negative for diverging light. A lens adds its power to the
//! vergence of the light crossing it (a converging lens has positive power).
//!
//! - Light from a display point `d` metres in front of the lens reaches it diverging: `-1/d`.
//! - Leaving the lens of total power `P` (fixed + tunable): `V1 = P - 1/d`.
//! - That light converges to (V1 > 0) or diverges from (V1 < 0) a point `1/V1` metres behind
//!   the lens, which is `1/V1 - s` from the eye's pupil `s` metres on; at the pupil the
//!   vergence is `V = 1 / (1/V1 - s) = V1 / (1 - s V1)`.
//! - The eye must accommodate `A = -V` diopters to focus it (a point 1/A metres in front):
//!   with `X = 1/d - P` (= `-V1`), `A = X / (1 + s X)`, the formula in hardware.md.
//! - Inverse: `X = A / (1 - s A)`, so the tunable power is `P - fixed = 1/d - fixed - X`.
//!
//! `s = 0` (the tunable lens at the pupil, or imaged onto it) makes the map linear,
//! `A = 1/d - P`, with slope -1: more lens power, a farther image. Angular size: the chief ray
//! from a display point at height `h` through the pupil's centre crosses the lens at height
//! `y = s h / (d + s - s d P)`, so the image subtends `h / (d + s - s d P)` at the eye; the bare
//! display (no lens, same place) subtends `h / (d + s)`. Their ratio is the angular
//! magnification, `(d + s) / (d + s - s d P)`: 1 at `s = 0`, and changing with `P` otherwise.
//! Since `d + s - s d P = d (1 + s X)`, it is positive (an upright image) exactly where the
//! demand formula is on the physical side of its pole (`1 + s X > 0`).

use super::{OpticsError, MAX_FOCUS_D};

/// Display, lens and eye positions of one eye (metres; powers in diopters).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThinLensLayout {
    /// Display to the tunable lens, metres (> 0).
    pub display_distance_m: f64,
    /// Tunable lens to the eye's entrance pupil, metres (>= 0).
    pub eye_relief_m: f64,
    /// A fixed lens (an eyepiece) at the tunable lens, diopters; 0 if none.
    pub fixed_power_d: f64,
}

impl ThinLensLayout {
    /// Checks every field; errors name the key as rig.toml spells it.
    pub fn new(
        display_distance_m: f64,
        eye_relief_m: f64,
        fixed_power_d: f64,
    ) -> Result<Self, OpticsError> {
        if !(display_distance_m.is_finite()
            && display_distance_m > 0.0
            && display_distance_m <= 100.0)
        {
            return Err(OpticsError::invalid(
                "display_distance_m",
                format!(
                    "{display_distance_m}: expected the display's distance from the tunable lens, \
                     0 to 100 m (e.g. 0.05)"
                ),
            ));
        }
        if !(eye_relief_m.is_finite() && (0.0..=0.2).contains(&eye_relief_m)) {
            return Err(OpticsError::invalid(
                "eye_relief_m",
                format!(
                    "{eye_relief_m}: expected the tunable lens's distance from the eye's pupil, \
                     0 to 0.2 m (e.g. 0.015; 0 for a lens at the pupil or a Badal system)"
                ),
            ));
        }
        if !(fixed_power_d.is_finite() && fixed_power_d.abs() <= 200.0) {
            return Err(OpticsError::invalid(
                "fixed_power_d",
                format!(
                    "{fixed_power_d}: expected the fixed lens's power, -200 to 200 D (0 if none)"
                ),
            ));
        }
        Ok(ThinLensLayout {
            display_distance_m,
            eye_relief_m,
            fixed_power_d,
        })
    }

    /// `X = 1/d - P` for a tunable power: the display's demand with the lens at the eye.
    fn x_of(&self, tunable_d: f64) -> f64 {
        1.0 / self.display_distance_m - self.fixed_power_d - tunable_d
    }

    /// Whether a tunable power forms the display's image in front of the eye, where
    /// [`ThinLensLayout::demand_at`] describes it (`1 + s X > 0`) and within [`MAX_FOCUS_D`].
    pub fn image_in_front(&self, tunable_d: f64) -> bool {
        1.0 + self.eye_relief_m * self.x_of(tunable_d) > 0.0
            && self.demand_at(tunable_d).abs() <= MAX_FOCUS_D
    }

    /// Accommodation demand at the eye for a tunable-lens power (the formula above).
    pub fn demand_at(&self, tunable_d: f64) -> f64 {
        let x = self.x_of(tunable_d);
        x / (1.0 + self.eye_relief_m * x)
    }

    /// The tunable-lens power giving accommodation demand `demand_d` (the inverse).
    /// `None` for a demand no lens power gives: an image at or behind the lens (`A >= 1/s`).
    pub fn power_for(&self, demand_d: f64) -> Option<f64> {
        let denominator = 1.0 - self.eye_relief_m * demand_d;
        (denominator > 0.0)
            .then(|| 1.0 / self.display_distance_m - self.fixed_power_d - demand_d / denominator)
    }

    /// Angular magnification at a tunable-lens power: the image's angular size at the eye
    /// over the bare display's at the same place.
    pub fn magnification_at(&self, tunable_d: f64) -> f64 {
        let (d, s) = (self.display_distance_m, self.eye_relief_m);
        let p = self.fixed_power_d + tunable_d;
        (d + s) / (d + s - s * d * p)
    }

    /// Whether every power in `lo..=hi` puts the display's image in front of the eye
    /// (`1 + s X > 0`, the side of the pole the formula describes; the image is then upright),
    /// no nearer than [`MAX_FOCUS_D`]: the map is finite and monotone there. `1 + s X` is
    /// linear in the power, so checking the ends checks the range.
    pub(super) fn check_range(&self, lo: f64, hi: f64) -> Result<(), OpticsError> {
        for p in [lo, hi] {
            if !self.image_in_front(p) {
                return Err(OpticsError::invalid(
                    "layout",
                    format!(
                        "at a lens power of {p} D this layout (display {} m, eye relief {} m, \
                         fixed lens {} D) forms the display's image at or behind the eye, or \
                         nearer than {MAX_FOCUS_D} D: check the distances and optics.lens_range",
                        self.display_distance_m, self.eye_relief_m, self.fixed_power_d
                    ),
                ));
            }
        }
        Ok(())
    }
}
