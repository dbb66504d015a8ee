//! The rig's procedural scene (`[content] source = "scene"`), animated as the demo's is: four
//! of its objects slide side to side ([`dioptra_sim::scene::animation`]); `animate = false`
//! keeps it still.
//!
//! Frame k shows the scene as it is at k x [`SCENE_UPDATE`] of rig time, so what is on show
//! at a given rig time depends on that time alone, and a replay renders the same frame from
//! its time ([`AnimatedScene::render_at`]). A worker thread ray-casts the next frame ahead of
//! the loop. On the system clock the loop never waits for it: a frame that is not ready when
//! due is counted late and the one before stays (or the newest ready one is shown). On a
//! simulated clock the loop waits for the frame that is due (simulated time stands still
//! meanwhile), so a run shows the same frames whatever the machine's load.
//!
//! At a panel's size the ray cast can take longer than [`SCENE_UPDATE`]. On the system clock
//! the worker then casts at the size it can (from the frame after the first, which is cast
//! before the loop starts; [`smaller_cast`]: each side divided by up to
//! [`MAX_CAST_DIVISOR`], the field kept) and scales the frame up to the display's size
//! (nearest pixel, so no depth is mixed), logs it once per change, and `/status` → `content`
//! shows `cast_size` and why (`cast_reduced`). On a simulated clock it always casts at full
//! size (what a run shows does not depend on the machine).
//!
//! Nor does it cast frames faster than the rig renders them: on the system clock, when the
//! recent renders ([`Content::rendered`]) take longer than [`SCENE_UPDATE`], the worker casts
//! only every [`paced_stride`]-th update (the frames between are skipped, not late), so the
//! cores go to the renders that show its frames; the first change logged in full, later ones
//! in a summary at most a minute ([`crate::repeats`]), and `/status` →
//! `content` shows `update_ms` and why (`update_slowed`). Its frames stay at multiples of
//! [`SCENE_UPDATE`] of rig time.

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use dioptra_core::{lock, Rgbd, Timestamp};
use dioptra_render::RenderError;
use dioptra_sim::scene::animation::Animation;
use dioptra_sim::scene::{render_pinhole, Camera, Scene};
use serde::Serialize;

use super::frame::{Arrival, ContentFrame};
use super::source::Content;
use crate::display::config::Display;
use crate::optics::config::Eye;
use crate::problem::Problem;
use crate::repeats::{Note, Repeats};

/// The scene's RGB-D is re-rendered this often (rig time).
pub const SCENE_UPDATE: Duration = Duration::from_millis(50);

/// Objects that move.
const MOVERS: usize = 4;

/// Rays per pixel of the scene's pinhole render (anti-aliased edges).
const SAMPLES: usize = 2;

/// The most each side of the cast is divided by when the scene cannot keep up.
pub const MAX_CAST_DIVISOR: usize = 8;

/// The most [`SCENE_UPDATE`]s between two frames cast when the renders are slow.
pub const MAX_STRIDE: u64 = 8;

/// The renders whose median time paces the scene ([`paced_stride`]): one slow render (the
/// first, cold) does not slow it.
const RENDERS_SEEN: usize = 5;

/// Whether the loop waits for the frame that is due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pacing {
    /// The system clock: never wait; a frame not ready when due is late.
    RealTime,
    /// A simulated clock, which stands still while the loop waits: wait for the due frame.
    Simulated,
}

/// What `/status` shows under `content` for the procedural scene.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SceneStatus {
    pub source: &'static str,
    pub seed: u64,
    pub animated: bool,
    /// Frames ray-cast (the first included).
    pub rendered: u64,
    /// Frames the display took up (the first included).
    pub shown: u64,
    /// Frames not rendered by the time they were due: an older one stayed on show.
    pub late: u64,
    /// Frames that failed to render (the one before stayed), and the newest reason.
    pub failed: u64,
    pub last_error: Option<String>,
    /// The scene time of the frame on show, ms of rig time.
    pub scene_time_ms: f64,
    /// Host time (ns) the frame on show became current.
    pub since_ns: u64,
    /// How long the frame on show has been on show, ms (at the time of asking).
    pub newest_age_ms: Option<f64>,
    /// The size the scene is ray cast at, pixels (the display's unless it cannot keep up).
    pub cast_size: [usize; 2],
    /// Why `cast_size` is smaller than the display's; `None`: it is not.
    pub cast_reduced: Option<String>,
    /// Rig time between two frames cast, ms: [`SCENE_UPDATE`] unless the renders are slower.
    pub update_ms: f64,
    /// Why `update_ms` is longer than [`SCENE_UPDATE`]; `None`: it is not.
    pub update_slowed: Option<String>,
    /// The newest frame failed to render (the next one rendered clears it).
    #[serde(skip)]
    pub failing: bool,
}

struct Shared {
    state: Mutex<Worker>,
    /// Wakes the worker: a frame is wanted, or the scene is dropped.
    wake: Condvar,
    /// Notified after each render, and when the worker ends.
    rendered: Condvar,
}

#[derive(Default)]
struct Worker {
    /// The scene time asked for and not started yet.
    want: Option<Timestamp>,
    /// The scene time being rendered.
    busy: Option<Timestamp>,
    /// The newest render: its scene time and frame (or why it failed).
    ready: Option<(Timestamp, Result<SceneViews, String>)>,
    rendered: u64,
    /// The cast's size and why it is smaller than the camera's ([`smaller_cast`]).
    cast_size: [usize; 2],
    cast_reduced: Option<String>,
    /// Updates between two frames cast ([`paced_stride`]; 0 counts as 1), the recent render
    /// times it follows, and why it is more than 1.
    stride: u64,
    renders: std::collections::VecDeque<Duration>,
    update_slowed: Option<String>,
    stop: bool,
    /// The worker thread has ended (stopped, or its render panicked).
    ended: bool,
}

/// The frame on show and the counters the loop keeps.
struct OnShow {
    time: Timestamp,
    frame: SceneViews,
    /// The due time last counted late (each counts once).
    late_at: Option<Timestamp>,
    status: SceneStatus,
    since: Instant,
}

/// The procedural scene and its render worker.
pub struct AnimatedScene {
    base: Scene,
    animation: Animation,
    cam: Camera,
    pacing: Pacing,
    shared: Arc<Shared>,
    on_show: Mutex<OnShow>,
    polled: Mutex<Polled>,
    /// The changes of the scene's pace, for the log.
    pace_log: Mutex<Repeats>,
}

/// What the loop has taken up ([`Content::poll`]).
#[derive(Default)]
struct Polled {
    /// Frames handed to the loop (the first included).
    given: u64,
    /// The latest poll.
    at: Option<Timestamp>,
}

/// The camera the rig's scene is seen through: `eye` over the display's pixels.
pub fn camera(eye: &Eye, display: &Display) -> Result<Camera, RenderError> {
    let model = eye.model(display.width).validated()?;
    Ok(Camera::new(
        model,
        display.width as usize,
        display.height as usize,
    ))
}

impl std::fmt::Debug for AnimatedScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AnimatedScene")
            .field("movers", &self.animation.len())
            .field("pacing", &self.pacing)
            .finish_non_exhaustive()
    }
}

/// One frame of the scene: the cyclopean view and, on a stereo layout, each eye's.
#[derive(Clone)]
struct SceneViews {
    centre: Arc<Rgbd>,
    eyes: Option<[Arc<Rgbd>; 2]>,
}

/// The scene seen from `x` metres right of the cyclopean eye, looking straight ahead.
fn cast(scene: &Scene, cam: &Camera, x: f32) -> Result<Rgbd, RenderError> {
    let (color, depth) = render_pinhole(scene, cam, [x, 0.0], SAMPLES)?;
    Ok(Rgbd::new(color, depth)?)
}

fn render_centre(
    base: &Scene,
    a: &Animation,
    cam: &Camera,
    t: Timestamp,
) -> Result<Rgbd, RenderError> {
    cast(&a.at(base, t.as_secs_f64()), cam, 0.0)
}

/// The frame of scene time `t`: with `half_ipd_m`, each eye's view too (parallel axes, the
/// eyes `2 x half_ipd_m` apart), ray cast here on the scene's worker, not on the render path.
fn render(
    base: &Scene,
    a: &Animation,
    cam: &Camera,
    t: Timestamp,
    half_ipd_m: Option<f32>,
) -> Result<SceneViews, RenderError> {
    render_cast(base, a, cam, cam, t, half_ipd_m)
}

/// [`render`], cast through `cast_cam` (`cam` or a smaller one over the same field) and
/// scaled up to `cam`'s size.
fn render_cast(
    base: &Scene,
    a: &Animation,
    cam: &Camera,
    cast_cam: &Camera,
    t: Timestamp,
    half_ipd_m: Option<f32>,
) -> Result<SceneViews, RenderError> {
    let scene = a.at(base, t.as_secs_f64());
    let to_size = |v: Arc<Rgbd>| -> Result<Arc<Rgbd>, RenderError> {
        if v.width() == cam.width && v.height() == cam.height {
            return Ok(v);
        }
        Ok(Arc::new(nearest_upscale(&v, cam.width, cam.height)?))
    };
    let centre = to_size(Arc::new(cast(&scene, cast_cam, 0.0)?))?;
    let eyes = match half_ipd_m {
        None => None,
        Some(h) => {
            let [l, r] = cast_eyes(&scene, cast_cam, h)?;
            Some([to_size(l)?, to_size(r)?])
        }
    };
    Ok(SceneViews { centre, eyes })
}

/// `v` at `width` x `height`, each pixel the nearest of `v`'s (colour and depth alike, so no
/// depth is mixed across an edge).
fn nearest_upscale(v: &Rgbd, width: usize, height: usize) -> Result<Rgbd, RenderError> {
    use dioptra_core::{DepthMap, Plane, RgbImage};
    let (w, h) = (v.width(), v.height());
    let xs: Vec<usize> = (0..width).map(|x| (x * w / width).min(w - 1)).collect();
    let scale = |p: &Plane| -> Result<Plane, RenderError> {
        let mut out = Vec::with_capacity(width * height);
        let mut above = None;
        for y in 0..height {
            let src = (y * h / height).min(h - 1);
            if above == Some(src) {
                // The row above came from the same row: copy it rather than gather again.
                out.extend_from_within(out.len() - width..);
            } else {
                let row = p.row(src);
                out.extend(xs.iter().map(|&x| row[x]));
                above = Some(src);
            }
        }
        Ok(Plane::from_vec(width, height, out)?)
    };
    let [r, g, b] = &v.color.channels;
    let color = RgbImage::from_planes(scale(r)?, scale(g)?, scale(b)?)?;
    let depth = DepthMap::from_diopters(scale(v.depth.plane())?)?;
    Ok(Rgbd::new(color, depth)?)
}

/// The divisor of each side after a cast at `divisor` took `took`: the smallest that
/// predicts (cost in proportion to pixels) a cast within 80 % of [`SCENE_UPDATE`], never
/// smaller than `divisor` (a scene that once fell behind is not enlarged again, so its frames
/// do not flip between sizes), at most [`MAX_CAST_DIVISOR`].
pub fn smaller_cast(divisor: usize, took: Duration) -> usize {
    let target = 0.8 * SCENE_UPDATE.as_secs_f64();
    let ratio = took.as_secs_f64() / target;
    if ratio <= 1.0 {
        return divisor;
    }
    ((divisor as f64 * ratio.sqrt()).ceil() as usize).clamp(divisor, MAX_CAST_DIVISOR)
}

/// The left and the right eye's views of `scene`, the eyes `2 x half_ipd_m` apart with
/// parallel axes, cast side by side: the animated scene's on its worker, and
/// `stereo::EyeViews`'s for a frame that brings its scene without them.
pub fn cast_eyes(
    scene: &Scene,
    cam: &Camera,
    half_ipd_m: f32,
) -> Result<[Arc<Rgbd>; 2], RenderError> {
    let (l, r) = rayon::join(
        || cast(scene, cam, -half_ipd_m),
        || cast(scene, cam, half_ipd_m),
    );
    Ok([Arc::new(l?), Arc::new(r?)])
}

/// The scene time of the frame due at `now`: the last multiple of [`SCENE_UPDATE`].
fn due_at(now: Timestamp) -> Timestamp {
    let step = SCENE_UPDATE.as_nanos() as u64;
    Timestamp(now.0 / step * step)
}

/// Ends the worker's state when its thread ends, however it ends, so that a loop waiting for
/// a frame is not left waiting.
struct EndGuard(Arc<Shared>);

impl Drop for EndGuard {
    fn drop(&mut self) {
        let mut w = lock(&self.0.state);
        w.ended = true;
        w.busy = None;
        self.0.rendered.notify_all();
    }
}

impl Worker {
    /// Rig time between two frames cast.
    fn step(&self) -> Duration {
        SCENE_UPDATE * self.stride.max(1) as u32
    }
}

/// The updates between two frames cast (`stride` now) when the recent renders' median time is
/// `median`: that many [`SCENE_UPDATE`]s rounded up, at most [`MAX_STRIDE`]. It grows as soon
/// as the median needs it and shrinks only once the median would fit 80 % of the shorter
/// stride, so a render time near a multiple of the update does not make it flip.
pub fn paced_stride(stride: u64, median: Duration) -> u64 {
    let stride = stride.max(1);
    let updates = |share: f64| {
        let n = median.as_secs_f64() / (share * SCENE_UPDATE.as_secs_f64());
        (n.ceil() as u64).clamp(1, MAX_STRIDE)
    };
    let wanted = updates(1.0);
    if wanted > stride {
        wanted
    } else {
        stride.min(updates(0.8))
    }
}

impl AnimatedScene {
    /// The scene of `seed` seen through `cam`, rendered at scene time 0; with `animate`, four
    /// of its objects (not the floor plate, its first) move and a worker renders ahead.
    pub fn start(
        seed: u64,
        cam: Camera,
        animate: bool,
        pacing: Pacing,
    ) -> Result<AnimatedScene, RenderError> {
        AnimatedScene::start_with_eyes(seed, cam, animate, pacing, None)
    }

    /// [`AnimatedScene::start`]; with `half_ipd_m` (a stereo layout) each frame carries each
    /// eye's view as well, the eyes `2 x half_ipd_m` apart.
    pub fn start_with_eyes(
        seed: u64,
        cam: Camera,
        animate: bool,
        pacing: Pacing,
        half_ipd_m: Option<f32>,
    ) -> Result<AnimatedScene, RenderError> {
        let base = Scene::generate(seed);
        let animation = if animate {
            let floor = base.objects.first().copied();
            Animation::pick(&base, MOVERS, |o| Some(*o) != floor)
        } else {
            Animation::default()
        };
        let started = Instant::now();
        let first = render(&base, &animation, &cam, Timestamp::ZERO, half_ipd_m)?;
        let mut worker = Worker {
            rendered: 1,
            cast_size: [cam.width, cam.height],
            ended: animation.is_empty(),
            ..Worker::default()
        };
        // On the system clock the worker starts at the size the first frame's cast says it
        // keeps up at, not with another full-size cast that the first renders wait behind.
        let divisor = match pacing {
            Pacing::RealTime if !animation.is_empty() => smaller_cast(1, started.elapsed()),
            _ => 1,
        };
        if divisor > 1 {
            note_reduced(&mut worker, &cam, divisor, started.elapsed());
        }
        let shared = Arc::new(Shared {
            state: Mutex::new(worker),
            wake: Condvar::new(),
            rendered: Condvar::new(),
        });
        if !animation.is_empty() {
            let (b, a, s) = (base.clone(), animation.clone(), shared.clone());
            std::thread::Builder::new()
                .name("dioptra-scene".into())
                .spawn(move || render_ahead(&b, &a, &cam, half_ipd_m, pacing, divisor, s))
                .map_err(|e| {
                    RenderError::Input(dioptra_core::InputError::InvalidValue(format!(
                        "cannot start the scene's render thread: {e}"
                    )))
                })?;
        }
        let status = SceneStatus {
            source: "scene",
            seed,
            animated: !animation.is_empty(),
            shown: 1,
            ..SceneStatus::default()
        };
        Ok(AnimatedScene {
            on_show: Mutex::new(OnShow {
                time: Timestamp::ZERO,
                frame: first,
                late_at: None,
                status,
                since: Instant::now(),
            }),
            base,
            animation,
            cam,
            pacing,
            shared,
            polled: Mutex::default(),
            pace_log: Mutex::new(Repeats::new("the procedural scene's pace changed")),
        })
    }

    /// The frame on show and its scene time.
    pub fn current(&self) -> (Arc<Rgbd>, Timestamp) {
        let on = lock(&self.on_show);
        (on.frame.centre.clone(), on.time)
    }

    /// The scene as it is at scene time `t` (what a frame of that time shows).
    pub fn scene_at(&self, t: Timestamp) -> Scene {
        self.animation.at(&self.base, t.as_secs_f64())
    }

    /// The frame of scene time `t`, rendered now on the caller's thread (a replay's depth).
    pub fn render_at(&self, t: Timestamp) -> Result<Rgbd, RenderError> {
        render_centre(&self.base, &self.animation, &self.cam, t)
    }

    /// The frame due at rig time `now` when it is newer than the one on show: the frame, and
    /// its scene time as its arrival (`ready`: `now`). Asks the worker for the frame after it.
    pub fn frame_at(&self, now: Timestamp) -> Option<(Arc<Rgbd>, Arrival)> {
        self.views_at(now).map(|(v, a)| (v.centre, a))
    }

    /// [`AnimatedScene::frame_at`], with each eye's view on a stereo layout.
    fn views_at(&self, now: Timestamp) -> Option<(SceneViews, Arrival)> {
        if self.animation.is_empty() {
            return None;
        }
        let due = due_at(now);
        let mut on = lock(&self.on_show);
        let mut w = lock(&self.shared.state);
        // On the system clock the updates between two frames cast (a stride over 1) are
        // skipped: not due, so not late.
        let step = match self.pacing {
            Pacing::RealTime => w.step(),
            Pacing::Simulated => SCENE_UPDATE,
        };
        if on.time + step > due {
            self.ask(&mut w, on.time + step);
            return None;
        }
        loop {
            if let Some((t, _)) = &w.ready {
                let t = *t;
                if t > due {
                    // Rendered ahead: not shown before its time.
                    return None;
                }
                // A frame newer than the one on show and not ahead of its time: the due one,
                // or (on the system clock) the newest there is.
                let take =
                    t > on.time && (t == due || (t < due && self.pacing == Pacing::RealTime));
                if take {
                    let (_, r) = w.ready.take()?;
                    if t < due {
                        count_late(&mut on, due);
                    }
                    self.ask(&mut w, due + step);
                    return self.take_up(&mut on, t, r, now);
                }
                if t <= on.time || t < due {
                    // Older than the one on show, or (waiting for the due one) stale.
                    w.ready = None;
                }
            }
            if w.ended {
                // No worker: the frame on show stays.
                count_late(&mut on, due);
                return None;
            }
            if w.busy.is_none() && w.ready.is_none() {
                w.want = Some(due);
                self.shared.wake.notify_one();
            }
            if self.pacing == Pacing::RealTime {
                count_late(&mut on, due);
                return None;
            }
            w = self
                .shared
                .rendered
                .wait(w)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }

    /// Asks the worker for the frame of scene time `t` when it has nothing to do.
    fn ask(&self, w: &mut MutexGuard<'_, Worker>, t: Timestamp) {
        if w.want.is_none() && w.busy.is_none() && w.ready.is_none() && !w.ended {
            w.want = Some(t);
            self.shared.wake.notify_one();
        }
    }

    fn take_up(
        &self,
        on: &mut OnShow,
        t: Timestamp,
        r: Result<SceneViews, String>,
        now: Timestamp,
    ) -> Option<(SceneViews, Arrival)> {
        // Not tried again either way: the next is due one update later.
        on.time = t;
        match r {
            Ok(frame) => {
                on.frame = frame.clone();
                on.since = Instant::now();
                on.status.shown += 1;
                on.status.since_ns = now.0;
                on.status.failing = false;
                Some((
                    frame,
                    Arrival {
                        arrived: t,
                        ready: now,
                    },
                ))
            }
            Err(e) => {
                if on.status.failed == 0 {
                    tracing::warn!(error = %e, "the scene did not render; the frame before stays");
                }
                on.status.failed += 1;
                on.status.last_error = Some(e);
                on.status.failing = true;
                None
            }
        }
    }

    pub fn status(&self) -> SceneStatus {
        let on = lock(&self.on_show);
        let mut st = on.status.clone();
        let w = lock(&self.shared.state);
        st.rendered = w.rendered;
        st.cast_size = w.cast_size;
        st.cast_reduced = w.cast_reduced.clone();
        st.update_ms = w.step().as_secs_f64() * 1e3;
        st.update_slowed = w.update_slowed.clone();
        drop(w);
        st.scene_time_ms = on.time.0 as f64 / 1e6;
        st.newest_age_ms = Some(on.since.elapsed().as_secs_f64() * 1e3);
        st
    }

    /// Blocks until the worker has a frame ready or has ended (tests).
    #[cfg(test)]
    fn wait_rendered(&self) {
        let mut w = lock(&self.shared.state);
        while w.ready.is_none() && !w.ended {
            w = self
                .shared
                .rendered
                .wait(w)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

impl Content for AnimatedScene {
    fn poll(&self, now: Timestamp) -> Option<ContentFrame> {
        let first = {
            let mut p = lock(&self.polled);
            p.at = Some(now);
            p.given == 0
        };
        let (views, arrival) = match self.views_at(now) {
            Some((frame, arrival)) => (frame, Some(arrival)),
            None if first => (lock(&self.on_show).frame.clone(), None),
            None => return None,
        };
        let time = lock(&self.on_show).time;
        let number = {
            let mut p = lock(&self.polled);
            p.given += 1;
            p.given
        };
        Some(ContentFrame {
            number,
            rgbd: views.centre,
            eyes: views.eyes,
            eye: None,
            arrival,
            scene_time: Some(time),
            scene: Some(Arc::new(self.scene_at(time))),
            views: None,
        })
    }
    fn rendered(&self, took: Duration, now: Timestamp) {
        if self.pacing == Pacing::Simulated || self.animation.is_empty() {
            return;
        }
        let mut w = lock(&self.shared.state);
        if w.renders.len() == RENDERS_SEEN {
            w.renders.pop_front();
        }
        w.renders.push_back(took);
        if w.renders.len() < RENDERS_SEEN {
            return;
        }
        let mut sorted: Vec<Duration> = w.renders.iter().copied().collect();
        sorted.sort_unstable();
        let median = sorted[sorted.len() / 2];
        let stride = paced_stride(w.stride, median);
        if stride == w.stride.max(1) {
            return;
        }
        w.stride = stride;
        let median_ms = median.as_secs_f64() * 1e3;
        let update_ms = w.step().as_secs_f64() * 1e3;
        let message = if stride == 1 {
            w.update_slowed = None;
            format!("the procedural scene is cast every {update_ms:.0} ms again: the renders take {median_ms:.0} ms")
        } else {
            let why = format!(
                "the renders take {median_ms:.0} ms (the median of the newest {RENDERS_SEEN}), longer than the scene's {:.0} ms update: it is cast every {update_ms:.0} ms (the frames between skipped), so the cores go to the renders; a faster method or backend (method, render.backend), foveation (render.foveation) or a smaller panel (display.width, display.height) brings its rate back",
                SCENE_UPDATE.as_secs_f64() * 1e3
            );
            w.update_slowed = Some(why.clone());
            why
        };
        drop(w);
        match lock(&self.pace_log).note("pace", &message, now) {
            Note::First => tracing::warn!("{message}"),
            Note::Summary(summary) => tracing::warn!("{summary}"),
            Note::Counted => {}
        }
    }
    fn next_due(&self) -> Option<Timestamp> {
        // The update after the latest poll's: a frame late on the system clock is taken up
        // by the polls before the loop's other steps, not by waking again at once.
        let at = lock(&self.polled).at?;
        (!self.animation.is_empty()).then(|| due_at(at) + SCENE_UPDATE)
    }
    fn status(&self) -> serde_json::Value {
        serde_json::to_value(AnimatedScene::status(self)).unwrap_or_default()
    }
    fn problems(&self) -> Vec<Problem> {
        let st = lock(&self.on_show).status.clone();
        match (st.failing, st.last_error) {
            (true, Some(e)) => vec![Problem::new(
                "content",
                "content.source",
                format!("the procedural scene's newest frame did not render (the one before stays): {e}"),
            )],
            _ => Vec::new(),
        }
    }
}

fn count_late(on: &mut OnShow, due: Timestamp) {
    if on.late_at != Some(due) {
        on.late_at = Some(due);
        on.status.late += 1;
    }
}

impl Drop for AnimatedScene {
    fn drop(&mut self) {
        lock(&self.shared.state).stop = true;
        self.shared.wake.notify_all();
    }
}

/// The camera of a cast at `divisor`: `cam`'s field, each side divided by it.
fn cast_camera(cam: &Camera, divisor: usize) -> Camera {
    Camera::new(
        cam.eye,
        (cam.width / divisor).max(1),
        (cam.height / divisor).max(1),
    )
}

/// Notes (for `/status`) and logs that the scene is cast at `divisor` because a frame took
/// `took`.
fn note_reduced(w: &mut Worker, cam: &Camera, divisor: usize, took: Duration) {
    let cast_cam = cast_camera(cam, divisor);
    let why = format!(
        "the procedural scene cannot keep up at the display's {} x {} (a frame took {:.0} ms against {:.0} ms): it is ray cast at {} x {} and scaled up; a smaller panel (display.width, display.height) or content from files or a stream keeps full size",
        cam.width,
        cam.height,
        took.as_secs_f64() * 1e3,
        SCENE_UPDATE.as_secs_f64() * 1e3,
        cast_cam.width,
        cast_cam.height
    );
    tracing::warn!("{why}");
    w.cast_size = [cast_cam.width, cast_cam.height];
    w.cast_reduced = Some(why);
}

/// The worker: casts each frame asked for, at `divisor` (then smaller while it cannot keep up,
/// on the system clock).
fn render_ahead(
    base: &Scene,
    a: &Animation,
    cam: &Camera,
    half_ipd_m: Option<f32>,
    pacing: Pacing,
    mut divisor: usize,
    shared: Arc<Shared>,
) {
    let _end = EndGuard(shared.clone());
    let mut cast_cam = cast_camera(cam, divisor);
    loop {
        let t = {
            let mut w = lock(&shared.state);
            loop {
                if w.stop {
                    return;
                }
                if let Some(t) = w.want.take() {
                    w.busy = Some(t);
                    break t;
                }
                w = shared
                    .wake
                    .wait(w)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
            }
        };
        let started = Instant::now();
        let r = render_cast(base, a, cam, &cast_cam, t, half_ipd_m).map_err(|e| e.to_string());
        let took = started.elapsed();
        let mut w = lock(&shared.state);
        if pacing == Pacing::RealTime && r.is_ok() {
            let next = smaller_cast(divisor, took);
            if next != divisor {
                divisor = next;
                cast_cam = cast_camera(cam, divisor);
                note_reduced(&mut w, cam, divisor, took);
            }
        }
        w.busy = None;
        w.rendered += 1;
        w.ready = Some((t, r));
        shared.rendered.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each output pixel is the input's at `(x * w / width, y * h / height)`, at a scale
    /// that is not a whole number and one that shrinks, colour and depth alike.
    #[test]
    fn the_nearest_upscale_takes_each_pixel_from_the_nearest_input_pixel() {
        use dioptra_core::{DepthMap, Plane, RgbImage};
        let (w, h) = (7usize, 5usize);
        let plane = |k: f32| {
            Plane::from_vec(w, h, (0..w * h).map(|i| k + i as f32 * 0.01).collect()).unwrap()
        };
        let v = Rgbd::new(
            RgbImage::from_planes(plane(0.0), plane(0.1), plane(0.2)).unwrap(),
            DepthMap::from_diopters(plane(1.0)).unwrap(),
        )
        .unwrap();
        for (width, height) in [(23usize, 17usize), (3, 2), (7, 5)] {
            let up = nearest_upscale(&v, width, height).unwrap();
            assert_eq!((up.width(), up.height()), (width, height));
            for y in 0..height {
                for x in 0..width {
                    let (sx, sy) = (x * w / width, y * h / height);
                    for c in 0..3 {
                        assert_eq!(
                            up.color.channels[c].row(y)[x],
                            v.color.channels[c].row(sy)[sx]
                        );
                    }
                    assert_eq!(up.depth.plane().row(y)[x], v.depth.plane().row(sy)[sx]);
                }
            }
        }
    }

    fn scene(pacing: Pacing) -> AnimatedScene {
        let eye = dioptra_core::EyeModel {
            width_px: 48,
            ..Default::default()
        };
        AnimatedScene::start(1_000_001, Camera::new(eye, 48, 48), true, pacing).unwrap()
    }

    fn ms(m: u64) -> Timestamp {
        Timestamp(m * 1_000_000)
    }

    #[test]
    fn on_simulated_time_each_due_frame_is_shown_at_its_time() {
        let a = scene(Pacing::Simulated);
        let (f0, t0) = a.current();
        assert_eq!(t0, ms(0));
        // Within the first update the first frame stays; the worker renders the next.
        assert!(a.frame_at(ms(10)).is_none());
        let (f1, arrival) = a.frame_at(ms(55)).expect("the frame of 50 ms");
        assert_eq!((arrival.arrived, arrival.ready), (ms(50), ms(55)));
        assert_ne!(f0.color, f1.color, "the objects moved");
        assert_eq!(*f1, a.render_at(ms(50)).unwrap(), "what a replay renders");
        // A call that skips updates waits for the frame due then, not the one rendered ahead.
        let (f4, arrival) = a.frame_at(ms(230)).expect("the frame of 200 ms");
        assert_eq!(arrival.arrived, ms(200));
        assert_eq!(*f4, a.render_at(ms(200)).unwrap());
        assert_eq!(a.current().1, ms(200));
        let st = a.status();
        assert_eq!((st.shown, st.late, st.failed), (3, 0, 0), "{st:?}");
        assert!(st.animated && st.rendered >= 3, "{st:?}");
    }

    #[test]
    fn on_the_system_clock_a_frame_not_ready_is_late_and_the_one_before_stays() {
        let a = scene(Pacing::RealTime);
        // Nothing was asked for yet: the frame of 50 ms is late, the first stays.
        assert!(a.frame_at(ms(60)).is_none());
        assert_eq!(a.current().1, ms(0));
        assert_eq!(a.status().late, 1);
        a.wait_rendered();
        // Taken up once rendered, though due earlier (counted late once).
        let (_, arrival) = a.frame_at(ms(80)).expect("the frame of 50 ms");
        assert_eq!(arrival.arrived, ms(50));
        assert_eq!(a.status().late, 1);
        // The next is rendered ahead and shown on time.
        a.wait_rendered();
        let (_, arrival) = a.frame_at(ms(100)).expect("the frame of 100 ms");
        assert_eq!(arrival.arrived, ms(100));
        // A newer frame than the one due is never shown early.
        a.wait_rendered();
        assert!(a.frame_at(ms(120)).is_none());
        assert_eq!(a.status().late, 1);
    }

    #[test]
    fn the_stride_follows_the_renders_median_time_without_flipping() {
        let ms = Duration::from_millis;
        // Renders within an update: every update is cast.
        assert_eq!(paced_stride(1, ms(30)), 1);
        assert_eq!(paced_stride(0, ms(50)), 1);
        // Slower: as many updates as the median takes, rounded up, at most MAX_STRIDE.
        assert_eq!(paced_stride(1, ms(51)), 2);
        assert_eq!(paced_stride(1, ms(140)), 3);
        assert_eq!(paced_stride(2, ms(150)), 3);
        assert_eq!(paced_stride(1, ms(5000)), MAX_STRIDE);
        // Shorter only once the median fits 80 % of the shorter stride.
        assert_eq!(paced_stride(3, ms(110)), 3, "110 ms > 80 % of 2 updates");
        assert_eq!(paced_stride(3, ms(80)), 2);
        assert_eq!(paced_stride(3, ms(10)), 1);
    }

    #[test]
    fn on_the_system_clock_slow_renders_slow_the_scene_and_the_frames_skipped_are_not_late() {
        let a = scene(Pacing::RealTime);
        // A cold first render, then renders of 140 ms: paced by their median, 3 updates.
        a.rendered(Duration::from_secs(2), ms(0));
        assert_eq!(
            a.status().update_ms,
            50.0,
            "not paced before {RENDERS_SEEN} renders"
        );
        for _ in 1..RENDERS_SEEN {
            a.rendered(Duration::from_millis(140), ms(0));
        }
        let st = a.status();
        assert_eq!(st.update_ms, 150.0, "{st:?}");
        let why = st.update_slowed.expect("why the scene is slowed");
        assert!(
            why.contains("140 ms") && why.contains("every 150 ms"),
            "{why}"
        );
        // The frame after the first is the one of 150 ms; the polls before it are not late.
        assert!(a.frame_at(ms(10)).is_none());
        a.wait_rendered();
        assert!(a.frame_at(ms(60)).is_none());
        assert!(a.frame_at(ms(120)).is_none());
        let (_, arrival) = a.frame_at(ms(155)).expect("the frame of 150 ms");
        assert_eq!(arrival.arrived, ms(150));
        a.wait_rendered();
        assert!(a.frame_at(ms(250)).is_none());
        let (f, arrival) = a.frame_at(ms(300)).expect("the frame of 300 ms");
        assert_eq!(arrival.arrived, ms(300));
        assert_eq!(
            *f,
            a.render_at(ms(300)).unwrap(),
            "frames stay those of their time"
        );
        let st = a.status();
        assert_eq!((st.shown, st.late), (3, 0), "{st:?}");
        // Fast renders again: every update is cast.
        for _ in 0..RENDERS_SEEN {
            a.rendered(Duration::from_millis(20), ms(300));
        }
        let st = a.status();
        assert_eq!((st.update_ms, st.update_slowed), (50.0, None));
    }

    #[test]
    fn on_simulated_time_slow_renders_do_not_slow_the_scene() {
        let a = scene(Pacing::Simulated);
        for _ in 0..RENDERS_SEEN {
            a.rendered(Duration::from_millis(400), ms(0));
        }
        assert_eq!(a.status().update_ms, 50.0);
        let (_, arrival) = a.frame_at(ms(50)).expect("the frame of 50 ms");
        assert_eq!(arrival.arrived, ms(50));
    }

    #[test]
    fn a_still_scene_never_changes() {
        let eye = dioptra_core::EyeModel {
            width_px: 32,
            ..Default::default()
        };
        let a = AnimatedScene::start(
            1_000_001,
            Camera::new(eye, 32, 32),
            false,
            Pacing::Simulated,
        )
        .unwrap();
        assert!(a.frame_at(ms(500)).is_none());
        assert_eq!(*a.current().0, a.render_at(ms(500)).unwrap());
        let st = a.status();
        assert!(!st.animated && st.rendered == 1 && st.late == 0, "{st:?}");
    }
}
