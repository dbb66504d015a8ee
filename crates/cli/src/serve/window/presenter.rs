//! The presenter: [`WindowSink`] hands each frame to a thread of its own, which owns the
//! windows' GPU surfaces and device ([`Presenter`]) and draws each window's images with the
//! rig's [`PanelDraw`] (the blit, and the eyes' image corrections where the rig has any).
//! Presenting blocks until a swapchain image is free (Fifo paces to the monitor's refresh),
//! so the loop's thread never draws; the newest frame wins.
//!
//! Two outputs (`layout = "two-outputs"`): a window per eye, one device, one frame drawn into
//! both in the same pass of the presenter: each window's next image is acquired (each waits
//! for its own monitor's vsync), both are drawn in one submission, and both are presented
//! before the next frame is taken. The two monitors' refreshes are not locked together, so
//! the eyes' images reach their panels up to one refresh apart; with monitors at different
//! rates the pair is paced by the slower (said once at start).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

use dioptra_core::{Side, Timestamp};
use dioptra_render::gpu::GpuContext;
use dioptra_rig::display::panel_draw::{DrawError, PanelDraw, Prepared};
use dioptra_rig::display::placement::{PlaceError, Placed, PlacementConfig, Placer};
use dioptra_rig::display::{DisplayError, DisplaySink, Frame, PanelImage};

use super::app::{OutputWindow, WindowReady};
use super::error::WindowError;
use super::monitor::surface_check;

/// The surface's configured format and the format its views are made in. Without image
/// corrections (`code_values` false) an sRGB view, so the blit's linear output is encoded by
/// the hardware; with them a non-sRGB view, as the transfer table writes the panel's code
/// values. `None` when the surface offers no 8-bit format with an sRGB twin.
pub fn surface_formats(
    offered: &[wgpu::TextureFormat],
    code_values: bool,
) -> Option<(wgpu::TextureFormat, wgpu::TextureFormat)> {
    let has_twin = |f: &wgpu::TextureFormat| f.add_srgb_suffix().is_srgb();
    if code_values {
        if let Some(&f) = offered.iter().find(|f| !f.is_srgb() && has_twin(f)) {
            return Some((f, f));
        }
        return offered
            .iter()
            .find(|f| f.is_srgb())
            .map(|&f| (f, f.remove_srgb_suffix()));
    }
    if let Some(&f) = offered.iter().find(|f| f.is_srgb()) {
        return Some((f, f));
    }
    offered
        .iter()
        .find(|f| has_twin(f))
        .map(|&f| (f, f.add_srgb_suffix()))
}

/// A frame for the presenter: which image of which frame.
struct Job {
    frame: Frame,
    layer: usize,
    /// Refused by the sink (it does not fit): the screens go black.
    blank: bool,
}

/// One window's monitor and surface, as the sink and the presenter share them.
struct OutputStats {
    /// The eye it shows (`None`: the one window, every eye of the layout).
    eye: Option<Side>,
    /// The monitor the window is on, and its size.
    monitor: String,
    monitor_size: (u32, u32),
    /// The surface's size now (the presenter follows the window's).
    surface: Mutex<(u32, u32)>,
}

/// What the presenter thread reports, and the placement state it shares with the sink.
struct PresenterStats {
    presented: AtomicU64,
    replaced: AtomicU64,
    /// Wall-clock interval between the last two presents, ns.
    last_interval_ns: AtomicU64,
    error: Mutex<Option<String>>,
    placer: Mutex<Placer>,
    outputs: Vec<OutputStats>,
}

impl PresenterStats {
    /// Layer `layer` of `frame`'s images placed on output `i`'s `surface`, or why they are not
    /// shown.
    fn place<'a>(
        &self,
        frame: &'a Frame,
        layer: usize,
        i: usize,
        surface: (u32, u32),
    ) -> Result<Vec<Placed<'a>>, PlaceError> {
        let o = &self.outputs[i];
        let placer = dioptra_core::lock(&self.placer);
        surface_check(placer.config.scale, surface, &o.monitor, o.monitor_size)
            .map_err(PlaceError::Surface)?;
        match o.eye {
            None => placer.place(frame, layer, surface),
            Some(eye) => placer.place_eyes(frame, layer, surface, &[Some(eye)]),
        }
    }

    /// Whether `frame`'s layer `layer` can be shown on every window as they are now.
    fn place_all(&self, frame: &Frame, layer: usize) -> Result<(), PlaceError> {
        for (i, o) in self.outputs.iter().enumerate() {
            let surface = *dioptra_core::lock(&o.surface);
            self.place(frame, layer, i, surface)?;
        }
        Ok(())
    }
}

/// The mailbox between the sink and the presenter thread.
struct Mailbox {
    job: Mutex<(Option<Job>, bool)>,
    ready: Condvar,
}

/// Shows frames in the window (or the two windows); see the module doc for the threads.
pub struct WindowSink {
    mailbox: Arc<Mailbox>,
    stats: Arc<PresenterStats>,
    shown: u64,
    describe: String,
    /// Each eye's image corrections, for `/status` (empty: none).
    panels: Vec<PanelImage>,
    last_compensation: [Option<f32>; 2],
    presenter: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for WindowSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe)
    }
}

impl WindowSink {
    /// Sets up the GPU surfaces of `ready`'s windows, on the render's device when `render` is
    /// given and its adapter can present to them, and starts the presenter thread. Images are
    /// placed as `placement` says (`display.layout`, `scale`, `eye_offset_px`) and, with
    /// `panels` (each eye's corrections, [`dioptra_rig::display::panel_images`]), corrected on
    /// the GPU: on the render's context, or where the rig renders on the CPU, on the
    /// process's GPU context ([`GpuContext::shared`]).
    pub fn new(
        ready: WindowReady,
        render: Option<Arc<GpuContext>>,
        placement: PlacementConfig,
        panels: Vec<PanelImage>,
    ) -> Result<WindowSink, WindowError> {
        let render = match render {
            None if !panels.is_empty() => Some(GpuContext::shared(None).map_err(|e| {
                WindowError::Gpu(format!(
                    "the eyes' image corrections ([optics], display.transfer) are drawn on a \
                     GPU: {e}"
                ))
            })?),
            r => r,
        };
        let presenter = Presenter::new(ready.outputs, render, &panels)?;
        let describe = presenter.describe();
        let outputs = presenter
            .outputs
            .iter()
            .map(|o| {
                let surface = (o.config.width, o.config.height);
                log_surface(surface, &o.monitor, o.monitor_size);
                OutputStats {
                    eye: o.eye,
                    monitor: o.monitor.clone(),
                    monitor_size: o.monitor_size,
                    surface: Mutex::new(surface),
                }
            })
            .collect();
        let mailbox = Arc::new(Mailbox {
            job: Mutex::new((None, false)),
            ready: Condvar::new(),
        });
        let stats = Arc::new(PresenterStats {
            presented: AtomicU64::new(0),
            replaced: AtomicU64::new(0),
            last_interval_ns: AtomicU64::new(0),
            error: Mutex::new(None),
            placer: Mutex::new(Placer::new(placement)),
            outputs,
        });
        let (mb, st) = (mailbox.clone(), stats.clone());
        let thread = std::thread::Builder::new()
            .name("dioptra-present".into())
            .spawn(move || present_loop(presenter, &mb, &st))
            .map_err(|e| WindowError::Gpu(format!("cannot start the presenter thread: {e}")))?;
        Ok(WindowSink {
            mailbox,
            stats,
            shown: 0,
            describe,
            panels,
            last_compensation: [None; 2],
            presenter: Some(thread),
        })
    }

    fn hand_over(&mut self, frame: &Frame, layer: usize) -> Result<(), DisplayError> {
        if let Some(e) = dioptra_core::lock(&self.stats.error).clone() {
            return Err(DisplayError::Window(e));
        }
        // Placed on the surfaces as they are now: a frame that does not fit is not shown, and
        // the screens go black rather than keep the previous stimulus.
        let placed = self.stats.place_all(frame, layer);
        if let Err(e) = &placed {
            refused(&self.stats, e);
        } else if layer == 0 {
            dioptra_core::lock(&self.stats.placer).shown(frame);
            self.last_compensation = frame.size_compensation;
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
        placed.map_err(DisplayError::NotShown)
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
        // The first window's monitor and surface at the top, as with one window; every
        // window's under `outputs` with two.
        let first = &s.outputs[0];
        let surface = *dioptra_core::lock(&first.surface);
        let mut v = serde_json::json!({
            "sink": self.describe,
            "shown": self.shown,
            "presented": s.presented.load(Ordering::Relaxed),
            "replaced": s.replaced.load(Ordering::Relaxed),
            "last_present_interval_ms": (interval > 0).then(|| interval as f64 / 1e6),
            "error": dioptra_core::lock(&s.error).clone(),
            "monitor": first.monitor,
            "monitor_size": [first.monitor_size.0, first.monitor_size.1],
            "surface_is_monitor_size": surface == first.monitor_size,
        });
        if s.outputs.len() > 1 {
            v["outputs"] = s
                .outputs
                .iter()
                .map(|o| {
                    let surface = *dioptra_core::lock(&o.surface);
                    serde_json::json!({
                        "eye": o.eye.map(Side::as_str),
                        "monitor": o.monitor,
                        "monitor_size": [o.monitor_size.0, o.monitor_size.1],
                        "surface": [surface.0, surface.1],
                        "surface_is_monitor_size": surface == o.monitor_size,
                    })
                })
                .collect();
        }
        if let (Some(o), serde_json::Value::Object(p)) = (
            v.as_object_mut(),
            dioptra_core::lock(&s.placer).status(Some(surface)),
        ) {
            o.extend(p);
        }
        if !self.panels.is_empty() {
            v["eyes_to_panel"] =
                dioptra_rig::display::eyes_status(&self.panels, self.last_compensation);
        }
        v
    }
}

/// Logs the surface size the system gave a window (a warning where it is not the monitor's).
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
fn present_loop(mut presenter: Presenter, mailbox: &Mailbox, stats: &PresenterStats) {
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
        match presenter.draw(&job.frame, job.layer, job.blank, stats) {
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

/// One window's GPU side: its surface and what it draws.
struct OutputSurface {
    window: Arc<winit::window::Window>,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    view_format: wgpu::TextureFormat,
    draw: PanelDraw,
    eye: Option<Side>,
    monitor: String,
    monitor_size: (u32, u32),
}

/// The windows' GPU side: one device, a surface per window.
struct Presenter {
    device: wgpu::Device,
    queue: wgpu::Queue,
    outputs: Vec<OutputSurface>,
    adapter: String,
    /// Which device draws, and why (for `/status`).
    device_note: String,
    corrects: bool,
}

impl Presenter {
    /// On the render's device when `render` is given and can present to every window, else on
    /// a device of the windows' own. Image corrections (`panels` not empty) need the former.
    fn new(
        windows: Vec<OutputWindow>,
        render: Option<Arc<GpuContext>>,
        panels: &[PanelImage],
    ) -> Result<Presenter, WindowError> {
        let gpu = |e: &dyn std::fmt::Display| WindowError::Gpu(e.to_string());
        let first = windows
            .first()
            .ok_or_else(|| gpu(&"no window to draw to"))?
            .window
            .clone();
        let mut note = "its own device: the rig renders on the CPU".to_string();
        if let Some(ctx) = render {
            let surfaces = windows
                .iter()
                .map(|w| ctx.instance().create_surface(w.window.clone()))
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| gpu(&e))?;
            if surfaces
                .iter()
                .all(|s| !s.get_capabilities(ctx.wgpu_adapter()).formats.is_empty())
            {
                let (device, queue) = (ctx.device().clone(), ctx.queue().clone());
                let adapter = ctx.wgpu_adapter().clone();
                let note = if panels.is_empty() {
                    "the render's device: frames are drawn without a copy"
                } else {
                    "the render's device: frames are drawn, corrected, without a copy"
                };
                return Presenter::on(
                    windows.into_iter().zip(surfaces).collect(),
                    &adapter,
                    device,
                    queue,
                    Some(ctx),
                    panels,
                    note.into(),
                );
            }
            if !panels.is_empty() {
                return Err(gpu(&format!(
                    "the GPU adapter {} cannot present to the window, and the eyes' image \
                     corrections ([optics], display.transfer) are drawn on it: choose an \
                     adapter that can (render.adapter)",
                    ctx.adapter().name
                )));
            }
            note = format!(
                "its own device: the render's adapter {} cannot present to this window, so \
                 frames are read back",
                ctx.adapter().name
            );
            tracing::warn!("the window draws on {note}");
        }
        let mut desc =
            wgpu::InstanceDescriptor::new_with_display_handle(Box::new(first.clone())).with_env();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(desc);
        let surfaces = windows
            .iter()
            .map(|w| instance.create_surface(w.window.clone()))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| gpu(&e))?;
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            compatible_surface: surfaces.first(),
            force_fallback_adapter: false,
            apply_limit_buckets: false,
        }))
        .map_err(|e| gpu(&format!("no GPU adapter can draw to the window: {e}")))?;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("dioptra-window"),
            ..Default::default()
        }))
        .map_err(|e| gpu(&e))?;
        Presenter::on(
            windows.into_iter().zip(surfaces).collect(),
            &adapter,
            device,
            queue,
            None,
            panels,
            note,
        )
    }

    /// Configures each surface for vsync (through an sRGB view, or a non-sRGB one for code
    /// values) and makes what it draws: each window gets its eye's corrections.
    fn on(
        windows: Vec<(OutputWindow, wgpu::Surface<'static>)>,
        adapter: &wgpu::Adapter,
        device: wgpu::Device,
        queue: wgpu::Queue,
        shared: Option<Arc<GpuContext>>,
        panels: &[PanelImage],
        device_note: String,
    ) -> Result<Presenter, WindowError> {
        let gpu = |e: &dyn std::fmt::Display| WindowError::Gpu(e.to_string());
        let mut outputs = Vec::with_capacity(windows.len());
        for (w, surface) in windows {
            let caps = surface.get_capabilities(adapter);
            let (format, view_format) = surface_formats(&caps.formats, !panels.is_empty())
                .ok_or_else(|| {
                    gpu(&format!(
                        "the surface on {} offers no 8-bit format with an sRGB twin (offers \
                         {:?})",
                        w.monitor, caps.formats
                    ))
                })?;
            if !caps.present_modes.contains(&wgpu::PresentMode::Fifo) {
                return Err(gpu(&format!(
                    "the surface on {} does not offer vsync (Fifo)",
                    w.monitor
                )));
            }
            let size = w.window.inner_size();
            let (width, height) = (size.width.max(1), size.height.max(1));
            let config = wgpu::SurfaceConfiguration {
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
                format,
                width,
                height,
                present_mode: wgpu::PresentMode::Fifo,
                desired_maximum_frame_latency: 1,
                view_formats: if view_format == format {
                    vec![]
                } else {
                    vec![view_format]
                },
                ..surface
                    .get_default_config(adapter, width, height)
                    .ok_or_else(|| gpu(&"the surface is not supported by the adapter"))?
            };
            // The one window draws every eye's image; a window per eye, its eye's.
            let own: Vec<PanelImage> = panels
                .iter()
                .filter(|p| w.eye.is_none() || p.eye == w.eye)
                .cloned()
                .collect();
            let draw = scoped(&device, || {
                surface.configure(&device, &config);
                PanelDraw::new(&device, view_format, shared.clone(), &own)
            })?
            .map_err(|e| gpu(&e))?;
            outputs.push(OutputSurface {
                window: w.window,
                surface,
                config,
                view_format,
                draw,
                eye: w.eye,
                monitor: w.monitor,
                monitor_size: w.monitor_size,
            });
        }
        let info = adapter.get_info();
        Ok(Presenter {
            device,
            queue,
            outputs,
            adapter: format!("{} ({:?})", info.name, info.backend),
            device_note,
            corrects: !panels.is_empty(),
        })
    }

    /// For `/status` and the log: where each window is and how it draws.
    fn describe(&self) -> String {
        let windows: Vec<String> = self
            .outputs
            .iter()
            .map(|o| {
                format!(
                    "{}{} ({:?}, surface {}x{})",
                    o.eye
                        .map_or(String::new(), |e| format!("{} eye on ", e.as_str())),
                    o.monitor,
                    o.config.format,
                    o.config.width,
                    o.config.height
                )
            })
            .collect();
        format!(
            "window{} on {} ({}, {}{})",
            if windows.len() > 1 { "s" } else { "" },
            windows.join(" and "),
            self.adapter,
            self.device_note,
            if self.corrects {
                "; each eye's image compensated, pre-warped and encoded for its panel on the GPU"
            } else {
                ""
            }
        )
    }

    /// Draws `frame`'s layer `layer` into every window and presents them; blocks until each
    /// has a swapchain image free (vsync). `Ok(false)`: no window presented this time
    /// (occluded, surface reconfigured). GPU errors are returned ([`scoped`]).
    /// `blank`: the sink refused the frame; only the marker patch is drawn, on black.
    fn draw(
        &mut self,
        frame: &Frame,
        layer: usize,
        blank: bool,
        stats: &PresenterStats,
    ) -> Result<bool, WindowError> {
        for o in &mut self.outputs {
            o.draw.set_marker(frame.marker);
        }
        let device = self.device.clone();
        scoped(&device, || self.draw_unscoped(frame, layer, blank, stats))?
    }

    fn draw_unscoped(
        &mut self,
        frame: &Frame,
        layer: usize,
        blank: bool,
        stats: &PresenterStats,
    ) -> Result<bool, WindowError> {
        let mut targets = Vec::with_capacity(self.outputs.len());
        let mut encoders = Vec::with_capacity(self.outputs.len());
        // Each window's prepared images live until the submission: an uploaded image goes
        // back to its pool when dropped, and the next window's upload would take the same
        // buffer and overwrite it before either is drawn (both windows showing one eye).
        let mut drawn: Vec<Vec<Prepared>> = Vec::with_capacity(self.outputs.len());
        for (i, o) in self.outputs.iter_mut().enumerate() {
            let win = o.window.inner_size();
            if (win.width, win.height) != (o.config.width, o.config.height)
                && win.width > 0
                && win.height > 0
            {
                o.config.width = win.width;
                o.config.height = win.height;
                o.surface.configure(&self.device, &o.config);
                let surface = (win.width, win.height);
                *dioptra_core::lock(&stats.outputs[i].surface) = surface;
                log_surface(surface, &o.monitor, o.monitor_size);
            }
            let surface = (o.config.width, o.config.height);
            // Placed again on the surface as it is now (it may have changed since the sink
            // looked); a frame that does not fit leaves the screen black.
            let placed = if blank {
                Ok(Vec::new())
            } else {
                stats.place(frame, layer, i, surface)
            };
            let mut prepared: Vec<Prepared> = Vec::with_capacity(2);
            match placed {
                Ok(placed) => {
                    for (slot, p) in placed.iter().enumerate() {
                        match o.draw.prepare(
                            &self.device,
                            &self.queue,
                            slot,
                            p,
                            frame.compensation_of(p.eye),
                        ) {
                            Ok(ready) => prepared.push(ready),
                            Err(DrawError::Refused(e)) => {
                                refused(stats, &e);
                                prepared.clear();
                                break;
                            }
                            Err(DrawError::Gpu(e)) => return Err(WindowError::Gpu(e)),
                        }
                    }
                }
                Err(e) => refused(stats, &e),
            }
            let target = match o.surface.get_current_texture() {
                wgpu::CurrentSurfaceTexture::Success(t)
                | wgpu::CurrentSurfaceTexture::Suboptimal(t) => t,
                wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                    continue
                }
                wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                    o.surface.configure(&self.device, &o.config);
                    continue;
                }
                wgpu::CurrentSurfaceTexture::Validation => {
                    return Err(WindowError::Gpu(
                        "acquiring the next surface image failed validation".into(),
                    ))
                }
            };
            let view = target.texture.create_view(&wgpu::TextureViewDescriptor {
                format: Some(o.view_format),
                ..Default::default()
            });
            let mut enc = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("window"),
                });
            o.draw
                .encode(&mut enc, &view, surface, &prepared)
                .map_err(|e| WindowError::Gpu(e.to_string()))?;
            encoders.push(enc.finish());
            drawn.push(prepared);
            targets.push((i, target));
        }
        if targets.is_empty() {
            return Ok(false);
        }
        // Every window's image in one submission, then every window presented: the eyes'
        // images of one frame go out together.
        self.queue.submit(encoders);
        drop(drawn);
        for (i, target) in targets {
            self.outputs[i].window.pre_present_notify();
            self.queue.present(target);
        }
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
            surface_formats(&[F::Bgra8Unorm, F::Bgra8UnormSrgb], false),
            Some((F::Bgra8UnormSrgb, F::Bgra8UnormSrgb))
        );
        assert_eq!(
            surface_formats(&[F::Bgra8Unorm], false),
            Some((F::Bgra8Unorm, F::Bgra8UnormSrgb))
        );
        assert_eq!(surface_formats(&[F::Rgba16Float], false), None);
        // Code values (the eyes' image corrections): through a view that does not encode.
        assert_eq!(
            surface_formats(&[F::Bgra8UnormSrgb, F::Bgra8Unorm], true),
            Some((F::Bgra8Unorm, F::Bgra8Unorm))
        );
        assert_eq!(
            surface_formats(&[F::Rgba16Float, F::Bgra8UnormSrgb], true),
            Some((F::Bgra8UnormSrgb, F::Bgra8Unorm))
        );
        assert_eq!(surface_formats(&[F::Rgba16Float], true), None);
    }
}
