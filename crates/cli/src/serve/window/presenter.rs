//! The presenter: [`WindowSink`] hands each frame to a thread of its own, which owns the
//! window's GPU surface and device ([`Blitter`]) and draws with the rig's blit
//! ([`dioptra_rig::display::blit`]). Presenting blocks until a swapchain image is free (Fifo
//! paces to the monitor's refresh), so the loop's thread never draws; the newest frame wins.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

use dioptra_core::Timestamp;
use dioptra_render::gpu::GpuContext;
use dioptra_rig::display::blit::Blit;
use dioptra_rig::display::placement::{PlaceError, Placed, PlacementConfig, Placer};
use dioptra_rig::display::{DisplayError, DisplaySink, Frame};
use dioptra_rig::render::FrameImage;

use super::app::WindowReady;
use super::error::WindowError;
use super::monitor::surface_check;

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
