//! The viewer's spectacle prescription (sphere only).
//!
//! A point at demand `A` (a point `1/A` metres in front of the eye) reaches spectacles worn
//! `v` metres in front of the eye with vergence `L = -1 / (1/A - v) = -A / (1 - v A)`; the
//! spectacle sphere `R` (a myope's is negative) adds its power, `L' = L + R`, and after `v`
//! metres more the light reaches the eye at `V = L' / (1 - v L')`. A corrected eye therefore
//! accommodates `-V` to see the point: that is the demand the rig must present to the
//! uncorrected eye so it sees what the corrected eye would. At `v = 0` it is simply `A - R`:
//! a -1 D myope looking at 1.5 D is shown 2.5 D (1.5 D beyond the far point at 1 m).
//! The inverse runs the same steps backwards: `L' = V / (1 + v V)`, `L = L' - R`,
//! `A = -L / (1 - v L)`.

use super::{OpticsError, MAX_FOCUS_D};

/// Spectacle prescriptions are written for a vertex distance; 12 mm is the usual one.
pub const DEFAULT_VERTEX_M: f64 = 0.012;

/// A spectacle sphere and the vertex distance it was prescribed at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prescription {
    /// Spectacle sphere, diopters (a myope's is negative); 0: no correction.
    pub sphere_d: f64,
    /// Spectacle lens to the eye, metres.
    pub vertex_m: f64,
}

impl Default for Prescription {
    fn default() -> Self {
        Prescription {
            sphere_d: 0.0,
            vertex_m: DEFAULT_VERTEX_M,
        }
    }
}

impl Prescription {
    /// Checks the values; `cylinder_d` is taken only to refuse it clearly when it is not 0.
    pub fn new(sphere_d: f64, cylinder_d: f64, vertex_m: f64) -> Result<Self, OpticsError> {
        if !(sphere_d.is_finite() && sphere_d.abs() <= 20.0) {
            return Err(OpticsError::invalid(
                "prescription_sphere_d",
                format!(
                    "{sphere_d}: expected the spectacle sphere in diopters, -20 to 20 (a myope's \
                     is negative)"
                ),
            ));
        }
        if cylinder_d != 0.0 {
            return Err(OpticsError::invalid(
                "prescription_cylinder_d",
                format!(
                    "{cylinder_d} D: astigmatism cannot be corrected by a spherical tunable lens, \
                     and the rig does not render it. Give the spherical equivalent (sphere + \
                     cylinder / 2 = {:.2} D) as prescription_sphere_d if the cylinder is small, \
                     or have the viewer wear their own correction (contact lenses) and leave \
                     the prescription at 0",
                    sphere_d + cylinder_d / 2.0
                ),
            ));
        }
        if !(vertex_m.is_finite() && (0.0..=0.025).contains(&vertex_m)) {
            return Err(OpticsError::invalid(
                "prescription_vertex_mm",
                format!(
                    "{} mm: expected the vertex distance the prescription was written for, 0 to \
                     25 mm (usually 12)",
                    vertex_m * 1000.0
                ),
            ));
        }
        Ok(Prescription { sphere_d, vertex_m })
    }

    /// True when it changes nothing.
    pub fn is_none(&self) -> bool {
        self.sphere_d == 0.0
    }

    /// The demand to present to the uncorrected eye for a point at demand `focus_d`.
    pub fn presented(&self, focus_d: f64) -> f64 {
        if self.is_none() {
            return focus_d;
        }
        let (v, a) = (self.vertex_m, focus_d.clamp(-MAX_FOCUS_D, MAX_FOCUS_D));
        let at_spectacles = -a / (1.0 - v * a) + self.sphere_d;
        -at_spectacles / (1.0 - v * at_spectacles)
    }

    /// The inverse of [`Prescription::presented`]: the focus a corrected eye has when the
    /// uncorrected eye is shown `presented_d`.
    pub fn focus_of(&self, presented_d: f64) -> f64 {
        if self.is_none() {
            return presented_d;
        }
        let v = self.vertex_m;
        let at_eye = -presented_d.clamp(-MAX_FOCUS_D, MAX_FOCUS_D);
        let after_spectacles = at_eye / (1.0 + v * at_eye);
        let before = after_spectacles - self.sphere_d;
        -before / (1.0 - v * before)
    }
}
