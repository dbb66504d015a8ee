//! The transfer pass on the GPU (`shaders/transfer.wgsl`), and the table both GPU passes read.

use std::sync::Arc;

use super::EncodeLut;
use crate::gpu::{BufRef, Frame, GpuContext, GpuError, GpuImage, ImageLayout, ShaderKernel};

/// transfer.wgsl with the table's reader joined after it.
pub(crate) const TRANSFER_WGSL: &str = concat!(
    include_str!("../../shaders/transfer.wgsl"),
    include_str!("../../shaders/transfer_lut.wgsl")
);

const ENCODE: ShaderKernel = ShaderKernel {
    source: TRANSFER_WGSL,
    entry: "encode",
    read_only: 2,
    read_write: 1,
};

/// transfer.wgsl's `Params`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct EncodeParams {
    width: u32,
    height: u32,
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
    lut_len: u32,
    _pad0: u32,
    _pad1: u32,
}

/// An [`EncodeLut`] in GPU memory, uploaded once.
#[derive(Clone)]
pub struct GpuEncodeLut {
    ctx: Arc<GpuContext>,
    buf: BufRef,
    len: u32,
}

impl GpuEncodeLut {
    pub fn new(ctx: &Arc<GpuContext>, lut: &EncodeLut) -> Result<GpuEncodeLut, GpuError> {
        Ok(GpuEncodeLut {
            ctx: ctx.clone(),
            buf: ctx.upload_resident("the transfer table", lut.values())?,
            len: lut.values().len() as u32,
        })
    }
    pub(crate) fn buffer(&self) -> &wgpu::Buffer {
        &self.buf.buffer
    }
    pub(crate) fn len(&self) -> u32 {
        self.len
    }
    pub(crate) fn ctx(&self) -> &Arc<GpuContext> {
        &self.ctx
    }
}

/// The transfer pass on the GPU: `image`'s linear light to code values, in a new image in
/// GPU memory (packed planes) on the same device.
pub fn encode_on_gpu(image: &GpuImage, lut: &GpuEncodeLut) -> Result<GpuImage, GpuError> {
    let ctx = image.context();
    if !Arc::ptr_eq(ctx, &lut.ctx) {
        return Err(GpuError::Validation(
            "the transfer table and the image are on different GPU contexts".into(),
        ));
    }
    let l: ImageLayout = image.layout();
    let out_layout = ImageLayout::packed(l.width, l.height, 0);
    let mut f = Frame::new(ctx)?;
    let out = f.scratch("the encoded image", 4 * out_layout.span().max(1) as u64)?;
    let params = EncodeParams {
        width: l.width as u32,
        height: l.height as u32,
        offset: l.offset as u32,
        row_pitch: l.row_pitch as u32,
        plane_pitch: l.plane_pitch as u32,
        lut_len: lut.len,
        _pad0: 0,
        _pad1: 0,
    };
    let wg = 16u32;
    f.dispatch_shader(
        &ENCODE,
        &params,
        &[image.buf(), &lut.buf, &out],
        [
            (l.width as u32).div_ceil(wg),
            (l.height as u32).div_ceil(wg),
            1,
        ],
    )?;
    f.finish()?;
    Ok(GpuImage::new(ctx, out, out_layout))
}

/// An image uploaded to GPU memory (packed planes), for a pass that reads one.
pub fn upload_image(
    ctx: &Arc<GpuContext>,
    image: &dioptra_core::RgbImage,
) -> Result<GpuImage, GpuError> {
    let mut data = Vec::with_capacity(3 * image.width() * image.height());
    for p in &image.channels {
        data.extend_from_slice(p.data());
    }
    let buf = ctx.upload_resident("an image", &data)?;
    Ok(GpuImage::new(
        ctx,
        buf,
        ImageLayout::packed(image.width(), image.height(), 0),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::uniforms::{rust_uniform, wgsl_uniform};

    #[test]
    fn the_uniform_matches_the_shader() {
        let rust = rust_uniform!(EncodeParams; width, height, offset, row_pitch, plane_pitch, lut_len, _pad0, _pad1);
        assert_eq!(wgsl_uniform(TRANSFER_WGSL), rust);
    }
}
