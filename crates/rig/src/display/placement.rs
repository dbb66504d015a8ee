//! Where each eye's image goes on the display surface (`display.layout`, `display.scale`,
//! `display.eye_offset_px`): pure functions, used by the headless sink and the window alike.
//!
//! An eye's *place* is the part of the surface it owns: the whole surface for layout `one`,
//! its half of a side-by-side panel (the left eye the left half), or its own output for
//! `two-outputs` (each output is a surface of its own). With `scale = "exact"` the image is
//! drawn 1:1 onto surface pixels, centred in its place and moved by the eye's offset; an image
//! that, so placed, is not wholly inside its place is a [`Misfit`] (it is not shown). With
//! `scale = "fit"` it is scaled (aspect kept) to the largest size that, centred and moved by
//! the offset, stays inside its place: the letterbox of before, offsets applied.

use dioptra_core::{RgbImage, Side};
use serde::Serialize;

use super::config::{Display, DisplayLayout, EyeOffsets, Scale};
use super::frame::Frame;
use crate::render::FrameImage;

/// A rectangle of surface pixels: `x`, `y` of its top-left corner (rows from the top).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl Rect {
    pub fn new(x: u32, y: u32, width: u32, height: u32) -> Rect {
        Rect {
            x,
            y,
            width,
            height,
        }
    }
    /// `[x, y, width, height]`.
    pub fn to_array(self) -> [u32; 4] {
        [self.x, self.y, self.width, self.height]
    }
    fn describe(self) -> String {
        format!("{}x{} at ({}, {})", self.width, self.height, self.x, self.y)
    }
}

/// The eye's place on a `surface` (width, height). `one` and `two-outputs`: the whole
/// surface (for `two-outputs` the surface is that eye's output). `side-by-side`: the left
/// half for the left eye, the rest (the right half; on an odd width one pixel wider) for the
/// right.
pub fn place(layout: DisplayLayout, surface: (u32, u32), side: Side) -> Rect {
    let (w, h) = surface;
    match (layout, side) {
        (DisplayLayout::One | DisplayLayout::TwoOutputs, _) => Rect::new(0, 0, w, h),
        (DisplayLayout::SideBySide, Side::Left) => Rect::new(0, 0, w / 2, h),
        (DisplayLayout::SideBySide, Side::Right) => Rect::new(w / 2, 0, w - w / 2, h),
    }
}

/// What a sink needs to know of `display` to place images: the layout, the scale and the
/// eyes' offsets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlacementConfig {
    pub layout: DisplayLayout,
    pub scale: Scale,
    pub offsets: EyeOffsets,
}

impl PlacementConfig {
    pub fn from_display(d: &Display) -> PlacementConfig {
        PlacementConfig {
            layout: d.layout,
            scale: d.scale,
            offsets: d.eye_offset_px,
        }
    }
    /// Layout `one`, exact, no offset: an image the surface's size is drawn as it is.
    pub fn one() -> PlacementConfig {
        PlacementConfig {
            layout: DisplayLayout::One,
            scale: Scale::Exact,
            offsets: EyeOffsets::default(),
        }
    }
    /// The eyes drawn, each with its place's side: `[None]` for layout `one` (its offset is
    /// `eye_offset_px.left`), the left and right eye otherwise.
    pub fn eyes(&self) -> &'static [Option<Side>] {
        if self.layout.stereo() {
            &[Some(Side::Left), Some(Side::Right)]
        } else {
            &[None]
        }
    }
    /// Where an `image` (width, height) of `eye` (`None`: layout `one`) goes on `surface`.
    pub fn placement(
        &self,
        surface: (u32, u32),
        eye: Option<Side>,
        image: (u32, u32),
    ) -> Result<Rect, Misfit> {
        let side = eye.unwrap_or(Side::Left);
        placement(
            self.layout,
            self.scale,
            surface,
            side,
            image,
            self.offsets.of(side),
        )
        .map_err(|mut m| {
            m.eye = eye;
            m
        })
    }
}

/// Why an image is not drawn: it does not fit its place.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Misfit {
    /// `None`: layout `one`'s image.
    pub eye: Option<Side>,
    pub layout: DisplayLayout,
    pub scale: Scale,
    pub surface: (u32, u32),
    pub place: Rect,
    pub image: (u32, u32),
    pub offset: [i32; 2],
    /// Exact: pixels of the placed image beyond its place's left, top, right and bottom
    /// edges. Fit: the offset leaves no room (or the image is empty), all zero.
    pub over: [u32; 4],
}

impl Misfit {
    /// How much wider and taller the image is than its place (0 where it is not).
    pub fn too_large_by(&self) -> (u32, u32) {
        (
            self.image.0.saturating_sub(self.place.width),
            self.image.1.saturating_sub(self.place.height),
        )
    }
}

impl std::fmt::Display for Misfit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (who, key) = match self.eye {
            None => ("the".to_string(), "display.eye_offset_px.left"),
            Some(Side::Left) => ("the left eye's".to_string(), "display.eye_offset_px.left"),
            Some(Side::Right) => ("the right eye's".to_string(), "display.eye_offset_px.right"),
        };
        let where_ = match (self.layout, self.eye) {
            (DisplayLayout::SideBySide, Some(s)) => format!("the {} half of", s.as_str()),
            (DisplayLayout::TwoOutputs, Some(s)) => format!("the {} output,", s.as_str()),
            _ => "all of".to_string(),
        };
        let (sw, sh) = self.surface;
        write!(
            f,
            "{who} {}x{} image, offset [{}, {}], does not fit its place ({where_} the {sw}x{sh} \
             surface: {})",
            self.image.0,
            self.image.1,
            self.offset[0],
            self.offset[1],
            self.place.describe()
        )?;
        let edges: Vec<String> = ["left", "top", "right", "bottom"]
            .iter()
            .zip(self.over)
            .filter(|(_, n)| *n > 0)
            .map(|(e, n)| format!("{n} px over its {e} edge"))
            .collect();
        match self.scale {
            Scale::Exact if !edges.is_empty() => {
                let (tw, th) = self.too_large_by();
                write!(f, ": {}", edges.join(", "))?;
                if tw > 0 || th > 0 {
                    write!(
                        f,
                        " (the image is {tw} px wider and {th} px taller than its place)"
                    )?;
                }
                write!(
                    f,
                    "; drawn 1:1 (display.scale = \"exact\"), it needs a larger surface, a \
                     smaller image (display.width, display.height) or a smaller {key}; \
                     display.scale = \"fit\" scales it to its place"
                )
            }
            _ if self.image.0 == 0 || self.image.1 == 0 => write!(f, ": the image is empty"),
            Scale::Exact => write!(f, ": the place is empty"),
            Scale::Fit => write!(
                f,
                ": moved by {key}, no part of its place is left to scale it into"
            ),
        }
    }
}

impl std::error::Error for Misfit {}

/// Where an `image` (width, height) of `side` goes on `surface` (for layout `one` pass
/// [`Side::Left`], whose offset it uses), moved by `offset` (pixels right and down):
/// `Exact`, 1:1, centred in its place (rounded towards the top left) plus the offset, or a
/// [`Misfit`] naming how far it reaches beyond; `Fit`, scaled to the largest size of its
/// aspect that stays in its place once centred and moved by the offset (with no offset:
/// the letterbox).
pub fn placement(
    layout: DisplayLayout,
    scale: Scale,
    surface: (u32, u32),
    side: Side,
    image: (u32, u32),
    offset: [i32; 2],
) -> Result<Rect, Misfit> {
    let p = place(layout, surface, side);
    let misfit = |over: [u32; 4]| Misfit {
        eye: layout.stereo().then_some(side),
        layout,
        scale,
        surface,
        place: p,
        image,
        offset,
        over,
    };
    let (iw, ih) = (i64::from(image.0), i64::from(image.1));
    let (px, py, pw, ph) = (
        i64::from(p.x),
        i64::from(p.y),
        i64::from(p.width),
        i64::from(p.height),
    );
    let (ox, oy) = (i64::from(offset[0]), i64::from(offset[1]));
    let (w, h) = match scale {
        Scale::Exact => (iw, ih),
        Scale::Fit => {
            let (aw, ah) = (pw - 2 * ox.abs(), ph - 2 * oy.abs());
            if aw <= 0 || ah <= 0 || iw == 0 || ih == 0 {
                return Err(misfit([0; 4]));
            }
            let s = (aw as f64 / iw as f64).min(ah as f64 / ih as f64);
            let fit = |v: i64, room: i64| ((v as f64 * s).round() as i64).clamp(1, room);
            (fit(iw, aw), fit(ih, ah))
        }
    };
    if w == 0 || h == 0 || pw == 0 || ph == 0 {
        return Err(misfit([0; 4]));
    }
    let x = px + (pw - w).div_euclid(2) + ox;
    let y = py + (ph - h).div_euclid(2) + oy;
    let beyond = |n: i64| u32::try_from(n.max(0)).unwrap_or(u32::MAX);
    let over = [
        beyond(px - x),
        beyond(py - y),
        beyond(x + w - (px + pw)),
        beyond(y + h - (py + ph)),
    ];
    if over != [0; 4] {
        return Err(misfit(over));
    }
    // Inside the place, so inside the surface: every value fits u32.
    let u = |v: i64| u32::try_from(v).unwrap_or(0);
    Ok(Rect::new(u(x), u(y), u(w), u(h)))
}

/// Draws `image` into `panel` at `rect`, nearest pixel (1:1 where `rect` is the image's
/// size): the CPU twin of the window's blit (`crates/cli/shaders/blit.wgsl`). Parts of `rect`
/// outside the panel are left out.
pub fn draw_into(panel: &mut RgbImage, image: &RgbImage, rect: Rect) {
    let (pw, ph) = (panel.width(), panel.height());
    let (iw, ih) = (image.width(), image.height());
    let (rw, rh) = (rect.width as usize, rect.height as usize);
    if iw == 0 || ih == 0 || rw == 0 || rh == 0 {
        return;
    }
    // The source pixel of each column and row, as the blit's sampler picks it: the one under
    // the destination pixel's centre.
    let src = |d: usize, r: usize, i: usize| ((2 * d + 1) * i / (2 * r)).min(i - 1);
    let cols: Vec<(usize, usize)> = (0..rw)
        .map(|dx| (rect.x as usize + dx, src(dx, rw, iw)))
        .filter(|(x, _)| *x < pw)
        .collect();
    for (dst, from) in panel.channels.iter_mut().zip(&image.channels) {
        let (dst, from) = (dst.data_mut(), from.data());
        for dy in 0..rh {
            let y = rect.y as usize + dy;
            if y >= ph {
                break;
            }
            let sy = src(dy, rh, ih);
            let (row, srow) = (y * pw, sy * iw);
            if rw == iw {
                let n = cols.len();
                dst[row + rect.x as usize..row + rect.x as usize + n]
                    .copy_from_slice(&from[srow..srow + n]);
            } else {
                for &(x, sx) in &cols {
                    dst[row + x] = from[srow + sx];
                }
            }
        }
    }
}

/// One image of a frame and where it goes.
#[derive(Debug, Clone, Copy)]
pub struct Placed<'a> {
    /// `None`: layout `one`.
    pub eye: Option<Side>,
    pub image: &'a FrameImage,
    pub rect: Rect,
}

/// Why a frame's images cannot be placed.
#[derive(Debug, Clone, PartialEq)]
pub enum PlaceError {
    Misfit(Misfit),
    /// The frame has no image for this layer (or the right eye fewer than the left).
    NoImage(String),
    /// The surface is not what the images are placed for (a window that is not the size of
    /// its monitor, with `scale = "exact"`).
    Surface(String),
}

impl std::fmt::Display for PlaceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlaceError::Misfit(m) => m.fmt(f),
            PlaceError::NoImage(s) | PlaceError::Surface(s) => f.write_str(s),
        }
    }
}

/// A sink's placement state: the config, and what it has reported (misfits, mono frames on a
/// stereo layout), each reason logged once.
#[derive(Debug, Clone)]
pub struct Placer {
    pub config: PlacementConfig,
    misfits: u64,
    newest_misfit: Option<String>,
    logged: std::collections::HashSet<String>,
    mono_on_stereo: u64,
}

/// Different misfit reasons logged at most: a surface resized step by step logs no more.
const REASONS_LOGGED: usize = 32;

impl Placer {
    pub fn new(config: PlacementConfig) -> Placer {
        Placer {
            config,
            misfits: 0,
            newest_misfit: None,
            logged: Default::default(),
            mono_on_stereo: 0,
        }
    }

    /// Layer `layer` of `frame`'s images and where each goes on `surface` (for
    /// `two-outputs`: one output's size; both eyes are placed on a surface that size).
    ///
    /// A frame without the right eye's images (`Frame::right` is `None`) on a stereo layout
    /// has its one image placed in both eyes' places (both eyes see the same view, no
    /// disparity); the sink counts it with [`Placer::shown`].
    pub fn place<'a>(
        &self,
        frame: &'a Frame,
        layer: usize,
        surface: (u32, u32),
    ) -> Result<Vec<Placed<'a>>, PlaceError> {
        self.place_eyes(frame, layer, surface, self.config.eyes())
    }

    /// [`Placer::place`] for `eyes` only (of [`PlacementConfig::eyes`]): a window per eye
    /// places its eye's image on its own surface.
    pub fn place_eyes<'a>(
        &self,
        frame: &'a Frame,
        layer: usize,
        surface: (u32, u32),
        eyes: &[Option<Side>],
    ) -> Result<Vec<Placed<'a>>, PlaceError> {
        let left = frame.layers.get(layer).ok_or_else(|| {
            PlaceError::NoImage(format!(
                "frame {} has no image {layer} (it has {})",
                frame.number,
                frame.layers.len()
            ))
        })?;
        let right = match (&frame.right, self.config.layout.stereo()) {
            (Some(r), true) => Some(r.get(layer).ok_or_else(|| {
                PlaceError::NoImage(format!(
                    "frame {}: the right eye has {} images, the left {}",
                    frame.number,
                    r.len(),
                    frame.layers.len()
                ))
            })?),
            _ => None,
        };
        let mut placed = Vec::with_capacity(2);
        for &eye in eyes {
            let image = match eye {
                Some(Side::Right) => right.unwrap_or(left),
                _ => left,
            };
            let size = (
                u32::try_from(image.width()).unwrap_or(u32::MAX),
                u32::try_from(image.height()).unwrap_or(u32::MAX),
            );
            let rect = self
                .config
                .placement(surface, eye, size)
                .map_err(PlaceError::Misfit)?;
            placed.push(Placed { eye, image, rect });
        }
        Ok(placed)
    }

    /// `frame` is shown: one with one view on a stereo layout is counted in
    /// `mono_on_stereo` (and logged the first time).
    pub fn shown(&mut self, frame: &Frame) {
        if self.config.layout.stereo() && frame.right.is_none() {
            if self.mono_on_stereo == 0 {
                tracing::warn!(
                    frame = frame.number,
                    layout = self.config.layout.as_str(),
                    "a frame with one view on a stereo layout: its image is shown to both \
                     eyes (counted in /status display.mono_on_stereo)"
                );
            }
            self.mono_on_stereo += 1;
        }
    }

    /// Counts a frame not shown because of `why`, and logs each reason once; true the first
    /// time for this reason (a binary without a log subscriber may print it then).
    pub fn refused(&mut self, why: &PlaceError) -> bool {
        self.misfits += 1;
        let reason = why.to_string();
        let first = self.logged.len() < REASONS_LOGGED && self.logged.insert(reason.clone());
        if first {
            tracing::warn!("frame not shown: {reason}");
        }
        self.newest_misfit = Some(reason);
        first
    }

    pub fn misfits(&self) -> u64 {
        self.misfits
    }
    pub fn mono_on_stereo(&self) -> u64 {
        self.mono_on_stereo
    }

    /// What `/status` shows: the layout, scale, surface, each eye's place on it, the misfits
    /// (count, newest reason) and the frames with one view on a stereo layout.
    pub fn status(&self, surface: Option<(u32, u32)>) -> serde_json::Value {
        let c = &self.config;
        let places = surface.map(|s| {
            let mut m = serde_json::Map::new();
            for &eye in c.eyes() {
                let side = eye.unwrap_or(Side::Left);
                m.insert(
                    eye.map_or("one", Side::as_str).into(),
                    serde_json::json!(place(c.layout, s, side).to_array()),
                );
            }
            m
        });
        serde_json::json!({
            "layout": c.layout.as_str(),
            "scale": c.scale.as_str(),
            "eye_offset_px": { "left": c.offsets.left, "right": c.offsets.right },
            "surface": surface.map(|(w, h)| [w, h]),
            "places": places,
            "misfit": { "count": self.misfits, "newest": self.newest_misfit },
            "mono_on_stereo": self.mono_on_stereo,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const L: Side = Side::Left;
    const R: Side = Side::Right;
    use DisplayLayout::{One, SideBySide, TwoOutputs};
    use Scale::{Exact, Fit};

    #[test]
    fn places_split_a_side_by_side_panel_and_give_other_layouts_the_whole_surface() {
        for s in [L, R] {
            assert_eq!(place(One, (640, 480), s), Rect::new(0, 0, 640, 480));
            assert_eq!(place(TwoOutputs, (640, 480), s), Rect::new(0, 0, 640, 480));
        }
        assert_eq!(place(SideBySide, (1024, 512), L), Rect::new(0, 0, 512, 512));
        assert_eq!(
            place(SideBySide, (1024, 512), R),
            Rect::new(512, 0, 512, 512)
        );
        // Odd width: the right half gets the extra column.
        assert_eq!(place(SideBySide, (1025, 512), L), Rect::new(0, 0, 512, 512));
        assert_eq!(
            place(SideBySide, (1025, 512), R),
            Rect::new(512, 0, 513, 512)
        );
    }

    #[test]
    fn exact_centres_the_image_in_its_place_and_adds_the_offset() {
        // Every layout, both eyes: centred 1:1.
        let cases = [
            (
                One,
                L,
                (640, 480),
                (512, 256),
                [0, 0],
                Rect::new(64, 112, 512, 256),
            ),
            (
                One,
                L,
                (640, 480),
                (512, 256),
                [-64, 112],
                Rect::new(0, 224, 512, 256),
            ),
            (
                TwoOutputs,
                L,
                (640, 480),
                (512, 256),
                [0, 0],
                Rect::new(64, 112, 512, 256),
            ),
            (
                TwoOutputs,
                R,
                (640, 480),
                (512, 256),
                [64, -112],
                Rect::new(128, 0, 512, 256),
            ),
            (
                SideBySide,
                L,
                (1920, 1080),
                (512, 512),
                [0, 0],
                Rect::new(224, 284, 512, 512),
            ),
            (
                SideBySide,
                R,
                (1920, 1080),
                (512, 512),
                [0, 0],
                Rect::new(1184, 284, 512, 512),
            ),
            // Offsets move each eye within its half, up to its edges.
            (
                SideBySide,
                L,
                (1920, 1080),
                (512, 512),
                [224, 0],
                Rect::new(448, 284, 512, 512),
            ),
            (
                SideBySide,
                R,
                (1920, 1080),
                (512, 512),
                [-224, -284],
                Rect::new(960, 0, 512, 512),
            ),
            // The image the size of its place fills it.
            (
                SideBySide,
                R,
                (1024, 512),
                (512, 512),
                [0, 0],
                Rect::new(512, 0, 512, 512),
            ),
            // An odd difference rounds towards the top left.
            (One, L, (5, 5), (2, 2), [0, 0], Rect::new(1, 1, 2, 2)),
        ];
        for (layout, side, surface, image, offset, want) in cases {
            assert_eq!(
                placement(layout, Exact, surface, side, image, offset),
                Ok(want),
                "{layout:?} {side:?} {surface:?} {image:?} {offset:?}"
            );
        }
    }

    #[test]
    fn exact_refuses_an_image_one_pixel_beyond_its_place_and_says_by_how_much() {
        // 512 wide in a 512 wide half: one pixel of offset is one pixel over.
        let m = placement(SideBySide, Exact, (1024, 512), R, (512, 512), [1, 0]).unwrap_err();
        assert_eq!(m.over, [0, 0, 1, 0]);
        assert_eq!(m.eye, Some(R));
        assert_eq!(m.place, Rect::new(512, 0, 512, 512));
        let s = m.to_string();
        assert!(
            s.starts_with("the right eye's 512x512 image, offset [1, 0]"),
            "{s}"
        );
        assert!(
            s.contains("the right half of the 1024x512 surface: 512x512 at (512, 0)"),
            "{s}"
        );
        assert!(s.contains("1 px over its right edge"), "{s}");
        assert!(s.contains("display.eye_offset_px.right"), "{s}");
        assert!(s.contains("display.scale = \"fit\""), "{s}");
        // The same to the left and up: the left eye is not allowed into the right half either.
        let m = placement(SideBySide, Exact, (1024, 512), L, (512, 512), [0, -1]).unwrap_err();
        assert_eq!(m.over, [0, 1, 0, 0]);
        let m = placement(SideBySide, Exact, (1024, 512), L, (512, 512), [1, 0]).unwrap_err();
        assert_eq!(m.over, [0, 0, 1, 0], "into the right eye's half");
        // One pixel taller than the surface: centred towards the top, so over the top edge.
        let m = placement(One, Exact, (512, 511), L, (512, 512), [0, 0]).unwrap_err();
        assert_eq!(m.over, [0, 1, 0, 0]);
        assert_eq!(m.eye, None);
        assert_eq!(m.too_large_by(), (0, 1));
        assert!(m.to_string().starts_with("the 512x512 image"), "{m}");
        assert!(m.to_string().contains("1 px taller"), "{m}");
        // A surface smaller than needed: a side-by-side panel 800 wide for two 512s.
        let m = placement(SideBySide, Exact, (800, 600), L, (512, 512), [0, 0]).unwrap_err();
        assert_eq!(m.over, [56, 0, 56, 0]);
        assert_eq!(m.too_large_by(), (112, 0));
        assert!(m.to_string().contains("112 px wider"), "{m}");
        // Two outputs: each output on its own.
        let m = placement(TwoOutputs, Exact, (511, 512), L, (512, 512), [0, 0]).unwrap_err();
        assert_eq!(m.over, [1, 0, 0, 0]);
        assert!(m.to_string().contains("the left output,"), "{m}");
        // An empty surface.
        let m = placement(One, Exact, (0, 0), L, (4, 4), [0, 0]).unwrap_err();
        assert!(m.to_string().contains("place is empty"), "{m}");
    }

    #[test]
    fn fit_is_the_letterbox_with_offsets_kept_inside_the_place() {
        // No offset: today's letterbox (the window's former test values).
        assert_eq!(
            placement(One, Fit, (1920, 1080), L, (96, 96), [0, 0]),
            Ok(Rect::new(420, 0, 1080, 1080))
        );
        assert_eq!(
            placement(One, Fit, (1920, 1080), L, (960, 540), [0, 0]),
            Ok(Rect::new(0, 0, 1920, 1080))
        );
        assert_eq!(
            placement(One, Fit, (100, 100), L, (200, 100), [0, 0]),
            Ok(Rect::new(0, 25, 100, 50))
        );
        // Side by side: each half letterboxed on its own.
        assert_eq!(
            placement(SideBySide, Fit, (1920, 1080), L, (512, 512), [0, 0]),
            Ok(Rect::new(0, 60, 960, 960))
        );
        assert_eq!(
            placement(SideBySide, Fit, (1920, 1080), R, (512, 512), [0, 0]),
            Ok(Rect::new(960, 60, 960, 960))
        );
        // An offset shrinks the image so that, moved, it stays in its half.
        assert_eq!(
            placement(SideBySide, Fit, (1920, 1080), R, (512, 512), [-30, 0]),
            Ok(Rect::new(960, 90, 900, 900))
        );
        assert_eq!(
            placement(TwoOutputs, Fit, (1920, 1080), L, (512, 512), [0, 40]),
            Ok(Rect::new(460, 80, 1000, 1000))
        );
        // Smaller or larger than its place: scaled either way.
        assert_eq!(
            placement(TwoOutputs, Fit, (100, 100), R, (400, 400), [0, 0]),
            Ok(Rect::new(0, 0, 100, 100))
        );
        // An offset that leaves no room: a misfit, fit or not.
        let m = placement(SideBySide, Fit, (200, 100), L, (10, 10), [50, 0]).unwrap_err();
        assert!(
            m.to_string().contains("no part of its place is left"),
            "{m}"
        );
        assert!(placement(SideBySide, Fit, (200, 100), L, (10, 10), [49, 0]).is_ok());
        let m = placement(One, Fit, (200, 100), L, (0, 10), [0, 0]).unwrap_err();
        assert!(m.to_string().contains("empty"), "{m}");
    }

    #[test]
    fn fit_placements_stay_inside_their_place_for_any_offset() {
        for surface in [(1920u32, 1080u32), (801, 599), (64, 64)] {
            for layout in [One, SideBySide, TwoOutputs] {
                for side in [L, R] {
                    for image in [(96u32, 96u32), (512, 256), (3, 700)] {
                        for offset in [[0, 0], [-17, 5], [31, -31], [1, 1]] {
                            let p = place(layout, surface, side);
                            if let Ok(r) = placement(layout, Fit, surface, side, image, offset) {
                                assert!(
                                    r.x >= p.x
                                        && r.y >= p.y
                                        && r.x + r.width <= p.x + p.width
                                        && r.y + r.height <= p.y + p.height
                                        && r.width > 0
                                        && r.height > 0,
                                    "{layout:?} {side:?} {surface:?} {image:?} {offset:?}: {r:?}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn drawing_1_to_1_copies_pixels_and_scaling_takes_the_nearest() {
        let vals: Vec<f32> = (0..12).map(|i| i as f32).collect();
        // 2 x 2, channel values 0..12 interleaved.
        let img = RgbImage::from_interleaved(2, 2, &vals).unwrap();
        let mut panel = RgbImage::new(5, 4, [-1.0; 3]);
        draw_into(&mut panel, &img, Rect::new(3, 1, 2, 2));
        assert_eq!(panel.pixel(3, 1), img.pixel(0, 0));
        assert_eq!(panel.pixel(4, 2), img.pixel(1, 1));
        assert_eq!(panel.pixel(2, 1), Some([-1.0; 3]));
        assert_eq!(panel.pixel(3, 3), Some([-1.0; 3]));
        // Doubled: each source pixel covers 2 x 2.
        let mut panel = RgbImage::new(4, 4, [0.0; 3]);
        draw_into(&mut panel, &img, Rect::new(0, 0, 4, 4));
        for y in 0..4 {
            for x in 0..4 {
                assert_eq!(panel.pixel(x, y), img.pixel(x / 2, y / 2), "{x},{y}");
            }
        }
    }
}
