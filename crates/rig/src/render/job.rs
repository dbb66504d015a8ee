//! What travels between the loop and the render worker: the job ([`RenderJob`]), the frame's
//! images ([`FrameImage`], on the host or the GPU) and the result ([`RenderOutput`]); what
//! renders it ([`Renderer`]); and what is shown when a render fails ([`unblurred`]).

use std::borrow::Cow;
use std::time::Duration;

use dioptra_core::{Diopters, RgbImage, Timestamp};
use dioptra_render::gpu::GpuImage;
use dioptra_render::RenderError;

use crate::content::frame::ContentFrame;
use crate::mode::{Method, Mode};

/// A frame to render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderJob {
    pub frame: u64,
    pub mode: Mode,
    pub method: Method,
    /// The focus it is rendered for (the lens's park power when the scheduler gave none).
    pub focus: Diopters,
    /// A stereo layout with a lens per eye: the right eye's focus (its own lens's); `None`:
    /// both eyes at `focus`.
    pub focus_right: Option<Diopters>,
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
    /// `none`, `gather`, `lightfield-N`, `pyramid` or `pyramid-foveated (...)`.
    pub choice: String,
    pub predicted_psnr_db: f64,
    /// The render's predicted time, one eye, ms.
    pub predicted_ms: f64,
    /// The time one eye's render may take (the display period less a margin, shared by the
    /// eyes), ms.
    pub budget_ms: f64,
    pub why: String,
}

/// Renders jobs. Called from the render worker's blocking thread, so it is shared and takes
/// `&self`; it knows nothing of where content comes from: each job brings its content frame.
pub trait Renderer: Send + Sync + 'static {
    /// Renders one frame of `content`.
    fn render(&self, job: &RenderJob, content: &ContentFrame) -> Result<RenderOutput, RenderError>;
    /// The modes in which a net's method (`network`, `refine`) cannot render, and why (its
    /// weights did not load; the API refuses a switch to them).
    fn network_missing(&self) -> Vec<(Mode, dioptra_sched::RenderMethod, String)> {
        Vec::new()
    }
    /// What `/status` shows under `render`: the backend frames are rendered on.
    fn backend_status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// A stereo layout's frame whose eyes' views are synthesised from its one RGB-D: each
    /// eye's view (the eyes at `positions`, metres, left then right) made on the renderer's
    /// device and rendered from there, the left eye's at `job.focus` and the right's at
    /// `job.focus_right` (else `focus`). `None`: this renderer does not (the caller makes the
    /// views on the host and renders each eye with [`Renderer::render`]).
    fn render_eyes_on_device(
        &self,
        _job: &RenderJob,
        _content: &ContentFrame,
        _positions: [[f32; 2]; 2],
    ) -> Option<Result<EyesOnDevice, RenderError>> {
        None
    }
}

/// Both eyes of a frame rendered from views made on the renderer's device.
#[derive(Debug)]
pub struct EyesOnDevice {
    /// The left eye's render, and the right eye's.
    pub outputs: [RenderOutput; 2],
    /// The views were synthesised for this call (not kept from an earlier render of the same
    /// content frame).
    pub made: bool,
}

/// What is shown when a render fails, so the display never freezes: the content without
/// blur (in multifocal mode spread evenly over the `planes`, which add up to it).
pub fn unblurred(mode: Mode, content: &ContentFrame, planes: usize) -> Option<Vec<RgbImage>> {
    let color = &content.rgbd.color;
    Some(match mode {
        Mode::Multifocal => {
            let n = planes.max(1);
            let share = 1.0 / n as f32;
            let [r, g, b] = color.channels.each_ref().map(|p| {
                let d = p.data().iter().map(|v| v * share).collect();
                dioptra_core::Plane::from_vec(p.width(), p.height(), d)
            });
            let layer = RgbImage::from_planes(r.ok()?, g.ok()?, b.ok()?).ok()?;
            vec![layer; n]
        }
        _ => vec![color.clone()],
    })
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
