//! The daemon's render workers' work: the rig shows a procedural scene (dioptra-sim, seed
//! `display.scene_seed`) rendered once as RGB-D at the display's size, and each frame is made
//! from it by the configured method on the CPU backend. The scene is static, so a multifocal
//! decomposition (which does not depend on the focus) is made once per method and reused.

use std::sync::{Arc, Mutex};

use dioptra_core::{Diopters, EyeModel, Millimeters, RgbImage, Rgbd};
use dioptra_render::lightfield::LightFieldParams;
use dioptra_render::multifocal::{default_focal_samples, linear_blend, optimized_blend};
use dioptra_render::{OptimizeParams, RenderError};

use super::config::{Method, Mode, RigConfig};
use super::devices::lock;
use dioptra_sched::RenderMethod;

/// Renders frames of one scene; shared by the render workers.
pub struct Renderer {
    input: Rgbd,
    eye: EyeModel,
    planes: Vec<Diopters>,
    layers: Mutex<Vec<(Method, Arc<Vec<RgbImage>>)>>,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("width", &self.input.width())
            .field("height", &self.input.height())
            .finish_non_exhaustive()
    }
}

impl Renderer {
    pub fn new(cfg: &RigConfig) -> Result<Renderer, RenderError> {
        let d = &cfg.display;
        let eye = EyeModel {
            pupil_diameter: Millimeters(cfg.eye.pupil_mm),
            fov_horizontal_deg: cfg.eye.fov_deg,
            width_px: d.width,
            ..EyeModel::default()
        }
        .validated()?;
        let cam = dioptra_sim::scene::Camera::new(eye, d.width as usize, d.height as usize);
        let scene = dioptra_sim::scene::Scene::generate(d.scene_seed);
        let (color, depth) = dioptra_sim::scene::render_pinhole(&scene, &cam, [0.0, 0.0], 2)?;
        Ok(Renderer {
            input: Rgbd::new(color, depth)?,
            eye,
            planes: cfg.optics.planes.iter().copied().map(Diopters).collect(),
            layers: Mutex::new(Vec::new()),
        })
    }

    /// The scene's RGB-D (its depth is what the scheduler looks up at the gaze point).
    pub fn input(&self) -> &Rgbd {
        &self.input
    }

    /// The images of one frame: one for varifocal and light field, one per plane for
    /// multifocal. CPU work: call it from a blocking thread.
    pub fn render(
        &self,
        mode: Mode,
        method: Method,
        focus: Diopters,
    ) -> Result<Vec<RgbImage>, RenderError> {
        match (mode, method.0) {
            (_, RenderMethod::Network | RenderMethod::Views) => Err(RenderError::Unsupported {
                backend: "daemon CPU",
                method: method.as_str(),
            }),
            (Mode::Multifocal, _) => Ok(self.layers(method)?.as_ref().clone()),
            (_, RenderMethod::LightFieldDefocus) => {
                Ok(vec![dioptra_render::lightfield::lightfield(
                    &self.input,
                    focus,
                    &self.eye,
                    LightFieldParams {
                        views: 16,
                        mip: true,
                    },
                )?])
            }
            _ => Ok(vec![dioptra_render::gather::gather(
                &self.input,
                focus,
                &self.eye,
            )?]),
        }
    }

    fn layers(&self, method: Method) -> Result<Arc<Vec<RgbImage>>, RenderError> {
        if let Some((_, l)) = lock(&self.layers).iter().find(|(m, _)| *m == method) {
            return Ok(l.clone());
        }
        let linear = linear_blend(&self.input, &self.planes)?;
        let images = if method.0 == RenderMethod::Optimized {
            let foci = default_focal_samples();
            let targets = foci
                .iter()
                .map(|&q| dioptra_render::gather::gather(&self.input, q, &self.eye))
                .collect::<Result<Vec<_>, _>>()?;
            let params = OptimizeParams {
                iterations: 30,
                ..OptimizeParams::default()
            };
            optimized_blend(
                &targets,
                &foci,
                &self.planes,
                &self.eye,
                Some(&linear),
                params,
                |_| {},
            )?
            .0
            .images
        } else {
            linear.images
        };
        let images = Arc::new(images);
        lock(&self.layers).push((method, images.clone()));
        Ok(images)
    }
}
