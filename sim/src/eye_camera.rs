//! A simulated camera at the eye: what a camera in the eye's place sees of the panel through
//! the rig's simulated optics, so that tests can check the image chain end to end.
//!
//! The optics (this module's own code, not the driver's or the renderer's):
//! - The panel ([`PanelResponse`]): each pixel a uniform square of light, its luminance per
//!   channel `black + (white - black) q^γ` for the code value `q` quantised to the panel's bit
//!   depth (light added on top of black: backlight bleed).
//! - The eyepiece ([`TrueEyepiece`]): per colour channel, Brown-Conrady radial and tangential
//!   terms taking an eye direction (tangents of its angles) to a panel pixel, as measured with
//!   the tunable lens at `reference_power_d`.
//! - The tunable lens ([`ThinLenses`]): display, lens (with a fixed lens at it), eye, as thin
//!   lenses. At power P the display's image is at vergence `A(P) = X / (1 + s X)`, `X = 1/d - P`
//!   at the eye, and subtends `M(P) = (d + s) / (d + s - s d P)` times the bare display's
//!   angle; a direction seen at lens power P is the one the eyepiece model has at the
//!   reference power scaled by `M(ref) / M(P)`.
//! - The eye's focus: the camera is focused at `focus_d` diopters; the panel's image is blurred
//!   by a disk `pupil * |focus - A(P)|` radians across (geometric defocus).
//! - The camera: an ideal pinhole camera (`f_px` pixels per unit tangent, centre `c`) that
//!   integrates each pixel over `supersample²` points.
//!
//! Layers shown one after another within the eye's integration time (a multifocal display) add
//! as light: [`EyeCamera::see_layers`].

use dioptra_core::{Plane, RgbImage};
use rayon::prelude::*;

/// The panel's light per code value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PanelResponse {
    pub gamma: f64,
    /// Luminance at code 0 and at full scale, cd/m².
    pub black_cd_m2: f64,
    pub white_cd_m2: f64,
    /// Code values are quantised to this many bits before they light the panel.
    pub bits: u32,
}

impl PanelResponse {
    /// A gamma-2.4 panel with a black of 0.3 cd/m² under a white of 120 cd/m² (a 400:1
    /// panel), 8 bits.
    pub fn example() -> Self {
        PanelResponse {
            gamma: 2.4,
            black_cd_m2: 0.3,
            white_cd_m2: 120.0,
            bits: 8,
        }
    }

    /// Luminance for code value `q` (0 to 1; NaN is 0).
    pub fn luminance(&self, q: f64) -> f64 {
        let q = if q.is_nan() { 0.0 } else { q.clamp(0.0, 1.0) };
        let full = ((1u64 << self.bits.clamp(1, 24)) - 1) as f64;
        let q = (q * full).round() / full;
        self.black_cd_m2 + (self.white_cd_m2 - self.black_cd_m2) * q.powf(self.gamma)
    }
}

/// A simulated spot photometer on the panel: the luminance of the patch shown, with
/// reproducible noise (a fraction of the reading, from a seed and the reading's index).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Photometer {
    pub panel: PanelResponse,
    /// Standard deviation of the noise, as a fraction of the reading.
    pub noise: f64,
    pub seed: u64,
}

impl Photometer {
    /// The reading of a patch at code value `q`; `index` picks the noise draw.
    pub fn read(&self, q: f64, index: u64) -> f64 {
        let l = self.panel.luminance(q);
        if self.noise == 0.0 {
            return l;
        }
        // Box-Muller on two splitmix64 draws.
        let u = |k: u64| {
            let mut z = self.seed ^ index.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ k;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let g = (-2.0 * u(1).ln()).sqrt() * (std::f64::consts::TAU * u(2)).cos();
        l * (1.0 + self.noise * g)
    }
}

/// One colour channel of the eyepiece: Brown-Conrady's radial (k1, k2, k3) and tangential (p1,
/// p2) terms and the intrinsics that take the distorted direction to a panel pixel (pixel
/// centres at integers).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EyepieceChannel {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    pub p1: f64,
    pub p2: f64,
}

impl EyepieceChannel {
    /// Eye direction (tangents) to the panel pixel the eye sees along it.
    pub fn panel_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        let rr = x * x + y * y;
        let radial = 1.0 + self.k1 * rr + self.k2 * rr * rr + self.k3 * rr * rr * rr;
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (rr + 2.0 * x * x);
        let yd = y * radial + self.p1 * (rr + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (self.fx * xd + self.cx, self.fy * yd + self.cy)
    }
}

/// The eyepiece's true distortion, red, green and blue.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueEyepiece(pub [EyepieceChannel; 3]);

/// Display, tunable lens (with a fixed lens at it) and eye as thin lenses, metres and diopters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThinLenses {
    pub display_distance_m: f64,
    pub eye_relief_m: f64,
    pub fixed_power_d: f64,
}

impl ThinLenses {
    /// The vergence the eye must accommodate to see the display sharp, at tunable power `p`.
    pub fn demand_d(&self, p: f64) -> f64 {
        let x = 1.0 / self.display_distance_m - self.fixed_power_d - p;
        x / (1.0 + self.eye_relief_m * x)
    }
    /// Angular size of the display's image against the bare display's.
    pub fn magnification(&self, p: f64) -> f64 {
        let (d, s) = (self.display_distance_m, self.eye_relief_m);
        (d + s) / (d + s - s * d * (self.fixed_power_d + p))
    }
}

/// The rig's optics in front of one eye.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimOptics {
    pub lenses: ThinLenses,
    pub eyepiece: TrueEyepiece,
    /// The tunable lens's power at which the eyepiece's model was measured.
    pub reference_power_d: f64,
}

/// The camera at the eye.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EyeCamera {
    pub width: usize,
    pub height: usize,
    /// Pixels per unit tangent.
    pub f_px: f64,
    /// The optical axis's pixel (pixel centres at integers).
    pub cx: f64,
    pub cy: f64,
    /// The eye's pupil (its blur), millimetres.
    pub pupil_mm: f64,
    /// Samples per pixel along each axis.
    pub supersample: usize,
}

impl EyeCamera {
    /// What the camera sees of one panel image (code values) shown with the tunable lens at
    /// `lens_power_d`, focused at `focus_d`: luminance per channel, cd/m².
    pub fn see(
        &self,
        panel: &RgbImage,
        response: &PanelResponse,
        optics: &SimOptics,
        lens_power_d: f64,
        focus_d: f64,
    ) -> RgbImage {
        let (w, h) = (self.width, self.height);
        let ratio = optics.lenses.magnification(optics.reference_power_d)
            / optics.lenses.magnification(lens_power_d);
        let n = self.supersample.max(1);
        // Code value to luminance once per panel pixel and channel.
        let light: Vec<Vec<f32>> = panel
            .channels
            .iter()
            .map(|p| {
                p.data()
                    .iter()
                    .map(|&q| response.luminance(f64::from(q)) as f32)
                    .collect()
            })
            .collect();
        let (pw, ph) = (panel.width() as i64, panel.height() as i64);
        let mut planes: Vec<Vec<f32>> = (0..3).map(|_| vec![0.0f32; w * h]).collect();
        for (c, plane) in planes.iter_mut().enumerate() {
            let eyepiece = optics.eyepiece.0[c];
            let light = &light[c];
            plane.par_chunks_mut(w).enumerate().for_each(|(j, row)| {
                for (i, out) in row.iter_mut().enumerate() {
                    let mut sum = 0.0f64;
                    for sy in 0..n {
                        for sx in 0..n {
                            let u = i as f64 - 0.5 + (sx as f64 + 0.5) / n as f64;
                            let v = j as f64 - 0.5 + (sy as f64 + 0.5) / n as f64;
                            let x = (u - self.cx) / self.f_px * ratio;
                            let y = (v - self.cy) / self.f_px * ratio;
                            let (px, py) = eyepiece.panel_pixel(x, y);
                            // The panel pixel whose square holds the point.
                            let (ix, iy) = ((px + 0.5).floor() as i64, (py + 0.5).floor() as i64);
                            if ix >= 0 && iy >= 0 && ix < pw && iy < ph {
                                sum += f64::from(light[(iy * pw + ix) as usize]);
                            }
                        }
                    }
                    *out = (sum / (n * n) as f64) as f32;
                }
            });
        }
        let defocus = (focus_d - optics.lenses.demand_d(lens_power_d)).abs();
        let blur_px = self.pupil_mm * 1e-3 * defocus * self.f_px;
        let planes: Vec<Plane> = planes
            .into_iter()
            .map(|p| disk_blur(&Plane::from_vec(w, h, p).expect("camera size"), blur_px))
            .collect();
        let [r, g, b]: [Plane; 3] = planes.try_into().expect("three channels");
        RgbImage::from_planes(r, g, b).expect("camera size")
    }

    /// Layers shown in turn within one exposure, each with the lens at its own power: their
    /// light adds.
    pub fn see_layers(
        &self,
        layers: &[(&RgbImage, f64)],
        response: &PanelResponse,
        optics: &SimOptics,
        focus_d: f64,
    ) -> RgbImage {
        let mut total = RgbImage::new(self.width, self.height, [0.0; 3]);
        for (panel, power) in layers {
            let seen = self.see(panel, response, optics, *power, focus_d);
            for (t, s) in total.channels.iter_mut().zip(&seen.channels) {
                for (a, b) in t.data_mut().iter_mut().zip(s.data()) {
                    *a += b;
                }
            }
        }
        total
    }
}

/// A disk blur of diameter `diameter_px`, each tap weighted by the fraction of its pixel
/// inside the disk (8 x 8 points), normalised; under half a pixel it is left sharp.
pub fn disk_blur(p: &Plane, diameter_px: f64) -> Plane {
    if diameter_px.is_nan() || diameter_px < 0.5 {
        return p.clone();
    }
    let radius = diameter_px / 2.0;
    let reach = radius.ceil() as i64;
    let mut taps = Vec::new();
    for dy in -reach..=reach {
        for dx in -reach..=reach {
            let mut inside = 0;
            for sy in 0..8 {
                for sx in 0..8 {
                    let x = dx as f64 - 0.5 + (sx as f64 + 0.5) / 8.0;
                    let y = dy as f64 - 0.5 + (sy as f64 + 0.5) / 8.0;
                    if x * x + y * y <= radius * radius {
                        inside += 1;
                    }
                }
            }
            if inside > 0 {
                taps.push((dx, dy, inside as f64 / 64.0));
            }
        }
    }
    let total: f64 = taps.iter().map(|t| t.2).sum();
    let (w, h) = (p.width() as i64, p.height() as i64);
    let data = p.data();
    let mut out = vec![0.0f32; (w * h) as usize];
    out.par_chunks_mut(w as usize)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let mut s = 0.0f64;
                for &(dx, dy, wgt) in &taps {
                    // Outside the camera's frame counts as its nearest edge pixel.
                    let xx = (x as i64 + dx).clamp(0, w - 1);
                    let yy = (y as i64 + dy).clamp(0, h - 1);
                    s += wgt * f64::from(data[(yy * w + xx) as usize]);
                }
                *o = (s / total) as f32;
            }
        });
    Plane::from_vec(w as usize, h as usize, out).expect("same size")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_panel_and_the_lenses_by_hand() {
        let p = PanelResponse::example();
        // 8-bit 128 is 0.50196: 0.3 + 119.7 * 0.50196^2.4.
        let want = 0.3 + 119.7 * (128.0f64 / 255.0).powf(2.4);
        assert!((p.luminance(0.5) - want).abs() < 1e-9);
        assert_eq!(p.luminance(f64::NAN), 0.3);
        let l = ThinLenses {
            display_distance_m: 0.05,
            eye_relief_m: 0.015,
            fixed_power_d: 18.0,
        };
        // X = 20 - 18 - 1 = 1 D at P = 1: A = 1 / 1.015.
        assert!((l.demand_d(1.0) - 1.0 / 1.015).abs() < 1e-12);
        // M = 0.065 / (0.065 - 0.015 * 0.05 * 19).
        assert!((l.magnification(1.0) - 0.065 / (0.065 - 0.000_75 * 19.0)).abs() < 1e-12);
    }

    #[test]
    fn a_photometer_s_noise_is_what_it_says() {
        let ph = Photometer {
            panel: PanelResponse::example(),
            noise: 0.01,
            seed: 7,
        };
        let n = 4000;
        let r: Vec<f64> = (0..n).map(|k| ph.read(1.0, k) / 120.0 - 1.0).collect();
        let mean = r.iter().sum::<f64>() / n as f64;
        let sd = (r.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        assert!(mean.abs() < 1e-3 && (sd - 0.01).abs() < 1e-3, "{mean} {sd}");
        assert_eq!(ph.read(0.3, 5), ph.read(0.3, 5));
    }

    #[test]
    fn a_disk_blur_keeps_light_and_spreads_a_point_over_its_disk() {
        let mut p = Plane::new(41, 41, 0.0);
        p.data_mut()[20 * 41 + 20] = 1.0;
        let b = disk_blur(&p, 10.0);
        let sum: f32 = b.data().iter().sum();
        assert!((sum - 1.0).abs() < 1e-5);
        // Inside radius 4 lit evenly; beyond 6 dark.
        assert!((b.get(23, 20).unwrap() - b.get(20, 20).unwrap()).abs() < 1e-7);
        assert_eq!(b.get(27, 20).unwrap(), 0.0);
    }
}
