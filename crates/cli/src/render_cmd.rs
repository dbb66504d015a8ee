//! `dioptra render | focalstack | decompose | retina | metrics`: the optics methods on files.

use crate::common::progress::bar;
use crate::common::slice_name;
use anyhow::{bail, Context, Result};
use clap::Args;
use dioptra_core::{Diopters, EyeModel, Millimeters, Plane, RgbImage, Rgbd};
use dioptra_net::gpu::{load_gpu_net, GpuNet};
use dioptra_net::refine::classical_defocus;
use dioptra_net::Task;
use dioptra_render::gpu::list_adapters;
use dioptra_render::io::{read_color, read_depth, write_color, DepthUnits};
use dioptra_render::metrics::quality;
use dioptra_render::multifocal::{linspace, Layers};
use dioptra_render::retina::LfView;
use dioptra_render::spectral::SpectralTargets;
use dioptra_render::{
    backend_on, Backend, DefocusMethod, LightFieldParams, OptimizeParams, SpectralParams,
};
use std::path::{Path, PathBuf};

/// Eye model and backend options shared by the optics commands.
#[derive(Args, Debug, Clone)]
pub struct EyeArgs {
    /// Horizontal field of view of the image, degrees.
    #[arg(long, default_value_t = 20.0)]
    pub fov_deg: f32,
    /// Pupil diameter, millimetres.
    #[arg(long, default_value_t = 4.0)]
    pub pupil_mm: f32,
    /// Compute backend: cpu or gpu. Default: gpu when a hardware GPU adapter exists, else cpu.
    #[arg(long)]
    pub backend: Option<String>,
    /// GPU adapter to use (part of its name, e.g. "nvidia" or "llvmpipe"); implies --backend gpu.
    #[arg(long)]
    pub adapter: Option<String>,
}

impl EyeArgs {
    pub fn eye(&self) -> Result<EyeModel> {
        let eye = EyeModel {
            pupil_diameter: Millimeters(self.pupil_mm),
            fov_horizontal_deg: self.fov_deg,
            ..EyeModel::default()
        };
        Ok(eye.validated()?)
    }
    /// The backend the render commands run on (see `--backend`).
    fn backend(&self) -> Result<Box<dyn Backend>> {
        choose_backend(self.backend.as_deref(), self.adapter.as_deref())
    }

    /// The backend for commands outside the render group: cpu unless asked for.
    fn backend_or_cpu(&self) -> Result<Box<dyn Backend>> {
        match (&self.backend, &self.adapter) {
            (None, None) => Ok(backend_on("cpu", None)?),
            _ => self.backend(),
        }
    }
}

/// `--backend NAME` / `--adapter NAME`: without either, gpu when a hardware adapter exists,
/// else cpu (said on stderr when only a software adapter is there).
fn choose_backend(backend: Option<&str>, adapter: Option<&str>) -> Result<Box<dyn Backend>> {
    let name = match (backend, adapter) {
        (Some(b), _) => b,
        (None, Some(_)) => "gpu",
        (None, None) => {
            let adapters = list_adapters();
            if adapters.iter().any(|a| !a.software) {
                "gpu"
            } else {
                if let Some(sw) = adapters.first() {
                    eprintln!(
                        "dioptra: only a software GPU adapter ({}); rendering on the CPU (--backend gpu uses it anyway)",
                        sw.name
                    );
                }
                "cpu"
            }
        }
    };
    if name == "cpu" && adapter.is_some() {
        bail!("--adapter selects a GPU adapter: it needs --backend gpu, not cpu");
    }
    Ok(backend_on(name, adapter)?)
}

/// An RGB-D input.
#[derive(Args, Debug, Clone)]
pub struct InputArgs {
    /// Colour image: PNG (8/16-bit sRGB) or EXR/PFM (linear).
    #[arg(long)]
    pub color: PathBuf,
    /// Depth: EXR/PFM in metres or 16-bit PNG in millimetres.
    #[arg(long)]
    pub depth: PathBuf,
    /// Override the depth file's units: m, mm or D.
    #[arg(long)]
    pub depth_units: Option<String>,
    /// Refuse images whose header claims more pixels than this (before reading them).
    #[arg(long, default_value_t = dioptra_render::io::DEFAULT_MAX_PIXELS)]
    pub max_pixels: u64,
}

impl InputArgs {
    fn load(&self) -> Result<Rgbd> {
        let color = dioptra_render::io::read_color_limited(&self.color, self.max_pixels)?;
        let units = self
            .depth_units
            .as_deref()
            .map(str::parse::<DepthUnits>)
            .transpose()?;
        let depth = dioptra_render::io::read_depth_limited(&self.depth, units, self.max_pixels)?;
        Rgbd::new(color, depth).with_context(|| {
            format!(
                "{} and {} must be the same size",
                self.color.display(),
                self.depth.display()
            )
        })
    }
}

/// Defocus method options.
#[derive(Args, Debug, Clone)]
pub struct MethodArgs {
    /// gather (single-image CoC blur), pyramid (gather's sums, large blurs spread at the resolution they leave: bounded cost), lightfield (Yu et al. 2010), network (DeepFocus C1) or
    /// refine (C1R: the classical render its weights name, corrected by a small net on the
    /// tiles near depth discontinuities).
    #[arg(long, default_value = "lightfield")]
    pub method: String,
    /// Network weights for --method network or refine (default: the shipped ones).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Virtual lens cameras for the lightfield method.
    #[arg(long, default_value_t = 36)]
    pub views: usize,
}

impl MethodArgs {
    fn method(&self) -> Result<DefocusMethod> {
        Ok(match self.method.parse::<DefocusMethod>()? {
            DefocusMethod::LightField(_) => DefocusMethod::LightField(LightFieldParams {
                views: self.views,
                mip: true,
            }),
            m => m,
        })
    }
}

fn parse_list(s: &str) -> Result<Vec<f32>> {
    s.split(',')
        .map(|v| {
            v.trim()
                .parse::<f32>()
                .with_context(|| format!("{v:?} in {s:?} is not a number"))
        })
        .collect()
}

fn parse_range(s: &str) -> Result<(f32, f32)> {
    match parse_list(s)?[..] {
        [a, b] => Ok((a, b)),
        _ => bail!("range {s:?} must be two numbers, e.g. 0.1,4.0"),
    }
}

fn ensure_dir(p: &Path) -> Result<()> {
    std::fs::create_dir_all(p).with_context(|| format!("cannot create directory {}", p.display()))
}

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    input: InputArgs,
    /// Focus distance, diopters.
    #[arg(long)]
    focus: f32,
    #[command(flatten)]
    method: MethodArgs,
    #[command(flatten)]
    eye: EyeArgs,
    /// Output image: .png (8-bit sRGB), .exr or .pfm (linear).
    #[arg(long)]
    out: PathBuf,
}

pub fn render(a: RenderArgs) -> Result<()> {
    let input = a.input.load()?;
    let b = a.eye.backend()?;
    let t = std::time::Instant::now();
    let mut note = String::new();
    let out = if a.method.method == "network" {
        let (weights, eye) = (a.method.weights.as_deref(), a.eye.eye()?);
        if b.name() == "gpu" {
            let net = load_gpu_net(weights, "c1", a.eye.adapter.as_deref())?;
            vec![net.defocus(&input, Diopters(a.focus), &eye)?]
        } else {
            let net = dioptra_net::load_net(weights, "c1")?;
            vec![net.defocus(&input, Diopters(a.focus), &eye)?]
        }
    } else if a.method.method == "refine" {
        let (weights, eye, q) = (a.method.weights.as_deref(), a.eye.eye()?, Diopters(a.focus));
        let net = dioptra_net::load_net(weights, "c1r")?;
        let Task::C1r { classical } = net.arch().task else {
            bail!("the c1r weights name no classical method");
        };
        let base = classical_defocus(b.as_ref(), classical, &input, q, &eye)?;
        let r = if b.name() == "gpu" {
            GpuNet::on(
                dioptra_render::gpu::GpuContext::shared(a.eye.adapter.as_deref())?,
                net.weights().clone(),
            )?
            .refine_defocus(&input, &base, q, &eye)?
        } else {
            net.refine_defocus(&input, &base, q, &eye)?
        };
        note = format!(
            "; {} refined on {:.0} % of the tiles",
            classical.label(),
            100.0 * r.tiles.fraction()
        );
        vec![r.image]
    } else {
        b.defocus(
            &input,
            &[Diopters(a.focus)],
            &a.eye.eye()?,
            a.method.method()?,
            &|_| {},
        )?
    };
    let img = out
        .into_iter()
        .next()
        .context("the backend returned no image")?;
    write_color(&a.out, &img)?;
    println!(
        "wrote {} ({:.0} ms{note})",
        a.out.display(),
        t.elapsed().as_secs_f64() * 1e3
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct FocalStackArgs {
    #[command(flatten)]
    input: InputArgs,
    /// Number of slices.
    #[arg(long, default_value_t = 40)]
    slices: usize,
    /// Focus range, diopters: near,far as lo,hi.
    #[arg(long, default_value = "0.1,4.0")]
    range: String,
    #[command(flatten)]
    method: MethodArgs,
    #[command(flatten)]
    eye: EyeArgs,
    /// Output directory (one focus_<q>D.<ext> per slice).
    #[arg(long)]
    out: PathBuf,
    /// Slice file type: png or exr.
    #[arg(long, default_value = "png")]
    ext: String,
}

pub fn focalstack(a: FocalStackArgs) -> Result<()> {
    let input = a.input.load()?;
    let (lo, hi) = parse_range(&a.range)?;
    if a.slices == 0 || a.slices > 1000 {
        bail!("--slices must be 1 to 1000");
    }
    let foci = linspace(lo, hi, a.slices);
    let b = a.eye.backend()?;
    let pb = bar(foci.len(), "focal stack")?;
    let stack = b.defocus(&input, &foci, &a.eye.eye()?, a.method.method()?, &|n| {
        pb.set_position(n as u64)
    })?;
    pb.finish();
    ensure_dir(&a.out)?;
    for (q, img) in foci.iter().zip(&stack) {
        write_color(&a.out.join(slice_name(*q, &a.ext)), img)?;
    }
    println!("wrote {} slices to {}", stack.len(), a.out.display());
    Ok(())
}

#[derive(Args, Debug)]
pub struct DecomposeArgs {
    #[command(flatten)]
    input: InputArgs,
    /// Display planes, diopters.
    #[arg(long, default_value = "0.2,0.8,1.4,2.0")]
    planes: String,
    /// linear (Akeley), optimized (Narain), spectral (the per-frequency least squares, after
    /// Mercier et al. 2017: real time), hybrid (spectral in a window around --gaze when a
    /// blurred depth step reaches the fovea, linear blending elsewhere, after Yu et al. 2019;
    /// the spectral options apply to its window), network (DeepFocus C4; its planes are fixed)
    /// or refine (C4R: linear blending corrected by a small net; its planes are fixed).
    #[arg(long, default_value = "optimized")]
    method: String,
    /// Hybrid: the gaze point, pixels "X,Y" (default: the image centre).
    #[arg(long)]
    gaze: Option<String>,
    /// Network weights for --method network or refine (default: the shipped ones).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Optimized and spectral: focal samples of the target focal stack (default 22 for
    /// optimized, the spectral default otherwise).
    #[arg(long)]
    focal_samples: Option<usize>,
    /// Optimized and spectral: range of the focal samples, diopters.
    #[arg(long, default_value = "0.1,2.2")]
    focal_range: String,
    /// Optimized and spectral: directory of target slices named focus_<q>D.<png|exr> (e.g.
    /// from `dioptra sim scene` or `dioptra focalstack`); without it the targets are rendered
    /// with --target-method.
    #[arg(long)]
    targets: Option<PathBuf>,
    /// Optimized and spectral: what renders the targets when --targets is absent: gather or
    /// lightfield; spectral also takes composite (the light field only where a blurred depth
    /// step reaches, the exact disk blur of smooth depth elsewhere), slices or
    /// normalized-slices (a focal stack built in the frequency domain from depth slices).
    /// Default: lightfield for optimized, the spectral default for spectral.
    #[arg(long)]
    target_method: Option<String>,
    /// Optimized and spectral: lightfield views for the targets (default 36 for optimized,
    /// the spectral default otherwise).
    #[arg(long)]
    target_views: Option<usize>,
    /// Optimized: iterations (default 100); spectral: projected steps after the clamp
    /// (default: the spectral default).
    #[arg(long)]
    iterations: Option<usize>,
    /// Spectral: weight of the prior toward linear blending, per focal sample.
    #[arg(long)]
    prior: Option<f32>,
    /// Spectral: the grid it solves on. 1: the image's own pixels (full resolution); s > 1: a
    /// grid s times coarser plus linear blending's detail above it; 0 (default): chosen from
    /// the widest blur (full resolution while it is under 10 px, 1/4 at 960 x 1080 over 20
    /// degrees).
    #[arg(long)]
    scale: Option<usize>,
    #[command(flatten)]
    eye: EyeArgs,
    /// Output directory: layer_<p>D.<ext> per plane.
    #[arg(long)]
    out: PathBuf,
    /// Layer file type: exr (exact) or png (8-bit sRGB).
    #[arg(long, default_value = "exr")]
    ext: String,
}

/// Finds `focus_<q>D.png` or `.exr` in `dir`.
fn find_slice(dir: &Path, q: Diopters) -> Result<PathBuf> {
    for ext in ["exr", "png", "pfm"] {
        let p = dir.join(slice_name(q, ext));
        if p.exists() {
            return Ok(p);
        }
    }
    bail!(
        "{} has no slice for {:.2} D (expected {})",
        dir.display(),
        q.0,
        slice_name(q, "png|exr")
    )
}

/// The target slices at `foci` from `dir`, each the input's size.
fn read_targets(dir: &Path, foci: &[Diopters], input: &Rgbd) -> Result<Vec<RgbImage>> {
    let t = foci
        .iter()
        .map(|&q| Ok(read_color(&find_slice(dir, q)?)?))
        .collect::<Result<Vec<_>>>()?;
    if let Some(bad) = t
        .iter()
        .find(|i| (i.width(), i.height()) != (input.width(), input.height()))
    {
        bail!(
            "target slices are {}x{} but the input is {}x{}",
            bad.width(),
            bad.height(),
            input.width(),
            input.height()
        );
    }
    Ok(t)
}

impl DecomposeArgs {
    /// The spectral decomposition's settings: its defaults, with what was given.
    fn spectral_params(&self) -> Result<SpectralParams> {
        let d = SpectralParams::default();
        let views = self.target_views.unwrap_or(match d.targets {
            SpectralTargets::Defocus(DefocusMethod::LightField(l))
            | SpectralTargets::Composite(l) => l.views,
            _ => 12,
        });
        let targets = match self.target_method.as_deref() {
            None => match d.targets {
                SpectralTargets::Defocus(DefocusMethod::LightField(l)) => {
                    SpectralTargets::Defocus(DefocusMethod::LightField(LightFieldParams {
                        views,
                        ..l
                    }))
                }
                SpectralTargets::Composite(l) => {
                    SpectralTargets::Composite(LightFieldParams { views, ..l })
                }
                t => t,
            },
            Some("slices") => SpectralTargets::Slices,
            Some("normalized-slices") => SpectralTargets::NormalizedSlices,
            Some("composite") => SpectralTargets::Composite(LightFieldParams { views, mip: true }),
            Some(m) => {
                SpectralTargets::Defocus(
                    MethodArgs {
                        method: m.to_string(),
                        views,
                        weights: None,
                    }
                    .method()
                    .context(
                        "--target-method: expected gather, lightfield, composite, slices or normalized-slices",
                    )?,
                )
            }
        };
        let p = SpectralParams {
            focal_samples: self.focal_samples.unwrap_or(d.focal_samples),
            focal_range: parse_range(&self.focal_range)?,
            prior: self.prior.unwrap_or(d.prior),
            iterations: self.iterations.unwrap_or(d.iterations),
            targets,
            scale: self.scale.unwrap_or(d.scale),
            ..d
        };
        if p.scale > dioptra_render::spectral_coarse::MAX_SCALE {
            bail!(
                "--scale {}: expected 0 (chosen from the blur), 1 (full resolution) to {}",
                p.scale,
                dioptra_render::spectral_coarse::MAX_SCALE
            );
        }
        p.check()?;
        Ok(p)
    }
}

pub fn layer_name(p: Diopters, ext: &str) -> String {
    format!("layer_{:.2}D.{ext}", p.0)
}

pub fn decompose(a: DecomposeArgs) -> Result<()> {
    let input = a.input.load()?;
    let planes: Vec<Diopters> = parse_list(&a.planes)?.into_iter().map(Diopters).collect();
    let eye = a.eye.eye()?;
    let b = a.eye.backend()?;
    let linear = b.linear_blend(&input, &planes)?;
    let layers = match a.method.as_str() {
        "linear" => linear,
        "hybrid" => {
            if a.targets.is_some() {
                bail!("--targets applies to --method spectral or optimized, not hybrid");
            }
            let gaze = match a.gaze.as_deref() {
                Some(g) => match parse_list(g)?[..] {
                    [x, y] => Some([x, y]),
                    _ => bail!("--gaze {g:?}: expected X,Y in pixels"),
                },
                None => None,
            };
            let params = dioptra_render::hybrid::HybridParams {
                spectral: a.spectral_params()?,
                ..Default::default()
            };
            let (layers, rep) = b.hybrid_blend(&input, &planes, &eye, gaze, &params)?;
            match rep.window {
                Some(w) => println!(
                    "hybrid decomposition on the {}: spectral in {}x{} px at ({}, {}), solved at 1/{}, around the gaze ({:.0}, {:.0})",
                    b.name(),
                    w.width,
                    w.height,
                    w.x0,
                    w.y0,
                    w.scale,
                    rep.gaze[0],
                    rep.gaze[1]
                ),
                None => println!(
                    "hybrid decomposition: no blurred depth step reaches the fovea around ({:.0}, {:.0}): linear blending",
                    rep.gaze[0], rep.gaze[1]
                ),
            }
            layers
        }
        "network" => {
            let l = if b.name() == "gpu" {
                load_gpu_net(a.weights.as_deref(), "c4", a.eye.adapter.as_deref())?
                    .decompose(&input)?
            } else {
                dioptra_net::load_net(a.weights.as_deref(), "c4")?.decompose(&input)?
            };
            if l.planes != planes {
                bail!(
                    "the network's planes are {:?}; pass --planes to match",
                    l.planes
                );
            }
            l
        }
        "refine" => {
            let net = dioptra_net::load_net(a.weights.as_deref(), "c4r")?;
            let (theirs, classical) = dioptra_net::refine::c4r_input(&net.arch().task)?;
            if theirs != planes {
                bail!("the network's planes are {theirs:?}; pass --planes to match");
            }
            // The classical layers the weights name, on the chosen backend.
            let base = dioptra_net::refine::classical_layers(
                b.as_ref(),
                classical,
                &input,
                &planes,
                &eye,
            )?;
            println!("refining {} layers", classical.label());
            if b.name() == "gpu" {
                GpuNet::on(
                    dioptra_render::gpu::GpuContext::shared(a.eye.adapter.as_deref())?,
                    net.weights().clone(),
                )?
                .refine_decompose(&input, &base)?
            } else {
                net.refine_decompose(&input, &base)?
            }
        }
        "spectral" => {
            let params = a.spectral_params()?;
            let foci = params.foci();
            // Given target stacks are solved at their own resolution.
            let grid = match &a.targets {
                Some(_) => 1,
                None => dioptra_render::spectral_coarse::scale_for(
                    &eye,
                    &planes,
                    input.width(),
                    params.scale,
                    params.focal_range,
                )?,
            };
            let (layers, rep) = match &a.targets {
                Some(dir) => {
                    let stack = read_targets(dir, &foci, &input)?;
                    if b.name() == "gpu" {
                        dioptra_render::Gpu::new(a.eye.adapter.as_deref())?
                            .spectral_blend_stack(&input, &stack, &planes, &eye, params)?
                    } else {
                        let plan = dioptra_render::spectral::plan_for(
                            &eye,
                            &planes,
                            input.width(),
                            input.height(),
                            params,
                        )?;
                        plan.solve(&plan.targets_stack(&input, &stack)?)?
                    }
                }
                None => b.spectral_blend(&input, &planes, &eye, params)?,
            };
            println!(
                "spectral decomposition on the {}: {}, {} focal samples, {} projected steps{}",
                b.name(),
                if grid == 1 {
                    "full resolution".to_string()
                } else {
                    format!("solved on a 1/{grid} grid plus linear blending's detail (--scale 1 for full resolution)")
                },
                params.focal_samples,
                rep.iterations,
                if rep.iterations == 0 {
                    String::new()
                } else if rep.refined {
                    format!(
                        " (objective {:.3e} -> {:.3e})",
                        rep.objective_clamped, rep.objective_final
                    )
                } else {
                    " (not kept: they did not lower the objective)".into()
                }
            );
            layers
        }
        "optimized" => {
            let (lo, hi) = parse_range(&a.focal_range)?;
            let samples = a.focal_samples.unwrap_or(22);
            if samples == 0 || samples > 200 {
                bail!("--focal-samples must be 1 to 200");
            }
            let foci = linspace(lo, hi, samples);
            let targets = match &a.targets {
                Some(dir) => read_targets(dir, &foci, &input)?,
                None => {
                    let pb = bar(foci.len(), "targets")?;
                    let t = b.defocus(
                        &input,
                        &foci,
                        &eye,
                        MethodArgs {
                            method: a
                                .target_method
                                .clone()
                                .unwrap_or_else(|| "lightfield".into()),
                            views: a.target_views.unwrap_or(36),
                            weights: None,
                        }
                        .method()?,
                        &|n| pb.set_position(n as u64),
                    )?;
                    pb.finish();
                    t
                }
            };
            let iterations = a.iterations.unwrap_or(100);
            let pb = bar(iterations, "optimizing")?;
            let params = OptimizeParams {
                iterations,
                tolerance: 0.0,
            };
            let (layers, rep) = b.optimized_blend(
                &targets,
                &foci,
                &planes,
                &eye,
                Some(&linear),
                params,
                &|n| pb.set_position(n as u64),
            )?;
            pb.finish();
            let trace: Vec<String> = rep.rms.iter().map(|(i, r)| format!("{i}:{r:.5}")).collect();
            println!(
                "optimized blending: {} iterations; rms retinal error by iteration {}",
                rep.iterations,
                trace.join(" ")
            );
            layers
        }
        m => bail!(
            "unknown decomposition method {m:?}: expected linear, optimized, spectral, hybrid, network or refine"
        ),
    };
    ensure_dir(&a.out)?;
    for (p, img) in layers.planes.iter().zip(&layers.images) {
        write_color(&a.out.join(layer_name(*p, &a.ext)), img)?;
    }
    println!(
        "wrote {} layers to {}",
        layers.images.len(),
        a.out.display()
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct RetinaArgs {
    /// Where the eye focuses, diopters.
    #[arg(long)]
    focus: f32,
    /// Multifocal: directory of layer_<p>D.<ext> files (from `dioptra decompose`).
    #[arg(long, conflicts_with_all = ["image", "lightfield"])]
    layers: Option<PathBuf>,
    /// Multifocal: the display planes, diopters.
    #[arg(long, default_value = "0.2,0.8,1.4,2.0")]
    planes: String,
    /// Varifocal: the image the display shows.
    #[arg(long, conflicts_with = "lightfield")]
    image: Option<PathBuf>,
    /// Varifocal: where the display's image lies, diopters.
    #[arg(long, default_value_t = 1.0)]
    display: f32,
    /// Light field: directory of view_<row>_<col>.png views on a square grid (from `dioptra sim scene`).
    #[arg(long)]
    lightfield: Option<PathBuf>,
    /// Light field: side of the square the views span, metres.
    #[arg(long, default_value_t = 0.01)]
    span: f32,
    #[command(flatten)]
    eye: EyeArgs,
    #[arg(long)]
    out: PathBuf,
}

/// Reads view_<r>_<c>.<png|exr> files of a square grid from `dir`.
pub fn read_light_field(dir: &Path, span: f32) -> Result<(Vec<LfView>, f32)> {
    let mut n = 0;
    while dir.join(format!("view_{:02}_{:02}.png", 0, n)).exists()
        || dir.join(format!("view_{:02}_{:02}.exr", 0, n)).exists()
    {
        n += 1;
    }
    if n == 0 {
        bail!("{} has no view_00_00.png or .exr", dir.display());
    }
    let step = if n > 1 {
        span / (n - 1) as f32
    } else {
        span.max(1e-6)
    };
    let mut views = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            let png = dir.join(format!("view_{r:02}_{c:02}.png"));
            let path = if png.exists() {
                png
            } else {
                dir.join(format!("view_{r:02}_{c:02}.exr"))
            };
            let half = (n - 1) as f32 * 0.5;
            views.push(LfView {
                position: [(c as f32 - half) * step, (r as f32 - half) * step],
                image: read_color(&path)?,
            });
        }
    }
    Ok((views, step))
}

pub fn retina(a: RetinaArgs) -> Result<()> {
    let eye = a.eye.eye()?;
    let b = a.eye.backend()?;
    let q = Diopters(a.focus);
    let img = if let Some(dir) = &a.layers {
        let planes: Vec<Diopters> = parse_list(&a.planes)?.into_iter().map(Diopters).collect();
        let images = planes
            .iter()
            .map(|&p| {
                let exr = dir.join(layer_name(p, "exr"));
                let path = if exr.exists() {
                    exr
                } else {
                    dir.join(layer_name(p, "png"))
                };
                Ok(read_color(&path)?)
            })
            .collect::<Result<Vec<RgbImage>>>()?;
        b.retina_multifocal(&Layers { planes, images }, &[q], &eye)?
            .remove(0)
    } else if let Some(path) = &a.image {
        b.retina_varifocal(&read_color(path)?, Diopters(a.display), q, &eye)?
    } else if let Some(dir) = &a.lightfield {
        let (views, step) = read_light_field(dir, a.span)?;
        b.retina_lightfield(&views, step, q, &eye)?
    } else {
        bail!(
            "give one of --layers DIR (multifocal), --image FILE (varifocal) or --lightfield DIR"
        );
    };
    write_color(&a.out, &img)?;
    println!("wrote {}", a.out.display());
    Ok(())
}

#[derive(Args, Debug)]
pub struct MetricsArgs {
    /// First image.
    #[arg(long)]
    a: PathBuf,
    /// Second image (same size).
    #[arg(long)]
    b: PathBuf,
    /// Optional mask image: pixels brighter than half are compared.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Also report each foveal region (fovea, periphery 1 and 2: rings of diameter 0.1, 0.4
    /// and 1 image diagonal) around --gaze.
    #[arg(long, conflicts_with = "mask")]
    regions: bool,
    /// Gaze (region centre) in pixels, x,y; the image centre by default.
    #[arg(long, requires = "regions")]
    gaze: Option<String>,
}

/// `--gaze x,y` in pixels, or the centre of a `w` x `h` image.
fn gaze_point(gaze: &Option<String>, w: usize, h: usize) -> Result<[f32; 2]> {
    Ok(match gaze {
        Some(g) => match parse_list(g)?[..] {
            [x, y] if x.is_finite() && y.is_finite() => [x, y],
            _ => bail!("--gaze must be x,y in pixels, for example --gaze 256,256"),
        },
        None => [w as f32 * 0.5, h as f32 * 0.5],
    })
}

/// Prints PSNR and SSIM per foveal region.
fn print_regions(a: &RgbImage, b: &RgbImage, centre: [f32; 2]) -> Result<()> {
    for (region, q) in dioptra_render::metrics::quality_by_region(a, b, centre)? {
        match q {
            Some(q) => println!(
                "{:<12} PSNR {:.2} dB  SSIM {:.4}",
                region.name(),
                q.psnr,
                q.ssim
            ),
            None => println!("{:<12} (no pixel of the image lies in it)", region.name()),
        }
    }
    Ok(())
}

pub fn metrics(a: MetricsArgs) -> Result<()> {
    let (x, y) = (read_color(&a.a)?, read_color(&a.b)?);
    let mask: Option<Plane> = match &a.mask {
        Some(p) => Some(read_color(p)?.channels[0].clone()),
        None => None,
    };
    let q = quality(&x, &y, mask.as_ref())?;
    println!("PSNR {:.2} dB", q.psnr);
    println!("SSIM {:.4}", q.ssim);
    if a.regions {
        print_regions(&x, &y, gaze_point(&a.gaze, x.width(), x.height())?)?;
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct LightFieldArgs {
    /// Directory of a light field's view_<r>_<c>.png and view_<r>_<c>_depth.exr (from
    /// `dioptra sim scene`); the input views are taken from it.
    #[arg(long)]
    views: PathBuf,
    /// How many input views: 5 (corners and centre) or 9 (corners, edge centres, centre).
    #[arg(long, default_value_t = 9)]
    inputs: usize,
    /// Side of the square the input grid spans, metres.
    #[arg(long, default_value_t = 0.01)]
    span: f32,
    /// Views per side of the synthesised light field (over the same square).
    #[arg(long, default_value_t = 9)]
    grid: usize,
    #[command(flatten)]
    eye: EyeArgs,
    /// Foveate the synthesised light field (Thumuluri & Sharma 2020): keep each view's
    /// log-polar samples around --gaze, with the view's own offsets r' and theta', and
    /// fill the rest (--foveate-fill). S is the log-buffer scale (2: about 10 % of the rays;
    /// 4: about 4 %). Prints the fraction of rays kept and the foveated views' PSNR per
    /// region (fovea, periphery 1 and 2) against the full synthesis. Every ray is still
    /// synthesised.
    #[arg(long, value_name = "S")]
    foveate: Option<f32>,
    /// Gaze (fovea centre) in pixels, x,y, for --foveate; the image centre by default.
    #[arg(long, requires = "foveate")]
    gaze: Option<String>,
    /// How --foveate fills the rays a view did not sample: across (every view's samples
    /// reprojected into each view by their depth, then interpolation; the default) or within
    /// (each view from its own samples only, the paper's interpolation).
    #[arg(long, requires = "foveate", default_value = "across")]
    foveate_fill: String,
    /// classical (forward warp of every input, the default) or refine (the classical views
    /// corrected by a C5R net where the warp's error map says they are likely wrong).
    #[arg(long, default_value = "classical")]
    method: String,
    /// C5R weights for --method refine (default: the shipped ones; train others with
    /// `dioptra train --config c5r`).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Output directory (view_<r>_<c>.png).
    #[arg(long)]
    out: PathBuf,
}

pub fn lightfield(a: LightFieldArgs) -> Result<()> {
    use dioptra_render::views::RgbdView;
    let mut n = 0;
    while a.views.join(format!("view_00_{n:02}.png")).exists() {
        n += 1;
    }
    if n < 2 {
        bail!(
            "{} needs a grid of at least 2 x 2 views named view_<r>_<c>.png",
            a.views.display()
        );
    }
    let (m, e) = (n / 2, n - 1);
    let picks: Vec<(usize, usize)> = match a.inputs {
        5 => vec![(0, 0), (0, e), (m, m), (e, 0), (e, e)],
        9 => vec![
            (0, 0),
            (0, m),
            (0, e),
            (m, 0),
            (m, m),
            (m, e),
            (e, 0),
            (e, m),
            (e, e),
        ],
        k => bail!("--inputs must be 5 or 9, not {k}"),
    };
    let step = a.span / (n - 1) as f32;
    let half = (n - 1) as f32 * 0.5;
    let inputs = picks
        .iter()
        .map(|&(r, c)| {
            let color = read_color(&a.views.join(format!("view_{r:02}_{c:02}.png")))?;
            let depth = read_depth(&a.views.join(format!("view_{r:02}_{c:02}_depth.exr")), None)?;
            let rgbd =
                Rgbd::new(color, depth).context("a view's colour and depth differ in size")?;
            Ok(RgbdView {
                position: [(c as f32 - half) * step, (r as f32 - half) * step],
                rgbd,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let backend = a.eye.backend_or_cpu()?;
    let eye = a.eye.eye()?;
    let t = std::time::Instant::now();
    let pb = bar(a.grid * a.grid, "views")?;
    let progress = |k: usize| pb.set_position(k as u64);
    let lf = match a.method.as_str() {
        "classical" => {
            if a.weights.is_some() {
                bail!("--weights applies to --method refine");
            }
            backend.synthesize_light_field(&inputs, a.grid, a.span, &eye, &progress)?
        }
        "refine" => {
            use dioptra_net::refine::{refine_light_field, view_tiles};
            let net = dioptra_net::load_net(a.weights.as_deref(), "c5r")?;
            // The warp and its error map run on the CPU; the net on the chosen backend.
            let gpu = if backend.name() == "gpu" {
                Some(GpuNet::on(
                    dioptra_render::gpu::GpuContext::shared(a.eye.adapter.as_deref())?,
                    net.weights().clone(),
                )?)
            } else {
                None
            };
            let tiles = std::cell::Cell::new(0.0);
            let refine = |v: &Rgbd, e: &_| {
                tiles.set(tiles.get() + view_tiles(e)?.fraction());
                match &gpu {
                    Some(g) => g.refine_view(v, e),
                    None => net.refine_view(v, e),
                }
            };
            let lf = refine_light_field(&inputs, a.grid, a.span, &eye, &refine, &progress)?;
            println!(
                "refined {:.1} % of the tiles (the warp's error map)",
                100.0 * tiles.get() / lf.len().max(1) as f64
            );
            lf
        }
        m => bail!("--method {m}: expected classical or refine"),
    };
    pb.finish();
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let positions: Vec<[f32; 2]> = lf.iter().map(|v| v.position).collect();
    let mut images: Vec<RgbImage> = lf.into_iter().map(|v| v.image).collect();
    let mut foveated = None;
    if let Some(scale) = a.foveate {
        let min = dioptra_render::foveate::MIN_SCALE;
        if !(scale.is_finite() && scale >= min) {
            bail!("--foveate takes a log-buffer scale S >= {min} (2: about 10 % of the rays), not {scale}");
        }
        let (w, h) = (images[0].width(), images[0].height());
        let centre = gaze_point(&a.gaze, w, h)?;
        use dioptra_net::fv::{foveate_light_field, Fill};
        let tf = std::time::Instant::now();
        let (views, fraction) = match a.foveate_fill.as_str() {
            "within" => foveate_light_field(&images, centre, scale, Fill::WithinViews)?,
            "across" => {
                // The classical warp's depth of every view (a refined view keeps it), on the CPU.
                let depths = dioptra_render::views::light_field_depths(&inputs, &positions, &eye)?;
                let fill = Fill::AcrossViews {
                    depths: &depths,
                    positions: &positions,
                    eye: &eye,
                };
                foveate_light_field(&images, centre, scale, fill)?
            }
            f => bail!("--foveate-fill {f}: expected across or within"),
        };
        let fill_ms = tf.elapsed().as_secs_f64() * 1e3;
        let regions = dioptra_net::fv::region_psnr(&views, &images, centre)?;
        images = views;
        foveated = Some((scale, centre, fraction, fill_ms, regions));
    }
    ensure_dir(&a.out)?;
    for (k, v) in images.iter().enumerate() {
        write_color(
            &a.out
                .join(format!("view_{:02}_{:02}.png", k / a.grid, k % a.grid)),
            v,
        )?;
    }
    println!(
        "synthesised {} views from {} inputs in {ms:.0} ms into {}",
        images.len(),
        inputs.len(),
        a.out.display()
    );
    if let Some((scale, centre, fraction, fill_ms, regions)) = foveated {
        println!(
            "foveated (S = {scale}, gaze {:.0},{:.0}): {:.2} % of the rays kept, filled {} in {fill_ms:.0} ms; PSNR against the full synthesis, over all views:",
            centre[0],
            centre[1],
            100.0 * fraction,
            a.foveate_fill
        );
        for (name, p) in regions {
            if p.is_finite() {
                println!("{name:<12} {p:.2} dB");
            } else {
                println!("{name:<12} identical (every pixel sampled)");
            }
        }
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct FoveateArgs {
    /// Colour image to sample.
    #[arg(long)]
    color: PathBuf,
    /// Gaze (fovea centre) in pixels, x,y; the image centre by default.
    #[arg(long)]
    gaze: Option<String>,
    /// Log-buffer scale S (2 samples about 10 %, 4 about 4 %).
    #[arg(long, default_value_t = 2.0)]
    scale: f32,
    /// Kernel parameter K.
    #[arg(long, default_value_t = 1.0)]
    kernel: f32,
    /// Per-view radial offset r'.
    #[arg(long, default_value_t = 1.0)]
    r_offset: f32,
    /// Per-view angular offset theta', radians.
    #[arg(long, default_value_t = 0.0)]
    theta_offset: f32,
    /// Interpolated image.
    #[arg(long)]
    out: PathBuf,
    /// Also write the sampling mask here.
    #[arg(long)]
    mask_out: Option<PathBuf>,
    /// Image to score the interpolated result against per foveal region (the input itself by
    /// default: what sampling and interpolation lose).
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Compute backend: cpu or gpu. Default: gpu when a hardware GPU adapter exists, else cpu.
    #[arg(long)]
    backend: Option<String>,
    /// GPU adapter to use (part of its name); implies --backend gpu.
    #[arg(long)]
    adapter: Option<String>,
}

pub fn foveate(a: FoveateArgs) -> Result<()> {
    use dioptra_render::foveate::LogPolar;
    let img = read_color(&a.color)?;
    let (w, h) = (img.width(), img.height());
    let centre = gaze_point(&a.gaze, w, h)?;
    let p = LogPolar {
        centre,
        scale: a.scale,
        kernel: a.kernel,
        r_offset: a.r_offset,
        theta_offset: a.theta_offset,
    };
    let b = choose_backend(a.backend.as_deref(), a.adapter.as_deref())?;
    let t = std::time::Instant::now();
    let fov = b.foveate(&img, &p)?;
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let (out, mask, fraction) = (fov.image, fov.mask, fov.fraction);
    write_color(&a.out, &out)?;
    if let Some(m) = &a.mask_out {
        let mp = mask.clone();
        write_color(m, &RgbImage::from_planes(mp.clone(), mp.clone(), mp)?)?;
    }
    println!(
        "sampled {:.2} % of pixels; wrote {} ({ms:.0} ms on the {} backend)",
        fraction * 100.0,
        a.out.display(),
        b.name()
    );
    let reference = match &a.reference {
        Some(r) => read_color(r)?,
        None => img,
    };
    print_regions(&out, &reference, centre)?;
    Ok(())
}
