//! Spectral multifocal decomposition (after Mercier et al. 2017): the least-squares fit of the
//! retinal images to a focal stack, solved in closed form per spatial frequency.
//!
//! The eye focusing at q_j sees z_j = sum_a k_aj * y_a (k_aj the disk PSF of plane a). On the
//! FFT grid every k_aj is diagonal, so minimising
//!   (1/nf) sum_j ||z_j - t_j||^2 + lambda sum_a ||y_a - l_a||^2
//! splits into one planes x planes system per frequency:
//!   (M + lambda I) Y = B + lambda L,  M_ab = (1/nf) sum_j K_aj K_bj,  B_a = (1/nf) sum_j K_aj T_j.
//! Every plane passes the low frequencies almost alike (M is nearly rank one there), so that
//! part of the split is ill-posed on its own: the prior toward linear blending's layers `l`
//! decides it, and keeps the layers near [0, 1] where linear blending always is.
//!
//! The targets: a focal stack built in the frequency domain from depth slices. The input's
//! colour is split between depth nodes (tent weights, the display planes among the nodes) into
//! slices S_d, and the stack is t_j = sum_d k(node_d, q_j) * S_d (additive layers, as the
//! display itself is). Then B = G S and L = E S with G_ad = (1/nf) sum_j K_aj K'_dj and E the
//! linear blend of each node, so the whole solve is Y = R S with
//! R = (M + lambda I)^-1 (G + lambda E): an np x nd real matrix per frequency, built once per
//! (eye, planes, foci, size, slices, prior) by [`SpectralPlan::new`] and reused for every frame.
//! A frame costs 3 nd forward and 3 np inverse real FFTs and one matrix product per frequency.
//! (A focal stack rendered by another method can be fitted instead: [`SpectralPlan::solve_stack`].)
//!
//! The display's [0, 1]: the solution is clamped; `iterations` steps on the same objective
//! with the layers held in [0, 1] may follow, kept only where they lower it: ADMM (the
//! default; its x-update is the exact per-frequency solve with (M + lambda I + rho I)^-1,
//! precomputed in the plan, so the well and the badly conditioned frequencies converge alike)
//! or projected gradient (FISTA, step 1 / the largest eigenvalue over all frequencies, where
//! the frequencies near lambda barely move). Each step costs 3 np forward and 3 np inverse
//! FFTs.
//!
//! Where the time goes at a panel's size (960 x 1080 per eye, 20 degrees over the width, so
//! 48 px per degree and blur kernels up to 22 px across; `examples/spectral_profile`, 2 cores):
//! at full resolution the composite target stack (its light field at 6 foci over the pixels a
//! blurred step reaches, a third of the image on a test scene, and the disk blur elsewhere)
//! about 60 % of 3 s of CPU, the FFTs on the 1000 x 1125 grid (30 forward for the targets and
//! the prior, 12 inverse, 24 per step and 12 for the final objective) the rest; the
//! per-frequency matrices (one 4 x 4 solve per frequency) are built once per settings. So
//! [`spectral_blend`] solves on a grid coarsened from the blur (`scale`, 1/4 there: about
//! 160 ms of CPU) plus linear blending's detail above it ([`crate::spectral_coarse`]); the
//! gaze-contingent hybrid runs the solve on a window around the gaze instead.

use crate::common::eye_for;
use crate::defocus::DefocusMethod;
use crate::error::{invalid, mismatch, RenderError};
use crate::fft2::{fft_size, Fft2, HalfSpectrum};
use crate::kernel::disk_kernel;
use crate::multifocal::{check_planes, linear_blend, linspace, Layers};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage, Rgbd};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// What the solve fits: the focal stack it is made from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SpectralTargets {
    /// Built in the frequency domain from depth slices of the input: the additive layered
    /// stack (the whole solve one matrix product per frequency).
    Slices,
    /// Depth slices, each focus normalised by the slices' blurred coverage.
    NormalizedSlices,
    /// Rendered from the input by a defocus method at every focal sample.
    Defocus(DefocusMethod),
    /// Rendered at every focal sample by [`crate::composite::composite_stack`]: the light
    /// field where a blurred depth step reaches, the exact disk blur of smooth depth elsewhere.
    Composite(crate::lightfield::LightFieldParams),
}

/// Settings of the spectral decomposition.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectralParams {
    /// Focal samples the retinal images are fitted at, evenly spaced over `focal_range`.
    pub focal_samples: usize,
    /// Range of the focal samples, diopters.
    pub focal_range: (f32, f32),
    /// Slice targets: largest spacing of the depth nodes (diopters); the display planes are
    /// nodes.
    pub slice_step: f32,
    /// Slice targets: the nearest depth node (diopters); nearer content is put on it.
    pub slice_max: f32,
    /// Weight of the prior toward linear blending, per focal sample.
    pub prior: f32,
    /// Steps of the box-constrained refinement after the clamp (0: clamp only).
    pub iterations: usize,
    /// What the solve fits.
    pub targets: SpectralTargets,
    /// How the steps after the clamp are taken.
    pub solver: SpectralSolver,
    /// The grid [`spectral_blend`] solves on: 1 the image's own pixels; s > 1 a grid s times
    /// coarser plus linear blending's detail above it ([`crate::spectral_coarse`]); 0 chooses
    /// from the widest blur ([`crate::spectral_coarse::AUTO_MIN_BLUR_PX`]: the image's own
    /// pixels while the blur is small, a 1/4 grid at 960 px over 20 degrees). A
    /// [`SpectralPlan`] always solves on its own grid.
    pub scale: usize,
}

/// The refinement after the clamp: both minimise the same objective over layers in [0, 1],
/// each step one forward and one inverse FFT per layer and channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SpectralSolver {
    /// Projected gradient (FISTA), step 1 / the largest eigenvalue over all frequencies.
    ProjectedGradient,
    /// ADMM on the split x = z, z in [0, 1] (Boyd et al. 2011, sec. 5.2): the x-update is the
    /// exact per-frequency solve (A + rho I)^-1 (A Y0 + rho (z - u)), so every frequency
    /// converges at its own rate instead of at the global step's; `rho` weighs the split
    /// (in the objective's units, per focal sample).
    Admm { rho: f32 },
}

/// The defaults were chosen by measurement on the test seeds (`cargo run --release -p
/// dioptra-render --example spectral_choice`) and on the independent Mitsuba set
/// (scripts/independent_validation; the tables are in crates/render/README.md): a composite
/// stack (a 12-view light field where a blurred depth step reaches, the smooth disk blur
/// elsewhere) at 6 focal samples, a prior of 0.02, then 3 ADMM steps (rho 0.3) after the
/// clamp. ADMM replaced 5 projected-gradient steps: 7 FFTs per layer and channel after the
/// clamp instead of 11, and a lower objective in as many steps (the test
/// `admm_gets_further_than_projected_gradient_in_as_many_steps`); the two against the truth
/// at a panel's size are in crates/render/README.md (`examples/hybrid_accuracy`).
impl Default for SpectralParams {
    fn default() -> Self {
        SpectralParams {
            focal_samples: 6,
            focal_range: (0.1, 2.2),
            slice_step: 0.3,
            slice_max: 4.0,
            prior: 0.02,
            iterations: 3,
            targets: SpectralTargets::Composite(crate::lightfield::LightFieldParams {
                views: 12,
                mip: true,
            }),
            solver: SpectralSolver::Admm { rho: 0.3 },
            scale: 0,
        }
    }
}

impl SpectralParams {
    pub fn check(&self) -> Result<(), RenderError> {
        let (lo, hi) = self.focal_range;
        if !(1..=200).contains(&self.focal_samples) {
            return Err(invalid(format!(
                "spectral focal samples = {}: expected 1 to 200",
                self.focal_samples
            )));
        }
        if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi >= lo && hi < 1000.0) {
            return Err(invalid(format!(
                "spectral focal range {lo}..{hi} D: expected 0 <= lo <= hi < 1000"
            )));
        }
        if !(self.slice_step.is_finite() && (0.05..=10.0).contains(&self.slice_step)) {
            return Err(invalid(format!(
                "spectral slice step {} D: expected 0.05 to 10",
                self.slice_step
            )));
        }
        if !(self.slice_max.is_finite() && self.slice_max > 0.0 && self.slice_max < 1000.0) {
            return Err(invalid(format!(
                "spectral slice max {} D: expected 0 < max < 1000",
                self.slice_max
            )));
        }
        if !(self.prior.is_finite() && self.prior > 0.0 && self.prior <= 1e6) {
            return Err(invalid(format!(
                "spectral prior weight {}: expected 0 < prior <= 1e6 (the lowest frequencies need it)",
                self.prior
            )));
        }
        if self.iterations > 1000 {
            return Err(invalid("spectral iterations must be at most 1000"));
        }
        if self.scale > crate::spectral_coarse::MAX_SCALE {
            return Err(invalid(format!(
                "spectral scale {}: expected 0 (automatic) to {}",
                self.scale,
                crate::spectral_coarse::MAX_SCALE
            )));
        }
        if let SpectralSolver::Admm { rho } = self.solver {
            if !(rho.is_finite() && rho > 0.0 && rho <= 1e6) {
                return Err(invalid(format!(
                    "spectral ADMM weight rho = {rho}: expected 0 < rho <= 1e6"
                )));
            }
        }
        Ok(())
    }

    pub fn foci(&self) -> Vec<Diopters> {
        linspace(self.focal_range.0, self.focal_range.1, self.focal_samples)
    }
}

/// The depth nodes: 0 D (unless a plane is there), the planes, and evenly spaced nodes
/// between them and up to `max`, no two more than `step` apart.
pub(crate) fn depth_nodes(planes: &[Diopters], step: f32, max: f32) -> Vec<f32> {
    let mut anchors: Vec<f32> = vec![0.0];
    anchors.extend(planes.iter().map(|p| p.0));
    anchors.push(max.max(planes.last().map_or(0.0, |p| p.0)));
    anchors.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    let mut nodes = vec![anchors[0]];
    for w in anchors.windows(2) {
        let n = ((w[1] - w[0]) / step - 1e-4).ceil().max(1.0) as usize;
        for k in 1..=n {
            nodes.push(w[0] + (w[1] - w[0]) * k as f32 / n as f32);
        }
    }
    nodes
}

/// Tent weights of depth `x` on `nodes` (increasing): the two bracketing nodes and the
/// weight of the upper one; outside the nodes, all on the nearest end.
#[inline]
pub(crate) fn bracket(nodes: &[f32], x: f32) -> (usize, usize, f32) {
    let k = nodes.partition_point(|&n| n <= x);
    if k == 0 {
        (0, 0, 0.0)
    } else if k == nodes.len() {
        (k - 1, k - 1, 0.0)
    } else {
        let (a, b) = (nodes[k - 1], nodes[k]);
        (k - 1, k, (x - a) / (b - a))
    }
}

/// The precomputed per-frequency matrices for one eye, plane set, focal sampling, image
/// size and slicing: build once per rig configuration, then [`SpectralPlan::decompose`] per
/// frame.
pub struct SpectralPlan {
    pub(crate) eye: EyeModel,
    pub(crate) planes: Vec<Diopters>,
    pub(crate) params: SpectralParams,
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) margin: usize,
    pub(crate) fft: Fft2,
    pub(crate) nodes: Vec<f32>,
    /// [a][d][f]: layer a's response to slice d (np x nd x nfreq).
    pub(crate) r: Vec<f32>,
    /// [a][b][f]: M + lambda I, symmetric (the refinement's operator).
    pub(crate) a: Vec<f32>,
    /// Step of the projected gradient: 1 / the largest eigenvalue of M + lambda I.
    pub(crate) step: f32,
    /// [a][b][f]: (M + lambda I)^-1.
    pub(crate) ainv: Vec<f32>,
    /// [a][b][f]: rho (M + lambda I + rho I)^-1, the ADMM x-update (empty for the projected
    /// gradient).
    pub(crate) admm: Vec<f32>,
    /// [a][j][f]: (1/nf) (M + lambda I)^-1 K_j, the fit of a rendered stack (its targets).
    pub(crate) fit: Vec<f32>,
    /// [j][a][f]: kernel spectra of the planes at each focus (normalised slices only).
    kstack: Vec<f32>,
    /// [j][d][f]: kernel spectra of the depth nodes at each focus (normalised slices only).
    knode: Vec<f32>,
    /// [a][d]: linear blending of each node.
    e: Vec<f32>,
}

/// What [`SpectralPlan::solve`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct SpectralReport {
    /// The objective (retinal mean squared error per focal sample and pixel, plus the prior,
    /// on the padded grid) of the clamped solution, and after the projected steps.
    pub objective_clamped: f64,
    pub objective_final: f64,
    /// Projected steps run, and whether their result was kept.
    pub iterations: usize,
    pub refined: bool,
}

/// The spectra a solve starts from: the unconstrained solution per channel and layer.
pub struct Unconstrained {
    /// [c * np + a]: half spectra of the unconstrained least-squares layers.
    y0: Vec<HalfSpectrum>,
}

impl SpectralPlan {
    /// Builds the matrices for `width` x `height` frames (a few hundred kernel FFTs).
    pub fn new(
        eye: &EyeModel,
        planes: &[Diopters],
        width: usize,
        height: usize,
        params: SpectralParams,
    ) -> Result<SpectralPlan, RenderError> {
        check_planes(planes)?;
        params.check()?;
        if width == 0 || height == 0 || width > 16384 || height > 16384 {
            return Err(invalid(format!(
                "image size {width}x{height}: expected 1 to 16384 per side"
            )));
        }
        let eye = eye_for(eye, width)?;
        let foci = params.foci();
        let slices = matches!(
            params.targets,
            SpectralTargets::Slices | SpectralTargets::NormalizedSlices
        );
        let nodes = if slices {
            depth_nodes(planes, params.slice_step, params.slice_max)
        } else {
            Vec::new()
        };
        let (np, nd, nf) = (planes.len(), nodes.len(), foci.len());
        // Every diameter a kernel takes, and the margin the widest needs.
        let diam = |x: f32, q: Diopters| eye.coc_px(Diopters(x), q);
        let mut max_r = 0;
        for &x in planes.iter().map(|p| &p.0).chain(&nodes) {
            for &q in &foci {
                max_r = max_r.max(disk_kernel(diam(x, q)).radius);
            }
        }
        let margin = max_r + 2;
        let fft = Fft2::new(fft_size(width + 2 * margin), fft_size(height + 2 * margin));
        let n = fft.len();
        // Kernel spectra, each distinct diameter once.
        let mut cache: HashMap<u32, Arc<Vec<f32>>> = HashMap::new();
        let mut spectrum = |d: f32| -> Arc<Vec<f32>> {
            cache
                .entry(d.to_bits())
                .or_insert_with(|| {
                    let k = disk_kernel(d);
                    let r = k.radius as isize;
                    Arc::new(fft.kernel((-r..=r).flat_map(|dy| {
                        let k = &k;
                        (-r..=r).map(move |dx| (dx, dy, k.at(dx, dy)))
                    })))
                })
                .clone()
        };
        let kp: Vec<Vec<Arc<Vec<f32>>>> = foci
            .iter()
            .map(|&q| planes.iter().map(|p| spectrum(diam(p.0, q))).collect())
            .collect();
        let kn: Vec<Vec<Arc<Vec<f32>>>> = foci
            .iter()
            .map(|&q| nodes.iter().map(|&x| spectrum(diam(x, q))).collect())
            .collect();
        // Linear blending of each node (exact: the planes are nodes).
        let mut e = vec![0.0f64; np * nd];
        for (d, &x) in nodes.iter().enumerate() {
            let pl: Vec<f32> = planes.iter().map(|p| p.0).collect();
            let (lo, hi, t) = bracket(&pl, x);
            e[lo * nd + d] += 1.0 - t as f64;
            e[hi * nd + d] += t as f64;
        }
        let lambda = params.prior as f64;
        let mut r = vec![0.0f32; np * nd * n];
        let mut a = vec![0.0f32; np * np * n];
        let mut kstack = Vec::new();
        let mut knode = Vec::new();
        if params.targets == SpectralTargets::NormalizedSlices {
            kstack = vec![0.0f32; nf * np * n];
            for (j, ks) in kp.iter().enumerate() {
                for (i, k) in ks.iter().enumerate() {
                    kstack[(j * np + i) * n..(j * np + i + 1) * n].copy_from_slice(k);
                }
            }
            knode = vec![0.0f32; nf * nd * n];
            for (j, ks) in kn.iter().enumerate() {
                for (d, k) in ks.iter().enumerate() {
                    knode[(j * nd + d) * n..(j * nd + d + 1) * n].copy_from_slice(k);
                }
            }
        }
        // Per frequency: M, G, then R = (M + lambda I)^-1 (G + lambda E) by Cholesky in f64.
        let chunk = 256;
        let nfit = nf;
        let identity: Vec<f64> = (0..np * np)
            .map(|k| if k / np == k % np { 1.0 } else { 0.0 })
            .collect();
        type Part = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, f32);
        let rho = match params.solver {
            SpectralSolver::Admm { rho } => Some(rho as f64),
            SpectralSolver::ProjectedGradient => None,
        };
        let results: Vec<Part> = (0..n.div_ceil(chunk))
            .into_par_iter()
            .map(|c| {
                let f0 = c * chunk;
                let f1 = (f0 + chunk).min(n);
                let mut rr = vec![0.0f32; np * nd * (f1 - f0)];
                let mut aa = vec![0.0f32; np * np * (f1 - f0)];
                let mut ai = vec![0.0f32; np * np * (f1 - f0)];
                let mut ft = vec![0.0f32; np * nfit * (f1 - f0)];
                let mut ad = vec![
                    0.0f32;
                    if rho.is_some() {
                        np * np * (f1 - f0)
                    } else {
                        0
                    }
                ];
                let mut lmax = 0.0f32;
                let mut m = vec![0.0f64; np * np];
                let mut g = vec![0.0f64; np * nd];
                let inv_nf = 1.0 / nf as f64;
                for f in f0..f1 {
                    m.iter_mut().for_each(|v| *v = 0.0);
                    g.iter_mut().for_each(|v| *v = 0.0);
                    for j in 0..nf {
                        for a in 0..np {
                            let ka = kp[j][a][f] as f64;
                            for b in 0..np {
                                m[a * np + b] += ka * kp[j][b][f] as f64;
                            }
                            for d in 0..nd {
                                g[a * nd + d] += ka * kn[j][d][f] as f64;
                            }
                        }
                    }
                    m.iter_mut().for_each(|v| *v *= inv_nf);
                    for a in 0..np {
                        m[a * np + a] += lambda;
                        for d in 0..nd {
                            g[a * nd + d] = g[a * nd + d] * inv_nf + lambda * e[a * nd + d];
                        }
                    }
                    // Gershgorin bound on the largest eigenvalue.
                    for a in 0..np {
                        let s: f64 = (0..np).map(|b| m[a * np + b].abs()).sum();
                        lmax = lmax.max(s as f32);
                        for b in 0..np {
                            aa[(a * np + b) * (f1 - f0) + f - f0] = m[a * np + b] as f32;
                        }
                    }
                    let x = cholesky_solve(&m, &g, np, nd);
                    for a in 0..np {
                        for d in 0..nd {
                            rr[(a * nd + d) * (f1 - f0) + f - f0] = x[a * nd + d] as f32;
                        }
                    }
                    let inv = cholesky_solve(&m, &identity, np, np);
                    if let Some(rho) = rho {
                        let mut mr = m.clone();
                        (0..np).for_each(|a| mr[a * np + a] += rho);
                        let b = cholesky_solve(&mr, &identity, np, np);
                        for (k, v) in b.iter().enumerate() {
                            ad[k * (f1 - f0) + f - f0] = (rho * v) as f32;
                        }
                    }
                    for a in 0..np {
                        for b in 0..np {
                            ai[(a * np + b) * (f1 - f0) + f - f0] = inv[a * np + b] as f32;
                        }
                        for j in 0..nfit {
                            let v: f64 = (0..np)
                                .map(|b| inv[a * np + b] * kp[j][b][f] as f64)
                                .sum::<f64>()
                                * inv_nf;
                            ft[(a * nfit + j) * (f1 - f0) + f - f0] = v as f32;
                        }
                    }
                }
                (rr, aa, ai, ft, ad, lmax)
            })
            .collect();
        let mut lmax = 0.0f32;
        let mut ainv = vec![0.0f32; np * np * n];
        let mut fit = vec![0.0f32; np * nfit * n];
        let mut admm = vec![0.0f32; if rho.is_some() { np * np * n } else { 0 }];
        for (c, (rr, aa, ai, ft, ad, l)) in results.into_iter().enumerate() {
            let f0 = c * chunk;
            let len = aa.len() / (np * np);
            let put = |dst: &mut [f32], src: &[f32], rows: usize| {
                for k in 0..rows {
                    dst[k * n + f0..k * n + f0 + len].copy_from_slice(&src[k * len..(k + 1) * len]);
                }
            };
            put(&mut r, &rr, np * nd);
            put(&mut a, &aa, np * np);
            put(&mut ainv, &ai, np * np);
            put(&mut fit, &ft, np * nfit);
            if rho.is_some() {
                put(&mut admm, &ad, np * np);
            }
            lmax = lmax.max(l);
        }
        Ok(SpectralPlan {
            eye,
            planes: planes.to_vec(),
            params,
            width,
            height,
            margin,
            fft,
            nodes,
            r,
            a,
            step: 1.0 / lmax.max(1e-6),
            ainv,
            admm,
            fit,
            kstack,
            knode,
            e: e.iter().map(|&v| v as f32).collect(),
        })
    }

    pub fn params(&self) -> &SpectralParams {
        &self.params
    }

    /// The padded grid the FFTs run on (width, height): the image and a margin for the
    /// widest kernel, each side a product of 2, 3 and 5.
    pub fn grid(&self) -> (usize, usize) {
        (self.fft.pw, self.fft.ph)
    }

    /// The depth nodes the colour is sliced at, diopters.
    pub fn nodes(&self) -> &[f32] {
        &self.nodes
    }

    /// Whether this plan serves `input` with these settings.
    pub fn fits(
        &self,
        eye: &EyeModel,
        planes: &[Diopters],
        width: usize,
        height: usize,
        params: &SpectralParams,
    ) -> bool {
        self.width == width
            && self.height == height
            && self.planes == planes
            && self.params == *params
            && eye_for(eye, width).is_ok_and(|e| e == self.eye)
    }

    fn check_input(&self, input: &Rgbd) -> Result<(), RenderError> {
        if (input.width(), input.height()) != (self.width, self.height) {
            return Err(mismatch(format!(
                "the input is {}x{} but the spectral plan was built for {}x{}",
                input.width(),
                input.height(),
                self.width,
                self.height
            )));
        }
        Ok(())
    }

    /// Source pixel of each padded-grid pixel (edge replication).
    fn source_index(&self) -> Vec<u32> {
        let (pw, ph, m) = (self.fft.pw, self.fft.ph, self.margin as isize);
        let (w, h) = (self.width as isize, self.height as isize);
        (0..pw * ph)
            .map(|i| {
                let x = (i % pw) as isize - m;
                let y = (i / pw) as isize - m;
                (y.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as u32
            })
            .collect()
    }

    /// A `width` x `height` plane on the padded grid, its edges replicated into the margin
    /// (what [`SpectralPlan::source_index`] maps, by rows).
    fn padded(&self, p: &[f32]) -> Vec<f32> {
        let (pw, ph, m, w, h) = (
            self.fft.pw,
            self.fft.ph,
            self.margin,
            self.width,
            self.height,
        );
        let mut out = Vec::with_capacity(pw * ph);
        for y in 0..ph {
            let row = &p[y.saturating_sub(m).min(h - 1) * w..][..w];
            out.extend(std::iter::repeat_n(row[0], m));
            out.extend_from_slice(row);
            out.extend(std::iter::repeat_n(row[w - 1], pw - m - w));
        }
        out
    }

    /// The unconstrained solution's spectra from the RGB-D alone (the focal stack built from
    /// depth slices in the frequency domain).
    pub fn targets_rgbd(&self, input: &Rgbd) -> Result<Unconstrained, RenderError> {
        self.check_input(input)?;
        let (np, nd, n) = (self.planes.len(), self.nodes.len(), self.fft.len());
        let src = self.source_index();
        let depth = input.depth.data();
        let nodes = &self.nodes;
        // Per padded pixel: its two nodes and the upper one's weight.
        let tents: Vec<(u16, u16, f32)> = src
            .par_iter()
            .map(|&s| {
                let (a, b, t) = bracket(nodes, depth[s as usize]);
                (a as u16, b as u16, t)
            })
            .collect();
        // Slices: [c * nd + d] colour, then (normalised targets) [3 nd + d] coverage.
        let normalize = match self.params.targets {
            SpectralTargets::Slices => false,
            SpectralTargets::NormalizedSlices => true,
            SpectralTargets::Defocus(_) | SpectralTargets::Composite(_) => {
                return Err(invalid(
                    "this spectral plan fits a rendered focal stack: use targets_stack",
                ))
            }
        };
        let count = if normalize { 4 * nd } else { 3 * nd };
        let spectra: Vec<HalfSpectrum> = (0..count)
            .into_par_iter()
            .map(|k| {
                let (c, d) = (k / nd, (k % nd) as u16);
                let col = input.color.channels.get(c).map(|p| p.data());
                let mut img: Vec<f32> = src
                    .iter()
                    .zip(&tents)
                    .map(|(&s, &(a, b, t))| {
                        let w = if a == d { 1.0 - t } else { 0.0 } + if b == d { t } else { 0.0 };
                        col.map_or(w, |col| w * col[s as usize])
                    })
                    .collect();
                self.fft.forward(&mut img)
            })
            .collect();
        if normalize {
            return Ok(self.normalized(&spectra));
        }
        // Y0[c][a] = sum_d R[a][d] S[c][d], by chunks of frequencies.
        let y0 = self.apply(&spectra, &self.r, nd, np, n);
        Ok(Unconstrained { y0 })
    }

    /// The unconstrained solution for targets from depth slices normalised per focus by
    /// their blurred coverage: per focus 4 inverse and 3 forward FFTs.
    fn normalized(&self, spectra: &[HalfSpectrum]) -> Unconstrained {
        let (np, nd, nf, n) = (
            self.planes.len(),
            self.nodes.len(),
            self.params.focal_samples,
            self.fft.len(),
        );
        let kn = |j: usize, d: usize| &self.knode[(j * nd + d) * n..(j * nd + d + 1) * n];
        let kp = |j: usize, a: usize| &self.kstack[(j * np + a) * n..(j * np + a + 1) * n];
        // B[c][a] = (1/nf) sum_j K_aj T_jc, summed over foci in parallel.
        let b = (0..nf)
            .into_par_iter()
            .map(|j| {
                let blurred: Vec<Vec<f32>> = (0..4)
                    .map(|c| {
                        let mut acc = vec![Complex32::default(); n];
                        for d in 0..nd {
                            for ((o, &s), &k) in
                                acc.iter_mut().zip(&spectra[c * nd + d]).zip(kn(j, d))
                            {
                                *o += s * k;
                            }
                        }
                        self.fft.inverse(acc)
                    })
                    .collect();
                let mut out = vec![vec![Complex32::default(); n]; 3 * np];
                for c in 0..3 {
                    let mut t: Vec<f32> = blurred[c]
                        .iter()
                        .zip(&blurred[3])
                        .map(|(&v, &a)| if a > 1e-4 { v / a } else { 0.0 })
                        .collect();
                    let ts = self.fft.forward(&mut t);
                    for a in 0..np {
                        for ((o, &s), &k) in out[c * np + a].iter_mut().zip(&ts).zip(kp(j, a)) {
                            *o += s * k;
                        }
                    }
                }
                out
            })
            .reduce(
                || vec![vec![Complex32::default(); n]; 3 * np],
                |mut x, y| {
                    for (x, y) in x.iter_mut().zip(&y) {
                        for (x, y) in x.iter_mut().zip(y) {
                            *x += y;
                        }
                    }
                    x
                },
            );
        let lambda = self.params.prior;
        let inv_nf = 1.0 / nf as f32;
        let rhs: Vec<HalfSpectrum> = b
            .into_par_iter()
            .enumerate()
            .map(|(k, mut r)| {
                let (c, a) = (k / np, k % np);
                r.iter_mut().for_each(|v| *v *= inv_nf);
                for d in 0..nd {
                    let e = self.e[a * nd + d] * lambda;
                    if e != 0.0 {
                        for (r, s) in r.iter_mut().zip(&spectra[c * nd + d]) {
                            *r += s * e;
                        }
                    }
                }
                r
            })
            .collect();
        Unconstrained {
            y0: self.apply(&rhs, &self.ainv, np, np, n),
        }
    }

    /// `out[c * rows + a] = sum_d mat[a][d] * inp[c * cols + d]` per frequency, for the three
    /// channels; `mat` is [a][d][f].
    fn apply(
        &self,
        inp: &[HalfSpectrum],
        mat: &[f32],
        cols: usize,
        rows: usize,
        n: usize,
    ) -> Vec<HalfSpectrum> {
        self.apply_sum(&[(inp, mat, cols, 1.0)], rows, n)
    }

    /// The sum of [`SpectralPlan::apply`]'s products over `terms` (inputs, matrix, its
    /// columns, a scale), in one pass over the frequencies.
    fn apply_sum(
        &self,
        terms: &[(&[HalfSpectrum], &[f32], usize, f32)],
        rows: usize,
        n: usize,
    ) -> Vec<HalfSpectrum> {
        const CHUNK: usize = 512;
        let mut outs: Vec<HalfSpectrum> = (0..3 * rows)
            .map(|_| vec![Complex32::default(); n])
            .collect();
        // Jobs of (first frequency, that chunk of every output).
        let mut jobs: Vec<(usize, Vec<&mut [Complex32]>)> = (0..n.div_ceil(CHUNK))
            .map(|k| (k * CHUNK, Vec::with_capacity(3 * rows)))
            .collect();
        for o in outs.iter_mut() {
            for (job, ch) in jobs.iter_mut().zip(o.chunks_mut(CHUNK)) {
                job.1.push(ch);
            }
        }
        jobs.into_par_iter().for_each(|(f0, mut outs)| {
            let len = outs[0].len();
            for (k, o) in outs.iter_mut().enumerate() {
                let (c, a) = (k / rows, k % rows);
                for &(inp, mat, cols, scale) in terms {
                    for d in 0..cols {
                        let m = &mat[(a * cols + d) * n + f0..][..len];
                        let s = &inp[c * cols + d][f0..f0 + len];
                        for ((o, &m), &s) in o.iter_mut().zip(m).zip(s) {
                            *o += s * (m * scale);
                        }
                    }
                }
            }
        });
        outs
    }

    /// The unconstrained solution's spectra fitting a focal stack rendered elsewhere (one
    /// image per focal sample of the plan), with the prior toward `input`'s linear blending.
    pub fn targets_stack(
        &self,
        input: &Rgbd,
        stack: &[RgbImage],
    ) -> Result<Unconstrained, RenderError> {
        self.check_input(input)?;
        let (np, nf, n) = (self.planes.len(), self.params.focal_samples, self.fft.len());
        if stack.len() != nf
            || stack
                .iter()
                .any(|t| (t.width(), t.height()) != (self.width, self.height))
        {
            return Err(mismatch(format!(
                "{} target slices for {nf} focal samples of {}x{}",
                stack.len(),
                self.width,
                self.height
            )));
        }
        let linear = linear_blend(input, &self.planes)?;
        // Y0[c][a] = sum_j FIT_aj T_jc + lambda sum_b AINV_ab L_bc: the targets' and the
        // linear layers' spectra in one parallel batch, then one pass over the frequencies.
        let spectra: Vec<HalfSpectrum> = (0..3 * (nf + np))
            .into_par_iter()
            .map(|k| {
                let p = if k < 3 * nf {
                    &stack[k % nf].channels[k / nf]
                } else {
                    let k = k - 3 * nf;
                    &linear.images[k % np].channels[k / np]
                };
                self.fft.forward(&mut self.padded(p.data()))
            })
            .collect();
        let (ts, ls) = spectra.split_at(3 * nf);
        let y0 = self.apply_sum(
            &[
                (ts, &self.fit, nf, 1.0),
                (ls, &self.ainv, np, self.params.prior),
            ],
            np,
            n,
        );
        Ok(Unconstrained { y0 })
    }

    /// The layers from the unconstrained spectra: inverse FFTs, the clamp to [0, 1], then
    /// the projected steps (kept only if they lower the objective).
    pub fn solve(&self, t: &Unconstrained) -> Result<(Layers, SpectralReport), RenderError> {
        let y0 = &t.y0;
        let mut x: Vec<Vec<f32>> = y0
            .par_iter()
            .map(|s| clamp01(self.fft.inverse(s.clone())))
            .collect();
        let mut report = SpectralReport {
            objective_clamped: f64::NAN,
            objective_final: f64::NAN,
            iterations: 0,
            refined: false,
        };
        if self.params.iterations > 0 {
            let clamped = x.clone();
            x = match self.params.solver {
                SpectralSolver::ProjectedGradient => self.fista(x, y0, &mut report),
                SpectralSolver::Admm { .. } => self.admm(x, y0, &mut report),
            };
            let mut spec: Vec<HalfSpectrum> = x
                .par_iter()
                .map(|v| self.fft.forward(&mut v.clone()))
                .collect();
            let fin = self.frequency_step(&mut spec, y0, Step::Gradient);
            if fin < report.objective_clamped {
                report.objective_final = fin;
                report.refined = true;
            } else {
                report.objective_final = report.objective_clamped;
                x = clamped;
            }
        }
        let layers = self.crop(&x)?;
        Ok((layers, report))
    }

    /// FISTA from the clamped layers `x`: the last iterate (in [0, 1]).
    fn fista(
        &self,
        mut x: Vec<Vec<f32>>,
        y0: &[HalfSpectrum],
        report: &mut SpectralReport,
    ) -> Vec<Vec<f32>> {
        let mut y = x.clone();
        let mut t_k = 1.0f64;
        for it in 0..self.params.iterations {
            let mut spec: Vec<HalfSpectrum> = y
                .into_par_iter()
                .map(|mut v| self.fft.forward(&mut v))
                .collect();
            // y - step A (Y - Y0) in place; the objective at y comes with it.
            let obj = self.frequency_step(&mut spec, y0, Step::Gradient);
            if it == 0 {
                report.objective_clamped = obj;
            }
            let next: Vec<Vec<f32>> = spec
                .into_par_iter()
                .map(|z| clamp01(self.fft.inverse(z)))
                .collect();
            let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t_k * t_k).sqrt());
            let mom = ((t_k - 1.0) / t_next) as f32;
            // y = next + mom (next - x), written over x's buffers.
            y = std::mem::replace(&mut x, next);
            y.par_iter_mut().zip(&x).for_each(|(od, nw)| {
                od.iter_mut()
                    .zip(nw)
                    .for_each(|(o, n)| *o = n + mom * (n - *o));
            });
            t_k = t_next;
            report.iterations = it + 1;
        }
        x
    }

    /// ADMM from the clamped layers `z` (u = 0): x = Y0 + rho (A + rho I)^-1 (z - u - Y0) per
    /// frequency, z = clamp(x + u), u += x - z. Returns the last z (in [0, 1]).
    fn admm(
        &self,
        mut z: Vec<Vec<f32>>,
        y0: &[HalfSpectrum],
        report: &mut SpectralReport,
    ) -> Vec<Vec<f32>> {
        let mut u: Vec<Vec<f32>> = z.iter().map(|v| vec![0.0f32; v.len()]).collect();
        for it in 0..self.params.iterations {
            let mut spec: Vec<HalfSpectrum> = z
                .par_iter()
                .zip(&u)
                .map(|(z, u)| {
                    let mut v: Vec<f32> = z.iter().zip(u).map(|(z, u)| z - u).collect();
                    self.fft.forward(&mut v)
                })
                .collect();
            // The objective at z - u comes with the x-update: at the first step, the clamp's.
            let obj = self.frequency_step(&mut spec, y0, Step::Admm);
            if it == 0 {
                report.objective_clamped = obj;
            }
            let xs: Vec<Vec<f32>> = spec.into_par_iter().map(|s| self.fft.inverse(s)).collect();
            z.par_iter_mut()
                .zip(u.par_iter_mut())
                .zip(&xs)
                .for_each(|((z, u), x)| {
                    for ((z, u), &x) in z.iter_mut().zip(u.iter_mut()).zip(x) {
                        let v = x + *u;
                        *z = v.clamp(0.0, 1.0);
                        *u = v - *z;
                    }
                });
            report.iterations = it + 1;
        }
        z
    }

    /// One step in frequency, in place, for every channel: the gradient step
    /// S <- S - step A (S - Y0), or ADMM's x-update S <- Y0 + rho (A + rho I)^-1 (S - Y0).
    /// Returns the objective at S before the step: (S - Y0)^H A (S - Y0) summed over the
    /// spectrum, per padded pixel (Parseval; the half spectrum's inner columns stand for two).
    fn frequency_step(&self, spec: &mut [HalfSpectrum], y0: &[HalfSpectrum], kind: Step) -> f64 {
        // Memory-bound: frequencies go in chunks whose residuals and gradients (every layer of
        // the three channels) stay in cache, each chunk of A (symmetric: its upper triangle)
        // is read once for the three channels, and every inner loop runs over contiguous
        // slices. (Fusing the step into the column transforms, a few columns of every layer at
        // a time, measured no faster.)
        const CHUNK: usize = 128;
        let (np, n, pw, ph) = (self.planes.len(), self.fft.len(), self.fft.pw, self.fft.ph);
        let rows = spec.len();
        // Jobs of (first frequency, that chunk of every layer).
        let mut jobs: Vec<(usize, Vec<&mut [Complex32]>)> = (0..n.div_ceil(CHUNK))
            .map(|k| (k * CHUNK, Vec::with_capacity(rows)))
            .collect();
        for v in spec.iter_mut() {
            for (job, ch) in jobs.iter_mut().zip(v.chunks_mut(CHUNK)) {
                job.1.push(ch);
            }
        }
        // Parseval's weight: 1 on the half spectrum's own columns (kx = 0, and the Nyquist
        // column of an even width), 2 on the others; column kx holds kx * ph .. (kx + 1) * ph.
        let once_from = if pw.is_multiple_of(2) {
            (self.fft.hw - 1) * ph
        } else {
            n
        };
        let step = self.step;
        let total: f64 = jobs
            .into_par_iter()
            .map(|(f0, mut ls)| {
                let m = ls[0].len();
                let at = |k: usize| k * m..(k + 1) * m;
                let mut d = vec![Complex32::default(); rows * m];
                for (k, l) in ls.iter().enumerate() {
                    for ((d, &l), &y) in d[at(k)].iter_mut().zip(l.iter()).zip(&y0[k][f0..]) {
                        *d = l - y;
                    }
                }
                let mut g = vec![Complex32::default(); rows * m];
                for a in 0..np {
                    for b in a..np {
                        let col = &self.a[(a * np + b) * n + f0..][..m];
                        for c in 0..rows / np {
                            let (ka, kb) = (c * np + a, c * np + b);
                            for ((g, &db), &k) in g[at(ka)].iter_mut().zip(&d[at(kb)]).zip(col) {
                                *g += db * k;
                            }
                            if a != b {
                                for ((g, &da), &k) in g[at(kb)].iter_mut().zip(&d[at(ka)]).zip(col)
                                {
                                    *g += da * k;
                                }
                            }
                        }
                    }
                }
                let mut acc = [0.0f32; CHUNK];
                for (k, l) in ls.iter_mut().enumerate() {
                    for (((l, g), da), acc) in
                        l.iter_mut().zip(&g[at(k)]).zip(&d[at(k)]).zip(&mut acc)
                    {
                        *acc += da.re * g.re + da.im * g.im;
                        if kind == Step::Gradient {
                            *l -= g * step;
                        }
                    }
                }
                if kind == Step::Admm {
                    // S = Y0 + B D, B = rho (A + rho I)^-1 (symmetric: its upper triangle).
                    for (k, l) in ls.iter_mut().enumerate() {
                        l.copy_from_slice(&y0[k][f0..f0 + m]);
                    }
                    for a in 0..np {
                        for b in a..np {
                            let col = &self.admm[(a * np + b) * n + f0..][..m];
                            for c in 0..rows / np {
                                let (ka, kb) = (c * np + a, c * np + b);
                                for ((l, &db), &k) in ls[ka].iter_mut().zip(&d[at(kb)]).zip(col) {
                                    *l += db * k;
                                }
                                if a != b {
                                    for ((l, &da), &k) in ls[kb].iter_mut().zip(&d[at(ka)]).zip(col)
                                    {
                                        *l += da * k;
                                    }
                                }
                            }
                        }
                    }
                }
                acc.iter()
                    .take(m)
                    .enumerate()
                    .map(|(i, &v)| {
                        let f = f0 + i;
                        v as f64 * if f < ph || f >= once_from { 1.0 } else { 2.0 }
                    })
                    .sum::<f64>()
            })
            .sum();
        let npix = (pw * ph) as f64;
        total / (npix * npix)
    }

    fn crop(&self, x: &[Vec<f32>]) -> Result<Layers, RenderError> {
        let (w, h, m, pw) = (self.width, self.height, self.margin, self.fft.pw);
        let np = self.planes.len();
        let plane = |v: &[f32]| -> Result<Plane, RenderError> {
            let mut out = Vec::with_capacity(w * h);
            for y in 0..h {
                let s = (y + m) * pw + m;
                out.extend_from_slice(&v[s..s + w]);
            }
            Ok(Plane::from_vec(w, h, out)?)
        };
        let images = (0..np)
            .map(|a| {
                Ok(RgbImage::from_planes(
                    plane(&x[a])?,
                    plane(&x[np + a])?,
                    plane(&x[2 * np + a])?,
                )?)
            })
            .collect::<Result<Vec<_>, RenderError>>()?;
        Ok(Layers {
            planes: self.planes.clone(),
            images,
        })
    }
}

/// What [`SpectralPlan::frequency_step`] does after the objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    Gradient,
    Admm,
}

fn clamp01(mut v: Vec<f32>) -> Vec<f32> {
    v.iter_mut().for_each(|p| *p = p.clamp(0.0, 1.0));
    v
}

/// Solves `m x = b` for an `n` x `n` symmetric positive definite `m` and `k` right-hand sides
/// (`b` row-major n x k), by Cholesky. A pivot that is not positive (cannot happen for
/// M + lambda I with lambda > 0) gives zeros for that row rather than NaN.
fn cholesky_solve(m: &[f64], b: &[f64], n: usize, k: usize) -> Vec<f64> {
    let mut l = vec![0.0f64; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = m[i * n + j];
            for p in 0..j {
                s -= l[i * n + p] * l[j * n + p];
            }
            if i == j {
                l[i * n + i] = if s > 0.0 { s.sqrt() } else { f64::INFINITY };
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut x = b.to_vec();
    for c in 0..k {
        for i in 0..n {
            let mut s = x[i * k + c];
            for p in 0..i {
                s -= l[i * n + p] * x[p * k + c];
            }
            x[i * k + c] = s / l[i * n + i];
        }
        for i in (0..n).rev() {
            let mut s = x[i * k + c];
            for p in i + 1..n {
                s -= l[p * n + i] * x[p * k + c];
            }
            x[i * k + c] = s / l[i * n + i];
        }
    }
    x
}

/// Plans kept for reuse: a rig renders every frame with the same settings.
static PLANS: Mutex<Vec<Arc<SpectralPlan>>> = Mutex::new(Vec::new());
const PLANS_KEPT: usize = 4;

/// The plan for these settings, from the process's cache or built (and cached) now.
pub fn plan_for(
    eye: &EyeModel,
    planes: &[Diopters],
    width: usize,
    height: usize,
    params: SpectralParams,
) -> Result<Arc<SpectralPlan>, RenderError> {
    if let Ok(list) = PLANS.lock() {
        if let Some(p) = list
            .iter()
            .find(|p| p.fits(eye, planes, width, height, &params))
        {
            return Ok(p.clone());
        }
    }
    let p = Arc::new(SpectralPlan::new(eye, planes, width, height, params)?);
    if let Ok(mut list) = PLANS.lock() {
        if list.len() >= PLANS_KEPT {
            list.remove(0);
        }
        list.push(p.clone());
    }
    Ok(p)
}

/// Spectral decomposition of `input` onto `planes` on the CPU (the CPU backend's
/// [`crate::Backend::spectral_blend`]): the plan built once and reused; a rendered target
/// stack made on the CPU.
pub fn spectral_blend(
    input: &Rgbd,
    planes: &[Diopters],
    eye: &EyeModel,
    params: SpectralParams,
) -> Result<(Layers, SpectralReport), RenderError> {
    crate::common::check_rgbd(input)?;
    check_planes(planes)?;
    params.check()?;
    let s = crate::spectral_coarse::scale_for(
        eye,
        planes,
        input.width(),
        params.scale,
        params.focal_range,
    )?;
    // Every scale solves with `scale: 1`, so that one plan serves them.
    let params = SpectralParams { scale: 1, ..params };
    if s > 1 {
        return crate::spectral_coarse::coarse_blend_with(input, planes, eye, s, |small, e| {
            spectral_blend(small, planes, e, params)
        });
    }
    let plan = plan_for(eye, planes, input.width(), input.height(), params)?;
    let t = match params.targets {
        SpectralTargets::Defocus(m) => {
            let stack = crate::defocus::defocus(input, &params.foci(), eye, m, |_| {})?;
            plan.targets_stack(input, &stack)?
        }
        SpectralTargets::Composite(lp) => {
            let stack = crate::composite::composite_stack(input, &params.foci(), eye, lp)?;
            plan.targets_stack(input, &stack)?
        }
        SpectralTargets::Slices | SpectralTargets::NormalizedSlices => plan.targets_rgbd(input)?,
    };
    plan.solve(&t)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::multifocal::{MultifocalRetina, DEFAULT_PLANES};
    use dioptra_core::DepthMap;

    fn planes() -> Vec<Diopters> {
        DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect()
    }

    /// A 1-degree field over 24 px gives kernels of several pixels, as 20 degrees over 512 does.
    fn eye() -> EyeModel {
        EyeModel {
            fov_horizontal_deg: 1.0,
            ..EyeModel::default()
        }
    }

    /// A textured plane: every pixel differs from its neighbours (also the hybrid's tests').
    pub(crate) fn texture(w: usize, h: usize, k: usize) -> Plane {
        Plane::from_vec(
            w,
            h,
            (0..w * h)
                .map(|i| 0.2 + 0.6 * ((i * k) % 13) as f32 / 13.0)
                .collect(),
        )
        .unwrap()
    }

    /// A textured RGB-D of `depth(x, y)` diopters (also the hybrid's tests').
    pub(crate) fn rgbd(w: usize, h: usize, depth: impl Fn(usize, usize) -> f32) -> Rgbd {
        let c = RgbImage::from_planes(texture(w, h, 7919), texture(w, h, 31), texture(w, h, 5))
            .unwrap();
        let d: Vec<f32> = (0..w * h).map(|i| depth(i % w, i / w)).collect();
        Rgbd::new(
            c,
            DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
        )
        .unwrap()
    }

    fn max_diff(a: &Layers, b: &Layers) -> f32 {
        a.images
            .iter()
            .zip(&b.images)
            .flat_map(|(x, y)| x.channels.iter().zip(&y.channels))
            .flat_map(|(p, q)| p.data().iter().zip(q.data()))
            .map(|(u, v)| (u - v).abs())
            .fold(0.0, f32::max)
    }

    #[test]
    fn nodes_hold_the_planes_and_the_step() {
        let n = depth_nodes(&planes(), 0.3, 4.0);
        for p in DEFAULT_PLANES {
            assert!(n.iter().any(|&x| (x - p).abs() < 1e-6), "{p} not in {n:?}");
        }
        assert_eq!(n[0], 0.0);
        assert!((n.last().unwrap() - 4.0).abs() < 1e-6);
        assert!(
            n.windows(2)
                .all(|w| w[1] > w[0] && w[1] - w[0] <= 0.3 + 1e-5),
            "{n:?}"
        );
        // A plane at 0 D is not doubled.
        let n = depth_nodes(&[Diopters(0.0), Diopters(1.0)], 0.5, 2.0);
        assert_eq!(n.len(), 5, "{n:?}");
        assert_eq!(bracket(&[0.0, 1.0, 2.0], 1.5), (1, 2, 0.5));
        assert_eq!(bracket(&[0.0, 1.0, 2.0], 7.0), (2, 2, 0.0));
    }

    #[test]
    fn content_on_one_plane_stays_there() {
        // Everything at 0.8 D: linear blending's layers (all on that plane) fit the slice
        // stack exactly and are the prior itself, so they are the optimum.
        let (w, h) = (24, 20);
        let input = rgbd(w, h, |_, _| 0.8);
        let params = SpectralParams {
            focal_samples: 8,
            iterations: 0,
            targets: SpectralTargets::Slices,
            scale: 1,
            ..SpectralParams::default()
        };
        let (layers, _) = spectral_blend(&input, &planes(), &eye(), params).unwrap();
        let linear = linear_blend(&input, &planes()).unwrap();
        let d = max_diff(&layers, &linear);
        assert!(d < 2e-3, "max difference from linear blending {d}");
    }

    #[test]
    fn slices_are_the_layered_focal_stack() {
        // The frequency-domain stack from depth slices is the retinal image of a display with
        // a plane at every node showing that node's slice: fitting that stack as given (the
        // stack path) must give the same layers as the slice path.
        let (w, h) = (24, 20);
        let input = rgbd(w, h, |x, y| if x + y < 20 { 0.3 } else { 1.7 });
        let eye = eye();
        // A firm prior: the ill-conditioned low frequencies would amplify the border's
        // difference between the two paths.
        let params = SpectralParams {
            focal_samples: 6,
            iterations: 0,
            prior: 0.05,
            targets: SpectralTargets::Slices,
            scale: 1,
            ..SpectralParams::default()
        };
        let plan = SpectralPlan::new(&eye, &planes(), w, h, params).unwrap();
        let nodes: Vec<Diopters> = plan.nodes().iter().map(|&x| Diopters(x)).collect();
        let slices = linear_blend(&input, &nodes).unwrap();
        let foci = params.foci();
        let r = MultifocalRetina::new(&slices, &eye, (foci[0], foci[5])).unwrap();
        let stack: Vec<RgbImage> = foci.iter().map(|&q| r.render(q).unwrap()).collect();
        let (a, _) = plan.solve(&plan.targets_rgbd(&input).unwrap()).unwrap();
        let (b, _) = plan
            .solve(&plan.targets_stack(&input, &stack).unwrap())
            .unwrap();
        // The stack path sees the stack cropped and edge-replicated again, so the two differ
        // near the border; what the eye sees of them must agree.
        let (ra, rb) = (
            MultifocalRetina::new(&a, &eye, (foci[0], foci[5])).unwrap(),
            MultifocalRetina::new(&b, &eye, (foci[0], foci[5])).unwrap(),
        );
        for &q in &foci {
            let p =
                crate::metrics::psnr(&ra.render(q).unwrap(), &rb.render(q).unwrap(), None).unwrap();
            assert!(p > 40.0, "focus {q}: slice and stack paths {p} dB apart");
        }
    }

    #[test]
    fn recovers_layers_a_display_showed() {
        // Targets made by a display (retinal images of known layers in [0.2, 0.8]) are fitted
        // almost exactly: the retinal images of the result match at every focus.
        let (w, h) = (24, 20);
        let eye = eye();
        let pl = [Diopters(0.2), Diopters(1.4)];
        let truth = Layers {
            planes: pl.to_vec(),
            images: vec![
                RgbImage::from_planes(texture(w, h, 3), texture(w, h, 11), texture(w, h, 17))
                    .unwrap(),
                RgbImage::from_planes(texture(w, h, 7), texture(w, h, 5), texture(w, h, 2))
                    .unwrap(),
            ],
        };
        let params = SpectralParams {
            focal_samples: 8,
            prior: 0.01,
            iterations: 20,
            ..SpectralParams::default()
        };
        let foci = params.foci();
        let r = MultifocalRetina::new(&truth, &eye, (foci[0], foci[7])).unwrap();
        let stack: Vec<RgbImage> = foci.iter().map(|&q| r.render(q).unwrap()).collect();
        // The prior's layers: anything (here a flat grey scene at 0.2 D).
        let input = rgbd(w, h, |_, _| 0.2);
        let plan = SpectralPlan::new(&eye, &pl, w, h, params).unwrap();
        let (got, rep) = plan
            .solve(&plan.targets_stack(&input, &stack).unwrap())
            .unwrap();
        assert!(rep.refined, "{rep:?}");
        let seen = MultifocalRetina::new(&got, &eye, (foci[0], foci[7])).unwrap();
        for &q in &[foci[1], foci[4], foci[7]] {
            let p = crate::metrics::psnr(&seen.render(q).unwrap(), &r.render(q).unwrap(), None)
                .unwrap();
            assert!(p > 45.0, "focus {q}: {p} dB");
        }
    }

    #[test]
    fn steps_never_raise_the_objective() {
        let (w, h) = (32, 24);
        let input = rgbd(w, h, |x, _| if x < 12 { 2.5 } else { 0.3 });
        for solver in [
            SpectralSolver::ProjectedGradient,
            SpectralSolver::Admm { rho: 0.3 },
        ] {
            let params = SpectralParams {
                focal_samples: 8,
                iterations: 8,
                prior: 0.002,
                targets: SpectralTargets::Slices,
                scale: 1,
                solver,
                ..SpectralParams::default()
            };
            let (layers, rep) = spectral_blend(&input, &planes(), &eye(), params).unwrap();
            assert_eq!(rep.iterations, 8);
            assert!(
                rep.objective_final <= rep.objective_clamped,
                "{solver:?}: {rep:?}"
            );
            assert!(rep.objective_final.is_finite());
            assert!(layers
                .images
                .iter()
                .flat_map(|i| i.channels.iter())
                .flat_map(|p| p.data())
                .all(|v| (0.0..=1.0).contains(v)));
        }
    }

    #[test]
    fn admm_gets_further_than_projected_gradient_in_as_many_steps() {
        // Why ADMM is the default: the projected gradient's global step (1 / the largest
        // eigenvalue) leaves the frequencies whose matrices are near the prior's lambda I
        // almost unmoved, ADMM's x-update solves every frequency exactly. Same objective, same
        // start (the clamp), the same FFTs per step. (After a single step the projected
        // gradient can be ahead: ADMM's first z is the clamp of an unconstrained solve.)
        let (w, h) = (40, 32);
        let input = rgbd(
            w,
            h,
            |x, y| if (x / 8 + y / 8) % 2 == 0 { 2.1 } else { 0.2 },
        );
        let run = |solver, iterations| {
            let params = SpectralParams {
                iterations,
                solver,
                targets: SpectralTargets::Slices,
                scale: 1,
                ..SpectralParams::default()
            };
            spectral_blend(&input, &planes(), &eye(), params).unwrap().1
        };
        let admm = SpectralSolver::Admm { rho: 0.3 };
        for steps in [3, 5, 8] {
            let (pg, ad) = (
                run(SpectralSolver::ProjectedGradient, steps),
                run(admm, steps),
            );
            assert_eq!(pg.objective_clamped, ad.objective_clamped);
            assert!(
                ad.objective_final < pg.objective_final,
                "{steps} steps: ADMM {ad:?} vs projected gradient {pg:?}"
            );
        }
        // And it converges: more steps, a lower objective.
        assert!(run(admm, 12).objective_final < run(admm, 3).objective_final);
    }

    #[test]
    fn the_default_coarsens_only_where_the_blur_is_wide() {
        // Kernels of a pixel or two (20 degrees over 64 px): the default solves the image's
        // own grid, the same layers as `scale: 1`.
        let input = rgbd(64, 48, |x, _| if x < 30 { 2.1 } else { 0.4 });
        let wide = EyeModel::default();
        let d = SpectralParams::default();
        assert_eq!(
            crate::spectral_coarse::scale_for(&wide, &planes(), 64, d.scale, d.focal_range)
                .unwrap(),
            1
        );
        let full = SpectralParams { scale: 1, ..d };
        let (a, ra) = spectral_blend(&input, &planes(), &wide, d).unwrap();
        let (b, rb) = spectral_blend(&input, &planes(), &wide, full).unwrap();
        assert_eq!(a, b);
        assert_eq!(ra, rb);
        // Kernels up to about 11 px (a panel's pitch): a 1/2 grid plus linear blending's
        // detail, which what the eye sees keeps near full spectral's, nearer than linear
        // blending's at every focal sample (measured 26.3 to 36.6 dB, mean 32.9; linear
        // 22.2 to 33.2, at least 3.4 dB further).
        let (w, h) = (128, 128);
        let input = rgbd(w, h, |x, y| if (x + 2 * y) % 48 < 24 { 1.9 } else { 0.3 });
        let e = EyeModel {
            fov_horizontal_deg: 4.0,
            ..EyeModel::default()
        };
        let quick = SpectralParams {
            targets: SpectralTargets::Defocus(crate::DefocusMethod::Gather),
            ..d
        };
        assert_eq!(
            crate::spectral_coarse::scale_for(&e, &planes(), w, d.scale, d.focal_range).unwrap(),
            2
        );
        let (coarse, _) = spectral_blend(&input, &planes(), &e, quick).unwrap();
        let (full, _) =
            spectral_blend(&input, &planes(), &e, SpectralParams { scale: 1, ..quick }).unwrap();
        let lin = linear_blend(&input, &planes()).unwrap();
        let foci = d.foci();
        let range = (foci[0], foci[foci.len() - 1]);
        let seen = |l: &Layers| MultifocalRetina::new(l, &e, range).unwrap();
        let (sc, sf, sl) = (seen(&coarse), seen(&full), seen(&lin));
        let mut sum = 0.0;
        for &q in &foci {
            let truth = sf.render(q).unwrap();
            let c = crate::metrics::psnr(&sc.render(q).unwrap(), &truth, None).unwrap();
            let l = crate::metrics::psnr(&sl.render(q).unwrap(), &truth, None).unwrap();
            eprintln!("focus {q}: coarse {c:.2} dB, linear {l:.2} dB from full spectral");
            assert!(c > l + 2.0, "focus {q}: coarse {c} dB, linear {l} dB");
            sum += c;
        }
        let mean = sum / foci.len() as f64;
        assert!(mean > 30.0, "coarse {mean} dB from full spectral, mean");
    }

    #[test]
    fn bad_settings_are_refused() {
        let input = rgbd(8, 8, |_, _| 1.0);
        let e = eye();
        for p in [
            SpectralParams {
                prior: 0.0,
                ..SpectralParams::default()
            },
            SpectralParams {
                focal_samples: 0,
                ..SpectralParams::default()
            },
            SpectralParams {
                slice_step: f32::NAN,
                ..SpectralParams::default()
            },
            SpectralParams {
                focal_range: (2.0, 1.0),
                ..SpectralParams::default()
            },
            SpectralParams {
                solver: SpectralSolver::Admm { rho: 0.0 },
                ..SpectralParams::default()
            },
            SpectralParams {
                solver: SpectralSolver::Admm { rho: f32::NAN },
                ..SpectralParams::default()
            },
            SpectralParams {
                scale: crate::spectral_coarse::MAX_SCALE + 1,
                ..SpectralParams::default()
            },
        ] {
            assert!(spectral_blend(&input, &planes(), &e, p).is_err(), "{p:?}");
        }
        let plan = SpectralPlan::new(&e, &planes(), 8, 8, SpectralParams::default()).unwrap();
        assert!(plan.targets_rgbd(&rgbd(9, 8, |_, _| 1.0)).is_err());
        assert!(plan
            .targets_stack(&input, &[RgbImage::new(8, 8, [0.5; 3])])
            .is_err());
    }
}
