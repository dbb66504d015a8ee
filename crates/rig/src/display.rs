//! Display output behind [`DisplaySink`]. [`HeadlessSink`] records each frame's timing (and
//! writes every Nth frame as PNG) for tests and CI; the binary's fullscreen window (winit
//! with a wgpu surface, vsync, on a chosen monitor) implements the same trait. Both place each eye's image on the surface with
//! [`placement`] (`display.layout`, `display.scale`, `display.eye_offset_px`).
//!
//! The marker patch (`display.marker_patch`): a square in one corner that both sinks draw
//! white or black over the frame, for a photodiode taped over it. [`Marker`] decides its
//! colour for each present (toggled on every frame, or on the events the config names) and
//! the loop hands it to the sink with the frame ([`Frame::marker`]); [`MarkerControl`] is how
//! the API asks for a marker and how `dioptra hil` holds the patch black.

use std::collections::VecDeque;
use std::path::PathBuf;

use dioptra_core::{RgbImage, Timestamp};
use serde::Serialize;
use thiserror::Error;

use config::DisplayLayout;

pub mod blit;
pub mod config;
pub mod frame;
pub mod marker;
pub mod pacing;
pub mod panel_draw;
pub mod panel_image;
pub mod placement;
pub mod status;

pub use frame::{Frame, MarkerDraw};
pub use marker::{Marker, MarkerControl};
pub use panel_image::PanelImage;
pub use status::DisplayHandle;

use placement::{PlaceError, PlacementConfig, Placer};

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
    /// An eye's way to its panel (the pre-warp mesh, the rig config's image settings).
    #[error("the eyes' images on their panels: {0}")]
    Panel(String),
    /// The frame is not shown: an image does not fit its place (or is missing). The sink
    /// has counted it in its status and logged the reason (once per reason).
    #[error("frame not shown: {0}")]
    NotShown(PlaceError),
}

/// When a frame was shown.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Shown {
    pub frame: u64,
    pub focus_d: f32,
    pub shown_ns: u64,
    /// The marker patch's colour in that present (true: white).
    pub marker_white: Option<bool>,
    /// Each eye's magnification compensation in that present ([`Frame::size_compensation`]).
    pub size_compensation: [Option<f32>; 2],
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

/// Keeps the last frames' timing in memory and writes every `png_every`th frame as PNG. A
/// frame left in GPU memory is read back only when it is written.
///
/// Each PNG is what the panel shows, each eye's image placed on it as the window places it
/// ([`placement`]): layout `one`, `frame_000042.png` (the panel `display.width` x `height`;
/// an image that size with no offset is written as it is); `side-by-side`, the same name, the
/// panel 2 x `display.width` wide, black around the images; `two-outputs`,
/// `frame_000042_left.png` and `frame_000042_right.png`, an output each. Multifocal: one per
/// plane (`frame_000042_plane1.png`, `frame_000042_left_plane1.png`). The marker patch is
/// painted in each panel's corner. A frame with one view on a stereo layout (`Frame::right`
/// `None`) has its image placed in both eyes' places (counted in `/status`
/// `mono_on_stereo`). A frame an image of which does not fit its place (`scale = "exact"`)
/// is not shown: counted in `/status` `misfit`, logged once per reason, and
/// [`DisplayError::NotShown`] returned.
#[derive(Debug)]
pub struct HeadlessSink {
    png_every: u32,
    /// The frame number the next PNG is due at: the next multiple of `png_every`.
    next_png: u64,
    dir: Option<PathBuf>,
    shown: u64,
    recent: VecDeque<Shown>,
    pngs: u64,
    placer: Placer,
    /// The panel (for `two-outputs`: each output); `None`: each image's own size.
    surface: Option<(u32, u32)>,
    /// Each eye's way to its panel (compensation, pre-warp, transfer); empty: each image
    /// written as it is, sRGB.
    panels: Vec<PanelImage>,
    /// The newest present's compensation per eye, for `/status`.
    last_compensation: [Option<f32>; 2],
}

/// How many frame timings a headless sink keeps.
const RECENT: usize = 256;

impl HeadlessSink {
    /// Layout `one`, each image written as it is.
    pub fn new(png_every: u32, dir: Option<PathBuf>) -> Result<Self, DisplayError> {
        HeadlessSink::with_placement(png_every, dir, PlacementConfig::one(), None)
    }

    /// The sink `display` asks for: its layout, scale and offsets on a panel of its size
    /// (`side-by-side`: 2 x `width` wide; `two-outputs`: an output `width` x `height` per eye).
    pub fn for_display(d: &config::Display) -> Result<Self, DisplayError> {
        let surface = match d.layout {
            DisplayLayout::SideBySide => (d.width.saturating_mul(2), d.height),
            DisplayLayout::One | DisplayLayout::TwoOutputs => (d.width, d.height),
        };
        HeadlessSink::with_placement(
            d.png_every,
            d.png_dir.clone(),
            PlacementConfig::from_display(d),
            Some(surface),
        )
    }

    pub fn with_placement(
        png_every: u32,
        dir: Option<PathBuf>,
        placement: PlacementConfig,
        surface: Option<(u32, u32)>,
    ) -> Result<Self, DisplayError> {
        if let (true, Some(d)) = (png_every > 0, &dir) {
            std::fs::create_dir_all(d).map_err(|source| DisplayError::Dir {
                path: d.clone(),
                source,
            })?;
        }
        Ok(HeadlessSink {
            png_every,
            next_png: 0,
            dir,
            shown: 0,
            recent: VecDeque::with_capacity(RECENT),
            pngs: 0,
            placer: Placer::new(placement),
            surface,
            panels: Vec::new(),
            last_compensation: [None; 2],
        })
    }

    /// The sink a rig config asks for ([`HeadlessSink::for_display`]), each eye's image
    /// scaled, pre-warped and encoded for its panel as `[optics]` and `display.transfer` say
    /// (the CPU twins of the window's GPU passes) when its PNGs are written.
    pub fn for_rig(cfg: &crate::config::RigConfig) -> Result<Self, DisplayError> {
        let mut sink = HeadlessSink::for_display(&cfg.display)?;
        sink.panels = panel_images(cfg)?;
        Ok(sink)
    }
    pub fn recent(&self) -> impl Iterator<Item = &Shown> {
        self.recent.iter()
    }
    pub fn pngs_written(&self) -> u64 {
        self.pngs
    }
    /// Frames not shown because an image did not fit its place.
    pub fn misfits(&self) -> u64 {
        self.placer.misfits()
    }
    /// Frames with one view shown on a stereo layout.
    pub fn mono_on_stereo(&self) -> u64 {
        self.placer.mono_on_stereo()
    }

    /// The surface for `frame`'s layer `layer`: the panel, or the image's own size.
    fn surface_for(&self, frame: &Frame, layer: usize) -> (u32, u32) {
        self.surface.unwrap_or_else(|| {
            frame.layers.get(layer).map_or((0, 0), |i| {
                (
                    u32::try_from(i.width()).unwrap_or(u32::MAX),
                    u32::try_from(i.height()).unwrap_or(u32::MAX),
                )
            })
        })
    }

    /// Writes each layer of `frame` as the panel (or panels) show it.
    fn write_pngs(&mut self, dir: &std::path::Path, frame: &Frame) -> Result<(), DisplayError> {
        let layers = frame.layers.len();
        let two_outputs = self.placer.config.layout == DisplayLayout::TwoOutputs;
        for layer in 0..layers {
            let surface = self.surface_for(frame, layer);
            let placed = self
                .placer
                .place(frame, layer, surface)
                .map_err(DisplayError::NotShown)?;
            // Two outputs: a panel per eye; otherwise one panel with every image on it.
            let panels: Vec<&[placement::Placed]> = if two_outputs {
                placed.chunks(1).collect()
            } else {
                vec![&placed[..]]
            };
            for on_panel in panels {
                let mut name = format!("frame_{:06}", frame.number);
                if let (true, Some(eye)) = (two_outputs, on_panel[0].eye) {
                    name += &format!("_{}", eye.as_str());
                }
                if layers > 1 {
                    name += &format!("_plane{layer}");
                }
                let path = dir.join(name + ".png");
                let failed = |e: dioptra_render::RenderError| DisplayError::Write {
                    frame: frame.number,
                    path: path.clone(),
                    detail: e.to_string(),
                };
                let whole = placement::Rect::new(0, 0, surface.0, surface.1);
                if !self.panels.is_empty() {
                    // Each image as its panel is driven: code values, written as they are.
                    let mut panel = RgbImage::new(surface.0 as usize, surface.1 as usize, [0.0; 3]);
                    for p in on_panel {
                        let image = p.image.to_host().map_err(failed)?;
                        let image = match self.panels.iter().find(|e| e.eye == p.eye) {
                            Some(e) => e
                                .to_panel(&image, frame.compensation_of(p.eye))
                                .map_err(failed)?,
                            None => image.into_owned(),
                        };
                        placement::draw_into(&mut panel, &image, p.rect);
                    }
                    if let Some(m) = &frame.marker {
                        m.paint(&mut panel);
                    }
                    dioptra_render::io::write_code_values(&path, &panel).map_err(failed)?;
                    self.pngs += 1;
                    continue;
                }
                let mut pixels = match on_panel {
                    // The image is the panel: written as it is.
                    [p] if p.rect == whole
                        && (p.image.width(), p.image.height())
                            == (surface.0 as usize, surface.1 as usize) =>
                    {
                        p.image.to_host().map_err(failed)?
                    }
                    _ => {
                        let mut panel =
                            RgbImage::new(surface.0 as usize, surface.1 as usize, [0.0; 3]);
                        for p in on_panel {
                            let image = p.image.to_host().map_err(failed)?;
                            placement::draw_into(&mut panel, &image, p.rect);
                        }
                        std::borrow::Cow::Owned(panel)
                    }
                };
                if let Some(m) = &frame.marker {
                    m.paint(pixels.to_mut());
                }
                dioptra_render::io::write_color(&path, &pixels).map_err(failed)?;
                self.pngs += 1;
            }
        }
        Ok(())
    }
}

impl DisplaySink for HeadlessSink {
    fn present(&mut self, frame: &Frame, now: Timestamp) -> Result<Timestamp, DisplayError> {
        // Placed before it counts as shown: a frame that does not fit is not shown.
        let surface = self.surface_for(frame, 0);
        if let Err(e) = self.placer.place(frame, 0, surface) {
            self.placer.refused(&e);
            return Err(DisplayError::NotShown(e));
        }
        self.placer.shown(frame);
        self.shown += 1;
        if self.recent.len() == RECENT {
            self.recent.pop_front();
        }
        self.recent.push_back(Shown {
            frame: frame.number,
            focus_d: frame.focus.0,
            shown_ns: now.0,
            marker_white: frame.marker.map(|m| m.white),
            size_compensation: frame.size_compensation,
        });
        self.last_compensation = frame.size_compensation;
        // By frame number, not by presentation: a frame shown again (a deadline miss) does not
        // shift the frames written. A frame number the scheduler skipped (its slot not
        // rendered) gives way to the next one shown.
        if let (true, Some(dir)) = (self.png_every > 0, self.dir.clone()) {
            if frame.number >= self.next_png {
                let every = u64::from(self.png_every);
                self.next_png = (frame.number / every + 1) * every;
                self.write_pngs(&dir, frame)?;
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
        let mut v = serde_json::json!({
            "sink": self.describe(),
            "shown": self.shown,
            "pngs_written": self.pngs_written(),
            "mean_interval_ms": interval_ms,
            "last": recent.last(),
        });
        if let (Some(o), serde_json::Value::Object(p)) =
            (v.as_object_mut(), self.placer.status(self.surface))
        {
            o.extend(p);
        }
        if !self.panels.is_empty() {
            v["eyes_to_panel"] = eyes_status(&self.panels, self.last_compensation);
        }
        v
    }
    fn describe(&self) -> String {
        match (&self.dir, self.png_every) {
            (Some(d), 1) => format!("headless (every frame to {})", d.display()),
            (Some(d), n) if n > 0 => {
                format!("headless (every {} frame to {})", ordinal(n), d.display())
            }
            _ => "headless".into(),
        }
    }
}

/// Each eye's [`PanelImage`] for a rig config; none when no eye's image changes on its way
/// to the panel (no compensation, no distortion, sRGB panels): images are written as they are.
pub fn panel_images(cfg: &crate::config::RigConfig) -> Result<Vec<PanelImage>, DisplayError> {
    let size = [cfg.display.width as usize, cfg.display.height as usize];
    let eyes = cfg
        .eye_images()
        .map_err(|e| DisplayError::Panel(e.to_string()))?;
    let panels = eyes
        .iter()
        .map(|e| PanelImage::new(e, size))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| DisplayError::Panel(format!("the pre-warp: {e}")))?;
    Ok(if panels.iter().any(PanelImage::changes_image) {
        panels
    } else {
        Vec::new()
    })
}

/// `/status`'s `display.eyes_to_panel`: each eye's compensation (the newest factor),
/// distortion and transfer, under `one`, or `left` and `right`.
pub fn eyes_status(panels: &[PanelImage], compensation: [Option<f32>; 2]) -> serde_json::Value {
    let mut v = serde_json::Map::new();
    for p in panels {
        let i = usize::from(p.eye == Some(dioptra_core::Side::Right));
        v.insert(
            p.eye.map_or("one", |e| e.as_str()).into(),
            p.status(compensation[i]),
        );
    }
    serde_json::Value::Object(v)
}

/// `n` as an English ordinal: 2nd, 3rd, 11th, 21st, 30th.
fn ordinal(n: u32) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use config::{Corner, MarkerEvent, MarkerPatch};

    /// The lab's report: `png_every = 30` wrote frames 0, 33, 61, 89 (each deadline miss shows
    /// a frame again and shifted the count) and `/status` said "every 1th frame".
    #[test]
    fn png_every_writes_by_frame_number_and_says_its_ordinal() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::new(30, Some(dir.path().join("f"))).unwrap();
        let frame = |n: u64| Frame {
            number: n,
            focus: Diopters(1.0),
            layers: vec![dioptra_core::RgbImage::new(4, 4, [0.5; 3]).into()].into(),
            right: None,
            marker: None,
            size_compensation: [None; 2],
        };
        let mut t = 0;
        for n in 0..=100u64 {
            // Frames 5, 29, 30 and 59 shown twice (their successors were late); 90 never
            // rendered (the scheduler skipped its slot).
            let times = if [5, 29, 30, 59].contains(&n) { 2 } else { 1 };
            for _ in 0..times {
                if n != 90 {
                    s.present(&frame(n), Timestamp(t)).unwrap();
                    t += 1000;
                }
            }
        }
        let mut written: Vec<String> = std::fs::read_dir(dir.path().join("f"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        written.sort();
        assert_eq!(
            written,
            [
                "frame_000000.png",
                "frame_000030.png",
                "frame_000060.png",
                "frame_000091.png"
            ]
        );
        assert!(
            s.describe().starts_with("headless (every 30th frame to "),
            "{}",
            s.describe()
        );
        let names: Vec<String> = [1, 2, 3, 4, 11, 12, 13, 21, 22, 23, 30, 101, 111]
            .into_iter()
            .map(ordinal)
            .collect();
        assert_eq!(
            names,
            [
                "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "23rd", "30th",
                "101st", "111th"
            ]
        );
        let every = HeadlessSink::new(1, Some(dir.path().join("g"))).unwrap();
        assert!(every.describe().starts_with("headless (every frame to "));
    }
    use dioptra_core::Diopters;

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
                size_compensation: [None; 2],
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
            size_compensation: [None; 2],
        };
        s.present(&f, Timestamp(5)).unwrap();
        assert_eq!(s.recent().last().unwrap().marker_white, Some(true));
        let png = dioptra_render::io::read_color(&dir.path().join("frame_000007.png")).unwrap();
        assert!(png.pixel(15, 0).unwrap()[0] > 0.99);
        assert!(png.pixel(11, 3).unwrap()[0] < 0.3);
        assert!(png.pixel(12, 4).unwrap()[0] < 0.3);
    }

    /// A `w` x `h` image whose every pixel differs from its neighbours by far more than an
    /// 8-bit sRGB step: red the column, green the row, blue `tag` (which image it is).
    fn pattern(w: usize, h: usize, tag: f32) -> RgbImage {
        let mut v = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                v.extend([(x + 1) as f32 / w as f32, (y + 1) as f32 / h as f32, tag]);
            }
        }
        RgbImage::from_interleaved(w, h, &v).unwrap()
    }

    /// What an 8-bit sRGB PNG gives back for a linear value.
    fn through_png(v: f32) -> f32 {
        let byte = (dioptra_core::image::linear_to_srgb(v) * 255.0).round();
        dioptra_core::image::srgb_to_linear(byte / 255.0)
    }

    /// Checks every pixel of the PNG at `path`: inside each `(image, x, y)` the image's pixel
    /// (1:1, its top-left at x, y), black elsewhere.
    fn assert_panel(
        path: &std::path::Path,
        size: (usize, usize),
        images: &[(&RgbImage, usize, usize)],
    ) {
        let png = dioptra_render::io::read_color(path).unwrap();
        assert_eq!((png.width(), png.height()), size, "{}", path.display());
        for y in 0..size.1 {
            for x in 0..size.0 {
                let want = images
                    .iter()
                    .find_map(|(img, x0, y0)| {
                        let (ix, iy) = (x.checked_sub(*x0)?, y.checked_sub(*y0)?);
                        img.pixel(ix, iy)
                    })
                    .unwrap_or([0.0; 3])
                    .map(through_png);
                assert_eq!(
                    png.pixel(x, y),
                    Some(want),
                    "{} pixel ({x}, {y})",
                    path.display()
                );
            }
        }
    }

    fn display(
        layout: DisplayLayout,
        scale: config::Scale,
        dir: &std::path::Path,
    ) -> config::Display {
        config::Display {
            width: 10,
            height: 8,
            layout,
            scale,
            eye_offset_px: config::EyeOffsets {
                left: [1, 0],
                right: [-1, 1],
            },
            png_every: 1,
            png_dir: Some(dir.to_path_buf()),
            ..Default::default()
        }
    }

    fn stereo_frame(number: u64, left: Vec<RgbImage>, right: Option<Vec<RgbImage>>) -> Frame {
        Frame {
            number,
            focus: Diopters(1.0),
            layers: left.into_iter().map(Into::into).collect::<Vec<_>>().into(),
            right: right.map(|r| r.into_iter().map(Into::into).collect::<Vec<_>>().into()),
            marker: None,
            size_compensation: [None; 2],
        }
    }

    #[test]
    fn side_by_side_writes_the_panel_with_each_eye_at_its_place() {
        use config::Scale;
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::for_display(&display(
            DisplayLayout::SideBySide,
            Scale::Exact,
            dir.path(),
        ))
        .unwrap();
        let (left, right) = (pattern(8, 6, 0.25), pattern(8, 6, 1.0));
        s.present(
            &stereo_frame(3, vec![left.clone()], Some(vec![right.clone()])),
            Timestamp(1),
        )
        .unwrap();
        // Panel 20 x 8; halves 10 x 8; an 8 x 6 image centred at (1, 1) of its half, moved
        // by its offset: the left eye's +1 right, the right eye's 1 left and 1 down.
        assert_panel(
            &dir.path().join("frame_000003.png"),
            (20, 8),
            &[(&left, 2, 1), (&right, 10, 2)],
        );
        let st = s.status();
        assert_eq!(st["layout"], "side-by-side");
        assert_eq!(st["scale"], "exact");
        assert_eq!(st["surface"], serde_json::json!([20, 8]));
        assert_eq!(st["places"]["left"], serde_json::json!([0, 0, 10, 8]));
        assert_eq!(st["places"]["right"], serde_json::json!([10, 0, 10, 8]));
        assert_eq!(st["misfit"]["count"], 0);
        assert_eq!(st["mono_on_stereo"], 0);
        assert_eq!(s.shown(), 1);

        // Multifocal: a panel per plane, each with both eyes' image of that plane.
        let planes_l = [pattern(8, 6, 0.0), pattern(8, 6, 0.5)];
        let planes_r = [pattern(8, 6, 0.75), pattern(8, 6, 1.0)];
        s.present_layer(
            &stereo_frame(4, planes_l.to_vec(), Some(planes_r.to_vec())),
            0,
            Timestamp(2),
        )
        .unwrap();
        for k in 0..2 {
            assert_panel(
                &dir.path().join(format!("frame_000004_plane{k}.png")),
                (20, 8),
                &[(&planes_l[k], 2, 1), (&planes_r[k], 10, 2)],
            );
        }
    }

    #[test]
    fn two_outputs_write_an_image_per_eye() {
        use config::Scale;
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::for_display(&display(
            DisplayLayout::TwoOutputs,
            Scale::Exact,
            dir.path(),
        ))
        .unwrap();
        let (left, right) = (pattern(8, 6, 0.25), pattern(8, 6, 1.0));
        s.present(
            &stereo_frame(9, vec![left.clone()], Some(vec![right.clone()])),
            Timestamp(1),
        )
        .unwrap();
        assert_panel(
            &dir.path().join("frame_000009_left.png"),
            (10, 8),
            &[(&left, 2, 1)],
        );
        assert_panel(
            &dir.path().join("frame_000009_right.png"),
            (10, 8),
            &[(&right, 0, 2)],
        );
        assert!(!dir.path().join("frame_000009.png").exists());
        assert_eq!(s.pngs_written(), 2);
        assert_eq!(
            s.status()["places"]["right"],
            serde_json::json!([0, 0, 10, 8])
        );
        // Multifocal: per eye and plane.
        let planes = [pattern(8, 6, 0.0), pattern(8, 6, 0.5)];
        s.present(
            &stereo_frame(10, planes.to_vec(), Some(planes.to_vec())),
            Timestamp(2),
        )
        .unwrap();
        for name in ["left_plane0", "left_plane1", "right_plane0", "right_plane1"] {
            assert!(
                dir.path().join(format!("frame_000010_{name}.png")).exists(),
                "{name}"
            );
        }
    }

    #[test]
    fn layout_one_writes_the_image_byte_for_byte_as_before() {
        use config::Scale;
        let dir = tempfile::tempdir().unwrap();
        let (old, new) = (dir.path().join("old"), dir.path().join("new"));
        let mut d = display(DisplayLayout::One, Scale::Exact, &new);
        d.eye_offset_px = Default::default();
        let mut configured = HeadlessSink::for_display(&d).unwrap();
        let mut plain = HeadlessSink::new(1, Some(old.clone())).unwrap();
        let img = pattern(10, 8, 0.5);
        let frame = stereo_frame(1, vec![img.clone()], None);
        for s in [&mut configured, &mut plain] {
            s.present(&frame, Timestamp(1)).unwrap();
        }
        let direct = dir.path().join("direct.png");
        dioptra_render::io::write_color(&direct, &img).unwrap();
        let bytes = |p: &std::path::Path| std::fs::read(p).unwrap();
        assert_eq!(bytes(&new.join("frame_000001.png")), bytes(&direct));
        assert_eq!(bytes(&old.join("frame_000001.png")), bytes(&direct));
        assert_eq!(configured.status()["surface"], serde_json::json!([10, 8]));
        assert_eq!(
            configured.status()["places"]["one"],
            serde_json::json!([0, 0, 10, 8])
        );
        assert_eq!(
            configured.mono_on_stereo(),
            0,
            "one view is what layout one shows"
        );
        // A smaller image is placed 1:1 in the middle of the panel, by the left offset.
        d.eye_offset_px.left = [-1, 1];
        let mut s = HeadlessSink::for_display(&d).unwrap();
        let small = pattern(4, 4, 0.0);
        s.present(&stereo_frame(2, vec![small.clone()], None), Timestamp(2))
            .unwrap();
        assert_panel(&new.join("frame_000002.png"), (10, 8), &[(&small, 2, 3)]);
    }

    #[test]
    fn a_misfit_is_not_shown_and_is_counted_with_its_reason() {
        use config::Scale;
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::for_display(&display(
            DisplayLayout::SideBySide,
            Scale::Exact,
            dir.path(),
        ))
        .unwrap();
        // 10 wide in a 10 wide half, but the left eye's offset moves it 1 px right.
        let frame = stereo_frame(
            5,
            vec![pattern(10, 6, 0.0)],
            Some(vec![pattern(10, 6, 1.0)]),
        );
        for n in 0..3 {
            let e = s.present(&frame, Timestamp(n)).unwrap_err();
            assert!(matches!(e, DisplayError::NotShown(_)), "{e}");
        }
        assert_eq!(s.shown(), 0);
        assert_eq!(s.pngs_written(), 0);
        assert_eq!(s.misfits(), 3);
        let st = s.status();
        assert_eq!(st["misfit"]["count"], 3);
        let newest = st["misfit"]["newest"].as_str().unwrap();
        assert!(
            newest.starts_with("the left eye's 10x6 image, offset [1, 0]")
                && newest.contains("1 px over its right edge"),
            "{newest}"
        );
        assert!(
            std::fs::read_dir(dir.path()).unwrap().next().is_none(),
            "nothing written"
        );
        // Fit: scaled into its place instead, and shown.
        let mut s =
            HeadlessSink::for_display(&display(DisplayLayout::SideBySide, Scale::Fit, dir.path()))
                .unwrap();
        s.present(&frame, Timestamp(9)).unwrap();
        assert_eq!((s.shown(), s.misfits()), (1, 0));
    }

    #[test]
    fn one_view_on_a_stereo_layout_goes_to_both_eyes_and_is_counted() {
        use config::Scale;
        let dir = tempfile::tempdir().unwrap();
        let mut s = HeadlessSink::for_display(&display(
            DisplayLayout::SideBySide,
            Scale::Exact,
            dir.path(),
        ))
        .unwrap();
        let img = pattern(8, 6, 0.5);
        for n in 0..2 {
            s.present(&stereo_frame(n, vec![img.clone()], None), Timestamp(n))
                .unwrap();
        }
        assert_panel(
            &dir.path().join("frame_000001.png"),
            (20, 8),
            &[(&img, 2, 1), (&img, 10, 2)],
        );
        assert_eq!(s.mono_on_stereo(), 2);
        assert_eq!(s.status()["mono_on_stereo"], 2);
    }
}
