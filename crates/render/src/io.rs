//! Image files. Colour: PNG 8/16-bit sRGB (decoded to linear on read), EXR and PFM linear.
//! Depth: EXR or PFM float metres, 16-bit PNG millimetres, unless overridden. Outputs are
//! chosen by extension: `.png` 8-bit sRGB, `.exr` and `.pfm` linear float.

use crate::error::RenderError;
use dioptra_core::image::{linear_to_srgb, srgb_to_linear};
use dioptra_core::{DepthMap, InputError, Plane, RgbImage};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Images with more pixels than this are refused from their header, before their pixels are
/// allocated (64 Mpx, e.g. 8192 x 8192: four f32 channels of it are 1 GiB).
pub const DEFAULT_MAX_PIXELS: u64 = 64 * 1024 * 1024;

/// Refuses a size a header claims when it exceeds `max_pixels`.
fn check_size(name: &str, w: u64, h: u64, max_pixels: u64) -> Result<(), RenderError> {
    let n = w.saturating_mul(h);
    if n > max_pixels {
        return Err(fmt_err(
            name,
            format!(
                "its header claims {w} x {h} pixels ({:.1} Mpx), more than the limit of {:.1} Mpx \
                 (--max-pixels)",
                n as f64 / 1048576.0,
                max_pixels as f64 / 1048576.0
            ),
        ));
    }
    Ok(())
}

/// What the numbers in a depth file mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DepthUnits {
    Meters,
    Millimeters,
    Diopters,
}

impl std::str::FromStr for DepthUnits {
    type Err = RenderError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "m" | "meters" | "metres" => Ok(DepthUnits::Meters),
            "mm" | "millimeters" | "millimetres" => Ok(DepthUnits::Millimeters),
            "D" | "d" | "diopters" | "dioptres" => Ok(DepthUnits::Diopters),
            _ => Err(crate::error::invalid(format!(
                "unknown depth units {s:?}: expected m, mm or D"
            ))),
        }
    }
}

/// An image file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageFormat {
    Png,
    Exr,
    Pfm,
}

impl ImageFormat {
    /// The format of an encoded image, from its first bytes (its signature).
    pub fn of_bytes(bytes: &[u8]) -> Option<ImageFormat> {
        if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            Some(ImageFormat::Png)
        } else if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
            Some(ImageFormat::Exr)
        } else if bytes.starts_with(b"PF") || bytes.starts_with(b"Pf") {
            Some(ImageFormat::Pfm)
        } else {
            None
        }
    }
}

fn format_of(path: &Path) -> Result<ImageFormat, RenderError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "png" => Ok(ImageFormat::Png),
        "exr" => Ok(ImageFormat::Exr),
        "pfm" => Ok(ImageFormat::Pfm),
        _ => Err(fmt_err(
            &path.display().to_string(),
            format!("unsupported file type {ext:?}: expected .png, .exr or .pfm"),
        )),
    }
}

/// The format of `bytes` from their signature, or an error naming `name`.
fn format_of_bytes(name: &str, bytes: &[u8]) -> Result<ImageFormat, RenderError> {
    ImageFormat::of_bytes(bytes).ok_or_else(|| {
        fmt_err(
            name,
            "not a PNG, EXR or PFM image (its first bytes are none of their signatures)",
        )
    })
}

fn fmt_err(name: &str, detail: impl Into<String>) -> RenderError {
    RenderError::Format {
        path: name.to_string(),
        detail: detail.into(),
    }
}

fn path_err(path: &Path, detail: impl Into<String>) -> RenderError {
    fmt_err(&path.display().to_string(), detail)
}

fn io_err(path: &Path, cause: std::io::Error) -> RenderError {
    RenderError::Io {
        path: path.display().to_string(),
        cause,
    }
}

/// Decoded file contents: channels (1 to 4) of f32 samples, row-major, top row first.
struct Raw {
    width: usize,
    height: usize,
    channels: Vec<Vec<f32>>,
    /// PNG samples are sRGB-encoded (or integer millimetres for depth), scaled to [0, 1].
    is_png: bool,
    max_int: f32,
}

fn png_reader<'b>(
    name: &str,
    bytes: &'b [u8],
) -> Result<png::Reader<std::io::Cursor<&'b [u8]>>, RenderError> {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND);
    dec.read_info()
        .map_err(|e| fmt_err(name, format!("not a readable PNG: {e}")))
}

fn decode_png(name: &str, bytes: &[u8], max_pixels: u64) -> Result<Raw, RenderError> {
    let mut reader = png_reader(name, bytes)?;
    let (w, h) = (reader.info().width, reader.info().height);
    check_size(name, u64::from(w), u64::from(h), max_pixels)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| fmt_err(name, "PNG is too large"))?;
    let mut buf = vec![0u8; size];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| fmt_err(name, format!("PNG decode failed: {e}")))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let nch = info.color_type.samples();
    let sixteen = info.bit_depth == png::BitDepth::Sixteen;
    let bps = if sixteen { 2 } else { 1 };
    let mut channels = vec![Vec::with_capacity(w * h); nch];
    for y in 0..h {
        let row = &buf[y * info.line_size..(y + 1) * info.line_size];
        for x in 0..w {
            for (c, ch) in channels.iter_mut().enumerate() {
                let o = (x * nch + c) * bps;
                let v = if sixteen {
                    u16::from_be_bytes([row[o], row[o + 1]]) as f32
                } else {
                    row[o] as f32
                };
                ch.push(v);
            }
        }
    }
    Ok(Raw {
        width: w,
        height: h,
        channels,
        is_png: true,
        max_int: if sixteen { 65535.0 } else { 255.0 },
    })
}

/// The size of an EXR's first layer, from its headers.
fn exr_size(name: &str, bytes: &[u8]) -> Result<Vec<(usize, usize)>, RenderError> {
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false)
        .map_err(|e| fmt_err(name, format!("not a readable EXR: {e}")))?;
    Ok(meta
        .headers
        .iter()
        .map(|h| (h.layer_size.width(), h.layer_size.height()))
        .collect())
}

fn decode_exr(name: &str, bytes: &[u8], max_pixels: u64) -> Result<Raw, RenderError> {
    // The headers alone first: the sizes they claim decide whether to read the pixels.
    for (w, h) in exr_size(name, bytes)? {
        check_size(name, w as u64, h as u64, max_pixels)?;
    }
    use exr::prelude::{ReadChannels as _, ReadLayers as _};
    let img = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| fmt_err(name, format!("not a readable EXR: {e}")))?;
    let layer = &img.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let list = &layer.channel_data.list;
    let find = |names: &[&str]| {
        list.iter().position(|c| {
            let n = c.name.to_string();
            let last = n.rsplit('.').next().unwrap_or("").to_string();
            names.iter().any(|m| last.eq_ignore_ascii_case(m))
        })
    };
    let pick: Vec<usize> = match (find(&["R"]), find(&["G"]), find(&["B"])) {
        (Some(r), Some(g), Some(b)) => vec![r, g, b],
        _ => match find(&["Z", "Y", "depth", "R"]) {
            Some(i) => vec![i],
            None if !list.is_empty() => vec![0],
            None => return Err(fmt_err(name, "EXR has no channels")),
        },
    };
    let channels = pick
        .iter()
        .map(|&i| list[i].sample_data.values_as_f32().collect::<Vec<f32>>())
        .collect();
    Ok(Raw {
        width: w,
        height: h,
        channels,
        is_png: false,
        max_int: 1.0,
    })
}

/// A PFM header: channels, width, height, whether the raster is little-endian, and where the
/// raster starts.
struct PfmHeader {
    channels: usize,
    width: usize,
    height: usize,
    little: bool,
    raster: usize,
}

fn pfm_header(name: &str, bytes: &[u8]) -> Result<PfmHeader, RenderError> {
    // Header: "PF" or "Pf", then width height, then scale (negative = little-endian), each
    // separated by whitespace, then one whitespace byte and the raster, bottom row first.
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err(fmt_err(name, "truncated PFM header"));
        }
        fields.push(String::from_utf8_lossy(&bytes[start..pos]).to_string());
    }
    let channels = match fields[0].as_str() {
        "PF" => 3,
        "Pf" => 1,
        m => return Err(fmt_err(name, format!("not a PFM file (magic {m:?})"))),
    };
    let parse = |s: &str| {
        s.parse::<usize>()
            .map_err(|_| fmt_err(name, format!("bad PFM size {s:?}")))
    };
    let scale: f32 = fields[3]
        .parse()
        .map_err(|_| fmt_err(name, "bad PFM scale"))?;
    Ok(PfmHeader {
        channels,
        width: parse(&fields[1])?,
        height: parse(&fields[2])?,
        little: scale < 0.0,
        raster: pos + 1,
    })
}

fn decode_pfm(name: &str, bytes: &[u8], max_pixels: u64) -> Result<Raw, RenderError> {
    let PfmHeader {
        channels: nch,
        width: w,
        height: h,
        little,
        raster: pos,
    } = pfm_header(name, bytes)?;
    check_size(name, w as u64, h as u64, max_pixels)?;
    let need = w
        .checked_mul(h)
        .and_then(|n| n.checked_mul(nch * 4))
        .ok_or_else(|| fmt_err(name, "PFM too large"))?;
    let data = pos
        .checked_add(need)
        .and_then(|end| bytes.get(pos..end))
        .ok_or_else(|| fmt_err(name, format!("PFM raster truncated: need {need} bytes")))?;
    let mut channels = vec![vec![0.0f32; w * h]; nch];
    for (k, b) in data.chunks_exact(4).enumerate() {
        let b = [b[0], b[1], b[2], b[3]];
        let v = if little {
            f32::from_le_bytes(b)
        } else {
            f32::from_be_bytes(b)
        };
        let (px, c) = (k / nch, k % nch);
        let (x, y) = (px % w, h - 1 - px / w);
        channels[c][y * w + x] = v;
    }
    Ok(Raw {
        width: w,
        height: h,
        channels,
        is_png: false,
        max_int: 1.0,
    })
}

fn decode_raw(
    name: &str,
    format: ImageFormat,
    bytes: &[u8],
    max_pixels: u64,
) -> Result<Raw, RenderError> {
    match format {
        ImageFormat::Png => decode_png(name, bytes, max_pixels),
        ImageFormat::Exr => decode_exr(name, bytes, max_pixels),
        ImageFormat::Pfm => decode_pfm(name, bytes, max_pixels),
    }
}

fn read_raw(path: &Path, max_pixels: u64) -> Result<Raw, RenderError> {
    if !path.exists() {
        return Err(io_err(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "file not found"),
        ));
    }
    let format = format_of(path)?;
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    decode_raw(&path.display().to_string(), format, &bytes, max_pixels)
}

/// The width and height of the image encoded in `bytes` (PNG, EXR or PFM, told apart by
/// their signatures), from its header alone; errors name `name`.
pub fn encoded_size(name: &str, bytes: &[u8]) -> Result<(usize, usize), RenderError> {
    match format_of_bytes(name, bytes)? {
        ImageFormat::Png => {
            let r = png_reader(name, bytes)?;
            Ok((r.info().width as usize, r.info().height as usize))
        }
        ImageFormat::Exr => exr_size(name, bytes)?
            .first()
            .copied()
            .ok_or_else(|| fmt_err(name, "EXR has no layers")),
        ImageFormat::Pfm => pfm_header(name, bytes).map(|h| (h.width, h.height)),
    }
}

/// Decodes a colour image from `bytes` (PNG, EXR or PFM by signature) into linear light,
/// refusing one of more than `max_pixels` from its header; errors name `name`.
pub fn decode_color(name: &str, bytes: &[u8], max_pixels: u64) -> Result<RgbImage, RenderError> {
    let raw = decode_raw(name, format_of_bytes(name, bytes)?, bytes, max_pixels)?;
    color_of(name, raw)
}

/// The first channel of the image in `bytes` (PNG, EXR or PFM by signature) as stored:
/// floats from EXR and PFM, integers from a 16-bit PNG (an 8-bit one is refused: too coarse
/// for depth). Refuses more than `max_pixels` from the header; errors name `name`.
pub fn decode_samples(name: &str, bytes: &[u8], max_pixels: u64) -> Result<Plane, RenderError> {
    let raw = decode_raw(name, format_of_bytes(name, bytes)?, bytes, max_pixels)?;
    if raw.is_png && raw.max_int < 65535.0 {
        return Err(fmt_err(
            name,
            "an 8-bit PNG has too little precision for depth: use a 16-bit PNG, EXR or PFM",
        ));
    }
    let Raw {
        width,
        height,
        mut channels,
        ..
    } = raw;
    let first = channels.swap_remove(0);
    Ok(Plane::from_vec(width, height, first)?)
}

/// Reads a colour image into linear light, refusing one larger than [`DEFAULT_MAX_PIXELS`].
pub fn read_color(path: &Path) -> Result<RgbImage, RenderError> {
    read_color_limited(path, DEFAULT_MAX_PIXELS)
}

/// [`read_color`], refusing images of more than `max_pixels` from their header.
pub fn read_color_limited(path: &Path, max_pixels: u64) -> Result<RgbImage, RenderError> {
    color_of(&path.display().to_string(), read_raw(path, max_pixels)?)
}

/// Decoded samples as a linear colour image.
fn color_of(name: &str, raw: Raw) -> Result<RgbImage, RenderError> {
    let (w, h) = (raw.width, raw.height);
    let pick = |c: usize| -> Vec<f32> {
        // Grey (+alpha) images repeat channel 0; alpha is dropped.
        let src = if raw.channels.len() >= 3 {
            &raw.channels[c]
        } else {
            &raw.channels[0]
        };
        if raw.is_png {
            src.iter()
                .map(|&v| srgb_to_linear(v / raw.max_int))
                .collect()
        } else {
            src.clone()
        }
    };
    let planes = [0, 1, 2].map(pick);
    if let Some(v) = planes.iter().flatten().find(|v| !v.is_finite()) {
        return Err(fmt_err(
            name,
            format!("colour contains a non-finite value ({v})"),
        ));
    }
    let [r, g, b] = planes;
    Ok(RgbImage::from_planes(
        Plane::from_vec(w, h, r)?,
        Plane::from_vec(w, h, g)?,
        Plane::from_vec(w, h, b)?,
    )?)
}

/// Reads a depth map. `units` overrides the format's default (metres for EXR/PFM,
/// millimetres for 16-bit PNG). NaN, negative or zero distances are errors naming the pixel.
pub fn read_depth(path: &Path, units: Option<DepthUnits>) -> Result<DepthMap, RenderError> {
    read_depth_limited(path, units, DEFAULT_MAX_PIXELS)
}

/// [`read_depth`], refusing images of more than `max_pixels` from their header.
pub fn read_depth_limited(
    path: &Path,
    units: Option<DepthUnits>,
    max_pixels: u64,
) -> Result<DepthMap, RenderError> {
    let raw = read_raw(path, max_pixels)?;
    if raw.is_png && raw.max_int < 65535.0 && units.is_none() {
        return Err(path_err(path, "8-bit PNG depth has too little precision: use 16-bit PNG (mm), EXR or PFM, or pass --depth-units"));
    }
    let units = units.unwrap_or(if raw.is_png {
        DepthUnits::Millimeters
    } else {
        DepthUnits::Meters
    });
    let v = &raw.channels[0];
    let r = match units {
        DepthUnits::Meters => DepthMap::from_meters(raw.width, raw.height, v),
        DepthUnits::Millimeters => {
            let m: Vec<f32> = v.iter().map(|x| x / 1000.0).collect();
            DepthMap::from_meters(raw.width, raw.height, &m)
        }
        DepthUnits::Diopters => {
            Plane::from_vec(raw.width, raw.height, v.clone()).and_then(DepthMap::from_diopters)
        }
    };
    r.map_err(|e: InputError| path_err(path, e.to_string()))
}

fn write_png(
    path: &Path,
    w: usize,
    h: usize,
    samples: &[u8],
    color: png::ColorType,
    depth: png::BitDepth,
) -> Result<(), RenderError> {
    let f = File::create(path).map_err(|e| io_err(path, e))?;
    let (wu, hu) = (u32::try_from(w), u32::try_from(h));
    let (Ok(wu), Ok(hu)) = (wu, hu) else {
        return Err(path_err(path, "image too large for PNG"));
    };
    let mut enc = png::Encoder::new(BufWriter::new(f), wu, hu);
    enc.set_color(color);
    enc.set_depth(depth);
    let mut wr = enc
        .write_header()
        .map_err(|e| path_err(path, format!("PNG encode failed: {e}")))?;
    wr.write_image_data(samples)
        .map_err(|e| path_err(path, format!("PNG encode failed: {e}")))?;
    wr.finish()
        .map_err(|e| path_err(path, format!("PNG encode failed: {e}")))
}

fn write_pfm(path: &Path, w: usize, h: usize, channels: &[&Plane]) -> Result<(), RenderError> {
    let f = File::create(path).map_err(|e| io_err(path, e))?;
    let mut out = BufWriter::new(f);
    let magic = if channels.len() == 3 { "PF" } else { "Pf" };
    let mut bytes = format!("{magic}\n{w} {h}\n-1.0\n").into_bytes();
    for y in (0..h).rev() {
        for x in 0..w {
            for c in channels {
                bytes.extend_from_slice(&c.data()[y * w + x].to_le_bytes());
            }
        }
    }
    out.write_all(&bytes)
        .and_then(|_| out.flush())
        .map_err(|e| io_err(path, e))
}

/// Writes a linear colour image: `.png` as 8-bit sRGB, `.exr`/`.pfm` as linear float.
pub fn write_color(path: &Path, img: &RgbImage) -> Result<(), RenderError> {
    let (w, h) = (img.width(), img.height());
    match format_of(path)? {
        ImageFormat::Png => {
            let bytes: Vec<u8> = img
                .to_interleaved()
                .iter()
                .map(|&v| (linear_to_srgb(v) * 255.0).round() as u8)
                .collect();
            write_png(
                path,
                w,
                h,
                &bytes,
                png::ColorType::Rgb,
                png::BitDepth::Eight,
            )
        }
        ImageFormat::Exr => {
            let c = &img.channels;
            exr::prelude::write_rgb_file(path, w, h, |x, y| {
                let i = y * w + x;
                (c[0].data()[i], c[1].data()[i], c[2].data()[i])
            })
            .map_err(|e| path_err(path, format!("EXR encode failed: {e}")))
        }
        ImageFormat::Pfm => write_pfm(path, w, h, &img.channels.each_ref()),
    }
}

/// Writes an image of code values (0 to 1, as the panel is driven: already encoded through
/// its transfer function) as an 8-bit PNG, each value rounded to the nearest code.
pub fn write_code_values(path: &Path, img: &RgbImage) -> Result<(), RenderError> {
    if format_of(path)? != ImageFormat::Png {
        return Err(path_err(path, "code values are written as PNG only"));
    }
    let bytes: Vec<u8> = img
        .to_interleaved()
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    write_png(
        path,
        img.width(),
        img.height(),
        &bytes,
        png::ColorType::Rgb,
        png::BitDepth::Eight,
    )
}

/// The code values of an 8-bit RGB PNG as written by [`write_code_values`]: (width, height,
/// RGB bytes, rows from the top). Another kind of PNG is refused.
pub fn read_code_values(path: &Path) -> Result<(usize, usize, Vec<u8>), RenderError> {
    let file = std::fs::File::open(path).map_err(|e| io_err(path, e))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| path_err(path, format!("PNG decode failed: {e}")))?;
    let mut buf = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| path_err(path, format!("PNG decode failed: {e}")))?;
    if (info.color_type, info.bit_depth) != (png::ColorType::Rgb, png::BitDepth::Eight) {
        return Err(path_err(
            path,
            format!(
                "a {:?} {:?}-bit PNG: code values are 8-bit RGB",
                info.color_type, info.bit_depth
            ),
        ));
    }
    buf.truncate(info.buffer_size());
    Ok((info.width as usize, info.height as usize, buf))
}

/// Writes depth as distance: `.png` 16-bit millimetres (clamped to 65.535 m), `.exr`/`.pfm`
/// float metres (0 D is written as infinity).
pub fn write_depth(path: &Path, depth: &DepthMap) -> Result<(), RenderError> {
    let (w, h) = (depth.width(), depth.height());
    let meters: Vec<f32> = depth
        .data()
        .iter()
        .map(|&d| if d > 0.0 { 1.0 / d } else { f32::INFINITY })
        .collect();
    match format_of(path)? {
        ImageFormat::Png => {
            let bytes: Vec<u8> = meters
                .iter()
                .flat_map(|m| ((m * 1000.0).round().clamp(1.0, 65535.0) as u16).to_be_bytes())
                .collect();
            write_png(
                path,
                w,
                h,
                &bytes,
                png::ColorType::Grayscale,
                png::BitDepth::Sixteen,
            )
        }
        ImageFormat::Exr => {
            use exr::prelude::*;
            let px = SpecificChannels::build()
                .with_channel("Z")
                .with_pixel_fn(|p: Vec2<usize>| (meters[p.y() * w + p.x()],));
            Image::from_channels((w, h), px)
                .write()
                .to_file(path)
                .map_err(|e| path_err(path, format!("EXR encode failed: {e}")))
        }
        ImageFormat::Pfm => {
            let p = Plane::from_vec(w, h, meters)?;
            write_pfm(path, w, h, &[&p])
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The refusal names the size and the limit (and did not allocate: a 60000 x 60000 float
    /// image would be 43 GB).
    fn refused_from_header(r: Result<RgbImage, RenderError>) {
        let e = r.expect_err("a hostile header was read");
        let msg = e.to_string();
        assert!(
            msg.contains("60000 x 60000") && msg.contains("--max-pixels"),
            "{msg}"
        );
    }

    fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        out.extend_from_slice(kind);
        out.extend_from_slice(data);
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        let crc = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(&body);
        out.extend_from_slice(&crc.to_be_bytes());
    }

    #[test]
    fn hostile_headers_are_refused_before_allocating() {
        // PNG: a 60000 x 60000 RGB IHDR and an empty IDAT, 60 bytes in all.
        let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&60000u32.to_be_bytes());
        ihdr.extend_from_slice(&60000u32.to_be_bytes());
        ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
        png_chunk(&mut png, b"IHDR", &ihdr);
        png_chunk(&mut png, b"IDAT", b"\x78\x9c\x03\x00\x00\x00\x00\x01");
        png_chunk(&mut png, b"IEND", b"");
        let p = tmp("huge.png");
        std::fs::write(&p, &png).unwrap();
        refused_from_header(read_color(&p));
        assert!(read_depth(&p, Some(DepthUnits::Millimeters)).is_err());

        // EXR: a real 4 x 4 file whose data window is rewritten to 60000 x 60000.
        let small = tmp("small.exr");
        write_color(&small, &RgbImage::new(4, 4, [0.5; 3])).unwrap();
        let mut exr = std::fs::read(&small).unwrap();
        let key = b"dataWindow\0box2i\0";
        let at = exr
            .windows(key.len())
            .position(|w| w == key)
            .expect("no dataWindow attribute")
            + key.len()
            + 4;
        exr[at + 8..at + 12].copy_from_slice(&59999i32.to_le_bytes());
        exr[at + 12..at + 16].copy_from_slice(&59999i32.to_le_bytes());
        let p = tmp("huge.exr");
        std::fs::write(&p, &exr).unwrap();
        refused_from_header(read_color(&p));

        // PFM: the header alone.
        let p = tmp("huge.pfm");
        std::fs::write(&p, b"PF\n60000 60000\n-1.0\n\0\0\0\0").unwrap();
        refused_from_header(read_color(&p));

        // The limit is the caller's: a 4 x 4 image over a 15-pixel limit is refused too.
        let e = read_color_limited(&small, 15).unwrap_err().to_string();
        assert!(e.contains("4 x 4"), "{e}");
        assert!(read_color_limited(&small, 16).is_ok());
    }

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("dioptra-render-io-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d.join(name)
    }

    fn sample() -> RgbImage {
        let d: Vec<f32> = (0..5 * 3 * 3)
            .map(|i| (i as f32 / 45.0).powf(1.5))
            .collect();
        RgbImage::from_interleaved(5, 3, &d).unwrap()
    }

    #[test]
    fn float_formats_round_trip_exactly() {
        let img = sample();
        for ext in ["exr", "pfm"] {
            let p = tmp(&format!("c.{ext}"));
            write_color(&p, &img).unwrap();
            assert_eq!(read_color(&p).unwrap(), img, "{ext}");
        }
        let depth = DepthMap::from_diopters(
            Plane::from_vec(3, 2, vec![0.0, 0.25, 1.0, 2.0, 4.0, 0.1]).unwrap(),
        )
        .unwrap();
        for ext in ["exr", "pfm", "png"] {
            let p = tmp(&format!("d.{ext}"));
            write_depth(&p, &depth).unwrap();
            let back = read_depth(&p, None).unwrap();
            for (a, b) in back.data().iter().zip(depth.data()) {
                // 16-bit PNG holds whole millimetres, and clamps infinity to 65.535 m.
                let tol = if ext == "png" { 0.016 } else { 1e-6 };
                assert!((a - b).abs() <= tol, "{ext}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn images_decode_from_memory_as_from_files() {
        let img = sample();
        for ext in ["png", "exr", "pfm"] {
            let p = tmp(&format!("m.{ext}"));
            write_color(&p, &img).unwrap();
            let bytes = std::fs::read(&p).unwrap();
            assert_eq!(ImageFormat::of_bytes(&bytes), Some(format_of(&p).unwrap()));
            assert_eq!(encoded_size("the colour file", &bytes).unwrap(), (5, 3));
            let from_memory = decode_color("the colour file", &bytes, 15).unwrap();
            assert_eq!(from_memory, read_color(&p).unwrap(), "{ext}");
            // The caller's limit, from the header, naming what it was given.
            let e = decode_color("the colour file", &bytes, 14)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("the colour file") && e.contains("5 x 3"),
                "{ext}: {e}"
            );
        }
        // Depth samples as stored: whole millimetres in a 16-bit PNG, metres in an EXR.
        let depth =
            DepthMap::from_diopters(Plane::from_vec(2, 1, vec![2.0, 0.5]).unwrap()).unwrap();
        for (ext, want) in [("png", [500.0, 2000.0]), ("exr", [0.5, 2.0])] {
            let p = tmp(&format!("md.{ext}"));
            write_depth(&p, &depth).unwrap();
            let s = decode_samples("the depth file", &std::fs::read(&p).unwrap(), 2).unwrap();
            assert_eq!(s.data(), &want, "{ext}");
        }
        let p = tmp("m8.png");
        write_color(&p, &img).unwrap();
        let e = decode_samples("the depth file", &std::fs::read(&p).unwrap(), 100)
            .unwrap_err()
            .to_string();
        assert!(e.contains("8-bit PNG") && e.contains("16-bit"), "{e}");
        let e = decode_color("the colour file", b"GIF89a\x01\x00", 100)
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a PNG, EXR or PFM"), "{e}");
        // A signature and nothing after it.
        assert!(encoded_size("x", b"\x89PNG\r\n\x1a\n").is_err());
        assert!(encoded_size("x", &[0x76, 0x2f, 0x31, 0x01]).is_err());
        assert!(decode_color("x", b"PF\n2 2\n-1.0\n\0", 100).is_err());
    }

    #[test]
    fn png_is_srgb_encoded_and_decoded() {
        let img = sample();
        let p = tmp("c.png");
        write_color(&p, &img).unwrap();
        let back = read_color(&p).unwrap();
        // 8-bit sRGB: error below half a code value in the encoded domain.
        for c in 0..3 {
            for (a, b) in back.channels[c].data().iter().zip(img.channels[c].data()) {
                assert!((linear_to_srgb(*a) - linear_to_srgb(*b)).abs() <= 0.5 / 255.0 + 1e-6);
            }
        }
    }

    #[test]
    fn clear_errors() {
        let e = read_color(Path::new("/nonexistent/x.png")).unwrap_err();
        assert!(e.to_string().contains("not found"), "{e}");
        let bad = tmp("bad.png");
        std::fs::write(&bad, b"not a png").unwrap();
        assert!(matches!(read_color(&bad), Err(RenderError::Format { .. })));
        assert!(matches!(
            read_color(Path::new("x.jpg")),
            Err(RenderError::Io { .. }) | Err(RenderError::Format { .. })
        ));
        // NaN and negative depth are rejected with the pixel named
        let p = tmp("nan.pfm");
        let plane = Plane::from_vec(2, 1, vec![1.0, f32::NAN]).unwrap();
        write_pfm(&p, 2, 1, &[&plane]).unwrap();
        let e = read_depth(&p, None).unwrap_err();
        assert!(e.to_string().contains("(1, 0)"), "{e}");
        let plane = Plane::from_vec(2, 1, vec![-1.0, 1.0]).unwrap();
        write_pfm(&p, 2, 1, &[&plane]).unwrap();
        assert!(read_depth(&p, None).is_err());
        let trunc = tmp("t.pfm");
        std::fs::write(&trunc, b"Pf\n4 4\n-1.0\n\0\0").unwrap();
        assert!(read_depth(&trunc, None)
            .unwrap_err()
            .to_string()
            .contains("truncated"));
    }
}
