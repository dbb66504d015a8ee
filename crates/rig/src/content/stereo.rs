//! Each eye's view of a content frame on a stereo layout (`display.layout` side-by-side or
//! two-outputs), made once per content frame:
//! - stereo content (a lab's left and right files, a stream's two halves): its own views;
//! - the procedural scene: ray cast from each eye's position, IPD apart on the horizontal,
//!   both looking straight ahead (parallel, as a stereo HMD's displays are: the eyes verge,
//!   the cameras do not): the rig's animated scene casts them on its own worker thread, ahead
//!   of the loop ([`super::scene`]); a frame that brings its scene but not its eyes' views (the
//!   demo's) has them cast here;
//! - one RGB-D (mono files or stream): each eye's view synthesised from it at that eye's
//!   position (`dioptra_render::views`), so a lab with one RGB-D still gets disparity.
//!   Disoccluded pixels are filled from the background side, as the light-field method's are.

use std::sync::{Arc, Mutex};

use dioptra_core::{lock, EyeModel, Rgbd, Side};
use dioptra_render::views::{synthesize_rgbd_view, RgbdView};
use dioptra_render::RenderError;
use dioptra_sim::scene::Camera;

use super::frame::ContentFrame;
use crate::display::config::Display;
use crate::optics::config::Eye;
use crate::problem::Problem;

/// Where each eye's view comes from, for the `/status` and the log.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ViewSource {
    /// The content's own two views.
    Stereo,
    /// Ray cast from the procedural scene at each eye.
    SceneRayCast,
    /// Synthesised from one RGB-D.
    Synthesised,
}

/// The views made from one content frame (its number).
type Made = (u64, [Arc<Rgbd>; 2], ViewSource);

/// Makes (and keeps, for the newest content frame) each eye's view.
pub struct EyeViews {
    cam: Camera,
    eye: EyeModel,
    half_ipd_m: f32,
    newest: Mutex<Option<Made>>,
    status: Mutex<EyeViewsStatus>,
}

/// What `/status` shows under `eye_views`.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct EyeViewsStatus {
    /// Where the newest views came from.
    pub source: Option<ViewSource>,
    /// Content frames whose views were made, and how many failed (the newest reason).
    pub made: u64,
    pub failed: u64,
    pub last_error: Option<String>,
    /// What making the newest took, ms (wall clock; both eyes; made on the device: with
    /// both eyes' renders).
    pub last_ms: Option<f64>,
    /// Where the newest views were made: `cpu`, or `gpu` (synthesised on the render's device
    /// and rendered from its memory, never on the host).
    pub made_on: Option<&'static str>,
    /// Half the interpupillary distance, mm: each eye's distance from the cyclopean eye.
    pub half_ipd_mm: f32,
    /// The newest frame's views failed (the next ones made clear it).
    #[serde(skip)]
    pub failing: bool,
}

impl std::fmt::Debug for EyeViews {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EyeViews")
            .field("half_ipd_m", &self.half_ipd_m)
            .finish_non_exhaustive()
    }
}

impl EyeViews {
    /// The eyes of `[eye]`: `ipd_mm` apart, seeing the display's field.
    pub fn new(eye: &Eye, display: &Display) -> Result<EyeViews, RenderError> {
        Ok(EyeViews {
            cam: super::scene::camera(eye, display)?,
            eye: eye.model(display.width).validated()?,
            half_ipd_m: eye.ipd_mm * 0.5e-3,
            newest: Mutex::new(None),
            status: Mutex::new(EyeViewsStatus {
                half_ipd_mm: eye.ipd_mm * 0.5,
                ..EyeViewsStatus::default()
            }),
        })
    }

    pub fn status(&self) -> serde_json::Value {
        serde_json::to_value(&*lock(&self.status)).unwrap_or_default()
    }

    /// The newest frame's views failed: each eye is not shown its own view.
    pub fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.status);
        match (st.failing, &st.last_error) {
            (true, Some(e)) => vec![Problem::new(
                "content",
                "display.layout",
                format!("the eyes' views of the newest frame were not made: {e}"),
            )],
            _ => Vec::new(),
        }
    }

    /// An eye's position, metres from the cyclopean eye (+x right).
    pub fn position(&self, side: Side) -> [f32; 2] {
        match side {
            Side::Left => [-self.half_ipd_m, 0.0],
            Side::Right => [self.half_ipd_m, 0.0],
        }
    }

    /// The left and right eye's views of `frame`, and where they came from. CPU work (a ray
    /// cast or a synthesis per eye on a new frame): call it from a blocking thread.
    pub fn of(&self, frame: &ContentFrame) -> Result<([Arc<Rgbd>; 2], ViewSource), RenderError> {
        if let Some((n, views, source)) = lock(&self.newest).as_ref() {
            if *n == frame.number {
                return Ok((views.clone(), *source));
            }
        }
        let started = std::time::Instant::now();
        let made = self.make(frame);
        let noted = made.as_ref().map(|(_, source)| *source);
        self.note(noted, started.elapsed(), "cpu");
        made
    }

    /// Whether `frame`'s views are synthesised from its one RGB-D (no views of its own, no
    /// scene to cast them from).
    pub fn synthesises(&self, frame: &ContentFrame) -> bool {
        frame.eyes.is_none() && frame.scene.is_none()
    }

    /// A frame's eyes were rendered from views on the render's device (`Ok(true)`: views
    /// synthesised for it; `false`: kept from an earlier render of it), in `took`, or failed.
    pub fn note_on_device(&self, made: Result<bool, &RenderError>, took: std::time::Duration) {
        match made {
            Ok(false) => lock(&self.status).made_on = Some("gpu"),
            Ok(true) => self.note(Ok(ViewSource::Synthesised), took, "gpu"),
            Err(e) => self.note(Err(e), took, "gpu"),
        }
    }

    fn note(
        &self,
        made: Result<ViewSource, &RenderError>,
        took: std::time::Duration,
        on: &'static str,
    ) {
        let mut st = lock(&self.status);
        match made {
            Ok(source) => {
                st.made += 1;
                st.source = Some(source);
                st.made_on = Some(on);
                st.failing = false;
                st.last_ms = Some(took.as_secs_f64() * 1e3);
            }
            Err(e) => {
                st.failed += 1;
                st.last_error = Some(e.to_string());
                st.failing = true;
            }
        }
    }

    fn make(&self, frame: &ContentFrame) -> Result<([Arc<Rgbd>; 2], ViewSource), RenderError> {
        let (views, source) = match (&frame.eyes, &frame.scene) {
            // The rig's scene casts its eyes' views on its own worker.
            (Some(eyes), Some(_)) => (eyes.clone(), ViewSource::SceneRayCast),
            (Some(eyes), None) => (eyes.clone(), ViewSource::Stereo),
            (None, Some(scene)) => (
                super::scene::cast_eyes(scene, &self.cam, self.half_ipd_m)?,
                ViewSource::SceneRayCast,
            ),
            (None, None) => {
                let input = [RgbdView {
                    position: [0.0, 0.0],
                    rgbd: frame.rgbd.as_ref().clone(),
                }];
                let synth = |side| -> Result<Arc<Rgbd>, RenderError> {
                    Ok(Arc::new(synthesize_rgbd_view(
                        &input,
                        self.position(side),
                        &self.eye,
                    )?))
                };
                let (l, r) = rayon::join(|| synth(Side::Left), || synth(Side::Right));
                ([l?, r?], ViewSource::Synthesised)
            }
        };
        let mut newest = lock(&self.newest);
        if newest.as_ref().is_none_or(|(n, _, _)| *n <= frame.number) {
            *newest = Some((frame.number, views.clone(), source));
        }
        Ok((views, source))
    }
}

#[cfg(test)]
mod tests;
