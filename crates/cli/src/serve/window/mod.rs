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
//! Drawing. The window draws with the rig's blit ([`dioptra_rig::display::blit`], beside the
//! placement it mirrors): its GPU objects are made once, and frames are linear light, packed as
//! 8-bit sRGB or read from the render's buffer. The surface is viewed through an sRGB format,
//! so the hardware encodes on write: what the monitor gets is the sRGB encoding of the frame,
//! as in the PNGs the headless sink writes.
//!
//! Placement. Each eye's image is drawn at the rectangle
//! [`dioptra_rig::display::placement`] gives for the surface the system made (the viewport
//! set to it): 1:1 onto surface pixels with `display.scale = "exact"`, centred in its place
//! (the whole surface for layout `one`, its half of a side-by-side panel, its own window for
//! `two-outputs`) and moved by `display.eye_offset_px`; scaled to fit with `"fit"` (the
//! letterbox). A frame that does not fit, or (exact) a surface that is not its monitor's size,
//! is not shown: counted in `/status` (`misfit`), logged once per reason; the screen goes
//! black rather than showing a stimulus at the wrong size or place. The window asks for its
//! monitor's size and position as well as fullscreen, so that without a window manager it
//! still covers the monitor; the surface size obtained is logged and in `/status`.
//!
//! Image corrections. Where the rig compensates magnification, pre-warps for an eyepiece or
//! drives a panel that is not sRGB, each eye's image is drawn through the GPU twin of the
//! headless sink's CPU path ([`dioptra_rig::display::panel_draw`]): the warp mesh per colour
//! channel, scaled for the frame's compensation, and the panel's transfer table, into a
//! non-sRGB view of the surface. Where the rig renders on the CPU these run on the process's
//! GPU context, the frames uploaded.
//!
//! Two outputs. `layout = "two-outputs"` opens a borderless fullscreen window on each of
//! `display.monitor_left` and `display.monitor_right` (name or index, as `display.monitor`),
//! each pixel-exact as the one window is, drawn on one device and presented together
//! ([`presenter`]'s doc says how, and the limits). A monitor that is not there stops
//! `dioptra serve` at start with the key and the list of monitors.
//!
//! Parts: [`app`] (the winit event loop on the main thread), [`monitor`] (display and monitor
//! choice), [`presenter`] (the sink, its thread and the windows' GPU surfaces).

mod app;
mod error;
mod monitor;
mod presenter;

pub use app::{run_on_main_thread, WindowReady};
pub use monitor::Outputs;
pub use presenter::WindowSink;
