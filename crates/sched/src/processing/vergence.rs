//! Vergence depth from two eye rays: the closest approach of the rays, with an uncertainty
//! propagated from the tracker's angular noise.

use dioptra_core::EyeRay;
use glam::DVec3;

/// One vergence measurement.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Vergence {
    /// Fixation depth, diopters from the midpoint of the eyes. Negative when the rays
    /// diverge (noise beyond optical infinity); kept signed so averages stay unbiased.
    pub diopters: f64,
    /// One standard deviation of `diopters`.
    pub sigma_d: f64,
    /// Midpoint of the rays' closest approach, mm, head frame (`None` when they do not converge).
    pub point_mm: Option<[f64; 3]>,
    /// Distance between the rays at their closest approach, mm (vertical misalignment).
    pub miss_mm: f64,
}

/// A direction or point as the public types hold it.
pub(crate) type V3 = [f64; 3];

/// The unit vector along `a`, when it has a length.
pub(crate) fn unit(a: DVec3) -> Option<DVec3> {
    let n = a.length();
    (n.is_finite() && n > 1e-9).then(|| a * (1.0 / n))
}
pub(crate) fn to_f64(a: [f32; 3]) -> DVec3 {
    DVec3::from(a.map(f64::from))
}

/// Vergence of two valid rays; `sigma_angle_deg` is the per-eye angular noise (1 sd).
/// `None` when either ray is invalid, non-finite, or the eyes coincide.
pub fn vergence(left: &EyeRay, right: &EyeRay, sigma_angle_deg: f64) -> Option<Vergence> {
    if !left.valid || !right.valid {
        return None;
    }
    let (p1, p2) = (to_f64(left.origin_mm), to_f64(right.origin_mm));
    let d1 = unit(to_f64(left.direction))?;
    let d2 = unit(to_f64(right.direction))?;
    if !(p1.is_finite() && p2.is_finite()) {
        return None;
    }
    let baseline = p2 - p1;
    let ipd_mm = baseline.length();
    if ipd_mm < 1.0 {
        return None;
    }
    let mid = (p1 + p2) * 0.5;
    // Closest approach of p1 + s d1 and p2 + t d2.
    let b = d1.dot(d2);
    let w = p1 - p2;
    let (d, e) = (d1.dot(w), d2.dot(w));
    let denom = 1.0 - b * b;
    // Vergence angle, signed: positive when the rays converge in front of the eyes.
    let cross_angle = denom.max(0.0).sqrt().atan2(b);
    let converging = (d1 - d2).dot(baseline) > 0.0;
    let ipd_m = ipd_mm * 1e-3;
    let sigma_angle = sigma_angle_deg.to_radians() * std::f64::consts::SQRT_2;
    let (diopters, point, miss) = if denom > 1e-12 {
        let s = (b * e - d) / denom;
        let t = (e - b * d) / denom;
        let q1 = p1 + d1 * s;
        let q2 = p2 + d2 * t;
        let miss = (q1 - q2).length();
        let point = (q1 + q2) * 0.5;
        let dist_mm = (point - mid).length();
        if converging && s > 0.0 && t > 0.0 && dist_mm > 1e-6 {
            (1000.0 / dist_mm, Some(point.to_array()), miss)
        } else {
            (-cross_angle / ipd_m, None, miss)
        }
    } else {
        (0.0, None, (w - d1 * d).length())
    };
    // Angular noise moves the vergence angle by sqrt(2) sigma; depth in diopters is
    // angle / IPD. A miss between the rays is read as extra angular error at that depth.
    let miss_angle = miss * 1e-3 * diopters.abs();
    let sigma_d = (sigma_angle.powi(2) + miss_angle.powi(2)).sqrt() / ipd_m;
    Some(Vergence {
        diopters,
        sigma_d,
        point_mm: point,
        miss_mm: miss,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray_at(origin: [f32; 3], target: [f32; 3]) -> EyeRay {
        let d: Vec<f32> = (0..3).map(|i| target[i] - origin[i]).collect();
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        EyeRay {
            origin_mm: origin,
            direction: [d[0] / n, d[1] / n, d[2] / n],
            pupil_mm: 4.0,
            valid: true,
        }
    }

    #[test]
    fn rays_aimed_at_half_a_metre_give_two_diopters() {
        for target in [
            [0.0, 0.0, 500.0],
            [120.0, -80.0, 480.0],
            [-200.0, 30.0, 450.0],
        ] {
            let l = ray_at([-32.0, 0.0, 0.0], target);
            let r = ray_at([32.0, 0.0, 0.0], target);
            let v = vergence(&l, &r, 0.5).unwrap();
            let dist = (target.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>()).sqrt();
            assert!((v.diopters - 1000.0 / dist).abs() < 0.05, "{v:?}");
            assert!(v.miss_mm < 1e-3);
        }
        let l = ray_at([-32.0, 0.0, 0.0], [0.0, 0.0, 500.0]);
        let r = ray_at([32.0, 0.0, 0.0], [0.0, 0.0, 500.0]);
        let v = vergence(&l, &r, 0.5).unwrap();
        assert!((v.diopters - 2.0).abs() < 0.05);
        // 0.5 deg per eye over a 64 mm baseline is about 0.19 D.
        assert!((v.sigma_d - 0.193).abs() < 0.01, "{}", v.sigma_d);
        let p = v.point_mm.unwrap();
        assert!((p[2] - 500.0).abs() < 0.1);
    }

    #[test]
    fn parallel_and_diverging_rays_are_at_or_beyond_infinity() {
        let fwd = |x: f32| EyeRay {
            origin_mm: [x, 0.0, 0.0],
            direction: [0.0, 0.0, 1.0],
            pupil_mm: 4.0,
            valid: true,
        };
        let v = vergence(&fwd(-32.0), &fwd(32.0), 0.5).unwrap();
        assert_eq!(v.diopters, 0.0);
        assert!(v.point_mm.is_none());
        // Each eye turned 0.1 deg outwards: about -0.055 D.
        let a = 0.1f32.to_radians();
        let mut l = fwd(-32.0);
        l.direction = [-a.sin(), 0.0, a.cos()];
        let mut r = fwd(32.0);
        r.direction = [a.sin(), 0.0, a.cos()];
        let v = vergence(&l, &r, 0.5).unwrap();
        assert!((v.diopters + 0.0545).abs() < 0.002, "{v:?}");
    }

    #[test]
    fn invalid_or_degenerate_rays_give_none() {
        let l = ray_at([-32.0, 0.0, 0.0], [0.0, 0.0, 500.0]);
        let mut r = ray_at([32.0, 0.0, 0.0], [0.0, 0.0, 500.0]);
        r.valid = false;
        assert!(vergence(&l, &r, 0.5).is_none());
        let mut r2 = l;
        r2.direction = [0.0, 0.0, 0.0];
        assert!(vergence(&l, &r2, 0.5).is_none());
        assert!(vergence(&l, &l, 0.5).is_none());
        let mut n = l;
        n.origin_mm[0] = f32::NAN;
        assert!(vergence(&n, &r2, 0.5).is_none());
    }
}
