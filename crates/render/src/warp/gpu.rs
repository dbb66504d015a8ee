//! The pre-warp on the GPU: a render pipeline (`shaders/warp.wgsl`) built once per target
//! format, a mesh uploaded once, and a draw per frame from an image in GPU memory into a
//! colour target (a window's surface; [`warp_to_image`] draws into a float texture and reads
//! it back, for the parity test and a headless sink on the GPU).

use std::sync::Arc;

use wgpu::util::DeviceExt;

use super::{WarpMesh, WarpVertex};
use crate::gpu::{GpuContext, GpuError, GpuImage};
use crate::transfer::gpu::GpuEncodeLut;
use dioptra_core::{Plane, RgbImage};

/// warp.wgsl with the transfer table's reader joined after it.
pub(crate) const WARP_WGSL: &str = concat!(
    include_str!("../../shaders/warp.wgsl"),
    include_str!("../../shaders/transfer_lut.wgsl")
);

/// warp.wgsl's `Params`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct WarpParams {
    width: u32,
    height: u32,
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
    lut_len: u32,
    scale: f32,
    centre_x: f32,
    centre_y: f32,
    target_width: f32,
    target_height: f32,
    _pad: u32,
}

/// A [`WarpMesh`] in GPU memory (vertex and index buffers, and the uniform its draws read),
/// uploaded once. Its parameters are written when a draw is recorded, so a mesh is drawn at
/// most once per submission (one eye's mesh, once per frame).
pub struct GpuWarpMesh {
    ctx: Arc<GpuContext>,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    params: wgpu::Buffer,
    count: u32,
    panel: [usize; 2],
    source: [usize; 2],
    centre: [f32; 2],
}

impl GpuWarpMesh {
    pub fn new(ctx: &Arc<GpuContext>, mesh: &WarpMesh) -> GpuWarpMesh {
        let device = ctx.device();
        GpuWarpMesh {
            ctx: ctx.clone(),
            vertices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("warp mesh vertices"),
                contents: bytemuck::cast_slice(mesh.vertices()),
                usage: wgpu::BufferUsages::VERTEX,
            }),
            indices: device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("warp mesh indices"),
                contents: bytemuck::cast_slice(mesh.indices()),
                usage: wgpu::BufferUsages::INDEX,
            }),
            params: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("warp params"),
                size: std::mem::size_of::<WarpParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            count: mesh.indices().len() as u32,
            panel: mesh.panel(),
            source: mesh.source(),
            centre: mesh.centre(),
        }
    }
    pub fn panel(&self) -> [usize; 2] {
        self.panel
    }
    /// The source image's size it reads (width, height).
    pub fn source(&self) -> [usize; 2] {
        self.source
    }
}

/// The warp's render pipeline for one target format, built once.
pub struct WarpPipeline {
    ctx: Arc<GpuContext>,
    format: wgpu::TextureFormat,
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    /// Bound as the table when a draw does not encode.
    no_lut: wgpu::Buffer,
}

impl WarpPipeline {
    /// The pipeline drawing into targets of `format` (a `*Srgb` format encodes sRGB in the
    /// hardware: give no transfer table then; a `*Unorm` one with the panel's table writes
    /// its code values).
    pub fn new(ctx: &Arc<GpuContext>, format: wgpu::TextureFormat) -> WarpPipeline {
        let device = ctx.device();
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("warp.wgsl"),
            source: wgpu::ShaderSource::Wgsl(WARP_WGSL.into()),
        });
        let storage = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("warp"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                storage(1),
                storage(2),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("warp"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let f2 = wgpu::VertexFormat::Float32x2;
        let attributes = [
            wgpu::VertexAttribute {
                format: f2,
                offset: 0,
                shader_location: 0,
            },
            wgpu::VertexAttribute {
                format: f2,
                offset: 8,
                shader_location: 1,
            },
            wgpu::VertexAttribute {
                format: f2,
                offset: 16,
                shader_location: 2,
            },
            wgpu::VertexAttribute {
                format: f2,
                offset: 24,
                shader_location: 3,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32,
                offset: 32,
                shader_location: 4,
            },
        ];
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("warp"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<WarpVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &attributes,
                })],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                // The mesh's triangles wind either way after the y flip: draw both.
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let no_lut = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("no transfer table"),
            contents: bytemuck::cast_slice(&[0.0f32; 4]),
            usage: wgpu::BufferUsages::STORAGE,
        });
        WarpPipeline {
            ctx: ctx.clone(),
            format,
            pipeline,
            layout,
            no_lut,
        }
    }

    pub fn format(&self) -> wgpu::TextureFormat {
        self.format
    }

    /// Records the warp of `source` through `mesh` into the render pass `pass` (whose target
    /// has this pipeline's format; its viewport says where the panel is on it). `scale` and
    /// `lut` as [`super::WarpDraw`]'s. The parameters go in the mesh's uniform (written on the
    /// queue, before the submission that holds `pass` runs); the bind group is made here, as
    /// the source's buffer changes from frame to frame.
    pub fn draw_in_pass(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        source: &GpuImage,
        mesh: &GpuWarpMesh,
        scale: f32,
        lut: Option<&GpuEncodeLut>,
    ) -> Result<(), GpuError> {
        let same = |c: &Arc<GpuContext>| Arc::ptr_eq(c, &self.ctx);
        if !same(source.context()) || !same(&mesh.ctx) || lut.is_some_and(|l| !same(l.ctx())) {
            return Err(GpuError::Validation(
                "the warp's pipeline, mesh, table and source are not all on one GPU context".into(),
            ));
        }
        let l = source.layout();
        if [l.width, l.height] != mesh.source {
            return Err(GpuError::Validation(format!(
                "the warp's mesh reads a {}x{} source, given {}x{}",
                mesh.source[0], mesh.source[1], l.width, l.height
            )));
        }
        if !(scale.is_finite() && scale > 0.0) {
            return Err(GpuError::Validation(format!(
                "a warp scale of {scale}: expected a number above 0"
            )));
        }
        let params = WarpParams {
            width: l.width as u32,
            height: l.height as u32,
            offset: l.offset as u32,
            row_pitch: l.row_pitch as u32,
            plane_pitch: l.plane_pitch as u32,
            lut_len: lut.map_or(0, |t| t.len()),
            scale,
            centre_x: mesh.centre[0],
            centre_y: mesh.centre[1],
            target_width: mesh.panel[0] as f32,
            target_height: mesh.panel[1] as f32,
            _pad: 0,
        };
        let device = self.ctx.device();
        self.ctx
            .queue()
            .write_buffer(&mesh.params, 0, bytemuck::bytes_of(&params));
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("warp"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: mesh.params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: source.buffer().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: lut.map_or(&self.no_lut, |t| t.buffer()).as_entire_binding(),
                },
            ],
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &bind, &[]);
        pass.set_vertex_buffer(0, mesh.vertices.slice(..));
        pass.set_index_buffer(mesh.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..mesh.count, 0, 0..1);
        Ok(())
    }
}

/// The warp drawn into a float texture of the panel's size and read back: the GPU twin of
/// [`super::warp_cpu`], one submission. `pipeline` must be for `Rgba32Float`.
pub fn warp_to_image(
    pipeline: &WarpPipeline,
    source: &GpuImage,
    mesh: &GpuWarpMesh,
    scale: f32,
    lut: Option<&GpuEncodeLut>,
) -> Result<RgbImage, GpuError> {
    if pipeline.format != wgpu::TextureFormat::Rgba32Float {
        return Err(GpuError::Validation(format!(
            "warp_to_image draws into Rgba32Float; this pipeline is for {:?}",
            pipeline.format
        )));
    }
    let ctx = &pipeline.ctx;
    let (device, queue) = (ctx.device(), ctx.queue());
    let [w, h] = mesh.panel;
    let max = device.limits().max_texture_dimension_2d as usize;
    if w > max || h > max {
        return Err(GpuError::TooLarge {
            what: format!("a {w}x{h} warp target"),
            bytes: (16 * w * h) as u64,
            max: (16 * max * max) as u64,
        });
    }
    let size = wgpu::Extent3d {
        width: w as u32,
        height: h as u32,
        depth_or_array_layers: 1,
    };
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("warp target"),
        size,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba32Float,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    });
    let view = texture.create_view(&Default::default());
    let row_bytes = (16 * w as u32).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
        * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("warp readback"),
        size: u64::from(row_bytes) * h as u64,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&Default::default());
    {
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("warp"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pipeline.draw_in_pass(&mut pass, source, mesh, scale, lut)?;
    }
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &readback,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row_bytes),
                rows_per_image: None,
            },
        },
        size,
    );
    let submitted = queue.submit([encoder.finish()]);
    readback.map_async(wgpu::MapMode::Read, .., |_| {});
    device
        .poll(wgpu::PollType::Wait {
            submission_index: Some(submitted),
            timeout: None,
        })
        .map_err(|e| match e {
            wgpu::PollError::Timeout => GpuError::Validation("GPU wait timed out".into()),
            _ => GpuError::DeviceLost,
        })?;
    let bytes = readback
        .get_mapped_range(..)
        .map_err(|e| GpuError::Validation(e.to_string()))?
        .to_vec();
    readback.unmap();
    let mut planes = [
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
    ];
    for y in 0..h {
        let row: &[f32] = bytemuck::cast_slice(&bytes[y * row_bytes as usize..][..16 * w]);
        for x in 0..w {
            for (c, p) in planes.iter_mut().enumerate() {
                p[y * w + x] = row[4 * x + c];
            }
        }
    }
    let bad = |e: dioptra_core::InputError| GpuError::Validation(e.to_string());
    let [r, g, b] = planes;
    RgbImage::from_planes(
        Plane::from_vec(w, h, r).map_err(bad)?,
        Plane::from_vec(w, h, g).map_err(bad)?,
        Plane::from_vec(w, h, b).map_err(bad)?,
    )
    .map_err(bad)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::uniforms::{rust_uniform, wgsl_uniform};

    #[test]
    fn the_uniform_and_the_vertex_match_the_shader() {
        let rust = rust_uniform!(WarpParams; width, height, offset, row_pitch, plane_pitch,
            lut_len, scale, centre_x, centre_y, target_width, target_height, _pad);
        assert_eq!(wgsl_uniform(WARP_WGSL), rust);
        // The vertex attributes' offsets above against the Rust vertex.
        assert_eq!(std::mem::offset_of!(WarpVertex, source), 8);
        assert_eq!(std::mem::offset_of!(WarpVertex, valid), 32);
        assert_eq!(std::mem::size_of::<WarpVertex>(), 36);
    }
}
