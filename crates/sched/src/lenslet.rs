//! The panel image of a lenslet (integral-imaging) near-eye light-field display, resampled from
//! a light field of pinhole views (Lanman and Luebke 2013).
//!
//! Geometry, per axis (x right, y down, z from the eye's pupil plane towards the display): the
//! lenslet array lies at `z = eye_relief`, the panel `gap` behind it. Lenslet `i` is centred at
//! `c = (i + 0.5 - n/2) * pitch`. Its elemental image is centred where the line from the pupil
//! centre through `c` meets the panel, `e = c (eye_relief + gap) / eye_relief`, and is that
//! much wider than the lenslet, so every lenslet's rays converge on the eye box. A pixel at
//! panel position `x` shows the ray through its lenslet's centre, which reaches the eye from
//! direction (tangent) `t = (x - c) / gap` and crosses the pupil plane at
//! `s = c - t * eye_relief`. The pixel's value is the light field at `(s, t)`: bilinear across
//! the views around `s` and within each view around `t`.

use dioptra_core::{InputError, Plane, RgbImage};

/// A lenslet display.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensletDisplay {
    /// Lenslets across and down.
    pub lenslets: [usize; 2],
    /// Panel pixels under each lenslet, per axis (the elemental image is this square).
    pub pixels_per_lenslet: usize,
    pub lenslet_pitch_m: f32,
    /// Panel to lenslet array, metres.
    pub gap_m: f32,
    /// Lenslet array to the eye's pupil plane, metres.
    pub eye_relief_m: f32,
}

/// A light field of pinhole views on a regular `grid` x `grid` lattice in the pupil plane,
/// `spacing_m` apart and centred on the eye, row-major from the top-left view (as
/// `dioptra_render::views::synthesize_light_field` and the scene simulator make them). Each
/// view's pixel `(x, y)` looks along tangent `((x + 0.5 - W/2) p, (y + 0.5 - H/2) p)`.
#[derive(Debug, Clone, Copy)]
pub struct ViewGrid<'a> {
    pub grid: usize,
    pub spacing_m: f32,
    pub views: &'a [RgbImage],
    /// Tangent-plane size of one view pixel (`EyeModel::pixel_pitch_tan` at the view width).
    pub pixel_pitch_tan: f32,
}

fn invalid(msg: String) -> InputError {
    InputError::InvalidValue(msg)
}

impl LensletDisplay {
    /// Panel size in pixels (width, height).
    pub fn panel_size(&self) -> (usize, usize) {
        (
            self.lenslets[0].saturating_mul(self.pixels_per_lenslet),
            self.lenslets[1].saturating_mul(self.pixels_per_lenslet),
        )
    }

    fn check(&self) -> Result<(), InputError> {
        let (w, h) = self.panel_size();
        if w == 0 || h == 0 || w.saturating_mul(h) > 1 << 26 {
            return Err(invalid(format!(
                "lenslet display {}x{} lenslets of {} px: expected 1 to 2^26 panel pixels",
                self.lenslets[0], self.lenslets[1], self.pixels_per_lenslet
            )));
        }
        let pos = |v: f32| v.is_finite() && v > 0.0;
        if !(pos(self.lenslet_pitch_m) && pos(self.gap_m) && pos(self.eye_relief_m)) {
            return Err(invalid(format!(
                "lenslet pitch {} m, gap {} m and eye relief {} m must all be > 0",
                self.lenslet_pitch_m, self.gap_m, self.eye_relief_m
            )));
        }
        Ok(())
    }

    /// The (pupil position, tangent) of the ray panel coordinate `k` shows, along one axis
    /// with `n` lenslets.
    fn ray(&self, k: usize, n: usize) -> (f32, f32) {
        let ppl = self.pixels_per_lenslet;
        let lens = k / ppl;
        let (pitch, er, gap) = (self.lenslet_pitch_m, self.eye_relief_m, self.gap_m);
        let c = (lens as f32 + 0.5 - n as f32 * 0.5) * pitch;
        let widen = (er + gap) / er;
        let x =
            c * widen + ((k % ppl) as f32 + 0.5 - ppl as f32 * 0.5) * (pitch * widen / ppl as f32);
        let t = (x - c) / gap;
        (c - t * er, t)
    }
}

/// Bilinear sample at continuous pixel position (x, y), centres at +0.5, edges clamped.
fn bilinear(p: &Plane, x: f32, y: f32) -> f32 {
    let (w, h) = (p.width() as isize, p.height() as isize);
    let (fx, fy) = (x - 0.5, y - 0.5);
    let (x0, y0) = (fx.floor(), fy.floor());
    let (tx, ty) = (fx - x0, fy - y0);
    let at =
        |xi: isize, yi: isize| p.data()[(yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)) as usize];
    let (xi, yi) = (x0 as isize, y0 as isize);
    let a = at(xi, yi) * (1.0 - tx) + at(xi + 1, yi) * tx;
    let b = at(xi, yi + 1) * (1.0 - tx) + at(xi + 1, yi + 1) * tx;
    a * (1.0 - ty) + b * ty
}

/// Index and weight of the two grid views around pupil coordinate `s` (clamped to the grid).
fn view_pair(s: f32, grid: usize, spacing: f32) -> [(usize, f32); 2] {
    if grid == 1 || spacing <= 0.0 {
        return [(0, 1.0), (0, 0.0)];
    }
    let u = (s / spacing + (grid - 1) as f32 * 0.5).clamp(0.0, (grid - 1) as f32);
    let i0 = (u.floor() as usize).min(grid - 2);
    let f = u - i0 as f32;
    [(i0, 1.0 - f), (i0 + 1, f)]
}

/// Where each panel column (or row) reads the light field: the first of the two views around
/// its pupil position and the weight of each, and its position in a view (pixels, centres at
/// +0.5): `[first view, its weight, the next view's weight, position]`. Panel pixel (x, y)
/// is the sum over the column's and the row's view pairs of the product of their weights
/// times the bilinear sample of view (row view, column view) at (column's, row's position),
/// pairs of weight 0 skipped: what [`elemental_images`] computes, and a GPU twin with it.
#[derive(Debug, Clone, PartialEq)]
pub struct Sampling {
    pub cols: Vec<[f32; 4]>,
    pub rows: Vec<[f32; 4]>,
}

/// A light field's lattice without its pixels: what [`sampling`] needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridGeometry {
    pub grid: usize,
    pub spacing_m: f32,
    pub pixel_pitch_tan: f32,
    /// Each view's width and height, pixels.
    pub view_size: (usize, usize),
}

impl ViewGrid<'_> {
    /// Its lattice, once its views are checked (as many as the grid has, all one size).
    pub fn geometry(&self) -> Result<GridGeometry, InputError> {
        if self.grid == 0 || self.views.len() != self.grid.saturating_mul(self.grid) {
            return Err(InputError::SizeMismatch(format!(
                "a {g}x{g} view grid needs {} views, got {}",
                self.grid.saturating_mul(self.grid),
                self.views.len(),
                g = self.grid
            )));
        }
        let (vw, vh) = (self.views[0].width(), self.views[0].height());
        if self
            .views
            .iter()
            .any(|v| (v.width(), v.height()) != (vw, vh))
        {
            return Err(InputError::SizeMismatch(
                "light-field views differ in size".into(),
            ));
        }
        Ok(GridGeometry {
            grid: self.grid,
            spacing_m: self.spacing_m,
            pixel_pitch_tan: self.pixel_pitch_tan,
            view_size: (vw, vh),
        })
    }
}

/// The [`Sampling`] of `display`'s panel for a light field on `lf`.
pub fn sampling(lf: &GridGeometry, display: &LensletDisplay) -> Result<Sampling, InputError> {
    display.check()?;
    let (vw, vh) = lf.view_size;
    if lf.grid == 0 || vw == 0 || vh == 0 {
        return Err(InputError::SizeMismatch(format!(
            "a {g}x{g} grid of {vw}x{vh} views is empty",
            g = lf.grid
        )));
    }
    let usable = |v: f32| v.is_finite() && v >= 0.0;
    if !usable(lf.spacing_m) || !usable(lf.pixel_pitch_tan) || lf.pixel_pitch_tan == 0.0 {
        return Err(invalid(format!(
            "view spacing {} m and pixel pitch {} must be finite and > 0",
            lf.spacing_m, lf.pixel_pitch_tan
        )));
    }
    let (w, h) = display.panel_size();
    let axis = |len: usize, lenslets: usize, view_len: usize| -> Vec<[f32; 4]> {
        (0..len)
            .map(|k| {
                let (s, t) = display.ray(k, lenslets);
                let [(i0, w0), (_, w1)] = view_pair(s, lf.grid, lf.spacing_m);
                [
                    i0 as f32,
                    w0,
                    w1,
                    t / lf.pixel_pitch_tan + view_len as f32 * 0.5,
                ]
            })
            .collect()
    };
    Ok(Sampling {
        cols: axis(w, display.lenslets[0], vw),
        rows: axis(h, display.lenslets[1], vh),
    })
}

/// The panel image (elemental images side by side) that shows `lf` on `display`.
pub fn elemental_images(
    lf: &ViewGrid<'_>,
    display: &LensletDisplay,
) -> Result<RgbImage, InputError> {
    let Sampling { cols, rows } = sampling(&lf.geometry()?, display)?;
    let (w, h) = (cols.len(), rows.len());
    let pair = |a: &[f32; 4]| [(a[0] as usize, a[1]), (a[0] as usize + 1, a[2])];
    let mut out = [0, 1, 2].map(|_| vec![0.0f32; w * h]);
    for (y, row) in rows.iter().enumerate() {
        let (vy, py) = (pair(row), row[3]);
        for (x, col) in cols.iter().enumerate() {
            let (vx, px) = (pair(col), col[3]);
            let mut acc = [0.0f32; 3];
            for &(j, wj) in &vy {
                for &(i, wi) in &vx {
                    let wt = wi * wj;
                    if wt == 0.0 {
                        continue;
                    }
                    let v = &lf.views[j * lf.grid + i];
                    for (c, a) in acc.iter_mut().enumerate() {
                        *a += wt * bilinear(&v.channels[c], px, py);
                    }
                }
            }
            for c in 0..3 {
                out[c][y * w + x] = acc[c];
            }
        }
    }
    let [r, g, b] = out;
    RgbImage::from_planes(
        Plane::from_vec(w, h, r)?,
        Plane::from_vec(w, h, g)?,
        Plane::from_vec(w, h, b)?,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Radiance of a textured plane `z0` metres away: linear in position, so bilinear
    /// resampling (across views and within a view) reproduces it exactly.
    fn radiance(x: f32, y: f32) -> [f32; 3] {
        [0.5 + 8.0 * x, 0.4 - 5.0 * y, 0.3 + 3.0 * x + 4.0 * y]
    }

    fn plane_light_field(
        grid: usize,
        spacing: f32,
        size: usize,
        pitch: f32,
        z0: f32,
    ) -> Vec<RgbImage> {
        let mut views = Vec::new();
        for j in 0..grid {
            for i in 0..grid {
                let s = [
                    (i as f32 - (grid - 1) as f32 * 0.5) * spacing,
                    (j as f32 - (grid - 1) as f32 * 0.5) * spacing,
                ];
                let mut px = Vec::with_capacity(size * size * 3);
                for y in 0..size {
                    for x in 0..size {
                        let t = [
                            (x as f32 + 0.5 - size as f32 * 0.5) * pitch,
                            (y as f32 + 0.5 - size as f32 * 0.5) * pitch,
                        ];
                        px.extend(radiance(s[0] + t[0] * z0, s[1] + t[1] * z0));
                    }
                }
                views.push(RgbImage::from_interleaved(size, size, &px).unwrap());
            }
        }
        views
    }

    #[test]
    fn panel_pixels_show_the_light_field_along_their_rays() {
        let (grid, spacing, size, pitch, z0) = (5, 0.001, 64, 0.01, 0.8);
        let views = plane_light_field(grid, spacing, size, pitch, z0);
        let lf = ViewGrid {
            grid,
            spacing_m: spacing,
            views: &views,
            pixel_pitch_tan: pitch,
        };
        let display = LensletDisplay {
            lenslets: [12, 10],
            pixels_per_lenslet: 7,
            lenslet_pitch_m: 0.0005,
            gap_m: 0.0033,
            eye_relief_m: 0.015,
        };
        let panel = elemental_images(&lf, &display).unwrap();
        assert_eq!((panel.width(), panel.height()), (84, 70));
        let mut worst = 0.0f32;
        for y in 0..70 {
            for x in 0..84 {
                let (sx, tx) = display.ray(x, 12);
                let (sy, ty) = display.ray(y, 10);
                // Every ray of this display stays inside the views' span and field.
                assert!(sx.abs() <= 0.002 && sy.abs() <= 0.002, "{sx} {sy}");
                assert!(tx.abs() < 30.0 * pitch && ty.abs() < 30.0 * pitch);
                let want = radiance(sx + tx * z0, sy + ty * z0);
                let got = panel.pixel(x, y).unwrap();
                for c in 0..3 {
                    worst = worst.max((got[c] - want[c]).abs());
                }
            }
        }
        assert!(worst < 1e-4, "worst error {worst}");
        // Neighbouring elemental images look through different lenslets: the same pixel of
        // each sees a different point of the plane.
        let a = panel.pixel(0, 35).unwrap()[0];
        let b = panel.pixel(7, 35).unwrap()[0];
        assert!((a - b).abs() > 1e-3, "{a} {b}");
    }

    #[test]
    fn bad_inputs_are_refused_with_what_is_wrong() {
        let views = plane_light_field(2, 0.001, 8, 0.004, 1.0);
        let display = LensletDisplay {
            lenslets: [4, 4],
            pixels_per_lenslet: 4,
            lenslet_pitch_m: 0.001,
            gap_m: 0.003,
            eye_relief_m: 0.015,
        };
        fn lf(views: &[RgbImage], grid: usize) -> ViewGrid<'_> {
            ViewGrid {
                grid,
                spacing_m: 0.001,
                views,
                pixel_pitch_tan: 0.004,
            }
        }
        assert!(elemental_images(&lf(&views, 2), &display).is_ok());
        let e = elemental_images(&lf(&views[..3], 2), &display).unwrap_err();
        assert!(e.to_string().contains("needs 4 views"), "{e}");
        let bad = LensletDisplay {
            gap_m: 0.0,
            ..display
        };
        assert!(elemental_images(&lf(&views, 2), &bad).is_err());
        let none = LensletDisplay {
            pixels_per_lenslet: 0,
            ..display
        };
        assert!(elemental_images(&lf(&views, 2), &none).is_err());
    }
}
