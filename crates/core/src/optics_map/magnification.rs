//! Magnification compensation: the scale that keeps the image's angular size at the eye
//! constant as the tunable lens's power changes.
//!
//! A layout's image subtends `M(P)` times the bare display's angle at lens power `P`
//! ([`ThinLensLayout::magnification_at`]). The reference is the power of least magnification
//! in the lens range (the range's lower end when the eye relief is above 0, since `M` grows
//! with `P` there; every power when it is 0): scaling the panel's image by
//! `c(P) = M(P_ref) / M(P)` about the optical axis keeps every angle what it is at `P_ref`,
//! and `c <= 1`, so the compensated image only ever shrinks on the panel and nothing drawn
//! is cut off. The renderer's field (and an eyepiece's distortion model, measured there)
//! is then the one seen at `P_ref`.
//!
//! [`ThinLensLayout::magnification_at`]: super::ThinLensLayout::magnification_at

use super::OpticsMap;
use crate::units::Diopters;

impl OpticsMap {
    /// The lens command of least magnification over the lens range (see the module's
    /// notes); `None` without a layout.
    pub fn magnification_reference(&self) -> Option<Diopters> {
        let l = self.layout()?;
        let r = self.range();
        let (lo, hi) = (f64::from(r.min.0), f64::from(r.max.0));
        Some(if l.magnification_at(hi) < l.magnification_at(lo) {
            r.max
        } else {
            r.min
        })
    }

    /// The scale for the panel's image at lens command `command` that keeps angular sizes
    /// what they are at `reference`: `M(reference) / M(command)`. `None` without a layout
    /// (the magnification is not known).
    pub fn size_compensation(&self, command: Diopters, reference: Diopters) -> Option<f64> {
        let l = self.layout()?;
        Some(l.magnification_at(f64::from(reference.0)) / l.magnification_at(f64::from(command.0)))
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Prescription, ThinLensLayout};
    use super::*;
    use crate::units::PowerRange;

    /// A square 10 mm wide on a display 50 mm from the lens, eye relief 15 mm, no fixed lens,
    /// lens range -2..+6 D. By hand (the chief ray through the pupil's centre meets the lens
    /// at y = s h / (d + s - s d P), so the half-angle's tangent is h / (d + s - s d P)):
    /// P = -2: 5 / (65 + 1.5) mm = 0.075187969..., P = +6: 5 / (65 - 4.5) = 0.082644628...
    /// The reference is -2 D (least magnification); compensated, the square is drawn
    /// c(P) = M(-2) / M(P) = (65 - 0.75 P) / 66.5 times as wide.
    #[test]
    fn a_compensated_square_keeps_its_angle_over_the_lens_range() {
        let layout = ThinLensLayout::new(0.05, 0.015, 0.0).unwrap();
        let range = PowerRange::new(Diopters(-2.0), Diopters(6.0)).unwrap();
        let map = OpticsMap::new(Some(layout), None, Prescription::default(), range).unwrap();
        assert_eq!(map.magnification_reference(), Some(Diopters(-2.0)));
        let half_mm = 5.0;
        // The square's half-angle tangent at power P for a half-width h on the display, by
        // the formula above (millimetres).
        let tangent = |h: f64, p: f64| h / (50.0 + 15.0 - 15.0 * 50.0 * p / 1000.0);
        assert!((tangent(half_mm, -2.0) - 0.075_187_969_924_812).abs() < 1e-12);
        assert!((tangent(half_mm, 6.0) - 0.082_644_628_099_174).abs() < 1e-12);
        let want = tangent(half_mm, -2.0);
        let mut uncompensated_spread = 0.0f64;
        for i in 0..=80 {
            let p = -2.0 + 0.1 * i as f64;
            let c = map
                .size_compensation(Diopters(p as f32), Diopters(-2.0))
                .unwrap();
            // By hand: c = (65 - 0.75 P) / 66.5.
            let p32 = f64::from(p as f32);
            assert!(
                (c - (65.0 - 0.75 * p32) / 66.5).abs() < 1e-12,
                "c at {p}: {c}"
            );
            assert!(c <= 1.0 + 1e-12);
            let seen = tangent(c * half_mm, p32);
            assert!(
                ((seen - want) / want).abs() < 1e-3,
                "at {p} D: {seen} vs {want}"
            );
            uncompensated_spread = uncompensated_spread.max((tangent(half_mm, p32) - want) / want);
        }
        // Without the compensation it grows by 9.9 % over the range.
        assert!(uncompensated_spread > 0.09, "{uncompensated_spread}");
    }

    #[test]
    fn no_layout_no_compensation_and_a_lens_at_the_pupil_needs_none() {
        let range = PowerRange::new(Diopters(0.0), Diopters(4.0)).unwrap();
        assert_eq!(
            OpticsMap::identity(range).size_compensation(Diopters(1.0), Diopters(0.0)),
            None
        );
        let at_pupil = ThinLensLayout::new(0.05, 0.0, 10.0).unwrap();
        let map = OpticsMap::new(Some(at_pupil), None, Prescription::default(), range).unwrap();
        for p in [0.0, 1.5, 4.0] {
            assert_eq!(map.size_compensation(Diopters(p), Diopters(0.0)), Some(1.0));
        }
    }
}
