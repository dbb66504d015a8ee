//! Image types. Colour is linear-light RGB in three f32 planes; depth is in diopters.
//! sRGB is decoded and encoded only at file I/O (see [`srgb_to_linear`]).

use crate::error::InputError;
use crate::units::Diopters;

/// One f32 channel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl Plane {
    pub fn new(width: usize, height: usize, fill: f32) -> Self {
        Plane {
            width,
            height,
            data: vec![fill; width * height],
        }
    }

    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Result<Self, InputError> {
        check_len(width, height, data.len())?;
        Ok(Plane {
            width,
            height,
            data,
        })
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    pub fn data(&self) -> &[f32] {
        &self.data
    }
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }
    pub fn into_vec(self) -> Vec<f32> {
        self.data
    }
    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        (x < self.width && y < self.height).then(|| self.data[y * self.width + x])
    }
    pub fn row(&self, y: usize) -> &[f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }
}

fn check_len(width: usize, height: usize, len: usize) -> Result<(), InputError> {
    match width.checked_mul(height) {
        Some(n) if n == len => Ok(()),
        _ => Err(InputError::SizeMismatch(format!(
            "{width}x{height} needs {} samples, got {len}",
            width.saturating_mul(height)
        ))),
    }
}

/// Linear-light RGB, one plane per channel.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub channels: [Plane; 3],
}

impl RgbImage {
    pub fn new(width: usize, height: usize, fill: [f32; 3]) -> Self {
        RgbImage {
            channels: fill.map(|v| Plane::new(width, height, v)),
        }
    }

    pub fn from_planes(r: Plane, g: Plane, b: Plane) -> Result<Self, InputError> {
        if (r.width, r.height) != (g.width, g.height) || (r.width, r.height) != (b.width, b.height)
        {
            return Err(InputError::SizeMismatch(format!(
                "channel sizes differ: {}x{}, {}x{}, {}x{}",
                r.width, r.height, g.width, g.height, b.width, b.height
            )));
        }
        Ok(RgbImage {
            channels: [r, g, b],
        })
    }

    /// From interleaved `[r, g, b, r, g, b, ...]` linear samples.
    pub fn from_interleaved(width: usize, height: usize, rgb: &[f32]) -> Result<Self, InputError> {
        check_len(width, height, rgb.len() / 3)?;
        if rgb.len() % 3 != 0 {
            return Err(InputError::SizeMismatch(
                "interleaved RGB length is not a multiple of 3".into(),
            ));
        }
        let mut img = RgbImage::new(width, height, [0.0; 3]);
        for (i, px) in rgb.chunks_exact(3).enumerate() {
            for (c, plane) in img.channels.iter_mut().enumerate() {
                plane.data[i] = px[c];
            }
        }
        Ok(img)
    }

    pub fn to_interleaved(&self) -> Vec<f32> {
        let n = self.width() * self.height();
        let mut out = Vec::with_capacity(n * 3);
        for i in 0..n {
            out.extend(self.channels.iter().map(|p| p.data[i]));
        }
        out
    }

    pub fn width(&self) -> usize {
        self.channels[0].width
    }
    pub fn height(&self) -> usize {
        self.channels[0].height
    }
    pub fn pixel(&self, x: usize, y: usize) -> Option<[f32; 3]> {
        let i = (x < self.width() && y < self.height()).then(|| y * self.width() + x)?;
        Some(self.channels.each_ref().map(|p| p.data[i]))
    }
}

/// Depth per pixel in diopters (0 D = infinitely far).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    plane: Plane,
}

impl DepthMap {
    /// Checks that every value is finite and non-negative, naming the first bad pixel.
    pub fn from_diopters(plane: Plane) -> Result<Self, InputError> {
        // One pass without an early exit (it vectorises); the pixel is looked for on failure.
        let valid = plane
            .data
            .iter()
            .fold(true, |ok, v| ok & (v.is_finite() & (*v >= 0.0)));
        if valid {
            return Ok(DepthMap { plane });
        }
        if let Some((i, v)) = plane
            .data
            .iter()
            .enumerate()
            .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
        {
            return Err(InputError::InvalidValue(format!(
                "depth at pixel ({}, {}) is {v} D: depth must be finite and >= 0 D",
                i % plane.width.max(1),
                i / plane.width.max(1)
            )));
        }
        Ok(DepthMap { plane })
    }

    /// From distances in metres (0 or negative is invalid; infinity is 0 D).
    pub fn from_meters(width: usize, height: usize, meters: &[f32]) -> Result<Self, InputError> {
        check_len(width, height, meters.len())?;
        let mut d = Vec::with_capacity(meters.len());
        for (i, &m) in meters.iter().enumerate() {
            if m.is_nan() || m <= 0.0 {
                return Err(InputError::InvalidValue(format!(
                    "depth at pixel ({}, {}) is {m} m: distances must be > 0 (NaN and negative are invalid)",
                    i % width.max(1),
                    i / width.max(1)
                )));
            }
            d.push(if m.is_infinite() { 0.0 } else { 1.0 / m });
        }
        Self::from_diopters(Plane::from_vec(width, height, d)?)
    }

    pub fn width(&self) -> usize {
        self.plane.width
    }
    pub fn height(&self) -> usize {
        self.plane.height
    }
    pub fn plane(&self) -> &Plane {
        &self.plane
    }
    /// The diopters plane, given up (to reuse its memory).
    pub fn into_plane(self) -> Plane {
        self.plane
    }
    pub fn data(&self) -> &[f32] {
        &self.plane.data
    }
    pub fn at(&self, x: usize, y: usize) -> Option<Diopters> {
        self.plane.get(x, y).map(Diopters)
    }
    /// Smallest and largest depth present, diopters; `None` for an empty map.
    pub fn range(&self) -> Option<(Diopters, Diopters)> {
        let mut it = self.plane.data.iter().copied();
        let first = it.next()?;
        let (lo, hi) = it.fold((first, first), |(lo, hi), v| (lo.min(v), hi.max(v)));
        Some((Diopters(lo), Diopters(hi)))
    }
}

/// A colour image with its depth, same size.
#[derive(Debug, Clone, PartialEq)]
pub struct Rgbd {
    pub color: RgbImage,
    pub depth: DepthMap,
}

impl Rgbd {
    pub fn new(color: RgbImage, depth: DepthMap) -> Result<Self, InputError> {
        if (color.width(), color.height()) != (depth.width(), depth.height()) {
            return Err(InputError::SizeMismatch(format!(
                "colour is {}x{} but depth is {}x{}",
                color.width(),
                color.height(),
                depth.width(),
                depth.height()
            )));
        }
        Ok(Rgbd { color, depth })
    }
    pub fn width(&self) -> usize {
        self.color.width()
    }
    pub fn height(&self) -> usize {
        self.color.height()
    }
}

/// The sRGB transfer function, decoded (IEC 61966-2-1).
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// The sRGB transfer function, encoded; input clamped to [0, 1].
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    if v <= 0.003_130_8 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_are_checked() {
        assert!(Plane::from_vec(3, 2, vec![0.0; 5]).is_err());
        assert!(Plane::from_vec(usize::MAX, 2, vec![]).is_err());
        let c = RgbImage::new(4, 3, [0.5; 3]);
        let d = DepthMap::from_diopters(Plane::new(3, 4, 1.0)).unwrap();
        assert!(matches!(Rgbd::new(c, d), Err(InputError::SizeMismatch(_))));
    }

    #[test]
    fn depth_rejects_nan_and_negative_and_names_pixel() {
        let e = DepthMap::from_meters(2, 2, &[1.0, 1.0, f32::NAN, 1.0]).unwrap_err();
        assert!(
            matches!(&e, InputError::InvalidValue(m) if m.contains("(0, 1)")),
            "{e}"
        );
        assert!(DepthMap::from_meters(2, 1, &[-1.0, 1.0]).is_err());
        let ok = DepthMap::from_meters(2, 1, &[0.5, f32::INFINITY]).unwrap();
        assert_eq!(ok.data(), &[2.0, 0.0]);
        assert_eq!(ok.range(), Some((Diopters(0.0), Diopters(2.0))));
    }

    #[test]
    fn interleaved_round_trip() {
        let px: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let img = RgbImage::from_interleaved(2, 2, &px).unwrap();
        assert_eq!(img.pixel(1, 0), Some([3.0, 4.0, 5.0]));
        assert_eq!(img.pixel(2, 0), None);
        assert_eq!(img.to_interleaved(), px);
    }

    #[test]
    fn srgb_round_trip_and_known_values() {
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
        assert!((linear_to_srgb(2.0) - 1.0).abs() < 1e-6);
        assert_eq!(linear_to_srgb(f32::NAN), 0.0);
        for i in 0..=255 {
            let v = i as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
        }
    }
}
