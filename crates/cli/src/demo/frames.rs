//! The demo's content: an animated procedural scene (four of its objects sliding, the
//! viewer's gaze targets on still surfaces), its RGB-D frames, each eye's view with `--eyes 2`,
//! and what scoring a kept frame against ground truth needs (what the eye sees of the frame
//! the rig's renderer made, a thin-lens render of the same scene). It is the rig runtime's
//! [`Content`]: the loop polls it for the scene as it is now, at most every 50 ms. Frames are
//! rendered by the rig's own renderer (`super::render`).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use dioptra_core::{lock, DepthMap, Diopters, EyeModel, RgbImage, Rgbd, Side, Timestamp};
use dioptra_render::retina::{retina_lightfield, retina_multifocal, retina_varifocal, LfView};
use dioptra_render::Layers;
use dioptra_rig::config::Mode as RigMode;
use dioptra_rig::content::{Content, ContentFrame};
use dioptra_rig::render::rgbd::{LF_GRID, LF_SPAN_M};
use dioptra_sched::depth::{window_depth, DepthWindow};
use dioptra_sched::processing::Angles;
use dioptra_sched::Mode;
use dioptra_sim::gaze::generator::{Segment, Target};
use dioptra_sim::scene::animation::{centre, Animation};
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, SceneOptions};

/// The scene's RGB-D input is re-rendered at most this often (20 Hz animation): ray casting
/// it is the demo's own cost, not the display pipeline's.
const SCENE_UPDATE: Duration = Duration::from_millis(50);

/// What the rig's renderer made of a kept frame.
pub enum Output {
    Image(RgbImage),
    Layers(Layers),
    /// The lenslet panel, and the views over the pupil it is made from.
    LightField {
        views: Vec<LfView>,
        panel: RgbImage,
    },
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

/// The scene as it is at one instant: its RGB-D, and with `--eyes 2` each eye's.
struct SceneFrame {
    scene: Scene,
    rgbd: Arc<Rgbd>,
    /// `--eyes 2`: each eye's view.
    eyes: Option<[Arc<Rgbd>; 2]>,
}

pub struct DemoFrames {
    mode: Mode,
    base: Scene,
    movers: Animation,
    cam: Camera,
    /// The rig renders light-field views at half size (a panel of 5 px per lenslet cannot
    /// show more): their ground truth is rendered at that size.
    lf_cam: Camera,
    eye: EyeModel,
    planes: Vec<Diopters>,
    targets: Vec<Target>,
    seconds: f64,
    started: Instant,
    /// `--eyes 2`: half the interpupillary distance, metres: each frame's eyes' views are
    /// ray cast with it, off the render path (as the rig's own scene does).
    half_ipd_m: Option<f32>,
    /// What changes as the run goes (the loop polls from its thread).
    state: Mutex<DemoState>,
}

#[derive(Default)]
struct DemoState {
    printed_second: u64,
    current_at: Option<Timestamp>,
    /// Content frames handed to the loop.
    given: u64,
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
        let lf_cam = Camera::square(eye, (size / 2).max(8));
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
            half_ipd_m: None,
            state: Mutex::new(DemoState::default()),
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

    /// When the frames kept for scoring are shown: 30 %, 55 % and 80 % into the run.
    pub fn keep_after(&self) -> Vec<Timestamp> {
        [0.3, 0.55, 0.8]
            .iter()
            .map(|f| Timestamp::ZERO + Duration::from_secs_f64(self.seconds * f))
            .collect()
    }

    /// The rig's multifocal planes, for a kept frame's layers.
    pub fn planes(&self) -> &[Diopters] {
        &self.planes
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
}

impl DemoFrames {
    /// The scene at `t` rendered as the renderer's input.
    fn content_at(&self, t: Timestamp) -> Option<SceneFrame> {
        let scene = self.scene_at(t);
        let (color, depth) = render_pinhole(&scene, &self.cam, [0.0, 0.0], 1).ok()?;
        let rgbd = Arc::new(Rgbd::new(color, depth).ok()?);
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
        Some(SceneFrame { scene, rgbd, eyes })
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
        // `--eyes 2`: each eye's view, cast here (the loop's step, free in simulated time).
        let content = self.content_at(t)?;
        let frame = ContentFrame {
            scene: Some(Arc::new(content.scene)),
            eyes: content.eyes,
            ..ContentFrame::new(number, content.rgbd)
        };
        lock(&self.state).given = number;
        Some(frame)
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
