//! Images kept in GPU memory ([`GpuImage`]): a method's output left in the buffer it was
//! written to, so that a display on the same device shows it without a copy to the host. Only
//! a consumer that needs the pixels on the host reads it back ([`GpuImage::read`], counted by
//! the [`super::Gpu`] that made it: [`super::Gpu::images_read_back`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::context::{BufRef, Frame, GpuContext};
use super::GpuError;
use dioptra_core::{Plane, RgbImage};

/// Where an image's pixels are in its buffer, counted in f32 values: planar linear RGB (the
/// red plane, then green, then blue), rows top first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageLayout {
    pub width: usize,
    pub height: usize,
    /// From the buffer's start to pixel (0, 0) of the red plane.
    pub offset: usize,
    /// From one row to the next.
    pub row_pitch: usize,
    /// From one colour plane to the next.
    pub plane_pitch: usize,
}

impl ImageLayout {
    /// Three `width` x `height` planes one after another from `offset`.
    pub fn packed(width: usize, height: usize, offset: usize) -> ImageLayout {
        ImageLayout {
            width,
            height,
            offset,
            row_pitch: width,
            plane_pitch: width * height,
        }
    }

    /// Values from `offset` to the image's last one, inclusive.
    pub fn span(&self) -> usize {
        if self.width == 0 || self.height == 0 {
            return 0;
        }
        2 * self.plane_pitch + (self.height - 1) * self.row_pitch + self.width
    }

    /// The image from `data`, which holds the buffer's values from `offset` on.
    pub(crate) fn image(&self, data: &[f32]) -> Result<RgbImage, GpuError> {
        if data.len() < self.span() {
            return Err(GpuError::Validation(format!(
                "readback of {} values, expected {}",
                data.len(),
                self.span()
            )));
        }
        let plane = |c: usize| {
            let start = c * self.plane_pitch;
            let mut v = Vec::with_capacity(self.width * self.height);
            for y in 0..self.height {
                let row = start + y * self.row_pitch;
                v.extend_from_slice(&data[row..row + self.width]);
            }
            Plane::from_vec(self.width, self.height, v)
        };
        let bad = |e: dioptra_core::InputError| GpuError::Validation(e.to_string());
        RgbImage::from_planes(
            plane(0).map_err(bad)?,
            plane(1).map_err(bad)?,
            plane(2).map_err(bad)?,
        )
        .map_err(bad)
    }
}

/// An RGB image in a storage buffer of a [`GpuContext`]'s device. Cloning it shares the
/// buffer, which returns to the context's pool when the last clone is dropped.
#[derive(Clone)]
pub struct GpuImage {
    ctx: Arc<GpuContext>,
    buf: BufRef,
    layout: ImageLayout,
    /// Counts its readbacks (its maker's count).
    reads: Option<Arc<AtomicU64>>,
}

impl std::fmt::Debug for GpuImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuImage")
            .field("layout", &self.layout)
            .field("adapter", &self.ctx.adapter().name)
            .finish()
    }
}

impl GpuImage {
    pub(crate) fn new(ctx: &Arc<GpuContext>, buf: BufRef, layout: ImageLayout) -> GpuImage {
        GpuImage {
            ctx: ctx.clone(),
            buf,
            layout,
            reads: None,
        }
    }

    /// Its readbacks counted in `reads`.
    pub(crate) fn counted_by(mut self, reads: &Arc<AtomicU64>) -> GpuImage {
        self.reads = Some(reads.clone());
        self
    }

    pub fn width(&self) -> usize {
        self.layout.width
    }
    pub fn height(&self) -> usize {
        self.layout.height
    }
    pub fn layout(&self) -> ImageLayout {
        self.layout
    }
    /// The context (and so the device) whose memory holds it.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }
    /// The storage buffer holding it (bind it whole: the layout says where the image is).
    pub fn buffer(&self) -> &wgpu::Buffer {
        &self.buf.buffer
    }

    /// Its buffer's handle (held by a frame that reads the image).
    pub(crate) fn buf(&self) -> &BufRef {
        &self.buf
    }

    /// Copies the image to the host (one submission), counted by its maker.
    pub fn read(&self) -> Result<RgbImage, GpuError> {
        let l = self.layout;
        let mut f = Frame::new(&self.ctx)?;
        let r = f.read_range(&self.buf, 4 * l.offset as u64, 4 * l.span() as u64);
        let (rb, _) = f.finish()?;
        if let Some(r) = &self.reads {
            r.fetch_add(1, Ordering::Relaxed);
        }
        l.image(&rb.f32s(r))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_padded_layout_reads_the_image_inside_the_padding() {
        // Two 2 x 1 images in 4 x 2 padded planes, the image at (1, 1) of each plane.
        let (pw, ph) = (4, 2);
        let data: Vec<f32> = (0..2 * 3 * pw * ph).map(|i| i as f32).collect();
        let second = ImageLayout {
            width: 2,
            height: 1,
            offset: 3 * pw * ph + pw + 1,
            row_pitch: pw,
            plane_pitch: pw * ph,
        };
        assert_eq!(second.span(), 2 * 8 + 2);
        let img = second.image(&data[second.offset..]).unwrap();
        assert_eq!(img.channels[0].data(), &[29.0, 30.0]);
        assert_eq!(img.channels[1].data(), &[37.0, 38.0]);
        assert_eq!(img.channels[2].data(), &[45.0, 46.0]);
        let short = &data[second.offset..second.offset + second.span() - 1];
        assert!(second.image(short).is_err());
        let packed = ImageLayout::packed(3, 2, 0);
        assert_eq!(packed.span(), 18);
        assert_eq!(ImageLayout::packed(0, 2, 5).span(), 0);
    }
}
