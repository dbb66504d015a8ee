//! Images kept in GPU memory ([`GpuImage`]): a method's output left in the buffer it was
//! written to, so that a display on the same device shows it without a copy to the host. Only
//! a consumer that needs the pixels on the host reads it back ([`GpuImage::read`], counted by
//! the [`super::Gpu`] that made it: [`super::Gpu::images_read_back`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::context::{BufRef, Frame, GpuContext};
use super::GpuError;
use crate::error::RenderError;
use dioptra_core::{DepthMap, Diopters, Plane, RgbImage, Rgbd};

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

/// Planar colour: R plane, then G, then B.
pub(crate) fn planar(img: &RgbImage) -> Vec<f32> {
    let mut v = Vec::with_capacity(3 * img.width() * img.height());
    for c in &img.channels {
        v.extend_from_slice(c.data());
    }
    v
}

/// An RGB-D image in a storage buffer of a [`GpuContext`]'s device (a view synthesised
/// there): four packed planes, red, green, blue (linear) and depth (diopters). Cloning it
/// shares the buffer.
#[derive(Clone)]
pub struct GpuRgbd {
    ctx: Arc<GpuContext>,
    buf: BufRef,
    width: usize,
    height: usize,
    depth_bound: (Diopters, Diopters),
    reads: Option<Arc<AtomicU64>>,
}

impl std::fmt::Debug for GpuRgbd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRgbd")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("adapter", &self.ctx.adapter().name)
            .finish()
    }
}

impl GpuRgbd {
    /// `buf` holds the four planes from its start; every depth in it lies in `depth_bound`.
    pub(crate) fn new(
        ctx: &Arc<GpuContext>,
        buf: BufRef,
        (width, height): (usize, usize),
        depth_bound: (Diopters, Diopters),
    ) -> GpuRgbd {
        GpuRgbd {
            ctx: ctx.clone(),
            buf,
            width,
            height,
            depth_bound,
            reads: None,
        }
    }

    /// Its readbacks counted in `reads`.
    pub(crate) fn counted_by(mut self, reads: &Arc<AtomicU64>) -> GpuRgbd {
        self.reads = Some(reads.clone());
        self
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Nearest and farthest depth it may hold, known without reading it back: an uploaded
    /// image's own range; a synthesised view's, its inputs' range and 0 D (a pixel nothing was
    /// seen near).
    pub fn depth_bound(&self) -> (Diopters, Diopters) {
        self.depth_bound
    }

    /// Its colour, in GPU memory (the same buffer).
    pub fn color(&self) -> GpuImage {
        GpuImage {
            ctx: self.ctx.clone(),
            buf: self.buf.clone(),
            layout: ImageLayout::packed(self.width, self.height, 0),
            reads: self.reads.clone(),
        }
    }

    /// Copies it to the host (one submission), counted by its maker.
    pub fn read(&self) -> Result<Rgbd, RenderError> {
        let n = self.width * self.height;
        let mut f = Frame::new(&self.ctx)?;
        let r = f.read(&self.buf, 16 * n as u64);
        let (rb, _) = f.finish()?;
        if let Some(r) = &self.reads {
            r.fetch_add(1, Ordering::Relaxed);
        }
        let data = rb.f32s(r);
        let color = ImageLayout::packed(self.width, self.height, 0).image(&data)?;
        let depth = data
            .get(3 * n..4 * n)
            .ok_or_else(|| GpuError::Validation("short RGB-D readback".into()))?;
        let depth = Plane::from_vec(self.width, self.height, depth.to_vec())?;
        Ok(Rgbd::new(color, DepthMap::from_diopters(depth)?)?)
    }
}

/// A GPU method's RGB-D input: on the host (uploaded by the frame that first reads it) or
/// already in GPU memory (a view synthesised there: nothing crosses to the device).
#[derive(Debug, Clone, Copy)]
pub enum RgbdInput<'a> {
    Host(&'a Rgbd),
    Gpu(&'a GpuRgbd),
}

impl<'a> From<&'a Rgbd> for RgbdInput<'a> {
    fn from(r: &'a Rgbd) -> Self {
        RgbdInput::Host(r)
    }
}

impl<'a> From<&'a GpuRgbd> for RgbdInput<'a> {
    fn from(r: &'a GpuRgbd) -> Self {
        RgbdInput::Gpu(r)
    }
}

impl RgbdInput<'_> {
    pub fn width(&self) -> usize {
        match self {
            RgbdInput::Host(r) => r.width(),
            RgbdInput::Gpu(g) => g.width,
        }
    }
    pub fn height(&self) -> usize {
        match self {
            RgbdInput::Host(r) => r.height(),
            RgbdInput::Gpu(g) => g.height,
        }
    }

    /// Nearest and farthest depth: a host image's own range, a GPU one's bound
    /// ([`GpuRgbd::depth_bound`]); what a method sizes its blur's reach by.
    pub fn depth_range(&self) -> Option<(Diopters, Diopters)> {
        match self {
            RgbdInput::Host(r) => r.depth.range(),
            RgbdInput::Gpu(g) => Some(g.depth_bound),
        }
    }

    /// Not empty (the CPU's `check_rgbd`).
    pub(crate) fn check(&self) -> Result<(), RenderError> {
        if self.width() == 0 || self.height() == 0 {
            return Err(crate::error::invalid("input image is empty"));
        }
        Ok(())
    }

    /// Its planar colour and its depth map as storage buffers of `f`'s device: a host image
    /// uploaded, a GPU one's colour bound where it is and its depth copied on the device.
    pub(crate) fn buffers(
        &self,
        ctx: &GpuContext,
        f: &mut Frame,
    ) -> Result<(BufRef, BufRef), RenderError> {
        match self {
            RgbdInput::Host(r) => Ok((
                f.upload("colour image", &planar(&r.color))?,
                f.upload("depth map", r.depth.data())?,
            )),
            RgbdInput::Gpu(g) => {
                if !std::ptr::eq(Arc::as_ptr(&g.ctx), ctx) {
                    return Err(GpuError::Validation(
                        "an RGB-D input in another GPU context's memory".into(),
                    )
                    .into());
                }
                let n = (g.width * g.height) as u64;
                let depth = f.scratch("depth map", 4 * n)?;
                f.copy(&g.buf, 12 * n, &depth, 0, 4 * n);
                Ok((g.buf.clone(), depth))
            }
        }
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
