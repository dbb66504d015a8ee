//! Display output behind [`DisplaySink`]. [`HeadlessSink`] records each frame's timing (and
//! writes every Nth frame as PNG) for tests and CI; the rig's fullscreen window
//! ([`super::window::WindowSink`]: winit with a wgpu surface, vsync, on a chosen monitor)
//! implements the same trait.
//!
//! The marker patch (`display.marker_patch`): a square in one corner that both sinks draw
//! white or black over the frame, for a photodiode taped over it. [`Marker`] decides its
//! colour for each present (toggled on every frame, or on the events the config names) and
//! the loop hands it to the sink with the frame ([`Frame::marker`]); [`MarkerControl`] is how
//! the API asks for a marker and how `dioptra hil` holds the patch black.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use dioptra_core::{Diopters, RgbImage, Timestamp};
use serde::Serialize;
use thiserror::Error;

use crate::config::{Corner, MarkerEvent, MarkerPatch};
use crate::render::FrameImage;

#[derive(Debug, Error)]
pub enum DisplayError {
    #[error("cannot create the frame directory {path}: {source}")]
    Dir {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write frame {frame} to {path}: {detail}")]
    Write {
        frame: u64,
        path: PathBuf,
        detail: String,
    },
    #[error("the display window: {0}")]
    Window(String),
}

/// A rendered frame: one image (varifocal, light field) or one per focal plane (multifocal).
#[derive(Debug, Clone)]
pub struct Frame {
    pub number: u64,
    /// The focus it was rendered for.
    pub focus: Diopters,
    /// Shared, so a sink can hand the frame to another thread without copying the images.
    /// On a stereo layout (`display.layout`): the left eye's.
    pub layers: std::sync::Arc<Vec<FrameImage>>,
    /// On a stereo layout: the right eye's images, as many as `layers`.
    pub right: Option<std::sync::Arc<Vec<FrameImage>>>,
    /// The marker patch to draw over it in this present, if the rig has one.
    pub marker: Option<MarkerDraw>,
}

/// The marker patch as a sink draws it in one present.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct MarkerDraw {
    pub corner: Corner,
    /// Side, pixels.
    pub size: u32,
    pub white: bool,
}

impl MarkerDraw {
    /// The patch in a `width` x `height` image (rows from the top): x, y, width, height,
    /// clipped to the image.
    pub fn rect(&self, width: u32, height: u32) -> [u32; 4] {
        let (w, h) = (self.size.min(width), self.size.min(height));
        let x = match self.corner {
            Corner::TopLeft | Corner::BottomLeft => 0,
            Corner::TopRight | Corner::BottomRight => width - w,
        };
        let y = match self.corner {
            Corner::TopLeft | Corner::TopRight => 0,
            Corner::BottomLeft | Corner::BottomRight => height - h,
        };
        [x, y, w, h]
    }

    /// Paints the patch into `image` (linear light: white 1, black 0).
    pub fn paint(&self, image: &mut RgbImage) {
        let (width, height) = (image.width(), image.height());
        let [x0, y0, w, h] = self.rect(
            u32::try_from(width).unwrap_or(u32::MAX),
            u32::try_from(height).unwrap_or(u32::MAX),
        );
        let v = if self.white { 1.0 } else { 0.0 };
        for plane in &mut image.channels {
            for y in y0 as usize..(y0 + h) as usize {
                let row = y * width;
                plane.data_mut()[row + x0 as usize..row + (x0 + w) as usize].fill(v);
            }
        }
    }
}

/// The patch's colour, present by present: the loop's own state.
#[derive(Debug, Clone)]
pub struct Marker {
    patch: MarkerPatch,
    white: bool,
    /// An event asked for a toggle at the next present.
    pending: bool,
    api_seen: u64,
}

impl Marker {
    /// Black until the first toggle.
    pub fn new(patch: &MarkerPatch) -> Marker {
        Marker {
            patch: patch.clone(),
            white: false,
            pending: false,
            api_seen: 0,
        }
    }

    /// `event` happened: the next present toggles the patch if the config names it.
    pub fn event(&mut self, event: MarkerEvent) {
        if self.patch.toggle_on.contains(&event) {
            self.pending = true;
        }
    }

    /// The patch for the next present.
    pub fn on_present(&mut self, control: &MarkerControl) -> MarkerDraw {
        let api = control.api_markers.load(Ordering::Relaxed);
        if api != self.api_seen {
            self.api_seen = api;
            self.event(MarkerEvent::ApiMarker);
        }
        if control.hold.load(Ordering::Relaxed) {
            // Held black: what happened meanwhile is not shown afterwards.
            self.white = false;
            self.pending = false;
        } else if self.pending || self.patch.toggle_on.contains(&MarkerEvent::Frame) {
            self.white = !self.white;
            self.pending = false;
        }
        MarkerDraw {
            corner: self.patch.corner,
            size: self.patch.size,
            white: self.white,
        }
    }
}

/// What outside the loop asks of the marker patch.
#[derive(Debug, Default)]
pub struct MarkerControl {
    hold: AtomicBool,
    api_markers: AtomicU64,
}

impl MarkerControl {
    /// Toggles the patch at the next present, where `toggle_on` names "api-marker" (the API's
    /// `POST /marker`). Returns the markers asked for so far.
    pub fn api_marker(&self) -> u64 {
        self.api_markers.fetch_add(1, Ordering::Relaxed) + 1
    }
    /// Holds the patch black (true) from the next present until released (false).
    pub fn hold_black(&self, hold: bool) {
        self.hold.store(hold, Ordering::Relaxed);
    }
}

/// When a frame was shown.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Shown {
    pub frame: u64,
    pub focus_d: f32,
    pub shown_ns: u64,
    /// The marker patch's colour in that present (true: white).
    pub marker_white: Option<bool>,
}

/// Where frames go.
pub trait DisplaySink: Send {
    /// Shows `frame` at or after `now`; returns the time it is on screen.
    fn present(&mut self, frame: &Frame, now: Timestamp) -> Result<Timestamp, DisplayError>;
    /// Multifocal: shows layer `layer` of `frame` in the sub-frame starting at `start`.
    fn present_layer(
        &mut self,
        frame: &Frame,
        layer: usize,
        start: Timestamp,
    ) -> Result<Timestamp, DisplayError>;
    /// Frames (multifocal: plane cycles) shown so far.
    fn shown(&self) -> u64;
    fn describe(&self) -> String;
    /// What `GET /status` shows about the display.
    fn status(&self) -> serde_json::Value;
}

/// Keeps the last frames' timing in memory and writes every `png_every`th frame as PNG
/// (`frame_000042.png`, or `frame_000042_plane1.png` per multifocal layer). A frame left in
/// GPU memory is read back only when it is written.
#[derive(Debug)]
pub struct HeadlessSink {
    png_every: u32,
    dir: Option<PathBuf>,
    shown: u64,
    recent: VecDeque<Shown>,
    pngs: u64,
}

/// How many frame timings a headless sink keeps.
const RECENT: usize = 256;

impl HeadlessSink {
    pub fn new(png_every: u32, dir: Option<PathBuf>) -> Result<Self, DisplayError> {
        if let (true, Some(d)) = (png_every > 0, &dir) {
            std::fs::create_dir_all(d).map_err(|source| DisplayError::Dir {
                path: d.clone(),
                source,
            })?;
        }
        Ok(HeadlessSink {
            png_every,
            dir,
            shown: 0,
            recent: VecDeque::with_capacity(RECENT),
            pngs: 0,
        })
    }
    pub fn recent(&self) -> impl Iterator<Item = &Shown> {
        self.recent.iter()
    }
    pub fn pngs_written(&self) -> u64 {
        self.pngs
    }
}

impl DisplaySink for HeadlessSink {
    fn present(&mut self, frame: &Frame, now: Timestamp) -> Result<Timestamp, DisplayError> {
        self.shown += 1;
        if self.recent.len() == RECENT {
            self.recent.pop_front();
        }
        self.recent.push_back(Shown {
            frame: frame.number,
            focus_d: frame.focus.0,
            shown_ns: now.0,
            marker_white: frame.marker.map(|m| m.white),
        });
        if let (true, Some(dir)) = (self.png_every > 0, &self.dir) {
            if (self.shown - 1).is_multiple_of(u64::from(self.png_every)) {
                for (i, layer) in frame.layers.iter().enumerate() {
                    let name = if frame.layers.len() == 1 {
                        format!("frame_{:06}.png", frame.number)
                    } else {
                        format!("frame_{:06}_plane{i}.png", frame.number)
                    };
                    let path = dir.join(name);
                    let failed = |e: dioptra_render::RenderError| DisplayError::Write {
                        frame: frame.number,
                        path: path.clone(),
                        detail: e.to_string(),
                    };
                    let mut pixels = layer.to_host().map_err(failed)?;
                    if let Some(m) = &frame.marker {
                        m.paint(pixels.to_mut());
                    }
                    dioptra_render::io::write_color(&path, &pixels).map_err(failed)?;
                    self.pngs += 1;
                }
            }
        }
        Ok(now)
    }
    fn present_layer(
        &mut self,
        frame: &Frame,
        layer: usize,
        start: Timestamp,
    ) -> Result<Timestamp, DisplayError> {
        // A plane cycle starts with layer 0: that is when the frame counts as shown (and is
        // written as PNGs, all layers).
        if layer == 0 {
            return self.present(frame, start);
        }
        Ok(start)
    }
    fn shown(&self) -> u64 {
        self.shown
    }
    fn status(&self) -> serde_json::Value {
        let recent: Vec<&Shown> = self.recent().collect();
        // Mean interval between the frames kept, ms.
        let interval_ms = match (recent.first(), recent.last()) {
            (Some(a), Some(b)) if recent.len() > 1 => {
                Some(b.shown_ns.saturating_sub(a.shown_ns) as f64 / 1e6 / (recent.len() - 1) as f64)
            }
            _ => None,
        };
        serde_json::json!({
            "sink": self.describe(),
            "shown": self.shown,
            "pngs_written": self.pngs_written(),
            "mean_interval_ms": interval_ms,
            "last": recent.last(),
        })
    }
    fn describe(&self) -> String {
        match (&self.dir, self.png_every) {
            (Some(d), n) if n > 0 => format!("headless (every {n}th frame to {})", d.display()),
            _ => "headless".into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headless_writes_every_nth_frame_and_keeps_timings() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::new(3, Some(dir.path().join("frames"))).unwrap();
        for n in 0..7u64 {
            let f = Frame {
                number: n,
                focus: Diopters(1.0),
                layers: vec![dioptra_core::RgbImage::new(8, 8, [0.5, 0.25, 0.0]).into()].into(),
                right: None,
                marker: None,
            };
            let t = s.present(&f, Timestamp(n * 1000)).unwrap();
            assert_eq!(t, Timestamp(n * 1000));
        }
        assert_eq!(s.shown(), 7);
        assert_eq!(s.pngs_written(), 3); // frames 0, 3, 6
        for n in [0, 3, 6] {
            assert!(dir.path().join(format!("frames/frame_{n:06}.png")).exists());
        }
        assert!(!dir.path().join("frames/frame_000001.png").exists());
        assert_eq!(s.recent().count(), 7);
    }

    fn patch(corner: Corner, toggle_on: Vec<MarkerEvent>) -> MarkerPatch {
        MarkerPatch {
            corner,
            size: 3,
            toggle_on,
        }
    }

    #[test]
    fn the_patch_is_painted_in_its_corner_and_nowhere_else() {
        for (corner, x0, y0) in [
            (Corner::TopLeft, 0, 0),
            (Corner::TopRight, 5, 0),
            (Corner::BottomLeft, 0, 3),
            (Corner::BottomRight, 5, 3),
        ] {
            let mut img = RgbImage::new(8, 6, [0.5; 3]);
            let m = MarkerDraw {
                corner,
                size: 3,
                white: true,
            };
            assert_eq!(m.rect(8, 6), [x0, y0, 3, 3]);
            m.paint(&mut img);
            for y in 0..6 {
                for x in 0..8 {
                    let inside = (x0..x0 + 3).contains(&x) && (y0..y0 + 3).contains(&y);
                    let want = if inside { 1.0 } else { 0.5 };
                    assert_eq!(
                        img.pixel(x as usize, y as usize),
                        Some([want; 3]),
                        "{corner:?} {x},{y}"
                    );
                }
            }
        }
        // Larger than the image: clipped.
        let m = MarkerDraw {
            corner: Corner::BottomRight,
            size: 50,
            white: false,
        };
        assert_eq!(m.rect(8, 6), [0, 0, 8, 6]);
    }

    #[test]
    fn the_marker_toggles_on_every_frame_or_on_the_events_named() {
        let control = MarkerControl::default();
        let mut every = Marker::new(&patch(Corner::TopLeft, vec![MarkerEvent::Frame]));
        let colours: Vec<bool> = (0..4).map(|_| every.on_present(&control).white).collect();
        assert_eq!(colours, [true, false, true, false]);

        let mut on = Marker::new(&patch(
            Corner::TopLeft,
            vec![MarkerEvent::LensCommand, MarkerEvent::ApiMarker],
        ));
        assert!(!on.on_present(&control).white);
        on.event(MarkerEvent::ModeChange); // not named: nothing
        assert!(!on.on_present(&control).white);
        on.event(MarkerEvent::LensCommand);
        on.event(MarkerEvent::LensCommand); // two before one present: one toggle
        assert!(on.on_present(&control).white);
        assert!(on.on_present(&control).white);
        control.api_marker();
        assert!(!on.on_present(&control).white);
        // Held black, whatever happens; released, it waits for the next event.
        control.hold_black(true);
        on.event(MarkerEvent::LensCommand);
        assert!(!on.on_present(&control).white);
        control.api_marker();
        assert!(!on.on_present(&control).white);
        control.hold_black(false);
        assert!(!on.on_present(&control).white);
        on.event(MarkerEvent::LensCommand);
        assert!(on.on_present(&control).white);
    }

    #[test]
    fn headless_pngs_carry_the_patch_and_the_timings_its_colour() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::new(1, Some(dir.path().to_path_buf())).unwrap();
        let f = Frame {
            number: 7,
            focus: Diopters(1.0),
            layers: vec![RgbImage::new(16, 16, [0.25; 3]).into()].into(),
            right: None,
            marker: Some(MarkerDraw {
                corner: Corner::TopRight,
                size: 4,
                white: true,
            }),
        };
        s.present(&f, Timestamp(5)).unwrap();
        assert_eq!(s.recent().last().unwrap().marker_white, Some(true));
        let png = dioptra_render::io::read_color(&dir.path().join("frame_000007.png")).unwrap();
        assert!(png.pixel(15, 0).unwrap()[0] > 0.99);
        assert!(png.pixel(11, 3).unwrap()[0] < 0.3);
        assert!(png.pixel(12, 4).unwrap()[0] < 0.3);
    }
}
