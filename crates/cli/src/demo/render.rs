//! The demo renders with the rig's renderer ([`RgbdRenderer`], the one `dioptra serve` runs:
//! every mode and method, `--method auto` planned there) and only watches it: [`Observed`]
//! passes each job through, times it, counts the planner's choices, and keeps the few frames
//! that are scored against ground truth (their images as the rig made them; in light-field
//! mode also the views the panel is made from).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dioptra_core::{lock, RgbImage, Side, Timestamp};
use dioptra_render::{Layers, RenderError};
use dioptra_rig::config::Mode;
use dioptra_rig::content::ContentFrame;
use dioptra_rig::render::rgbd::RgbdRenderer;
use dioptra_rig::render::{RenderJob, RenderOutput, Renderer};
use dioptra_sched::RenderMethod;

use super::frames::{Kept, Output};

/// The rig's renderer, watched.
pub struct Observed {
    inner: Arc<RgbdRenderer>,
    planes: Vec<dioptra_core::Diopters>,
    state: Mutex<Watched>,
}

#[derive(Default)]
struct Watched {
    /// When the next frames to keep are shown, earliest first.
    keep_after: Vec<Timestamp>,
    kept: Vec<Kept>,
    /// `--eyes 2`: the frame whose left eye was kept: its right eye is kept too.
    keep_right: Option<u64>,
    /// `method = "auto"`: frames per choice so far.
    planned: std::collections::BTreeMap<String, u64>,
    /// `--eyes 2`: each eye's render times, left and right.
    eye_render: [Vec<Duration>; 2],
}

impl Observed {
    /// Watches `inner`, keeping the first frame shown at or after each of `keep_after`;
    /// `planes` are the rig's multifocal planes (a kept frame's layers').
    pub fn new(
        inner: Arc<RgbdRenderer>,
        keep_after: Vec<Timestamp>,
        planes: Vec<dioptra_core::Diopters>,
    ) -> Self {
        Observed {
            inner,
            planes,
            state: Mutex::new(Watched {
                keep_after,
                ..Default::default()
            }),
        }
    }

    /// `--method auto`: how many frames the planner gave each method.
    pub fn planned(&self) -> std::collections::BTreeMap<String, u64> {
        lock(&self.state).planned.clone()
    }

    /// `--eyes 2`: the render time of each frame of one eye (`right`: the right eye's).
    pub fn eye_render_times(&self, right: bool) -> Vec<Duration> {
        lock(&self.state).eye_render[usize::from(right)].clone()
    }

    pub fn take_kept(&self) -> Vec<Kept> {
        std::mem::take(&mut lock(&self.state).kept)
    }

    /// What scoring needs of a frame the rig rendered: its images on the host, and in
    /// light-field mode the views its panel is made from.
    fn output(
        &self,
        job: &RenderJob,
        frame: &ContentFrame,
        out: &RenderOutput,
    ) -> Result<Output, RenderError> {
        let mut images = out
            .images
            .iter()
            .map(|i| i.to_host().map(|i| i.into_owned()))
            .collect::<Result<Vec<RgbImage>, _>>()?;
        Ok(match job.mode {
            Mode::Multifocal => Output::Layers(Layers {
                images,
                planes: self.planes.clone(),
            }),
            Mode::Lightfield => Output::LightField {
                views: self.inner.light_field_views(frame, job.method.0)?,
                panel: images.swap_remove(0),
            },
            _ => Output::Image(images.swap_remove(0)),
        })
    }
}

impl Renderer for Observed {
    fn render(&self, job: &RenderJob, frame: &ContentFrame) -> Result<RenderOutput, RenderError> {
        let started = Instant::now();
        let mut out = self.inner.render(job, frame)?;
        let took = started.elapsed();
        let keep = {
            let mut st = lock(&self.state);
            if let Some(p) = &out.planned {
                *st.planned.entry(p.choice.clone()).or_insert(0) += 1;
            }
            if let Some(eye) = frame.eye {
                st.eye_render[usize::from(eye == Side::Right)].push(took);
            }
            if frame.eye == Some(Side::Right) {
                st.keep_right.take_if(|f| *f == job.frame).is_some()
            } else if st
                .keep_after
                .first()
                .is_some_and(|&t| job.display_time >= t)
            {
                st.keep_after.remove(0);
                if frame.eye == Some(Side::Left) {
                    st.keep_right = Some(job.frame);
                }
                true
            } else {
                false
            }
        };
        if keep {
            let output = self.output(job, frame, &out)?;
            let scene = frame.scene.as_deref().cloned().ok_or_else(|| {
                RenderError::Input(dioptra_core::InputError::InvalidValue(
                    "the demo's content frame has no scene to score against".into(),
                ))
            })?;
            lock(&self.state).kept.push(Kept {
                frame: job.frame,
                eye: frame.eye,
                display_time: job.display_time,
                scene,
                input: frame.rgbd.as_ref().clone(),
                output,
            });
        }
        // The render itself: the copies kept for scoring are the demo's.
        out.cost = Some(took);
        Ok(out)
    }
    fn network_missing(&self) -> Vec<(Mode, RenderMethod, String)> {
        self.inner.network_missing()
    }
    fn backend_status(&self) -> serde_json::Value {
        Renderer::backend_status(self.inner.as_ref())
    }
}
