//! The rig's display output: a borderless fullscreen window on a chosen monitor (winit), drawn
//! with wgpu through a surface presented with vsync (`PresentMode::Fifo`).
//!
//! Threads. winit wants its event loop on the main thread (macOS requires it, and winit refuses
//! another thread elsewhere unless told otherwise), so with `[display] kind = "window"`
//! `dioptra serve` runs [`run_on_main_thread`]: the main thread opens the display, creates the
//! window and then only handles window events, while the daemon (its tokio runtime and every
//! task) runs on a thread of its own. Presenting blocks until a swapchain image is free (Fifo
//! paces to the monitor's refresh), so [`WindowSink`] never draws on the loop's thread either:
//! it hands each frame to a presenter thread, which owns the GPU objects. The newest frame
//! wins: a frame handed over while the previous one still waits for vsync replaces it (counted
//! in `GET /status` as `replaced`).
//!
//! One device. When the rig renders on the GPU, the window's surface is made from the render's
//! own wgpu instance and drawn with its device ([`dioptra_render::gpu::GpuContext`]): a frame
//! left in GPU memory ([`FrameImage::Gpu`]) is drawn straight from the buffer the render wrote,
//! with no copy to the host. Otherwise (the rig renders on the CPU, or the render's adapter
//! cannot present to this window) the window opens a device of its own, and a frame in GPU
//! memory is read back first (counted in `/status` render `images_read_back`).
//!
//! GPU objects are made once: the pipelines, sampler, frame texture (remade only if the frame
//! size changes) and a staging buffer for the packed pixels. Frames are linear light. A frame
//! on the host is packed as 8-bit sRGB into an `Rgba8UnormSrgb` texture (sampling decodes to
//! linear); a frame in GPU memory is read by the blit's second fragment shader from its planar
//! f32 buffer, clamped to [0, 1] as the packing does. The surface is viewed through an sRGB
//! format, so the hardware encodes on write: what the monitor gets is the sRGB encoding of the
//! frame, as in the PNGs the headless sink writes.
//!
//! Placement. Each eye's image is drawn at the rectangle
//! [`dioptra_rig::display::placement`] gives for the surface the system made (the viewport
//! set to it): 1:1 onto surface pixels with `display.scale = "exact"`, centred in its place
//! (the whole surface for layout `one`, its half of a side-by-side panel) and moved by
//! `display.eye_offset_px`; scaled to fit with `"fit"` (the letterbox). A frame that does not
//! fit, or (exact) a surface that is not its monitor's size, is not shown: counted in
//! `/status` (`misfit`), logged once per reason; the screen goes black rather than showing a
//! stimulus at the wrong size or place. The window asks for its monitor's size and position
//! as well as fullscreen, so that without a window manager it still covers the monitor; the
//! surface size obtained is logged and in `/status`. Layout `two-outputs` (a window per
//! monitor) is not supported by the window yet: `dioptra serve` refuses it naming
//! `display.layout`.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

use dioptra_core::image::linear_to_srgb;
use dioptra_core::{RgbImage, Timestamp};
use dioptra_render::gpu::{GpuContext, GpuImage};

use thiserror::Error;

use dioptra_rig::config::Scale;
use dioptra_rig::display::placement::{PlaceError, Placed, PlacementConfig, Placer, Rect};
use dioptra_rig::display::{DisplayError, DisplaySink, Frame, MarkerDraw};
use dioptra_rig::render::FrameImage;

pub use dioptra_rig::config::MonitorChoice;

/// The window draws layouts `one` and `side-by-side`; a window per monitor is not built yet.
pub fn window_layout_supported(layout: dioptra_rig::config::DisplayLayout) -> anyhow::Result<()> {
    if layout == dioptra_rig::config::DisplayLayout::TwoOutputs {
        anyhow::bail!(
            "display.layout = \"two-outputs\" with display.kind = \"window\" is not supported \
             yet (the window draws one monitor): use layout = \"side-by-side\" on one panel \
             spanning both eyes, or kind = \"headless\" (an image per eye)"
        );
    }
    Ok(())
}

#[derive(Debug, Error)]
pub enum WindowError {
    #[error(
        "no display: set DISPLAY/WAYLAND_DISPLAY or use [display] kind = \"headless\" in the rig config"
    )]
    NoDisplay,
    #[error("cannot open the display ({detail}); check DISPLAY/WAYLAND_DISPLAY or use [display] kind = \"headless\"")]
    Open { detail: String },
    #[error("display.monitor: {0}")]
    Monitor(String),
    #[error("cannot create the window: {0}")]
    Create(String),
    #[error("the window's GPU surface: {0}")]
    Gpu(String),
}

/// Whether a display server is named in the environment. winit would say the same in its own
/// words; this names the rig config's alternative.
pub fn check_display_env(
    wayland_display: Option<&str>,
    wayland_socket: Option<&str>,
    x11_display: Option<&str>,
) -> Result<(), WindowError> {
    let set = |v: Option<&str>| v.is_some_and(|s| !s.is_empty());
    if set(wayland_display) || set(wayland_socket) || set(x11_display) {
        Ok(())
    } else {
        Err(WindowError::NoDisplay)
    }
}

fn env_display_check() -> Result<(), WindowError> {
    let var = |k| std::env::var(k).ok();
    check_display_env(
        var("WAYLAND_DISPLAY").as_deref(),
        var("WAYLAND_SOCKET").as_deref(),
        var("DISPLAY").as_deref(),
    )
}

/// A monitor as the system lists it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MonitorInfo {
    pub name: Option<String>,
    pub size: (u32, u32),
    pub position: (i32, i32),
}

impl std::fmt::Display for MonitorInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:?} {}x{} at ({}, {})",
            self.name.as_deref().unwrap_or("(unnamed)"),
            self.size.0,
            self.size.1,
            self.position.0,
            self.position.1
        )
    }
}

/// Picks the monitor for `choice` (exact name, then the name ignoring case, or index); with no
/// choice, the primary monitor, else the first. The error lists what is there.
pub fn choose_monitor(
    monitors: &[MonitorInfo],
    choice: Option<&MonitorChoice>,
    primary: Option<usize>,
) -> Result<usize, String> {
    let list = || {
        if monitors.is_empty() {
            "the system lists no monitors".to_string()
        } else {
            let all: Vec<String> = monitors
                .iter()
                .enumerate()
                .map(|(i, m)| format!("{i}: {m}"))
                .collect();
            format!("available: {}", all.join(", "))
        }
    };
    match choice {
        None if monitors.is_empty() => Err(list()),
        None => Ok(primary.filter(|&p| p < monitors.len()).unwrap_or(0)),
        Some(MonitorChoice::Index(i)) if *i < monitors.len() => Ok(*i),
        Some(MonitorChoice::Index(i)) => Err(format!("there is no monitor {i}; {}", list())),
        Some(MonitorChoice::Name(n)) => {
            let by = |eq: &dyn Fn(&str) -> bool| {
                monitors
                    .iter()
                    .position(|m| m.name.as_deref().is_some_and(eq))
            };
            by(&|m| m == n)
                .or_else(|| by(&|m| m.eq_ignore_ascii_case(n)))
                .ok_or_else(|| format!("no monitor named {n:?}; {}", list()))
        }
    }
}

/// Packs a linear-light frame as 8-bit sRGB RGBA rows (alpha 255) into `out`, for an
/// `Rgba8UnormSrgb` texture. Values outside 0..1 are clamped, NaN is black.
pub fn pack_rgba8_srgb(image: &RgbImage, out: &mut Vec<u8>) {
    let [r, g, b] = &image.channels;
    out.clear();
    out.reserve(r.data().len() * 4);
    let enc = |v: f32| (linear_to_srgb(v) * 255.0).round() as u8;
    for ((&r, &g), &b) in r.data().iter().zip(g.data()).zip(b.data()) {
        out.extend_from_slice(&[enc(r), enc(g), enc(b), 255]);
    }
}

/// With `display.scale = "exact"` the surface must be its monitor's size (the panel the
/// offsets and places are measured on): the reason it is not, for `/status` and the log.
pub fn surface_check(
    scale: Scale,
    surface: (u32, u32),
    monitor: &str,
    monitor_size: (u32, u32),
) -> Result<(), String> {
    if scale == Scale::Fit || surface == monitor_size {
        return Ok(());
    }
    Err(format!(
        "the window's surface is {}x{} but {monitor} is {}x{} (no window manager made the \
         window fullscreen?): drawn 1:1 (display.scale = \"exact\") the images would not be \
         where the panel's places are; display.scale = \"fit\" shows them scaled to the \
         surface",
        surface.0, surface.1, monitor_size.0, monitor_size.1
    ))
}

/// The surface's configured format and the format its views are made in: an sRGB format
/// either way, so the blit's linear output is encoded. `None` when the surface offers neither
/// an sRGB format nor one with an sRGB twin.
pub fn surface_formats(
    offered: &[wgpu::TextureFormat],
) -> Option<(wgpu::TextureFormat, wgpu::TextureFormat)> {
    if let Some(&f) = offered.iter().find(|f| f.is_srgb()) {
        return Some((f, f));
    }
    offered
        .iter()
        .find(|f| f.add_srgb_suffix().is_srgb())
        .map(|&f| (f, f.add_srgb_suffix()))
}

/// A frame for the presenter: which image of which frame.
struct Job {
    frame: Frame,
    layer: usize,
    /// Refused by the sink (it does not fit): the screen goes black.
    blank: bool,
}

/// What the presenter thread reports, and the placement state it shares with the sink.
struct PresenterStats {
    presented: AtomicU64,
    replaced: AtomicU64,
    /// Wall-clock interval between the last two presents, ns.
    last_interval_ns: AtomicU64,
    error: Mutex<Option<String>>,
    /// The surface's size now (the presenter follows the window's).
    surface: Mutex<(u32, u32)>,
    placer: Mutex<Placer>,
    /// The monitor the window is on, and its size.
    monitor: String,
    monitor_size: (u32, u32),
}

impl PresenterStats {
    /// Layer `layer` of `frame`'s images placed on `surface`, or why it is not shown.
    fn place<'a>(
        &self,
        frame: &'a Frame,
        layer: usize,
        surface: (u32, u32),
    ) -> Result<Vec<Placed<'a>>, PlaceError> {
        let placer = dioptra_core::lock(&self.placer);
        surface_check(
            placer.config.scale,
            surface,
            &self.monitor,
            self.monitor_size,
        )
        .map_err(PlaceError::Surface)?;
        placer.place(frame, layer, surface)
    }
}

/// The mailbox between the sink and the presenter thread.
struct Mailbox {
    job: Mutex<(Option<Job>, bool)>,
    ready: Condvar,
}

/// Shows frames in the window; see the module doc for the threads.
pub struct WindowSink {
    mailbox: Arc<Mailbox>,
    stats: Arc<PresenterStats>,
    shown: u64,
    describe: String,
    presenter: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for WindowSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe)
    }
}

impl WindowSink {
    /// Sets up the GPU surface of `ready`'s window, on the render's device when `render` is
    /// given and its adapter can present to the window, and starts the presenter thread.
    /// Images are placed as `placement` says (`display.layout`, `scale`, `eye_offset_px`).
    pub fn new(
        ready: WindowReady,
        render: Option<Arc<GpuContext>>,
        placement: PlacementConfig,
    ) -> Result<WindowSink, WindowError> {
        let WindowReady {
            window,
            monitor,
            monitor_size,
        } = ready;
        let blitter = Blitter::new(window, render)?;
        let surface = (blitter.config.width, blitter.config.height);
        let describe = format!(
            "window on {monitor} ({}, {:?}, surface {}x{}, {})",
            blitter.adapter, blitter.config.format, surface.0, surface.1, blitter.device_note
        );
        log_surface(surface, &monitor, monitor_size);
        let mailbox = Arc::new(Mailbox {
            job: Mutex::new((None, false)),
            ready: Condvar::new(),
        });
        let stats = Arc::new(PresenterStats {
            presented: AtomicU64::new(0),
            replaced: AtomicU64::new(0),
            last_interval_ns: AtomicU64::new(0),
            error: Mutex::new(None),
            surface: Mutex::new(surface),
            placer: Mutex::new(Placer::new(placement)),
            monitor,
            monitor_size,
        });
        let (mb, st) = (mailbox.clone(), stats.clone());
        let presenter = std::thread::Builder::new()
            .name("dioptra-present".into())
            .spawn(move || presenter(blitter, &mb, &st))
            .map_err(|e| WindowError::Gpu(format!("cannot start the presenter thread: {e}")))?;
        Ok(WindowSink {
            mailbox,
            stats,
            shown: 0,
            describe,
            presenter: Some(presenter),
        })
    }

    fn hand_over(&mut self, frame: &Frame, layer: usize) -> Result<(), DisplayError> {
        if let Some(e) = dioptra_core::lock(&self.stats.error).clone() {
            return Err(DisplayError::Window(e));
        }
        // Placed on the surface as it is now: a frame that does not fit is not shown, and the
        // screen goes black rather than keep the previous stimulus.
        let surface = *dioptra_core::lock(&self.stats.surface);
        let placed = self.stats.place(frame, layer, surface);
        if let Err(e) = &placed {
            refused(&self.stats, e);
        } else if layer == 0 {
            dioptra_core::lock(&self.stats.placer).shown(frame);
        }
        let mut slot = dioptra_core::lock(&self.mailbox.job);
        if slot
            .0
            .replace(Job {
                frame: frame.clone(),
                layer,
                blank: placed.is_err(),
            })
            .is_some()
        {
            self.stats.replaced.fetch_add(1, Ordering::Relaxed);
        }
        self.mailbox.ready.notify_one();
        placed.map(|_| ()).map_err(DisplayError::NotShown)
    }
}

impl Drop for WindowSink {
    fn drop(&mut self) {
        dioptra_core::lock(&self.mailbox.job).1 = true;
        self.mailbox.ready.notify_one();
        if let Some(t) = self.presenter.take() {
            let _ = t.join();
        }
    }
}

impl DisplaySink for WindowSink {
    /// Hands the frame to the presenter; it is on screen at the first vsync after it is drawn.
    /// Returns `now`: the actual present pace is in [`DisplaySink::status`].
    fn present(&mut self, frame: &Frame, now: Timestamp) -> Result<Timestamp, DisplayError> {
        self.hand_over(frame, 0)?;
        self.shown += 1;
        Ok(now)
    }
    fn present_layer(
        &mut self,
        frame: &Frame,
        layer: usize,
        start: Timestamp,
    ) -> Result<Timestamp, DisplayError> {
        self.hand_over(frame, layer)?;
        if layer == 0 {
            self.shown += 1;
        }
        Ok(start)
    }
    fn shown(&self) -> u64 {
        self.shown
    }
    fn describe(&self) -> String {
        self.describe.clone()
    }
    fn status(&self) -> serde_json::Value {
        let s = &self.stats;
        let interval = s.last_interval_ns.load(Ordering::Relaxed);
        let surface = *dioptra_core::lock(&s.surface);
        let mut v = serde_json::json!({
            "sink": self.describe,
            "shown": self.shown,
            "presented": s.presented.load(Ordering::Relaxed),
            "replaced": s.replaced.load(Ordering::Relaxed),
            "last_present_interval_ms": (interval > 0).then(|| interval as f64 / 1e6),
            "error": dioptra_core::lock(&s.error).clone(),
            "monitor": s.monitor,
            "monitor_size": [s.monitor_size.0, s.monitor_size.1],
            "surface_is_monitor_size": surface == s.monitor_size,
        });
        if let (Some(o), serde_json::Value::Object(p)) = (
            v.as_object_mut(),
            dioptra_core::lock(&s.placer).status(Some(surface)),
        ) {
            o.extend(p);
        }
        v
    }
}

/// Logs the surface size the system gave the window (a warning where it is not the monitor's).
/// On stderr, as `dioptra serve` reports (it installs no log subscriber).
fn log_surface(surface: (u32, u32), monitor: &str, monitor_size: (u32, u32)) {
    let (w, h) = surface;
    let (mw, mh) = monitor_size;
    if surface == monitor_size {
        eprintln!("dioptra serve: surface {w}x{h} on {monitor} ({mw}x{mh})");
    } else {
        eprintln!(
            "dioptra serve: warning: surface {w}x{h} on {monitor} ({mw}x{mh}): not the \
             monitor's size (no window manager made the window fullscreen?)"
        );
    }
}

/// Counts a frame not shown; prints each reason the first time.
fn refused(stats: &PresenterStats, why: &PlaceError) {
    if dioptra_core::lock(&stats.placer).refused(why) {
        eprintln!("dioptra serve: frame not shown: {why} (counted in /status display.misfit)");
    }
}

/// The presenter thread: draws the newest job until the sink is dropped.
fn presenter(mut blitter: Blitter, mailbox: &Mailbox, stats: &PresenterStats) {
    let mut last: Option<Instant> = None;
    loop {
        let job = {
            let mut slot = dioptra_core::lock(&mailbox.job);
            loop {
                if slot.1 {
                    return;
                }
                if let Some(j) = slot.0.take() {
                    break j;
                }
                slot = mailbox
                    .ready
                    .wait(slot)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
            }
        };
        match blitter.draw(&job.frame, job.layer, job.blank, stats) {
            Ok(true) => {
                let now = Instant::now();
                if let Some(l) = last {
                    let ns = u64::try_from((now - l).as_nanos()).unwrap_or(u64::MAX);
                    stats.last_interval_ns.store(ns, Ordering::Relaxed);
                }
                last = Some(now);
                stats.presented.fetch_add(1, Ordering::Relaxed);
            }
            // Skipped (occluded, timed out, reconfigured): the next frame tries again.
            Ok(false) => {}
            Err(e) => {
                *dioptra_core::lock(&stats.error) = Some(e.to_string());
                return;
            }
        }
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
/// slot's image at its rectangle ([`dioptra_rig::display::placement`]) into any view of
/// `target_format`.
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
    /// [`placement`]: dioptra_rig::display::placement
    pub fn encode(
        &self,
        enc: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        target_size: (u32, u32),
        draws: &[(usize, Rect)],
    ) {
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
            let inside = r.width > 0
                && r.height > 0
                && u64::from(r.x) + u64::from(r.width) <= u64::from(tw)
                && u64::from(r.y) + u64::from(r.height) <= u64::from(th);
            if !inside {
                continue;
            }
            // Integer viewport: pixel centres land on texel centres, 1:1 at the image's size.
            pass.set_viewport(
                r.x as f32,
                r.y as f32,
                r.width as f32,
                r.height as f32,
                0.0,
                1.0,
            );
            pass.set_scissor_rect(r.x, r.y, r.width, r.height);
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bind_group, &[]);
            pass.draw(0..3, 0..1);
        }
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

/// The window's GPU side: surface, device and the blit.
struct Blitter {
    window: Arc<winit::window::Window>,
    surface: wgpu::Surface<'static>,
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// The render's context when the window draws with its device.
    shared: Option<Arc<GpuContext>>,
    config: wgpu::SurfaceConfiguration,
    view_format: wgpu::TextureFormat,
    blit: Blit,
    adapter: String,
    /// Which device draws, and why (for `/status`).
    device_note: String,
}

impl Blitter {
    /// On the render's device when `render` is given and can present to the window, else on
    /// a device of the window's own.
    fn new(
        window: Arc<winit::window::Window>,
        render: Option<Arc<GpuContext>>,
    ) -> Result<Blitter, WindowError> {
        let gpu = |e: &dyn std::fmt::Display| WindowError::Gpu(e.to_string());
        let mut note = "its own device: the rig renders on the CPU".to_string();
        if let Some(ctx) = render {
            let surface = ctx
                .instance()
                .create_surface(window.clone())
                .map_err(|e| gpu(&e))?;
            let caps = surface.get_capabilities(ctx.wgpu_adapter());
            if caps.formats.is_empty() {
                note = format!(
                    "its own device: the render's adapter {} cannot present to this window, so \
                     frames are read back",
                    ctx.adapter().name
                );
                tracing::warn!("the window draws on {note}");
                drop(surface);
            } else {
                let (device, queue) = (ctx.device().clone(), ctx.queue().clone());
                let adapter = ctx.wgpu_adapter().clone();
                return Blitter::on(
                    window,
                    surface,
                    &adapter,
                    device,
                    queue,
                    Some(ctx),
                    "the render's device: frames are drawn without a copy".into(),
                );
            }
        }
        let mut desc =
            wgpu::InstanceDescriptor::new_with_display_handle(Box::new(window.clone())).with_env();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(desc);
        let surface = instance
            .create_surface(window.clone())
            .map_err(|e| gpu(&e))?;
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: Some(&surface),
            force_fallback_adapter: false,
            apply_limit_buckets: false,
        }))
        .map_err(|e| gpu(&format!("no GPU adapter can draw to the window: {e}")))?;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("dioptra-window"),
            ..Default::default()
        }))
        .map_err(|e| gpu(&e))?;
        Blitter::on(window, surface, &adapter, device, queue, None, note)
    }

    /// Configures `surface` for vsync through an sRGB view and makes the blit.
    fn on(
        window: Arc<winit::window::Window>,
        surface: wgpu::Surface<'static>,
        adapter: &wgpu::Adapter,
        device: wgpu::Device,
        queue: wgpu::Queue,
        shared: Option<Arc<GpuContext>>,
        device_note: String,
    ) -> Result<Blitter, WindowError> {
        let gpu = |e: &dyn std::fmt::Display| WindowError::Gpu(e.to_string());
        let caps = surface.get_capabilities(adapter);
        let (format, view_format) = surface_formats(&caps.formats).ok_or_else(|| {
            gpu(&format!(
                "the surface offers no sRGB format (offers {:?})",
                caps.formats
            ))
        })?;
        if !caps.present_modes.contains(&wgpu::PresentMode::Fifo) {
            return Err(gpu(&"the surface does not offer vsync (Fifo)"));
        }
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let config = wgpu::SurfaceConfiguration {
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            format,
            width: w,
            height: h,
            present_mode: wgpu::PresentMode::Fifo,
            desired_maximum_frame_latency: 1,
            view_formats: if view_format == format {
                vec![]
            } else {
                vec![view_format]
            },
            ..surface
                .get_default_config(adapter, w, h)
                .ok_or_else(|| gpu(&"the surface is not supported by the adapter"))?
        };
        let blit = scoped(&device, || {
            surface.configure(&device, &config);
            Blit::new(&device, view_format)
        })?;
        let info = adapter.get_info();
        Ok(Blitter {
            window,
            surface,
            device,
            queue,
            shared,
            config,
            view_format,
            blit,
            adapter: format!("{} ({:?})", info.name, info.backend),
            device_note,
        })
    }

    /// Presents `image`; blocks until a swapchain image is free (vsync). `Ok(false)`: skipped
    /// this time (window occluded, surface reconfigured). Its GPU errors are returned
    /// ([`scoped`]).
    /// `blank`: the sink refused the frame; only the marker patch is drawn, on black.
    fn draw(
        &mut self,
        frame: &Frame,
        layer: usize,
        blank: bool,
        stats: &PresenterStats,
    ) -> Result<bool, WindowError> {
        self.blit.set_marker(frame.marker);
        let device = self.device.clone();
        scoped(&device, || self.draw_unscoped(frame, layer, blank, stats))?
    }

    /// Uploads (or points at) `image` for slot `slot`.
    fn show(&mut self, slot: usize, image: &FrameImage) -> Result<(), WindowError> {
        match image {
            FrameImage::Host(i) => self.blit.upload(&self.device, &self.queue, slot, i),
            FrameImage::Gpu(g)
                if self
                    .shared
                    .as_ref()
                    .is_some_and(|c| Arc::ptr_eq(c, g.context())) =>
            {
                self.blit.show_buffer(&self.device, &self.queue, slot, g)
            }
            // Another device's memory: through the host.
            FrameImage::Gpu(g) => {
                let pixels = g
                    .read()
                    .map_err(|e| WindowError::Gpu(format!("reading the frame back: {e}")))?;
                self.blit.upload(&self.device, &self.queue, slot, &pixels)
            }
        }
        Ok(())
    }

    fn draw_unscoped(
        &mut self,
        frame: &Frame,
        layer: usize,
        blank: bool,
        stats: &PresenterStats,
    ) -> Result<bool, WindowError> {
        let win = self.window.inner_size();
        if (win.width, win.height) != (self.config.width, self.config.height)
            && win.width > 0
            && win.height > 0
        {
            self.config.width = win.width;
            self.config.height = win.height;
            self.surface.configure(&self.device, &self.config);
            let surface = (win.width, win.height);
            *dioptra_core::lock(&stats.surface) = surface;
            log_surface(surface, &stats.monitor, stats.monitor_size);
        }
        let surface = (self.config.width, self.config.height);
        // Placed again on the surface as it is now (it may have changed since the sink looked);
        // a frame that does not fit leaves the screen black.
        let mut draws = Vec::with_capacity(2);
        let placed = if blank {
            Ok(Vec::new())
        } else {
            stats.place(frame, layer, surface)
        };
        match placed {
            Ok(placed) => {
                for (slot, p) in placed.iter().enumerate() {
                    self.show(slot, p.image)?;
                    draws.push((slot, p.rect));
                }
            }
            Err(e) => refused(stats, &e),
        }
        let target = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(t)
            | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                return Ok(false)
            }
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                self.surface.configure(&self.device, &self.config);
                return Ok(false);
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                return Err(WindowError::Gpu(
                    "acquiring the next surface image failed validation".into(),
                ))
            }
        };
        let view = target.texture.create_view(&wgpu::TextureViewDescriptor {
            format: Some(self.view_format),
            ..Default::default()
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("blit"),
            });
        self.blit.encode(&mut enc, &view, surface, &draws);
        self.queue.submit([enc.finish()]);
        self.window.pre_present_notify();
        self.queue.present(target);
        Ok(true)
    }
}

/// Runs `work` with this thread's GPU errors on `device` caught (validation, out of memory)
/// and returned, so that on a device shared with the render they never fail a render.
fn scoped<T>(device: &wgpu::Device, work: impl FnOnce() -> T) -> Result<T, WindowError> {
    let oom = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
    let invalid = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let out = work();
    let errors = [
        pollster::block_on(invalid.pop()),
        pollster::block_on(oom.pop()),
    ];
    match errors.into_iter().flatten().next() {
        Some(e) => Err(WindowError::Gpu(e.to_string())),
        None => Ok(out),
    }
}

/// What the main thread hands the daemon's thread: the window, its monitor's name and size.
pub struct WindowReady {
    pub window: Arc<winit::window::Window>,
    pub monitor: String,
    /// The monitor's size, physical pixels: what the surface should be.
    pub monitor_size: (u32, u32),
}

/// A message to the main thread's event loop.
#[derive(Debug)]
enum UserEvent {
    /// The daemon's thread has finished.
    DaemonDone,
}

/// Opens the display and a borderless fullscreen window on the chosen monitor on this (the
/// main) thread, runs `daemon` on a thread of its own with the window, and handles window
/// events here until it returns. Closing the window (or Escape in it) triggers `stop`, which
/// the daemon treats like Ctrl-C. Returns the daemon's result.
pub fn run_on_main_thread<F>(
    choice: Option<MonitorChoice>,
    stop: tokio_util::sync::CancellationToken,
    daemon: F,
) -> anyhow::Result<()>
where
    F: FnOnce(WindowReady) -> anyhow::Result<()> + Send + 'static,
{
    env_display_check()?;
    let event_loop = winit::event_loop::EventLoop::<UserEvent>::with_user_event()
        .build()
        .map_err(|e| WindowError::Open {
            detail: e.to_string(),
        })?;
    let mut app = App {
        choice,
        stop,
        daemon: Some(Box::new(daemon)),
        proxy: event_loop.create_proxy(),
        thread: None,
        window: None,
        error: None,
        daemon_done: Arc::new(AtomicBool::new(false)),
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| anyhow::anyhow!("the window's event loop failed: {e}"))?;
    app.stop.cancel();
    let result = match app.thread.take() {
        Some(t) => t
            .join()
            .unwrap_or_else(|_| Err(anyhow::anyhow!("the daemon's thread panicked"))),
        None => Ok(()),
    };
    match app.error.take() {
        Some(e) => Err(e.into()),
        None => result,
    }
}

type DaemonFn = Box<dyn FnOnce(WindowReady) -> anyhow::Result<()> + Send>;

struct App {
    choice: Option<MonitorChoice>,
    stop: tokio_util::sync::CancellationToken,
    daemon: Option<DaemonFn>,
    proxy: winit::event_loop::EventLoopProxy<UserEvent>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<()>>>,
    window: Option<Arc<winit::window::Window>>,
    error: Option<WindowError>,
    daemon_done: Arc<AtomicBool>,
}

impl App {
    fn open(
        &mut self,
        event_loop: &winit::event_loop::ActiveEventLoop,
    ) -> Result<WindowReady, WindowError> {
        let monitors: Vec<winit::monitor::MonitorHandle> =
            event_loop.available_monitors().collect();
        let infos: Vec<MonitorInfo> = monitors
            .iter()
            .map(|m| MonitorInfo {
                name: m.name(),
                size: (m.size().width, m.size().height),
                position: (m.position().x, m.position().y),
            })
            .collect();
        let primary = event_loop
            .primary_monitor()
            .and_then(|p| monitors.iter().position(|m| *m == p));
        let i =
            choose_monitor(&infos, self.choice.as_ref(), primary).map_err(WindowError::Monitor)?;
        // The monitor's size and position as well as fullscreen: without a window manager
        // (which is what makes a window fullscreen on X11) the window still covers it.
        let (size, position) = (infos[i].size, infos[i].position);
        let attrs = winit::window::Window::default_attributes()
            .with_title("dioptra")
            .with_decorations(false)
            .with_inner_size(winit::dpi::PhysicalSize::new(size.0, size.1))
            .with_position(winit::dpi::PhysicalPosition::new(position.0, position.1))
            .with_fullscreen(Some(winit::window::Fullscreen::Borderless(Some(
                monitors[i].clone(),
            ))));
        let window = event_loop
            .create_window(attrs)
            .map_err(|e| WindowError::Create(e.to_string()))?;
        window.set_cursor_visible(false);
        Ok(WindowReady {
            window: Arc::new(window),
            monitor: format!("monitor {i}: {}", infos[i]),
            monitor_size: size,
        })
    }
}

impl winit::application::ApplicationHandler<UserEvent> for App {
    fn resumed(&mut self, event_loop: &winit::event_loop::ActiveEventLoop) {
        let Some(daemon) = self.daemon.take() else {
            return;
        };
        match self.open(event_loop) {
            Ok(ready) => {
                self.window = Some(ready.window.clone());
                let (proxy, done) = (self.proxy.clone(), self.daemon_done.clone());
                let spawned = std::thread::Builder::new()
                    .name("dioptra-daemon".into())
                    .spawn(move || {
                        let r = daemon(ready);
                        done.store(true, Ordering::SeqCst);
                        let _ = proxy.send_event(UserEvent::DaemonDone);
                        r
                    });
                match spawned {
                    Ok(t) => self.thread = Some(t),
                    Err(e) => {
                        self.error = Some(WindowError::Create(format!(
                            "cannot start the daemon's thread: {e}"
                        )));
                        event_loop.exit();
                    }
                }
            }
            Err(e) => {
                self.error = Some(e);
                event_loop.exit();
            }
        }
    }

    fn user_event(&mut self, event_loop: &winit::event_loop::ActiveEventLoop, e: UserEvent) {
        match e {
            UserEvent::DaemonDone => event_loop.exit(),
        }
    }

    fn window_event(
        &mut self,
        event_loop: &winit::event_loop::ActiveEventLoop,
        _id: winit::window::WindowId,
        event: winit::event::WindowEvent,
    ) {
        use winit::event::WindowEvent;
        use winit::keyboard::{Key, NamedKey};
        match event {
            WindowEvent::CloseRequested => self.stop.cancel(),
            WindowEvent::KeyboardInput { event, .. }
                if event.logical_key == Key::Named(NamedKey::Escape) =>
            {
                self.stop.cancel()
            }
            _ => {}
        }
        if self.daemon_done.load(Ordering::SeqCst) {
            event_loop.exit();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mon(name: &str, x: i32) -> MonitorInfo {
        MonitorInfo {
            name: Some(name.into()),
            size: (1920, 1080),
            position: (x, 0),
        }
    }

    #[test]
    fn no_display_in_the_environment_is_a_clear_error() {
        let e = check_display_env(None, None, None).unwrap_err();
        let s = e.to_string();
        assert!(s.contains("no display: set DISPLAY/WAYLAND_DISPLAY"), "{s}");
        assert!(s.contains("kind = \"headless\""), "{s}");
        // Empty counts as unset, as winit treats it.
        assert!(check_display_env(Some(""), None, Some("")).is_err());
        assert!(check_display_env(None, None, Some(":0")).is_ok());
        assert!(check_display_env(Some("wayland-0"), None, None).is_ok());
        assert!(check_display_env(None, Some("3"), None).is_ok());
    }

    #[test]
    fn monitors_are_chosen_by_name_index_or_primary() {
        let ms = [mon("HDMI-1", 0), mon("DP-2", 1920), mon("eDP-1", 3840)];
        let name = |n: &str| Some(MonitorChoice::Name(n.into()));
        assert_eq!(choose_monitor(&ms, name("DP-2").as_ref(), None), Ok(1));
        assert_eq!(choose_monitor(&ms, name("hdmi-1").as_ref(), None), Ok(0));
        assert_eq!(
            choose_monitor(&ms, Some(&MonitorChoice::Index(2)), None),
            Ok(2)
        );
        assert_eq!(choose_monitor(&ms, None, Some(2)), Ok(2));
        assert_eq!(choose_monitor(&ms, None, None), Ok(0));
        // A primary index the list does not have falls back to the first.
        assert_eq!(choose_monitor(&ms, None, Some(7)), Ok(0));
    }

    #[test]
    fn an_unknown_monitor_lists_the_available_ones() {
        let ms = [mon("HDMI-1", 0), mon("DP-2", 1920)];
        let e = choose_monitor(&ms, Some(&MonitorChoice::Name("DP-9".into())), None).unwrap_err();
        assert!(e.contains("no monitor named \"DP-9\""), "{e}");
        assert!(
            e.contains("0: \"HDMI-1\" 1920x1080 at (0, 0)")
                && e.contains("1: \"DP-2\" 1920x1080 at (1920, 0)"),
            "{e}"
        );
        let e = choose_monitor(&ms, Some(&MonitorChoice::Index(5)), None).unwrap_err();
        assert!(
            e.contains("there is no monitor 5") && e.contains("DP-2"),
            "{e}"
        );
        let e = choose_monitor(&[], None, None).unwrap_err();
        assert!(e.contains("no monitors"), "{e}");
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

    #[test]
    fn exact_needs_the_surface_to_be_the_monitors_size() {
        assert_eq!(
            surface_check(Scale::Exact, (1920, 1080), "monitor 0", (1920, 1080)),
            Ok(())
        );
        // What Xvfb without a window manager gave: refused, saying both sizes and the way out.
        let e = surface_check(
            Scale::Exact,
            (800, 600),
            "monitor 0: \"screen\"",
            (1024, 768),
        )
        .unwrap_err();
        assert!(
            e.contains("surface is 800x600 but monitor 0: \"screen\" is 1024x768")
                && e.contains("display.scale = \"fit\""),
            "{e}"
        );
        // Fit draws on whatever surface there is.
        assert_eq!(
            surface_check(Scale::Fit, (800, 600), "monitor 0", (1024, 768)),
            Ok(())
        );
    }

    #[test]
    fn two_outputs_in_a_window_is_refused_naming_the_key() {
        use dioptra_rig::config::DisplayLayout;
        let e = super::window_layout_supported(DisplayLayout::TwoOutputs).unwrap_err();
        assert!(
            e.to_string().contains("display.layout = \"two-outputs\""),
            "{e}"
        );
        assert!(super::window_layout_supported(DisplayLayout::SideBySide).is_ok());
        assert!(super::window_layout_supported(DisplayLayout::One).is_ok());
    }

    fn fit(image: (u32, u32), surface: (u32, u32)) -> Rect {
        dioptra_rig::display::placement::placement(
            dioptra_rig::config::DisplayLayout::One,
            Scale::Fit,
            surface,
            dioptra_core::Side::Left,
            image,
            [0, 0],
        )
        .unwrap()
    }

    #[test]
    fn the_surface_is_written_through_an_srgb_format() {
        use wgpu::TextureFormat as F;
        assert_eq!(
            surface_formats(&[F::Bgra8Unorm, F::Bgra8UnormSrgb]),
            Some((F::Bgra8UnormSrgb, F::Bgra8UnormSrgb))
        );
        assert_eq!(
            surface_formats(&[F::Bgra8Unorm]),
            Some((F::Bgra8Unorm, F::Bgra8UnormSrgb))
        );
        assert_eq!(surface_formats(&[F::Rgba16Float]), None);
    }

    /// A headless device (lavapipe here), or `None` (test skipped) when there is no adapter
    /// and DIOPTRA_REQUIRE_GPU is not 1, as in dioptra-render's GPU tests.
    fn headless_device() -> Option<(wgpu::Device, wgpu::Queue)> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(desc);
        let adapter = match pollster::block_on(
            instance.request_adapter(&wgpu::RequestAdapterOptions::default()),
        ) {
            Ok(a) => a,
            Err(e) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
                eprintln!("skipped: no GPU adapter ({e})");
                return None;
            }
            Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1): {e}"),
        };
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
            format: wgpu::TextureFormat::Rgba8UnormSrgb,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: u64::from(tw * th * 4),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&Default::default());
        blit.encode(
            &mut enc,
            &target.create_view(&Default::default()),
            size,
            draws,
        );
        enc.copy_texture_to_buffer(
            target.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(tw * 4),
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
        let got = readback.slice(..).get_mapped_range().unwrap().to_vec();
        got
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
        use dioptra_rig::config::Corner;
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
        let gpu = match dioptra_render::Gpu::new(None) {
            Ok(g) => g,
            Err(e) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
                eprintln!("skipped: no GPU adapter ({e})");
                return;
            }
            Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1): {e}"),
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
    /// ([`dioptra_rig::display::placement::draw_into`], its CPU twin), pixel for pixel.
    #[test]
    fn each_eye_is_drawn_at_its_place_as_the_headless_panel_has_it() {
        use dioptra_rig::config::DisplayLayout;
        use dioptra_rig::display::placement::{draw_into, placement};
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
