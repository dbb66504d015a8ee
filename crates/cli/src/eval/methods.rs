//! The methods `dioptra eval` measures, each with its setting: how to run one on a backend
//! and what the eye sees of its output at a focus.

use anyhow::{anyhow, Result};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_net::gpu::GpuNet;
use dioptra_net::refine::{classical_defocus, Refined};
use dioptra_net::{Arch, Classical, CpuNet, Task, Weights};
use dioptra_render::multifocal::DEFAULT_PLANES;
use dioptra_render::{
    Backend, DefocusMethod, Layers, LightFieldParams, OptimizeParams, SpectralParams,
};

/// One method with one setting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    Gather,
    LightField {
        views: usize,
    },
    /// DeepFocus C1 at interleave rate `rate`.
    NetworkC1 {
        rate: usize,
    },
    Linear,
    /// Optimized blending fitted to the ground-truth focal stack (its best case: an oracle
    /// no rig has).
    Optimized {
        iterations: usize,
    },
    /// Optimized blending as a rig runs it: fitted to a focal stack gathered from the RGB-D,
    /// from linear blending (the daemon's `method = "optimized"`, and `decompose --method
    /// optimized` without `--targets`). Its time includes the stack and the linear start.
    OptimizedGather {
        iterations: usize,
    },
    /// The spectral decomposition (per-frequency least squares; the daemon's `method =
    /// "spectral"`) with its default settings, its time including its target stack.
    Spectral,
    NetworkC4,
    /// C1R: the classical render its weights name, refined on the error map's tiles.
    RefineC1,
    /// C4R: linear blending's layers, refined.
    RefineC4,
}

impl Method {
    pub fn name(&self) -> &'static str {
        match self {
            Method::Gather => "gather",
            Method::LightField { .. } => "lightfield",
            Method::NetworkC1 { .. } => "network-c1",
            Method::Linear => "linear",
            Method::Optimized { .. } => "optimized",
            Method::OptimizedGather { .. } => "optimized-gather",
            Method::Spectral => "spectral",
            Method::NetworkC4 => "network-c4",
            Method::RefineC1 => "refine-c1r",
            Method::RefineC4 => "refine-c4r",
        }
    }

    pub fn setting(&self) -> String {
        match self {
            Method::Gather
            | Method::Linear
            | Method::Spectral
            | Method::RefineC1
            | Method::RefineC4 => String::new(),
            Method::LightField { views } => format!("{views} views"),
            Method::NetworkC1 { rate } => format!("r={rate}"),
            Method::Optimized { iterations } | Method::OptimizedGather { iterations } => {
                format!("{iterations} it")
            }
            Method::NetworkC4 => "r=2".into(),
        }
    }

    /// Name and setting together, for chart series and tables.
    pub fn label(&self) -> String {
        let s = self.setting();
        if s.is_empty() {
            self.name().into()
        } else {
            format!("{} {s}", self.name())
        }
    }

    /// Multifocal methods make display layers once for every focus; the others make one
    /// image per focus (a varifocal frame).
    pub fn multifocal(&self) -> bool {
        matches!(
            self,
            Method::Linear
                | Method::Optimized { .. }
                | Method::OptimizedGather { .. }
                | Method::Spectral
                | Method::NetworkC4
                | Method::RefineC4
        )
    }

    /// Relative cost among the settings of one method (views, iterations, pixels per
    /// interleaved pixel), for predicting a setting's time from a cheaper one's.
    pub fn relative_cost(&self) -> f64 {
        match *self {
            Method::LightField { views } => views as f64,
            Method::Optimized { iterations } | Method::OptimizedGather { iterations } => {
                iterations as f64
            }
            Method::NetworkC1 { rate } => 1.0 / (rate * rate) as f64,
            _ => 1.0,
        }
    }

    pub fn network(&self) -> bool {
        matches!(
            self,
            Method::NetworkC1 { .. } | Method::NetworkC4 | Method::RefineC1 | Method::RefineC4
        )
    }
}

/// The networks to run: the shipped weights when present, else randomly initialised nets of
/// the same architecture (timed only, never scored).
pub struct Nets {
    c1: Option<CpuNet>,
    c4: Option<CpuNet>,
    c1r: Option<CpuNet>,
    c4r: Option<CpuNet>,
    c5r: Option<CpuNet>,
    /// Why the shipped weights are not used, when they are not.
    c1_missing: String,
    c4_missing: String,
    c1r_missing: String,
    c4r_missing: String,
    c5r_missing: String,
}

fn load_shipped(config: &str) -> (Option<CpuNet>, String) {
    let path = dioptra_net::shipped_weights(config);
    if !path.exists() {
        return (None, "untrained: no shipped weights".into());
    }
    match dioptra_net::load_net(None, config) {
        Ok(n) => (Some(n), String::new()),
        Err(e) => (
            None,
            format!("untrained: shipped weights failed to load ({e})"),
        ),
    }
}

/// A network to run and whether it is trained (its outputs may be scored).
pub struct NetChoice<'a> {
    pub net: std::borrow::Cow<'a, CpuNet>,
    pub trained: bool,
    pub note: String,
}

impl Nets {
    pub fn load() -> Nets {
        let (c1, c1_missing) = load_shipped("c1");
        let (c4, c4_missing) = load_shipped("c4");
        let (c1r, c1r_missing) = load_shipped("c1r");
        let (c4r, c4r_missing) = load_shipped("c4r");
        let (c5r, c5r_missing) = load_shipped("c5r");
        Nets {
            c1,
            c4,
            c1r,
            c4r,
            c1_missing,
            c4_missing,
            c1r_missing,
            c4r_missing,
            c5r,
            c5r_missing,
        }
    }

    /// The shipped C5R net (light-field refinement), or why there is none.
    pub fn c5r(&self) -> Result<&CpuNet, &str> {
        self.c5r.as_ref().ok_or(self.c5r_missing.as_str())
    }

    /// The shipped C1 net's interleave rate, when there is one.
    pub fn c1_rate(&self) -> Option<usize> {
        self.c1.as_ref().map(|n| n.arch().rate)
    }

    /// The net for `m` (a network method).
    pub fn choose(&self, m: Method) -> Result<NetChoice<'_>> {
        let (shipped, missing, config, rate) = match m {
            Method::NetworkC1 { rate } => (&self.c1, &self.c1_missing, "c1", Some(rate)),
            Method::NetworkC4 => (&self.c4, &self.c4_missing, "c4", None),
            Method::RefineC1 => (&self.c1r, &self.c1r_missing, "c1r", None),
            Method::RefineC4 => (&self.c4r, &self.c4r_missing, "c4r", None),
            _ => return Err(anyhow!("{} is not a network", m.name())),
        };
        if let Some(n) = shipped {
            if rate.is_none_or(|r| r == n.arch().rate) {
                return Ok(NetChoice {
                    net: std::borrow::Cow::Borrowed(n),
                    trained: true,
                    note: standing(m).into(),
                });
            }
        }
        // Same architecture as the shipped net (or the preset), at the rate asked for.
        let mut arch = match shipped {
            Some(n) => n.arch().clone(),
            None => Arch::preset(config)?,
        };
        if let Some(r) = rate {
            arch.rate = r;
        }
        let note = match shipped {
            Some(n) => format!(
                "untrained: the shipped {config} net has r={}, this r is timed with random weights",
                n.arch().rate
            ),
            None => missing.clone(),
        };
        let net = CpuNet::new(Weights::random(&arch, 7)?)?;
        Ok(NetChoice {
            net: std::borrow::Cow::Owned(net),
            trained: false,
            note,
        })
    }
}

/// Why a shipped refinement net is not the daemon's default: what it scored on the
/// independent validation set (Mitsuba 3 scenes, scripts/independent_validation), where a net
/// must never be below its classical input to be one.
fn standing(m: Method) -> &'static str {
    match m {
        Method::RefineC1 => {
            "not the daemon's default: on the independent set (scripts/independent_validation/\
             defocus_scores.md) below the 36-view light field on 11 of 12 scenes"
        }
        Method::RefineC4 => {
            "not the daemon's default: on the independent set (scripts/independent_validation/\
             scores.md) below linear blending, its input, on every scene"
        }
        _ => "",
    }
}

/// A network on the backend that runs it: the same weights on the CPU or the GPU.
#[derive(Clone, Copy)]
pub enum NetOn<'a> {
    Cpu(&'a CpuNet),
    Gpu(&'a GpuNet),
}

impl NetOn<'_> {
    fn backend_name(self) -> &'static str {
        match self {
            NetOn::Cpu(_) => "cpu",
            NetOn::Gpu(_) => "gpu",
        }
    }
    fn defocus(self, input: &Rgbd, q: Diopters, eye: &EyeModel) -> Result<RgbImage> {
        Ok(match self {
            NetOn::Cpu(n) => n.defocus(input, q, eye)?,
            NetOn::Gpu(n) => n.defocus(input, q, eye)?,
        })
    }
    fn decompose(self, input: &Rgbd) -> Result<Layers> {
        Ok(match self {
            NetOn::Cpu(n) => n.decompose(input)?,
            NetOn::Gpu(n) => n.decompose(input)?,
        })
    }
    fn classical(self) -> Result<Classical> {
        let task = match self {
            NetOn::Cpu(n) => &n.arch().task,
            NetOn::Gpu(n) => &n.arch().task,
        };
        match task {
            Task::C1r { classical } => Ok(*classical),
            t => Err(anyhow!("{} is not a c1r net", t.name())),
        }
    }
    fn refine_defocus(
        self,
        input: &Rgbd,
        base: &RgbImage,
        q: Diopters,
        eye: &EyeModel,
    ) -> Result<Refined> {
        Ok(match self {
            NetOn::Cpu(n) => n.refine_defocus(input, base, q, eye)?,
            NetOn::Gpu(n) => n.refine_defocus(input, base, q, eye)?,
        })
    }
    fn refine_decompose(self, input: &Rgbd, linear: &Layers) -> Result<Layers> {
        Ok(match self {
            NetOn::Cpu(n) => n.refine_decompose(input, linear)?,
            NetOn::Gpu(n) => n.refine_decompose(input, linear)?,
        })
    }
}

/// The display planes of the multifocal methods (DeepFocus's 0.2, 0.8, 1.4, 2.0 D).
pub fn planes() -> Vec<Diopters> {
    DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect()
}

/// A varifocal method's image at focus `q`, and for C1R the fraction of tiles it ran on.
pub fn defocus(
    backend: &dyn Backend,
    m: Method,
    net: Option<NetOn>,
    input: &Rgbd,
    q: Diopters,
    eye: &EyeModel,
) -> Result<(RgbImage, Option<f64>)> {
    let method = match m {
        Method::Gather => DefocusMethod::Gather,
        Method::LightField { views } => {
            DefocusMethod::LightField(LightFieldParams { views, mip: true })
        }
        Method::NetworkC1 { .. } => {
            let net = net.ok_or_else(|| anyhow!("network-c1 needs a net"))?;
            return Ok((net.defocus(input, q, eye)?, None));
        }
        Method::RefineC1 => {
            let net = net.ok_or_else(|| anyhow!("refine-c1r needs a net"))?;
            // The classical render on the same backend as the net (the frame's whole cost).
            let base = if net.backend_name() == backend.name() {
                classical_defocus(backend, net.classical()?, input, q, eye)?
            } else {
                return Err(anyhow!(
                    "refine-c1r: the net runs on {} but the backend is {}",
                    net.backend_name(),
                    backend.name()
                ));
            };
            let r = net.refine_defocus(input, &base, q, eye)?;
            return Ok((r.image, Some(r.tiles.fraction())));
        }
        _ => return Err(anyhow!("{} is not a varifocal method", m.name())),
    };
    let img = backend
        .defocus(input, &[q], eye, method, &|_| {})?
        .pop()
        .ok_or_else(|| anyhow!("{} made no image", m.name()))?;
    Ok((img, None))
}

/// What a multifocal method needs besides the RGB-D input: the focal stack optimized
/// blending fits (ground truth, as the accuracy tests use) and its foci.
pub struct MultifocalTargets<'a> {
    pub stack: &'a [RgbImage],
    pub foci: &'a [Diopters],
    pub linear_init: &'a Layers,
}

/// A multifocal method's layers.
pub fn decompose(
    backend: &dyn Backend,
    m: Method,
    net: Option<NetOn>,
    input: &Rgbd,
    targets: &MultifocalTargets,
    eye: &EyeModel,
) -> Result<Layers> {
    let planes = planes();
    match m {
        Method::Linear => Ok(backend.linear_blend(input, &planes)?),
        Method::Optimized { iterations } => Ok(backend
            .optimized_blend(
                targets.stack,
                targets.foci,
                &planes,
                eye,
                Some(targets.linear_init),
                OptimizeParams {
                    iterations,
                    tolerance: 0.0,
                },
                &|_| {},
            )?
            .0),
        Method::OptimizedGather { iterations } => {
            let stack =
                backend.defocus(input, targets.foci, eye, DefocusMethod::Gather, &|_| {})?;
            let linear = backend.linear_blend(input, &planes)?;
            Ok(backend
                .optimized_blend(
                    &stack,
                    targets.foci,
                    &planes,
                    eye,
                    Some(&linear),
                    OptimizeParams {
                        iterations,
                        tolerance: 0.0,
                    },
                    &|_| {},
                )?
                .0)
        }
        Method::Spectral => Ok(backend
            .spectral_blend(input, &planes, eye, SpectralParams::default())?
            .0),
        Method::NetworkC4 => {
            let net = net.ok_or_else(|| anyhow!("network-c4 needs a net"))?;
            net.decompose(input)
        }
        Method::RefineC4 => {
            let net = net.ok_or_else(|| anyhow!("refine-c4r needs a net"))?;
            let linear = backend.linear_blend(input, &planes)?;
            net.refine_decompose(input, &linear)
        }
        _ => Err(anyhow!("{} is not a multifocal method", m.name())),
    }
}

/// Finite and in-range check of an output: values that are not finite, and values outside
/// [0, 1] by more than 1e-3.
pub fn out_of_range(images: &[&RgbImage]) -> (usize, usize) {
    let (mut nonfinite, mut outside) = (0, 0);
    for img in images {
        for v in img.channels.iter().flat_map(|p| p.data()) {
            if !v.is_finite() {
                nonfinite += 1;
            } else if !(-1e-3..=1.0 + 1e-3).contains(v) {
                outside += 1;
            }
        }
    }
    (nonfinite, outside)
}
