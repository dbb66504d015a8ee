//! RGB-D frames pushed by a running application (`[content] source = "stream"`).
//!
//! Two ways in, one decoder ([`decode_frame`]):
//! - the fast path, a shared-memory ring of frame slots: a file (0600) the daemon creates and
//!   maps, which the application maps too, writes a frame into a slot and names it with
//!   `POST /frame {"slot", "seq"}`. The daemon copies the slot out before it answers, so the
//!   slot is the application's again once the answer arrives. Layout: [`super::ring`] (spec:
//!   RING.md); `GET /frame/ring` says it too.
//! - the slow, simple path, `PUT /frame?width=&height=&color=&depth=[&near=&far=&seq=]` with
//!   the colour bytes then the depth bytes as the body; or, with `color=png|exr|pfm` and
//!   `color_bytes=N`, a colour image file (N bytes) then a depth image file (EXR, PFM or
//!   16-bit PNG), decoded by `dioptra render`'s readers. One body, so one frame is atomic.
//!
//! A frame is refused, with the reason, counted and never shown when: its size is not the
//! display's, a buffer is shorter or longer than its size says, a depth is NaN or outside its
//! convention's range, its sequence number is not newer than the newest accepted, or its slot
//! was rewritten while it was read. The frame on show stays until a good one replaces it.
//!
//! On a stereo rig (`display.layout` side-by-side or two-outputs) a frame is one of: a mono
//! frame of one eye's size (each eye's view synthesised from it); both eyes side by side,
//! 2 x width wide (split here, the left half the left eye's); or one eye's half (`eye=left`,
//! `eye=right`, a slot's `eye`), numbered with `seq`, the pair's two halves sharing it. A
//! pair is shown only once both halves arrived, in either order; a half waits until its
//! partner comes or a newer pair or whole frame completes (then it is dropped, counted under
//! `halves_dropped`); a half older than the newest complete pair is refused as stale.
//!
//! Light-field content (`content.views = N`): a frame may be an N x N grid of views, each sent
//! on its own naming its view (`view=ROW_COLUMN`, a slot's `view`) and the frame's `seq` (on a
//! stereo rig also its eye: each eye's own grid), collected as halves are and shown once
//! every view arrived ([`ContentFrame::views`]).

use std::fs::OpenOptions;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use dioptra_core::image::srgb_to_linear;
use dioptra_core::{lock, DepthMap, Plane, RgbImage, Rgbd, Side, Timestamp};
use dioptra_render::io::{decode_color, decode_samples, encoded_size, ImageFormat};
use rayon::prelude::*;
use serde::Serialize;

use super::ring::{eye_of_code, RingHeader, SlotHeader};
pub use super::ring::{RING_HEADER, RING_MAGIC, RING_SLOTS, RING_VERSION, SLOT_HEADER};
use super::{Arrival, Content, ContentFrame, ContentView};

/// The colour's encoding: raw pixels, or (`PUT /frame` only) an image file, whose frame's
/// depth is an image file too.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ColorFormat {
    /// 8-bit sRGB, 3 bytes a pixel.
    Rgb8 = 1,
    /// 8-bit sRGB with alpha (ignored), 4 bytes a pixel.
    Rgba8 = 2,
    /// Linear light, 3 little-endian f32 a pixel.
    Rgbf32 = 3,
    /// A PNG file (8 or 16-bit, sRGB).
    Png = 4,
    /// An EXR file (linear light).
    Exr = 5,
    /// A PFM file (linear light).
    Pfm = 6,
}

impl ColorFormat {
    /// Bytes a pixel of raw colour; `None` for an image file.
    pub fn bytes_per_px(self) -> Option<usize> {
        match self {
            ColorFormat::Rgb8 => Some(3),
            ColorFormat::Rgba8 => Some(4),
            ColorFormat::Rgbf32 => Some(12),
            ColorFormat::Png | ColorFormat::Exr | ColorFormat::Pfm => None,
        }
    }
    /// The image file format of an encoded colour.
    fn file_format(self) -> Option<ImageFormat> {
        match self {
            ColorFormat::Png => Some(ImageFormat::Png),
            ColorFormat::Exr => Some(ImageFormat::Exr),
            ColorFormat::Pfm => Some(ImageFormat::Pfm),
            _ => None,
        }
    }
    /// Its name in `PUT /frame?color=`.
    pub fn as_str(self) -> &'static str {
        match self {
            ColorFormat::Rgb8 => "rgb8",
            ColorFormat::Rgba8 => "rgba8",
            ColorFormat::Rgbf32 => "rgbf32",
            ColorFormat::Png => "png",
            ColorFormat::Exr => "exr",
            ColorFormat::Pfm => "pfm",
        }
    }
    /// A ring slot's colour format (raw pixels only).
    pub fn from_code(c: u32) -> Option<Self> {
        [Self::Rgb8, Self::Rgba8, Self::Rgbf32]
            .into_iter()
            .find(|f| *f as u32 == c)
    }
    pub fn parse(s: &str) -> Option<Self> {
        [
            Self::Rgb8,
            Self::Rgba8,
            Self::Rgbf32,
            Self::Png,
            Self::Exr,
            Self::Pfm,
        ]
        .into_iter()
        .find(|f| f.as_str() == s)
    }
}

/// What the depth values are (each a little-endian f32).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum DepthKind {
    /// Distance along the view axis, metres (> 0; +inf is optical infinity).
    Metres = 1,
    /// Diopters (>= 0).
    Diopters = 2,
    /// Distance along the view axis, millimetres (> 0; a 16-bit PNG's usual unit).
    Millimetres = 7,
    /// An OpenGL depth buffer in normalised device coordinates, [-1, 1], -1 at `near`.
    Gl = 3,
    /// The same with reversed Z: 1 at `near`, -1 at `far`.
    GlReversed = 4,
    /// A Vulkan / Direct3D depth buffer, [0, 1], 0 at `near`.
    Vulkan = 5,
    /// Reversed Z, [0, 1], 1 at `near`, 0 at `far` (`far` may be infinite).
    VulkanReversed = 6,
}

impl DepthKind {
    pub fn from_code(c: u32) -> Option<Self> {
        [
            Self::Metres,
            Self::Diopters,
            Self::Millimetres,
            Self::Gl,
            Self::GlReversed,
            Self::Vulkan,
            Self::VulkanReversed,
        ]
        .into_iter()
        .find(|k| *k as u32 == c)
    }
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "m" => Some(Self::Metres),
            "mm" => Some(Self::Millimetres),
            "D" => Some(Self::Diopters),
            "gl" => Some(Self::Gl),
            "gl-reversed" => Some(Self::GlReversed),
            "vulkan" | "d3d" => Some(Self::Vulkan),
            "vulkan-reversed" | "d3d-reversed" => Some(Self::VulkanReversed),
            _ => None,
        }
    }
    fn is_buffer(self) -> bool {
        !matches!(self, Self::Metres | Self::Millimetres | Self::Diopters)
    }

    /// `v` in diopters, or why it is refused. `near`/`far` in metres (checked by the caller).
    #[inline(always)]
    fn diopters(self, v: f32, near: f32, far: f32) -> Result<f32, &'static str> {
        if v.is_nan() {
            return Err("NaN");
        }
        let (n, f) = (f64::from(near), f64::from(far));
        let v64 = f64::from(v);
        // Eye-space distance, metres.
        let z = match self {
            Self::Diopters => {
                return if v.is_finite() && v >= 0.0 {
                    Ok(v)
                } else {
                    Err("not a finite power >= 0 D")
                }
            }
            Self::Metres => {
                return if v > 0.0 {
                    Ok((1.0 / v64) as f32)
                } else {
                    Err("not a distance > 0 m")
                }
            }
            Self::Millimetres => {
                return if v > 0.0 {
                    Ok((1000.0 / v64) as f32)
                } else {
                    Err("not a distance > 0 mm")
                }
            }
            Self::Gl | Self::GlReversed => {
                if !(-1.0..=1.0).contains(&v) {
                    return Err("outside an OpenGL depth buffer's [-1, 1]");
                }
                let d = if self == Self::Gl { v64 } else { -v64 };
                // z_ndc = (f + n - 2 f n / z) / (f - n), solved for z.
                if f.is_infinite() {
                    2.0 * n / (1.0 - d)
                } else {
                    2.0 * f * n / (f + n - d * (f - n))
                }
            }
            Self::Vulkan | Self::VulkanReversed => {
                if !(0.0..=1.0).contains(&v) {
                    return Err("outside a depth buffer's [0, 1]");
                }
                let d = if self == Self::Vulkan { v64 } else { 1.0 - v64 };
                // d = f (z - n) / (z (f - n)), solved for z.
                if f.is_infinite() {
                    n / (1.0 - d)
                } else {
                    f * n / (f - d * (f - n))
                }
            }
        };
        // At the far plane of an infinite projection z is +inf: 0 D.
        Ok(if z.is_infinite() {
            0.0
        } else {
            (1.0 / z) as f32
        })
    }
}

/// A frame's description.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameDesc {
    pub width: usize,
    pub height: usize,
    pub color: ColorFormat,
    pub depth: DepthKind,
    /// Near and far planes of a depth buffer, metres (far may be infinite for reversed Z).
    pub near: Option<f32>,
    pub far: Option<f32>,
    /// Must grow from frame to frame; `None`: the daemon numbers it.
    pub seq: Option<u64>,
    /// The application's time for the frame, ns (kept, not interpreted).
    pub app_time_ns: Option<u64>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FrameError {
    #[error("the frame is {got_w}x{got_h}; the display is {want_w}x{want_h}")]
    WrongSize {
        got_w: usize,
        got_h: usize,
        want_w: usize,
        want_h: usize,
    },
    #[error("the {what} is {got} bytes; a {w}x{h} frame's is {want}")]
    Length {
        what: &'static str,
        got: usize,
        want: usize,
        w: usize,
        h: usize,
    },
    #[error("depth at pixel ({x}, {y}) is {value}: {why}")]
    Depth {
        x: usize,
        y: usize,
        value: f32,
        why: &'static str,
    },
    #[error("{0}")]
    Invalid(String),
    #[error("sequence number {seq} is not newer than {newest}, the newest frame accepted")]
    Stale { seq: u64, newest: u64 },
    /// One eye's half not newer than that eye's newest half, the newest complete frame or
    /// the newest half dropped unpaired.
    #[error(
        "the {} eye's sequence number {seq} is not newer than {newest}: that eye's newest \
         half, or a frame or pair already complete or dropped (its pair can no longer be shown)",
        eye.as_str()
    )]
    StaleHalf { eye: Side, seq: u64, newest: u64 },
    /// A view of a grid not newer than the newest of the same view (and eye), the newest
    /// complete frame or the newest frame dropped incomplete.
    #[error(
        "view {view}'s sequence number {seq} is not newer than {newest}: that view's newest, \
         or a frame already complete or dropped (it can no longer be shown)"
    )]
    StaleView { view: String, seq: u64, newest: u64 },
    /// A view the rig has no place for, or one that does not fit its frame's other parts.
    #[error("{0}")]
    View(String),
    /// A stereo rig's frame of the wrong size: one eye's (`eye`) or a whole one.
    #[error(
        "the {}frame is {got_w}x{got_h}; {}",
        eye.map_or(String::new(), |e| format!("{} eye's ", e.as_str())),
        if eye.is_some() {
            format!("one eye's image is {want_w}x{want_h}")
        } else {
            format!(
                "one eye's image is {want_w}x{want_h} (a mono frame), or {}x{want_h} for both \
                 eyes side by side",
                2 * want_w
            )
        }
    )]
    WrongEyeSize {
        eye: Option<Side>,
        got_w: usize,
        got_h: usize,
        want_w: usize,
        want_h: usize,
    },
    /// The frame's eye: unknown, or named on a rig that shows one image.
    #[error("{0}")]
    Eye(String),
    #[error("slot {0} was rewritten while the daemon read it (its sequence number changed)")]
    Torn(usize),
    #[error("the {what}: {detail}")]
    Encoding { what: &'static str, detail: String },
    /// A `PUT /frame` request that does not describe a frame (its query or Content-Type).
    #[error("{0}")]
    Request(String),
    #[error("PUT /frame needs Content-Type: application/octet-stream")]
    MediaType,
    #[error("the body is larger than a {w}x{h} frame's {max} bytes")]
    TooLarge { max: usize, w: usize, h: usize },
    #[error("the frame's body did not arrive within {0} s")]
    Timeout(u64),
    #[error("the content source is not \"stream\"")]
    NotStreaming,
}

impl FrameError {
    /// A short name for counting refusals.
    pub fn kind(&self) -> &'static str {
        match self {
            FrameError::WrongSize { .. } | FrameError::WrongEyeSize { .. } => "wrong_size",
            FrameError::StaleHalf { .. } | FrameError::StaleView { .. } => "stale",
            FrameError::View(_) => "view",
            FrameError::Eye(_) => "eye",
            FrameError::Length { .. } => "length",
            FrameError::Depth { .. } => "depth",
            FrameError::Invalid(_) => "invalid",
            FrameError::Stale { .. } => "stale",
            FrameError::Torn(_) => "torn",
            FrameError::Encoding { .. } => "encoding",
            FrameError::Request(_) | FrameError::MediaType => "request",
            FrameError::TooLarge { .. } => "too_large",
            FrameError::Timeout(_) => "timeout",
            FrameError::NotStreaming => "not_streaming",
        }
    }
}

/// Decodes one frame: colour to linear light (8-bit from sRGB), depth to diopters. Raw
/// pixels, or (colour an image file) a colour and a depth image file.
pub fn decode_frame(
    desc: &FrameDesc,
    color: &[u8],
    depth: &[u8],
    display: (usize, usize),
) -> Result<Rgbd, FrameError> {
    decode_frame_into(
        desc,
        color,
        depth,
        display,
        &Planes::new(display.0 * display.1),
    )
}

/// Spare planes of one frame size, reused from frame to frame: a fresh allocation each frame
/// costs a page fault and the kernel's zeroing per page (a 1920 x 1080 frame is 33 MB).
struct Planes {
    len: usize,
    spare: Mutex<Vec<Vec<f32>>>,
}

/// Spare planes kept: two frames' worth.
const SPARE_PLANES: usize = 8;

impl Planes {
    fn new(len: usize) -> Planes {
        Planes {
            len,
            spare: Mutex::new(Vec::new()),
        }
    }
    /// A plane of `len` values (its contents are to be overwritten).
    fn take(&self) -> Vec<f32> {
        lock(&self.spare)
            .pop()
            .unwrap_or_else(|| vec![0.0; self.len])
    }
    fn give(&self, v: Vec<f32>) {
        let mut spare = lock(&self.spare);
        if v.len() == self.len && spare.len() < SPARE_PLANES {
            spare.push(v);
        }
    }
    /// A frame no one else holds: its planes are kept for the next ones.
    fn give_frame(&self, frame: Arc<Rgbd>) {
        if let Ok(Rgbd { color, depth }) = Arc::try_unwrap(frame) {
            let [r, g, b] = color.channels;
            for p in [r, g, b, depth.into_plane()] {
                self.give(p.into_vec());
            }
        }
    }
}

/// Depth values as stored: little-endian f32 bytes (raw frames) or decoded samples (files).
#[derive(Clone, Copy)]
enum DepthValues<'a> {
    Le(&'a [u8]),
    Samples(&'a [f32]),
}

impl DepthValues<'_> {
    fn at(&self, i: usize) -> f32 {
        match self {
            DepthValues::Le(b) => {
                f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
            }
            DepthValues::Samples(s) => s[i],
        }
    }
}

fn decode_frame_into(
    desc: &FrameDesc,
    color: &[u8],
    depth: &[u8],
    display: (usize, usize),
    planes: &Planes,
) -> Result<Rgbd, FrameError> {
    let (w, h) = (desc.width, desc.height);
    if (w, h) != display {
        return Err(FrameError::WrongSize {
            got_w: w,
            got_h: h,
            want_w: display.0,
            want_h: display.1,
        });
    }
    let (near, far) = depth_planes(desc)?;
    let bad = |e: dioptra_core::InputError| FrameError::Invalid(e.to_string());
    let (color, depth) = match desc.color.bytes_per_px() {
        Some(bpp) => {
            let n = w * h;
            for (what, got, want) in [
                ("colour", color.len(), n * bpp),
                ("depth", depth.len(), n * 4),
            ] {
                if got != want {
                    return Err(FrameError::Length {
                        what,
                        got,
                        want,
                        w,
                        h,
                    });
                }
            }
            let color = raw_color(desc.color, color, (w, h), planes)?;
            let depth = to_diopters(
                desc.depth,
                (near, far),
                (w, h),
                DepthValues::Le(depth),
                planes,
            );
            (color, depth?)
        }
        None => {
            let (color, samples) = decode_files(desc, color, depth)?;
            let values = DepthValues::Samples(samples.data());
            (
                color,
                to_diopters(desc.depth, (near, far), (w, h), values, planes)?,
            )
        }
    };
    let depth = DepthMap::from_diopters(Plane::from_vec(w, h, depth).map_err(bad)?).map_err(bad)?;
    Rgbd::new(color, depth).map_err(bad)
}

/// The near and far planes of a depth buffer, checked (`(1, 2)`, unused, for distances).
fn depth_planes(desc: &FrameDesc) -> Result<(f32, f32), FrameError> {
    if !desc.depth.is_buffer() {
        return Ok((1.0, 2.0));
    }
    match (desc.near, desc.far) {
        (Some(n), Some(f)) if n > 0.0 && n.is_finite() && f > n => Ok((n, f)),
        _ => Err(FrameError::Invalid(format!(
            "a {:?} depth buffer needs near and far planes in metres with 0 < near < far \
             (far may be infinite): got near {:?}, far {:?}",
            desc.depth, desc.near, desc.far
        ))),
    }
}

/// 8-bit sRGB to linear light.
fn srgb_lut() -> &'static [f32; 256] {
    static LUT: std::sync::OnceLock<[f32; 256]> = std::sync::OnceLock::new();
    LUT.get_or_init(|| std::array::from_fn(|v| srgb_to_linear(v as f32 / 255.0)))
}

/// Raw colour pixels in linear light, converted a row per task (rayon).
fn raw_color(
    format: ColorFormat,
    color: &[u8],
    (w, h): (usize, usize),
    planes: &Planes,
) -> Result<RgbImage, FrameError> {
    let (mut r, mut g, mut b) = (planes.take(), planes.take(), planes.take());
    let bpp = format.bytes_per_px().unwrap_or(3);
    let rows = r
        .par_chunks_mut(w.max(1))
        .zip(g.par_chunks_mut(w.max(1)))
        .zip(b.par_chunks_mut(w.max(1)))
        .zip(color.par_chunks(bpp * w.max(1)));
    match format {
        ColorFormat::Rgb8 | ColorFormat::Rgba8 => {
            let lut = srgb_lut();
            rows.for_each(|(((r, g), b), src)| {
                for (((r, g), b), px) in r.iter_mut().zip(g).zip(b).zip(src.chunks_exact(bpp)) {
                    *r = lut[usize::from(px[0])];
                    *g = lut[usize::from(px[1])];
                    *b = lut[usize::from(px[2])];
                }
            });
        }
        _ => {
            let value = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let finite = rows
                .map(|(((r, g), b), src)| {
                    let mut ok = true;
                    for (((r, g), b), px) in r.iter_mut().zip(g).zip(b).zip(src.chunks_exact(12)) {
                        let v = [value(&px[0..4]), value(&px[4..8]), value(&px[8..12])];
                        ok &= v.iter().all(|v| v.is_finite());
                        (*r, *g, *b) = (v[0].max(0.0), v[1].max(0.0), v[2].max(0.0));
                    }
                    ok
                })
                .reduce(|| true, |a, b| a && b);
            if !finite {
                for p in [r, g, b] {
                    planes.give(p);
                }
                // Rare: find the first bad value for the error.
                let (i, v) = color
                    .chunks_exact(4)
                    .map(value)
                    .enumerate()
                    .find(|(_, v)| !v.is_finite())
                    .unwrap_or((0, f32::NAN));
                return Err(FrameError::Invalid(format!(
                    "colour at pixel ({}, {}) is {v}",
                    (i / 3) % w,
                    (i / 3) / w
                )));
            }
        }
    }
    let bad = |e: dioptra_core::InputError| FrameError::Invalid(e.to_string());
    RgbImage::from_planes(
        Plane::from_vec(w, h, r).map_err(bad)?,
        Plane::from_vec(w, h, g).map_err(bad)?,
        Plane::from_vec(w, h, b).map_err(bad)?,
    )
    .map_err(bad)
}

/// A colour and a depth image file: each must be the frame's size (checked from its header,
/// before its pixels are allocated) and the colour file of the declared format.
fn decode_files(
    desc: &FrameDesc,
    color: &[u8],
    depth: &[u8],
) -> Result<(RgbImage, Plane), FrameError> {
    let (w, h) = (desc.width, desc.height);
    let encoding = |what: &'static str| {
        move |e: dioptra_render::RenderError| FrameError::Encoding {
            what,
            detail: match e {
                dioptra_render::RenderError::Format { detail, .. } => detail,
                other => other.to_string(),
            },
        }
    };
    let want = desc.color.file_format();
    if ImageFormat::of_bytes(color) != want {
        return Err(FrameError::Encoding {
            what: "colour file",
            detail: format!(
                "color={} and the body does not start with one (put the colour file first, \
                 then the depth file, and say where the colour ends with color_bytes)",
                desc.color.as_str()
            ),
        });
    }
    for (what, bytes) in [("colour file", color), ("depth file", depth)] {
        let (fw, fh) = encoded_size(what, bytes).map_err(encoding(what))?;
        if (fw, fh) != (w, h) {
            return Err(FrameError::Encoding {
                what,
                detail: format!("it is {fw}x{fh}; the frame is {w}x{h}"),
            });
        }
    }
    let px = (w * h) as u64;
    let color = decode_color("colour file", color, px).map_err(encoding("colour file"))?;
    let depth = decode_samples("depth file", depth, px).map_err(encoding("depth file"))?;
    Ok((color, depth))
}

/// Depth values converted to diopters a row per task (rayon), or the first pixel refused.
fn to_diopters(
    kind: DepthKind,
    (near, far): (f32, f32),
    (w, h): (usize, usize),
    values: DepthValues,
    planes: &Planes,
) -> Result<Vec<f32>, FrameError> {
    let mut out = planes.take();
    // One loop per convention, so each compiles to its own conversion with no match inside.
    let good = match kind {
        DepthKind::Metres => convert_rows(&mut out, w, values, |v| {
            DepthKind::Metres.diopters(v, near, far)
        }),
        DepthKind::Millimetres => convert_rows(&mut out, w, values, |v| {
            DepthKind::Millimetres.diopters(v, near, far)
        }),
        DepthKind::Diopters => convert_rows(&mut out, w, values, |v| {
            DepthKind::Diopters.diopters(v, near, far)
        }),
        DepthKind::Gl => convert_rows(&mut out, w, values, |v| {
            DepthKind::Gl.diopters(v, near, far)
        }),
        DepthKind::GlReversed => convert_rows(&mut out, w, values, |v| {
            DepthKind::GlReversed.diopters(v, near, far)
        }),
        DepthKind::Vulkan => convert_rows(&mut out, w, values, |v| {
            DepthKind::Vulkan.diopters(v, near, far)
        }),
        DepthKind::VulkanReversed => convert_rows(&mut out, w, values, |v| {
            DepthKind::VulkanReversed.diopters(v, near, far)
        }),
    };
    if good {
        return Ok(out);
    }
    planes.give(out);
    // Rare: the first refused pixel, for the error.
    let refused = (0..w * h).find_map(|i| {
        let v = values.at(i);
        kind.diopters(v, near, far).err().map(|why| (i, v, why))
    });
    let (i, v, why) = refused.unwrap_or((0, f32::NAN, "refused"));
    Err(FrameError::Depth {
        x: i % w.max(1),
        y: i / w.max(1),
        value: v,
        why,
    })
}

/// `out`'s rows of `w` converted from `values` by `convert`, a row per task (rayon); whether
/// every value converted.
fn convert_rows(
    out: &mut [f32],
    w: usize,
    values: DepthValues,
    convert: impl Fn(f32) -> Result<f32, &'static str> + Sync,
) -> bool {
    let put = |v: f32, d: &mut f32| match convert(v) {
        Ok(v) => {
            *d = v;
            true
        }
        Err(_) => false,
    };
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .map(|(y, row)| {
            let from = y * w..(y + 1) * w;
            match values {
                DepthValues::Le(b) => b[4 * from.start..4 * from.end]
                    .chunks_exact(4)
                    .zip(row)
                    .fold(true, |ok, (v, d)| {
                        put(f32::from_le_bytes([v[0], v[1], v[2], v[3]]), d) & ok
                    }),
                DepthValues::Samples(s) => s[from]
                    .iter()
                    .zip(row)
                    .fold(true, |ok, (&v, d)| put(v, d) & ok),
            }
        })
        .reduce(|| true, |a, b| a && b)
}

fn count_refusal(st: &mut StreamStatus, e: FrameError) -> FrameError {
    *st.refused.entry(e.kind()).or_default() += 1;
    st.last_error = Some(e.to_string());
    e
}

/// What `/status` shows under `content` for a stream.
#[derive(Debug, Clone, Default, Serialize)]
pub struct StreamStatus {
    pub source: &'static str,
    /// A stereo rig: frames may be one eye's half, a pair shown once both arrived.
    pub stereo: bool,
    /// Frames accepted (on a stereo rig a pair counts once, when its second half arrives).
    pub received: u64,
    /// Accepted frames the display took up.
    pub shown: u64,
    /// Accepted frames a newer one replaced before the display took them up.
    pub replaced: u64,
    /// One eye's halves accepted (stereo rig).
    pub halves_received: u64,
    /// Light-field content: views of a grid accepted (`content.views`).
    pub views_received: u64,
    /// Halves (and views of a grid) waiting for the rest of their frame's.
    pub halves_waiting: u64,
    /// Halves whose partner never came: dropped, never shown, when a newer pair or frame
    /// completed (or more than [`MAX_WAITING`] sequence numbers waited).
    pub halves_dropped: u64,
    /// Frames refused, by reason; the newest reason in `last_error`.
    pub refused: std::collections::BTreeMap<&'static str, u64>,
    pub last_error: Option<String>,
    /// Sequence number of the newest frame (or half) accepted, and of the one on show.
    pub newest_seq: Option<u64>,
    pub on_show_seq: Option<u64>,
    /// Host time (ns) the newest accepted frame arrived, and its application time.
    pub newest_received_ns: Option<u64>,
    pub newest_app_time_ns: Option<u64>,
    /// How old the newest accepted frame is, ms (at the time of asking).
    pub newest_age_ms: Option<f64>,
    pub ring: Option<String>,
    /// Light-field content: views per side of a frame's grid.
    pub views: Option<usize>,
    #[serde(skip)]
    newest_at: Option<std::time::Instant>,
}

/// Sequence numbers whose halves may wait for their partner at once; one more drops the
/// oldest (each waiting half holds a frame's memory).
pub const MAX_WAITING: usize = 4;

/// A frame ready to show: one view, or (`eyes`) a pair whose `frame` is the left eye's; with
/// `views`, a grid's (each eye's) whose `frame` and `eyes` are its central views.
struct Pending {
    frame: Arc<Rgbd>,
    eyes: Option<[Arc<Rgbd>; 2]>,
    views: Option<Arc<[ContentView]>>,
    seq: u64,
    arrival: Arrival,
}

impl Pending {
    /// Every image it holds, once each (for giving their memory back).
    fn images(self) -> Vec<Arc<Rgbd>> {
        match (self.views, self.eyes) {
            (Some(views), _) => views.iter().map(|v| v.rgbd.clone()).collect(),
            (None, Some([l, r])) => vec![l, r],
            (None, None) => vec![self.frame],
        }
    }
}

/// A frame decoded, before it is paired or shown.
#[derive(Debug)]
enum Decoded {
    /// One view (a mono rig's frame, or a mono frame on a stereo rig).
    Whole(Rgbd),
    /// Both eyes, from a side-by-side frame.
    Pair([Rgbd; 2]),
    /// One eye's half of a pair.
    Half(Side, Rgbd),
    /// One view of a grid (index row by row; an eye's own grid, or the one grid).
    View(Option<Side>, usize, Rgbd),
}

impl Decoded {
    /// The part of a frame it is; `None`: a whole frame.
    fn part(&self) -> Option<Part> {
        match self {
            Decoded::Half(e, _) => Some(Part {
                eye: Some(*e),
                view: None,
            }),
            Decoded::View(eye, v, _) => Some(Part {
                eye: *eye,
                view: Some(*v),
            }),
            _ => None,
        }
    }
}

/// A part of a frame sent on its own: an eye's half (`view` `None`) or a view of a grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Part {
    eye: Option<Side>,
    view: Option<usize>,
}

impl Part {
    /// The key of its newest sequence number.
    fn key(self) -> (u32, Option<usize>) {
        (super::ring::eye_code(self.eye), self.view)
    }

    /// What its frame is made of, and its place there, for a grid of `per_eye` views.
    fn place(self, per_eye: usize) -> (Parts, usize) {
        match (self.eye, self.view) {
            (Some(e), None) => (Parts::Halves, eye_index(e)),
            (None, Some(v)) => (Parts::Grid, v),
            (Some(e), Some(v)) => (Parts::EyeGrids, eye_index(e) * per_eye + v),
            // Not a part: never asked.
            (None, None) => (Parts::Halves, 0),
        }
    }
}

/// What a frame sent in parts is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Parts {
    /// A stereo pair's two halves.
    Halves,
    /// The views of one grid.
    Grid,
    /// Each eye's views of its own grid, the left eye's first.
    EyeGrids,
}

impl Parts {
    fn count(self, per_eye: usize) -> usize {
        match self {
            Parts::Halves => 2,
            Parts::Grid => per_eye,
            Parts::EyeGrids => 2 * per_eye,
        }
    }
}

/// A frame's parts as they arrive.
struct Waiting {
    parts: Parts,
    got: Vec<Option<Arc<Rgbd>>>,
}

/// The part of a frame an eye and a view name (`None`: a whole frame).
fn part_of(eye: Option<Side>, view: Option<usize>) -> Option<Part> {
    (eye.is_some() || view.is_some()).then_some(Part { eye, view })
}

fn eye_index(e: Side) -> usize {
    match e {
        Side::Left => 0,
        Side::Right => 1,
    }
}

/// The collecting of frames sent in parts (a stereo rig's halves, a grid's views), and the
/// sequence numbers that make a part stale.
#[derive(Default)]
struct Pairing {
    /// Each part's newest accepted (an eye's half, a view of a grid), by [`Part::key`].
    newest_part: std::collections::BTreeMap<(u32, Option<usize>), u64>,
    /// Frames up to this number can no longer be shown: the newest frame complete (accepted
    /// whole, or its last part arrived), or the newest dropped incomplete.
    floor: Option<u64>,
    /// Parts waiting for the rest of their frame's (the same sequence number).
    waiting: std::collections::BTreeMap<u64, Waiting>,
}

impl Pairing {
    fn halves_waiting(&self) -> u64 {
        self.waiting
            .values()
            .map(|w| w.got.iter().flatten().count() as u64)
            .sum()
    }
}

/// The shared-memory ring: the file and its mapping.
struct Ring {
    path: PathBuf,
    map: memmap2::MmapRaw,
    slot_bytes: usize,
}

impl Ring {
    fn create(path: &Path, header: RingHeader) -> std::io::Result<Ring> {
        use std::os::unix::fs::OpenOptionsExt;
        let slot_bytes = header.slot_bytes as usize;
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            if !meta.file_type().is_file() {
                return Err(std::io::Error::other(format!(
                    "{} exists and is not a regular file; choose another content.ring",
                    path.display()
                )));
            }
            // A ring an earlier daemon left.
            std::fs::remove_file(path)?;
        }
        let mut f = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .mode(0o600)
            .custom_flags(libc_o_nofollow())
            .open(path)?;
        f.write_all(&header.encode())?;
        f.set_len((RING_HEADER + RING_SLOTS * slot_bytes) as u64)?;
        let map = memmap2::MmapOptions::new().map_raw(&f)?;
        Ok(Ring {
            path: path.to_path_buf(),
            map,
            slot_bytes,
        })
    }

    /// Copies `len` bytes at `offset`. The application may write the file at any time, so it
    /// is read through the raw pointer, never as a Rust reference.
    fn read(&self, offset: usize, len: usize) -> Vec<u8> {
        let mut out = vec![0u8; len];
        debug_assert!(offset + len <= self.map.len());
        // SAFETY: offset + len is inside the mapping (checked by the callers against
        // slot_bytes); the bytes are copied, not referenced.
        unsafe {
            std::ptr::copy_nonoverlapping(self.map.as_ptr().add(offset), out.as_mut_ptr(), len);
        }
        out
    }

    fn seq(&self, slot: usize) -> u64 {
        let b = self.read(RING_HEADER + slot * self.slot_bytes, 8);
        std::sync::atomic::fence(std::sync::atomic::Ordering::Acquire);
        u64::from_le_bytes(b.try_into().unwrap_or([0; 8]))
    }
}

impl Drop for Ring {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

fn libc_o_nofollow() -> i32 {
    // O_NOFOLLOW on Linux (x86-64, aarch64): do not open through a planted symlink.
    0o400000
}

/// The stream source: the newest accepted frame, waiting for the display.
pub struct StreamFrames {
    /// One eye's image (the display's on a mono rig).
    size: (usize, usize),
    stereo: bool,
    /// Light-field content: views per side and each view's position (metres, row by row).
    grid: Option<(usize, Vec<[f32; 2]>)>,
    ring: Option<Ring>,
    pending: Mutex<Option<Pending>>,
    status: Mutex<StreamStatus>,
    /// Locked only while `status` is.
    pairing: Mutex<Pairing>,
    /// Memory of frames done with, for the next ones.
    planes: Planes,
    /// The same for side-by-side frames (2 x width), before they are split.
    wide_planes: Planes,
    /// Notified at each accepted frame: the loop takes it up then.
    arrivals: Arc<tokio::sync::Notify>,
    /// The views on show (given back for reuse when the next are taken up), and how many
    /// frames the loop has been handed.
    on_show: Mutex<(Vec<Arc<Rgbd>>, u64)>,
}

impl std::fmt::Debug for StreamFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamFrames")
            .field("size", &self.size)
            .field("stereo", &self.stereo)
            .finish_non_exhaustive()
    }
}

impl StreamFrames {
    /// A stream of `width` x `height` frames with its ring at `ring` (`None`: `PUT /frame`
    /// only).
    pub fn open(width: usize, height: usize, ring: Option<&Path>) -> std::io::Result<Self> {
        Self::with_eyes(width, height, false, ring)
    }

    /// [`StreamFrames::open`] for a rig whose display is `stereo` (`width` x `height` is then
    /// one eye's image): frames may be one eye's half or both eyes side by side.
    pub fn with_eyes(
        width: usize,
        height: usize,
        stereo: bool,
        ring: Option<&Path>,
    ) -> std::io::Result<Self> {
        let header = RingHeader::for_eyes(width, height, stereo);
        let ring = ring.map(|p| Ring::create(p, header)).transpose()?;
        Ok(StreamFrames {
            size: (width, height),
            stereo,
            grid: None,
            status: Mutex::new(StreamStatus {
                source: "stream",
                stereo,
                ring: ring.as_ref().map(|r| r.path.display().to_string()),
                ..Default::default()
            }),
            ring,
            pending: Mutex::new(None),
            pairing: Mutex::new(Pairing::default()),
            planes: Planes::new(width * height),
            wide_planes: Planes::new(2 * width * height),
            arrivals: Arc::new(tokio::sync::Notify::new()),
            on_show: Mutex::new((Vec::new(), 0)),
        })
    }

    /// The stream with light-field content: frames may be a grid of `views` x `views` views
    /// over a square of `span_mm`, each sent on its own naming its view.
    pub fn with_view_grid(mut self, views: usize, span_mm: f64) -> Result<Self, String> {
        let positions = dioptra_sim::scene::light_field_positions(views, (span_mm * 1e-3) as f32)
            .map_err(|e| e.to_string())?;
        self.grid = Some((views, positions));
        lock(&self.status).views = Some(views);
        Ok(self)
    }

    /// Views per eye of a grid (1 without one).
    fn per_eye(&self) -> usize {
        self.grid.as_ref().map_or(1, |(n, _)| n * n)
    }

    /// The view `PUT /frame?view=ROW_COLUMN` names (`None`: a whole frame), or why it is
    /// refused.
    pub fn parse_view(&self, view: Option<&str>) -> Result<Option<usize>, FrameError> {
        let Some(name) = view else {
            return Ok(None);
        };
        let n = self.grid.as_ref().map_or(0, |(n, _)| *n);
        let parsed = name
            .split_once('_')
            .and_then(|(r, c)| Some((r.parse::<usize>().ok()?, c.parse::<usize>().ok()?)));
        match parsed {
            Some((r, c)) if r < n && c < n => self.check_view(Some(r * n + c)),
            _ if n == 0 => self.check_view(Some(0)),
            _ => Err(FrameError::View(format!(
                "view={name:?}: expected ROW_COLUMN, each 0 to {} (content.views = {n})",
                n - 1
            ))),
        }
    }

    /// A view is refused on a rig without a grid, and past its grid.
    fn check_view(&self, view: Option<usize>) -> Result<Option<usize>, FrameError> {
        match (view, &self.grid) {
            (None, _) => Ok(None),
            (Some(_), None) => Err(FrameError::View(
                "this rig's content is one view a frame: send frames without a view, or set \
                 content.views for light-field content"
                    .into(),
            )),
            (Some(v), Some((n, _))) if v >= n * n => Err(FrameError::View(format!(
                "view {v}: the grid has views 0 to {} (content.views = {n})",
                n * n - 1
            ))),
            (Some(v), _) => Ok(Some(v)),
        }
    }

    /// The frame shown before any arrives: black at optical infinity.
    pub fn placeholder(&self) -> Rgbd {
        let (w, h) = self.size;
        let zero = || Plane::from_vec(w, h, vec![0.0; w * h]).expect("sized plane");
        Rgbd::new(
            RgbImage::from_planes(zero(), zero(), zero()).expect("equal planes"),
            DepthMap::from_diopters(zero()).expect("0 D is valid"),
        )
        .expect("equal sizes")
    }

    /// `GET /frame/ring`: where the ring is and its layout.
    pub fn ring_json(&self) -> serde_json::Value {
        match &self.ring {
            None => serde_json::json!({
                "path": null,
                "width": self.size.0,
                "height": self.size.1,
                "stereo": self.stereo,
                "views": self.grid.as_ref().map(|(n, _)| n),
            }),
            Some(r) => serde_json::json!({
                "path": r.path.display().to_string(),
                "magic": String::from_utf8_lossy(RING_MAGIC),
                "version": RING_VERSION,
                "slots": RING_SLOTS,
                "width": self.size.0,
                "height": self.size.1,
                "stereo": self.stereo,
                "views": self.grid.as_ref().map(|(n, _)| n),
                "header_bytes": RING_HEADER,
                "slot_header_bytes": SLOT_HEADER,
                "slot_bytes": r.slot_bytes,
                "slot_header": super::ring::layout_json(super::ring::SLOT_FIELDS),
                "eyes": super::ring::EYE_CODES.iter().map(|&(n, c)| (n.to_string(), c.into()))
                    .collect::<serde_json::Map<_, _>>(),
            }),
        }
    }

    /// The eye `PUT /frame?eye=` names (`None`: no eye), or why it is refused.
    pub fn parse_eye(&self, eye: Option<&str>) -> Result<Option<Side>, FrameError> {
        let Some(name) = eye else {
            return Ok(None);
        };
        let side = Side::parse(name).ok_or_else(|| {
            FrameError::Eye(format!(
                "eye={name:?}: expected left or right (or no eye: a mono frame, or on a \
                 stereo rig both eyes side by side)"
            ))
        })?;
        self.check_eye(Some(side))
    }

    /// `eye` is refused on a rig that shows one image.
    fn check_eye(&self, eye: Option<Side>) -> Result<Option<Side>, FrameError> {
        match eye {
            Some(e) if !self.stereo => Err(FrameError::Eye(format!(
                "eye {}: this rig shows one image (display.layout = \"one\"); send frames \
                 without an eye",
                e.as_str()
            ))),
            _ => Ok(eye),
        }
    }

    /// Whether a frame of `width` x `height` for `eye` is both eyes side by side (a stereo
    /// rig's 2 x width frame without an eye), or why its size is refused.
    pub fn side_by_side(
        &self,
        width: usize,
        height: usize,
        eye: Option<Side>,
    ) -> Result<bool, FrameError> {
        let (w, h) = self.size;
        if (width, height) == (w, h) {
            return Ok(false);
        }
        if self.stereo && eye.is_none() && (width, height) == (2 * w, h) {
            return Ok(true);
        }
        Err(if self.stereo {
            FrameError::WrongEyeSize {
                eye,
                got_w: width,
                got_h: height,
                want_w: w,
                want_h: h,
            }
        } else {
            FrameError::WrongSize {
                got_w: width,
                got_h: height,
                want_w: w,
                want_h: h,
            }
        })
    }

    /// A frame from `PUT /frame` (no eye: mono, or on a stereo rig possibly side by side).
    pub fn submit(
        &self,
        desc: &FrameDesc,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        self.submit_eye(desc, None, color, depth, now)
    }

    /// A frame from `PUT /frame?eye=`: `eye`'s half of a pair, or (`None`) a whole frame.
    pub fn submit_eye(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        self.submit_part(desc, eye, None, color, depth, now)
    }

    /// A frame from `PUT /frame?eye=&view=`: a view of a grid (`view`; `eye`'s own grid on a
    /// stereo rig), `eye`'s half of a pair, or (both `None`) a whole frame.
    pub fn submit_part(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        view: Option<usize>,
        color: &[u8],
        depth: &[u8],
        now: Timestamp,
    ) -> Result<u64, FrameError> {
        let t0 = std::time::Instant::now();
        let r = self
            .check_eye(eye)
            .and_then(|eye| Ok((eye, self.check_view(view)?)))
            .and_then(|(eye, view)| Ok((self.check_seq(desc.seq, part_of(eye, view))?, eye, view)))
            .and_then(|(seq, eye, view)| Ok((seq, self.decode(desc, eye, view, color, depth)?)));
        self.accept(r, desc.app_time_ns, now, t0)
    }

    /// Decodes a frame for `eye` (and `view`): a side-by-side one split into the two eyes'.
    fn decode(
        &self,
        desc: &FrameDesc,
        eye: Option<Side>,
        view: Option<usize>,
        color: &[u8],
        depth: &[u8],
    ) -> Result<Decoded, FrameError> {
        if let Some(v) = view {
            let (w, h) = self.size;
            if (desc.width, desc.height) != (w, h) {
                return Err(FrameError::View(format!(
                    "the view's frame is {}x{}; a view is one eye's image, {w}x{h}",
                    desc.width, desc.height
                )));
            }
            let frame = decode_frame_into(desc, color, depth, self.size, &self.planes)?;
            return Ok(Decoded::View(eye, v, frame));
        }
        if self.side_by_side(desc.width, desc.height, eye)? {
            let (w, h) = self.size;
            let wide = decode_frame_into(desc, color, depth, (2 * w, h), &self.wide_planes)?;
            return Ok(Decoded::Pair(self.split(wide)?));
        }
        let frame = decode_frame_into(desc, color, depth, self.size, &self.planes)?;
        Ok(match eye {
            Some(e) => Decoded::Half(e, frame),
            None => Decoded::Whole(frame),
        })
    }

    /// A side-by-side frame's left and right halves.
    fn split(&self, wide: Rgbd) -> Result<[Rgbd; 2], FrameError> {
        let (w, h) = self.size;
        let Rgbd { color, depth } = wide;
        let [r, g, b] = color.channels;
        let mut halves: [Vec<Plane>; 2] = [Vec::new(), Vec::new()];
        let bad = |e: dioptra_core::InputError| FrameError::Invalid(e.to_string());
        for plane in [r, g, b, depth.into_plane()] {
            let src = plane.into_vec();
            let (mut left, mut right) = (self.planes.take(), self.planes.take());
            for ((row, l), r) in src
                .chunks_exact(2 * w.max(1))
                .zip(left.chunks_exact_mut(w.max(1)))
                .zip(right.chunks_exact_mut(w.max(1)))
            {
                l.copy_from_slice(&row[..w]);
                r.copy_from_slice(&row[w..]);
            }
            self.wide_planes.give(src);
            halves[0].push(Plane::from_vec(w, h, left).map_err(bad)?);
            halves[1].push(Plane::from_vec(w, h, right).map_err(bad)?);
        }
        let view = |planes: Vec<Plane>| -> Result<Rgbd, FrameError> {
            let [r, g, b, d]: [Plane; 4] = planes
                .try_into()
                .map_err(|_| FrameError::Invalid("four planes".into()))?;
            let color = RgbImage::from_planes(r, g, b).map_err(bad)?;
            Rgbd::new(color, DepthMap::from_diopters(d).map_err(bad)?).map_err(bad)
        };
        let [left, right] = halves;
        Ok([view(left)?, view(right)?])
    }

    /// A frame the application wrote into ring slot `slot` with sequence number `seq`.
    pub fn submit_slot(&self, slot: usize, seq: u64, now: Timestamp) -> Result<u64, FrameError> {
        let t0 = std::time::Instant::now();
        let r = self.read_slot(slot, seq);
        let app = r.as_ref().ok().and_then(|(_, _, a)| *a);
        self.accept(r.map(|(s, f, _)| (s, f)), app, now, t0)
    }

    fn read_slot(&self, slot: usize, seq: u64) -> Result<(u64, Decoded, Option<u64>), FrameError> {
        self.read_slot_then(slot, seq, || {})
    }

    /// [`StreamFrames::read_slot`], calling `copied` once the slot's bytes are copied (a test
    /// rewrites the slot there, as an application that does not wait for the answer might).
    fn read_slot_then(
        &self,
        slot: usize,
        seq: u64,
        copied: impl FnOnce(),
    ) -> Result<(u64, Decoded, Option<u64>), FrameError> {
        let ring = self.ring.as_ref().ok_or_else(|| {
            FrameError::Invalid("this daemon has no shared-memory ring: use PUT /frame".into())
        })?;
        if slot >= RING_SLOTS {
            return Err(FrameError::Invalid(format!(
                "slot {slot}: the ring has slots 0 to {}",
                RING_SLOTS - 1
            )));
        }
        let base = RING_HEADER + slot * ring.slot_bytes;
        let in_slot = ring.seq(slot);
        if in_slot != seq {
            return Err(FrameError::Invalid(format!(
                "slot {slot} holds sequence number {in_slot}, not {seq} (write the sequence \
                 number last, after the frame)"
            )));
        }
        let mut bytes = [0u8; SLOT_HEADER];
        bytes.copy_from_slice(&ring.read(base, SLOT_HEADER));
        let h = SlotHeader::decode(&bytes);
        let eye = eye_of_code(h.eye).ok_or_else(|| {
            FrameError::Eye(format!(
                "slot {slot}: unknown eye {} (0 none, 1 left, 2 right)",
                h.eye
            ))
        })?;
        let eye = self.check_eye(eye)?;
        let view = self.check_view(h.view.checked_sub(1).map(|v| v as usize))?;
        let seq = self.check_seq(Some(seq), part_of(eye, view))?;
        let color = ColorFormat::from_code(h.color_format).ok_or_else(|| {
            FrameError::Invalid(format!(
                "slot {slot}: unknown colour format {}",
                h.color_format
            ))
        })?;
        let depth = DepthKind::from_code(h.depth_kind).ok_or_else(|| {
            FrameError::Invalid(format!("slot {slot}: unknown depth kind {}", h.depth_kind))
        })?;
        let desc = FrameDesc {
            width: h.width as usize,
            height: h.height as usize,
            color,
            depth,
            near: Some(h.near),
            far: Some(h.far),
            seq: Some(seq),
            app_time_ns: Some(h.app_time_ns).filter(|&t| t != 0),
        };
        let (cb, db) = (h.color_bytes as usize, h.depth_bytes as usize);
        let room = ring.slot_bytes - SLOT_HEADER;
        if cb.checked_add(db).is_none_or(|total| total > room) {
            return Err(FrameError::Invalid(format!(
                "slot {slot}: {cb} colour and {db} depth bytes do not fit its {room}"
            )));
        }
        let color_bytes = ring.read(base + SLOT_HEADER, cb);
        let depth_bytes = ring.read(base + SLOT_HEADER + cb, db);
        copied();
        if ring.seq(slot) != seq {
            return Err(FrameError::Torn(slot));
        }
        let frame = self.decode(&desc, eye, view, &color_bytes, &depth_bytes)?;
        Ok((seq, frame, desc.app_time_ns))
    }

    /// The sequence number a frame (or a part of one) gets: its own if new, or the next.
    fn check_seq(&self, seq: Option<u64>, part: Option<Part>) -> Result<u64, FrameError> {
        let st = lock(&self.status);
        let pairing = lock(&self.pairing);
        next_seq(&st, &pairing, seq, part)
    }

    fn accept(
        &self,
        r: Result<(u64, Decoded), FrameError>,
        app_time_ns: Option<u64>,
        now: Timestamp,
        started: std::time::Instant,
    ) -> Result<u64, FrameError> {
        // Ready once copied and converted: the request's arrival plus that work.
        let arrival = Arrival {
            arrived: now,
            ready: now + started.elapsed(),
        };
        let mut st = lock(&self.status);
        let (seq, decoded) = match r {
            Err(e) => return Err(count_refusal(&mut st, e)),
            Ok(r) => r,
        };
        let mut pairing = lock(&self.pairing);
        // Two requests may race past check_seq: the newer wins. A part must fit the parts
        // of its frame already in (a grid's view with an eye, or without, as the first).
        let per_eye = self.per_eye();
        let misfit = decoded.part().and_then(|part| {
            let (parts, _) = part.place(per_eye);
            let first = pairing.waiting.get(&seq).map(|w| w.parts)?;
            (first != parts).then(|| {
                FrameError::View(format!(
                    "frame {seq}'s parts so far are {}, and this one is {}: send each eye's \
                     views with eye= (or none with it), for every view of a frame alike",
                    parts_name(first),
                    parts_name(parts)
                ))
            })
        });
        if let Some(e) = next_seq(&st, &pairing, Some(seq), decoded.part())
            .err()
            .or(misfit)
        {
            drop(pairing);
            self.give_back(decoded);
            return Err(count_refusal(&mut st, e));
        }
        st.newest_seq = Some(st.newest_seq.map_or(seq, |n| n.max(seq)));
        st.newest_received_ns = Some(now.0);
        st.newest_at = Some(std::time::Instant::now());
        st.newest_app_time_ns = app_time_ns;
        let complete = match decoded {
            Decoded::Whole(f) => Some((Arc::new(f), None, None)),
            Decoded::Pair([l, r]) => {
                let l = Arc::new(l);
                Some((l.clone(), Some([l, Arc::new(r)]), None))
            }
            Decoded::Half(eye, f) => {
                st.halves_received += 1;
                self.add_part(
                    &mut st,
                    &mut pairing,
                    seq,
                    Part {
                        eye: Some(eye),
                        view: None,
                    },
                    f,
                )
            }
            Decoded::View(eye, v, f) => {
                st.views_received += 1;
                self.add_part(&mut st, &mut pairing, seq, Part { eye, view: Some(v) }, f)
            }
        };
        if let Some((frame, eyes, views)) = complete {
            // Parts older than a complete frame can no longer be shown.
            let newer = pairing.waiting.split_off(&(seq + 1));
            let older = std::mem::replace(&mut pairing.waiting, newer);
            for (_, parts) in older {
                st.halves_dropped += self.drop_halves(parts);
            }
            pairing.floor = Some(seq);
            st.received += 1;
            let old = lock(&self.pending).replace(Pending {
                frame,
                eyes,
                views,
                seq,
                arrival,
            });
            if let Some(old) = old {
                self.give_pending(old);
                st.replaced += 1;
            }
            self.arrivals.notify_one();
        }
        st.halves_waiting = pairing.halves_waiting();
        Ok(seq)
    }

    /// Files `part` of frame `seq` among its frame's parts: the frame (its view, its eyes'
    /// views and every view of a grid) when it was the last one missing.
    #[allow(clippy::type_complexity)]
    fn add_part(
        &self,
        st: &mut StreamStatus,
        pairing: &mut Pairing,
        seq: u64,
        part: Part,
        frame: Rgbd,
    ) -> Option<(
        Arc<Rgbd>,
        Option<[Arc<Rgbd>; 2]>,
        Option<Arc<[ContentView]>>,
    )> {
        let per_eye = self.per_eye();
        let (parts, i) = part.place(per_eye);
        pairing.newest_part.insert(part.key(), seq);
        let waiting = pairing.waiting.entry(seq).or_insert_with(|| Waiting {
            parts,
            got: vec![None; parts.count(per_eye)],
        });
        waiting.got[i] = Some(Arc::new(frame));
        if waiting.got.iter().any(Option::is_none) {
            if pairing.waiting.len() > MAX_WAITING {
                if let Some((k, oldest)) = pairing.waiting.pop_first() {
                    st.halves_dropped += self.drop_halves(oldest);
                    pairing.floor = pairing.floor.max(Some(k));
                }
            }
            return None;
        }
        // The frame arrives with its last part.
        let got: Vec<Arc<Rgbd>> = pairing
            .waiting
            .remove(&seq)?
            .got
            .into_iter()
            .flatten()
            .collect();
        let centre = self.grid.as_ref().map_or(0, |(n, _)| (n / 2) * n + n / 2);
        Some(match parts {
            Parts::Halves => (got[0].clone(), Some([got[0].clone(), got[1].clone()]), None),
            Parts::Grid | Parts::EyeGrids => {
                let positions = self.grid.as_ref().map_or(&[][..], |(_, p)| &p[..]);
                let eyes: &[Option<Side>] = if parts == Parts::Grid {
                    &[None]
                } else {
                    &[Some(Side::Left), Some(Side::Right)]
                };
                let views = ContentView::grid(eyes, positions, &got);
                let pair = (parts == Parts::EyeGrids)
                    .then(|| [got[centre].clone(), got[per_eye + centre].clone()]);
                (got[centre].clone(), pair, Some(views))
            }
        })
    }

    /// Gives back the memory of a frame's parts dropped; how many there were.
    fn drop_halves(&self, waiting: Waiting) -> u64 {
        let mut n = 0;
        for h in waiting.got.into_iter().flatten() {
            self.planes.give_frame(h);
            n += 1;
        }
        n
    }

    fn give_back(&self, d: Decoded) {
        match d {
            Decoded::Whole(f) | Decoded::Half(_, f) | Decoded::View(_, _, f) => {
                self.planes.give_frame(Arc::new(f))
            }
            Decoded::Pair(p) => p
                .into_iter()
                .for_each(|f| self.planes.give_frame(Arc::new(f))),
        }
    }

    fn give_pending(&self, p: Pending) {
        // A pair's `frame` is one of its eyes' views, a grid's one of its views: each image
        // is given back once.
        for image in p.images() {
            self.planes.give_frame(image);
        }
    }

    /// A frame the display is done with: its memory is reused for the next ones when no one
    /// else holds it.
    pub fn recycle(&self, frame: Arc<Rgbd>) {
        self.planes.give_frame(frame);
    }

    /// Counts a frame refused before it was read (a request that does not describe one, or
    /// one of the wrong size), as [`StreamFrames::submit`] counts its own refusals.
    pub fn refuse(&self, e: FrameError) -> FrameError {
        count_refusal(&mut lock(&self.status), e)
    }

    /// The newest frame not yet taken up by the display, if any, and when it arrived (a pair:
    /// the left eye's view; [`Content::poll`] gives both).
    pub fn take_new(&self) -> Option<(Arc<Rgbd>, Arrival)> {
        self.take_pending().map(|p| (p.frame, p.arrival))
    }

    fn take_pending(&self) -> Option<Pending> {
        let p = lock(&self.pending).take()?;
        let mut st = lock(&self.status);
        st.shown += 1;
        st.on_show_seq = Some(p.seq);
        Some(p)
    }

    pub fn status(&self) -> StreamStatus {
        let mut st = lock(&self.status).clone();
        st.newest_age_ms = st.newest_at.map(|t| t.elapsed().as_secs_f64() * 1e3);
        st
    }
}

/// The sequence number a frame (or a part of one) gets: its own if newer than the newest
/// accepted (a part: than the newest of the same part and the newest complete frame), else
/// stale; a frame without one gets the next. A part must carry its own.
fn next_seq(
    st: &StreamStatus,
    pairing: &Pairing,
    seq: Option<u64>,
    part: Option<Part>,
) -> Result<u64, FrameError> {
    let Some(part) = part else {
        return match (seq, st.newest_seq) {
            (Some(s), Some(n)) if s <= n => Err(FrameError::Stale { seq: s, newest: n }),
            (Some(s), _) => Ok(s),
            (None, n) => Ok(n.map_or(1, |n| n + 1)),
        };
    };
    let seq = seq.ok_or_else(|| {
        FrameError::Request(match (part.eye, part.view) {
            (Some(eye), None) => format!(
                "the {} eye's frame needs its sequence number (seq=N): a pair's two halves \
                 share it",
                eye.as_str()
            ),
            _ => {
                "a view needs its frame's sequence number (seq=N): a frame's views share it".into()
            }
        })
    })?;
    let newest = pairing
        .newest_part
        .get(&part.key())
        .copied()
        .max(pairing.floor);
    match (newest, part.eye, part.view) {
        (Some(n), Some(eye), None) if seq <= n => Err(FrameError::StaleHalf {
            eye,
            seq,
            newest: n,
        }),
        (Some(n), eye, Some(v)) if seq <= n => Err(FrameError::StaleView {
            view: match eye {
                Some(e) => format!("{v} of the {} eye", e.as_str()),
                None => v.to_string(),
            },
            seq,
            newest: n,
        }),
        _ => Ok(seq),
    }
}

/// What a frame's parts are, in an error's words.
fn parts_name(parts: Parts) -> &'static str {
    match parts {
        Parts::Halves => "an eye's halves",
        Parts::Grid => "views of one grid",
        Parts::EyeGrids => "views of each eye's grid",
    }
}

impl Content for StreamFrames {
    /// The newest accepted frame (or complete pair) not taken up yet; at the first call, the
    /// black placeholder if none arrived. The views it replaces are given back for reuse.
    fn poll(&self, _now: Timestamp) -> Option<ContentFrame> {
        let mut on_show = lock(&self.on_show);
        let (p, arrival) = match self.take_pending() {
            Some(p) => {
                let arrival = Some(p.arrival);
                (p, arrival)
            }
            None if on_show.1 == 0 => (
                Pending {
                    frame: Arc::new(self.placeholder()),
                    eyes: None,
                    views: None,
                    seq: 0,
                    arrival: Arrival {
                        arrived: Timestamp::ZERO,
                        ready: Timestamp::ZERO,
                    },
                },
                None,
            ),
            None => return None,
        };
        let frame = ContentFrame {
            arrival,
            eyes: p.eyes.clone(),
            views: p.views.clone(),
            ..ContentFrame::new(on_show.1 + 1, p.frame.clone())
        };
        for old in std::mem::replace(&mut on_show.0, p.images()) {
            self.recycle(old);
        }
        on_show.1 += 1;
        Some(frame)
    }
    fn arrivals(&self) -> Option<Arc<tokio::sync::Notify>> {
        Some(self.arrivals.clone())
    }
    fn status(&self) -> serde_json::Value {
        serde_json::to_value(StreamFrames::status(self)).unwrap_or_default()
    }
    fn frame_ingest(&self) -> Option<&StreamFrames> {
        Some(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn desc(w: usize, h: usize, color: ColorFormat, depth: DepthKind) -> FrameDesc {
        FrameDesc {
            width: w,
            height: h,
            color,
            depth,
            near: Some(0.1),
            far: Some(100.0),
            seq: None,
            app_time_ns: None,
        }
    }

    fn f32s(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    /// A depth buffer value of a point at `z` metres, by each API's projection.
    fn buffer_value(kind: DepthKind, z: f64, n: f64, f: f64) -> f32 {
        let vk = if f.is_infinite() {
            1.0 - n / z
        } else {
            f * (z - n) / (z * (f - n))
        };
        let gl = if f.is_infinite() {
            1.0 - 2.0 * n / z
        } else {
            (f + n - 2.0 * f * n / z) / (f - n)
        };
        (match kind {
            DepthKind::Vulkan => vk,
            DepthKind::VulkanReversed => 1.0 - vk,
            DepthKind::Gl => gl,
            DepthKind::GlReversed => -gl,
            _ => unreachable!(),
        }) as f32
    }

    #[test]
    fn every_depth_convention_gives_the_same_diopters() {
        for kind in [
            DepthKind::Gl,
            DepthKind::GlReversed,
            DepthKind::Vulkan,
            DepthKind::VulkanReversed,
        ] {
            for far in [100.0f64, f64::INFINITY] {
                for z in [0.25f64, 0.5, 1.0, 2.0, 10.0] {
                    let v = buffer_value(kind, z, 0.1, far);
                    let d = kind.diopters(v, 0.1, far as f32).unwrap();
                    let want = 1.0 / z;
                    assert!(
                        (f64::from(d) - want).abs() < 2e-3 * want.max(1.0),
                        "{kind:?} far {far} z {z}: {d} D, want {want}"
                    );
                }
            }
        }
        assert_eq!(
            DepthKind::VulkanReversed.diopters(0.0, 0.1, f32::INFINITY),
            Ok(0.0)
        );
        assert_eq!(DepthKind::Metres.diopters(0.5, 0.0, 0.0), Ok(2.0));
        assert_eq!(DepthKind::Metres.diopters(f32::INFINITY, 0.0, 0.0), Ok(0.0));
        assert_eq!(DepthKind::Diopters.diopters(1.5, 0.0, 0.0), Ok(1.5));
    }

    #[test]
    fn bad_depth_is_refused_naming_the_pixel() {
        let d = desc(2, 2, ColorFormat::Rgb8, DepthKind::Metres);
        let color = vec![0u8; 12];
        let e = decode_frame(&d, &color, &f32s(&[1.0, 1.0, f32::NAN, 1.0]), (2, 2)).unwrap_err();
        assert!(matches!(e, FrameError::Depth { x: 0, y: 1, .. }), "{e}");
        let e = decode_frame(&d, &color, &f32s(&[1.0, -1.0, 1.0, 1.0]), (2, 2)).unwrap_err();
        assert!(matches!(e, FrameError::Depth { x: 1, y: 0, .. }), "{e}");
        let vk = desc(2, 2, ColorFormat::Rgb8, DepthKind::Vulkan);
        let e = decode_frame(&vk, &color, &f32s(&[0.5, 1.5, 0.5, 0.5]), (2, 2)).unwrap_err();
        assert!(e.to_string().contains("[0, 1]"), "{e}");
        let mut no_planes = vk;
        no_planes.near = None;
        let e = decode_frame(&no_planes, &color, &f32s(&[0.5; 4]), (2, 2)).unwrap_err();
        assert!(e.to_string().contains("near and far"), "{e}");
    }

    #[test]
    fn wrong_sizes_and_lengths_are_refused() {
        let d = desc(2, 2, ColorFormat::Rgba8, DepthKind::Diopters);
        let depth = f32s(&[1.0; 4]);
        let e = decode_frame(&d, &[0u8; 16], &depth, (3, 2)).unwrap_err();
        assert!(matches!(e, FrameError::WrongSize { .. }), "{e}");
        let e = decode_frame(&d, &[0u8; 12], &depth, (2, 2)).unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::Length {
                    what: "colour",
                    got: 12,
                    want: 16,
                    ..
                }
            ),
            "{e}"
        );
        let e = decode_frame(&d, &[0u8; 16], &depth[..15], (2, 2)).unwrap_err();
        assert!(matches!(e, FrameError::Length { what: "depth", .. }), "{e}");
    }

    #[test]
    fn colour_is_decoded_from_srgb_or_taken_linear() {
        let d = desc(1, 1, ColorFormat::Rgb8, DepthKind::Diopters);
        let f = decode_frame(&d, &[255, 0, 188], &f32s(&[1.0]), (1, 1)).unwrap();
        let px: Vec<f32> = f.color.channels.iter().map(|p| p.data()[0]).collect();
        assert_eq!(px[0], 1.0);
        assert_eq!(px[1], 0.0);
        assert!((px[2] - 0.5).abs() < 0.01, "{px:?}");
        let d = desc(1, 1, ColorFormat::Rgbf32, DepthKind::Diopters);
        let f = decode_frame(&d, &f32s(&[0.25, 0.5, 0.75]), &f32s(&[1.0]), (1, 1)).unwrap();
        assert_eq!(f.color.channels[1].data()[0], 0.5);
        assert_eq!(f.depth.plane().data()[0], 1.0);
    }

    #[test]
    fn image_files_decode_as_dioptra_render_reads_them() {
        use dioptra_render::io::{read_color, read_depth, write_color, write_depth};
        let dir = tempfile::tempdir().unwrap();
        let vals: Vec<f32> = (0..18).map(|i| i as f32 / 17.0).collect();
        let color = RgbImage::from_interleaved(3, 2, &vals).unwrap();
        let depth = DepthMap::from_diopters(
            Plane::from_vec(3, 2, vec![0.5, 1.0, 2.0, 4.0, 0.25, 1.0]).unwrap(),
        )
        .unwrap();
        let file = |name: &str| dir.path().join(name);
        write_color(&file("c.png"), &color).unwrap();
        write_color(&file("c.exr"), &color).unwrap();
        write_depth(&file("d.png"), &depth).unwrap();
        write_depth(&file("d.exr"), &depth).unwrap();
        let bytes = |name: &str| std::fs::read(file(name)).unwrap();
        for (c, fmt, d, kind) in [
            ("c.png", ColorFormat::Png, "d.png", DepthKind::Millimetres),
            ("c.exr", ColorFormat::Exr, "d.exr", DepthKind::Metres),
        ] {
            let f = decode_frame(&desc(3, 2, fmt, kind), &bytes(c), &bytes(d), (3, 2)).unwrap();
            assert_eq!(f.color, read_color(&file(c)).unwrap(), "{c}");
            let want = read_depth(&file(d), None).unwrap();
            for (a, b) in f.depth.data().iter().zip(want.data()) {
                assert!((a - b).abs() <= 1e-6 * b.max(1.0), "{d}: {a} vs {b}");
            }
        }
        let png = desc(3, 2, ColorFormat::Png, DepthKind::Millimetres);
        // The colour part is not the format named.
        let e = decode_frame(&png, &bytes("c.exr"), &bytes("d.png"), (3, 2)).unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::Encoding {
                    what: "colour file",
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("color=png"), "{e}");
        // A file of another size than the frame: refused from its header.
        write_depth(
            &file("small.png"),
            &DepthMap::from_diopters(Plane::new(2, 2, 1.0)).unwrap(),
        )
        .unwrap();
        let e = decode_frame(&png, &bytes("c.png"), &bytes("small.png"), (3, 2)).unwrap_err();
        assert!(
            e.to_string()
                .contains("depth file: it is 2x2; the frame is 3x2"),
            "{e}"
        );
        // A depth file cut short, and NaN depth named by pixel.
        let cut = bytes("d.png");
        let e = decode_frame(&png, &bytes("c.png"), &cut[..cut.len() / 2], (3, 2)).unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::Encoding {
                    what: "depth file",
                    ..
                }
            ),
            "{e}"
        );
        // A PFM's rows run bottom to top: its second value is pixel (1, 1).
        let mut nan_pfm = b"Pf\n3 2\n-1.0\n".to_vec();
        nan_pfm.extend(f32s(&[1.0, f32::NAN, 1.0, 1.0, 1.0, 1.0]));
        let metres = desc(3, 2, ColorFormat::Png, DepthKind::Metres);
        let e = decode_frame(&metres, &bytes("c.png"), &nan_pfm, (3, 2)).unwrap_err();
        assert!(matches!(e, FrameError::Depth { x: 1, y: 1, .. }), "{e}");
    }

    #[test]
    fn the_newest_frame_wins_and_every_frame_is_accounted_for() {
        let s = StreamFrames::open(1, 1, None).unwrap();
        let d = FrameDesc {
            seq: Some(5),
            ..desc(1, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        let depth = f32s(&[1.0]);
        assert_eq!(s.submit(&d, &[1, 2, 3], &depth, Timestamp(10)), Ok(5));
        // A stale one is refused, the newer one replaces the first before the display took it.
        let e = s.submit(&d, &[1, 2, 3], &depth, Timestamp(11)).unwrap_err();
        assert!(matches!(e, FrameError::Stale { seq: 5, newest: 5 }));
        let d7 = FrameDesc { seq: Some(7), ..d };
        assert_eq!(s.submit(&d7, &[9, 9, 9], &depth, Timestamp(12)), Ok(7));
        assert!(s.take_new().is_some());
        assert!(s.take_new().is_none(), "taken once");
        let st = s.status();
        assert_eq!((st.received, st.shown, st.replaced), (2, 1, 1));
        assert_eq!(st.refused.get("stale"), Some(&1));
        assert_eq!(st.on_show_seq, Some(7));
        assert!(st.newest_age_ms.is_some());
        // Unnumbered frames continue the numbering.
        let auto = FrameDesc { seq: None, ..d };
        assert_eq!(s.submit(&auto, &[0, 0, 0], &depth, Timestamp(13)), Ok(8));
    }

    /// Frames given back are reused only when no one else holds them: a frame still held
    /// keeps its pixels whatever comes after it, and reused memory holds the new frame whole.
    #[test]
    fn reused_memory_never_changes_a_frame_still_held() {
        let s = StreamFrames::open(2, 1, None).unwrap();
        let d = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
        let send = |v: u8, depth: f32| {
            s.submit(&d, &[v; 6], &f32s(&[depth; 2]), Timestamp(0))
                .unwrap();
        };
        send(255, 1.0);
        let held = s.take_new().unwrap().0;
        let kept = held.clone();
        // Given back while `kept` holds it: not reused.
        s.recycle(held);
        for (k, v) in [(0u8, 2.0f32), (128, 3.0), (64, 4.0)] {
            send(k, v);
            // Replaced before shown: its memory goes to the next frame.
            send(k / 2, v + 0.5);
            let f = s.take_new().unwrap().0;
            assert_eq!(f.depth.data(), &[v + 0.5; 2]);
            assert_eq!(
                f.color.channels[0].data()[0],
                srgb_lut()[usize::from(k / 2)]
            );
            s.recycle(f);
        }
        assert_eq!(kept.color.channels[0].data(), &[1.0, 1.0]);
        assert_eq!(kept.depth.data(), &[1.0, 1.0]);
        assert!(
            !lock(&s.planes.spare).is_empty(),
            "frames given back are kept for reuse"
        );
    }

    /// Writes a frame into a ring slot the way a client does: sequence number last.
    fn write_slot(ring: &Ring, slot: usize, seq: u64, w: u32, h: u32, color: &[u8], depth: &[u8]) {
        write_eye_slot(ring, slot, (seq, 0), w, h, color, depth)
    }

    /// [`write_slot`] with the slot's `eye` code.
    fn write_eye_slot(
        ring: &Ring,
        slot: usize,
        (seq, eye): (u64, u32),
        w: u32,
        h: u32,
        color: &[u8],
        depth: &[u8],
    ) {
        write_part_slot(ring, slot, (seq, eye, 0), w, h, color, depth)
    }

    /// [`write_slot`] with the slot's `eye` and `view` codes.
    fn write_part_slot(
        ring: &Ring,
        slot: usize,
        (seq, eye, view): (u64, u32, u32),
        w: u32,
        h: u32,
        color: &[u8],
        depth: &[u8],
    ) {
        let base = RING_HEADER + slot * ring.slot_bytes;
        let head = SlotHeader {
            seq,
            color_format: ColorFormat::Rgb8 as u32,
            depth_kind: DepthKind::Diopters as u32,
            near: f32::NAN,
            far: f32::NAN,
            width: w,
            height: h,
            app_time_ns: 0,
            color_bytes: color.len() as u64,
            depth_bytes: depth.len() as u64,
            eye,
            view,
        };
        let mut bytes = head.encode().to_vec();
        bytes.extend_from_slice(color);
        bytes.extend_from_slice(depth);
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(&ring.path)
            .unwrap();
        use std::os::unix::fs::FileExt;
        f.write_all_at(&bytes[8..], (base + 8) as u64).unwrap();
        f.write_all_at(&seq.to_le_bytes(), base as u64).unwrap();
    }

    #[test]
    fn a_ring_slot_is_read_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames");
        let s = StreamFrames::open(2, 1, Some(&path)).unwrap();
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&path).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o600);
        let ring = s.ring.as_ref().unwrap();
        let header = std::fs::read(&path).unwrap();
        assert_eq!(&header[..8], RING_MAGIC);
        write_slot(ring, 1, 3, 2, 1, &[255; 6], &f32s(&[0.5, 2.0]));
        assert_eq!(s.submit_slot(1, 3, Timestamp(1)), Ok(3));
        let (f, _) = s.take_new().unwrap();
        assert_eq!(f.depth.plane().data(), &[0.5, 2.0]);
        // The wrong sequence number, a slot out of range, sizes that overflow the slot.
        assert!(s.submit_slot(1, 4, Timestamp(2)).is_err());
        assert!(s.submit_slot(RING_SLOTS, 4, Timestamp(2)).is_err());
        write_slot(ring, 0, 9, 2, 1, &[0; 6], &vec![0; ring.slot_bytes]);
        let e = s.submit_slot(0, 9, Timestamp(3)).unwrap_err();
        assert!(e.to_string().contains("do not fit"), "{e}");
        // A truncated slot: its header says fewer depth bytes than the frame needs.
        write_slot(ring, 2, 10, 2, 1, &[0; 6], &f32s(&[1.0]));
        let e = s.submit_slot(2, 10, Timestamp(4)).unwrap_err();
        assert!(matches!(e, FrameError::Length { what: "depth", .. }), "{e}");
        // A slot rewritten while it was copied out is torn.
        write_slot(ring, 2, 11, 2, 1, &[0; 6], &f32s(&[1.0, 1.0]));
        let e = s
            .read_slot_then(2, 11, || {
                write_slot(ring, 2, 12, 2, 1, &[1; 6], &f32s(&[2.0, 2.0]))
            })
            .unwrap_err();
        assert_eq!(e, FrameError::Torn(2));
        let st = s.status();
        assert_eq!(st.received, 1);
        assert_eq!(st.refused.values().sum::<u64>(), 4);
        drop(s);
        assert!(!path.exists(), "the ring is removed with the stream");
    }

    #[test]
    fn a_ring_path_that_is_a_symlink_is_not_followed() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target");
        std::fs::write(&target, b"keep").unwrap();
        let link = dir.path().join("frames");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let e = StreamFrames::open(2, 2, Some(&link)).unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
        assert_eq!(std::fs::read(&target).unwrap(), b"keep");
    }

    /// A 2 x 1 stereo stream's halves: one eye's frame of `v` (sRGB byte) at `d` D.
    fn half(s: &StreamFrames, eye: Side, seq: u64, v: u8, d: f32) -> Result<u64, FrameError> {
        let desc = FrameDesc {
            seq: Some(seq),
            ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        s.submit_eye(&desc, Some(eye), &[v; 6], &f32s(&[d; 2]), Timestamp(seq))
    }

    /// The views of the frame the display takes up next (left, right), as (red, depth).
    fn pair_of(s: &StreamFrames) -> Option<(u64, [(f32, f32); 2])> {
        let f = s.poll(Timestamp(0))?;
        let [l, r] = f.eyes.clone().expect("a pair");
        assert!(Arc::ptr_eq(&f.rgbd, &l), "rgbd is the left eye's view");
        let px = |v: &Rgbd| (v.color.channels[0].data()[0], v.depth.data()[0]);
        Some((s.status().on_show_seq.unwrap(), [px(&l), px(&r)]))
    }

    /// On a stereo rig halves are paired by sequence number: a lone half is not shown; a pair
    /// is, once both halves arrived in either order; a half whose partner never came is
    /// dropped when a newer pair completes, and refused if it comes after that.
    #[test]
    fn halves_are_paired_by_sequence_number() {
        let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
        let lut = srgb_lut();
        // The placeholder first, then nothing while only the left half of 1 is in.
        assert!(s.poll(Timestamp(0)).unwrap().eyes.is_none());
        assert_eq!(half(&s, Side::Left, 1, 10, 1.0), Ok(1));
        assert!(s.poll(Timestamp(0)).is_none(), "a lone half is not shown");
        let st = s.status();
        assert_eq!((st.received, st.halves_waiting), (0, 1), "{st:?}");
        assert_eq!(half(&s, Side::Right, 1, 20, 2.0), Ok(1));
        assert_eq!(
            pair_of(&s),
            Some((1, [(lut[10], 1.0), (lut[20], 2.0)])),
            "each eye its own half"
        );
        // Late: the right half of 2 never comes before pair 3 completes.
        half(&s, Side::Left, 2, 30, 1.5).unwrap();
        half(&s, Side::Left, 3, 40, 1.25).unwrap();
        assert!(
            s.poll(Timestamp(0)).is_none(),
            "2 and 3 wait for their right halves"
        );
        half(&s, Side::Right, 3, 50, 2.5).unwrap();
        assert_eq!(pair_of(&s), Some((3, [(lut[40], 1.25), (lut[50], 2.5)])));
        let st = s.status();
        assert_eq!((st.halves_dropped, st.halves_waiting), (1, 0), "{st:?}");
        // The late half after its pair was overtaken: refused, never shown.
        let e = half(&s, Side::Right, 2, 60, 3.0).unwrap_err();
        assert_eq!(
            e,
            FrameError::StaleHalf {
                eye: Side::Right,
                seq: 2,
                newest: 3
            }
        );
        assert!(
            e.to_string().contains("right eye's sequence number 2"),
            "{e}"
        );
        // Right before left; pair 4 completes, then 5, before the display looks: 4 is
        // replaced by 5.
        half(&s, Side::Right, 4, 1, 0.5).unwrap();
        half(&s, Side::Left, 4, 3, 0.5).unwrap();
        half(&s, Side::Left, 5, 2, 0.75).unwrap();
        half(&s, Side::Right, 5, 4, 0.75).unwrap();
        assert_eq!(pair_of(&s), Some((5, [(lut[2], 0.75), (lut[4], 0.75)])));
        assert!(s.poll(Timestamp(0)).is_none());
        // A half again for an eye's number already in, and a half without a number.
        let e = half(&s, Side::Left, 5, 0, 1.0).unwrap_err();
        assert!(matches!(e, FrameError::StaleHalf { seq: 5, .. }), "{e}");
        let unnumbered = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
        let e = s
            .submit_eye(
                &unnumbered,
                Some(Side::Left),
                &[0; 6],
                &f32s(&[1.0; 2]),
                Timestamp(0),
            )
            .unwrap_err();
        assert!(e.to_string().contains("needs its sequence number"), "{e}");
        let st = s.status();
        assert_eq!(
            (st.received, st.shown, st.replaced, st.halves_received),
            (4, 3, 1, 9),
            "{st:?}"
        );
        assert_eq!(st.refused.get("stale"), Some(&2), "{st:?}");
        assert_eq!(st.refused.get("request"), Some(&1), "{st:?}");
        assert_eq!(st.newest_seq, Some(5));
    }

    /// Halves waiting for more than MAX_WAITING sequence numbers drop the oldest; a whole
    /// frame on a stereo rig (mono: its eyes are synthesised) drops every older half.
    #[test]
    fn waiting_halves_are_bounded_and_a_whole_frame_overtakes_them() {
        let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
        for seq in 1..=MAX_WAITING as u64 + 1 {
            half(&s, Side::Left, seq, 0, 1.0).unwrap();
        }
        let st = s.status();
        assert_eq!(
            (st.halves_waiting, st.halves_dropped),
            (MAX_WAITING as u64, 1),
            "{st:?}"
        );
        // The oldest (1) is gone: its right half can no longer make a pair.
        let e = half(&s, Side::Right, 1, 0, 1.0).unwrap_err();
        assert!(matches!(e, FrameError::StaleHalf { newest: 1, .. }), "{e}");
        half(&s, Side::Right, 2, 0, 1.0).unwrap();
        assert!(
            s.take_new().is_some(),
            "pair 2, whose left half still waited"
        );
        let mono = FrameDesc {
            seq: Some(10),
            ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        s.submit(&mono, &[9; 6], &f32s(&[2.0; 2]), Timestamp(0))
            .unwrap();
        let f = s.poll(Timestamp(0)).unwrap();
        assert!(f.eyes.is_none(), "a mono frame: eyes synthesised later");
        let st = s.status();
        assert_eq!(
            (st.halves_waiting, st.halves_dropped, st.on_show_seq),
            (0, MAX_WAITING as u64, Some(10)),
            "{st:?}"
        );
    }

    /// A frame 2 x width wide without an eye is both eyes side by side: its left half is the
    /// left eye's. Sizes that fit neither, an unknown eye and an eye on a mono rig are
    /// refused.
    #[test]
    fn a_side_by_side_frame_is_split_and_bad_eyes_are_refused() {
        let s = StreamFrames::with_eyes(2, 1, true, None).unwrap();
        let wide = desc(4, 1, ColorFormat::Rgb8, DepthKind::Diopters);
        let color = [10, 10, 10, 20, 20, 20, 30, 30, 30, 40, 40, 40];
        s.submit(&wide, &color, &f32s(&[1.0, 2.0, 3.0, 4.0]), Timestamp(0))
            .unwrap();
        let f = s.poll(Timestamp(0)).unwrap();
        let [l, r] = f.eyes.clone().expect("a pair");
        let lut = srgb_lut();
        assert_eq!(l.color.channels[1].data(), &[lut[10], lut[20]]);
        assert_eq!(r.color.channels[2].data(), &[lut[30], lut[40]]);
        assert_eq!(l.depth.data(), &[1.0, 2.0]);
        assert_eq!(r.depth.data(), &[3.0, 4.0]);
        assert_eq!((l.width(), r.width()), (2, 2));
        // One eye's half must be one eye's size; a whole frame one of the two sizes.
        let e = s
            .submit_eye(
                &FrameDesc {
                    seq: Some(9),
                    ..wide
                },
                Some(Side::Left),
                &color,
                &f32s(&[1.0; 4]),
                Timestamp(0),
            )
            .unwrap_err();
        assert!(
            e.to_string()
                .contains("left eye's frame is 4x1; one eye's image is 2x1"),
            "{e}"
        );
        assert_eq!(e.kind(), "wrong_size");
        let e = s.side_by_side(3, 1, None).unwrap_err();
        assert!(
            e.to_string().contains("or 4x1 for both eyes side by side"),
            "{e}"
        );
        let e = s.parse_eye(Some("middle")).unwrap_err();
        assert!(e.to_string().contains("expected left or right"), "{e}");
        assert_eq!(s.parse_eye(Some("right")), Ok(Some(Side::Right)));
        let mono = StreamFrames::open(2, 1, None).unwrap();
        let e = mono.parse_eye(Some("left")).unwrap_err();
        assert!(e.to_string().contains("display.layout = \"one\""), "{e}");
        assert_eq!(e.kind(), "eye");
        let e = mono.side_by_side(4, 1, None).unwrap_err();
        assert!(
            matches!(e, FrameError::WrongSize { .. }),
            "a mono rig takes no pair: {e}"
        );
    }

    /// A ring slot's `eye`: two slots of the same number make a pair; a stereo ring's slots
    /// hold a side-by-side frame; an unknown eye, or an eye on a mono rig, is refused.
    #[test]
    fn ring_slots_name_their_eye() {
        let dir = tempfile::tempdir().unwrap();
        let s = StreamFrames::with_eyes(2, 1, true, Some(&dir.path().join("stereo"))).unwrap();
        let ring = s.ring.as_ref().unwrap();
        assert_eq!(ring.slot_bytes, SLOT_HEADER + 2 * 2 * 16);
        write_eye_slot(ring, 0, (7, 1), 2, 1, &[255; 6], &f32s(&[1.0; 2]));
        write_eye_slot(ring, 1, (7, 2), 2, 1, &[0; 6], &f32s(&[2.0; 2]));
        assert_eq!(s.submit_slot(0, 7, Timestamp(1)), Ok(7));
        assert_eq!(s.status().received, 0, "the left half waits");
        assert_eq!(s.submit_slot(1, 7, Timestamp(2)), Ok(7));
        let f = s.poll(Timestamp(2)).unwrap();
        let [l, r] = f.eyes.expect("a pair");
        assert_eq!((l.depth.data()[0], r.depth.data()[0]), (1.0, 2.0));
        assert_eq!(
            f.arrival.map(|a| a.arrived),
            Some(Timestamp(2)),
            "with its second half"
        );
        // Both eyes in one slot (eye 0, 2 x width).
        write_eye_slot(
            ring,
            2,
            (8, 0),
            4,
            1,
            &[9; 12],
            &f32s(&[1.0, 1.0, 3.0, 3.0]),
        );
        assert_eq!(s.submit_slot(2, 8, Timestamp(3)), Ok(8));
        let [l, r] = s.poll(Timestamp(3)).unwrap().eyes.expect("a pair");
        assert_eq!(
            (l.depth.data(), r.depth.data()),
            (&[1.0, 1.0][..], &[3.0, 3.0][..])
        );
        write_eye_slot(ring, 0, (9, 3), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
        let e = s.submit_slot(0, 9, Timestamp(4)).unwrap_err();
        assert!(e.to_string().contains("unknown eye 3"), "{e}");
        let mono = StreamFrames::open(2, 1, Some(&dir.path().join("mono"))).unwrap();
        let ring = mono.ring.as_ref().unwrap();
        assert_eq!(ring.slot_bytes, SLOT_HEADER + 2 * 16);
        write_eye_slot(ring, 0, (1, 2), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
        let e = mono.submit_slot(0, 1, Timestamp(0)).unwrap_err();
        assert_eq!(e.kind(), "eye", "{e}");
        assert_eq!(mono.status().refused.get("eye"), Some(&1));
    }

    /// A 2 x 1 stream's view `v` of frame `seq` (`eye`'s grid, or the one grid): red `r`
    /// (sRGB byte), `d` D.
    fn view(
        s: &StreamFrames,
        eye: Option<Side>,
        v: &str,
        seq: u64,
        r: u8,
        d: f32,
    ) -> Result<u64, FrameError> {
        let desc = FrameDesc {
            seq: Some(seq),
            ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        let v = s.parse_view(Some(v))?;
        s.submit_part(&desc, eye, v, &[r; 6], &f32s(&[d; 2]), Timestamp(seq))
    }

    /// Light-field content (`content.views = 2`): a frame's views, sent in any order, are
    /// shown together once the last arrives, each at its place in the grid, the central one
    /// as the frame's RGB-D; one view twice, a view of a frame overtaken by a newer one, a
    /// view outside the grid or of another size is refused; views of an overtaken frame are
    /// dropped and counted.
    #[test]
    fn a_grids_views_are_shown_together_once_all_arrived() {
        let s = StreamFrames::open(2, 1, None)
            .unwrap()
            .with_view_grid(2, 4.0)
            .unwrap();
        let lut = srgb_lut();
        assert!(
            s.poll(Timestamp(0)).unwrap().views.is_none(),
            "the placeholder"
        );
        for (k, name) in [(3, "1_1"), (0, "0_0"), (2, "1_0")] {
            assert_eq!(view(&s, None, name, 1, 10 + k, 1.0 + f32::from(k)), Ok(1));
            assert!(s.poll(Timestamp(0)).is_none(), "view {name} of 4: not yet");
        }
        assert_eq!(s.status().halves_waiting, 3);
        view(&s, None, "0_1", 1, 11, 2.0).unwrap();
        let f = s.poll(Timestamp(0)).expect("frame 1 complete");
        let views = f.views.clone().expect("its views");
        assert_eq!(views.len(), 4);
        let positions = dioptra_sim::scene::light_field_positions(2, 0.004).unwrap();
        for (k, v) in views.iter().enumerate() {
            assert_eq!(v.position, positions[k], "view {k}");
            assert!(v.eye.is_none());
            assert_eq!(v.rgbd.color.channels[0].data()[0], lut[10 + k], "view {k}");
            assert_eq!(v.rgbd.depth.data()[0], 1.0 + k as f32, "view {k}");
        }
        // Row 1, column 1: the central view of an even grid (right of and below the centre).
        assert!(Arc::ptr_eq(&f.rgbd, &views[3].rgbd));
        let st = s.status();
        assert_eq!(
            (st.views_received, st.received, st.halves_waiting),
            (4, 1, 0),
            "{st:?}"
        );
        // The same view again for frame 1: stale.
        let e = view(&s, None, "0_0", 1, 0, 1.0).unwrap_err();
        assert!(
            matches!(
                e,
                FrameError::StaleView {
                    seq: 1,
                    newest: 1,
                    ..
                }
            ),
            "{e}"
        );
        // Frame 2 half in, then a whole frame 3: 2's views are dropped, later ones refused.
        view(&s, None, "0_0", 2, 0, 1.0).unwrap();
        view(&s, None, "1_1", 2, 0, 1.0).unwrap();
        let whole = FrameDesc {
            seq: Some(3),
            ..desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        s.submit(&whole, &[7; 6], &f32s(&[0.5; 2]), Timestamp(3))
            .unwrap();
        let f = s.poll(Timestamp(0)).unwrap();
        assert!(f.views.is_none(), "a whole frame is one view");
        let st = s.status();
        assert_eq!((st.halves_dropped, st.halves_waiting), (2, 0), "{st:?}");
        assert!(matches!(
            view(&s, None, "0_1", 2, 0, 1.0),
            Err(FrameError::StaleView {
                seq: 2,
                newest: 3,
                ..
            })
        ));
        // Outside the grid, no sequence number, another size: refused naming why.
        for bad in ["2_0", "0", "a_b", "0_-1"] {
            let e = view(&s, None, bad, 4, 0, 1.0).unwrap_err();
            assert!(matches!(e, FrameError::View(_)), "{bad}: {e}");
            assert!(e.to_string().contains("content.views = 2"), "{e}");
        }
        let no_seq = desc(2, 1, ColorFormat::Rgb8, DepthKind::Diopters);
        let e = s
            .submit_part(
                &no_seq,
                None,
                Some(0),
                &[0; 6],
                &f32s(&[1.0; 2]),
                Timestamp(5),
            )
            .unwrap_err();
        assert!(
            matches!(e, FrameError::Request(_)) && e.to_string().contains("seq=N"),
            "{e}"
        );
        let wide = FrameDesc {
            seq: Some(6),
            ..desc(4, 1, ColorFormat::Rgb8, DepthKind::Diopters)
        };
        let e = s
            .submit_part(
                &wide,
                None,
                Some(0),
                &[0; 12],
                &f32s(&[1.0; 4]),
                Timestamp(6),
            )
            .unwrap_err();
        assert!(e.to_string().contains("one eye's image, 2x1"), "{e}");
        // (A view=... that does not parse is counted by PUT /frame, before the frame is read.)
        assert_eq!(s.status().refused.get("view"), Some(&1));
        // A rig without a grid refuses views.
        let plain = StreamFrames::open(2, 1, None).unwrap();
        let e = view(&plain, None, "0_0", 1, 0, 1.0).unwrap_err();
        assert!(e.to_string().contains("content.views"), "{e}");
    }

    /// A stereo rig: each eye's own grid (views with `eye`), the frame's eyes their central
    /// views; a frame's views with and without an eye do not mix. Ring slots name their view.
    #[test]
    fn each_eye_may_stream_its_own_grid_and_slots_name_their_view() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames");
        let s = StreamFrames::with_eyes(2, 1, true, Some(&path))
            .unwrap()
            .with_view_grid(2, 10.0)
            .unwrap();
        assert_eq!(s.ring_json()["views"], 2);
        s.poll(Timestamp(0));
        for (eye, base) in [(Side::Left, 20u8), (Side::Right, 40)] {
            for k in 0..4u8 {
                let name = format!("{}_{}", k / 2, k % 2);
                view(&s, Some(eye), &name, 1, base + k, 1.0).unwrap();
            }
        }
        let f = s.poll(Timestamp(0)).expect("both grids complete");
        let views = f.views.clone().unwrap();
        assert_eq!(views.len(), 8);
        let lut = srgb_lut();
        for (k, v) in views.iter().enumerate() {
            let (eye, base) = if k < 4 {
                (Side::Left, 20)
            } else {
                (Side::Right, 40)
            };
            assert_eq!(v.eye, Some(eye));
            assert_eq!(v.rgbd.color.channels[0].data()[0], lut[base + k % 4]);
        }
        let [l, r] = f.eyes.clone().unwrap();
        assert!(Arc::ptr_eq(&l, &views[3].rgbd) && Arc::ptr_eq(&r, &views[7].rgbd));
        // Frame 2: a view of the one grid, then one of an eye's: refused.
        view(&s, None, "0_0", 2, 0, 1.0).unwrap();
        let e = view(&s, Some(Side::Left), "0_1", 2, 0, 1.0).unwrap_err();
        assert!(e.to_string().contains("views of one grid"), "{e}");
        // Frame 3 through the ring: slot `view` 1 + index, the right eye's.
        let ring = s.ring.as_ref().unwrap();
        for k in 0..4u32 {
            write_part_slot(
                ring,
                0,
                (3, 0, 1 + k),
                2,
                1,
                &[60 + k as u8; 6],
                &f32s(&[1.0; 2]),
            );
            s.submit_slot(0, 3, Timestamp(3)).unwrap();
        }
        let f = s.poll(Timestamp(0)).expect("frame 3 from the ring");
        let views = f.views.clone().unwrap();
        assert!(views.iter().all(|v| v.eye.is_none()) && views.len() == 4);
        assert_eq!(views[2].rgbd.color.channels[0].data()[0], lut[62]);
        write_part_slot(ring, 1, (4, 0, 5), 2, 1, &[0; 6], &f32s(&[1.0; 2]));
        let e = s.submit_slot(1, 4, Timestamp(4)).unwrap_err();
        assert!(matches!(e, FrameError::View(_)), "{e}");
    }
}
