//! Spectral layers at a panel's size: the decomposition solved on a grid `s` times coarser
//! than the image, plus linear blending's detail above that grid (`L + up(Y - down(L))`: the
//! solve's change to the coarse linear layers, upsampled bilinearly, added to the fine ones).
//!
//! Why: at 960 x 1080 per eye (48 px per degree) a full-resolution solve costs about 3 s of
//! CPU (`examples/spectral_profile`: the 6-focus composite target stack 1.9 s, its 30 forward
//! FFTs of the 1000 x 1125 grid 0.3 s, the clamp and 3 ADMM steps 0.9 s); its FFTs alone,
//! whatever the targets, are over a second. The planes differ in what the eye sees only
//! through their blur, and blur carries no detail finer than itself: detail finer than the
//! coarse grid is seen sharply only by a focus near its own plane, where linear blending is
//! exact. The cost falls as s squared (the light field's and the FFTs' work per pixel do not
//! depend on it, gather's falls faster). What it costs in accuracy is measured against
//! full-resolution spectral and the thin-lens truth (crates/render/README.md,
//! `examples/hybrid_accuracy`). The gaze-contingent hybrid ([`crate::hybrid`]) solves its
//! window the same way.

use crate::common::eye_for;
use crate::error::RenderError;
use crate::multifocal::{linear_blend, Layers};
use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;

/// With `scale` = 0 the grid is coarsened until the widest blur (CoC diameter of a plane at
/// the farthest focal sample) is at most this many of its pixels; below it the image is
/// solved at full resolution. Chosen by measurement at 960 x 1080 (crates/render/README.md):
/// a 1/4 grid there.
pub const AUTO_MIN_BLUR_PX: f32 = 5.0;

/// The largest grid divisor there is: beyond it the grid would not hold the blur itself.
pub const MAX_SCALE: usize = 16;

/// The widest blur of `planes` over `focal_range` (diopters), full-resolution pixels of
/// `eye` (sized to the image already): a plane seen at the farthest focal sample.
pub fn widest_blur_px(eye: &EyeModel, planes: &[Diopters], focal_range: (f32, f32)) -> f32 {
    let (lo, hi) = focal_range;
    planes
        .iter()
        .flat_map(|&p| [eye.coc_px(p, Diopters(lo)), eye.coc_px(p, Diopters(hi))])
        .fold(0.0f32, f32::max)
}

/// The largest s (1 to [`MAX_SCALE`]) with `max_blur_px / s >= min_blur_px`, 1 at least.
pub fn auto_scale(max_blur_px: f32, min_blur_px: f32) -> usize {
    ((max_blur_px / min_blur_px).floor() as usize).clamp(1, MAX_SCALE)
}

/// The grid divisor [`crate::spectral::spectral_blend`] solves a `width`-pixel image at:
/// `scale` if set, else [`auto_scale`] of the widest blur over `focal_range` at
/// [`AUTO_MIN_BLUR_PX`].
pub fn scale_for(
    eye: &EyeModel,
    planes: &[Diopters],
    width: usize,
    scale: usize,
    focal_range: (f32, f32),
) -> Result<usize, RenderError> {
    if scale > 0 {
        return Ok(scale);
    }
    let eye = eye_for(eye, width)?;
    Ok(auto_scale(
        widest_blur_px(&eye, planes, focal_range),
        AUTO_MIN_BLUR_PX,
    ))
}

/// The same eye seeing `width` pixels at `pitch` (tangent units per pixel): a window of a
/// larger image, or a coarser grid over the same field.
pub fn eye_with_pitch(eye: &EyeModel, pitch: f32, width: usize) -> Result<EyeModel, RenderError> {
    let fov = 2.0 * (0.5 * pitch * width as f32).atan().to_degrees();
    eye_for(
        &EyeModel {
            fov_horizontal_deg: fov,
            ..*eye
        },
        width,
    )
}

/// Box average over s x s blocks: `ceil(w / s)` x `ceil(h / s)`, a block cut by the right or
/// bottom edge the mean of the pixels it has.
pub(crate) fn box_down(p: &Plane, s: usize) -> Result<Plane, RenderError> {
    let (fw, fh) = (p.width(), p.height());
    let (w, h) = (fw.div_ceil(s), fh.div_ceil(s));
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            let rows = (y * s..((y + 1) * s).min(fh)).len();
            for sy in y * s..(y * s + rows) {
                for (o, block) in row.iter_mut().zip(p.row(sy).chunks(s)) {
                    *o += block.iter().sum::<f32>();
                }
            }
            for (x, o) in row.iter_mut().enumerate() {
                let cols = (x * s..((x + 1) * s).min(fw)).len();
                *o *= 1.0 / (rows * cols) as f32;
            }
        });
    Ok(Plane::from_vec(w, h, out)?)
}

/// Per fine coordinate of `n` upsampled by `s` from `cn` coarse ones: the two coarse indices
/// and the weight of the second (pixel centres aligned, edges clamped).
pub(crate) fn up_taps(n: usize, cn: usize, s: usize) -> Vec<(usize, usize, f32)> {
    (0..n)
        .map(|x| {
            let u = ((x as f32 + 0.5) / s as f32 - 0.5).max(0.0);
            let i = (u.floor() as usize).min(cn.max(1) - 1);
            (i, (i + 1).min(cn.max(1) - 1), u - i as f32)
        })
        .collect()
}

/// `input` at 1/s resolution (colour and depth box-averaged).
pub fn down_rgbd(input: &Rgbd, s: usize) -> Result<Rgbd, RenderError> {
    let [r, g, b] = &input.color.channels;
    let color = RgbImage::from_planes(box_down(r, s)?, box_down(g, s)?, box_down(b, s)?)?;
    let depth = DepthMap::from_diopters(box_down(input.depth.plane(), s)?)?;
    Ok(Rgbd::new(color, depth)?)
}

/// The layers of `input` solved on a 1/s grid by `solve` (the coarse RGB-D and its eye; the
/// CPU's [`crate::spectral::spectral_blend`] or a backend's, with its report `R`), plus
/// linear blending's detail above that grid, clamped to the display's [0, 1].
pub fn coarse_blend_with<R>(
    input: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
    s: usize,
    solve: impl FnOnce(&Rgbd, &EyeModel) -> Result<(Layers, R), RenderError>,
) -> Result<(Layers, R), RenderError> {
    crate::common::check_rgbd(input)?;
    let (w, h) = (input.width(), input.height());
    let eye = eye_for(eye, w)?;
    let small = down_rgbd(input, s)?;
    let seye = eye_with_pitch(&eye, eye.pixel_pitch_tan() * s as f32, small.width())?;
    let (solved, report) = solve(&small, &seye)?;
    if solved.images.len() != planes.len()
        || solved.width() != small.width()
        || solved.height() != small.height()
    {
        return Err(crate::error::mismatch(
            "the coarse spectral layers do not match the planes and the coarse grid",
        ));
    }
    let mut layers = linear_blend(input, planes)?;
    let (cw, ch) = (small.width(), small.height());
    let (tx, ty) = (up_taps(w, cw, s), up_taps(h, ch, s));
    let jobs: Vec<(&mut Plane, &Plane)> = layers
        .images
        .iter_mut()
        .zip(&solved.images)
        .flat_map(|(l, y)| l.channels.iter_mut().zip(y.channels.iter()))
        .collect();
    jobs.into_par_iter()
        .try_for_each(|(lin, sol)| -> Result<(), RenderError> {
            // The solve's change to the coarse linear layer, each coarse row upsampled along x
            // once, then each fine row a blend of two of those.
            let mut change = box_down(lin, s)?;
            for (c, &y) in change.data_mut().iter_mut().zip(sol.data()) {
                *c = y - *c;
            }
            let wide: Vec<Vec<f32>> = (0..ch)
                .map(|y| {
                    let r = change.row(y);
                    tx.iter()
                        .map(|&(a, b, u)| r[a] + (r[b] - r[a]) * u)
                        .collect()
                })
                .collect();
            for (row, &(i0, i1, t)) in lin.data_mut().chunks_exact_mut(w).zip(&ty) {
                let (r0, r1) = (&wide[i0], &wide[i1]);
                for ((o, &a), &b) in row.iter_mut().zip(r0).zip(r1) {
                    *o = (*o + a + (b - a) * t).clamp(0.0, 1.0);
                }
            }
            Ok(())
        })?;
    Ok((layers, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::multifocal::DEFAULT_PLANES;

    /// A textured RGB-D at 1.1 D everywhere.
    fn rgbd(w: usize, h: usize) -> Rgbd {
        let plane = |k: usize| {
            let v = (0..w * h).map(|i| 0.1 + 0.8 * ((i * k) % 17) as f32 / 17.0);
            Plane::from_vec(w, h, v.collect()).unwrap()
        };
        let color = RgbImage::from_planes(plane(3), plane(7), plane(11)).unwrap();
        let depth = DepthMap::from_diopters(Plane::new(w, h, 1.1)).unwrap();
        Rgbd::new(color, depth).unwrap()
    }

    fn planes() -> Vec<Diopters> {
        DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect()
    }

    #[test]
    fn box_down_averages_whole_and_cut_blocks() {
        // 5 x 3 by 2: blocks of 4, 2 (right edge), 2 (bottom edge) and 1 pixels.
        let p = Plane::from_vec(5, 3, (0..15).map(|v| v as f32).collect()).unwrap();
        let d = box_down(&p, 2).unwrap();
        assert_eq!((d.width(), d.height()), (3, 2));
        let want = [
            (0.0 + 1.0 + 5.0 + 6.0) / 4.0,
            (2.0 + 3.0 + 7.0 + 8.0) / 4.0,
            (4.0 + 9.0) / 2.0,
            (10.0 + 11.0) / 2.0,
            (12.0 + 13.0) / 2.0,
            14.0,
        ];
        for (g, w) in d.data().iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{:?} vs {want:?}", d.data());
        }
    }

    #[test]
    fn auto_scale_follows_the_blur() {
        assert_eq!(auto_scale(4.9, AUTO_MIN_BLUR_PX), 1);
        assert_eq!(auto_scale(21.8, 5.0), 4);
        assert_eq!(auto_scale(21.8, 8.0), 2);
        assert_eq!(auto_scale(1e6, 5.0), MAX_SCALE);
        assert_eq!(auto_scale(f32::NAN, 5.0), 1);
    }

    #[test]
    fn a_solve_that_returns_linear_blending_gives_linear_blending() {
        // On flat depth the coarse input's linear blending is the box average of the fine
        // one's: the change is zero and linear blending comes back, whatever the image's size
        // against the scale (odd sizes have cut blocks).
        for (w, h, s) in [(64, 48, 2), (61, 47, 4), (10, 9, 3)] {
            let input = rgbd(w, h);
            let eye = EyeModel::default();
            let (layers, _) = coarse_blend_with(&input, &planes(), &eye, s, |small, _| {
                Ok((linear_blend(small, &planes())?, ()))
            })
            .unwrap();
            let lin = linear_blend(&input, &planes()).unwrap();
            assert_eq!(layers.images.len(), lin.images.len());
            for (a, b) in layers.images.iter().zip(&lin.images) {
                assert_eq!((a.width(), a.height()), (w, h));
                for (p, q) in a.channels.iter().zip(&b.channels) {
                    for (u, v) in p.data().iter().zip(q.data()) {
                        assert!((u - v).abs() < 1e-5, "{w}x{h}/{s}: {u} vs {v}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_solve_of_the_wrong_size_is_an_error() {
        let input = rgbd(32, 32);
        let r = coarse_blend_with(&input, &planes(), &EyeModel::default(), 2, |_, _| {
            Ok((linear_blend(&rgbd(8, 8), &planes())?, ()))
        });
        assert!(r.is_err());
    }
}
