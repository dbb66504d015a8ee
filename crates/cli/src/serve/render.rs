//! The daemon's render workers' work: the rig shows a procedural scene (dioptra-sim, seed
//! `display.scene_seed`) rendered once as RGB-D at the display's size, and each frame is made
//! from it by the configured method on the CPU backend. The scene is static, so a multifocal
//! decomposition (which does not depend on the focus) is made once per method and reused, and
//! so is the light-field panel: 5 x 5 pinhole views of the scene over a 4 mm pupil, resampled
//! by `dioptra_sched::lenslet` onto a lenslet display of (width / 5) x (height / 5) lenslets of
//! 5 x 5 pixels (0.25 mm pitch, 0.94 mm gap, 15 mm eye relief).
//!
//! With `method = "auto"` (varifocal mode) each frame's method is chosen here, where frames
//! are rendered, by `dioptra_render::planner` from the frame's depth around the gaze point
//! and the focus: no blur, gather, or the light-field method with as few views as the
//! disparity needs. The scheduler (sans-IO) chooses the focus, not the method.

use std::sync::{Arc, Mutex};

use dioptra_core::{Diopters, EyeModel, Millimeters, RgbImage, Rgbd};
use dioptra_render::lightfield::LightFieldParams;
use dioptra_render::multifocal::{default_focal_samples, linear_blend, optimized_blend};
use dioptra_render::planner::{Choice, FrameStats, Planner, Target};
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
    scene: dioptra_sim::scene::Scene,
    cam: dioptra_sim::scene::Camera,
    panel: Mutex<Option<Arc<RgbImage>>>,
    /// `method = "auto"`: plan each varifocal frame.
    auto: bool,
}

/// A frame's images, and the planner's choice when it chose.
#[derive(Debug)]
pub struct RenderedFrame {
    pub images: Vec<RgbImage>,
    /// `method = "auto"`: what the planner chose and why.
    pub planned: Option<Planned>,
}

/// The planner's choice for one frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Planned {
    /// `none`, `gather` or `lightfield-N`.
    pub choice: String,
    pub predicted_psnr_db: f64,
    pub why: String,
}

/// The light field shown in light-field mode: views per side and the pupil span they cover.
const LF_GRID: usize = 5;
const LF_SPAN_M: f32 = 0.004;

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
        let cam = dioptra_sim::scene::Camera::new(eye, d.width as usize, d.height as usize);
        Ok(Renderer {
            input: Rgbd::new(color, depth)?,
            eye,
            planes: cfg.optics.planes.iter().copied().map(Diopters).collect(),
            layers: Mutex::new(Vec::new()),
            scene,
            cam,
            panel: Mutex::new(None),
            auto: cfg.auto_method,
        })
    }

    /// The scene's RGB-D (its depth is what the scheduler looks up at the gaze point).
    pub fn input(&self) -> &Rgbd {
        &self.input
    }

    /// The images of one frame: one for varifocal and light field, one per plane for
    /// multifocal. `gaze` is the gaze point in pixels (the image centre when unknown); with
    /// `method = "auto"` the planner chooses a varifocal frame's method from it. CPU work:
    /// call it from a blocking thread.
    pub fn render(
        &self,
        mode: Mode,
        method: Method,
        focus: Diopters,
        gaze: Option<[f32; 2]>,
    ) -> Result<RenderedFrame, RenderError> {
        if self.auto && mode == Mode::Varifocal {
            let (w, h) = (self.input.width() as f32, self.input.height() as f32);
            let gaze = gaze.unwrap_or([0.5 * w, 0.5 * h]);
            let stats = FrameStats::from_rgbd(&self.input, gaze, focus, &self.eye);
            let plan = Planner.plan(&stats, &Target::default());
            let image = match plan.choice {
                Choice::None => self.input.color.clone(),
                Choice::Gather => dioptra_render::gather::gather(&self.input, focus, &self.eye)?,
                Choice::LightField { views } => dioptra_render::lightfield::lightfield(
                    &self.input,
                    focus,
                    &self.eye,
                    LightFieldParams { views, mip: true },
                )?,
            };
            return Ok(RenderedFrame {
                images: vec![image],
                planned: Some(Planned {
                    choice: plan.choice.to_string(),
                    predicted_psnr_db: plan.predicted_psnr,
                    why: plan.why,
                }),
            });
        }
        Ok(RenderedFrame {
            images: self.render_fixed(mode, method, focus)?,
            planned: None,
        })
    }

    fn render_fixed(
        &self,
        mode: Mode,
        method: Method,
        focus: Diopters,
    ) -> Result<Vec<RgbImage>, RenderError> {
        match (mode, method.0) {
            (_, RenderMethod::Views) => Ok(vec![self.panel()?.as_ref().clone()]),
            (_, RenderMethod::Network) => Err(RenderError::Unsupported {
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

    /// The lenslet panel image of the scene's light field.
    fn panel(&self) -> Result<Arc<RgbImage>, RenderError> {
        use dioptra_sched::lenslet::{elemental_images, LensletDisplay, ViewGrid};
        if let Some(p) = lock(&self.panel).as_ref() {
            return Ok(p.clone());
        }
        let (w, h) = (self.cam.width, self.cam.height);
        // Views at half size: a panel of 5 px per lenslet cannot show more.
        let vcam = dioptra_sim::scene::Camera::new(self.cam.eye, (w / 2).max(8), (h / 2).max(8));
        let views =
            dioptra_sim::scene::render_light_field(&self.scene, &vcam, LF_GRID, LF_SPAN_M, 1)?;
        let images: Vec<RgbImage> = views.into_iter().map(|v| v.color).collect();
        let grid = ViewGrid {
            grid: LF_GRID,
            spacing_m: LF_SPAN_M / (LF_GRID - 1) as f32,
            views: &images,
            pixel_pitch_tan: vcam.eye.pixel_pitch_tan(),
        };
        let display = LensletDisplay {
            lenslets: [(w / 5).max(1), (h / 5).max(1)],
            pixels_per_lenslet: 5,
            lenslet_pitch_m: 0.000_25,
            gap_m: 0.000_94,
            eye_relief_m: 0.015,
        };
        let panel = Arc::new(elemental_images(&grid, &display)?);
        *lock(&self.panel) = Some(panel.clone());
        Ok(panel)
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
