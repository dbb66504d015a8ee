//! The GPU twin of the headless sink's panel composition ([`super::placement::draw_into`]): a
//! wgpu blit that draws each eye's image at the rectangle [`super::placement`] gives, into any
//! texture view (the window's sRGB surface), and the marker patch in the panel's corner (the
//! GPU twin of [`MarkerDraw::paint`]). Pipelines, sampler, a texture and layout uniform per eye
//! and the staging bytes are made once; WGSL in `shaders/blit.wgsl`.
//!
//! Frames are linear light. A frame on the host is packed as 8-bit sRGB into an
//! `Rgba8UnormSrgb` texture (sampling decodes to linear); a frame in GPU memory is read by the
//! blit's second fragment shader from its planar f32 buffer, clamped to [0, 1] as the packing
//! does. Drawn into an sRGB view, the hardware encodes on write.

use dioptra_core::image::linear_to_srgb;
use dioptra_core::RgbImage;
use dioptra_render::gpu::GpuImage;
use rayon::prelude::*;

use super::placement::Rect;
use super::MarkerDraw;

/// Packs a linear-light frame as 8-bit sRGB RGBA rows (alpha 255) into `out`, for an
/// `Rgba8UnormSrgb` texture. Values outside 0..1 are clamped, NaN is black: each byte is
/// `round(255 linear_to_srgb(v))`, by table ([`Srgb8`]); rows in parallel.
pub fn pack_rgba8_srgb(image: &RgbImage, out: &mut Vec<u8>) {
    let [r, g, b] = &image.channels;
    let (w, n) = (image.width(), r.data().len());
    out.clear();
    if n == 0 {
        return;
    }
    out.resize(n * 4, 255);
    let table = Srgb8::get();
    out.par_chunks_mut(w * 4)
        .zip(r.data().par_chunks(w))
        .zip(g.data().par_chunks(w))
        .zip(b.data().par_chunks(w))
        .for_each(|(((row, r), g), b)| {
            for (((px, &r), &g), &b) in row.chunks_exact_mut(4).zip(r).zip(g).zip(b) {
                px[..3].copy_from_slice(&[table.encode(r), table.encode(g), table.encode(b)]);
            }
        });
}

/// The 8-bit sRGB encoding by formula: what [`Srgb8`]'s table gives, byte for byte.
fn srgb8_exact(v: f32) -> u8 {
    (linear_to_srgb(v) * 255.0).round() as u8
}

/// The bits of a value's pattern below its table bucket (the bucket: the pattern's top bits;
/// over [0, 1] the pattern rises with the value).
const SRGB8_BUCKET_BITS: u32 = 16;

/// [`srgb8_exact`] by table. The byte is a step function of the value that rises by one at
/// 255 thresholds, found once by bisection of the formula itself; each bucket of bit patterns
/// holds at most one (they are over 10^5 patterns apart, a bucket 2^16), so per bucket the
/// byte at its start and the offset where it rises give every byte exactly.
struct Srgb8 {
    /// Per bucket: the byte at its start (low 8 bits) and above them the offset in the bucket
    /// where the byte rises by one (`1 << SRGB8_BUCKET_BITS`: it does not).
    table: Vec<u32>,
}

impl Srgb8 {
    fn get() -> &'static Srgb8 {
        static TABLE: std::sync::OnceLock<Srgb8> = std::sync::OnceLock::new();
        TABLE.get_or_init(Srgb8::new)
    }

    /// The first bit pattern in [0, 1] whose byte is `k` or more, for `k` in 1..=255.
    fn thresholds() -> Vec<u32> {
        let one = 1.0f32.to_bits();
        (1..=255u8)
            .map(|k| {
                // The byte at `lo` is below `k`, at `hi` it is `k` or more.
                let (mut lo, mut hi) = (0u32, one);
                while hi - lo > 1 {
                    let mid = lo + (hi - lo) / 2;
                    if srgb8_exact(f32::from_bits(mid)) >= k {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                hi
            })
            .collect()
    }

    fn new() -> Srgb8 {
        let thresholds = Srgb8::thresholds();
        let size = 1u32 << SRGB8_BUCKET_BITS;
        let buckets = (1.0f32.to_bits() >> SRGB8_BUCKET_BITS) + 1;
        let table = (0..buckets)
            .map(|i| {
                let start = i << SRGB8_BUCKET_BITS;
                let below = thresholds.partition_point(|&t| t <= start) as u32;
                let rise = thresholds
                    .get(below as usize)
                    .filter(|&&t| t - start < size)
                    .map_or(size, |&t| t - start);
                (rise << 8) | below
            })
            .collect();
        Srgb8 { table }
    }

    #[inline]
    fn encode(&self, v: f32) -> u8 {
        // NaN, negatives and -0 are 0; above 1 is 1.
        let bits = if v > 0.0 { v.min(1.0).to_bits() } else { 0 };
        let e = self.table[(bits >> SRGB8_BUCKET_BITS) as usize];
        let low = bits & ((1 << SRGB8_BUCKET_BITS) - 1);
        (e & 0xff) as u8 + u8::from(low >= e >> 8)
    }
}

/// Where the blit reads the frame it draws.
enum Source {
    /// The frame texture's bind group.
    Texture(wgpu::BindGroup),
    /// A frame left in GPU memory: the bind group of its buffer and layout.
    Buffer(wgpu::BindGroup),
}

/// A [`GpuImage`]'s layout, as `blit.wgsl`'s `Layout` reads it.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LayoutUniform {
    width: u32,
    height: u32,
    offset: u32,
    row_pitch: u32,
    plane_pitch: u32,
    _pad: [u32; 3],
}

/// One image the blit draws (an eye's): its texture (remade only when its size changes), the
/// layout uniform of a frame in GPU memory, and where the next draw reads it.
struct Slot {
    /// The frame texture and its size.
    texture: Option<(wgpu::Texture, (u32, u32))>,
    layout_uniform: wgpu::Buffer,
    source: Option<Source>,
}

/// The blit: pipelines, sampler, a [`Slot`] per eye, staging bytes, made once; draws each
/// slot's image at its rectangle ([`super::placement`]) into any view of `target_format`.
pub struct Blit {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
    buffer_pipeline: wgpu::RenderPipeline,
    buffer_layout: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    slots: [Slot; 2],
    staging: Vec<u8>,
    /// The marker patch's pipelines (white, black), and the patch the next draw shows.
    patch: [wgpu::RenderPipeline; 2],
    marker: Option<MarkerDraw>,
}

const FRAME_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;

fn bind_entry(binding: u32, ty: wgpu::BindingType) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty,
        count: None,
    }
}

impl Blit {
    pub fn new(device: &wgpu::Device, target_format: wgpu::TextureFormat) -> Blit {
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("blit"),
            source: wgpu::ShaderSource::Wgsl(include_str!("../../shaders/blit.wgsl").into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("blit"),
            entries: &[
                bind_entry(
                    0,
                    wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                ),
                bind_entry(
                    1,
                    wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                ),
            ],
        });
        let buffer_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("blit from a buffer"),
            entries: &[
                bind_entry(
                    2,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                bind_entry(
                    3,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
            ],
        });
        let pipeline_for = |layout: Option<&wgpu::BindGroupLayout>, fragment: &str| {
            let layouts = [layout];
            let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("blit"),
                bind_group_layouts: if layout.is_some() { &layouts } else { &[] },
                immediate_size: 0,
            });
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("blit"),
                layout: Some(&pipeline_layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some("vs_main"),
                    compilation_options: Default::default(),
                    buffers: &[],
                },
                primitive: wgpu::PrimitiveState::default(),
                depth_stencil: None,
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(fragment),
                    compilation_options: Default::default(),
                    targets: &[Some(target_format.into())],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let pipeline = pipeline_for(Some(&layout), "fs_main");
        let buffer_pipeline = pipeline_for(Some(&buffer_layout), "fs_buffer");
        let patch = [
            pipeline_for(None, "fs_white"),
            pipeline_for(None, "fs_black"),
        ];
        // Nearest: a frame shown at the monitor's own size is copied pixel for pixel.
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("blit"),
            ..Default::default()
        });
        let slot = || Slot {
            texture: None,
            layout_uniform: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("frame layout"),
                size: std::mem::size_of::<LayoutUniform>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            source: None,
        };
        Blit {
            pipeline,
            layout,
            buffer_pipeline,
            buffer_layout,
            sampler,
            slots: [slot(), slot()],
            staging: Vec::new(),
            patch,
            marker: None,
        }
    }

    /// The marker patch the next draws show over the frame (`None`: none).
    pub fn set_marker(&mut self, marker: Option<MarkerDraw>) {
        self.marker = marker;
    }

    /// Packs and uploads `image` into slot `slot`'s texture (0 or 1: an eye's), and draws
    /// that slot from it from now on.
    pub fn upload(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        slot: usize,
        image: &RgbImage,
    ) {
        let size = (image.width() as u32, image.height() as u32);
        let Some(sl) = self.slots.get(slot) else {
            return;
        };
        if sl.texture.as_ref().is_none_or(|t| t.1 != size) {
            let texture = self.frame_texture(device, size);
            self.slots[slot].texture = Some((texture, size));
        }
        let Some((texture, _)) = &self.slots[slot].texture else {
            return;
        };
        pack_rgba8_srgb(image, &mut self.staging);
        queue.write_texture(
            texture.as_image_copy(),
            &self.staging,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(size.0 * 4),
                rows_per_image: Some(size.1),
            },
            wgpu::Extent3d {
                width: size.0,
                height: size.1,
                depth_or_array_layers: 1,
            },
        );
        let view = texture.create_view(&Default::default());
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("frame"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&self.sampler),
                },
            ],
        });
        self.slots[slot].source = Some(Source::Texture(bind_group));
    }

    /// Draws slot `slot` from `image`, in GPU memory of this device, from now on: no copy,
    /// only its layout is written.
    pub fn show_buffer(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        slot: usize,
        image: &GpuImage,
    ) {
        let Some(sl) = self.slots.get_mut(slot) else {
            return;
        };
        let l = image.layout();
        let u32_of = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        let uniform = LayoutUniform {
            width: u32_of(l.width),
            height: u32_of(l.height),
            offset: u32_of(l.offset),
            row_pitch: u32_of(l.row_pitch),
            plane_pitch: u32_of(l.plane_pitch),
            _pad: [0; 3],
        };
        queue.write_buffer(&sl.layout_uniform, 0, bytemuck::bytes_of(&uniform));
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("frame in GPU memory"),
            layout: &self.buffer_layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: sl.layout_uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: image.buffer().as_entire_binding(),
                },
            ],
        });
        sl.source = Some(Source::Buffer(bind_group));
    }

    /// Draws each `(slot, rect)` of `draws`, the slot's image at `rect` (1:1 where `rect` is
    /// its size, nearest pixel otherwise), into `target` (cleared to black), and the marker
    /// patch in the target's corner. Rectangles are inside the target ([`placement`] gives
    /// only such); one that is not is left out.
    ///
    /// [`placement`]: super::placement
    pub fn encode(
        &self,
        enc: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
        draws: &[(usize, Rect)],
    ) {
        let drawn: Result<(), std::convert::Infallible> =
            self.encode_with(enc, target, target_size, draws, |_| Ok(()));
        let Ok(()) = drawn;
    }

    /// [`Blit::encode`], with `more` recorded in the same render pass after the slots' images
    /// and before the marker patch (the panel passes' warped images,
    /// [`super::panel_draw`]). `more`'s error is returned after the pass is closed.
    pub fn encode_with<E>(
        &self,
        enc: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
        draws: &[(usize, Rect)],
        more: impl FnOnce(&mut wgpu::RenderPass<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("blit"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                    store: wgpu::StoreOp::Store,
                },
            })],
            ..Default::default()
        });
        let (tw, th) = target_size;
        for &(slot, r) in draws {
            let (pipeline, bind_group) = match self.slots.get(slot).and_then(|s| s.source.as_ref())
            {
                Some(Source::Texture(bg)) => (&self.pipeline, bg),
                Some(Source::Buffer(bg)) => (&self.buffer_pipeline, bg),
                None => continue,
            };
            if !set_rect(&mut pass, r, target_size) {
                continue;
            }
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bind_group, &[]);
            pass.draw(0..3, 0..1);
        }
        let more = more(&mut pass);
        // The patch goes in the panel's corner, where the photodiode is, wherever the images are.
        if let Some(m) = self.marker {
            let [px, py, pw, ph] = m.rect(tw, th);
            if pw > 0 && ph > 0 {
                pass.set_viewport(0.0, 0.0, tw as f32, th as f32, 0.0, 1.0);
                pass.set_scissor_rect(px, py, pw, ph);
                pass.set_pipeline(&self.patch[usize::from(!m.white)]);
                pass.draw(0..3, 0..1);
            }
        }
        more
    }

    fn frame_texture(&self, device: &wgpu::Device, size: (u32, u32)) -> wgpu::Texture {
        device.create_texture(&wgpu::TextureDescriptor {
            label: Some("frame"),
            size: wgpu::Extent3d {
                width: size.0,
                height: size.1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: FRAME_FORMAT,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        })
    }
}

/// Sets `pass`'s viewport and scissor to `r` (integer, so pixel centres land on texel
/// centres: 1:1 at the image's size); false, and nothing set, when `r` is empty or not inside
/// a target of `target_size`.
pub(crate) fn set_rect(pass: &mut wgpu::RenderPass<'_>, r: Rect, target_size: (u32, u32)) -> bool {
    let (tw, th) = target_size;
    let inside = r.width > 0
        && r.height > 0
        && u64::from(r.x) + u64::from(r.width) <= u64::from(tw)
        && u64::from(r.y) + u64::from(r.height) <= u64::from(th);
    if inside {
        pass.set_viewport(
            r.x as f32,
            r.y as f32,
            r.width as f32,
            r.height as f32,
            0.0,
            1.0,
        );
        pass.set_scissor_rect(r.x, r.y, r.width, r.height);
    }
    inside
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::config::Scale;

    /// blit.wgsl's `Layout` as naga lays it out is [`LayoutUniform`]: the same members at the
    /// same offsets, and the Rust struct padded to a 16-byte multiple as a uniform binding
    /// wants.
    #[test]
    fn the_layout_uniform_matches_the_shader() {
        let module = naga::front::wgsl::parse_str(include_str!("../../shaders/blit.wgsl"))
            .unwrap_or_else(|e| panic!("blit.wgsl does not parse: {e}"));
        let mut layouter = naga::proc::Layouter::default();
        layouter.update(module.to_ctx()).unwrap();
        let (_, ty) = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some("Layout"))
            .unwrap();
        let naga::TypeInner::Struct { members, span } = &ty.inner else {
            panic!("Layout is not a struct");
        };
        let shader: Vec<(String, u32, u32)> = members
            .iter()
            .map(|m| {
                (
                    m.name.clone().unwrap_or_default(),
                    m.offset,
                    layouter[m.ty].size,
                )
            })
            .collect();
        let field = |name: &str, offset: usize| (name.to_string(), offset as u32, 4u32);
        use std::mem::offset_of;
        assert_eq!(
            shader,
            [
                field("width", offset_of!(LayoutUniform, width)),
                field("height", offset_of!(LayoutUniform, height)),
                field("offset", offset_of!(LayoutUniform, offset)),
                field("row_pitch", offset_of!(LayoutUniform, row_pitch)),
                field("plane_pitch", offset_of!(LayoutUniform, plane_pitch)),
            ]
        );
        let size = std::mem::size_of::<LayoutUniform>() as u32;
        assert!(
            size >= *span && size.is_multiple_of(16),
            "{size} bytes for a {span}-byte uniform"
        );
    }

    #[test]
    fn frames_pack_as_srgb_rgba_rows() {
        // 2 x 2: row 0 = black, white; row 1 = linear 0.5 grey, out-of-range and NaN.
        let img = RgbImage::from_interleaved(
            2,
            2,
            &[
                0.0,
                0.0,
                0.0,
                1.0,
                1.0,
                1.0, //
                0.5,
                0.5,
                0.5,
                -1.0,
                7.0,
                f32::NAN,
            ],
        )
        .unwrap();
        let mut out = vec![1, 2, 3];
        pack_rgba8_srgb(&img, &mut out);
        assert_eq!(
            out,
            [
                0, 0, 0, 255, 255, 255, 255, 255, //
                188, 188, 188, 255, 0, 255, 0, 255,
            ]
        );
    }

    /// Every byte the table packs is the formula's: the specials (0, -0, 1, negatives, above
    /// 1, infinities, NaN, the smallest subnormal), every 997th bit pattern from 0 to 2, every
    /// 9973rd negative down to -2, and every pattern within 300 of each point where the byte
    /// rises (it changes only there), in each channel.
    #[test]
    fn packing_gives_the_formulas_byte_for_every_value() {
        let rises = Srgb8::thresholds();
        assert!(
            rises
                .windows(2)
                .all(|p| p[0] >> SRGB8_BUCKET_BITS < p[1] >> SRGB8_BUCKET_BITS),
            "two rises in one bucket: the table would be wrong"
        );
        let two = 2.0f32.to_bits();
        let mut values: Vec<f32> = vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            1.5,
            255.0,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::MIN_POSITIVE,
            f32::from_bits(1),
            -f32::from_bits(1),
            1.0 - f32::EPSILON / 2.0,
            1.0 + f32::EPSILON,
        ];
        values.extend((0..two).step_by(997).map(f32::from_bits));
        values.extend((0..two).step_by(9973).map(|b| -f32::from_bits(b)));
        for &t in &rises {
            values.extend((t.saturating_sub(300)..=t + 300).map(f32::from_bits));
        }
        let width = 1024;
        values.resize(values.len().next_multiple_of(width), 0.5);
        let n = values.len();
        let channel = |shift: usize| {
            let v = (0..n).map(|i| values[(i + shift) % n]).collect();
            dioptra_core::Plane::from_vec(width, n / width, v).unwrap()
        };
        let img = RgbImage::from_planes(channel(0), channel(1), channel(2)).unwrap();
        let mut out = vec![7; 3];
        pack_rgba8_srgb(&img, &mut out);
        assert_eq!(out.len(), 4 * n);
        for (i, px) in out.chunks_exact(4).enumerate() {
            for (c, &byte) in px[..3].iter().enumerate() {
                let v = img.channels[c].data()[i];
                assert_eq!(byte, srgb8_exact(v), "{v:e} ({:#010x})", v.to_bits());
            }
            assert_eq!(px[3], 255);
        }
    }

    /// [`packing_gives_the_formulas_byte_for_every_value`] over every value in [0, 1] (the
    /// others clamp to its ends): a billion values, 2.4 s on two cores in the test profile.
    #[test]
    fn the_table_gives_the_formulas_byte_for_every_value_in_range() {
        use rayon::prelude::*;
        let table = Srgb8::get();
        let wrong = (0..=1.0f32.to_bits())
            .into_par_iter()
            .filter(|&b| table.encode(f32::from_bits(b)) != srgb8_exact(f32::from_bits(b)))
            .count();
        assert_eq!(wrong, 0);
    }

    fn fit(image: (u32, u32), surface: (u32, u32)) -> Rect {
        crate::display::placement::placement(
            crate::config::DisplayLayout::One,
            Scale::Fit,
            surface,
            dioptra_core::Side::Left,
            image,
            [0, 0],
        )
        .unwrap()
    }

    /// `Some` of a GPU object, or `None` (test skipped, said on stderr) when there is no
    /// adapter and DIOPTRA_REQUIRE_GPU is not 1, as in dioptra-render's GPU tests; with it 1,
    /// a missing adapter fails the test.
    pub(crate) fn gpu_or_skip<T, E: std::fmt::Display>(made: Result<T, E>) -> Option<T> {
        match made {
            Ok(t) => Some(t),
            Err(e) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
                eprintln!("skipped: no GPU adapter ({e})");
                None
            }
            Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1): {e}"),
        }
    }

    /// A headless device (lavapipe here), or `None` (test skipped, [`gpu_or_skip`]).
    fn headless_device() -> Option<(wgpu::Device, wgpu::Queue)> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(desc);
        let adapter = gpu_or_skip(pollster::block_on(
            instance.request_adapter(&wgpu::RequestAdapterOptions::default()),
        ))?;
        Some(pollster::block_on(adapter.request_device(&Default::default())).unwrap())
    }

    /// Draws what `blit` shows into a new `Rgba8UnormSrgb` texture of `size` and reads it back.
    fn draw_and_read(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        blit: &Blit,
        size: (u32, u32),
        draws: &[(usize, Rect)],
    ) -> Vec<u8> {
        read_target(
            device,
            queue,
            wgpu::TextureFormat::Rgba8UnormSrgb,
            size,
            |enc, view| blit.encode(enc, view, size, draws),
        )
    }

    /// What `encode` draws into a new texture of `format` (4 bytes a pixel) and `size`, read
    /// back: rows of RGBA bytes.
    pub(crate) fn read_target(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        format: wgpu::TextureFormat,
        size: (u32, u32),
        encode: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::TextureView),
    ) -> Vec<u8> {
        let (tw, th) = size;
        let extent = wgpu::Extent3d {
            width: tw,
            height: th,
            depth_or_array_layers: 1,
        };
        let target = device.create_texture(&wgpu::TextureDescriptor {
            label: None,
            size: extent,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        // Rows padded to the copy alignment, dropped again below.
        let row = (tw * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: u64::from(row * th),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&Default::default());
        encode(&mut enc, &target.create_view(&Default::default()));
        enc.copy_texture_to_buffer(
            target.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(row),
                    rows_per_image: Some(th),
                },
            },
            extent,
        );
        queue.submit([enc.finish()]);
        readback
            .slice(..)
            .map_async(wgpu::MapMode::Read, |r| r.unwrap());
        device.poll(wgpu::PollType::wait_indefinitely()).unwrap();
        let mapped = readback.slice(..).get_mapped_range().unwrap();
        mapped
            .chunks(row as usize)
            .flat_map(|r| &r[..(tw * 4) as usize])
            .copied()
            .collect()
    }

    /// The blit (shader, texture packing, sRGB target) without a window: a frame drawn into an
    /// sRGB texture of twice its size reads back as the frame's sRGB bytes, pixel-doubled, with
    /// black bars where the aspect differs.
    #[test]
    fn the_blit_draws_the_frame_srgb_encoded_and_letterboxed() {
        let Some((device, queue)) = headless_device() else {
            return;
        };
        let mut blit = Blit::new(&device, wgpu::TextureFormat::Rgba8UnormSrgb);
        // A 4 x 2 frame of distinct linear values on a 64 x 64 target: scale 16, bars of 16 rows.
        let vals: Vec<f32> = (0..24).map(|i| i as f32 / 23.0).collect();
        let img = RgbImage::from_interleaved(4, 2, &vals).unwrap();
        let (tw, th) = (64u32, 64u32);
        // Twice, to check the texture made once is reused and rewritten.
        let at = fit((4, 2), (tw, th));
        assert_eq!(at, Rect::new(0, 16, 64, 32));
        blit.upload(&device, &queue, 0, &RgbImage::new(4, 2, [1.0, 0.0, 0.0]));
        draw_and_read(&device, &queue, &blit, (tw, th), &[(0, at)]);
        blit.upload(&device, &queue, 0, &img);
        let got = draw_and_read(&device, &queue, &blit, (tw, th), &[(0, at)]);
        assert!(blit.slots[0].texture.is_some());
        let mut packed = Vec::new();
        pack_rgba8_srgb(&img, &mut packed);
        // Scale 16: the frame fills rows 16..48; rows above and below are black.
        let px =
            |x: u32, y: u32| &got[((y * tw + x) * 4) as usize..((y * tw + x) * 4 + 4) as usize];
        for y in 0..th {
            for x in 0..tw {
                let want: [u8; 4] = if (16..48).contains(&y) {
                    let (fx, fy) = (x / 16, (y - 16) / 16);
                    let i = ((fy * 4 + fx) * 4) as usize;
                    packed[i..i + 4].try_into().unwrap()
                } else {
                    [0, 0, 0, 255]
                };
                let have = px(x, y);
                // Decode and re-encode through the GPU may differ by one step.
                for c in 0..4 {
                    assert!(
                        have[c].abs_diff(want[c]) <= 1,
                        "pixel ({x}, {y}): {have:?}, want {want:?}"
                    );
                }
            }
        }
    }

    /// The marker patch is drawn in the surface's corner over the letterboxed frame, white or
    /// black, as the headless sink paints it ([`MarkerDraw::paint`], its CPU twin).
    #[test]
    fn the_marker_patch_is_drawn_in_the_panels_corner() {
        use crate::config::Corner;
        let Some((device, queue)) = headless_device() else {
            return;
        };
        let mut blit = Blit::new(&device, wgpu::TextureFormat::Rgba8UnormSrgb);
        let grey = RgbImage::new(4, 2, [0.2; 3]);
        blit.upload(&device, &queue, 0, &grey);
        let (tw, th) = (64u32, 64u32);
        for (corner, white) in [
            (Corner::TopLeft, true),
            (Corner::BottomRight, false),
            (Corner::TopRight, true),
        ] {
            let m = MarkerDraw {
                corner,
                size: 8,
                white,
            };
            blit.set_marker(Some(m));
            let got = draw_and_read(
                &device,
                &queue,
                &blit,
                (tw, th),
                &[(0, fit((4, 2), (tw, th)))],
            );
            // The CPU twin on an image of the target's size: the frame letterboxed (rows 16..48
            // grey, the rest black), then the patch painted.
            let mut want = RgbImage::new(tw as usize, th as usize, [0.0; 3]);
            for plane in &mut want.channels {
                for y in 16..48 {
                    plane.data_mut()[y * tw as usize..(y + 1) * tw as usize].fill(0.2);
                }
            }
            m.paint(&mut want);
            let mut packed = Vec::new();
            pack_rgba8_srgb(&want, &mut packed);
            for (i, (a, b)) in got.iter().zip(&packed).enumerate() {
                assert!(
                    a.abs_diff(*b) <= 1,
                    "{corner:?}: byte {i} (pixel {}, {}): {a} drawn, {b} painted",
                    (i / 4) as u32 % tw,
                    (i / 4) as u32 / tw
                );
            }
        }
        // Without a patch the corner shows the frame again (here: the black bar).
        blit.set_marker(None);
        let got = draw_and_read(
            &device,
            &queue,
            &blit,
            (tw, th),
            &[(0, fit((4, 2), (tw, th)))],
        );
        assert_eq!(&got[..4], &[0, 0, 0, 255]);
    }

    /// A frame the renderer left in GPU memory is drawn from its buffer on the render's own
    /// device as the texture path draws its readback (within one sRGB step), and drawing it
    /// reads nothing back.
    #[test]
    fn a_frame_in_gpu_memory_is_drawn_as_its_readback_is() {
        let Some(gpu) = gpu_or_skip(dioptra_render::Gpu::new(None)) else {
            return;
        };
        // One plane at the depth of every pixel: linear blending gives the colour itself,
        // out-of-range values included (clamped by both paths).
        let vals: Vec<f32> = (0..30).map(|i| i as f32 / 20.0 - 0.2).collect();
        let color = RgbImage::from_interleaved(5, 2, &vals).unwrap();
        let depth =
            dioptra_core::DepthMap::from_diopters(dioptra_core::Plane::new(5, 2, 1.0)).unwrap();
        let input = dioptra_core::Rgbd::new(color, depth).unwrap();
        let kept = gpu
            .linear_blend_on_gpu(&input, &[dioptra_core::Diopters(1.0)])
            .unwrap()
            .remove(0);
        let ctx = gpu.context();
        let (device, queue) = (ctx.device(), ctx.queue());
        let mut blit = Blit::new(device, wgpu::TextureFormat::Rgba8UnormSrgb);
        let reads = gpu.images_read_back();
        let at = [(1, fit((5, 2), (64, 64)))];
        blit.show_buffer(device, queue, 1, &kept);
        let from_buffer = draw_and_read(device, queue, &blit, (64, 64), &at);
        assert_eq!(gpu.images_read_back(), reads, "drawn without a readback");
        blit.upload(device, queue, 1, &kept.read().unwrap());
        let from_texture = draw_and_read(device, queue, &blit, (64, 64), &at);
        assert_eq!(from_buffer.len(), from_texture.len());
        for (i, (a, b)) in from_buffer.iter().zip(&from_texture).enumerate() {
            assert!(
                a.abs_diff(*b) <= 1,
                "byte {i}: {a} from the buffer, {b} from the texture"
            );
        }
        // Not all black: the frame is there (12 x 12 pixels per frame pixel, centred).
        assert!(from_buffer.chunks(4).any(|p| p[0] > 200), "no bright pixel");
    }

    /// Side by side, each eye's image drawn at the rectangle placement gives (1:1, and scaled
    /// with fit) reads back as the headless sink composes the panel
    /// ([`crate::display::placement::draw_into`], its CPU twin), pixel for pixel.
    #[test]
    fn each_eye_is_drawn_at_its_place_as_the_headless_panel_has_it() {
        use crate::config::DisplayLayout;
        use crate::display::placement::{draw_into, placement};
        let Some((device, queue)) = headless_device() else {
            return;
        };
        let mut blit = Blit::new(&device, wgpu::TextureFormat::Rgba8UnormSrgb);
        // Every pixel distinct: red the column, green the row, blue the eye.
        let pattern = |w: usize, h: usize, tag: f32| {
            let v: Vec<f32> = (0..w * h)
                .flat_map(|i| {
                    [
                        (i % w + 1) as f32 / w as f32,
                        (i / w + 1) as f32 / h as f32,
                        tag,
                    ]
                })
                .collect();
            RgbImage::from_interleaved(w, h, &v).unwrap()
        };
        let (left, right) = (pattern(9, 5, 0.2), pattern(11, 7, 0.9));
        let (tw, th) = (64u32, 16u32);
        for (scale, offsets) in [
            (Scale::Exact, [[3, -2], [-4, 1]]),
            (Scale::Fit, [[0, 0], [2, 1]]),
        ] {
            let mut want = RgbImage::new(tw as usize, th as usize, [0.0; 3]);
            let mut draws = Vec::new();
            for (slot, (side, img)) in [
                (dioptra_core::Side::Left, &left),
                (dioptra_core::Side::Right, &right),
            ]
            .into_iter()
            .enumerate()
            {
                let size = (img.width() as u32, img.height() as u32);
                let r = placement(
                    DisplayLayout::SideBySide,
                    scale,
                    (tw, th),
                    side,
                    size,
                    offsets[slot],
                )
                .unwrap();
                blit.upload(&device, &queue, slot, img);
                draw_into(&mut want, img, r);
                draws.push((slot, r));
            }
            if scale == Scale::Exact {
                // By hand: the left half is 32 x 16; a 9 x 5 image centred at (11, 5), moved
                // (3, -2); the right one 11 x 7 at 32 + 10, 4, moved (-4, 1).
                assert_eq!(draws[0].1, Rect::new(14, 3, 9, 5));
                assert_eq!(draws[1].1, Rect::new(38, 5, 11, 7));
            }
            let got = draw_and_read(&device, &queue, &blit, (tw, th), &draws);
            let mut packed = Vec::new();
            pack_rgba8_srgb(&want, &mut packed);
            for (i, (a, b)) in got.iter().zip(&packed).enumerate() {
                assert!(
                    a.abs_diff(*b) <= 1,
                    "{scale:?}: byte {i} (pixel {}, {}): {a} drawn, {b} composed",
                    (i / 4) as u32 % tw,
                    (i / 4) as u32 / tw
                );
            }
        }
    }
}
