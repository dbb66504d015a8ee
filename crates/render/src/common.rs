//! Checks and geometry shared by the methods.

use crate::error::{invalid, RenderError};
use dioptra_core::{Diopters, EyeModel, Rgbd};

/// The eye model for an image `width` pixels wide (the field stays the same), validated.
pub fn eye_for(eye: &EyeModel, width: usize) -> Result<EyeModel, RenderError> {
    let w =
        u32::try_from(width).map_err(|_| invalid(format!("image width {width} is too large")))?;
    Ok(eye.with_width(w).validated()?)
}

/// An eye's focus. 0 D is optical infinity; below it the eye focuses beyond infinity (a
/// relaxed hyperopic eye, or a lens set to a negative power), and the circle of confusion
/// still follows from |depth - focus|. (The networks of `dioptra-net` take the same range.)
pub fn check_focus(q: Diopters) -> Result<(), RenderError> {
    if q.0.is_finite() && q.0.abs() < 1000.0 {
        Ok(())
    } else {
        Err(invalid(format!(
            "focus {q} is invalid: expected finite and -1000 < q < 1000 D"
        )))
    }
}

/// A display plane's distance: optical infinity (0 D) or nearer.
pub(crate) fn check_plane(q: Diopters) -> Result<(), RenderError> {
    if q.0.is_finite() && q.0 >= 0.0 && q.0 < 1000.0 {
        Ok(())
    } else {
        Err(invalid(format!(
            "display plane {q} is invalid: expected finite and 0 <= q < 1000 D"
        )))
    }
}

pub(crate) fn check_rgbd(input: &Rgbd) -> Result<(), RenderError> {
    if input.width() == 0 || input.height() == 0 {
        return Err(invalid("input image is empty"));
    }
    Ok(())
}

/// Largest circle-of-confusion diameter (pixels) over the image for focus `q`.
pub(crate) fn max_coc(input: &Rgbd, eye: &EyeModel, q: Diopters) -> f32 {
    coc_over(input.depth.range(), eye, q)
}

/// Largest circle-of-confusion diameter (pixels) for focus `q` over depths in `range`.
pub(crate) fn coc_over(range: Option<(Diopters, Diopters)>, eye: &EyeModel, q: Diopters) -> f32 {
    match range {
        Some((lo, hi)) => eye.coc_px(lo, q).max(eye.coc_px(hi, q)),
        None => 0.0,
    }
}
