//! What the rig shows, apart from how it is rendered: a content source makes RGB-D frames and
//! the loop hears of each one when it arrives ([`Content::poll`], woken by
//! [`Content::next_due`] and [`Content::arrivals`]); the scheduler gets the frame's depth then,
//! and the renderer ([`crate::render::Renderer`]) is handed the frame with each job.
//!
//! - [`scene`]: the procedural scene, animated on the rig's clock;
//! - [`files`]: a lab's RGB-D files, one frame or a numbered sequence;
//! - [`stream`]: frames an application pushes (shared-memory ring or `PUT /frame`), the
//!   ring's byte layout in [`ring`];
//! - [`Still`]: one fixed frame (loop tests);
//! - [`stereo`]: each eye's view on a stereo layout (the content's own two, the scene ray
//!   cast per eye, or synthesised from one RGB-D).

pub mod config;
pub mod files;
pub mod ring;
pub mod scene;
pub mod stereo;
pub mod stream;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use dioptra_core::{DepthMap, RgbImage, Rgbd, Side, Timestamp};

use crate::api::Api;
use crate::display::config::Display;
use crate::optics::config::Eye;
use config::{ContentConfig, ContentSource, DEFAULT_VIEW_SPAN_MM};

/// When a content frame arrived (a stream frame's request, a file frame's due time, the
/// scene's frame time) and when it was ready to show, on the rig's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arrival {
    pub arrived: Timestamp,
    pub ready: Timestamp,
}

/// One view of light-field content: an RGB-D image seen from `position` (metres in the pupil
/// plane, x right and y down, from `eye`'s centre; `eye` `None`: from the centre between the
/// eyes, or a mono rig's eye).
#[derive(Debug, Clone)]
pub struct ContentView {
    pub eye: Option<Side>,
    pub position: [f32; 2],
    pub rgbd: Arc<Rgbd>,
}

impl ContentView {
    /// The views of an N x N grid per eye: `rgbds` holds each of `eyes`' grid in turn, in
    /// `positions`' order.
    pub fn grid(
        eyes: &[Option<Side>],
        positions: &[[f32; 2]],
        rgbds: &[Arc<Rgbd>],
    ) -> Arc<[ContentView]> {
        let per_eye = positions.len();
        eyes.iter()
            .enumerate()
            .flat_map(|(e, &eye)| {
                positions
                    .iter()
                    .enumerate()
                    .map(move |(k, &position)| ContentView {
                        eye,
                        position,
                        rgbd: rgbds[e * per_eye + k].clone(),
                    })
            })
            .collect()
    }
}

/// One frame of content, as the loop takes it up.
#[derive(Debug, Clone)]
pub struct ContentFrame {
    /// Counts the frames the source put on show, from 1; what is made from a frame (layers,
    /// a light-field panel) is kept under its number.
    pub number: u64,
    /// Colour (linear) and depth (diopters), spanning the eye's field: the view the
    /// scheduler reads fixation depth from (the cyclopean view; stereo content without one:
    /// the left eye's).
    pub rgbd: Arc<Rgbd>,
    /// Stereo content: the left and the right eye's views (`None`: one view; a stereo
    /// layout then synthesises each eye's from `rgbd`).
    pub eyes: Option<[Arc<Rgbd>; 2]>,
    /// The eye this frame is the view of (a frame [`ContentFrame::for_eye`] made); `None`: the
    /// cyclopean or only view.
    pub eye: Option<Side>,
    /// When it arrived (`None`: a still frame, or a source that does not know).
    pub arrival: Option<Arrival>,
    /// The procedural scene's time of the frame: recorded with its depth, so a replay renders
    /// the same frame.
    pub scene_time: Option<Timestamp>,
    /// The procedural scene as this frame shows it: light-field mode ray casts its own views
    /// from it instead of synthesising them from the RGB-D.
    pub scene: Option<Arc<dioptra_sim::scene::Scene>>,
    /// Light-field content (`content.views`): every view of the frame's grid (a stereo rig's
    /// `%e` grids: each eye's), from which light-field mode synthesises the panel's views;
    /// `rgbd` (and `eyes`) are the grid's central view. `None`: one view per eye.
    pub views: Option<Arc<[ContentView]>>,
}

impl ContentFrame {
    /// A frame with only its pixels (no arrival, no scene).
    pub fn new(number: u64, rgbd: Arc<Rgbd>) -> ContentFrame {
        ContentFrame {
            number,
            rgbd,
            eyes: None,
            eye: None,
            arrival: None,
            scene_time: None,
            scene: None,
            views: None,
        }
    }

    /// The frame as `side`'s eye sees it (`view`: that eye's RGB-D), for rendering that eye.
    pub fn for_eye(&self, side: Side, view: Arc<Rgbd>) -> ContentFrame {
        ContentFrame {
            rgbd: view,
            eyes: None,
            eye: Some(side),
            ..self.clone()
        }
    }

    /// Its depth map, for the scheduler.
    pub fn depth(&self) -> Arc<DepthMap> {
        Arc::new(self.rgbd.depth.clone())
    }
}

/// A content source. Shared by the loop (which polls it), the API (status, frame ingest) and
/// the source's own worker threads, so it takes `&self`.
pub trait Content: Send + Sync + 'static {
    /// The frame to show at `now` when it is not the one returned last; always `Some` at the
    /// first call (which starts a sequence's clock).
    fn poll(&self, now: Timestamp) -> Option<ContentFrame>;
    /// When the next frame falls due on the source's own clock (a sequence, the animated
    /// scene): the loop polls then. `None`: no frame is due (a still frame, a stream).
    fn next_due(&self) -> Option<Timestamp> {
        None
    }
    /// Notified when a frame arrives from outside the loop (a stream's frame): the loop polls
    /// then.
    fn arrivals(&self) -> Option<Arc<tokio::sync::Notify>> {
        None
    }
    /// What `/status` shows under `content`: the source and its counters.
    fn status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// `source = "stream"`: where the API hands an application's frames.
    fn frame_ingest(&self) -> Option<&stream::StreamFrames> {
        None
    }
}

/// Why a content source did not open.
#[derive(Debug, thiserror::Error)]
pub enum ContentError {
    #[error("content: {0}")]
    Config(String),
    /// A file the config names (`key`: `content.color`, ...) cannot be used; `reason` begins
    /// with its path.
    #[error("{key}: {reason}")]
    File {
        key: &'static str,
        path: std::path::PathBuf,
        reason: String,
    },
    #[error("cannot render the scene the display shows: {0}")]
    Scene(#[source] dioptra_render::RenderError),
}

/// The content source `[content]` describes, at the display's size, seen by `eye` (the scene;
/// `api`: where a stream's ring goes by default); `pacing` says whether the loop waits for the
/// animated scene's frames (on a simulated clock). CPU work (the scene's first frame is ray
/// cast, the first file decoded): call it from a blocking thread.
pub fn open(
    c: &ContentConfig,
    display: &Display,
    eye: &Eye,
    api: &Api,
    pacing: scene::Pacing,
) -> Result<Arc<dyn Content>, ContentError> {
    let d = display;
    Ok(match c.source {
        ContentSource::Scene => {
            let animate = c.animate.unwrap_or(true);
            let cam = scene::camera(eye, display).map_err(ContentError::Scene)?;
            Arc::new(
                scene::AnimatedScene::start_with_eyes(
                    d.scene_seed,
                    cam,
                    animate,
                    pacing,
                    d.stereo().then_some(eye.ipd_mm * 0.5e-3),
                )
                .map_err(ContentError::Scene)?,
            )
        }
        ContentSource::Files => Arc::new(files::FileFrames::open(c, display)?),
        ContentSource::Stream => {
            let ring = c.ring_path(api);
            let s = stream::StreamFrames::with_eyes(
                d.width as usize,
                d.height as usize,
                d.stereo(),
                ring.as_deref(),
            )
            .map_err(|e| {
                let path = ring.clone().unwrap_or_default();
                ContentError::File {
                    key: "content.ring",
                    reason: format!(
                        "{}: cannot create the shared-memory ring: {e}",
                        path.display()
                    ),
                    path,
                }
            })?;
            let s = match c.views {
                Some(n) => s
                    .with_view_grid(n, c.view_span_mm.unwrap_or(DEFAULT_VIEW_SPAN_MM))
                    .map_err(|e| ContentError::Config(format!("content.views: {e}")))?,
                None => s,
            };
            Arc::new(s)
        }
    })
}

/// One fixed frame: given once, then never changes.
#[derive(Debug)]
pub struct Still {
    frame: ContentFrame,
    given: AtomicBool,
}

impl Still {
    pub fn new(rgbd: Rgbd) -> Still {
        Still {
            frame: ContentFrame::new(1, Arc::new(rgbd)),
            given: AtomicBool::new(false),
        }
    }

    /// A black frame of `depth` (loop tests, where only the depth matters).
    pub fn of_depth(depth: &DepthMap) -> Still {
        Still::new(Rgbd {
            color: RgbImage::new(depth.width(), depth.height(), [0.0; 3]),
            depth: depth.clone(),
        })
    }
}

impl Content for Still {
    fn poll(&self, _now: Timestamp) -> Option<ContentFrame> {
        (!self.given.swap(true, Ordering::AcqRel)).then(|| self.frame.clone())
    }
    fn status(&self) -> serde_json::Value {
        serde_json::json!({ "source": "still" })
    }
}
