//! What a sink is handed to show: a rendered [`Frame`] (each eye's images) and the marker
//! patch to draw over it ([`MarkerDraw`]).

use dioptra_core::{Diopters, RgbImage};
use serde::Serialize;

use super::config::Corner;
use crate::render::FrameImage;

/// A rendered frame: one image (varifocal, light field) or one per focal plane (multifocal).
#[derive(Debug, Clone)]
pub struct Frame {
    pub number: u64,
    /// The focus it was rendered for.
    pub focus: Diopters,
    /// Shared, so a sink can hand the frame to another thread without copying the images.
    /// On a stereo layout (`display.layout`): the left eye's.
    pub layers: std::sync::Arc<Vec<FrameImage>>,
    /// On a stereo layout: the right eye's images, as many as `layers`.
    pub right: Option<std::sync::Arc<Vec<FrameImage>>>,
    /// The marker patch to draw over it in this present, if the rig has one.
    pub marker: Option<MarkerDraw>,
}

/// The marker patch as a sink draws it in one present.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct MarkerDraw {
    pub corner: Corner,
    /// Side, pixels.
    pub size: u32,
    pub white: bool,
}

impl MarkerDraw {
    /// The patch in a `width` x `height` image (rows from the top): x, y, width, height,
    /// clipped to the image.
    pub fn rect(&self, width: u32, height: u32) -> [u32; 4] {
        let (w, h) = (self.size.min(width), self.size.min(height));
        let x = match self.corner {
            Corner::TopLeft | Corner::BottomLeft => 0,
            Corner::TopRight | Corner::BottomRight => width - w,
        };
        let y = match self.corner {
            Corner::TopLeft | Corner::TopRight => 0,
            Corner::BottomLeft | Corner::BottomRight => height - h,
        };
        [x, y, w, h]
    }

    /// Paints the patch into `image` (linear light: white 1, black 0).
    pub fn paint(&self, image: &mut RgbImage) {
        let (width, height) = (image.width(), image.height());
        let [x0, y0, w, h] = self.rect(
            u32::try_from(width).unwrap_or(u32::MAX),
            u32::try_from(height).unwrap_or(u32::MAX),
        );
        let v = if self.white { 1.0 } else { 0.0 };
        for plane in &mut image.channels {
            for y in y0 as usize..(y0 + h) as usize {
                let row = y * width;
                plane.data_mut()[row + x0 as usize..row + (x0 + w) as usize].fill(v);
            }
        }
    }
}
