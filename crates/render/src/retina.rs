//! What the eye sees focusing at q through a varifocal display, a multifocal layer stack,
//! or a light-field display.

use crate::common::{check_focus, check_plane, eye_for};
use crate::error::{invalid, mismatch, RenderError};
use crate::kernel::{disk_kernel, FftConv};
use crate::multifocal::{Layers, MultifocalRetina};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage};
use rayon::prelude::*;

/// Checks a varifocal display's inputs (both backends); returns the eye at the image's width.
pub(crate) fn check_varifocal_inputs(
    image: &RgbImage,
    display: Diopters,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<EyeModel, RenderError> {
    check_plane(display)?;
    check_focus(focus)?;
    if image.width() == 0 || image.height() == 0 {
        return Err(invalid("image is empty"));
    }
    eye_for(eye, image.width())
}

/// A light field's inputs, checked: the views' size, the eye at that width, and each view's
/// share of the pupil.
pub(crate) struct LightFieldInputs {
    pub w: usize,
    pub h: usize,
    pub eye: EyeModel,
    pub weights: Vec<f32>,
    /// The weights' sum (positive).
    pub total: f32,
}

/// Checks a light-field display's inputs (both backends).
pub(crate) fn check_lightfield_inputs(
    views: &[LfView],
    spacing: f32,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<LightFieldInputs, RenderError> {
    check_focus(focus)?;
    let first = views
        .first()
        .ok_or_else(|| invalid("the light field has no views"))?;
    let (w, h) = (first.image.width(), first.image.height());
    if w == 0
        || h == 0
        || views
            .iter()
            .any(|v| (v.image.width(), v.image.height()) != (w, h))
    {
        return Err(mismatch("light-field views are empty or differ in size"));
    }
    if !(spacing.is_finite() && spacing > 0.0)
        || views
            .iter()
            .any(|v| !v.position.iter().all(|p| p.is_finite()))
    {
        return Err(invalid(format!(
            "view spacing {spacing} m or a view position is invalid"
        )));
    }
    let eye = eye_for(eye, w)?;
    let weights = pupil_weights(views, spacing, 0.5 * eye.pupil_diameter.to_meters().0);
    let total: f32 = weights.iter().sum();
    if total <= 0.0 {
        return Err(invalid("no light-field view lies inside the pupil"));
    }
    Ok(LightFieldInputs {
        w,
        h,
        eye,
        weights,
        total,
    })
}

/// A varifocal display showing `image` at `display` diopters, seen focusing at `focus`:
/// the image convolved with the disk PSF of diameter coc(display, focus).
pub fn retina_varifocal(
    image: &RgbImage,
    display: Diopters,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let eye = check_varifocal_inputs(image, display, focus, eye)?;
    let k = disk_kernel(eye.coc_px(display, focus));
    if k.radius == 0 {
        return Ok(image.clone());
    }
    let conv = FftConv::new(image.width(), image.height(), k.radius);
    let c = &image.channels;
    let (r, g) = conv.convolve_pair(&c[0], Some(&c[1]), &k);
    let (b, _) = conv.convolve_pair(&c[2], None, &k);
    Ok(RgbImage::from_planes(r, g, b)?)
}

/// A multifocal display's retinal images at each focus in `foci`.
pub fn retina_multifocal(
    layers: &Layers,
    foci: &[Diopters],
    eye: &EyeModel,
) -> Result<Vec<RgbImage>, RenderError> {
    let (lo, hi) = foci.iter().fold((f32::INFINITY, 0.0f32), |(lo, hi), q| {
        (lo.min(q.0), hi.max(q.0))
    });
    if foci.is_empty() {
        return Ok(Vec::new());
    }
    let r = MultifocalRetina::new(layers, eye, (Diopters(lo), Diopters(hi)))?;
    foci.iter().map(|&q| r.render(q)).collect()
}

/// One view of a light-field display: a pinhole image seen from `position` (metres in the
/// pupil plane), looking straight ahead.
#[derive(Debug, Clone, PartialEq)]
pub struct LfView {
    pub position: [f32; 2],
    pub image: RgbImage,
}

/// Bilinear sample with edge clamping at pixel position (x, y) (centres at +0.5).
pub(crate) fn bilinear(p: &Plane, x: f32, y: f32) -> f32 {
    Taps::new(p.width(), p.height(), x, y).read(p.data())
}

/// A bilinear read's four taps at pixel position (x, y) (centres at +0.5) of a `w` x `h`
/// image, clamped to its edges: their indices (the top-left tap, its right, below, below
/// right) and the weights along x and y, shared by every plane read there.
pub(crate) struct Taps {
    pub(crate) at: [usize; 4],
    pub(crate) tx: f32,
    pub(crate) ty: f32,
}

impl Taps {
    #[inline]
    pub(crate) fn new(w: usize, h: usize, x: f32, y: f32) -> Taps {
        let (w, h) = (w as isize, h as isize);
        let (fx, fy) = (x - 0.5, y - 0.5);
        let (x0, y0) = (fx.floor(), fy.floor());
        let (xi, yi) = (x0 as isize, y0 as isize);
        let at = |dx: isize, dy: isize| {
            (yi.saturating_add(dy).clamp(0, h - 1) * w + xi.saturating_add(dx).clamp(0, w - 1))
                as usize
        };
        Taps {
            at: [at(0, 0), at(1, 0), at(0, 1), at(1, 1)],
            tx: fx - x0,
            ty: fy - y0,
        }
    }

    /// The read of plane `p` (row-major, the taps' size).
    #[inline]
    pub(crate) fn read(&self, p: &[f32]) -> f32 {
        let (tx, ty) = (self.tx, self.ty);
        let a = p[self.at[0]] * (1.0 - tx) + p[self.at[1]] * tx;
        let b = p[self.at[2]] * (1.0 - tx) + p[self.at[3]] * tx;
        a * (1.0 - ty) + b * ty
    }
}

/// Pupil weight of each view: the area of its cell (the square of side `spacing` around it)
/// inside the pupil disk, by 32 x 32 subsampling.
pub(crate) fn pupil_weights(views: &[LfView], spacing: f32, radius: f32) -> Vec<f32> {
    const N: usize = 32;
    views
        .iter()
        .map(|v| {
            let mut inside = 0;
            for j in 0..N {
                for i in 0..N {
                    let x = v.position[0] + spacing * ((i as f32 + 0.5) / N as f32 - 0.5);
                    let y = v.position[1] + spacing * ((j as f32 + 0.5) / N as f32 - 0.5);
                    if x * x + y * y <= radius * radius {
                        inside += 1;
                    }
                }
            }
            inside as f32 / (N * N) as f32
        })
        .collect()
}

/// A light-field display seen by the eye focusing at `focus`: shift-and-add of the views over
/// the pupil. The view at lens position L is shifted by L q / pitch pixels and weighted by its
/// share of the pupil; `spacing` is the view grid pitch in metres.
pub fn retina_lightfield(
    views: &[LfView],
    spacing: f32,
    focus: Diopters,
    eye: &EyeModel,
) -> Result<RgbImage, RenderError> {
    let LightFieldInputs {
        w,
        h,
        eye,
        weights,
        total,
    } = check_lightfield_inputs(views, spacing, focus, eye)?;
    let pitch = eye.pixel_pitch_tan();
    let mut planes = [0, 1, 2].map(|_| vec![0.0f32; w * h]);
    for (v, &wt) in views.iter().zip(&weights) {
        if wt == 0.0 {
            continue;
        }
        let (sx, sy) = (
            v.position[0] * focus.0 / pitch,
            v.position[1] * focus.0 / pitch,
        );
        for (c, out) in planes.iter_mut().enumerate() {
            let src = &v.image.channels[c];
            out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                for (x, o) in row.iter_mut().enumerate() {
                    *o += wt / total * bilinear(src, x as f32 + 0.5 - sx, y as f32 + 0.5 - sy);
                }
            });
        }
    }
    let [r, g, b] =
        planes.map(|d| Plane::from_vec(w, h, d).unwrap_or_else(|_| Plane::new(w, h, 0.0)));
    Ok(RgbImage::from_planes(r, g, b)?)
}
