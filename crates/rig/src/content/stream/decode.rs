//! Pixel decoding: a frame's description ([`FrameDesc`]) and its colour and depth bytes (raw
//! pixels, or image files) to linear-light colour and depth in diopters, or why the frame is
//! refused ([`FrameError`]).

use dioptra_core::image::srgb_to_linear;
use dioptra_core::{DepthMap, Plane, RgbImage, Rgbd, Side};
use dioptra_render::io::{decode_color, decode_samples, encoded_size, ImageFormat};
use rayon::prelude::*;
use serde::Serialize;

use super::pool::Planes;

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
    pub(super) fn diopters(self, v: f32, near: f32, far: f32) -> Result<f32, &'static str> {
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
    /// The config key a refusal is about: the display's size, its layout (eyes), the view
    /// grid, or (the frame's own fault) the content source.
    pub fn config_key(&self) -> &'static str {
        match self {
            FrameError::WrongSize { .. } | FrameError::WrongEyeSize { .. } => "display.width",
            FrameError::Eye(_) => "display.layout",
            FrameError::View(_) | FrameError::StaleView { .. } => "content.views",
            _ => "content.source",
        }
    }

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

pub(super) fn decode_frame_into(
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
pub(super) fn srgb_lut() -> &'static [f32; 256] {
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
