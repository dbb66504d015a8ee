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
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
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
    let planes: [Plane; 3] = [0, 1, 2].map(|c| {
        Plane::from_vec(w, h, out.iter().map(|p| p[c]).collect())
            .unwrap_or_else(|_| Plane::new(w, h, 0.0))
    });
    let [r, g, b] = planes;
    Ok(RgbImage::from_planes(r, g, b)?)
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
