//! The eye model and circle of confusion, as in DeepFocus (sec. 3.2.1 and its public code).
//!
//! A thin-lens eye focused at `q` diopters images a point at `d` diopters as a disk whose
//! angular diameter is `A * |d - q|` radians (A = pupil diameter in metres). On a display of
//! `width` pixels spanning a horizontal field `fov`, one pixel subtends `2 tan(fov/2) / width`
//! (tangent-plane units), so the disk is `A |d - q| width / (2 tan(fov/2))` pixels across.
//! DeepFocus's code writes the same thing through the 17 mm lens-retina distance, which cancels.
//! The multifocal kernel `|q/p - 1| * A / pixel_size` with `pixel_size = 2 tan(fov/2) / p / width`
//! reduces to the same expression with `d = p`.

use crate::error::InputError;
use crate::units::{Diopters, Meters, Millimeters};

/// Eye and display geometry. Defaults are DeepFocus's: 4 mm pupil, 17 mm lens-retina,
/// 20 degree horizontal field over 512 pixels (0.682 mrad per pixel).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EyeModel {
    pub pupil_diameter: Millimeters,
    pub lens_to_retina: Millimeters,
    pub fov_horizontal_deg: f32,
    pub width_px: u32,
}

impl Default for EyeModel {
    fn default() -> Self {
        EyeModel {
            pupil_diameter: Millimeters(4.0),
            lens_to_retina: Millimeters(17.0),
            fov_horizontal_deg: 20.0,
            width_px: 512,
        }
    }
}

impl EyeModel {
    /// Checks every field; an eye model from a config file goes through here.
    pub fn validated(self) -> Result<Self, InputError> {
        let bad = |what: &str, v: f32, want: &str| {
            Err(InputError::InvalidValue(format!(
                "{what} = {v} is invalid: expected {want}"
            )))
        };
        if !(self.pupil_diameter.0.is_finite() && self.pupil_diameter.0 > 0.0) {
            return bad(
                "pupil diameter (mm)",
                self.pupil_diameter.0,
                "a positive number, e.g. 4",
            );
        }
        if !(self.lens_to_retina.0.is_finite() && self.lens_to_retina.0 > 0.0) {
            return bad(
                "lens-retina distance (mm)",
                self.lens_to_retina.0,
                "a positive number, e.g. 17",
            );
        }
        if !(self.fov_horizontal_deg > 0.0 && self.fov_horizontal_deg < 179.0) {
            return bad(
                "horizontal field of view (deg)",
                self.fov_horizontal_deg,
                "0 < fov < 179",
            );
        }
        if self.width_px == 0 {
            return bad("width (px)", 0.0, "at least 1 pixel");
        }
        Ok(self)
    }

    /// The same eye on a display `width_px` wide (the field stays the same).
    pub fn with_width(self, width_px: u32) -> Self {
        EyeModel { width_px, ..self }
    }

    /// Size of one pixel on the tangent plane at unit distance (≈ radians for small fields).
    pub fn pixel_pitch_tan(&self) -> f32 {
        2.0 * (self.fov_horizontal_deg.to_radians() * 0.5).tan() / self.width_px as f32
    }

    /// Angle one pixel subtends at the centre of the field, radians.
    pub fn pixel_angle_rad(&self) -> f32 {
        2.0 * (0.5 * self.pixel_pitch_tan()).atan()
    }

    fn pupil_m(&self) -> f32 {
        self.pupil_diameter.to_meters().0
    }

    /// Circle-of-confusion diameter in pixels for a point at `depth` when the eye focuses at `focus`.
    pub fn coc_px(&self, depth: Diopters, focus: Diopters) -> f32 {
        self.pupil_m() * (depth.0 - focus.0).abs() / self.pixel_pitch_tan()
    }

    /// Circle-of-confusion diameter on the retina, metres (DeepFocus's `coc_m`).
    pub fn coc_retina(&self, depth: Diopters, focus: Diopters) -> Meters {
        Meters(self.pupil_m() * self.lens_to_retina.to_meters().0 * (depth.0 - focus.0).abs())
    }

    /// Multifocal retinal kernel diameter, pixels, for display plane `plane` seen focusing at `focus`.
    pub fn plane_kernel_px(&self, plane: Diopters, focus: Diopters) -> f32 {
        self.coc_px(plane, focus)
    }

    /// Depth-of-field half width in diopters: how far from focus a point may lie before its
    /// blur exceeds `max_blur_px` pixels.
    pub fn dof_half_width(&self, max_blur_px: f32) -> Diopters {
        Diopters(max_blur_px.max(0.0) * self.pixel_pitch_tan() / self.pupil_m())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f32, b: f32, tol: f32) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn deepfocus_pixel_angle() {
        // 2 tan(10°)/512 = 0.352654/512 = 6.8878e-4; DeepFocus quotes 0.68 mrad per pixel.
        let eye = EyeModel::default();
        assert!(close(eye.pixel_pitch_tan(), 6.8878e-4, 1e-7));
        assert!(close(eye.pixel_angle_rad(), 6.8878e-4, 1e-7));
    }

    #[test]
    fn coc_hand_computed() {
        let eye = EyeModel::default();
        // 0.004 m * 1 D / 6.8878e-4 = 5.8074 px
        assert!(close(
            eye.coc_px(Diopters(2.0), Diopters(1.0)),
            5.8074,
            1e-3
        ));
        // symmetric, zero in focus
        assert!(close(
            eye.coc_px(Diopters(0.5), Diopters(1.5)),
            5.8074,
            1e-3
        ));
        assert_eq!(eye.coc_px(Diopters(1.5), Diopters(1.5)), 0.0);
        // 0.1 D to 4.0 D (the extremes of DeepFocus's focal stack): 3.9 D -> 22.649 px
        assert!(close(
            eye.coc_px(Diopters(0.1), Diopters(4.0)),
            22.649,
            2e-3
        ));
        // 8 mm pupil doubles it
        let wide = EyeModel {
            pupil_diameter: Millimeters(8.0),
            ..eye
        };
        assert!(close(
            wide.coc_px(Diopters(2.0), Diopters(1.0)),
            11.6148,
            2e-3
        ));
        // a 256-px render of the same field halves it
        assert!(close(
            eye.with_width(256).coc_px(Diopters(2.0), Diopters(1.0)),
            2.9037,
            1e-3
        ));
        // retina: 0.004 * 0.017 * 1 = 6.8e-5 m
        assert!(close(
            eye.coc_retina(Diopters(2.0), Diopters(1.0)).0,
            6.8e-5,
            1e-9
        ));
    }

    #[test]
    fn deepfocus_code_formula_agrees() {
        // DeepFocus's code: P = 1/0.017 + q; coc_m = A |(P - d)/(P - q) - 1|;
        // coc_px = coc_m / (2 * 0.017 * tan(fov/2)) * width.
        let eye = EyeModel::default();
        for (d, q) in [(0.1f32, 2.2f32), (1.0, 1.4), (3.7, 0.2)] {
            let p = 1.0 / 0.017 + q;
            let coc_m = 0.004 * ((p - d) / (p - q) - 1.0).abs();
            let theirs = coc_m / (2.0 * 0.017 * 10f32.to_radians().tan()) * 512.0;
            let ours = eye.coc_px(Diopters(d), Diopters(q));
            assert!(
                close(ours, theirs, 1e-3 * theirs.max(1.0)),
                "{d} {q}: {ours} vs {theirs}"
            );
        }
    }

    #[test]
    fn dof_inverts_coc() {
        let eye = EyeModel::default();
        let half = eye.dof_half_width(1.0);
        assert!(close(
            eye.coc_px(Diopters(1.0 + half.0), Diopters(1.0)),
            1.0,
            1e-4
        ));
    }

    #[test]
    fn validation_names_the_field() {
        let e = EyeModel {
            fov_horizontal_deg: 0.0,
            ..EyeModel::default()
        }
        .validated();
        assert!(matches!(e, Err(InputError::InvalidValue(m)) if m.contains("field of view")));
        assert!(EyeModel::default().validated().is_ok());
    }
}
