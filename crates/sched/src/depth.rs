//! Fixation depth from the frame's depth map at the gaze point, occlusion-aware: the depths in
//! a small window around the gaze point are binned in diopters and split into surfaces (the
//! histogram's modes). A mean across an occluding edge would land between two surfaces, on
//! nothing; a mode lands on one of them. Vergence then picks between the surfaces: it is
//! noisy and lags, but tells near from far.

use dioptra_core::{DepthMap, Diopters};

/// Window and binning settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthWindow {
    /// Radius of the window around the gaze point, degrees (about the tracker's accuracy).
    pub radius_deg: f32,
    /// Histogram bin width, diopters.
    pub bin_d: f32,
    /// At most this many samples across the window's diameter (larger windows are strided).
    pub max_samples_across: usize,
}

impl Default for DepthWindow {
    fn default() -> Self {
        DepthWindow {
            radius_deg: 0.75,
            bin_d: 0.05,
            max_samples_across: 24,
        }
    }
}

const BINS: usize = 256;
/// Most surfaces reported from one window.
pub const MAX_SURFACES: usize = 3;

/// One surface in the window.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Surface {
    pub diopters: f32,
    /// Share of the window's (centre-weighted) samples on this surface, 0..=1.
    pub share: f32,
}

/// The surfaces found around a gaze point, largest share first.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WindowDepth {
    pub surfaces: [Surface; MAX_SURFACES],
    pub count: usize,
}

impl WindowDepth {
    pub fn surfaces(&self) -> &[Surface] {
        &self.surfaces[..self.count]
    }

    /// The surface to focus on: the largest, unless vergence (diopters, 1-sd uncertainty)
    /// clearly favours another one present in the window.
    pub fn choose(&self, vergence: Option<(f64, f64)>) -> Option<Surface> {
        let s = self.surfaces();
        let Some((vd, sigma)) = vergence.filter(|v| v.0.is_finite() && v.1.is_finite()) else {
            return s.first().copied();
        };
        // Vergence lags accommodation demand by ~150 ms: widen its uncertainty by that much.
        let sig = (sigma * sigma + 0.25 * 0.25).sqrt().max(1e-3);
        s.iter()
            .copied()
            .map(|c| {
                let z = (f64::from(c.diopters) - vd) / sig;
                (c, f64::from(c.share) * (0.2 + (-0.5 * z * z).exp()))
            })
            .fold(
                None,
                |best: Option<(Surface, f64)>, (c, score)| match best {
                    Some((_, b)) if b >= score => best,
                    _ => Some((c, score)),
                },
            )
            .map(|(c, _)| c)
    }
}

/// Pixel position (x, y, centres at +0.5) of a head-frame direction (+x right, +y up, +z
/// forward) on an image spanning `fov_horizontal_deg` across its width, centred straight ahead
/// (the scene's camera convention: y down). `None` behind the eye.
pub fn pixel_of(direction: [f64; 3], width: usize, fov_horizontal_deg: f32) -> Option<(f64, f64)> {
    let [dx, dy, dz] = direction;
    if dz.is_nan() || dz <= 1e-6 || width == 0 {
        return None;
    }
    let pitch = 2.0 * (f64::from(fov_horizontal_deg).to_radians() * 0.5).tan() / width as f64;
    if !(pitch.is_finite() && pitch > 0.0) {
        return None;
    }
    Some((dx / dz / pitch, -dy / dz / pitch))
}

/// The surfaces in the window around `direction` (see [`pixel_of`]). `None` when the gaze
/// point is off the image or the window holds no valid depth.
pub fn window_depth(
    depth: &DepthMap,
    direction: [f64; 3],
    fov_horizontal_deg: f32,
    cfg: &DepthWindow,
) -> Option<WindowDepth> {
    let (w, h) = (depth.width(), depth.height());
    let (ox, oy) = pixel_of(direction, w, fov_horizontal_deg)?;
    let (cx, cy) = (ox + w as f64 * 0.5, oy + h as f64 * 0.5);
    if !(cx >= 0.0 && cy >= 0.0 && cx < w as f64 && cy < h as f64) {
        return None;
    }
    let pitch = 2.0 * (f64::from(fov_horizontal_deg).to_radians() * 0.5).tan() / w as f64;
    let radius = (f64::from(cfg.radius_deg.max(0.0)).to_radians().tan() / pitch).max(0.5);
    let across = cfg.max_samples_across.clamp(1, 64) as f64;
    let step = (2.0 * radius / across).max(1.0);
    let sigma2 = (0.5 * radius).powi(2).max(0.25);
    let bin = f64::from(cfg.bin_d).max(1e-3);
    let mut weight = [0.0f32; BINS];
    let mut sum = [0.0f32; BINS];
    let data = depth.data();
    let n = (2.0 * radius / step).ceil() as i64;
    let mut total = 0.0f32;
    for j in 0..=n {
        let dy = -radius + j as f64 * step;
        for i in 0..=n {
            let dx = -radius + i as f64 * step;
            let r2 = dx * dx + dy * dy;
            if r2 > radius * radius {
                continue;
            }
            let (x, y) = ((cx + dx).floor(), (cy + dy).floor());
            if x < 0.0 || y < 0.0 || x >= w as f64 || y >= h as f64 {
                continue;
            }
            let d = data[y as usize * w + x as usize];
            if !(d.is_finite() && d >= 0.0) {
                continue;
            }
            let k = ((f64::from(d) / bin) as usize).min(BINS - 1);
            let wt = (-0.5 * r2 / sigma2).exp() as f32;
            weight[k] += wt;
            sum[k] += wt * d;
            total += wt;
        }
    }
    if total <= 0.0 {
        return None;
    }
    // Surfaces: peaks of the histogram smoothed over 3 bins, each taking the bins within two
    // of it (a slanted surface spreads over a few bins).
    let smooth = |k: usize| {
        weight[k.saturating_sub(1)] * 0.5 + weight[k] + weight[(k + 1).min(BINS - 1)] * 0.5
    };
    let mut out = WindowDepth::default();
    let mut taken = [false; BINS];
    for _ in 0..MAX_SURFACES {
        let mut best: Option<(usize, f32)> = None;
        for k in 0..BINS {
            if taken[k] || weight[k] <= 0.0 {
                continue;
            }
            let s = smooth(k);
            if best.is_none_or(|b| s > b.1) {
                best = Some((k, s));
            }
        }
        let Some((k, _)) = best else { break };
        let (lo, hi) = (k.saturating_sub(2), (k + 2).min(BINS - 1));
        let (mut wsum, mut dsum) = (0.0f32, 0.0f32);
        for b in lo..=hi {
            if !taken[b] {
                wsum += weight[b];
                dsum += sum[b];
                taken[b] = true;
            }
        }
        if wsum <= 0.0 {
            continue;
        }
        let share = wsum / total;
        // Specks (a few pixels of another surface) are not worth focusing on.
        if out.count > 0 && share < 0.05 {
            break;
        }
        out.surfaces[out.count] = Surface {
            diopters: dsum / wsum,
            share,
        };
        out.count += 1;
    }
    (out.count > 0).then_some(out)
}

/// The depth to focus on at `direction`: a surface from the window, chosen with vergence.
pub fn fixation_depth(
    depth: &DepthMap,
    direction: [f64; 3],
    fov_horizontal_deg: f32,
    cfg: &DepthWindow,
    vergence: Option<(f64, f64)>,
) -> Option<Diopters> {
    window_depth(depth, direction, fov_horizontal_deg, cfg)?
        .choose(vergence)
        .map(|s| Diopters(s.diopters))
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::Plane;

    const FOV: f32 = 20.0;

    /// Left half at `left` D, right half at `right` D.
    fn split(w: usize, left: f32, right: f32) -> DepthMap {
        let mut p = Plane::new(w, w, 0.0);
        for y in 0..w {
            for x in 0..w {
                p.data_mut()[y * w + x] = if x < w / 2 { left } else { right };
            }
        }
        DepthMap::from_diopters(p).unwrap()
    }

    fn dir(yaw_deg: f64, pitch_deg: f64) -> [f64; 3] {
        let (y, p) = (yaw_deg.to_radians(), pitch_deg.to_radians());
        [p.cos() * y.sin(), p.sin(), p.cos() * y.cos()]
    }

    #[test]
    fn pixel_mapping_follows_the_scene_camera() {
        // Straight ahead is the image centre; up is towards row 0.
        assert_eq!(pixel_of([0.0, 0.0, 1.0], 256, FOV), Some((0.0, 0.0)));
        let (x, y) = pixel_of(dir(5.0, 5.0), 256, FOV).unwrap();
        let pitch = 2.0 * 10f64.to_radians().tan() / 256.0;
        assert!((x - 5f64.to_radians().tan() / pitch).abs() < 1e-9);
        assert!(y < -60.0, "{y}");
        assert!(pixel_of([0.0, 0.0, -1.0], 256, FOV).is_none());
    }

    #[test]
    fn a_window_across_an_edge_finds_both_surfaces_not_their_mean() {
        let d = split(256, 2.0, 0.5);
        // Just left of the edge: mostly the near surface, some of the far one.
        let wd = window_depth(&d, dir(-0.3, 0.0), FOV, &DepthWindow::default()).unwrap();
        let s = wd.surfaces();
        assert_eq!(s.len(), 2, "{s:?}");
        assert!((s[0].diopters - 2.0).abs() < 1e-4 && s[0].share > 0.5);
        assert!((s[1].diopters - 0.5).abs() < 1e-4);
        // No surface at the mean of the two.
        assert!(s.iter().all(|c| (c.diopters - 1.25).abs() > 0.5));
        // Alone, the window picks the larger surface; vergence near 0.5 D picks the far one.
        assert_eq!(wd.choose(None).unwrap().diopters, s[0].diopters);
        assert!((wd.choose(Some((0.55, 0.1))).unwrap().diopters - 0.5).abs() < 1e-4);
        // Vastly uncertain vergence does not override the window.
        assert!((wd.choose(Some((0.55, 10.0))).unwrap().diopters - 2.0).abs() < 1e-4);
    }

    #[test]
    fn inside_a_surface_and_off_the_image() {
        let d = split(256, 2.0, 0.5);
        let got = fixation_depth(&d, dir(5.0, 2.0), FOV, &DepthWindow::default(), None).unwrap();
        assert_eq!(got, Diopters(0.5));
        assert!(fixation_depth(&d, dir(30.0, 0.0), FOV, &DepthWindow::default(), None).is_none());
        assert!(
            fixation_depth(&d, [f64::NAN, 0.0, 1.0], FOV, &DepthWindow::default(), None).is_none()
        );
    }
}
