//! The demo's content and renderer: an animated procedural scene, its RGB-D frames, the CPU
//! render methods per mode, and the few frames kept for scoring against ground truth. It is
//! the rig runtime's [`Content`] (the loop polls it for the scene as it is now, at most every
//! 50 ms) and its [`Renderer`] (the rig renders on its worker thread). With `--method auto` (varifocal) each frame's method is
//! chosen here, where it is rendered, by `dioptra_render::planner` from the frame's depth
//! around the gaze point and its focus.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use dioptra_core::{lock, DepthMap, Diopters, EyeModel, RgbImage, Rgbd, Side, Timestamp};
use dioptra_render::lightfield::lightfield;
use dioptra_render::multifocal::linear_blend;
use dioptra_render::planner::{Choice, FrameStats, Planner};
use dioptra_render::retina::{retina_lightfield, retina_multifocal, retina_varifocal, LfView};
use dioptra_render::views::{synthesize_light_field, RgbdView};
use dioptra_render::LightFieldParams;
use dioptra_render::RenderError;
use dioptra_render::{gather::gather, Layers};
use dioptra_rig::config::Mode as RigMode;
use dioptra_rig::content::{Content, ContentFrame};
use dioptra_rig::render::{RenderJob, RenderOutput, Renderer};
use dioptra_sched::depth::{window_depth, DepthWindow};
use dioptra_sched::lenslet::{elemental_images, LensletDisplay, ViewGrid};
use dioptra_sched::processing::Angles;
use dioptra_sched::Mode;
use dioptra_sim::gaze::generator::{Segment, Target};
use dioptra_sim::scene::animation::{centre, Animation};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, SceneOptions};

/// The light field shown in light-field mode: 5 x 5 views over the 4 mm pupil, synthesised
/// from 5 sparse RGB-D views (centre and corners).
const LF_GRID: usize = 5;
const LF_SPAN_M: f32 = 0.004;

/// A lenslet display in front of the eye: 24 x 24 lenslets of 5 x 5 pixels (one per view).
const LENSLETS: LensletDisplay = LensletDisplay {
    lenslets: [24, 24],
    pixels_per_lenslet: 5,
    lenslet_pitch_m: 0.00025,
    gap_m: 0.00094,
    eye_relief_m: 0.015,
};

/// The scene's RGB-D input is re-rendered at most this often (20 Hz animation): ray casting
/// it is the demo's own cost, not the display pipeline's.
const SCENE_UPDATE: Duration = Duration::from_millis(50);

/// What a frame's renderer made.
pub enum Output {
    Image(RgbImage),
    Layers(Layers),
    LightField { views: Vec<LfView>, panel: RgbImage },
}

/// A frame kept for scoring.
pub struct Kept {
    pub frame: u64,
    /// Whose view (`--eyes 2`); `None`: the one eye's.
    pub eye: Option<Side>,
    pub display_time: Timestamp,
    pub scene: Scene,
    pub input: Rgbd,
    pub output: Output,
}

/// The scene as it is at one instant: its RGB-D, and the sparse views light-field mode
/// synthesises from.
struct SceneFrame {
    /// The content frame's number.
    number: u64,
    scene: Scene,
    rgbd: Arc<Rgbd>,
    sparse: Vec<RgbdView>,
    /// `--eyes 2`: each eye's view.
    eyes: Option<[Arc<Rgbd>; 2]>,
}

/// Scene frames kept for renders still to come (a render may show a frame the loop has
/// already moved past).
const FRAMES_KEPT: usize = 4;

pub struct DemoFrames {
    mode: Mode,
    base: Scene,
    movers: Animation,
    cam: Camera,
    /// Light-field views are made at half size: the lenslet panel (120 px) cannot show more,
    /// and view synthesis is the slow part.
    lf_cam: Camera,
    eye: EyeModel,
    planes: Vec<Diopters>,
    targets: Vec<Target>,
    seconds: f64,
    started: Instant,
    /// `--method auto`: plan each varifocal frame.
    auto: bool,
    /// `--eyes 2`: half the interpupillary distance, metres: each frame's eyes' views are
    /// ray cast with it, off the render path (as the rig's own scene does).
    half_ipd_m: Option<f32>,
    /// What changes as the run goes: the loop and the render thread both reach it.
    state: Mutex<DemoState>,
}

#[derive(Default)]
struct DemoState {
    printed_second: u64,
    /// The newest scene frames, oldest first.
    recent: std::collections::VecDeque<Arc<SceneFrame>>,
    current_at: Option<Timestamp>,
    /// Content frames handed to the loop.
    given: u64,
    keep_after: Vec<Timestamp>,
    kept: Vec<Kept>,
    /// `--method auto`: frames per choice so far.
    planned: std::collections::BTreeMap<String, u64>,
    /// `--eyes 2`: each eye's render times, left and right.
    eye_render: [Vec<Duration>; 2],
    /// `--eyes 2`: the frame whose left eye was kept: its right eye is kept too.
    keep_right: Option<u64>,
}

/// Gaze angles of a scene point (scene: x right, y down, z forward).
fn angles_of(p: [f32; 3]) -> Angles {
    Angles::from_direction([f64::from(p[0]), -f64::from(p[1]), f64::from(p[2])])
}

impl DemoFrames {
    /// The demo scene of `seed` at `size` pixels, seen through `eye` (the rig config's), with
    /// the rig's multifocal `planes`.
    pub fn new(
        mode: Mode,
        seed: u64,
        size: usize,
        seconds: f64,
        auto: bool,
        eye: EyeModel,
        planes: Vec<Diopters>,
    ) -> Result<Self> {
        let base = Scene::generate_with(
            seed,
            &SceneOptions {
                objects: 12,
                depth_range: (0.3, 3.0),
                semi_transparent: false,
            },
        );
        let cam = Camera::square(eye, size);
        let lf_cam = Camera::square(eye, (size / 2).max(16));
        let (_, depth) =
            render_pinhole(&base, &cam, [0.0, 0.0], 1).context("cannot render the demo scene")?;
        let targets = pick_targets(&depth, eye.fov_horizontal_deg);
        // Animate objects away from the gaze targets, so the viewer's objects stay put.
        let movers = Animation::pick(&base, 4, |o| {
            let a = angles_of(centre(&o.shape));
            targets.iter().all(|t| {
                a.distance_deg(&Angles {
                    yaw_deg: t.yaw_deg,
                    pitch_deg: t.pitch_deg,
                }) > 5.0
            })
        });
        let keep_after = [0.3, 0.55, 0.8]
            .iter()
            .map(|f| Timestamp::ZERO + Duration::from_secs_f64(seconds * f))
            .collect();
        Ok(DemoFrames {
            mode,
            base,
            movers,
            cam,
            lf_cam,
            eye,
            planes,
            targets,
            seconds,
            started: Instant::now(),
            auto,
            half_ipd_m: None,
            state: Mutex::new(DemoState {
                keep_after,
                ..Default::default()
            }),
        })
    }

    /// `--eyes 2`: each frame carries each eye's view, the eyes `2 x half_ipd_m` apart.
    pub fn with_eyes(self, half_ipd_m: Option<f32>) -> Self {
        DemoFrames { half_ipd_m, ..self }
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// The viewer's script: fixate each target in turn, with a blink now and then.
    pub fn gaze_scene(&self) -> dioptra_sim::gaze::Scene {
        let mut script = Vec::new();
        for i in 0..self.targets.len() {
            script.push(Segment::Fixate { target: i, ms: 700 });
            if i == 1 {
                script.push(Segment::Blink { ms: 150 });
            }
        }
        dioptra_sim::gaze::Scene {
            name: "demo".into(),
            targets: self.targets.clone(),
            script,
        }
    }

    fn scene_at(&self, t: Timestamp) -> Scene {
        self.movers.at(&self.base, t.as_secs_f64())
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

    /// What the eye focused at `accommodation` sees of a kept frame, with the lens (varifocal)
    /// really at `lens`.
    pub fn eye_view(
        &self,
        k: &Kept,
        accommodation: Diopters,
        lens: Option<Diopters>,
    ) -> Result<RgbImage> {
        Ok(match &k.output {
            Output::Image(img) => {
                let display = Diopters(lens.unwrap_or(accommodation).0.max(0.0));
                retina_varifocal(img, display, accommodation, &self.eye)?
            }
            Output::Layers(l) => retina_multifocal(l, &[accommodation], &self.eye)?
                .pop()
                .context("no retinal image")?,
            Output::LightField { views, .. } => retina_lightfield(
                views,
                LF_SPAN_M / (LF_GRID - 1) as f32,
                accommodation,
                &self.eye,
            )?,
        })
    }

    pub fn ground_truth(
        &self,
        k: &Kept,
        accommodation: Diopters,
        samples: u32,
    ) -> Result<RgbImage> {
        let cam = match k.output {
            Output::LightField { .. } => &self.lf_cam,
            _ => &self.cam,
        };
        Ok(render_thin_lens(&k.scene, cam, accommodation, samples)?)
    }

    /// The displayed image(s) of a kept frame, named for their files.
    pub fn rendered_images(&self, k: &Kept) -> Vec<(String, RgbImage)> {
        match &k.output {
            Output::Image(img) => vec![("rendered".into(), img.clone())],
            Output::Layers(l) => l
                .images
                .iter()
                .zip(&l.planes)
                .map(|(img, p)| (format!("layer_{:.1}D", p.0), img.clone()))
                .collect(),
            Output::LightField { panel, .. } => vec![("rendered".into(), panel.clone())],
        }
    }

    /// The planner's method for a varifocal frame focused at `q`, at the job's gaze point.
    fn plan(&self, job: &RenderJob, input: &Rgbd, q: Diopters) -> Choice {
        let (w, h) = (input.width() as f32, input.height() as f32);
        let gaze = job.gaze.unwrap_or([0.5 * w, 0.5 * h]);
        let stats = FrameStats::from_rgbd(input, gaze, q, &self.eye);
        let plan = Planner.plan(&stats, &dioptra_render::planner::Target::default());
        *lock(&self.state)
            .planned
            .entry(plan.choice.to_string())
            .or_insert(0) += 1;
        plan.choice
    }

    fn render_output(&self, job: &RenderJob, input: &Rgbd, sparse: &[RgbdView]) -> Option<Output> {
        Some(match self.mode {
            Mode::Varifocal => {
                let q = Diopters(job.focus.0.max(0.0));
                let choice = if self.auto {
                    self.plan(job, input, q)
                } else {
                    Choice::Gather
                };
                Output::Image(match choice {
                    Choice::None => input.color.clone(),
                    Choice::Gather => gather(input, q, &self.eye).ok()?,
                    Choice::LightField { views } => {
                        lightfield(input, q, &self.eye, LightFieldParams { views, mip: true })
                            .ok()?
                    }
                })
            }
            Mode::Multifocal => Output::Layers(linear_blend(input, &self.planes).ok()?),
            Mode::LightField => {
                let views =
                    synthesize_light_field(sparse, LF_GRID, LF_SPAN_M, &self.eye, |_| {}).ok()?;
                let images: Vec<RgbImage> = views.iter().map(|v| v.image.clone()).collect();
                let grid = ViewGrid {
                    grid: LF_GRID,
                    spacing_m: LF_SPAN_M / (LF_GRID - 1) as f32,
                    views: &images,
                    pixel_pitch_tan: self.lf_cam.eye.pixel_pitch_tan(),
                };
                let panel = elemental_images(&grid, &LENSLETS).ok()?;
                Output::LightField { views, panel }
            }
        })
    }
}

impl DemoFrames {
    /// The scene at `t` rendered as the renderer's input.
    fn content_at(&self, t: Timestamp, number: u64) -> Option<SceneFrame> {
        let scene = self.scene_at(t);
        let (color, depth) = render_pinhole(&scene, &self.cam, [0.0, 0.0], 1).ok()?;
        let rgbd = Arc::new(Rgbd::new(color, depth).ok()?);
        let mut sparse = Vec::new();
        if self.mode == Mode::LightField {
            let h = LF_SPAN_M * 0.5;
            for position in [[0.0, 0.0], [-h, -h], [h, -h], [-h, h], [h, h]] {
                let (c, d) = render_pinhole(&scene, &self.lf_cam, position, 1).ok()?;
                sparse.push(RgbdView {
                    position,
                    rgbd: Rgbd::new(c, d).ok()?,
                });
            }
        }
        let eyes = match self.half_ipd_m {
            None => None,
            Some(h) => {
                let cast = |x: f32| -> Option<Arc<Rgbd>> {
                    let (c, d) = render_pinhole(&scene, &self.cam, [x, 0.0], 1).ok()?;
                    Some(Arc::new(Rgbd::new(c, d).ok()?))
                };
                Some([cast(-h)?, cast(h)?])
            }
        };
        Some(SceneFrame {
            number,
            scene,
            rgbd,
            sparse,
            eyes,
        })
    }
}

impl Content for DemoFrames {
    fn poll(&self, t: Timestamp) -> Option<ContentFrame> {
        {
            let mut st = lock(&self.state);
            let second = t.as_secs_f64() as u64;
            if second > st.printed_second {
                st.printed_second = second;
                println!(
                    "  {second:>3} / {:.0} s simulated ({:.1} s wall)",
                    self.seconds,
                    self.started.elapsed().as_secs_f64()
                );
            }
            if st
                .current_at
                .is_some_and(|c| t.saturating_since(c) < SCENE_UPDATE)
            {
                return None;
            }
            st.current_at = Some(t);
        }
        let number = lock(&self.state).given + 1;
        let content = Arc::new(self.content_at(t, number)?);
        // `--eyes 2`: each eye's view, cast here (the loop's step, free in simulated time).
        let frame = ContentFrame {
            scene: Some(Arc::new(content.scene.clone())),
            eyes: content.eyes.clone(),
            ..ContentFrame::new(number, content.rgbd.clone())
        };
        let mut st = lock(&self.state);
        st.given = number;
        if st.recent.len() == FRAMES_KEPT {
            st.recent.pop_front();
        }
        st.recent.push_back(content);
        Some(frame)
    }
}

impl Renderer for DemoFrames {
    fn render(&self, job: &RenderJob, frame: &ContentFrame) -> Result<RenderOutput, RenderError> {
        let content = lock(&self.state)
            .recent
            .iter()
            .find(|c| c.number == frame.number)
            .cloned()
            .ok_or_else(|| {
                RenderError::Input(dioptra_core::InputError::InvalidValue(format!(
                    "the demo's scene frame {} is no longer kept",
                    frame.number
                )))
            })?;
        // A stereo layout's eye: its own view (the rig made it); else the scene's.
        let input = match frame.eye {
            Some(_) => &frame.rgbd,
            None => &content.rgbd,
        };
        let started = Instant::now();
        let output = self
            .render_output(job, input, &content.sparse)
            .ok_or_else(|| {
                RenderError::Input(dioptra_core::InputError::InvalidValue(
                    "the demo frame did not render".into(),
                ))
            })?;
        let took = started.elapsed();
        let images = match &output {
            Output::Image(img) => vec![img.clone().into()],
            Output::Layers(l) => l.images.iter().cloned().map(Into::into).collect(),
            Output::LightField { panel, .. } => vec![panel.clone().into()],
        };
        let mut st = lock(&self.state);
        if let Some(eye) = frame.eye {
            st.eye_render[usize::from(eye == Side::Right)].push(took);
        }
        let kept = |output| Kept {
            frame: job.frame,
            eye: frame.eye,
            display_time: job.display_time,
            scene: content.scene.clone(),
            input: input.as_ref().clone(),
            output,
        };
        if frame.eye == Some(Side::Right) {
            if st.keep_right.take() == Some(job.frame) {
                st.kept.push(kept(output));
            }
        } else if let Some(&after) = st.keep_after.first() {
            if job.display_time >= after {
                st.keep_after.remove(0);
                if frame.eye == Some(Side::Left) {
                    st.keep_right = Some(job.frame);
                }
                st.kept.push(kept(output));
            }
        }
        Ok(RenderOutput {
            images,
            planned: None,
            // The render itself: the copies for the sink and the kept frames are the demo's.
            cost: Some(took),
        })
    }
}

/// The rig config's mode for a scheduler mode.
pub fn rig_mode(mode: Mode) -> RigMode {
    RigMode::from_sched(mode)
}

/// Up to four gaze targets on uniform surfaces at different depths.
fn pick_targets(depth: &DepthMap, fov_deg: f32) -> Vec<Target> {
    let window = DepthWindow {
        radius_deg: 1.2,
        ..DepthWindow::default()
    };
    let mut cands: Vec<Target> = Vec::new();
    let step = 1.5;
    let mut yaw = -7.5;
    while yaw <= 7.5 {
        let mut pitch = -7.5;
        while pitch <= 7.5 {
            let a = Angles {
                yaw_deg: yaw,
                pitch_deg: pitch,
            };
            if let Some(w) = window_depth(depth, a.direction(), fov_deg, &window) {
                let s = w.surfaces()[0];
                if s.share > 0.97 && (0.25..=3.5).contains(&s.diopters) {
                    cands.push(Target {
                        yaw_deg: yaw,
                        pitch_deg: pitch,
                        diopters: f64::from(s.diopters),
                    });
                }
            }
            pitch += step;
        }
        yaw += step;
    }
    cands.sort_by(|a, b| a.diopters.total_cmp(&b.diopters));
    let mut picked: Vec<Target> = Vec::new();
    // Spread over depth: nearest, farthest, then the ones most unlike those picked.
    let far_apart = |t: &Target, p: &[Target]| {
        p.iter().all(|q| {
            (t.yaw_deg - q.yaw_deg).hypot(t.pitch_deg - q.pitch_deg) >= 4.0
                && (t.diopters - q.diopters).abs() >= 0.2
        })
    };
    for t in cands.iter().rev().chain(cands.iter()) {
        if picked.len() < 2 && far_apart(t, &picked) {
            picked.push(*t);
        }
    }
    while picked.len() < 4 {
        let best = cands
            .iter()
            .filter(|t| far_apart(t, &picked))
            .max_by(|a, b| {
                let d = |t: &Target| {
                    picked
                        .iter()
                        .map(|q| (t.diopters - q.diopters).abs())
                        .fold(f64::INFINITY, f64::min)
                };
                d(a).total_cmp(&d(b))
            })
            .copied();
        match best {
            Some(t) => picked.push(t),
            None => break,
        }
    }
    if picked.len() < 2 {
        // A scene with no clear surfaces: look straight ahead and at a corner of the wall.
        picked = vec![
            Target {
                yaw_deg: 0.0,
                pitch_deg: 0.0,
                diopters: 1.0,
            },
            Target {
                yaw_deg: 6.0,
                pitch_deg: 5.0,
                diopters: 0.5,
            },
        ];
    }
    picked
}
