use std::sync::Mutex;

use super::*;
use crate::config::RigConfig;
use crate::content::stream::{ColorFormat, DepthKind, FrameDesc};
use crate::render::RenderOutput;
use crate::{Rig, RigSetup};

#[derive(Debug, Clone, Copy, PartialEq)]
enum Seen {
    /// A content frame reached the scheduler: its number and its depth (one value).
    Content(u64, f32),
    /// The scheduler asked for a render.
    Request(u64),
    /// A render job ran on a content frame.
    Rendered(u64, u64),
}

type Log = Arc<Mutex<Vec<(Timestamp, Seen)>>>;

struct Watch(Log);

impl LoopHook for Watch {
    fn content(&mut self, now: Timestamp, frame: &ContentFrame) {
        let d = frame.rgbd.depth.data()[0];
        self.0
            .lock()
            .unwrap()
            .push((now, Seen::Content(frame.number, d)));
    }
    fn command(&mut self, now: Timestamp, cmd: &Command) {
        if let Command::RenderFrame(r) = cmd {
            self.0.lock().unwrap().push((now, Seen::Request(r.frame.0)));
        }
    }
}

/// 1 x 1 images in 2 ms of simulated time, noting which content frame each job showed.
struct Tiny(Log, Arc<dyn crate::Clock>);

impl Renderer for Tiny {
    fn render(
        &self,
        job: &RenderJob,
        content: &ContentFrame,
    ) -> Result<RenderOutput, dioptra_render::RenderError> {
        let now = self.1.now();
        let seen = Seen::Rendered(job.frame, content.number);
        self.0.lock().unwrap().push((now, seen));
        Ok(RenderOutput {
            images: vec![dioptra_core::RgbImage::new(1, 1, [0.5; 3]).into()],
            planned: None,
            cost: Some(Duration::from_millis(2)),
        })
    }
}

/// Notes each eye's render: the eye and its focus.
type EyeFoci = Arc<Mutex<Vec<(Option<Side>, Diopters)>>>;
struct PerEye(EyeFoci);

impl Renderer for PerEye {
    fn render(
        &self,
        job: &RenderJob,
        content: &ContentFrame,
    ) -> Result<RenderOutput, dioptra_render::RenderError> {
        self.0.lock().unwrap().push((content.eye, job.focus));
        // The eye's image says which eye it is: 0.25 left, 0.75 right.
        let v = if content.eye == Some(Side::Right) {
            0.75
        } else {
            0.25
        };
        Ok(RenderOutput {
            images: vec![dioptra_core::RgbImage::new(2, 2, [v; 3]).into()],
            planned: None,
            cost: Some(Duration::from_millis(2)),
        })
    }
}

/// Notes each render request's focus per eye (the right's: the left's with one lens).
struct Requests(Arc<Mutex<Vec<(Diopters, Diopters)>>>);

impl LoopHook for Requests {
    fn command(&mut self, _now: Timestamp, cmd: &Command) {
        if let Command::RenderFrame(r) = cmd {
            if let Some(f) = r.focus {
                self.0.lock().unwrap().push((f, r.focus_right.unwrap_or(f)));
            }
        }
    }
}

/// Keeps each frame it is shown.
struct Keep(Arc<Mutex<Vec<Frame>>>);

impl DisplaySink for Keep {
    fn present(
        &mut self,
        frame: &Frame,
        now: Timestamp,
    ) -> Result<Timestamp, crate::display::DisplayError> {
        self.0.lock().unwrap().push(frame.clone());
        Ok(now)
    }
    fn present_layer(
        &mut self,
        frame: &Frame,
        _: usize,
        start: Timestamp,
    ) -> Result<Timestamp, crate::display::DisplayError> {
        self.present(frame, start)
    }
    fn shown(&self) -> u64 {
        self.0.lock().unwrap().len() as u64
    }
    fn describe(&self) -> String {
        "kept".into()
    }
    fn status(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

/// On a stereo layout each eye is rendered from its own view of the content at its own
/// lens's focus, and the display is handed both eyes' images.
#[tokio::test(start_paused = true)]
async fn on_a_stereo_layout_each_eye_is_rendered_from_its_view_at_its_lenss_focus() {
    // The right lens settles four times slower than the left: while they move, the
    // scheduler predicts different powers, so the eyes' foci differ.
    let text = crate::config::EXAMPLE_SIM_BINOCULAR_RIG;
    let i = text.find("[devices.lens.right]").unwrap();
    let text = text[..i].to_string()
        + &text[i..].replacen("sim_settle_ms = 15.0", "sim_settle_ms = 60.0", 1)
        + "\n[content]\nanimate = false\n";
    let cfg = RigConfig::parse(&text).unwrap();
    assert!(cfg.display.stereo());
    let clock: Arc<dyn crate::Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
    let (renders, frames, requests) = (Arc::default(), Arc::default(), Arc::default());
    let mut setup = RigSetup::new(cfg);
    setup.simulated_time = true;
    setup.clock = Some(clock.clone());
    setup.renderer = Some(Arc::new(PerEye(Arc::clone(&renders))));
    setup.sink = Some(Box::new(Keep(Arc::clone(&frames))));
    setup.hooks.push(Box::new(Requests(Arc::clone(&requests))));
    let rig = Rig::start(setup).await.unwrap();
    tokio::time::sleep(Duration::from_millis(2500)).await;
    let views = rig.state().status_json()["eye_views"].clone();
    assert_eq!(views["source"], "scene-ray-cast", "{views}");
    assert_eq!(
        (views["made"].as_u64(), views["failed"].as_u64()),
        (Some(1), Some(0)),
        "{views}"
    );
    rig.state().cancel.cancel();
    assert!(rig.wait().await.ok());
    let renders = renders.lock().unwrap().clone();
    assert!(renders.len() >= 10, "{renders:?}");
    // Left then right, frame after frame, from each eye's own view (never the cyclopean).
    for pair in renders.chunks(2) {
        assert_eq!(
            (pair[0].0, pair[1].0),
            (Some(Side::Left), Some(Side::Right)),
            "{renders:?}"
        );
    }
    // Each eye at the scheduler's focus for it: the left at the request's focus, the right
    // at its own lens's.
    let requests: Vec<(Diopters, Diopters)> = requests.lock().unwrap().clone();
    let rendered: Vec<(Diopters, Diopters)> = renders.chunks(2).map(|p| (p[0].1, p[1].1)).collect();
    assert_eq!(rendered, requests[..rendered.len()]);
    let differ = rendered
        .iter()
        .filter(|(l, r)| (l.0 - r.0).abs() > 0.05)
        .count();
    assert!(differ > 0, "{rendered:?}");
    let frames = frames.lock().unwrap().clone();
    assert!(!frames.is_empty());
    for f in &frames {
        let right = f.right.as_ref().expect("the right eye's images");
        let px = |img: &crate::render::FrameImage| img.to_host().unwrap().pixel(0, 0).unwrap()[0];
        assert_eq!((px(&f.layers[0]), px(&right[0])), (0.25, 0.75));
    }
}

/// A frame an application pushes is an event of its own: its depth reaches the scheduler
/// when it arrives, before the next render request, and that request's job renders it.
#[tokio::test(start_paused = true)]
async fn a_pushed_frames_depth_reaches_the_scheduler_before_the_next_render_request() {
    let text = crate::config::EXAMPLE_SIM_RIG.to_string()
        + "\n[content]\nsource = \"stream\"\nring = \"none\"\n";
    let cfg = RigConfig::parse(&text).unwrap();
    let content = crate::content::open_simulated(&cfg);
    let log = Log::default();
    let clock: Arc<dyn crate::Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
    let mut setup = RigSetup::new(cfg);
    setup.simulated_time = true;
    setup.clock = Some(clock.clone());
    setup.content = Some(content.clone());
    setup.renderer = Some(Arc::new(Tiny(log.clone(), clock.clone())));
    setup.hooks.push(Box::new(Watch(log.clone())));
    let rig = Rig::start(setup).await.unwrap();
    // Frames are requested every 16.7 ms (at 101 and 117 ms here); push between two.
    tokio::time::sleep(Duration::from_millis(105)).await;
    let last_request = log
        .lock()
        .unwrap()
        .iter()
        .rev()
        .find_map(|(t, s)| matches!(s, Seen::Request(_)).then_some(*t))
        .expect("frames were requested");
    let pushed = clock.now();
    assert!(pushed > last_request);
    let (w, h) = (96, 96);
    let desc = FrameDesc {
        width: w,
        height: h,
        color: ColorFormat::Rgb8,
        depth: DepthKind::Diopters,
        near: None,
        far: None,
        seq: Some(1),
        app_time_ns: None,
    };
    let depth: Vec<u8> = (0..w * h).flat_map(|_| 2.0f32.to_le_bytes()).collect();
    content
        .frame_ingest()
        .unwrap()
        .submit(&desc, &vec![128; 3 * w * h], &depth, pushed)
        .unwrap();
    tokio::time::sleep(Duration::from_millis(40)).await;
    rig.state().cancel.cancel();
    assert!(rig.wait().await.ok());
    let log = log.lock().unwrap().clone();
    // The placeholder (black at 0 D) first, then the pushed frame at the time it came.
    let (i, (t, _)) = log
        .iter()
        .enumerate()
        .find(|(_, (_, s))| *s == Seen::Content(2, 2.0))
        .expect("the pushed frame reached the scheduler");
    assert_eq!(*t, pushed, "{log:?}");
    assert_eq!(log[0].1, Seen::Content(1, 0.0), "{log:?}");
    // No request between the last one before the push and the frame's arrival; the next
    // one comes after it, and its job renders the pushed frame.
    assert!(
        !log[..i]
            .iter()
            .any(|(t, s)| matches!(s, Seen::Request(_)) && *t > last_request),
        "{log:?}"
    );
    let next = log[i..]
        .iter()
        .find_map(|(t, s)| match s {
            Seen::Request(f) => Some((*t, *f)),
            _ => None,
        })
        .expect("a frame was requested after the push");
    assert!(next.0 > pushed, "{log:?}");
    assert!(
        log.iter().any(|(_, s)| *s == Seen::Rendered(next.1, 2)),
        "the next frame renders the pushed content: {log:?}"
    );
}

/// Makes both eyes of a synthesised frame "on its device" when `on_device`, noting the calls;
/// the host path's renders are noted too.
struct Device {
    on_device: bool,
    device_calls: Mutex<Vec<u64>>,
    host_renders: Mutex<u64>,
}

impl Renderer for Device {
    fn render(
        &self,
        _job: &RenderJob,
        _content: &ContentFrame,
    ) -> Result<RenderOutput, dioptra_render::RenderError> {
        *self.host_renders.lock().unwrap() += 1;
        Ok(RenderOutput {
            images: vec![dioptra_core::RgbImage::new(2, 2, [0.5; 3]).into()],
            planned: None,
            cost: Some(Duration::from_millis(2)),
        })
    }
    fn render_eyes_on_device(
        &self,
        _job: &RenderJob,
        content: &ContentFrame,
        positions: [[f32; 2]; 2],
    ) -> Option<Result<crate::render::EyesOnDevice, dioptra_render::RenderError>> {
        if !self.on_device {
            return None;
        }
        // The eyes IPD / 2 either side of the cyclopean eye.
        assert!(positions[0][0] < 0.0 && positions[1][0] == -positions[0][0]);
        let mut calls = self.device_calls.lock().unwrap();
        let made = !calls.contains(&content.number);
        calls.push(content.number);
        let out = || RenderOutput {
            images: vec![dioptra_core::RgbImage::new(2, 2, [0.5; 3]).into()],
            planned: None,
            cost: Some(Duration::from_millis(2)),
        };
        Some(Ok(crate::render::EyesOnDevice {
            outputs: [out(), out()],
            made,
        }))
    }
}

/// A stereo layout's frame with one RGB-D (a stream's placeholder here) has its eyes' views
/// made where the renderer can, on its device, and never on the host then; a renderer that
/// cannot leaves them to the host. `/status` says where.
#[tokio::test(start_paused = true)]
async fn a_synthesised_frames_eyes_are_made_on_the_renderers_device_where_it_can() {
    for on_device in [true, false] {
        let text = crate::config::EXAMPLE_SIM_BINOCULAR_RIG.to_string()
            + "\n[content]\nsource = \"stream\"\nring = \"none\"\n";
        let cfg = RigConfig::parse(&text).unwrap();
        let renderer = Arc::new(Device {
            on_device,
            device_calls: Mutex::default(),
            host_renders: Mutex::default(),
        });
        let clock: Arc<dyn crate::Clock> = Arc::new(dioptra_sim::tokio_clock::TokioClock::new());
        let mut setup = RigSetup::new(cfg);
        setup.simulated_time = true;
        setup.clock = Some(clock);
        setup.renderer = Some(renderer.clone());
        let rig = Rig::start(setup).await.unwrap();
        tokio::time::sleep(Duration::from_millis(500)).await;
        let views = rig.state().status_json()["eye_views"].clone();
        rig.state().cancel.cancel();
        assert!(rig.wait().await.ok());
        let calls = renderer.device_calls.lock().unwrap().clone();
        let host = *renderer.host_renders.lock().unwrap();
        assert_eq!(views["source"], "synthesised", "{views}");
        if on_device {
            assert!(calls.len() >= 10, "{calls:?}");
            assert_eq!(host, 0, "no eye rendered on the host path");
            assert_eq!(views["made_on"], "gpu", "{views}");
            // The one placeholder frame's views made once, then kept.
            assert_eq!(views["made"], 1, "{views}");
        } else {
            assert!(host >= 20, "{host}");
            assert_eq!(views["made_on"], "cpu", "{views}");
        }
    }
}
