//! The rig's renderer of RGB-D content (the procedural scene, a lab's files, a stream: each
//! job brings its [`ContentFrame`]), each frame made by the job's method on the rig's backend.
//! A multifocal decomposition (which
//! does not depend on the focus) is made once per method and content frame, and so is the
//! light-field panel: 5 x 5 views over a 4 mm pupil (the scene's own pinhole views, or views
//! synthesised from a file or stream frame's RGB-D), resampled by `dioptra_sched::lenslet`
//! onto a lenslet display of (width / 5) x (height / 5) lenslets of 5 x 5 pixels (0.25 mm
//! pitch, 0.94 mm gap, 15 mm eye relief).
//!
//! With `method = "auto"` (varifocal mode) each frame's method is chosen here, where frames
//! are rendered, by `dioptra_render::planner` from the frame's depth around the gaze point
//! and the focus: no blur, gather, or the light-field method with as few views as the
//! disparity needs. The scheduler (sans-IO) chooses the focus, not the method.
//!
//! `method = "network"` renders with the DeepFocus-family network: C1 (defocus at the frame's
//! focus) in varifocal mode, C4 (layers for the rig's planes) in multifocal mode, from
//! `render.weights` (default the shipped weights), on the GPU when the rig renders there (the
//! same weights uploaded once to the render's device) and on the CPU otherwise. Every method
//! (optimized blending included) runs on the rig's backend; on the GPU each frame's GPU time
//! comes from timestamp queries where the adapter has them (`/status` → `render`). Both are loaded at start; the
//! configured mode's must load (else the daemon does not start, naming the file), the other's
//! absence only refuses a switch to it.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use dioptra_core::{lock, Diopters, EyeModel, InputError, RgbImage, Rgbd, Side};
use dioptra_render::backend::Backend;
use dioptra_render::defocus::PyramidParams;
use dioptra_render::foveated::Foveation;
use dioptra_render::gpu::{GpuRgbd, PanelSampling};
use dioptra_render::hybrid::{HybridParams, HybridReport};
use dioptra_render::lightfield::LightFieldParams;
use dioptra_render::multifocal::default_focal_samples;
use dioptra_render::planner::{
    self, Deadline, FoveationSettings, FrameStats, FrameWide, Planner, Target, TimedPlan,
};
use dioptra_render::retina::LfView;
use dioptra_render::views::RgbdView;
use dioptra_render::{Cpu, DefocusMethod, Gpu, OptimizeParams, RenderError, SpectralParams};
use dioptra_sched::lenslet::{elemental_images, sampling, GridGeometry, LensletDisplay, ViewGrid};

use super::config::{Render, RenderBackend};
use super::job::{EyesOnDevice, FrameImage, Planned, RenderJob, RenderOutput, Renderer};
use crate::content::frame::{ContentFrame, ContentView};
use crate::display::config::Display;
use crate::mode::{Method, Mode};
use crate::optics::config::{Eye, Optics};
use dioptra_sched::RenderMethod;

/// Renders frames of RGB-D content (the procedural scene, a lab's files, a stream) by the
/// job's method on the rig's backend.
pub struct RgbdRenderer {
    eye: EyeModel,
    planes: Vec<Diopters>,
    /// The display's size: a light-field panel's lenslets cover it.
    size: (usize, usize),
    /// The newest content frame rendered: what the caches below may hold.
    newest: AtomicU64,
    /// Multifocal layers per method, content frame and eye.
    layers: Mutex<Vec<CachedLayers>>,
    /// `render.hybrid`: the hybrid decomposition's settings (`method = "hybrid"`).
    hybrid: HybridParams,
    /// `render.spectral`: the spectral decomposition's settings (`method = "spectral"`).
    spectral: SpectralParams,
    /// The light-field panels, each made from the content frame numbered with it, for the eye
    /// with it (`None`: the one view of a mono layout).
    panel: Mutex<Vec<CachedPanel>>,
    /// Each eye's view of the content frame numbered with them, synthesised on the GPU and
    /// kept there (left, right): a stereo layout's eyes from one RGB-D.
    eye_views: Mutex<Option<(u64, Arc<[GpuRgbd; 2]>)>>,
    /// Content frames' RGB-D (per content frame and eye) uploaded to the GPU, while the rig
    /// renders there: each uploaded once however many frames show it.
    resident: Mutex<Vec<(FrameKey, GpuRgbd)>>,
    /// The planner's whole-frame statistics of content frames' RGB-D (per content frame and
    /// eye, with the RGB-D they are of): computed once however many renders plan on it.
    frame_wide: Mutex<Vec<KeptFrameWide>>,
    /// Half the interpupillary distance, metres: where each eye's light field is centred.
    half_ipd_m: f32,
    /// `render.foveation`: the pyramid method's (fixed or the planner's) around each eye's
    /// gaze; `None`: off.
    foveation: Option<FoveationSettings>,
    /// The time one eye's varifocal render may take, for the planner (`method = "auto"`): the
    /// display period less a margin, shared by the eyes.
    deadline: Deadline,
    /// Where gather, light-field defocus and linear blending run ([`RenderBackend`]).
    compute: Mutex<Compute>,
    /// The net of each mode and method (`network`: C1, C4; `refine`: C1R, C4R), or why it
    /// did not load.
    nets: CpuNets,
}

/// A light-field panel: its content frame's number, its eye, the method that made it (views
/// or refine), the panel.
type CachedPanel = (u64, Option<Side>, RenderMethod, FrameImage);

/// A content frame's number and the eye it is rendered for.
type FrameKey = (u64, Option<Side>);

/// The planner's whole-frame statistics of the RGB-D of a content frame and eye.
type KeptFrameWide = (FrameKey, Arc<Rgbd>, Arc<FrameWide>);

/// Multifocal layers one method made from the content frame numbered `frame`, for `eye`.
struct CachedLayers {
    frame: u64,
    eye: Option<Side>,
    method: Method,
    /// The eye's gaze (pixels) they were made around: the hybrid's depend on it.
    gaze: [f32; 2],
    images: Arc<Vec<FrameImage>>,
}

/// The light field shown in light-field mode: views per side and the pupil span they cover.
pub const LF_GRID: usize = 5;
pub const LF_SPAN_M: f32 = 0.004;

impl std::fmt::Debug for RgbdRenderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RgbdRenderer")
            .field("width", &self.size.0)
            .field("height", &self.size.1)
            .finish_non_exhaustive()
    }
}

impl RgbdRenderer {
    /// The renderer of `[render]` for `[eye]` over the display's pixels, making
    /// `optics.planes`' layers: its backend opened and its nets loaded (the rig checks that
    /// the configured mode's loaded).
    pub fn new(
        render: &Render,
        eye: &Eye,
        display: &Display,
        optics: &Optics,
    ) -> Result<RgbdRenderer, RenderError> {
        let d = display;
        let model = eye.model(d.width).validated()?;
        let nets = NET_CONFIGS
            .iter()
            .map(|&(mode, method, config)| {
                ((mode, method), load_net(render, &optics.planes, config))
            })
            .collect();
        let compute = Compute::open(render, &nets)?;
        Ok(RgbdRenderer {
            compute: Mutex::new(compute),
            eye: model,
            planes: optics.planes.iter().copied().map(Diopters).collect(),
            size: (d.width as usize, d.height as usize),
            newest: AtomicU64::new(0),
            layers: Mutex::new(Vec::new()),
            hybrid: render.hybrid.params(),
            spectral: render.spectral.params(),
            panel: Mutex::new(Vec::new()),
            eye_views: Mutex::new(None),
            resident: Mutex::new(Vec::new()),
            frame_wide: Mutex::new(Vec::new()),
            half_ipd_m: eye.ipd_mm * 0.5e-3,
            foveation: render.foveation.settings(),
            deadline: eye_deadline(display),
            nets,
        })
    }

    /// One defocused image on the rig's backend; a GPU failure moves the rig to the CPU
    /// (said in the log and `/status`) and the frame is rendered there.
    fn defocus(
        &self,
        input: &Rgbd,
        focus: Diopters,
        method: DefocusMethod,
    ) -> Result<FrameImage, RenderError> {
        self.on_backend(&defocus_label(method), |gpu| match gpu {
            Some(g) => Ok(FrameImage::Gpu(
                g.defocus_on_gpu(input, focus, &self.eye, method)?,
            )),
            None => Cpu
                .defocus(input, &[focus], &self.eye, method, &|_| {})?
                .pop()
                .map(FrameImage::Host)
                .ok_or_else(|| {
                    RenderError::Input(InputError::InvalidValue("no image rendered".into()))
                }),
        })
    }

    fn linear(&self, input: &Rgbd) -> Result<Vec<FrameImage>, RenderError> {
        self.on_backend("linear", |gpu| match gpu {
            Some(g) => Ok(on_gpu(g.linear_blend_on_gpu(input, &self.planes)?)),
            None => Ok(on_host(Cpu.linear_blend(input, &self.planes)?.images)),
        })
    }

    /// Runs `work` on the rig's GPU (`Some`) or the CPU (`None`), timing it on the GPU
    /// (`label` in `/status`); a GPU failure moves the rig to the CPU (said in the log and
    /// `/status`) and reruns it there.
    fn on_backend<T>(
        &self,
        label: &str,
        work: impl Fn(Option<&Gpu>) -> Result<T, RenderError>,
    ) -> Result<T, RenderError> {
        let gpu = lock(&self.compute).gpu.clone();
        match work(gpu.as_deref()) {
            Err(RenderError::Gpu(e)) => {
                lock(&self.compute).fall_back(&e);
                let v = work(None)?;
                lock(&self.compute).ran(label, "cpu");
                Ok(v)
            }
            Ok(v) => {
                match gpu {
                    Some(g) => self.ran_on_gpu(&g, label),
                    None => lock(&self.compute).ran(label, "cpu"),
                }
                Ok(v)
            }
            Err(e) => Err(e),
        }
    }

    /// `job` for both eyes from views synthesised from `content`'s one RGB-D on `gpu` (the
    /// eyes at `positions`), every stage in GPU memory: the views made once per content frame,
    /// each eye rendered from its own.
    fn eyes_from_gpu(
        &self,
        gpu: &Gpu,
        job: &RenderJob,
        content: &ContentFrame,
        positions: [[f32; 2]; 2],
    ) -> Result<EyesOnDevice, RenderError> {
        self.take_up(content);
        let kept = lock(&self.eye_views)
            .as_ref()
            .filter(|(n, _)| *n == content.number)
            .map(|(_, v)| v.clone());
        let made = kept.is_none();
        let views = match kept {
            Some(v) => v,
            None => {
                let input = [RgbdView {
                    position: [0.0, 0.0],
                    rgbd: content.rgbd.as_ref().clone(),
                }];
                let made = gpu.synthesize_rgbd_views_on_gpu(&input, &positions, &self.eye)?;
                self.ran_on_gpu(gpu, "eye views");
                let [l, r]: [GpuRgbd; 2] = made.try_into().map_err(|_| {
                    dioptra_render::GpuError::Validation("not one view per eye".into())
                })?;
                let v = Arc::new([l, r]);
                let mut kept = lock(&self.eye_views);
                if kept.as_ref().is_none_or(|(n, _)| *n <= content.number) {
                    *kept = Some((content.number, v.clone()));
                }
                v
            }
        };
        let [left_view, right_view] = views.as_ref();
        let mut ask = Ask::of(job);
        let left_frame = content.for_eye(Side::Left, content.rgbd.clone());
        let left = self.render_view(gpu, &ask, &left_frame, left_view, true)?;
        ask.focus = job.focus_right.unwrap_or(job.focus);
        let right_frame = content.for_eye(Side::Right, content.rgbd.clone());
        let right = self.render_view(gpu, &ask, &right_frame, right_view, true)?;
        Ok(EyesOnDevice {
            outputs: [left, right],
            made,
        })
    }

    /// `ask` of `frame` (its eye's) rendered on `gpu` from its RGB-D `view` there. With
    /// `auto`, the planner judges the fixated region on the frame's host RGB-D: for a view
    /// `synthesised` from it, at the cyclopean gaze (the eye's view is it shifted by the
    /// disparity); a foveated render is centred on the eye's own gaze.
    fn render_view(
        &self,
        gpu: &Gpu,
        ask: &Ask,
        frame: &ContentFrame,
        view: &GpuRgbd,
        synthesised: bool,
    ) -> Result<RenderOutput, RenderError> {
        let (input, focus) = (frame.rgbd.as_ref(), ask.focus);
        let gaze = self.eye_gaze(input, ask.gaze, frame.eye, focus);
        if ask.auto && ask.mode == Mode::Varifocal {
            let plan_eye = if synthesised { None } else { frame.eye };
            let plan = self.plan(
                frame,
                self.eye_gaze(input, ask.gaze, plan_eye, focus),
                focus,
            );
            let image = match plan.setting.method() {
                None => FrameImage::Gpu(view.color()),
                Some(m) => self.defocus_view(gpu, view, focus, foveated_at(m, gaze))?,
            };
            return Ok(RenderOutput {
                images: vec![image],
                planned: Some(self.planned(&plan)),
                cost: None,
            });
        }
        let images = match (ask.mode, ask.method.0) {
            (Mode::Multifocal, _) => self
                .cached_layers(frame, ask.method, gaze, || {
                    let layers = gpu.linear_blend_on_gpu(view, &self.planes)?;
                    self.ran_on_gpu(gpu, "linear");
                    Ok((on_gpu(layers), method_note(ask.method)))
                })?
                .as_ref()
                .clone(),
            (_, method) => {
                let m = self.fixed_defocus(method, gaze);
                vec![self.defocus_view(gpu, view, focus, m)?]
            }
        };
        Ok(RenderOutput {
            images,
            planned: None,
            cost: None,
        })
    }

    /// `ask` of `content` on the GPU from its RGB-D uploaded there once per content frame and
    /// eye, where the rig renders there and the method renders from GPU memory
    /// ([`from_device`]); `None`: render it on the host's copy (a GPU failure moves the rig to
    /// the CPU).
    fn frame_on_gpu(
        &self,
        ask: &Ask,
        content: &ContentFrame,
    ) -> Result<Option<RenderOutput>, RenderError> {
        if !from_device(ask) {
            return Ok(None);
        }
        let Some(gpu) = lock(&self.compute).gpu.clone() else {
            return Ok(None);
        };
        let rendered = self
            .resident(&gpu, content)
            .and_then(|view| self.render_view(&gpu, ask, content, &view, false));
        match rendered {
            Err(RenderError::Gpu(e)) => {
                lock(&self.compute).fall_back(&e);
                Ok(None)
            }
            r => r.map(Some),
        }
    }

    /// `content`'s RGB-D in `gpu`'s memory: uploaded once per content frame and eye.
    fn resident(&self, gpu: &Gpu, content: &ContentFrame) -> Result<GpuRgbd, RenderError> {
        let key = (content.number, content.eye);
        if let Some((_, v)) = lock(&self.resident).iter().find(|(k, _)| *k == key) {
            return Ok(v.clone());
        }
        let view = gpu.upload_rgbd(&content.rgbd)?;
        lock(&self.compute).ran("content upload", "host to gpu");
        if self.keeps(content) {
            lock(&self.resident).push((key, view.clone()));
        }
        Ok(view)
    }

    fn defocus_view(
        &self,
        gpu: &Gpu,
        view: &GpuRgbd,
        focus: Diopters,
        method: DefocusMethod,
    ) -> Result<FrameImage, RenderError> {
        let image = gpu.defocus_on_gpu(view, focus, &self.eye, method)?;
        self.ran_on_gpu(gpu, &defocus_label(method));
        Ok(FrameImage::Gpu(image))
    }

    /// `label` ran on `gpu`: its GPU time and its backend noted for `/status`.
    fn ran_on_gpu(&self, gpu: &Gpu, label: &str) {
        let mut c = lock(&self.compute);
        c.timed(label, gpu.last_stats().gpu_ns);
        c.ran(label, "gpu");
    }

    /// The GPU context frames are rendered on and left in, while the rig renders on the GPU
    /// (a window on its device shows them without a copy).
    pub fn gpu_context(&self) -> Option<Arc<dioptra_render::gpu::GpuContext>> {
        lock(&self.compute)
            .gpu
            .as_ref()
            .map(|g| g.context().clone())
    }

    /// C1 (varifocal) on the GPU when the rig renders there, else on the CPU.
    fn net_defocus(
        &self,
        mode: Mode,
        input: &Rgbd,
        focus: Diopters,
    ) -> Result<RgbImage, RenderError> {
        let key = (mode, RenderMethod::Network);
        if let Some(img) = self.on_gpu_net(key, |g| g.defocus(input, focus, &self.eye))? {
            return Ok(img);
        }
        self.net(key)?
            .defocus(input, focus, &self.eye)
            .map_err(net_error)
    }

    /// C1R (varifocal): its classical render on the rig's backend, refined by the net on the
    /// GPU when the rig renders there, else on the CPU.
    fn refine_defocus(&self, input: &Rgbd, focus: Diopters) -> Result<RgbImage, RenderError> {
        let key = (Mode::Varifocal, RenderMethod::Refine);
        let cpu = self.net(key)?;
        let dioptra_net::Task::C1r { classical } = cpu.arch().task else {
            return Err(net_error(dioptra_net::NetError::WrongConfig {
                expected: "c1r".into(),
                asked: cpu.arch().task.name().into(),
            }));
        };
        let base = self.on_backend("refine (classical)", |gpu| {
            dioptra_net::refine::classical_defocus(
                backend_of(gpu),
                classical,
                input,
                focus,
                &self.eye,
            )
            .map_err(net_error)
        })?;
        let refined = self.on_gpu_net(key, |g| g.refine_defocus(input, &base, focus, &self.eye))?;
        let r = match refined {
            Some(r) => r,
            None => cpu
                .refine_defocus(input, &base, focus, &self.eye)
                .map_err(net_error)?,
        };
        lock(&self.compute).refine_tiles = Some(r.tiles.fraction());
        Ok(r.image)
    }

    /// C5R (light field): each panel view synthesised from `inputs` on the CPU with the warp's
    /// error map, refined on the tiles it marks by the net on the GPU when the rig renders
    /// there, else on the CPU.
    fn refine_light_field(&self, inputs: &[RgbdView]) -> Result<Vec<LfView>, RenderError> {
        let key = (Mode::Lightfield, RenderMethod::Refine);
        let cpu = self.net(key)?;
        let gpu = lock(&self.compute).gpu_net(key);
        let tiles = std::sync::Mutex::new((0usize, 0usize));
        let views = dioptra_net::refine::refine_light_field(
            inputs,
            LF_GRID,
            LF_SPAN_M,
            &self.eye,
            &|view, errors| {
                let t = dioptra_net::refine::view_tiles(errors)?;
                let mut n = lock(&tiles);
                n.0 += t.on.iter().filter(|&&o| o).count();
                n.1 += t.on.len();
                drop(n);
                match &gpu {
                    Some(g) => g.refine_view(view, errors),
                    None => cpu.refine_view(view, errors),
                }
            },
            &|_| {},
        )
        .map_err(net_error)?;
        let (on, all) = *lock(&tiles);
        lock(&self.compute).refine_tiles = Some(on as f64 / all.max(1) as f64);
        Ok(views)
    }

    /// C4R (multifocal): the classical decomposition its weights name (linear blending or
    /// spectral) on the rig's backend, refined by the net on the GPU when the rig renders
    /// there, else on the CPU.
    fn refine_decompose(&self, input: &Rgbd) -> Result<Vec<RgbImage>, RenderError> {
        let key = (Mode::Multifocal, RenderMethod::Refine);
        let cpu = self.net(key)?;
        let (_, classical) = dioptra_net::refine::c4r_input(&cpu.arch().task).map_err(net_error)?;
        let base = self.on_backend("refine (classical)", |gpu| {
            dioptra_net::refine::classical_layers(
                backend_of(gpu),
                classical,
                input,
                &self.planes,
                &self.eye,
            )
            .map_err(net_error)
        })?;
        if let Some(l) = self.on_gpu_net(key, |g| g.refine_decompose(input, &base))? {
            return Ok(l.images);
        }
        Ok(cpu
            .refine_decompose(input, &base)
            .map_err(net_error)?
            .images)
    }

    /// `run` on the GPU copy of the net `key` when the rig renders there (its GPU time shown
    /// under the method's name): `None` when there is none, or when the GPU failed and the
    /// rig fell back to the CPU, for the caller to run the CPU net.
    fn on_gpu_net<T>(
        &self,
        key: NetKey,
        run: impl FnOnce(&dioptra_net::gpu::GpuNet) -> Result<T, dioptra_net::NetError>,
    ) -> Result<Option<T>, RenderError> {
        let Some(g) = lock(&self.compute).gpu_net(key) else {
            return Ok(None);
        };
        match run(&g) {
            Ok(out) => {
                lock(&self.compute).timed(key.1.as_str(), g.last_stats().gpu_ns);
                Ok(Some(out))
            }
            Err(dioptra_net::NetError::Render(RenderError::Gpu(e))) => {
                lock(&self.compute).fall_back(&e);
                Ok(None)
            }
            Err(e) => Err(net_error(e)),
        }
    }

    /// C4 (multifocal layers) on the GPU when the rig renders there, else on the CPU.
    fn net_decompose(&self, input: &Rgbd) -> Result<Vec<RgbImage>, RenderError> {
        let key = (Mode::Multifocal, RenderMethod::Network);
        if let Some(l) = self.on_gpu_net(key, |g| g.decompose(input))? {
            return Ok(l.images);
        }
        Ok(self
            .net((Mode::Multifocal, RenderMethod::Network))?
            .decompose(input)
            .map_err(net_error)?
            .images)
    }

    /// Where frames are rendered, for `/status`.
    pub fn backend_status(&self) -> serde_json::Value {
        lock(&self.compute).status()
    }

    fn net(&self, key: NetKey) -> Result<&dioptra_net::CpuNet, RenderError> {
        match self.nets.iter().find(|(k, _)| *k == key) {
            Some((_, Ok(n))) => Ok(n),
            Some((_, Err(why))) => Err(RenderError::Input(InputError::InvalidValue(why.clone()))),
            None => Err(RenderError::Unsupported {
                backend: "daemon CPU",
                method: "network or refine (lightfield)",
            }),
        }
    }

    /// The planner's setting for a varifocal frame: the cheapest predicted to meet the
    /// accuracy target in the fovea (the rig's foveation radius, else the planner's) within
    /// the frame's time budget, the rig's foveation offered around `gaze`.
    fn plan(&self, frame: &ContentFrame, gaze: [f32; 2], focus: Diopters) -> TimedPlan {
        let fovea_deg = self
            .foveation
            .map_or(planner::FOVEA_RADIUS_DEG, |f| f.radius_deg);
        let stats = FrameStats::around(
            &self.frame_wide(frame),
            &frame.rgbd,
            gaze,
            fovea_deg,
            focus,
            &self.eye,
        );
        Planner.plan_within(&stats, &Target::default(), &self.deadline, self.foveation)
    }

    /// The planner's whole-frame statistics of `frame`'s RGB-D: computed on its first plan,
    /// then kept while it is the newest content frame.
    fn frame_wide(&self, frame: &ContentFrame) -> Arc<FrameWide> {
        let key = (frame.number, frame.eye);
        let kept = lock(&self.frame_wide)
            .iter()
            .find(|(k, rgbd, _)| *k == key && Arc::ptr_eq(rgbd, &frame.rgbd))
            .map(|(_, _, wide)| wide.clone());
        if let Some(wide) = kept {
            return wide;
        }
        let wide = Arc::new(FrameWide::of(&frame.rgbd));
        if self.keeps(frame) {
            lock(&self.frame_wide).push((key, frame.rgbd.clone(), wide.clone()));
        }
        wide
    }

    /// Where `eye`'s gaze falls on its image (pixels), from the gaze on the one image (the
    /// cyclopean eye's; the image's centre when unknown): the fixation point, at the focus's
    /// distance along that ray, seen from the eye's own position (half the interpupillary
    /// distance to its side; the eyes' cameras are parallel). Clamped to the image.
    fn eye_gaze(
        &self,
        input: &Rgbd,
        gaze: Option<[f32; 2]>,
        eye: Option<Side>,
        focus: Diopters,
    ) -> [f32; 2] {
        let (w, h) = (input.width() as f32, input.height() as f32);
        let [x, y] = gaze.unwrap_or([0.5 * w, 0.5 * h]);
        // The image may be smaller than the display (content at a reduced size).
        let pitch_tan = self.eye.with_width(input.width() as u32).pixel_pitch_tan();
        let shift_px = self.half_ipd_m * focus.0.max(0.0) / pitch_tan;
        let x = match eye {
            Some(Side::Left) => x + shift_px,
            Some(Side::Right) => x - shift_px,
            None => x,
        };
        [x.clamp(0.0, w), y.clamp(0.0, h)]
    }

    /// Notes `content` as the newest frame rendered: what was made from older frames is
    /// dropped.
    fn take_up(&self, content: &ContentFrame) {
        let n = content.number;
        if self.newest.fetch_max(n, Ordering::AcqRel) < n {
            lock(&self.layers).retain(|l| l.frame >= n);
            lock(&self.panel).retain(|(k, _, _, _)| *k >= n);
            lock(&self.resident).retain(|((k, _), _)| *k >= n);
            lock(&self.frame_wide).retain(|((k, _), _, _)| *k >= n);
        }
    }

    /// Whether what is made from `content` may be kept: no newer frame was rendered since.
    fn keeps(&self, content: &ContentFrame) -> bool {
        self.newest.load(Ordering::Acquire) == content.number
    }

    /// The images of one frame: one for varifocal and light field, one per plane for
    /// multifocal. `gaze` is the gaze point in pixels (the image centre when unknown); with
    /// `auto` (`method = "auto"`) the planner chooses a varifocal frame's method from it. CPU
    /// work: call it from a blocking thread.
    pub fn render_frame(
        &self,
        content: &ContentFrame,
        mode: Mode,
        method: Method,
        focus: Diopters,
        gaze: Option<[f32; 2]>,
        auto: bool,
    ) -> Result<RenderOutput, RenderError> {
        self.take_up(content);
        let ask = Ask {
            mode,
            method,
            focus,
            gaze,
            auto,
        };
        if let Some(out) = self.frame_on_gpu(&ask, content)? {
            return Ok(out);
        }
        let input = content.rgbd.as_ref();
        let gaze = self.eye_gaze(input, gaze, content.eye, focus);
        if auto && mode == Mode::Varifocal {
            let plan = self.plan(content, gaze, focus);
            let image = match plan.setting.method() {
                None => FrameImage::Host(input.color.clone()),
                Some(m) => self.defocus(input, focus, m)?,
            };
            return Ok(RenderOutput {
                images: vec![image],
                planned: Some(self.planned(&plan)),
                cost: None,
            });
        }
        Ok(RenderOutput {
            images: self.render_fixed(content, mode, method, focus, gaze)?,
            planned: None,
            cost: None,
        })
    }

    /// What `/status` says of the planner's `plan`.
    fn planned(&self, plan: &TimedPlan) -> Planned {
        Planned {
            choice: plan.setting.to_string(),
            predicted_psnr_db: plan.predicted_psnr,
            predicted_ms: plan.predicted_ms,
            budget_ms: self.deadline.budget_ms,
            why: plan.why.clone(),
        }
    }

    /// The defocus of a varifocal frame with the fixed `method` (gather for any other than
    /// the pyramid and the light field's), a foveated pyramid around `gaze`.
    fn fixed_defocus(&self, method: RenderMethod, gaze: [f32; 2]) -> DefocusMethod {
        match method {
            RenderMethod::LightFieldDefocus => DefocusMethod::LightField(LightFieldParams {
                views: 16,
                mip: true,
            }),
            RenderMethod::Pyramid => DefocusMethod::Pyramid(PyramidParams {
                foveation: self.foveation.map(|f| Foveation {
                    gaze,
                    radius_deg: f.radius_deg,
                    mar_slope: f.mar_slope,
                }),
            }),
            _ => DefocusMethod::Gather,
        }
    }

    fn render_fixed(
        &self,
        content: &ContentFrame,
        mode: Mode,
        method: Method,
        focus: Diopters,
        gaze: [f32; 2],
    ) -> Result<Vec<FrameImage>, RenderError> {
        let input = content.rgbd.as_ref();
        match (mode, method.0) {
            (_, RenderMethod::Views) | (Mode::Lightfield, RenderMethod::Refine) => {
                Ok(vec![self.panel(content, method.0)?])
            }
            (Mode::Multifocal, _) => Ok(self.layers(content, method, gaze)?.as_ref().clone()),
            (_, RenderMethod::Network) => Ok(vec![self.net_defocus(mode, input, focus)?.into()]),
            (_, RenderMethod::Refine) => Ok(vec![self.refine_defocus(input, focus)?.into()]),
            (_, m) => Ok(vec![self.defocus(
                input,
                focus,
                self.fixed_defocus(m, gaze),
            )?]),
        }
    }

    /// The input views for `eye`'s light field from a frame's view grids: the eye's own grid
    /// where it has one, else the one grid, its positions taken from the eye's centre.
    fn eye_inputs(&self, views: &[ContentView], eye: Option<Side>) -> Vec<RgbdView> {
        let own = eye.is_some() && views.iter().any(|v| v.eye == eye);
        let centre = match (own, eye) {
            (false, Some(Side::Left)) => -self.half_ipd_m,
            (false, Some(Side::Right)) => self.half_ipd_m,
            _ => 0.0,
        };
        views
            .iter()
            .filter(|v| if own { v.eye == eye } else { v.eye.is_none() })
            .map(|v| RgbdView {
                position: [v.position[0] - centre, v.position[1]],
                rgbd: v.rgbd.as_ref().clone(),
            })
            .collect()
    }

    /// The lenslet panel image of the light field of the content frame `shown`: the
    /// procedural scene's own views, or views synthesised from a file or stream frame's RGB-D.
    /// With `Refine`, file and stream content's views are the classical ones refined by C5R
    /// (the procedural scene's own views need no synthesis). Views synthesised by the classical
    /// method on the GPU are resampled there, the panel left in GPU memory.
    fn panel(
        &self,
        content: &ContentFrame,
        method: RenderMethod,
    ) -> Result<FrameImage, RenderError> {
        if let Some((_, _, _, p)) = lock(&self.panel)
            .iter()
            .find(|(n, e, m, _)| *n == content.number && *e == content.eye && *m == method)
        {
            return Ok(p.clone());
        }
        let panel = if method == RenderMethod::Views && content.scene.is_none() {
            let input = self.light_field_inputs(content);
            self.on_backend("light-field panel", |gpu| match gpu {
                Some(g) => {
                    let view_size = input
                        .first()
                        .map_or((0, 0), |v| (v.rgbd.width(), v.rgbd.height()));
                    let sampling = self.panel_sampling(view_size, self.eye.pixel_pitch_tan())?;
                    Ok(FrameImage::Gpu(g.lenslet_panel_on_gpu(
                        &input, LF_GRID, LF_SPAN_M, &self.eye, &sampling,
                    )?))
                }
                None => {
                    let views =
                        Cpu.synthesize_light_field(&input, LF_GRID, LF_SPAN_M, &self.eye, &|_| {})?;
                    let images: Vec<RgbImage> = views.into_iter().map(|v| v.image).collect();
                    Ok(lenslet_panel(&images, self.eye.pixel_pitch_tan(), self.size)?.into())
                }
            })?
        } else {
            // Views on the host (the scene's ray cast, or refined by the net): resampled on
            // the rig's backend.
            let (views, pixel_pitch_tan) = self.views(content, method)?;
            let images: Vec<RgbImage> = views.into_iter().map(|v| v.image).collect();
            self.on_backend("lenslet panel", |gpu| match gpu {
                Some(g) => {
                    let view_size = images.first().map_or((0, 0), |v| (v.width(), v.height()));
                    let sampling = self.panel_sampling(view_size, pixel_pitch_tan)?;
                    Ok(FrameImage::Gpu(g.lenslet_panel_of_views_on_gpu(
                        &images, LF_GRID, &sampling,
                    )?))
                }
                None => Ok(lenslet_panel(&images, pixel_pitch_tan, self.size)?.into()),
            })?
        };
        // Kept unless the content moved on while it was made.
        if self.keeps(content) {
            lock(&self.panel).push((content.number, content.eye, method, panel.clone()));
        }
        Ok(panel)
    }

    /// The `LF_GRID` x `LF_GRID` views over the pupil (`LF_SPAN_M`) that the light-field panel
    /// of `content` is made from by `method`, each at its position on the pupil: what the eye
    /// sees through the panel is these, refocused (`dioptra_render::retina::retina_lightfield`).
    /// Made anew (the panel, not the views, is cached): for scoring a frame, not per frame.
    pub fn light_field_views(
        &self,
        content: &ContentFrame,
        method: RenderMethod,
    ) -> Result<Vec<LfView>, RenderError> {
        Ok(self.views(content, method)?.0)
    }

    /// How the lenslet panel over the display samples a light field of views `view_size`
    /// pixels of `pixel_pitch_tan` (dioptra-sched's, for the GPU's resampling).
    fn panel_sampling(
        &self,
        view_size: (usize, usize),
        pixel_pitch_tan: f32,
    ) -> Result<PanelSampling, RenderError> {
        let geometry = GridGeometry {
            grid: LF_GRID,
            spacing_m: LF_SPAN_M / (LF_GRID - 1) as f32,
            pixel_pitch_tan,
            view_size,
        };
        let s = sampling(&geometry, &lenslet_display(self.size))?;
        Ok(PanelSampling {
            cols: s.cols,
            rows: s.rows,
        })
    }

    /// What a file or stream frame's light field is synthesised from: its views (a view
    /// grid), or the frame as the view from the pupil's centre.
    fn light_field_inputs(&self, content: &ContentFrame) -> Vec<RgbdView> {
        match &content.views {
            Some(views) => self.eye_inputs(views, content.eye),
            None => vec![RgbdView {
                position: [0.0, 0.0],
                rgbd: content.rgbd.as_ref().clone(),
            }],
        }
    }

    /// The light field's views and their pixel pitch (tangent).
    fn views(
        &self,
        content: &ContentFrame,
        method: RenderMethod,
    ) -> Result<(Vec<LfView>, f32), RenderError> {
        let (w, h) = self.size;
        Ok(match &content.scene {
            Some(scene) => {
                // Views at half size: a panel of 5 px per lenslet cannot show more.
                let vcam =
                    dioptra_sim::scene::Camera::new(self.eye, (w / 2).max(8), (h / 2).max(8));
                // Centred on the eye's own position (IPD / 2 from the scene's centre).
                let centre = match content.eye {
                    Some(Side::Left) => -self.half_ipd_m,
                    Some(Side::Right) => self.half_ipd_m,
                    None => 0.0,
                };
                let views = dioptra_sim::scene::light_field_positions(LF_GRID, LF_SPAN_M)?
                    .into_iter()
                    .map(|[x, y]| {
                        dioptra_sim::scene::render_pinhole(scene, &vcam, [x + centre, y], 1).map(
                            |(image, _)| LfView {
                                position: [x, y],
                                image,
                            },
                        )
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                lock(&self.compute).ran("views (scene ray cast)", "cpu");
                (views, vcam.eye.pixel_pitch_tan())
            }
            None => {
                let input = self.light_field_inputs(content);
                let views = if method == RenderMethod::Refine {
                    self.refine_light_field(&input)?
                } else {
                    self.on_backend("views", |gpu| {
                        backend_of(gpu).synthesize_light_field(
                            &input,
                            LF_GRID,
                            LF_SPAN_M,
                            &self.eye,
                            &|_| {},
                        )
                    })?
                };
                (views, self.eye.pixel_pitch_tan())
            }
        })
    }

    /// The layers `method` made of `content` (its eye's), kept or made by `make` (with a note
    /// of what ran for `/status`); the hybrid's are made again when the eye's `gaze` moved
    /// further than its cross-fade's width.
    fn cached_layers(
        &self,
        content: &ContentFrame,
        method: Method,
        gaze: [f32; 2],
        make: impl FnOnce() -> Result<(Vec<FrameImage>, serde_json::Value), RenderError>,
    ) -> Result<Arc<Vec<FrameImage>>, RenderError> {
        let input = content.rgbd.as_ref();
        let gaze_moved = |at: [f32; 2]| -> bool {
            if method.0 != RenderMethod::Hybrid {
                return false;
            }
            let px = self.hybrid.blend_deg * self.px_per_deg(input.width());
            (at[0] - gaze[0]).hypot(at[1] - gaze[1]) > px
        };
        if let Some(l) = lock(&self.layers).iter().find(|l| {
            l.frame == content.number
                && l.eye == content.eye
                && l.method == method
                && !gaze_moved(l.gaze)
        }) {
            return Ok(l.images.clone());
        }
        let (images, note) = make()?;
        let images = Arc::new(images);
        lock(&self.compute).decomposed(content.eye, note);
        if self.keeps(content) {
            let mut cache = lock(&self.layers);
            cache.retain(|l| {
                !(l.frame == content.number && l.eye == content.eye && l.method == method)
            });
            cache.push(CachedLayers {
                frame: content.number,
                eye: content.eye,
                method,
                gaze,
                images: images.clone(),
            });
        }
        Ok(images)
    }

    /// The layers of `content` for its eye by `method`, made once per content frame (the
    /// hybrid's around the eye's `gaze`).
    fn layers(
        &self,
        content: &ContentFrame,
        method: Method,
        gaze: [f32; 2],
    ) -> Result<Arc<Vec<FrameImage>>, RenderError> {
        self.cached_layers(content, method, gaze, || {
            self.make_layers(content, method, gaze)
        })
    }

    fn make_layers(
        &self,
        content: &ContentFrame,
        method: Method,
        gaze: [f32; 2],
    ) -> Result<(Vec<FrameImage>, serde_json::Value), RenderError> {
        let input = content.rgbd.as_ref();
        let mut note = method_note(method);
        let images = if method.0 == RenderMethod::Hybrid {
            let (layers, report) = self.on_backend("hybrid", |gpu| {
                backend_of(gpu).hybrid_blend(
                    input,
                    &self.planes,
                    &self.eye,
                    Some(gaze),
                    &self.hybrid,
                )
            })?;
            note = hybrid_note(&report);
            on_host(layers.images)
        } else if method.0 == RenderMethod::Network {
            on_host(self.net_decompose(input)?)
        } else if method.0 == RenderMethod::Refine {
            on_host(self.refine_decompose(input)?)
        } else if method.0 == RenderMethod::Spectral {
            // Its default settings (dioptra_render::spectral: a composite stack at 6 foci) on
            // the grid `render.spectral.scale` asks, the plan built once for that grid (on the
            // GPU, its matrices uploaded once); on the rig's backend, the layers left on the
            // GPU there.
            let params = self.spectral;
            note = spectral_note(&self.eye, &self.planes, input.width(), params)?;
            self.on_backend("spectral", |gpu| {
                Ok(match gpu {
                    Some(g) => on_gpu(
                        g.spectral_blend_on_gpu(input, &self.planes, &self.eye, params)?
                            .0,
                    ),
                    None => on_host(
                        Cpu.spectral_blend(input, &self.planes, &self.eye, params)?
                            .0
                            .images,
                    ),
                })
            })?
        } else if method.0 == RenderMethod::Optimized {
            // Targets (a gathered focal stack), the linear start and the iterations all on
            // the rig's backend; on the GPU the layers stay there.
            let foci = default_focal_samples();
            let params = OptimizeParams {
                iterations: 30,
                ..OptimizeParams::default()
            };
            self.on_backend("optimized", |gpu| {
                let b = backend_of(gpu);
                let linear = b.linear_blend(input, &self.planes)?;
                let targets = b.defocus(input, &foci, &self.eye, DefocusMethod::Gather, &|_| {})?;
                let init = Some(&linear);
                Ok(match gpu {
                    Some(g) => on_gpu(
                        g.optimized_blend_on_gpu(
                            &targets,
                            &foci,
                            &self.planes,
                            &self.eye,
                            init,
                            params,
                        )?
                        .0,
                    ),
                    None => on_host(
                        b.optimized_blend(
                            &targets,
                            &foci,
                            &self.planes,
                            &self.eye,
                            init,
                            params,
                            &|_| {},
                        )?
                        .0
                        .images,
                    ),
                })
            })?
        } else {
            self.linear(input)?
        };
        Ok((images, note))
    }

    /// Pixels per degree at the centre of an image `width` pixels across the eye's field.
    fn px_per_deg(&self, width: usize) -> f32 {
        1.0f32.to_radians().tan() / self.eye.with_width(width as u32).pixel_pitch_tan()
    }
}

impl Renderer for RgbdRenderer {
    fn render(&self, job: &RenderJob, content: &ContentFrame) -> Result<RenderOutput, RenderError> {
        self.render_frame(content, job.mode, job.method, job.focus, job.gaze, job.auto)
    }
    fn backend_status(&self) -> serde_json::Value {
        RgbdRenderer::backend_status(self)
    }
    /// On the GPU, for the methods that render from an RGB-D in GPU memory (the varifocal
    /// defocus methods, chosen or `auto`, and multifocal linear blending): a GPU failure moves
    /// the rig to the CPU, where the caller makes the views.
    fn render_eyes_on_device(
        &self,
        job: &RenderJob,
        content: &ContentFrame,
        positions: [[f32; 2]; 2],
    ) -> Option<Result<EyesOnDevice, RenderError>> {
        if !from_device(&Ask::of(job)) {
            return None;
        }
        let gpu = lock(&self.compute).gpu.clone()?;
        match self.eyes_from_gpu(&gpu, job, content, positions) {
            Err(RenderError::Gpu(e)) => {
                lock(&self.compute).fall_back(&e);
                None
            }
            made => Some(made),
        }
    }
    fn network_missing(&self) -> Vec<(Mode, RenderMethod, String)> {
        self.nets
            .iter()
            .filter_map(|((m, r), n)| n.as_ref().err().map(|e| (*m, *r, e.clone())))
            .collect()
    }
}

/// What `/status` says of a multifocal decomposition other than the hybrid: its method.
fn method_note(method: Method) -> serde_json::Value {
    serde_json::json!({ "method": method.as_str() })
}

/// What `/status` says of a spectral decomposition: the grid it was solved on.
fn spectral_note(
    eye: &EyeModel,
    planes: &[Diopters],
    width: usize,
    params: SpectralParams,
) -> Result<serde_json::Value, RenderError> {
    let grid = dioptra_render::spectral_coarse::scale_for(
        eye,
        planes,
        width,
        params.scale,
        params.focal_range,
    )?;
    Ok(serde_json::json!({
        "method": "spectral",
        "grid": if grid == 1 {
            "full resolution".to_string()
        } else {
            format!("1/{grid}, plus linear blending's detail (render.spectral.scale = 1 for full resolution)")
        },
        "scale": grid,
    }))
}

/// What `/status` says of a hybrid decomposition: whether the fovea was optimised (a blurred
/// depth step reached it: spectral layers in a window around the gaze) or left to linear
/// blending, where, and how long its stages took.
fn hybrid_note(report: &HybridReport) -> serde_json::Value {
    let window = report.window.map(|w| {
        serde_json::json!({
            "x0": w.x0, "y0": w.y0, "width": w.width, "height": w.height,
            "scale": w.scale,
        })
    });
    serde_json::json!({
        "method": "hybrid",
        "fovea": if report.window.is_some() { "spectral" } else { "linear" },
        "why": if report.window.is_some() {
            "a blurred depth step reaches the fovea"
        } else {
            "no blurred depth step reaches the fovea"
        },
        "gaze_px": report.gaze,
        "window": window,
        "stages_ms": {
            "linear": report.stages_ms.linear,
            "scan": report.stages_ms.scan,
            "solve": report.stages_ms.solve,
            "compose": report.stages_ms.compose,
        },
    })
}

/// The time one eye's varifocal frame may take: the display period less the margin for the
/// rest of the frame ([`super::budget::margin_ms`]), split between the eyes rendered one after
/// the other, on the cores rayon renders on.
fn eye_deadline(display: &Display) -> Deadline {
    let period_ms = 1e3 / display.frame_hz.max(1e-3);
    let eyes = if display.stereo() { 2.0 } else { 1.0 };
    let frame = Deadline::from_period(period_ms, super::budget::margin_ms(period_ms), 1);
    Deadline {
        budget_ms: frame.budget_ms / eyes,
        cores: rayon::current_num_threads(),
    }
}

/// The lenslet display's image of a `LF_GRID` x `LF_GRID` light field of `views` (pixel pitch
/// `pixel_pitch_tan`) for a `w` x `h` display: (w / 5) x (h / 5) lenslets of 5 x 5 pixels.
fn lenslet_panel(
    views: &[RgbImage],
    pixel_pitch_tan: f32,
    size: (usize, usize),
) -> Result<RgbImage, RenderError> {
    let grid = ViewGrid {
        grid: LF_GRID,
        spacing_m: LF_SPAN_M / (LF_GRID - 1) as f32,
        views,
        pixel_pitch_tan,
    };
    Ok(elemental_images(&grid, &lenslet_display(size))?)
}

/// The lenslet display over a `w` x `h` panel: (w / 5) x (h / 5) lenslets of 5 x 5 pixels.
fn lenslet_display((w, h): (usize, usize)) -> LensletDisplay {
    LensletDisplay {
        lenslets: [(w / 5).max(1), (h / 5).max(1)],
        pixels_per_lenslet: 5,
        lenslet_pitch_m: 0.000_25,
        gap_m: 0.000_94,
        eye_relief_m: 0.015,
    }
}

/// What a frame is asked for: the job's or `render_frame`'s.
#[derive(Debug, Clone, Copy)]
struct Ask {
    mode: Mode,
    method: Method,
    focus: Diopters,
    gaze: Option<[f32; 2]>,
    auto: bool,
}

impl Ask {
    fn of(job: &RenderJob) -> Ask {
        Ask {
            mode: job.mode,
            method: job.method,
            focus: job.focus,
            gaze: job.gaze,
            auto: job.auto,
        }
    }
}

/// Whether `ask` renders from an RGB-D in GPU memory on the GPU: the varifocal defocus
/// methods (chosen or `auto`) and multifocal linear blending.
fn from_device(ask: &Ask) -> bool {
    match (ask.mode, ask.method.0) {
        (Mode::Varifocal, _) if ask.auto => true,
        (Mode::Varifocal, m) => matches!(
            m,
            RenderMethod::Gather | RenderMethod::Pyramid | RenderMethod::LightFieldDefocus
        ),
        (Mode::Multifocal, m) => m == RenderMethod::Linear,
        _ => false,
    }
}

/// A defocus method's name in `/status`.
fn defocus_label(method: DefocusMethod) -> String {
    match method {
        DefocusMethod::Gather => "gather".to_string(),
        DefocusMethod::Pyramid(_) => "pyramid".to_string(),
        DefocusMethod::LightField(p) => format!("lightfield-{}", p.views),
    }
}

/// `method` with its foveation (if any) centred on `gaze`.
fn foveated_at(method: DefocusMethod, gaze: [f32; 2]) -> DefocusMethod {
    match method {
        DefocusMethod::Pyramid(PyramidParams { foveation: Some(f) }) => {
            DefocusMethod::Pyramid(PyramidParams {
                foveation: Some(Foveation { gaze, ..f }),
            })
        }
        m => m,
    }
}

/// The backend of `on_backend`'s choice: the rig's GPU, or the CPU.
fn backend_of(gpu: Option<&Gpu>) -> &dyn Backend {
    match gpu {
        Some(g) => g,
        None => &Cpu,
    }
}

fn on_gpu(images: Vec<dioptra_render::gpu::GpuImage>) -> Vec<FrameImage> {
    images.into_iter().map(FrameImage::Gpu).collect()
}

fn on_host(images: Vec<RgbImage>) -> Vec<FrameImage> {
    images.into_iter().map(FrameImage::Host).collect()
}

fn net_error(e: dioptra_net::NetError) -> RenderError {
    RenderError::Input(InputError::InvalidValue(format!("network: {e}")))
}

/// The nets the daemon loads: which mode and method each serves, and its configuration.
const NET_CONFIGS: [(Mode, RenderMethod, &str); 5] = [
    (Mode::Varifocal, RenderMethod::Network, "c1"),
    (Mode::Multifocal, RenderMethod::Network, "c4"),
    (Mode::Varifocal, RenderMethod::Refine, "c1r"),
    (Mode::Multifocal, RenderMethod::Refine, "c4r"),
    (Mode::Lightfield, RenderMethod::Refine, "c5r"),
];

/// A net's mode and method.
type NetKey = (Mode, RenderMethod);

/// Loads the net of `config` (`c1`, `c4`, `c1r`, `c4r`, `c5r`) from `render.weights`, checking that
/// a multifocal net's planes are the rig's `optics.planes` (`rig_planes`).
fn load_net(
    render: &Render,
    rig_planes: &[f32],
    config: &str,
) -> Result<Arc<dioptra_net::CpuNet>, String> {
    let path = render.weights_file(config);
    let what = match config {
        "c1" => "varifocal mode's network (C1)",
        "c4" => "multifocal mode's network (C4)",
        "c1r" => "varifocal mode's refinement net (C1R)",
        "c5r" => "light-field mode's refinement net (C5R)",
        _ => "multifocal mode's refinement net (C4R)",
    };
    if !path.exists() {
        return Err(format!(
            "render.weights: the {what} weights file {} does not exist; train it with \
             `dioptra train --config {config}` and set render.weights to the directory holding \
             {config}.safetensors",
            path.display()
        ));
    }
    let net = dioptra_net::load_net(Some(&path), config)
        .map_err(|e| format!("render.weights: {}: {e}", path.display()))?;
    if let Some(planes) = net.arch().task.planes() {
        let same = planes.len() == rig_planes.len()
            && planes
                .iter()
                .zip(rig_planes)
                .all(|(a, b)| (a - b).abs() < 1e-4);
        if !same {
            return Err(format!(
                "render.weights: {} makes layers for planes {planes:?} D, and optics.planes is {:?} D",
                path.display(),
                rig_planes
            ));
        }
    }
    Ok(Arc::new(net))
}

/// The net of each mode and method, loaded for the CPU (or why not).
type CpuNets = Vec<(NetKey, Result<Arc<dioptra_net::CpuNet>, String>)>;

/// The render backend and what `/status` says of it.
struct Compute {
    /// The GPU frames are rendered on (`None`: the CPU).
    gpu: Option<Arc<dioptra_render::Gpu>>,
    /// The nets on the GPU, per mode and method (or why that one runs on the CPU).
    gpu_nets: Vec<(NetKey, Result<Arc<dioptra_net::gpu::GpuNet>, String>)>,
    /// The fraction of the error map's tiles C1R's net ran on in the newest refined frame.
    refine_tiles: Option<f64>,
    adapter: Option<String>,
    /// Whether the adapter has timestamp queries (GPU time per method in `/status`).
    timestamps: bool,
    /// GPU time per method, µs, from timestamp queries.
    gpu_time: std::collections::BTreeMap<String, hdrhistogram::Histogram<u64>>,
    /// The newest multifocal decomposition per eye (`mono` for one image): its method, and
    /// the hybrid's fovea ([`hybrid_note`]).
    decompositions: std::collections::BTreeMap<&'static str, serde_json::Value>,
    /// Why the rig renders on the CPU although the config asked for (or allowed) the GPU.
    cpu_because: Option<String>,
    /// Per stage of a frame (each eye's view, each method, the light-field panel, the content
    /// upload), where it ran (`gpu`, `cpu`, or `host to gpu` for an upload) and how many times:
    /// `/status`'s `render.stages`, one `{"stage", "on", "count"}` each.
    stages: std::collections::BTreeMap<String, std::collections::BTreeMap<&'static str, u64>>,
}

impl Compute {
    fn cpu(because: Option<String>) -> Compute {
        Compute {
            gpu: None,
            gpu_nets: Vec::new(),
            refine_tiles: None,
            adapter: None,
            timestamps: false,
            gpu_time: Default::default(),
            decompositions: Default::default(),
            cpu_because: because,
            stages: Default::default(),
        }
    }

    fn gpu(adapter: Option<&str>, nets: &CpuNets) -> Result<Compute, dioptra_render::GpuError> {
        let gpu = Arc::new(dioptra_render::Gpu::new(adapter)?);
        let ctx = dioptra_render::gpu::GpuContext::shared(adapter)?;
        let name = gpu.context().adapter().name.clone();
        // The same weights the CPU loaded, uploaded once to the render's device.
        let gpu_nets = nets
            .iter()
            .filter_map(|((m, r), n)| {
                let n = n.as_ref().ok()?;
                let g = dioptra_net::gpu::GpuNet::on(ctx.clone(), n.weights().clone())
                    .map(Arc::new)
                    .map_err(|e| {
                        tracing::warn!(mode = m.as_str(), method = r.as_str(), error = %e, "the net runs on the CPU");
                        e.to_string()
                    });
                Some(((*m, *r), g))
            })
            .collect();
        Ok(Compute {
            timestamps: gpu.context().has_timestamps(),
            gpu: Some(gpu),
            gpu_nets,
            refine_tiles: None,
            adapter: Some(name),
            gpu_time: Default::default(),
            decompositions: Default::default(),
            cpu_because: None,
            stages: Default::default(),
        })
    }

    /// `[render] backend`: `gpu` must open (or the rig does not start); `auto` takes a
    /// hardware adapter when there is one and the CPU otherwise.
    fn open(render: &Render, nets: &CpuNets) -> Result<Compute, RenderError> {
        let adapter = render.adapter.as_deref();
        match render.backend {
            RenderBackend::Cpu => Ok(Compute::cpu(None)),
            RenderBackend::Gpu => Ok(Compute::gpu(adapter, nets)?),
            RenderBackend::Auto => {
                if !dioptra_render::gpu::hardware_adapter_exists() {
                    return Ok(Compute::cpu(Some(
                        "no hardware GPU adapter (render.backend = \"gpu\" uses a software one)"
                            .into(),
                    )));
                }
                Ok(Compute::gpu(adapter, nets).unwrap_or_else(|e| {
                    tracing::warn!(error = %e, "cannot open the GPU; rendering on the CPU");
                    Compute::cpu(Some(format!("the GPU did not open: {e}")))
                }))
            }
        }
    }

    fn gpu_net(&self, key: NetKey) -> Option<Arc<dioptra_net::gpu::GpuNet>> {
        self.gpu_nets
            .iter()
            .find(|(k, _)| *k == key)
            .and_then(|(_, n)| n.as_ref().ok().cloned())
    }

    /// Records `label`'s GPU time (timestamp queries; nothing without them).
    fn timed(&mut self, label: &str, gpu_ns: Option<f64>) {
        let Some(ns) = gpu_ns else { return };
        if !self.gpu_time.contains_key(label) {
            match hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3) {
                Ok(h) => self.gpu_time.insert(label.to_string(), h),
                Err(_) => return,
            };
        }
        if let Some(h) = self.gpu_time.get_mut(label) {
            h.saturating_record((ns / 1e3).round().max(1.0) as u64);
        }
    }

    /// `stage` ran `on` (a backend, or what crossed between them).
    fn ran(&mut self, stage: &str, on: &'static str) {
        *self
            .stages
            .entry(stage.to_string())
            .or_default()
            .entry(on)
            .or_default() += 1;
    }

    fn fall_back(&mut self, e: &dioptra_render::GpuError) {
        if self.cpu_because.is_none() {
            tracing::error!(error = %e, "the GPU failed; rendering on the CPU from now on");
            let decompositions = std::mem::take(&mut self.decompositions);
            let stages = std::mem::take(&mut self.stages);
            *self = Compute::cpu(Some(format!("the GPU failed: {e}")));
            self.decompositions = decompositions;
            self.stages = stages;
        }
    }

    /// Notes the newest multifocal decomposition made for `eye`, with the backend it ran on.
    fn decomposed(&mut self, eye: Option<Side>, mut note: serde_json::Value) {
        note["backend"] = serde_json::json!(if self.gpu.is_some() { "gpu" } else { "cpu" });
        self.decompositions
            .insert(eye.map_or("mono", Side::as_str), note);
    }

    fn status(&self) -> serde_json::Value {
        let gpu_time: serde_json::Map<String, serde_json::Value> = self
            .gpu_time
            .iter()
            .map(|(k, h)| {
                (
                    k.clone(),
                    serde_json::json!({
                        "count": h.len(),
                        "p50_us": h.value_at_quantile(0.5),
                        "p99_us": h.value_at_quantile(0.99),
                        "max_us": h.max(),
                    }),
                )
            })
            .collect();
        let nets_of = |method: RenderMethod| -> serde_json::Map<String, serde_json::Value> {
            self.gpu_nets
                .iter()
                .filter(|((_, r), _)| *r == method)
                .map(|((m, _), n)| {
                    (
                        m.as_str().to_string(),
                        match n {
                            Ok(_) => serde_json::json!("gpu"),
                            Err(e) => serde_json::json!(format!("cpu: {e}")),
                        },
                    )
                })
                .collect()
        };
        serde_json::json!({
            "backend": if self.gpu.is_some() { "gpu" } else { "cpu" },
            // Frame images left in GPU memory and read back (a PNG written, a window on
            // another device).
            "images_read_back": self.gpu.as_ref().map(|g| g.images_read_back()),
            "adapter": self.adapter,
            "cpu_because": self.cpu_because,
            "timestamps": self.timestamps,
            "gpu_time_us": gpu_time,
            "network": nets_of(RenderMethod::Network),
            "refine": nets_of(RenderMethod::Refine),
            // Where the spectral decomposition runs: the rig's backend.
            "spectral_on": if self.gpu.is_some() { "gpu" } else { "cpu" },
            "refine_tiles_run": self.refine_tiles,
            // The newest multifocal decomposition per eye: which ran, and the hybrid's fovea
            // (optimised at a depth step, or linear).
            "decomposition": self.decompositions,
            "stages": self
                .stages
                .iter()
                .flat_map(|(stage, on)| {
                    on.iter().map(move |(on, count)| {
                        serde_json::json!({"stage": stage, "on": on, "count": count})
                    })
                })
                .collect::<Vec<_>>(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{RigConfig, EXAMPLE_SIM_RIG};
    use crate::content::stream::{ColorFormat, DepthKind, FrameDesc};
    use dioptra_core::Timestamp;

    /// `/status` says which grid a spectral decomposition was solved on: the image's own at a
    /// small image, 1/4 at a 960 px panel over 20 degrees, what `render.spectral.scale` asks
    /// when set.
    #[test]
    fn the_spectral_note_names_its_grid() {
        let eye = EyeModel::default();
        let planes: Vec<Diopters> = dioptra_render::multifocal::DEFAULT_PLANES
            .iter()
            .map(|&p| Diopters(p))
            .collect();
        let auto = SpectralParams::default();
        let note = |w: usize, p: SpectralParams| spectral_note(&eye, &planes, w, p).unwrap();
        let small = note(96, auto);
        assert_eq!(small["grid"], "full resolution", "{small}");
        assert_eq!(small["scale"], 1);
        let panel = note(960, auto);
        assert_eq!(panel["scale"], 4, "{panel}");
        assert!(panel["grid"]
            .as_str()
            .unwrap()
            .contains("render.spectral.scale = 1"));
        let full = note(960, SpectralParams { scale: 1, ..auto });
        assert_eq!(full["grid"], "full resolution", "{full}");
    }

    /// A textured frame of `size` px: the left half at 3 D, the right at 0.25 D (a depth step
    /// through the middle, where the gaze is).
    fn step_frame(size: usize) -> ContentFrame {
        use dioptra_core::{DepthMap, Plane};
        let n = size * size;
        let tex: Vec<f32> = (0..n * 3)
            .map(|i| (((i / 3) % size / 3 + (i / 3) / size / 3) % 2) as f32 * 0.3 + 0.35)
            .collect();
        let depth: Vec<f32> = (0..n)
            .map(|i| if i % size < size / 2 { 3.0 } else { 0.25 })
            .collect();
        let rgbd = Rgbd::new(
            RgbImage::from_interleaved(size, size, &tex).unwrap(),
            DepthMap::from_diopters(Plane::from_vec(size, size, depth).unwrap()).unwrap(),
        )
        .unwrap();
        ContentFrame::new(1, Arc::new(rgbd))
    }

    /// The one-lens example rig at `size` px refreshing at `hz`, foveated as `foveation`
    /// says, rendering on the CPU.
    fn renderer(size: usize, hz: f64, foveation: &str) -> RgbdRenderer {
        let text = EXAMPLE_SIM_RIG
            .replace("width = 96", &format!("width = {size}"))
            .replace("height = 96", &format!("height = {size}"))
            .replace("frame_hz = 60.0", &format!("frame_hz = {hz}"))
            .replace("method = \"gather\"", "method = \"auto\"")
            + &format!("\n[render]\nbackend = \"cpu\"\nfoveation = {foveation}\n");
        let cfg = RigConfig::parse(&text).unwrap();
        RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap()
    }

    /// With `method = "auto"` the planner works within the frame's time budget (the display
    /// period less a margin): a long period leaves it the setting its accuracy target asks, a
    /// short one a cheaper setting predicted to fit. Costs are the planner's predictions (the
    /// rig's clock plays no part), so the test does not depend on this machine's speed.
    #[test]
    fn under_a_short_budget_the_planner_picks_a_cheaper_setting_that_fits() {
        let size = 192;
        let frame = step_frame(size);
        let gaze = Some([0.5 * size as f32, 0.5 * size as f32]);
        let plan = |hz: f64| {
            let r = renderer(size, hz, "{ radius_deg = 5.0 }");
            let out = r
                .render_frame(
                    &frame,
                    Mode::Varifocal,
                    Method(RenderMethod::Gather),
                    Diopters(0.25),
                    gaze,
                    true,
                )
                .unwrap();
            // The chosen setting was rendered: one image of the frame's size.
            assert_eq!(out.images.len(), 1);
            assert_eq!(
                (out.images[0].width(), out.images[0].height()),
                (size, size)
            );
            out.planned.unwrap()
        };
        let long = plan(1.0);
        // 1 Hz: 900 ms.
        assert!((long.budget_ms - 900.0).abs() < 1e-6, "{long:?}");
        // A period whose budget (less its tenth) is half the unconstrained choice's time.
        let short = plan(1e3 / (long.predicted_ms / 0.9 * 0.5).max(1.2));
        eprintln!("long: {long:?}\nshort: {short:?}");
        assert!(short.budget_ms < long.predicted_ms, "{short:?}");
        assert!(long.predicted_ms <= long.budget_ms, "{long:?}");
        assert!(
            short.predicted_ms <= short.budget_ms,
            "the short budget's choice must be predicted to fit: {short:?}"
        );
        assert!(
            short.predicted_ms < long.predicted_ms && short.choice != long.choice,
            "a cheaper setting under the short budget: {short:?} against {long:?}"
        );
        assert!(short.why.contains("budget"), "{short:?}");
    }

    /// The planner's whole-frame statistics are computed once per content frame and eye and
    /// kept while the frame is the newest: each eye's, and a newer frame's, are their own.
    #[test]
    fn the_planners_whole_frame_statistics_are_kept_per_content_frame_and_eye() {
        let r = renderer(64, 60.0, "{ radius_deg = 5.0 }");
        let frame = step_frame(64);
        let render = |f: &ContentFrame, focus: f32| {
            let g = Some([32.0, 32.0]);
            let m = Method(RenderMethod::Gather);
            r.render_frame(f, Mode::Varifocal, m, Diopters(focus), g, true)
                .unwrap()
        };
        render(&frame, 0.25);
        let first = r.frame_wide(&frame);
        render(&frame, 2.0);
        assert!(Arc::ptr_eq(&first, &r.frame_wide(&frame)), "kept");
        assert_eq!(*first, FrameWide::of(&frame.rgbd));
        // The right eye's view of the same content frame (nearer): its own statistics.
        let nearer = {
            let mut rgbd = frame.rgbd.as_ref().clone();
            let d = rgbd.depth.data().iter().map(|d| d + 0.5).collect();
            rgbd.depth = dioptra_core::DepthMap::from_diopters(
                dioptra_core::Plane::from_vec(64, 64, d).unwrap(),
            )
            .unwrap();
            Arc::new(rgbd)
        };
        let right = frame.for_eye(Side::Right, nearer);
        render(&right, 0.25);
        assert_eq!(*r.frame_wide(&right), FrameWide::of(&right.rgbd));
        assert_ne!(*r.frame_wide(&right), *first);
        // A newer content frame: the older frame's are dropped.
        let newer = ContentFrame::new(2, frame.rgbd.clone());
        render(&newer, 0.25);
        assert_eq!(lock(&r.frame_wide).len(), 1);
        assert!(lock(&r.frame_wide).iter().all(|((n, _), _, _)| *n == 2));
    }

    /// Each eye's gaze is where the fixation point (the cyclopean gaze at the focus's
    /// distance) falls on that eye's image: nearer focus, further apart; at 0 D both at the
    /// cyclopean gaze.
    #[test]
    fn each_eye_sees_the_fixation_point_from_its_own_position() {
        let r = renderer(192, 60.0, "\"off\"");
        let input = step_frame(192);
        let g = Some([96.0, 96.0]);
        let at = |eye, d: f32| r.eye_gaze(&input.rgbd, g, eye, Diopters(d));
        assert_eq!(at(None, 2.0), [96.0, 96.0]);
        assert_eq!(at(Some(Side::Left), 0.0), [96.0, 96.0]);
        let (l, rt) = (at(Some(Side::Left), 1.0), at(Some(Side::Right), 1.0));
        // 31.5 mm at 1 m is 1.8 degrees; over 20 degrees of 192 px, about 17 px.
        let px = 0.0315 / r.eye.with_width(192).pixel_pitch_tan();
        assert!(
            (l[0] - 96.0 - px).abs() < 1e-3 && (96.0 - rt[0] - px).abs() < 1e-3,
            "{l:?} {rt:?}"
        );
        assert!((16.0..18.0).contains(&px), "{px}");
        assert!(at(Some(Side::Left), 2.0)[0] > l[0]);
        // Never off the image.
        assert_eq!(at(Some(Side::Left), 100.0)[0], 192.0);
    }

    /// `method = "pyramid"` with `render.foveation` renders the foveated pyramid around the
    /// gaze: the same as full resolution at the gaze, coarser (different) far from it.
    #[test]
    fn foveation_renders_full_resolution_around_the_gaze_only() {
        let size = 192;
        let frame = step_frame(size);
        let full = renderer(size, 60.0, "\"off\"");
        let fov = renderer(
            size,
            60.0,
            "{ radius_deg = 2.0, falloff_arcmin_per_deg = 60.0 }",
        );
        let gaze = Some([40.0, 96.0]);
        let image = |r: &RgbdRenderer| {
            r.render_frame(
                &frame,
                Mode::Varifocal,
                Method(RenderMethod::Pyramid),
                Diopters(3.0),
                gaze,
                false,
            )
            .unwrap()
            .images[0]
                .to_host()
                .unwrap()
                .into_owned()
        };
        let (a, b) = (image(&full), image(&fov));
        let diff = |x0: usize, x1: usize| {
            let mut d = 0.0f32;
            for c in 0..3 {
                for y in 80..112 {
                    for x in x0..x1 {
                        d = d.max((a.channels[c].row(y)[x] - b.channels[c].row(y)[x]).abs());
                    }
                }
            }
            d
        };
        // 2 degrees over 20 of 192 px: about 19 px around x = 40.
        assert!(diff(32, 48) < 1e-3, "fovea {}", diff(32, 48));
        assert!(diff(150, 190) > 1e-3, "periphery {}", diff(150, 190));
    }

    /// `method = "hybrid"` on `backend` (the one-lens example rig at `size` px): its layers for
    /// `frame` around `gaze`, with what `/status` says of the decomposition.
    fn hybrid_layers(
        r: &RgbdRenderer,
        frame: &ContentFrame,
        gaze: [f32; 2],
    ) -> (Vec<RgbImage>, serde_json::Value) {
        let out = r
            .render_frame(
                frame,
                Mode::Multifocal,
                Method(RenderMethod::Hybrid),
                Diopters(1.0),
                Some(gaze),
                false,
            )
            .unwrap();
        let layers = out
            .images
            .iter()
            .map(|i| i.to_host().unwrap().into_owned())
            .collect();
        (layers, r.backend_status()["decomposition"]["mono"].clone())
    }

    /// The multifocal hybrid optimises the fovea where a blurred depth step reaches it (the
    /// step under the gaze: the layers there are not linear blending's, far from the gaze
    /// they are) and is linear blending where none does (the gaze on flat depth); `/status`
    /// says which. The layers follow the gaze within one content frame. On the CPU, and on
    /// the GPU where an adapter exists.
    #[test]
    fn the_hybrid_optimises_the_fovea_at_a_depth_step_near_the_gaze_only() {
        let size = 128;
        let frame = step_frame(size);
        let max_diff = |a: &[RgbImage], b: &[RgbImage], x: usize, y: usize| -> f32 {
            let mut d = 0.0f32;
            for (p, q) in a.iter().zip(b) {
                for c in 0..3 {
                    d = d.max((p.channels[c].row(y)[x] - q.channels[c].row(y)[x]).abs());
                }
            }
            d
        };
        let mut backends = vec!["cpu"];
        if dioptra_render::Gpu::new(None).is_ok() {
            backends.push("gpu");
        } else {
            eprintln!("gpu: skipped, no GPU adapter");
        }
        for backend in backends {
            let text = EXAMPLE_SIM_RIG
                .replace("width = 96", &format!("width = {size}"))
                .replace("height = 96", &format!("height = {size}"))
                + &format!(
                    "\n[render]\nbackend = \"{backend}\"\nhybrid = {{ fovea_deg = 1.0, blend_deg = 0.2, scale = 1 }}\n"
                );
            let cfg = RigConfig::parse(&text).unwrap();
            let r = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
            let lin = Cpu.linear_blend(&frame.rgbd, &r.planes).unwrap().images;
            // The gaze on the step (x = 64): the fovea optimised, linear blending far away.
            let (at_step, note) = hybrid_layers(&r, &frame, [64.0, 64.0]);
            assert_eq!(at_step.len(), lin.len());
            assert_eq!(note["method"], "hybrid", "{backend}: {note}");
            assert_eq!(note["fovea"], "spectral", "{backend}: {note}");
            assert_eq!(note["backend"], backend, "{note}");
            assert!(
                note["window"]["width"].as_u64().unwrap() < size as u64,
                "{note}"
            );
            assert!(
                max_diff(&at_step, &lin, 64, 64) > 1e-3,
                "{backend}: the fovea at the step is linear blending's"
            );
            for (x, y) in [(0, 0), (127, 127), (0, 127)] {
                assert_eq!(max_diff(&at_step, &lin, x, y), 0.0, "{backend}: ({x}, {y})");
            }
            // The gaze on the near half's flat depth, no step within reach of the fovea (1
            // degree, 6 px here): linear blending everywhere, made again for the new gaze.
            let (flat, note) = hybrid_layers(&r, &frame, [16.0, 64.0]);
            assert_eq!(note["fovea"], "linear", "{backend}: {note}");
            assert!(note["window"].is_null(), "{note}");
            assert_eq!(flat, lin, "{backend}");
            // Back at the step: optimised again.
            let (again, note) = hybrid_layers(&r, &frame, [64.0, 64.0]);
            assert_eq!(note["fovea"], "spectral", "{backend}: {note}");
            assert!(max_diff(&again, &lin, 64, 64) > 1e-3, "{backend}");
        }
    }

    /// On a stereo layout each eye of one content frame gets its own layers and its own panel:
    /// the caches hold them per eye (the right eye is never shown the left's), and the light
    /// field of the scene is centred on each eye.
    #[test]
    fn each_eye_of_one_content_frame_gets_its_own_layers_and_panel() {
        let text = crate::config::EXAMPLE_SIM_BINOCULAR_RIG.to_string()
            + "\n[content]\nanimate = false\n\n[render]\nbackend = \"cpu\"\n";
        let cfg = RigConfig::parse(&text).unwrap();
        let r = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        let content = crate::content::open_simulated(&cfg);
        let frame = content.poll(Timestamp::ZERO).unwrap();
        let views = crate::content::stereo::EyeViews::new(&cfg.eye, &cfg.display).unwrap();
        let ([left, right], _) = views.of(&frame).unwrap();
        let eyes = [
            frame.for_eye(Side::Left, left),
            frame.for_eye(Side::Right, right),
        ];
        for (mode, method) in [
            (Mode::Multifocal, RenderMethod::Linear),
            (Mode::Lightfield, RenderMethod::Views),
        ] {
            let out: Vec<Vec<RgbImage>> = eyes
                .iter()
                .map(|e| {
                    r.render_frame(e, mode, Method(method), Diopters(1.0), None, false)
                        .unwrap()
                        .images
                        .iter()
                        .map(|i| i.to_host().unwrap().into_owned())
                        .collect()
                })
                .collect();
            assert_ne!(out[0], out[1], "{mode:?}: each eye its own");
            // Asked again (from the caches): the same per eye.
            for (e, want) in eyes.iter().zip(&out) {
                let again: Vec<RgbImage> = r
                    .render_frame(e, mode, Method(method), Diopters(1.0), None, false)
                    .unwrap()
                    .images
                    .iter()
                    .map(|i| i.to_host().unwrap().into_owned())
                    .collect();
                assert_eq!(&again, want, "{mode:?} {:?}", e.eye);
            }
        }
    }

    /// Light-field mode on streamed content: the panel is made from views synthesised from the
    /// frame on show, and made again when another frame comes.
    #[test]
    fn light_field_mode_shows_a_streamed_frames_light_field() {
        let text = EXAMPLE_SIM_RIG.to_string()
            + "\n[content]\nsource = \"stream\"\nring = \"none\"\n\n[render]\nbackend = \"cpu\"\n";
        let cfg = RigConfig::parse(&text).unwrap();
        let r = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        let content = crate::content::open_simulated(&cfg);
        let (w, h) = (96, 96);
        // At optical infinity every view is the frame itself: the panel is the lenslet
        // resampling of 25 copies of it.
        let send = |seq: u64, colour: &dyn Fn(usize) -> u8| {
            let desc = FrameDesc {
                width: w,
                height: h,
                color: ColorFormat::Rgb8,
                depth: DepthKind::Diopters,
                near: None,
                far: None,
                seq: Some(seq),
                app_time_ns: None,
            };
            let color: Vec<u8> = (0..3 * w * h).map(colour).collect();
            let depth: Vec<u8> = (0..w * h).flat_map(|_| 0f32.to_le_bytes()).collect();
            let stream = content.frame_ingest().unwrap();
            stream
                .submit(&desc, &color, &depth, Timestamp(seq))
                .unwrap();
            content.poll(Timestamp(seq)).expect("the frame is taken up")
        };
        let panel =
            |frame: &ContentFrame| light_field_panel(&r, frame, RenderMethod::Views).unwrap();
        let one = send(1, &|i| (i * 7 % 251) as u8);
        let first = panel(&one);
        let copies = vec![one.rgbd.color.clone(); LF_GRID * LF_GRID];
        let want = lenslet_panel(&copies, r.eye.pixel_pitch_tan(), (w, h)).unwrap();
        assert_eq!(
            (first.width(), first.height()),
            (want.width(), want.height())
        );
        let p = dioptra_render::metrics::psnr(&first, &want, None).unwrap();
        assert!(p > 60.0, "{p} dB from the frame's own lenslet image");
        // The same frame: the panel is kept. Another frame: made again.
        assert_eq!(panel(&one), first);
        let two = send(2, &|i| (i * 13 % 241) as u8);
        assert_ne!(panel(&two), first);
    }

    /// Light-field mode on a view grid (`content.views`): the panel is synthesised from every
    /// view, and is nearer the scene's own light field (its 5 x 5 pinhole views, ray cast)
    /// than the panel made from the central view alone.
    #[test]
    fn a_view_grid_makes_a_truer_panel_than_its_central_view() {
        use dioptra_sim::scene::{light_field_positions, render_pinhole, Camera};
        let text = EXAMPLE_SIM_RIG.to_string()
            + "\n[content]\nanimate = false\n\n[render]\nbackend = \"cpu\"\n";
        let cfg = RigConfig::parse(&text).unwrap();
        let r = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        let content = crate::content::open_simulated(&cfg);
        let scene = content.poll(Timestamp::ZERO).unwrap().scene.unwrap();
        let (w, h) = r.size;
        let cam = Camera::new(r.eye, w, h);
        let view = |p: [f32; 2]| render_pinhole(&scene, &cam, p, 2).unwrap();
        let grid: Arc<[ContentView]> = light_field_positions(3, LF_SPAN_M)
            .unwrap()
            .into_iter()
            .map(|position| {
                let (c, d) = view(position);
                ContentView {
                    eye: None,
                    position,
                    rgbd: Arc::new(Rgbd::new(c, d).unwrap()),
                }
            })
            .collect();
        let truth: Vec<RgbImage> = light_field_positions(LF_GRID, LF_SPAN_M)
            .unwrap()
            .into_iter()
            .map(|p| view(p).0)
            .collect();
        let truth = lenslet_panel(&truth, r.eye.pixel_pitch_tan(), (w, h)).unwrap();
        let centre = ContentFrame::new(1, grid[4].rgbd.clone());
        let all = ContentFrame {
            views: Some(grid.clone()),
            ..ContentFrame::new(2, grid[4].rgbd.clone())
        };
        let score = |frame: &ContentFrame| {
            let panel = light_field_panel(&r, frame, RenderMethod::Views).unwrap();
            dioptra_render::metrics::psnr(&panel, &truth, None).unwrap()
        };
        let (one, nine) = (score(&centre), score(&all));
        eprintln!("panel against the scene's: central view {one:.2} dB, 3 x 3 grid {nine:.2} dB");
        assert!(
            nine > one + 2.0,
            "{nine:.2} dB from the grid, {one:.2} from its centre"
        );
    }

    /// A stereo rig's eye takes its own grid as it is, or the one grid from its own centre
    /// (IPD / 2 to the side).
    #[test]
    fn each_eye_takes_its_own_grid_or_the_one_grid_from_its_centre() {
        let text = crate::config::EXAMPLE_SIM_BINOCULAR_RIG.to_string()
            + "\n[render]\nbackend = \"cpu\"\n";
        let cfg = RigConfig::parse(&text).unwrap();
        let r = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        let rgbd = Arc::new(
            Rgbd::new(
                RgbImage::new(4, 4, [0.5; 3]),
                dioptra_core::DepthMap::from_diopters(dioptra_core::Plane::new(4, 4, 1.0)).unwrap(),
            )
            .unwrap(),
        );
        let at = |eye, x: f32| ContentView {
            eye,
            position: [x, 0.002],
            rgbd: rgbd.clone(),
        };
        let half = r.half_ipd_m;
        let xs = |v: Vec<RgbdView>| v.iter().map(|v| v.position).collect::<Vec<_>>();
        let one = [at(None, -0.001), at(None, 0.001)];
        assert_eq!(
            xs(r.eye_inputs(&one, None)),
            [[-0.001, 0.002], [0.001, 0.002]]
        );
        let left = xs(r.eye_inputs(&one, Some(Side::Left)));
        assert_eq!(left, [[-0.001 + half, 0.002], [0.001 + half, 0.002]]);
        let right = xs(r.eye_inputs(&one, Some(Side::Right)));
        assert_eq!(right, [[-0.001 - half, 0.002], [0.001 - half, 0.002]]);
        let own = [at(Some(Side::Left), -0.001), at(Some(Side::Right), 0.003)];
        assert_eq!(xs(r.eye_inputs(&own, Some(Side::Right))), [[0.003, 0.002]]);
        assert_eq!(xs(r.eye_inputs(&own, Some(Side::Left))), [[-0.001, 0.002]]);
    }

    /// Light-field mode's `refine` (C5R from `render.weights`): an untrained net (its last
    /// layer zero) makes the classical panel exactly, a net with a nonzero last layer another
    /// one; without the weights file the frame fails naming render.weights and how to train;
    /// without render.weights the shipped net refines.
    #[test]
    fn light_field_refine_is_the_classical_panel_corrected_by_c5r() {
        let dir = tempfile::tempdir().unwrap();
        let arch = dioptra_net::Arch::preset("c5r").unwrap();
        let rig = |weights: &std::path::Path| {
            let text = format!(
                "{EXAMPLE_SIM_RIG}\n[content]\nanimate = false\n\n[render]\nbackend = \"cpu\"\nweights = {:?}\n",
                weights.display().to_string()
            );
            let cfg = RigConfig::parse(&text).unwrap();
            RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap()
        };
        let r = rig(dir.path());
        let content = ContentFrame::new(1, Arc::new(scene_rgbd(&r)));
        let panel = |r: &RgbdRenderer, m: RenderMethod| light_field_panel(r, &content, m);
        let e = panel(&r, RenderMethod::Refine).unwrap_err().to_string();
        assert!(
            e.contains("render.weights") && e.contains("dioptra train --config c5r"),
            "{e}"
        );
        let classical = panel(&r, RenderMethod::Views).unwrap();
        let untrained = dioptra_net::Weights::random(&arch, 1).unwrap();
        untrained.save(&dir.path().join("c5r.safetensors")).unwrap();
        let r = rig(dir.path());
        assert_eq!(panel(&r, RenderMethod::Refine).unwrap(), classical);
        let mut moved = untrained.clone();
        let last = moved.convs.last_mut().unwrap();
        for (k, v) in last.weight.iter_mut().enumerate() {
            *v = 0.02 * ((k % 7) as f32 - 3.0);
        }
        moved.save(&dir.path().join("c5r.safetensors")).unwrap();
        let r = rig(dir.path());
        assert_ne!(panel(&r, RenderMethod::Refine).unwrap(), classical);
        let tiles = r.backend_status()["refine_tiles_run"].as_f64().unwrap();
        assert!(tiles > 0.0 && tiles <= 1.0, "{tiles}");
        // Without render.weights the shipped C5R refines.
        let text = format!(
            "{EXAMPLE_SIM_RIG}\n[content]\nanimate = false\n\n[render]\nbackend = \"cpu\"\n"
        );
        let cfg = RigConfig::parse(&text).unwrap();
        let shipped = RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics).unwrap();
        assert_ne!(panel(&shipped, RenderMethod::Refine).unwrap(), classical);
    }

    /// A binocular rig on the GPU backend makes each eye's view of a one-RGB-D frame on the
    /// device, once per content frame, and renders each eye from there: the images stay in GPU
    /// memory (nothing read back), `/status` says where each stage ran, and the images are the
    /// CPU rig's (views synthesised and rendered on the host) within 1e-3.
    #[test]
    fn a_gpu_rig_makes_and_renders_each_eyes_view_on_the_device() {
        let Some((gpu, cpu, cfg)) = on_gpu_and_cpu(crate::config::EXAMPLE_SIM_BINOCULAR_RIG) else {
            return;
        };
        let views = crate::content::stereo::EyeViews::new(&cfg.eye, &cfg.display).unwrap();
        let positions = [views.position(Side::Left), views.position(Side::Right)];
        let host = |img: &FrameImage| img.to_host().unwrap().into_owned();
        for (k, (mode, method, auto)) in [
            (Mode::Varifocal, RenderMethod::Gather, false),
            (Mode::Varifocal, RenderMethod::Pyramid, false),
            (Mode::Multifocal, RenderMethod::Linear, false),
            (Mode::Varifocal, RenderMethod::Gather, true),
        ]
        .into_iter()
        .enumerate()
        {
            let frame = ContentFrame::new(k as u64 + 1, Arc::new(scene_rgbd(&gpu)));
            assert!(views.synthesises(&frame));
            let reads = gpu.backend_status()["images_read_back"].as_u64();
            let job = RenderJob {
                frame: 1,
                mode,
                method: Method(method),
                focus: Diopters(1.2),
                focus_right: Some(Diopters(0.8)),
                gaze: Some([60.0, 50.0]),
                auto,
                display_time: Timestamp::ZERO,
            };
            let made = gpu
                .render_eyes_on_device(&job, &frame, positions)
                .expect("made on the device")
                .unwrap();
            assert!(made.made, "{method:?}: the views made for the frame");
            let again = gpu
                .render_eyes_on_device(&job, &frame, positions)
                .unwrap()
                .unwrap();
            assert!(!again.made, "{method:?}: the views kept for the frame");
            assert_eq!(
                gpu.backend_status()["images_read_back"].as_u64(),
                reads,
                "{method:?}: nothing read back to render both eyes"
            );
            let ([left, right], _) = views.of(&frame).unwrap();
            let eyes = [
                (frame.for_eye(Side::Left, left), job.clone()),
                (
                    frame.for_eye(Side::Right, right),
                    RenderJob {
                        focus: Diopters(0.8),
                        ..job.clone()
                    },
                ),
            ];
            for (out, (eye_frame, eye_job)) in made.outputs.iter().zip(&eyes) {
                assert!(
                    out.images.iter().all(|i| matches!(i, FrameImage::Gpu(_))),
                    "{method:?}: left in GPU memory"
                );
                if auto {
                    assert!(out.planned.is_some());
                    continue;
                }
                let want = cpu.render(eye_job, eye_frame).unwrap();
                assert_eq!(out.images.len(), want.images.len());
                for (a, b) in out.images.iter().zip(&want.images) {
                    let (a, b) = (host(a), host(b));
                    let max = max_abs_difference(&a, &b);
                    eprintln!("{method:?} {:?}: max |gpu - cpu| = {max:e}", eye_frame.eye);
                    assert!(max < 1e-3, "{method:?} {:?}: {max}", eye_frame.eye);
                }
            }
        }
        let st = gpu.backend_status();
        let ran = |stage: &str, on: &str| stage_count(&st, stage, on);
        assert_eq!(ran("eye views", "gpu"), 4, "{st}");
        for stage in ["eye views", "gather", "pyramid", "linear"] {
            assert!(ran(stage, "gpu") > 0, "{stage}: {st}");
            assert_eq!(ran(stage, "cpu"), 0, "{stage}: {st}");
        }
        // Methods that cannot render from GPU memory (here the network) are left to the host.
        let net = RenderJob {
            frame: 1,
            mode: Mode::Varifocal,
            method: Method(RenderMethod::Network),
            focus: Diopters(1.0),
            focus_right: None,
            gaze: None,
            auto: false,
            display_time: Timestamp::ZERO,
        };
        let frame = ContentFrame::new(9, Arc::new(scene_rgbd(&gpu)));
        assert!(gpu.render_eyes_on_device(&net, &frame, positions).is_none());
    }

    /// The renderers of `rig` (its content still) on the GPU and on the CPU, and its config;
    /// `None` (skipped) without a GPU adapter unless DIOPTRA_REQUIRE_GPU is 1.
    fn on_gpu_and_cpu(rig: &str) -> Option<(RgbdRenderer, RgbdRenderer, RigConfig)> {
        let on = |backend: &str| {
            let text =
                format!("{rig}\n[content]\nanimate = false\n\n[render]\nbackend = \"{backend}\"\n");
            let cfg = RigConfig::parse(&text).unwrap();
            (
                RgbdRenderer::new(&cfg.render, &cfg.eye, &cfg.display, &cfg.optics),
                cfg,
            )
        };
        let (gpu, cfg) = on("gpu");
        match gpu {
            Ok(gpu) => Some((gpu, on("cpu").0.unwrap(), cfg)),
            Err(e) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
                eprintln!("skipped: no GPU adapter ({e})");
                None
            }
            Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1): {e}"),
        }
    }

    /// On the GPU a content frame's RGB-D is uploaded once, however many frames (foci) show
    /// it, and each is rendered from GPU memory: the CPU rig's images within 1e-3.
    #[test]
    fn a_gpu_rig_uploads_a_content_frame_once_and_renders_it_from_there() {
        let Some((gpu, cpu, _)) = on_gpu_and_cpu(EXAMPLE_SIM_RIG) else {
            return;
        };
        let frame = ContentFrame::new(1, Arc::new(scene_rgbd(&gpu)));
        let reads = gpu.backend_status()["images_read_back"].as_u64();
        let render = |r: &RgbdRenderer, focus: f32| {
            r.render_frame(
                &frame,
                Mode::Varifocal,
                Method(RenderMethod::Gather),
                Diopters(focus),
                None,
                false,
            )
            .unwrap()
            .images
            .remove(0)
        };
        let on_gpu = [render(&gpu, 0.5), render(&gpu, 2.5)];
        assert!(on_gpu.iter().all(|i| matches!(i, FrameImage::Gpu(_))));
        assert_eq!(gpu.backend_status()["images_read_back"].as_u64(), reads);
        for (image, focus) in on_gpu.iter().zip([0.5, 2.5]) {
            let (a, b) = (image.to_host().unwrap(), render(&cpu, focus));
            let b = b.to_host().unwrap();
            let max = max_abs_difference(&a, &b);
            assert!(max < 1e-3, "{focus} D: {max}");
        }
        let st = gpu.backend_status();
        let count = |stage: &str, on: &str| stage_count(&st, stage, on);
        assert_eq!(count("content upload", "host to gpu"), 1, "{st}");
        assert_eq!(count("gather", "gpu"), 2, "{st}");
        assert_eq!(count("gather", "cpu"), 0, "{st}");
    }

    /// On the GPU the light-field panel is made there and left in GPU memory: a file or stream
    /// frame's views synthesised and resampled there, the procedural scene's ray-cast views
    /// uploaded and resampled there; the CPU rig's panels within 1e-3.
    #[test]
    fn a_gpu_rigs_light_field_panel_is_made_and_kept_on_the_device() {
        let Some((gpu, cpu, cfg)) = on_gpu_and_cpu(EXAMPLE_SIM_RIG) else {
            return;
        };
        let content = crate::content::open_simulated(&cfg);
        let scene = content.poll(Timestamp::ZERO).unwrap();
        assert!(scene.scene.is_some());
        let file = ContentFrame::new(scene.number + 1, Arc::new(scene_rgbd(&gpu)));
        for (frame, stage) in [(&scene, "lenslet panel"), (&file, "light-field panel")] {
            let reads = gpu.backend_status()["images_read_back"].as_u64();
            let panel = |r: &RgbdRenderer| {
                r.render_frame(
                    frame,
                    Mode::Lightfield,
                    Method(RenderMethod::Views),
                    Diopters(1.0),
                    None,
                    false,
                )
                .unwrap()
                .images
                .remove(0)
            };
            let on_gpu = panel(&gpu);
            assert!(
                matches!(on_gpu, FrameImage::Gpu(_)),
                "{stage}: in GPU memory"
            );
            assert_eq!(gpu.backend_status()["images_read_back"].as_u64(), reads);
            let (a, b) = (on_gpu.to_host().unwrap(), panel(&cpu));
            let b = b.to_host().unwrap();
            let max = max_abs_difference(&a, &b);
            eprintln!("{stage}: max |gpu - cpu| = {max:e}");
            assert!(max < 1e-3, "{stage}: {max}");
            let st = gpu.backend_status();
            let on = |on: &str| stage_count(&st, stage, on) > 0;
            assert!(on("gpu") && !on("cpu"), "{stage}: {st}");
        }
    }

    /// How many times `/status` `render.stages` says `stage` ran `on` a backend.
    fn stage_count(status: &serde_json::Value, stage: &str, on: &str) -> u64 {
        status["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["stage"] == stage && s["on"] == on)
            .map_or(0, |s| s["count"].as_u64().unwrap())
    }

    /// The largest difference between two images' channel values.
    fn max_abs_difference(a: &RgbImage, b: &RgbImage) -> f32 {
        (0..3)
            .flat_map(|c| {
                let (a, b) = (a.channels[c].data(), b.channels[c].data());
                a.iter()
                    .zip(b)
                    .map(|(x, y)| (x - y).abs())
                    .collect::<Vec<_>>()
            })
            .fold(0.0f32, f32::max)
    }

    /// The light-field panel `r` shows for `frame` with `method`.
    fn light_field_panel(
        r: &RgbdRenderer,
        frame: &ContentFrame,
        method: RenderMethod,
    ) -> Result<RgbImage, RenderError> {
        r.render_frame(
            frame,
            Mode::Lightfield,
            Method(method),
            Diopters(1.0),
            None,
            false,
        )
        .map(|out| out.images[0].to_host().unwrap().into_owned())
    }

    /// The example rig's procedural scene as one RGB-D frame of the renderer's size.
    fn scene_rgbd(r: &RgbdRenderer) -> Rgbd {
        let scene = dioptra_sim::scene::Scene::generate(dioptra_sim::scene::Split::Test.seed(3));
        let cam = dioptra_sim::scene::Camera::new(r.eye, r.size.0, r.size.1);
        let (c, d) = dioptra_sim::scene::render_pinhole(&scene, &cam, [0.0, 0.0], 1).unwrap();
        Rgbd::new(c, d).unwrap()
    }
}
