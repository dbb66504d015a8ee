//! Foveated view synthesis (FV, Thumuluri & Sharma 2020): the view grid, the foveated input
//! views (the renderer's log-polar masks and inverse-distance interpolation,
//! [`dioptra_render::foveate`]) and the network's input built from them.

use crate::arch::{Task, DEPTH_NORM};
use crate::cpu::{Act, CpuNet};
use crate::error::{input, NetError};
use crate::tasks::rgb_at;
use dioptra_core::{Plane, RgbImage, Rgbd};
use dioptra_render::foveate::{
    interpolate, interpolate_across_views, log_polar_mask, LogPolar, SampledView,
};

/// Lens-plane positions (metres) of a `grid` x `grid` view grid spanning `span` metres in x
/// and y, centred on the axis; row-major (row = y).
pub fn grid_positions(grid: usize, span: f32) -> Vec<[f32; 2]> {
    let step = if grid > 1 {
        span / (grid - 1) as f32
    } else {
        0.0
    };
    let m = (grid as f32 - 1.0) * 0.5;
    (0..grid * grid)
        .map(|i| {
            let (r, c) = ((i / grid) as f32, (i % grid) as f32);
            [(c - m) * step, (r - m) * step]
        })
        .collect()
}

/// The log-polar mask parameters of input view `k` for gaze `centre` and log-buffer scale
/// `scale`: each view gets its own offsets r' and theta' (eq. 5-6), so the views sample
/// different pixels at the same density.
pub fn view_mask(centre: [f32; 2], width: usize, scale: f32, k: usize) -> LogPolar {
    // theta' steps by a golden-ratio fraction of one angular step (2 pi / Theta, Theta = W/S).
    let angular_step = std::f32::consts::TAU * scale / width.max(1) as f32;
    LogPolar {
        centre,
        scale,
        kernel: 1.0,
        r_offset: 1.0 + 0.07 * k as f32,
        theta_offset: angular_step * (0.618_034 * k as f32).fract(),
    }
}

/// How a foveated light field fills the rays its views did not sample.
#[derive(Debug, Clone, Copy)]
pub enum Fill<'a> {
    /// Each view from its own samples (eq. 9), as the seed does.
    WithinViews,
    /// Every view's samples reprojected into each view by their depth (diopters, one plane
    /// per view), then eq. 9 for what none reaches
    /// ([`dioptra_render::foveate::interpolate_across_views`]).
    AcrossViews {
        depths: &'a [Plane],
        positions: &'a [[f32; 2]],
        eye: &'a dioptra_core::EyeModel,
    },
}

/// The light field `lf` foveated as FV samples its views: each view keeps its own log-polar
/// samples around `centre` (log-buffer scale `scale`, the view's offsets from [`view_mask`])
/// and the rest is filled as `fill` says. The views, and the fraction of the rays kept over
/// all of them.
pub fn foveate_light_field(
    lf: &[RgbImage],
    centre: [f32; 2],
    scale: f32,
    fill: Fill,
) -> Result<(Vec<RgbImage>, f64), NetError> {
    let Some(first) = lf.first() else {
        return Err(input("no views to foveate"));
    };
    let (w, h) = (first.width(), first.height());
    let masks = (0..lf.len())
        .map(|k| Ok(log_polar_mask(w, h, &view_mask(centre, w, scale, k))?))
        .collect::<Result<Vec<_>, NetError>>()?;
    let kept = masks.iter().map(|m| m.1).sum::<f64>() / lf.len() as f64;
    let views = match fill {
        Fill::WithinViews => lf
            .iter()
            .zip(&masks)
            .map(|(view, (mask, _))| Ok(interpolate(view, mask)?))
            .collect::<Result<Vec<_>, NetError>>()?,
        Fill::AcrossViews {
            depths,
            positions,
            eye,
        } => {
            if depths.len() != lf.len() || positions.len() != lf.len() {
                return Err(input(format!(
                    "{} views with {} depths and {} positions: expected one each",
                    lf.len(),
                    depths.len(),
                    positions.len()
                )));
            }
            let sampled: Vec<SampledView> = lf
                .iter()
                .zip(depths)
                .zip(positions)
                .zip(&masks)
                .map(|(((image, depth), &position), (mask, _))| SampledView {
                    position,
                    image,
                    depth,
                    mask,
                })
                .collect();
            interpolate_across_views(&sampled, eye)?
        }
    };
    Ok((views, kept))
}

/// Per foveal region around `centre` (fovea, periphery 1 and 2, by name), the PSNR of `views`
/// against `reference`, of the mean squared error over the views (infinite where identical);
/// a region with no pixel (a gaze far off-centre) is left out.
pub fn region_psnr(
    views: &[RgbImage],
    reference: &[RgbImage],
    centre: [f32; 2],
) -> Result<Vec<(&'static str, f64)>, NetError> {
    use dioptra_render::metrics::{psnr, FovealRegion};
    let (Some(first), true) = (views.first(), views.len() == reference.len()) else {
        return Err(input(format!(
            "{} views against {} references: expected as many, at least one",
            views.len(),
            reference.len()
        )));
    };
    let (w, h) = (first.width(), first.height());
    let mut out = Vec::new();
    for region in FovealRegion::ALL {
        let mask = region.mask(w, h, centre);
        if !mask.data().iter().any(|&v| v > 0.5) {
            continue;
        }
        let mut mse = 0.0;
        for (v, r) in views.iter().zip(reference) {
            // Back to the mean squared error (peak 1), so identical views average in.
            mse += 10f64.powf(-psnr(v, r, Some(&mask))? / 10.0);
        }
        out.push((region.name(), -10.0 * (mse / views.len() as f64).log10()));
    }
    Ok(out)
}

/// One foveated input view: its sampling mask (1 = sampled), the depth at the sampled pixels
/// (diopters, 0 elsewhere, as in the paper) and the interpolated colour.
#[derive(Debug, Clone)]
pub struct FoveatedView {
    pub mask: Plane,
    pub depth: Plane,
    pub color: RgbImage,
    /// Fraction of the view's pixels sampled.
    pub fraction: f64,
}

/// Foveates `view` with `mask` (the log-polar parameters), or keeps every pixel for `None`
/// (the paper's S = 0).
pub fn foveate_view(view: &Rgbd, mask: Option<&LogPolar>) -> Result<FoveatedView, NetError> {
    let (w, h) = (view.width(), view.height());
    let Some(p) = mask else {
        return Ok(FoveatedView {
            mask: Plane::new(w, h, 1.0),
            depth: view.depth.plane().clone(),
            color: view.color.clone(),
            fraction: 1.0,
        });
    };
    let (m, fraction) = log_polar_mask(w, h, p)?;
    let color = interpolate(&view.color, &m)?;
    let d: Vec<f32> = view
        .depth
        .data()
        .iter()
        .zip(m.data())
        .map(|(&d, &s)| if s > 0.5 { d } else { 0.0 })
        .collect();
    Ok(FoveatedView {
        depth: Plane::from_vec(w, h, d)?,
        mask: m,
        color,
        fraction,
    })
}

/// Pushes one view's 5 input values at pixel `i`: mask, sampled depth / 4, R, G, B.
pub fn push_view_pixel(v: &FoveatedView, i: usize, out: &mut Vec<f32>) {
    out.extend_from_slice(&[
        v.mask.data()[i],
        v.depth.data()[i] / DEPTH_NORM,
        v.color.channels[0].data()[i],
        v.color.channels[1].data()[i],
        v.color.channels[2].data()[i],
    ]);
}

/// The FV network's input (HWC, 5 channels per view, views in order).
pub fn fv_input(views: &[FoveatedView]) -> Result<Act, NetError> {
    let first = views.first().ok_or_else(|| input("no input views"))?;
    let (w, h) = (first.mask.width(), first.mask.height());
    if views
        .iter()
        .any(|v| (v.mask.width(), v.mask.height()) != (w, h))
    {
        return Err(input("input views differ in size"));
    }
    let mut data = Vec::with_capacity(w * h * 5 * views.len());
    for i in 0..w * h {
        for v in views {
            push_view_pixel(v, i, &mut data);
        }
    }
    Act::new(h, w, 5 * views.len(), data)
}

impl CpuNet {
    /// FV: every view of the grid (row-major) from the foveated input views (in
    /// [`Task::input_views`] order).
    pub fn synthesize_light_field(
        &self,
        views: &[FoveatedView],
    ) -> Result<Vec<RgbImage>, NetError> {
        self.arch().expect_task("fv")?;
        let Task::Fv { views: n, grid } = self.arch().task else {
            return Err(input("not an FV network"));
        };
        if views.len() != n {
            return Err(input(format!(
                "the FV network takes {n} input views, got {}",
                views.len()
            )));
        }
        let y = self.forward(&fv_input(views)?)?;
        (0..grid * grid).map(|k| rgb_at(&y, k)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Arch, Weights};
    use dioptra_core::DepthMap;

    fn view(w: usize, h: usize) -> Rgbd {
        let ramp: Vec<f32> = (0..w * h * 3)
            .map(|i| ((i / 3) % w) as f32 / w as f32)
            .collect();
        let d = Plane::from_vec(
            w,
            h,
            (0..w * h).map(|i| 1.0 + (i / w) as f32 * 0.01).collect(),
        );
        Rgbd::new(
            RgbImage::from_interleaved(w, h, &ramp).unwrap(),
            DepthMap::from_diopters(d.unwrap()).unwrap(),
        )
        .unwrap()
    }

    #[test]
    fn grid_is_centred_and_row_major() {
        let p = grid_positions(3, 0.004);
        assert_eq!(p[0], [-0.002, -0.002]);
        assert_eq!(p[4], [0.0, 0.0]);
        assert_eq!(p[5], [0.002, 0.0]);
    }

    #[test]
    fn foveated_views_keep_samples_and_zero_the_rest_of_the_depth() {
        let v = view(64, 48);
        let full = foveate_view(&v, None).unwrap();
        assert_eq!(full.fraction, 1.0);
        let p = view_mask([32.0, 24.0], 64, 2.0, 1);
        let f = foveate_view(&v, Some(&p)).unwrap();
        assert!(f.fraction > 0.01 && f.fraction < 0.5, "{}", f.fraction);
        for i in 0..64 * 48 {
            if f.mask.data()[i] > 0.5 {
                assert_eq!(f.depth.data()[i], v.depth.data()[i]);
            } else {
                assert_eq!(f.depth.data()[i], 0.0);
            }
        }
        // Views differ in which pixels they sample.
        let g = foveate_view(&v, Some(&view_mask([32.0, 24.0], 64, 2.0, 2))).unwrap();
        assert_ne!(f.mask, g.mask);
        let x = fv_input(&[f.clone(), g]).unwrap();
        assert_eq!((x.h, x.w, x.c), (48, 64, 10));
        let i = 100;
        assert_eq!(x.data[i * 10 + 1], f.depth.data()[i] / DEPTH_NORM);
        assert_eq!(x.data[i * 10 + 2], f.color.channels[0].data()[i]);
    }

    #[test]
    fn synthesis_returns_the_grid_and_checks_the_view_count() {
        let mut a = Arch::preset("fv").unwrap();
        (a.layers, a.channels, a.unet_channels) = (3, 4, 2);
        let net = CpuNet::new(Weights::random(&a, 0).unwrap()).unwrap();
        let f = foveate_view(&view(20, 12), None).unwrap();
        let out = net.synthesize_light_field(&vec![f.clone(); 5]).unwrap();
        assert_eq!(out.len(), 9);
        assert_eq!((out[8].width(), out[8].height()), (20, 12));
        assert!(net.synthesize_light_field(&[f]).is_err());
    }
}
