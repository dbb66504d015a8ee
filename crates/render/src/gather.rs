//! Single-image gather blur driven by the circle of confusion: the common real-time baseline.
//!
//! Each output pixel averages the neighbours whose CoC disk covers it ("scatter as gather"),
//! each weighted by 1 / (its disk's area) so a sample spreads its energy over its disk. A
//! neighbour behind the centre pixel may spread no further than the centre's own CoC, which
//! stops sharp foreground from being washed over by blurred background. It still bleeds
//! across depth edges and cannot show hidden background: the failure the light-field method
//! addresses.

use crate::common::{check_focus, check_rgbd, eye_for, max_coc};
use crate::error::RenderError;
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use rayon::prelude::*;

/// Gather-blur `input` as seen by `eye` focused at `focus`.
pub fn gather(input: &Rgbd, focus: Diopters, eye: &EyeModel) -> Result<RgbImage, RenderError> {
    check_rgbd(input)?;
    check_focus(focus)?;
    let eye = eye_for(eye, input.width())?;
    let (w, h) = (input.width(), input.height());
    let depth = input.depth.data();
    let radius: Vec<f32> = depth
        .par_iter()
        .map(|&d| 0.5 * eye.coc_px(Diopters(d), focus))
        .collect();
    let reach = (0.5 * max_coc(input, &eye, focus) + 0.5).ceil().min(256.0) as isize;
    let ch = input.color.channels.each_ref().map(|p| p.data());
    // Offsets within reach, with their distances, computed once instead of per tap.
    let offsets: Vec<(isize, isize, f32)> = (-reach..=reach)
        .flat_map(|dy| {
            (-reach..=reach).map(move |dx| (dx, dy, ((dx * dx + dy * dy) as f32).sqrt()))
        })
        .filter(|o| o.2 <= reach as f32 + 0.5)
        .collect();
    // Nearest first, so a pixel stops once no neighbour's disk can reach it: the largest
    // radius within reach (a separable max filter) bounds every tap.
    let mut offsets = offsets;
    offsets.sort_by(|a, b| a.2.total_cmp(&b.2));
    let local_max = max_filter(&radius, w, h, reach as usize);
    let mut out = vec![[0.0f32; 3]; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let i = y * w + x;
            let (dc, rc) = (depth[i], radius[i]);
            let mut acc = [0.0f32; 3];
            let mut wsum = 0.0f32;
            let interior = x as isize >= reach
                && y as isize >= reach
                && (x as isize) < w as isize - reach
                && (y as isize) < h as isize - reach;
            let limit = local_max[i] + 0.5;
            for &(dx, dy, dist) in &offsets {
                if dist > limit {
                    break;
                }
                let (sx, sy) = (x as isize + dx, y as isize + dy);
                if !interior && (sx < 0 || sy < 0 || sx >= w as isize || sy >= h as isize) {
                    continue;
                }
                let j = sy as usize * w + sx as usize;
                let mut r = radius[j];
                if depth[j] < dc {
                    r = r.min(rc);
                }
                // Antialiased disk edge: full weight inside, linear over the last pixel.
                let cover = (r + 0.5 - dist).clamp(0.0, 1.0);
                if cover > 0.0 {
                    let rr = r.max(0.5);
                    let wgt = cover / (rr * rr);
                    for c in 0..3 {
                        acc[c] += wgt * ch[c][j];
                    }
                    wsum += wgt;
                }
            }
            // The centre always covers itself, so wsum > 0.
            *o = acc.map(|v| v / wsum);
        }
    });
    Ok(RgbImage::from_interleaved(w, h, out.as_flattened())?)
}

/// Maximum over the (2r+1) x (2r+1) window around each pixel, rows then columns.
fn max_filter(v: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let src = &v[y * w..(y + 1) * w];
        for (x, o) in row.iter_mut().enumerate() {
            *o = src[x.saturating_sub(r)..(x + r + 1).min(w)]
                .iter()
                .copied()
                .fold(0.0, f32::max);
        }
    });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
            for (o, &t) in row.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *o = o.max(t);
            }
        }
    });
    out
}

/// [`gather`] where depth is smooth: each pixel in `want` the mean of the colour over its own
/// CoC disk, with gather's antialiased edge. Where every neighbour within reach shares the
/// pixel's blur this is what gather computes, in O(radius) per pixel (per-row prefix sums)
/// instead of O(radius^2); across a depth step it is wrong (no neighbour's disk spreads over
/// the pixel), so C1R uses it only where its error map finds no blurred step within reach.
/// Pixels outside `want` are black.
pub fn gather_smooth(
    input: &Rgbd,
    focus: Diopters,
    eye: &EyeModel,
    want: &[bool],
) -> Result<RgbImage, RenderError> {
    check_rgbd(input)?;
    check_focus(focus)?;
    let eye = eye_for(eye, input.width())?;
    let (w, h) = (input.width(), input.height());
    if want.len() != w * h {
        return Err(crate::error::invalid(format!(
            "the pixel mask has {} entries for a {w}x{h} image",
            want.len()
        )));
    }
    let ch = input.color.channels.each_ref().map(|p| p.data());
    // CoC radius per diopter of defocus, once (coc_px evaluates a tangent per call).
    let half_px_per_d = 0.5 * eye.coc_px(Diopters(1.0), Diopters(0.0));
    let radius: Vec<f32> = input
        .depth
        .data()
        .par_iter()
        .map(|&d| half_px_per_d * (d - focus.0).abs())
        .collect();
    // Per row, w + 1 running sums: the sum over [a, b) is p[b] - p[a].
    let mut prefix = vec![[0.0f32; 3]; h * (w + 1)];
    prefix
        .par_chunks_mut(w + 1)
        .enumerate()
        .for_each(|(y, row)| {
            for x in 0..w {
                row[x + 1] = [0, 1, 2].map(|c| row[x][c] + ch[c][y * w + x]);
            }
        });
    let mut out = vec![[0.0f32; 3]; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let r_row = &radius[y * w..(y + 1) * w];
        let want_row = &want[y * w..(y + 1) * w];
        for (x, o) in row.iter_mut().enumerate() {
            if !want_row[x] {
                continue;
            }
            let outer = r_row[x] + 0.5;
            let (mut a, mut ws) = ([0.0f32; 3], 0.0f32);
            // Rows y - dy and y + dy share their span and ramp weights (computed once).
            for dy in 0..=outer.floor() as usize {
                let rows = [y.checked_sub(dy), Some(y + dy).filter(|&v| dy > 0 && v < h)];
                if rows == [None, None] {
                    continue;
                }
                let dyf = dy as f32;
                // Gather's weight: clamp(r + 0.5 - distance, 0, 1). Full weight out to
                // distance outer - 1 (a prefix-sum span), the ramp beyond pixel by pixel.
                let inner = (outer - 1.0).max(0.0).powi(2) - dyf * dyf;
                let mut k = 0;
                if outer >= 1.0 && inner >= 0.0 {
                    let f = inner.sqrt().floor() as usize;
                    let (lo, hi) = (x.saturating_sub(f), (x + f + 1).min(w));
                    for sy in rows.into_iter().flatten() {
                        let pre = &prefix[sy * (w + 1)..(sy + 1) * (w + 1)];
                        for c in 0..3 {
                            a[c] += pre[hi][c] - pre[lo][c];
                        }
                        ws += (hi - lo) as f32;
                    }
                    k = f + 1;
                }
                loop {
                    let wt = (outer - ((k * k) as f32 + dyf * dyf).sqrt()).min(1.0);
                    if wt <= 0.0 {
                        break;
                    }
                    let pair = if k == 0 {
                        [Some(x), None]
                    } else {
                        [x.checked_sub(k), Some(x + k).filter(|&v| v < w)]
                    };
                    for sy in rows.into_iter().flatten() {
                        for sx in pair.into_iter().flatten() {
                            for c in 0..3 {
                                a[c] += wt * ch[c][sy * w + sx];
                            }
                            ws += wt;
                        }
                    }
                    k += 1;
                }
            }
            // The centre pixel weighs at least 1/2 (outer >= 1/2 at distance 0).
            *o = a.map(|v| v / ws);
        }
    });
    Ok(RgbImage::from_interleaved(w, h, out.as_flattened())?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::{DepthMap, Plane};

    fn noise_rgbd(w: usize, h: usize, depth: f32) -> Rgbd {
        // A fixed hash per pixel and channel: texture at every scale.
        let v = |i: usize, c: usize| {
            let x = (i * 3 + c) as u32;
            (x.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32
        };
        let plane = |c: usize| Plane::from_vec(w, h, (0..w * h).map(|i| v(i, c)).collect());
        let color =
            RgbImage::from_planes(plane(0).unwrap(), plane(1).unwrap(), plane(2).unwrap()).unwrap();
        Rgbd::new(
            color,
            DepthMap::from_diopters(Plane::new(w, h, depth)).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn gather_smooth_equals_gather_where_depth_is_constant() {
        let (w, h) = (48, 40);
        // A narrow field of view: blur disks of up to 20 px on a small image.
        let eye = EyeModel {
            fov_horizontal_deg: 1.0,
            ..EyeModel::default()
        }
        .with_width(w as u32);
        let rgbd = noise_rgbd(w, h, 1.0);
        // Sharp, sub-pixel, a few pixels, and a disk reaching past the image's borders.
        let mut widest: f32 = 0.0;
        for q in [1.0f32, 1.1, 1.6, 3.5] {
            let r = 0.5 * eye_for(&eye, w).unwrap().coc_px(Diopters(1.0), Diopters(q));
            widest = widest.max(r);
            let g = gather(&rgbd, Diopters(q), &eye).unwrap();
            let s = gather_smooth(&rgbd, Diopters(q), &eye, &vec![true; w * h]).unwrap();
            for c in 0..3 {
                for (i, (a, b)) in g.channels[c]
                    .data()
                    .iter()
                    .zip(s.channels[c].data())
                    .enumerate()
                {
                    assert!(
                        (a - b).abs() < 1e-5,
                        "focus {q} (radius {r:.1} px), pixel {i}: {a} vs {b}"
                    );
                }
            }
        }
        assert!(widest > 12.0, "the widest disk is {widest} px");
    }

    #[test]
    fn gather_smooth_fills_only_the_pixels_asked_for() {
        let (w, h) = (20, 12);
        let eye = EyeModel::default().with_width(w as u32);
        let rgbd = noise_rgbd(w, h, 2.0);
        let want: Vec<bool> = (0..w * h).map(|i| i % 3 == 0).collect();
        let all = gather_smooth(&rgbd, Diopters(0.5), &eye, &vec![true; w * h]).unwrap();
        let some = gather_smooth(&rgbd, Diopters(0.5), &eye, &want).unwrap();
        for c in 0..3 {
            for (i, &wanted) in want.iter().enumerate() {
                let want_v = if wanted {
                    all.channels[c].data()[i]
                } else {
                    0.0
                };
                assert_eq!(some.channels[c].data()[i], want_v, "pixel {i}");
            }
        }
        let e = gather_smooth(&rgbd, Diopters(0.5), &eye, &want[1..]).unwrap_err();
        assert!(e.to_string().contains("239 entries for a 20x12"), "{e}");
    }
}
