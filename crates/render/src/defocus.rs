//! The defocus methods for RGB-D input and their CPU implementation: the choice a caller
//! passes to [`crate::Backend::defocus`], here below the backend so that the methods built on
//! a focal stack (the spectral decomposition's targets) can name it.

use crate::error::{invalid, RenderError};
use crate::foveated::Foveation;
use crate::gather::gather;
use crate::lightfield::{LightFieldParams, LightFieldPrep};
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use std::str::FromStr;

/// Settings of the pyramid method.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PyramidParams {
    /// Render at full resolution only around this gaze, coarser outside as acuity falls
    /// ([`crate::foveated`]); `None`: every pixel at full resolution.
    pub foveation: Option<Foveation>,
}

/// A defocus method for RGB-D input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DefocusMethod {
    Gather,
    /// Gather's sums with every blur of 6 px or more spread at the resolution it leaves:
    /// bounded work per pixel (see [`crate::pyramid`]); foveated around a gaze when asked.
    Pyramid(PyramidParams),
    LightField(LightFieldParams),
}

impl FromStr for DefocusMethod {
    type Err = RenderError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "gather" => Ok(DefocusMethod::Gather),
            "pyramid" => Ok(DefocusMethod::Pyramid(PyramidParams::default())),
            "lightfield" => Ok(DefocusMethod::LightField(LightFieldParams::default())),
            _ => Err(invalid(format!(
                "unknown defocus method {s:?}: expected gather, pyramid or lightfield"
            ))),
        }
    }
}

/// Depth-of-field images of `input` at every focus in `foci` on the CPU (the CPU backend's
/// [`crate::Backend::defocus`]); `progress` is called with the slices done. Work that does
/// not depend on focus is done once.
pub fn defocus(
    input: &Rgbd,
    foci: &[Diopters],
    eye: &EyeModel,
    method: DefocusMethod,
    mut progress: impl FnMut(usize),
) -> Result<Vec<RgbImage>, RenderError> {
    let mut out = Vec::with_capacity(foci.len());
    match method {
        DefocusMethod::Gather => {
            for &q in foci {
                out.push(gather(input, q, eye)?);
                progress(out.len());
            }
        }
        DefocusMethod::Pyramid(p) => {
            for &q in foci {
                out.push(match p.foveation {
                    None => crate::pyramid::pyramid(input, q, eye)?,
                    Some(f) => crate::foveated::foveated(input, q, eye, &f)?.image,
                });
                progress(out.len());
            }
        }
        DefocusMethod::LightField(p) => {
            let prep = LightFieldPrep::new(input, eye, p)?;
            for &q in foci {
                out.push(prep.render(q)?);
                progress(out.len());
            }
        }
    }
    Ok(out)
}
