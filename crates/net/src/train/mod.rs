//! Training with candle (chosen over burn by measured step time and simplicity; see the
//! crate README). The model runs the same [`crate::graph::forward`] as CPU inference.
//!
//! Losses (DeepFocus, sec. 3 and its released code), with `e = prediction - target` and
//! `dx`, `dy` its horizontal and vertical finite differences:
//! - log-L1 (C1, C3): `log10 mean|e| + 0.5 (log10 mean|dx e| + log10 mean|dy e|)`;
//! - log-L2 (C4, C5): the same with squared errors (the PSNR form).
//!
//! The log makes the loss scale-free: every halving of the error lowers it by the same amount,
//! so late training is not starved of gradient. C4 is trained through the retinal model
//! ([`retina`]): the loss is on the focal stack its layers produce, never on the layers.

pub mod conv;
pub mod data;
pub mod model;
pub mod refine_data;
pub mod retina;
pub mod trainer;

pub use model::{Adam, CandleNet};
pub use trainer::{train, TrainConfig, TrainEvent};

use candle_core::{Result, Tensor};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LossKind {
    LogL1,
    LogL2,
}

impl LossKind {
    pub fn for_task(task: &crate::Task) -> LossKind {
        match task {
            crate::Task::C1 | crate::Task::C3 { .. } => LossKind::LogL1,
            crate::Task::C4 { .. }
            | crate::Task::C5 { .. }
            | crate::Task::Fv { .. }
            | crate::Task::C1r { .. }
            | crate::Task::C4r { .. }
            | crate::Task::C5r { .. } => LossKind::LogL2,
        }
    }
}

/// The DeepFocus loss of `pred` against `target`, both NCHW.
pub fn loss(pred: &Tensor, target: &Tensor, kind: LossKind) -> Result<Tensor> {
    let e = (pred - target)?;
    let (_, _, h, w) = e.dims4()?;
    let dx = (e.narrow(3, 1, w - 1)? - e.narrow(3, 0, w - 1)?)?;
    let dy = (e.narrow(2, 1, h - 1)? - e.narrow(2, 0, h - 1)?)?;
    let log10 = |t: &Tensor| -> Result<Tensor> {
        let m = match kind {
            LossKind::LogL1 => t.abs()?.mean_all()?,
            LossKind::LogL2 => t.sqr()?.mean_all()?,
        };
        // The floor keeps a perfect fit from giving -inf.
        (m + 1e-10)?.log()? * std::f64::consts::LOG10_E
    };
    log10(&e)? + ((log10(&dx)? + log10(&dy)?)? * 0.5)?
}

/// sRGB encoding of linear values in [0, 1], differentiable (the metrics' encoding: the
/// refinement nets train on the error the PSNR they are judged by measures).
pub fn srgb(x: &Tensor) -> Result<Tensor> {
    const CUT: f64 = 0.003_130_8;
    let low = (x * 12.92)?;
    let high = ((x.maximum(CUT)?.powf(1.0 / 2.4)? * 1.055)? - 0.055)?;
    x.le(CUT)?.where_cond(&low, &high)
}

/// `log10` of the mean squared error of `pred` against `target` (NCHW), over the pixels
/// where `mask` (N x 1 x H x W) is 1 when given: -PSNR / 10 for a peak of 1.
pub fn log_mse(pred: &Tensor, target: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    let e2 = (pred - target)?.sqr()?;
    let mse = match mask {
        None => e2.mean_all()?,
        Some(m) => {
            let c = e2.dim(1)? as f64;
            let count = (m.sum_all()? * c)?;
            (e2.broadcast_mul(m)?.sum_all()? / count.maximum(1.0)?)?
        }
    };
    (mse + 1e-10)?.log()? * std::f64::consts::LOG10_E
}
