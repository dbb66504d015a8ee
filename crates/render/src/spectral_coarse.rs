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
use crate::multifocal::{check_planes, layers_of, linear_weights, rows_of, Layers};
use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;

/// With `scale` = 0 the grid is coarsened as far as the widest blur (CoC diameter of a plane
/// at the farthest focal sample) stays at least this many of its pixels: the image's own grid
/// while that blur is under twice this. Chosen for time at 960 x 1080 (a 1/4 grid there, 1/2
/// at 8 px; what each costs in accuracy is in crates/render/README.md).
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
pub(crate) fn eye_with_pitch(
    eye: &EyeModel,
    pitch: f32,
    width: usize,
) -> Result<EyeModel, RenderError> {
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

/// `input` at 1/s resolution (colour and depth box-averaged, as [`box_down`]) and its linear
/// blending's layers box-averaged (`[plane * 3 + channel]`, each `ceil(w / s)` x
/// `ceil(h / s)`), in one pass over the input: the fine linear layers are never stored.
fn down_with_linear(
    input: &Rgbd,
    planes: &[Diopters],
    s: usize,
) -> Result<(Rgbd, Vec<Vec<f32>>), RenderError> {
    let (fw, fh) = (input.width(), input.height());
    let (w, h) = (fw.div_ceil(s), fh.div_ceil(s));
    let k = 3 * planes.len();
    let depth = input.depth.data();
    let color: Vec<&[f32]> = input.color.channels.iter().map(|p| p.data()).collect();
    // Per coarse row: colour (3), depth (1), then the linear layers (k), `w` values each.
    let rows: Vec<Vec<f32>> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut acc = vec![0.0f32; (4 + k) * w];
            let rows = (y * s..((y + 1) * s).min(fh)).len();
            for sy in y * s..y * s + rows {
                for x in 0..fw {
                    let (i, cx) = (sy * fw + x, x / s);
                    let (a, b, t) = linear_weights(planes, depth[i]);
                    for (c, col) in color.iter().enumerate() {
                        let v = col[i];
                        acc[c * w + cx] += v;
                        acc[(4 + a * 3 + c) * w + cx] += v * (1.0 - t);
                        acc[(4 + b * 3 + c) * w + cx] += v * t;
                    }
                    acc[3 * w + cx] += depth[i];
                }
            }
            for x in 0..w {
                let cols = (x * s..((x + 1) * s).min(fw)).len();
                let inv = 1.0 / (rows * cols) as f32;
                for j in 0..4 + k {
                    acc[j * w + x] *= inv;
                }
            }
            acc
        })
        .collect();
    let plane = |j: usize| -> Vec<f32> {
        rows.iter()
            .flat_map(|r| r[j * w..(j + 1) * w].iter().copied())
            .collect()
    };
    let p = |j: usize| Plane::from_vec(w, h, plane(j));
    let small = Rgbd::new(
        RgbImage::from_planes(p(0)?, p(1)?, p(2)?)?,
        DepthMap::from_diopters(p(3)?)?,
    )?;
    Ok((small, (4..4 + k).map(plane).collect()))
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
    check_planes(planes)?;
    let (w, h) = (input.width(), input.height());
    let eye = eye_for(eye, w)?;
    let (small, down_linear) = down_with_linear(input, planes, s)?;
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
    // The solve's change to the coarse linear layers, [plane * 3 + channel].
    let change: Vec<Vec<f32>> = solved
        .images
        .iter()
        .flat_map(|img| img.channels.iter())
        .zip(down_linear)
        .map(|(y, mut d)| {
            d.iter_mut().zip(y.data()).for_each(|(d, &y)| *d = y - *d);
            d
        })
        .collect();
    // Per fine row: the change upsampled (the two coarse rows blended, then along x) plus
    // the pixel's linear blending, clamped.
    let (cw, k) = (small.width(), change.len());
    let (tx, ty) = (up_taps(w, cw, s), up_taps(h, small.height(), s));
    let depth = input.depth.data();
    let mut data: Vec<Vec<f32>> = (0..k).map(|_| vec![0.0f32; w * h]).collect();
    rows_of(&mut data, w)
        .par_iter_mut()
        .enumerate()
        .for_each(|(y, out)| {
            let (i0, i1, t) = ty[y];
            let mut mix = vec![0.0f32; cw];
            for (o, ch) in out.iter_mut().zip(&change) {
                let (r0, r1) = (&ch[i0 * cw..][..cw], &ch[i1 * cw..][..cw]);
                for ((m, &a), &b) in mix.iter_mut().zip(r0).zip(r1) {
                    *m = a + (b - a) * t;
                }
                for (o, &(a, b, u)) in o.iter_mut().zip(&tx) {
                    *o = mix[a] + (mix[b] - mix[a]) * u;
                }
            }
            for (x, &d) in depth[y * w..(y + 1) * w].iter().enumerate() {
                let (a, b, t) = linear_weights(planes, d);
                for (c, col) in input.color.channels.iter().enumerate() {
                    let v = col.data()[y * w + x];
                    out[a * 3 + c][x] += v * (1.0 - t);
                    out[b * 3 + c][x] += v * t;
                }
            }
            for o in out.iter_mut() {
                o.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
            }
        });
    Ok((layers_of(planes, w, h, data)?, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::multifocal::{linear_blend, DEFAULT_PLANES};

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
