//! Display output behind [`DisplaySink`]. [`HeadlessSink`] records each frame's timing (and
//! writes every Nth frame as PNG) for tests and CI; the rig's fullscreen window
//! ([`super::window::WindowSink`]: winit with a wgpu surface, vsync, on a chosen monitor)
//! implements the same trait.

use std::collections::VecDeque;
use std::path::PathBuf;

use dioptra_core::{Diopters, Timestamp};
use serde::Serialize;
use thiserror::Error;

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
    pub layers: std::sync::Arc<Vec<FrameImage>>,
}

/// When a frame was shown.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Shown {
    pub frame: u64,
    pub focus_d: f32,
    pub shown_ns: u64,
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
                    let pixels = layer.to_host().map_err(failed)?;
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
}
