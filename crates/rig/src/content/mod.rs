//! What the rig shows, apart from how it is rendered: a content source makes RGB-D frames and
//! the loop hears of each one when it arrives ([`Content::poll`], woken by
//! [`Content::next_due`] and [`Content::arrivals`]); the scheduler gets the frame's depth then,
//! and the renderer (`render::Renderer`) is handed the frame with each job.
//!
//! - [`frame`]: a content frame as the loop takes it up; [`source`]: what a content source is;
//! - [`scene`]: the procedural scene, animated on the rig's clock;
//! - [`files`]: a lab's RGB-D files, one frame or a numbered sequence;
//! - [`stream`]: frames an application pushes (shared-memory ring or `PUT /frame`), the
//!   ring's byte layout in [`ring`];
//! - [`Still`]: one fixed frame (loop tests);
//! - [`stereo`]: each eye's view on a stereo layout (the content's own two, the scene ray
//!   cast per eye, or synthesised from one RGB-D);
//! - [`config`]: `[content]`; [`open`] makes the source it describes; [`status`]: what the
//!   part publishes.

pub mod config;
pub mod files;
pub mod frame;
pub mod ring;
pub mod scene;
pub mod source;
pub mod status;
pub mod stereo;
pub mod stream;

use std::sync::Arc;

pub use frame::{Arrival, ContentFrame, ContentView};
pub use source::{Content, ContentError, Still};
pub use status::ContentHandle;

use crate::api::Api;
use crate::display::config::Display;
use crate::optics::config::Eye;
use config::{ContentConfig, ContentSource, DEFAULT_VIEW_SPAN_MM};

/// Tests' content of `cfg` on the simulated clock.
#[cfg(test)]
pub(crate) fn open_simulated(cfg: &crate::config::RigConfig) -> Arc<dyn Content> {
    open(
        &cfg.content,
        &cfg.display,
        &cfg.eye,
        &cfg.api,
        scene::Pacing::Simulated,
    )
    .unwrap()
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
