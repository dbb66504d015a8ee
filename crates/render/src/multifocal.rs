//! Multifocal decomposition: linear blending (Akeley et al. 2004) and optimized blending
//! (Narain et al. 2015; DeepFocus eq. 2-3).
//!
//! The eye focusing at q_j sees z_j = sum_i k_ij * y_i, with k_ij a disk of diameter
//! A |q_j - p_i| in angle (the eye model's CoC of plane p_i). Optimized blending minimises
//! sum_j ||z_j - t_j||^2 over layers 0 <= y_i <= 1 for target focal-stack slices t_j.
//!
//! The problem is posed on the FFT engine's padded grid (targets extended by edge replication,
//! layers free in the margin), where every k_ij is diagonal in frequency: the normal matrix
//! M(f) = sum_j k_ij(f) k_i'j(f) is a 4 x 4 per frequency, precomputed once, and each
//! iteration costs one forward and one inverse FFT per layer and channel pair. The solver is
//! FISTA (accelerated projected gradient) with step 1 / L, L a Gershgorin bound on the
//! largest eigenvalue of M over all frequencies.

use crate::common::{check_focus, check_plane, eye_for};
use crate::error::{invalid, mismatch, RenderError};
use crate::kernel::{disk_kernel, FftConv, Spectrum};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;

/// DeepFocus's display planes, diopters.
pub const DEFAULT_PLANES: [f32; 4] = [0.2, 0.8, 1.4, 2.0];

/// `n` evenly spaced values from `lo` to `hi` inclusive (e.g. 22 focal samples 0.1..=2.2 D).
pub fn linspace(lo: f32, hi: f32, n: usize) -> Vec<Diopters> {
    match n {
        0 => vec![],
        1 => vec![Diopters(lo)],
        _ => (0..n)
            .map(|i| Diopters(lo + (hi - lo) * i as f32 / (n - 1) as f32))
            .collect(),
    }
}

/// DeepFocus's multifocal focal samples: 22 over 0.1 to 2.2 D.
pub fn default_focal_samples() -> Vec<Diopters> {
    linspace(0.1, 2.2, 22)
}

/// A multifocal layer stack: one linear-light image per display plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Layers {
    pub planes: Vec<Diopters>,
    pub images: Vec<RgbImage>,
}

impl Layers {
    pub fn width(&self) -> usize {
        self.images.first().map_or(0, |i| i.width())
    }
    pub fn height(&self) -> usize {
        self.images.first().map_or(0, |i| i.height())
    }
    pub(crate) fn check(&self) -> Result<(), RenderError> {
        check_planes(&self.planes)?;
        if self.images.len() != self.planes.len() {
            return Err(mismatch(format!(
                "{} planes but {} images",
                self.planes.len(),
                self.images.len()
            )));
        }
        let (w, h) = (self.width(), self.height());
        if w == 0
            || h == 0
            || self
                .images
                .iter()
                .any(|i| (i.width(), i.height()) != (w, h))
        {
            return Err(mismatch("layer images are empty or differ in size"));
        }
        Ok(())
    }
}

/// Display planes a decomposition takes at most (the GPU kernels hold one value per plane in
/// registers; the shaders get it from here).
pub(crate) const MAX_PLANES: usize = 16;

pub(crate) fn check_planes(planes: &[Diopters]) -> Result<(), RenderError> {
    if planes.is_empty() || planes.len() > MAX_PLANES {
        return Err(invalid(format!(
            "{} display planes: expected 1 to {MAX_PLANES}",
            planes.len()
        )));
    }
    for &p in planes {
        check_plane(p)?;
    }
    if planes.windows(2).any(|w| w[0].0 >= w[1].0) {
        return Err(invalid(
            "display planes must be strictly increasing in diopters",
        ));
    }
    Ok(())
}

/// Linear blending's split of depth `d` (diopters): the two planes bracketing it and the
/// weight of the second; outside the planes, all on the nearest.
#[inline]
pub(crate) fn linear_weights(planes: &[Diopters], d: f32) -> (usize, usize, f32) {
    let np = planes.len();
    let k = planes.partition_point(|p| p.0 <= d);
    if k == 0 {
        (0, 0, 0.0)
    } else if k == np {
        (k - 1, k - 1, 0.0)
    } else {
        let (p0, p1) = (planes[k - 1].0, planes[k].0);
        (k - 1, k, (d - p0) / (p1 - p0))
    }
}

/// Linear blending: each pixel's colour is split between the two planes bracketing its depth,
/// in proportion to dioptric distance; depths outside the planes go to the nearest plane.
pub fn linear_blend(input: &Rgbd, planes: &[Diopters]) -> Result<Layers, RenderError> {
    check_planes(planes)?;
    let (w, h) = (input.width(), input.height());
    let np = planes.len();
    let depth = input.depth.data();
    // Per plane and channel, filled row by row in parallel.
    let mut data: Vec<Vec<f32>> = (0..np * 3).map(|_| vec![0.0f32; w * h]).collect();
    rows_of(&mut data, w)
        .par_iter_mut()
        .enumerate()
        .for_each(|(y, out)| {
            for (x, &d) in depth[y * w..(y + 1) * w].iter().enumerate() {
                let i = y * w + x;
                let (a, b, t) = linear_weights(planes, d);
                for c in 0..3 {
                    let v = input.color.channels[c].data()[i];
                    out[a * 3 + c][x] += v * (1.0 - t);
                    out[b * 3 + c][x] += v * t;
                }
            }
        });
    layers_of(planes, w, h, data)
}

/// Each row (`w` values) of every plane in `data`: `[y][plane]`, for filling the rows in
/// parallel.
pub(crate) fn rows_of(data: &mut [Vec<f32>], w: usize) -> Vec<Vec<&mut [f32]>> {
    let h = data.first().map_or(0, |d| d.len() / w.max(1));
    let mut rows: Vec<Vec<&mut [f32]>> = (0..h).map(|_| Vec::with_capacity(data.len())).collect();
    for d in data.iter_mut() {
        for (y, r) in d.chunks_mut(w).enumerate() {
            rows[y].push(r);
        }
    }
    rows
}

/// Layers on `planes` from `w` x `h` planes `[plane * 3 + channel]`.
pub(crate) fn layers_of(
    planes: &[Diopters],
    w: usize,
    h: usize,
    data: Vec<Vec<f32>>,
) -> Result<Layers, RenderError> {
    let mut it = data.into_iter();
    let mut images = Vec::with_capacity(planes.len());
    for _ in 0..planes.len() {
        let mut next = || Plane::from_vec(w, h, it.next().unwrap_or_default());
        images.push(RgbImage::from_planes(next()?, next()?, next()?)?);
    }
    Ok(Layers {
        planes: planes.to_vec(),
        images,
    })
}

/// Settings of optimized blending.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OptimizeParams {
    pub iterations: usize,
    /// Stop early when the objective's relative decrease over 10 iterations falls below this.
    pub tolerance: f64,
}

impl Default for OptimizeParams {
    fn default() -> Self {
        OptimizeParams {
            iterations: 100,
            tolerance: 0.0,
        }
    }
}

/// How the optimization went. `rms` is the root-mean-square retinal error (linear units,
/// over slices, channels and the padded grid) sampled every 10 iterations and at the end.
#[derive(Debug, Clone, PartialEq)]
pub struct OptimizeReport {
    pub iterations: usize,
    pub rms: Vec<(usize, f64)>,
    pub converged: bool,
}

/// Largest kernel radius (pixels) the retinal images of `planes` need for focus in `foci`.
fn max_radius(eye: &EyeModel, planes: &[Diopters], foci: &[Diopters]) -> usize {
    let mut m = 0usize;
    for &p in planes {
        for &q in foci {
            m = m.max(disk_kernel(eye.coc_px(p, q)).radius);
        }
    }
    m
}

/// Real kernel spectra for every plane at focus `q`.
fn plane_spectra(
    conv: &FftConv,
    eye: &EyeModel,
    planes: &[Diopters],
    q: Diopters,
) -> Vec<Vec<f32>> {
    let ks: Vec<_> = planes
        .iter()
        .map(|&p| disk_kernel(eye.coc_px(p, q)))
        .collect();
    let mut out = Vec::with_capacity(ks.len());
    for pair in ks.chunks(2) {
        let b = pair.get(1).cloned().unwrap_or_else(|| disk_kernel(0.0));
        let (sa, sb) = conv.kernel_spectra(&pair[0], &b);
        out.push(sa);
        if pair.len() == 2 {
            out.push(sb);
        }
    }
    out
}

/// Checks optimized blending's inputs (both backends); returns the targets' size.
pub(crate) fn check_optimize_inputs(
    targets: &[RgbImage],
    foci: &[Diopters],
    planes: &[Diopters],
    init: Option<&Layers>,
    params: &OptimizeParams,
) -> Result<(usize, usize), RenderError> {
    check_planes(planes)?;
    if targets.is_empty() || targets.len() != foci.len() {
        return Err(mismatch(format!(
            "{} target slices for {} focal samples",
            targets.len(),
            foci.len()
        )));
    }
    foci.iter().try_for_each(|&q| check_focus(q))?;
    let (w, h) = (targets[0].width(), targets[0].height());
    if w == 0 || h == 0 || targets.iter().any(|t| (t.width(), t.height()) != (w, h)) {
        return Err(mismatch("target slices are empty or differ in size"));
    }
    if let Some(l) = init {
        l.check()?;
        if (l.width(), l.height()) != (w, h) || l.planes != planes {
            return Err(mismatch(
                "initial layers do not match the targets' size or the planes",
            ));
        }
    }
    if params.iterations > 100_000 {
        return Err(invalid("iterations must be at most 100000"));
    }
    Ok((w, h))
}

/// Optimized blending of `targets` (slice j seen focusing at `foci[j]`) onto `planes`,
/// starting from `init` (e.g. [`linear_blend`]) or from the targets' mean split evenly.
pub fn optimized_blend(
    targets: &[RgbImage],
    foci: &[Diopters],
    planes: &[Diopters],
    eye: &EyeModel,
    init: Option<&Layers>,
    params: OptimizeParams,
    mut progress: impl FnMut(usize),
) -> Result<(Layers, OptimizeReport), RenderError> {
    let (w, h) = check_optimize_inputs(targets, foci, planes, init, &params)?;
    let eye = eye_for(eye, w)?;
    let np = planes.len();
    let conv = FftConv::new(w, h, max_radius(&eye, planes, foci));
    let n = conv.pw * conv.ph;
    // Channel groups packed as complex: (R + iG) and (B + 0i).
    let groups: [(usize, Option<usize>); 2] = [(0, Some(1)), (2, None)];
    let tri = |a: usize, b: usize| if a <= b { a * np + b } else { b * np + a };
    let mut m = vec![vec![0.0f32; n]; np * np];
    let mut bvec: Vec<Vec<Spectrum>> = (0..2)
        .map(|_| vec![vec![Complex32::default(); n]; np])
        .collect();
    let mut tnorm = 0.0f64;
    for (j, &q) in foci.iter().enumerate() {
        let ks = plane_spectra(&conv, &eye, planes, q);
        for a in 0..np {
            for b in a..np {
                let (ka, kb) = (&ks[a], &ks[b]);
                m[tri(a, b)]
                    .par_iter_mut()
                    .enumerate()
                    .for_each(|(f, v)| *v += ka[f] * kb[f]);
            }
        }
        for (g, &(c0, c1)) in groups.iter().enumerate() {
            let t = &targets[j].channels;
            let spec = conv.forward_pair(&t[c0], c1.map(|c| &t[c]));
            for (i, k) in ks.iter().enumerate() {
                bvec[g][i]
                    .par_iter_mut()
                    .enumerate()
                    .for_each(|(f, v)| *v += spec[f] * k[f]);
            }
            // |t|^2 on the padded grid, through Parseval.
            tnorm += spec.par_iter().map(|z| z.norm_sqr() as f64).sum::<f64>() / n as f64;
        }
    }
    // Gershgorin bound on the largest eigenvalue of M(f) over all f.
    let lipschitz = (0..n)
        .into_par_iter()
        .map(|f| {
            (0..np)
                .map(|a| (0..np).map(|b| m[tri(a, b)][f].abs()).sum::<f32>())
                .fold(0.0f32, f32::max)
        })
        .reduce(|| 0.0, f32::max)
        .max(1e-6);
    let step = 1.0 / lipschitz;

    // Spatial layers on the padded grid: [group][plane] -> (re, im).
    let start = |i: usize, c: usize| -> Vec<f32> {
        match init {
            Some(l) => conv.pad(&l.images[i].channels[c]),
            None => {
                let mean: Vec<f32> = (0..w * h)
                    .map(|p| {
                        targets.iter().map(|t| t.channels[c].data()[p]).sum::<f32>()
                            / (targets.len() * np) as f32
                    })
                    .collect();
                conv.pad(&Plane::from_vec(w, h, mean).unwrap_or_else(|_| Plane::new(w, h, 0.0)))
            }
        }
    };
    let mut x: Vec<Vec<(Vec<f32>, Vec<f32>)>> = groups
        .iter()
        .map(|&(c0, c1)| {
            (0..np)
                .map(|i| (start(i, c0), c1.map_or(vec![0.0; n], |c| start(i, c))))
                .collect()
        })
        .collect();
    let mut y = x.clone();
    let mut t_k = 1.0f64;
    let mut report = OptimizeReport {
        iterations: 0,
        rms: Vec::new(),
        converged: false,
    };
    let samples = (foci.len() * 3 * n) as f64;
    let objective = |specs: &[Vec<Spectrum>]| -> f64 {
        // sum_f Y^H M Y - 2 Re(Y^H B), over groups, / n, plus |t|^2.
        let mut acc = 0.0f64;
        for (g, ys) in specs.iter().enumerate() {
            acc += (0..n)
                .into_par_iter()
                .map(|f| {
                    let mut s = 0.0f64;
                    for a in 0..np {
                        let mut my = Complex32::default();
                        for b in 0..np {
                            my += ys[b][f] * m[tri(a, b)][f];
                        }
                        let ya = ys[a][f].conj();
                        s += (ya * my).re as f64 - 2.0 * (ya * bvec[g][a][f]).re as f64;
                    }
                    s
                })
                .sum::<f64>()
                / n as f64;
        }
        ((acc + tnorm).max(0.0) / samples).sqrt()
    };
    let mut last_rms = f64::INFINITY;
    for it in 0..params.iterations {
        let mut specs: Vec<Vec<Spectrum>> = Vec::with_capacity(2);
        for yg in &y {
            specs.push(
                yg.iter()
                    .map(|(re, im)| conv.forward_padded(re, im))
                    .collect(),
            );
        }
        if it % 10 == 0 {
            let r = objective(&specs);
            report.rms.push((it, r));
            if params.tolerance > 0.0
                && last_rms.is_finite()
                && (last_rms - r) <= params.tolerance * last_rms
            {
                report.converged = true;
                report.iterations = it;
                break;
            }
            last_rms = r;
        }
        let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t_k * t_k).sqrt());
        let mom = ((t_k - 1.0) / t_next) as f32;
        for (g, ys) in specs.iter().enumerate() {
            for a in 0..np {
                // Gradient step in frequency: Y_a - step (sum_b M_ab Y_b - B_a).
                let z: Spectrum = (0..n)
                    .into_par_iter()
                    .map(|f| {
                        let mut my = Complex32::default();
                        for b in 0..np {
                            my += ys[b][f] * m[tri(a, b)][f];
                        }
                        ys[a][f] - (my - bvec[g][a][f]) * step
                    })
                    .collect();
                let (mut re, mut im) = conv.inverse_padded(z);
                re.par_iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
                im.par_iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
                if groups[g].1.is_none() {
                    im.iter_mut().for_each(|v| *v = 0.0);
                }
                // Momentum: y = x_new + mom (x_new - x_old).
                let (xo_re, xo_im) = &x[g][a];
                let yr: Vec<f32> = re
                    .par_iter()
                    .zip(xo_re.par_iter())
                    .map(|(nw, od)| nw + mom * (nw - od))
                    .collect();
                let yi: Vec<f32> = im
                    .par_iter()
                    .zip(xo_im.par_iter())
                    .map(|(nw, od)| nw + mom * (nw - od))
                    .collect();
                y[g][a] = (yr, yi);
                x[g][a] = (re, im);
            }
        }
        t_k = t_next;
        report.iterations = it + 1;
        progress(it + 1);
    }
    // Final objective at the returned (projected) layers.
    let specs: Vec<Vec<Spectrum>> = x
        .iter()
        .map(|xg| {
            xg.iter()
                .map(|(re, im)| conv.forward_padded(re, im))
                .collect()
        })
        .collect();
    report.rms.push((report.iterations, objective(&specs)));
    let images = (0..np)
        .map(|i| {
            let r = conv.crop(&x[0][i].0);
            let g = conv.crop(&x[0][i].1);
            let b = conv.crop(&x[1][i].0);
            RgbImage::from_planes(r, g, b)
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((
        Layers {
            planes: planes.to_vec(),
            images,
        },
        report,
    ))
}

/// The retinal image of a multifocal display: each layer convolved with its plane's disk PSF
/// for focus `q`, summed. Layer spectra are computed once and reused for every focus.
pub struct MultifocalRetina {
    conv: FftConv,
    eye: EyeModel,
    planes: Vec<Diopters>,
    /// [plane] -> (R + iG, B) spectra.
    spectra: Vec<[Spectrum; 2]>,
}

impl MultifocalRetina {
    /// Prepares `layers` for focus anywhere in `focus_range` (sets the FFT padding).
    pub fn new(
        layers: &Layers,
        eye: &EyeModel,
        focus_range: (Diopters, Diopters),
    ) -> Result<Self, RenderError> {
        layers.check()?;
        check_focus(focus_range.0)?;
        check_focus(focus_range.1)?;
        let eye = eye_for(eye, layers.width())?;
        let conv = FftConv::new(
            layers.width(),
            layers.height(),
            max_radius(&eye, &layers.planes, &[focus_range.0, focus_range.1]),
        );
        let spectra = layers
            .images
            .iter()
            .map(|im| {
                let c = &im.channels;
                [
                    conv.forward_pair(&c[0], Some(&c[1])),
                    conv.forward_pair(&c[2], None),
                ]
            })
            .collect();
        Ok(MultifocalRetina {
            conv,
            eye,
            planes: layers.planes.clone(),
            spectra,
        })
    }

    /// What the eye sees focusing at `focus` (kernels wider than the prepared range are clamped).
    pub fn render(&self, focus: Diopters) -> Result<RgbImage, RenderError> {
        check_focus(focus)?;
        let ks = plane_spectra(&self.conv, &self.eye, &self.planes, focus);
        let n = self.conv.pw * self.conv.ph;
        let mut out = Vec::with_capacity(2);
        for g in 0..2 {
            let s: Spectrum = (0..n)
                .into_par_iter()
                .map(|f| {
                    ks.iter()
                        .zip(&self.spectra)
                        .map(|(k, sp)| sp[g][f] * k[f])
                        .sum()
                })
                .collect();
            out.push(self.conv.inverse_pair(s));
        }
        let [(r, gr), (b, _)] = [out.swap_remove(0), out.swap_remove(0)];
        Ok(RgbImage::from_planes(r, gr, b)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dioptra_core::DepthMap;

    fn rgbd(depths: &[f32]) -> Rgbd {
        let n = depths.len();
        let c = RgbImage::new(n, 1, [0.5, 0.25, 1.0]);
        let d = DepthMap::from_diopters(Plane::from_vec(n, 1, depths.to_vec()).unwrap()).unwrap();
        Rgbd::new(c, d).unwrap()
    }

    #[test]
    fn linear_blend_splits_by_dioptric_distance() {
        let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
        let l = linear_blend(&rgbd(&[0.0, 0.5, 1.4, 3.0]), &planes).unwrap();
        let at = |i: usize, x: usize| l.images[i].channels[0].data()[x];
        assert_eq!(at(0, 0), 0.5); // beyond the farthest plane: all on 0.2 D
        assert!((at(0, 1) - 0.25).abs() < 1e-6 && (at(1, 1) - 0.25).abs() < 1e-6); // halfway 0.2-0.8
        assert!((at(2, 2) - 0.5).abs() < 1e-6 && at(1, 2).abs() < 1e-6);
        assert_eq!(at(3, 3), 0.5);
        // energy is conserved at every pixel
        for x in 0..4 {
            let s: f32 = (0..4).map(|i| at(i, x)).sum();
            assert!((s - 0.5).abs() < 1e-6);
        }
        assert!(linear_blend(&rgbd(&[1.0]), &[Diopters(1.0), Diopters(0.5)]).is_err());
    }

    #[test]
    fn optimized_recovers_a_single_plane_scene() {
        // Targets made by a display with content on one plane are reproduced exactly.
        // A 1-degree field over 24 px gives kernels of several pixels, as 20 degrees over 512 does.
        let eye = EyeModel {
            fov_horizontal_deg: 1.0,
            ..EyeModel::default()
        };
        let planes = [Diopters(0.2), Diopters(1.4)];
        let (w, h) = (24, 20);
        let tex: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919) % 13) as f32 / 13.0)
            .collect();
        let img = RgbImage::from_planes(
            Plane::from_vec(w, h, tex.clone()).unwrap(),
            Plane::from_vec(w, h, tex.iter().map(|v| 1.0 - v).collect()).unwrap(),
            Plane::new(w, h, 0.3),
        )
        .unwrap();
        let truth = Layers {
            planes: planes.to_vec(),
            images: vec![RgbImage::new(w, h, [0.0; 3]), img],
        };
        let foci = linspace(0.1, 2.2, 6);
        let retina =
            MultifocalRetina::new(&truth, &eye.with_width(w as u32), (foci[0], foci[5])).unwrap();
        let targets: Vec<RgbImage> = foci.iter().map(|&q| retina.render(q).unwrap()).collect();
        let params = OptimizeParams {
            iterations: 200,
            tolerance: 0.0,
        };
        let (layers, rep) =
            optimized_blend(&targets, &foci, &planes, &eye, None, params, |_| {}).unwrap();
        assert_eq!(rep.iterations, 200);
        let first = rep.rms.first().unwrap().1;
        let last = rep.rms.last().unwrap().1;
        // The padded-grid objective keeps a floor from the replicated margin; it must still fall.
        assert!(last < 0.5 * first, "rms {first} -> {last}");
        let r = MultifocalRetina::new(&layers, &eye, (foci[0], foci[5])).unwrap();
        let psnr = crate::metrics::psnr(
            &r.render(Diopters(1.0)).unwrap(),
            &retina.render(Diopters(1.0)).unwrap(),
            None,
        )
        .unwrap();
        assert!(psnr > 45.0, "{psnr} dB");
    }
}
