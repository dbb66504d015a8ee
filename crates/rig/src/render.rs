//! The render worker's side of the loop: what makes a frame's images ([`Renderer`]), and the
//! job and result that travel between the loop and the worker thread.

use std::borrow::Cow;
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{DepthMap, Diopters, RgbImage, Timestamp};
use dioptra_render::gpu::GpuImage;
use dioptra_render::RenderError;

use crate::config::{Method, Mode};

/// A frame to render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderJob {
    pub frame: u64,
    pub mode: Mode,
    pub method: Method,
    /// The focus it is rendered for (the lens's park power when the scheduler gave none).
    pub focus: Diopters,
    /// Gaze point on the frame, pixels (for `method = "auto"`).
    pub gaze: Option<[f32; 2]>,
    /// `method = "auto"`: the planner chooses this (varifocal) frame's method.
    pub auto: bool,
    /// When the scheduler will show it.
    pub display_time: Timestamp,
}

/// One image of a frame, where it was made: on the host, or in the GPU memory of the
/// render's device (a window on that device shows it without a copy; anything that needs its
/// pixels on the host reads it back: [`FrameImage::to_host`]).
#[derive(Debug, Clone)]
pub enum FrameImage {
    Host(RgbImage),
    Gpu(GpuImage),
}

impl FrameImage {
    pub fn width(&self) -> usize {
        match self {
            FrameImage::Host(i) => i.width(),
            FrameImage::Gpu(g) => g.width(),
        }
    }
    pub fn height(&self) -> usize {
        match self {
            FrameImage::Host(i) => i.height(),
            FrameImage::Gpu(g) => g.height(),
        }
    }
    /// Its pixels on the host: the image itself, or a copy read back from the GPU.
    pub fn to_host(&self) -> Result<Cow<'_, RgbImage>, RenderError> {
        match self {
            FrameImage::Host(i) => Ok(Cow::Borrowed(i)),
            FrameImage::Gpu(g) => Ok(Cow::Owned(g.read()?)),
        }
    }
}

impl From<RgbImage> for FrameImage {
    fn from(i: RgbImage) -> FrameImage {
        FrameImage::Host(i)
    }
}

/// A frame's images, and the planner's choice when it chose.
#[derive(Debug)]
pub struct RenderOutput {
    /// One image (varifocal, light field) or one per focal plane (multifocal).
    pub images: Vec<FrameImage>,
    /// `method = "auto"`: what the planner chose and why.
    pub planned: Option<Planned>,
    /// The time the render counts as having taken. `None`: the wall time it took on this
    /// machine. A scripted renderer (the loop tests) gives its own.
    pub cost: Option<Duration>,
}

/// The planner's choice for one frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Planned {
    /// `none`, `gather` or `lightfield-N`.
    pub choice: String,
    pub predicted_psnr_db: f64,
    pub why: String,
}

/// When a content frame arrived (a stream frame's request, a file frame's due time) and when it
/// was ready to render, on the rig's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arrival {
    pub arrived: Timestamp,
    pub ready: Timestamp,
}

/// Makes frames from the rig's content. Called from the render worker's blocking thread
/// (`render`) and from the loop (`depth`), so it is shared and takes `&self`.
pub trait Renderer: Send + Sync + 'static {
    /// The depth map (diopters, spanning the eye's field) of the content at `now`, when it
    /// differs from the one returned last; always `Some` at the first call. The scheduler
    /// reads the fixation depth from it.
    fn depth(&self, now: Timestamp) -> Option<Arc<DepthMap>>;
    /// The arrival of the content frame the latest `depth` call took up, once (`None` when
    /// it took none, or the source does not know: a still scene).
    fn take_arrival(&self) -> Option<Arrival> {
        None
    }
    /// The scene time of the content frame on show, for content that has one (the animated
    /// procedural scene): recorded with each depth, so a replay renders the same frame.
    fn content_time(&self) -> Option<Timestamp> {
        None
    }
    /// Renders one frame.
    fn render(&self, job: &RenderJob) -> Result<RenderOutput, RenderError>;
    /// The modes in which a net's method (`network`, `refine`) cannot render, and why (its
    /// weights did not load; the API refuses a switch to them).
    fn network_missing(&self) -> Vec<(Mode, dioptra_sched::RenderMethod, String)> {
        Vec::new()
    }
    /// What is shown when `render` fails, so the display never freezes: the content without
    /// blur (in multifocal mode spread evenly over the planes, which add up to it). `None`:
    /// nothing (the previous frame stays up).
    fn unblurred(&self, _job: &RenderJob) -> Option<Vec<RgbImage>> {
        None
    }
    /// What `/status` shows under `content`: the source and its counters.
    fn content_status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// What `/status` shows under `render`: the backend frames are rendered on.
    fn backend_status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// `source = "stream"`: where the API hands an application's frames.
    fn stream(&self) -> Option<&crate::stream::StreamFrames> {
        None
    }
}

/// The kind of a render error, for counting and rate-limited logging.
pub fn error_kind(e: &RenderError) -> &'static str {
    match e {
        RenderError::Input(_) => "input",
        RenderError::Unsupported { .. } => "unsupported",
        RenderError::Gpu(_) => "gpu",
        RenderError::Io { .. } => "io",
        RenderError::Format { .. } => "format",
    }
}
