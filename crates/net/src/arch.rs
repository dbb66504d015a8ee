//! The DeepFocus-family architecture, parameterised, and the configurations C1-C5.
//!
//! Graph (shared by every backend and by training; layers are numbered from 0):
//! - the input (full resolution, `in_channels`) is space-to-depth interleaved at rate `r`;
//! - layer `i` is a 3x3 convolution with bias ("same" zero padding) and, except for the last
//!   layer, an ELU. Its input is `h[i-1]` (or the interleaved input for `i = 0`), plus
//!   `h[i-3]` when `i` is odd and `i >= 3`: one residual connection per two layers, as in
//!   DeepFocus's released code;
//! - with `concat_input`, the interleaved input is appended to the last layer's input channels
//!   (after the features);
//! - the last layer outputs `out_channels * r^2` channels, mapped to [0, 1] by `(tanh x + 1) / 2`,
//!   then depth-to-space back to full resolution. The refinement nets (C1R, C4R) skip the
//!   `tanh`: their output is a correction added to a classical method's result (then clamped
//!   to [0, 1] by the task code), and their last layer starts at zero, so an untrained
//!   refinement net returns the classical result unchanged.
//!
//! - FV only (Thumuluri & Sharma 2020, sec. 4.3): a small U-Net runs in parallel on the same
//!   interleaved input and its output is added to the last layer's before the `tanh`:
//!   two 3x3 convolutions at the interleaved resolution (`u` channels), 2x2 average pool, two at
//!   1/2 (`2u`), 2x2 average pool, one at 1/4 (`2u`), nearest upsampling and concatenation with
//!   the skip at each level (one convolution each), and a last convolution to the output
//!   channels. Its convolutions follow the chain's in the weights, named `unet{j}`.
//!
//! Interleave channel order: interleaved channel `c * r^2 + dy * r + dx` holds channel `c` at
//! pixel `(r*Y + dy, r*X + dx)` of the full-resolution image (PyTorch's `pixel_unshuffle`
//! order, not TensorFlow's `(dy*r + dx)*C + c`); depth-to-space is its exact inverse.

use crate::error::NetError;
use serde::{Deserialize, Serialize};

/// Input normalisation, as in DeepFocus: depth in diopters / 4, CoC in pixels / 30.
pub const DEPTH_NORM: f32 = 4.0;
pub const COC_NORM: f32 = 30.0;
/// C5R's parallax inputs (pixels) / 4: about the largest between a novel view and its
/// nearest input per diopter, or across a depth step, on the 9 x 9 light fields over 1 cm
/// it trains on.
pub const PARALLAX_NORM: f32 = 4.0;

/// The classical defocus method a C1R net refines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum Classical {
    Gather,
    /// The light-field method (Yu et al.) with `views` lens samples, mip prefiltered.
    Lightfield {
        views: usize,
    },
}

impl Classical {
    pub fn label(&self) -> String {
        match self {
            Classical::Gather => "gather".into(),
            Classical::Lightfield { views } => format!("lightfield {views} views"),
        }
    }
}

/// The classical decomposition a C4R net refines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ClassicalLayers {
    /// Linear blending (Akeley et al.). A file that names no classical input refines these.
    #[default]
    Linear,
    /// The spectral decomposition with [`dioptra_render::SpectralParams::default`]'s
    /// settings at the time it runs.
    Spectral,
}

impl ClassicalLayers {
    pub fn label(&self) -> &'static str {
        match self {
            ClassicalLayers::Linear => "linear",
            ClassicalLayers::Spectral => "spectral",
        }
    }
    pub fn is_linear(&self) -> bool {
        *self == ClassicalLayers::Linear
    }
}

/// What a network computes, by inputs and outputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "config", rename_all = "lowercase")]
pub enum Task {
    /// Defocus: RGB + depth + CoC map (5 channels) -> RGB at the CoC map's focus.
    C1,
    /// Focal stack: RGB + depth (4) -> one RGB slice per focus in `foci` (diopters).
    C3 { foci: Vec<f32> },
    /// Multifocal decomposition: RGB + depth (4) -> one RGB layer per display plane;
    /// trained through the retinal model on the focal stack at `foci`.
    C4 { planes: Vec<f32>, foci: Vec<f32> },
    /// Light field: `views` (5 or 9) RGB-D views (4 each) -> all `grid` x `grid` RGB views.
    C5 { views: usize, grid: usize },
    /// Foveated view synthesis (Thumuluri & Sharma 2020): per input view (`views`, 5 or 9 of
    /// the grid) its log-polar sampling mask, sampled depth / 4 and interpolated RGB (5 each)
    /// -> all `grid` x `grid` RGB views.
    Fv { views: usize, grid: usize },
    /// Defocus refinement: RGB + depth + CoC map + the `classical` method's render at the
    /// CoC map's focus (8 channels) -> a correction of that render (3).
    C1r { classical: Classical },
    /// Multifocal refinement: RGB + depth + the `classical` decomposition's layers for
    /// `planes` (4 + 3M) -> a correction of those layers (3M); trained through the retina at
    /// `foci`. `classical` is absent from the JSON when linear (files from before it existed
    /// refine linear blending).
    C4r {
        planes: Vec<f32>,
        foci: Vec<f32>,
        #[serde(default, skip_serializing_if = "ClassicalLayers::is_linear")]
        classical: ClassicalLayers,
    },
    /// Light-field refinement: per novel view, its classical synthesis from `views` (5 or 9)
    /// RGB-D inputs (RGB and warped depth), the warp's error map (hole, parallax across a depth
    /// step, the inputs' colour spread) and the view's parallax per diopter from its nearest
    /// input (x, y): 9 channels -> a correction of the view (3). Trained on `grid` x `grid`
    /// light fields; runs on any grid.
    C5r { views: usize, grid: usize },
}

/// Convolutions of the FV U-Net (see the module docs).
pub const UNET_CONVS: usize = 7;

impl Task {
    pub fn name(&self) -> &'static str {
        match self {
            Task::C1 => "c1",
            Task::C3 { .. } => "c3",
            Task::C4 { .. } => "c4",
            Task::C5 { .. } => "c5",
            Task::Fv { .. } => "fv",
            Task::C1r { .. } => "c1r",
            Task::C4r { .. } => "c4r",
            Task::C5r { .. } => "c5r",
        }
    }
    /// Refinement nets output a correction of a classical result, not an image.
    pub fn residual(&self) -> bool {
        matches!(self, Task::C1r { .. } | Task::C4r { .. } | Task::C5r { .. })
    }
    /// The display planes of a multifocal net (C4, C4R).
    pub fn planes(&self) -> Option<&[f32]> {
        match self {
            Task::C4 { planes, .. } | Task::C4r { planes, .. } => Some(planes),
            _ => None,
        }
    }
    pub fn in_channels(&self) -> usize {
        match self {
            Task::C1 => 5,
            Task::C3 { .. } | Task::C4 { .. } => 4,
            Task::C5 { views, .. } => 4 * views,
            Task::Fv { views, .. } => 5 * views,
            Task::C1r { .. } => 8,
            Task::C4r { planes, .. } => 4 + 3 * planes.len(),
            Task::C5r { .. } => 9,
        }
    }
    pub fn out_channels(&self) -> usize {
        match self {
            Task::C1 => 3,
            Task::C3 { foci } => 3 * foci.len(),
            Task::C4 { planes, .. } | Task::C4r { planes, .. } => 3 * planes.len(),
            Task::C1r { .. } | Task::C5r { .. } => 3,
            Task::C5 { grid, .. } | Task::Fv { grid, .. } => 3 * grid * grid,
        }
    }
    /// Grid indices (row-major, `row * grid + col`) of the input views of C5, FV and C5R: the four
    /// corners and the centre (5), plus the edge midpoints (9), as in DeepFocus's light-field
    /// configurations. Empty for the other tasks.
    pub fn input_views(&self) -> Vec<usize> {
        let (Task::C5 { views, grid } | Task::Fv { views, grid } | Task::C5r { views, grid }) =
            self
        else {
            return Vec::new();
        };
        let (g, m) = (*grid, grid / 2);
        let mut rc = vec![(0, 0), (0, g - 1), (m, m), (g - 1, 0), (g - 1, g - 1)];
        if *views == 9 {
            rc.extend([(0, m), (m, 0), (m, g - 1), (g - 1, m)]);
        }
        let mut v: Vec<usize> = rc.iter().map(|(r, c)| r * g + c).collect();
        v.sort_unstable();
        v
    }

    fn validate(&self) -> Result<(), String> {
        let diopters = |v: &[f32], what: &str, max: usize| -> Result<(), String> {
            if v.is_empty() || v.len() > max {
                return Err(format!("{} {what}: expected 1 to {max}", v.len()));
            }
            if v.iter()
                .any(|d| !(d.is_finite() && (0.0..100.0).contains(d)))
                || v.windows(2).any(|w| w[0] >= w[1])
            {
                return Err(format!(
                    "{what} {v:?}: expected finite, increasing diopters"
                ));
            }
            Ok(())
        };
        match self {
            Task::C1 => Ok(()),
            Task::C3 { foci } => diopters(foci, "focal slices", 64),
            Task::C4 { planes, foci } | Task::C4r { planes, foci, .. } => {
                diopters(planes, "display planes", 16)?;
                diopters(foci, "focal samples", 64)
            }
            Task::C1r { classical } => match classical {
                Classical::Gather => Ok(()),
                Classical::Lightfield { views } if (1..=256).contains(views) => Ok(()),
                Classical::Lightfield { views } => {
                    Err(format!("{views} light-field views: expected 1 to 256"))
                }
            },
            Task::C5 { views, grid } | Task::Fv { views, grid } | Task::C5r { views, grid } => {
                if ![5, 9].contains(views) || !(3..=9).contains(grid) || grid % 2 == 0 {
                    Err(format!(
                        "{views} input views on a {grid}x{grid} grid: expected 5 or 9 views, an odd grid 3 to 9"
                    ))
                } else {
                    Ok(())
                }
            }
        }
    }
}

/// The architecture: stored as JSON in the weights file's metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Arch {
    #[serde(flatten)]
    pub task: Task,
    /// Interleave rate r (1, 2 or 4).
    pub rate: usize,
    /// Convolution layers, the last one included (at least 2).
    pub layers: usize,
    /// Feature channels of the hidden layers.
    pub channels: usize,
    /// Concatenate the interleaved input before the last layer.
    pub concat_input: bool,
    /// Channels of the parallel U-Net's first level (FV only; 0 = no U-Net). Absent from the
    /// JSON when 0, so C1-C5 files are unchanged.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub unet_channels: usize,
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

/// Every configuration [`Arch::preset`] knows, as `dioptra train --config` takes them.
pub const CONFIGS: &[&str] = &["c1", "c3", "c4", "c5", "fv", "c1r", "c4r", "c5r"];

impl Arch {
    /// The small defocus net this project starts from: 8 layers x 32 channels, r = 2.
    pub fn c1_small() -> Arch {
        Arch {
            task: Task::C1,
            rate: 2,
            layers: 8,
            channels: 32,
            concat_input: false,
            unet_channels: 0,
        }
    }

    /// Default architecture of each configuration ([`CONFIGS`]).
    pub fn preset(name: &str) -> Result<Arch, NetError> {
        let stack = |lo: f32, hi: f32, n: usize| -> Vec<f32> {
            (0..n)
                .map(|i| lo + (hi - lo) * i as f32 / (n - 1) as f32)
                .collect()
        };
        let task = match name {
            "c1" => Task::C1,
            // 40 slices 0.1-4.0 D in DeepFocus; 10 keep the small net small.
            "c3" => Task::C3 {
                foci: stack(0.1, 4.0, 10),
            },
            "c4" => Task::C4 {
                planes: vec![0.2, 0.8, 1.4, 2.0],
                foci: stack(0.1, 2.2, 22),
            },
            "c5" => Task::C5 { views: 5, grid: 9 },
            // The four corners and the centre of a 3x3 grid: the paper's 9 inputs of a 9x9
            // grid cost 81 renders per training scene; 5 of 9 keeps the same task (synthesise
            // the views between foveated inputs) at a size this machine trains in minutes.
            "fv" => Task::Fv { views: 5, grid: 3 },
            "c1r" => Task::C1r {
                classical: Classical::Lightfield { views: 12 },
            },
            "c4r" => Task::C4r {
                planes: vec![0.2, 0.8, 1.4, 2.0],
                foci: stack(0.1, 2.2, 22),
                classical: ClassicalLayers::Linear,
            },
            // DeepFocus's light field: 9 x 9 views from 9.
            "c5r" => Task::C5r { views: 9, grid: 9 },
            _ => {
                return Err(NetError::BadArch(format!(
                    "unknown configuration {name:?}: expected c1, c3, c4, c5, fv, c1r, c4r or c5r"
                )))
            }
        };
        let fv = matches!(task, Task::Fv { .. });
        // The refinement nets are small: they learn a residual, on the CPU, run per frame.
        // C1R's is the shipped net's size: its tiles must cost less than the light field it
        // refines (issue 21's time target).
        let (layers, channels) = match task {
            // C5R runs per novel view: 72 of them in a 9 x 9 light field.
            Task::C1r { .. } | Task::C5r { .. } => (6, 16),
            Task::C4r { .. } => (6, 32),
            _ => (8, 32),
        };
        let arch = Arch {
            layers,
            channels,
            // The light-field nets (and FV's long skip, sec. 4.3.2) see the input at the end.
            concat_input: matches!(task, Task::C5 { .. } | Task::Fv { .. }),
            unet_channels: if fv { 16 } else { 0 },
            task,
            ..Arch::c1_small()
        };
        arch.validate()?;
        Ok(arch)
    }

    pub fn in_channels(&self) -> usize {
        self.task.in_channels()
    }
    pub fn out_channels(&self) -> usize {
        self.task.out_channels()
    }

    /// Refuses to run this network as configuration `name` when it is another one.
    pub fn expect_task(&self, name: &str) -> Result<(), NetError> {
        let have = self.task.name();
        if have != name {
            return Err(NetError::WrongConfig {
                expected: have.into(),
                asked: name.into(),
            });
        }
        Ok(())
    }

    pub fn validate(&self) -> Result<(), NetError> {
        let bad = |m: String| Err(NetError::BadArch(m));
        if ![1, 2, 4].contains(&self.rate) {
            return bad(format!("interleave rate {}: expected 1, 2 or 4", self.rate));
        }
        if !(2..=64).contains(&self.layers) {
            return bad(format!("{} layers: expected 2 to 64", self.layers));
        }
        if !(1..=1024).contains(&self.channels) {
            return bad(format!("{} channels: expected 1 to 1024", self.channels));
        }
        let fv = matches!(self.task, Task::Fv { .. });
        if fv != (self.unet_channels > 0) || self.unet_channels > 512 {
            return bad(format!(
                "{} U-Net channels for {}: FV needs 1 to 512, the other configurations 0",
                self.unet_channels,
                self.task.name()
            ));
        }
        self.task.validate().map_err(NetError::BadArch)
    }

    /// Every convolution: the chain's `layers`, then the U-Net's.
    pub fn conv_count(&self) -> usize {
        self.layers
            + if self.unet_channels > 0 {
                UNET_CONVS
            } else {
                0
            }
    }

    /// The weights' name stem of convolution `i`: `conv{i}` in the chain, `unet{j}` after.
    pub fn conv_name(&self, i: usize) -> String {
        if i < self.layers {
            format!("conv{i}")
        } else {
            format!("unet{}", i - self.layers)
        }
    }

    /// What the full-resolution input's size must divide by: the rate, times 4 for the
    /// U-Net's two poolings.
    pub fn size_multiple(&self) -> usize {
        self.rate * if self.unet_channels > 0 { 4 } else { 1 }
    }

    /// Input and output channels of U-Net convolution `j` (interleaved domain).
    fn unet_io(&self, j: usize) -> (usize, usize) {
        let (u, x0) = (
            self.unet_channels,
            self.in_channels() * self.rate * self.rate,
        );
        match j {
            0 => (x0, u),
            1 => (u, u),
            2 => (u, 2 * u),
            3 => (2 * u, 2 * u),
            // Upsampled bottleneck + level-1 skip, then upsampled + level-0 skip.
            4 => (4 * u, 2 * u),
            5 => (2 * u + u, u),
            _ => (u, self.out_channels() * self.rate * self.rate),
        }
    }

    /// Input channels of convolution `i` (interleaved domain).
    pub fn conv_in(&self, i: usize) -> usize {
        let rr = self.rate * self.rate;
        if i >= self.layers {
            self.unet_io(i - self.layers).0
        } else if i == 0 {
            self.in_channels() * rr
        } else if i + 1 == self.layers && self.concat_input {
            self.channels + self.in_channels() * rr
        } else {
            self.channels
        }
    }

    /// Output channels of convolution `i` (interleaved domain).
    pub fn conv_out(&self, i: usize) -> usize {
        if i >= self.layers {
            self.unet_io(i - self.layers).1
        } else if i + 1 == self.layers {
            self.out_channels() * self.rate * self.rate
        } else {
            self.channels
        }
    }

    /// The earlier layer output added to layer `i`'s input, if any.
    pub fn residual_from(&self, i: usize) -> Option<usize> {
        (i >= 3 && i % 2 == 1).then(|| i - 3)
    }

    /// Shapes of every tensor, by name, in file order: `conv{i}.weight` [out, in, 3, 3] and
    /// `conv{i}.bias` [out] (`unet{j}.*` for the U-Net's).
    pub fn tensor_shapes(&self) -> Vec<(String, Vec<usize>)> {
        (0..self.conv_count())
            .flat_map(|i| {
                let n = self.conv_name(i);
                [
                    (
                        format!("{n}.weight"),
                        vec![self.conv_out(i), self.conv_in(i), 3, 3],
                    ),
                    (format!("{n}.bias"), vec![self.conv_out(i)]),
                ]
            })
            .collect()
    }

    pub fn to_json(&self) -> String {
        // A plain struct of numbers, strings and vectors always serialises.
        serde_json::to_string(self).unwrap_or_default()
    }

    pub fn from_json(s: &str) -> Result<Arch, NetError> {
        let a: Arch =
            serde_json::from_str(s).map_err(|e| NetError::BadArch(format!("{e} in {s:?}")))?;
        a.validate()?;
        Ok(a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trip_keeps_every_field() {
        for name in ["c1", "c3", "c4", "c5", "fv", "c5r"] {
            let mut a = Arch::preset(name).unwrap();
            a.rate = 4;
            a.layers = 5;
            let b = Arch::from_json(&a.to_json()).unwrap();
            assert_eq!(a, b);
        }
    }

    #[test]
    fn a_c4r_file_names_its_classical_input_and_older_files_refine_linear_blending() {
        // The JSON of a C4R file from before the choice existed (the shipped c4r's).
        let old = r#"{"config":"c4r","planes":[0.2,0.8,1.4,2.0],"foci":[0.1,0.2],"rate":2,"layers":6,"channels":32,"concat_input":false}"#;
        let a = Arch::from_json(old).unwrap();
        let Task::C4r { classical, .. } = a.task else {
            panic!("{a:?}");
        };
        assert_eq!(classical, ClassicalLayers::Linear);
        // Linear is left out of the JSON, so such a file is written as before.
        assert!(!a.to_json().contains("classical"), "{}", a.to_json());
        let mut s = Arch::preset("c4r").unwrap();
        if let Task::C4r { classical, .. } = &mut s.task {
            *classical = ClassicalLayers::Spectral;
        }
        assert!(
            s.to_json().contains(r#""classical":"spectral""#),
            "{}",
            s.to_json()
        );
        assert_eq!(Arch::from_json(&s.to_json()).unwrap(), s);
        // An unknown classical input is refused.
        let bad = old.replace(r#""rate""#, r#""classical":"optimized","rate""#);
        assert!(Arch::from_json(&bad).is_err());
    }

    #[test]
    fn channel_counts_follow_the_configuration() {
        let c1 = Arch::preset("c1").unwrap();
        assert_eq!((c1.conv_in(0), c1.conv_out(7)), (20, 12));
        let c4 = Arch::preset("c4").unwrap();
        assert_eq!((c4.conv_in(0), c4.conv_out(7)), (16, 48));
        let c5 = Arch::preset("c5").unwrap();
        // 5 views x RGB-D in, concatenated before the last layer; 81 RGB views out.
        assert_eq!(c5.conv_in(7), 32 + 80);
        assert_eq!(c5.conv_out(7), 243 * 4);
        // C5R: a view's RGB, depth, 3 error channels and offset in; an RGB correction out.
        let c5r = Arch::preset("c5r").unwrap();
        assert_eq!((c5r.conv_in(0), c5r.conv_out(5)), (36, 12));
        assert!(c5r.task.residual());
        assert_eq!(
            c5r.task.input_views(),
            vec![0, 4, 8, 36, 40, 44, 72, 76, 80]
        );
    }

    #[test]
    fn fv_has_a_unet_beside_the_chain() {
        let fv = Arch::preset("fv").unwrap();
        // 5 views x (mask, depth, RGB), interleaved at r = 2.
        assert_eq!((fv.in_channels(), fv.conv_in(0)), (25, 100));
        assert_eq!(fv.conv_count(), 8 + UNET_CONVS);
        assert_eq!(fv.conv_name(8), "unet0");
        assert_eq!((fv.conv_in(8), fv.conv_out(8)), (100, 16));
        assert_eq!((fv.conv_in(12), fv.conv_in(13)), (64, 48));
        // Both branches end in the same output channels, so they can be summed.
        assert_eq!(fv.conv_out(14), fv.conv_out(7));
        assert_eq!(fv.conv_out(14), 27 * 4);
        assert_eq!(fv.size_multiple(), 8);
        assert_eq!(fv.task.input_views(), vec![0, 2, 4, 6, 8]);
        let nine = Task::Fv { views: 9, grid: 9 }.input_views();
        assert_eq!(nine, vec![0, 4, 8, 36, 40, 44, 72, 76, 80]);
        // C1-C5 JSON carries no U-Net key; FV without a U-Net (or C1 with one) is refused.
        assert!(!Arch::c1_small().to_json().contains("unet"));
        let mut bad = fv.clone();
        bad.unet_channels = 0;
        assert!(bad.validate().is_err());
        let mut bad = Arch::c1_small();
        bad.unet_channels = 8;
        assert!(bad.validate().is_err());
        assert!(Arch::from_json(r#"{"config":"fv","views":5,"grid":4,"rate":2,"layers":4,"channels":8,"concat_input":true,"unet_channels":8}"#).is_err());
    }

    #[test]
    fn residuals_every_two_layers() {
        let a = Arch::c1_small();
        let r: Vec<_> = (0..8).map(|i| a.residual_from(i)).collect();
        assert_eq!(r, [None, None, None, Some(0), None, Some(2), None, Some(4)]);
    }

    #[test]
    fn invalid_architectures_are_refused() {
        let mut a = Arch::c1_small();
        a.rate = 3;
        assert!(a.validate().is_err());
        assert!(Arch::from_json(
            r#"{"config":"c1","rate":2,"layers":1,"channels":8,"concat_input":false}"#
        )
        .is_err());
        assert!(Arch::from_json(
            r#"{"config":"c9","rate":2,"layers":4,"channels":8,"concat_input":false}"#
        )
        .is_err());
        assert!(Arch::from_json(r#"{"config":"c3","foci":[1.0,0.5],"rate":2,"layers":4,"channels":8,"concat_input":false}"#).is_err());
        assert!(Arch::preset("c2").is_err());
    }
}
