//! The eyepiece pre-warp: a mesh over the panel whose vertices say, per colour channel, where
//! the source image must be read so that the eye, looking through the eyepiece, sees the source
//! undistorted and without colour fringes.
//!
//! The model is `dioptra_core::distortion`'s (OpenCV's camera model per channel: eye direction
//! to panel pixel). The source image is the renderer's ideal image, in which a direction
//! `(x, y)` is at the render intrinsics' `(fx x + cx, fy y + cy)` (panel pixels, scaled to the
//! source's size when it is rendered at another). A panel pixel `u` shows, in channel `c`, the
//! source at `render(unproject_c(u))`. The inverse is solved once per vertex when the mesh is
//! built ([`WarpMesh::new`]); between vertices the source position is interpolated linearly
//! over the two triangles of each grid cell, as a GPU rasterises them.
//!
//! Drawn by [`warp_cpu`] (the CPU twin, for the headless sink) and [`gpu::WarpPipeline`]
//! (`shaders/warp.wgsl`, a render pipeline built once that draws a frame from GPU memory into
//! any colour target: a window's surface, or a texture read back). Both scale the source
//! positions about the optical centre by a factor given per draw (the magnification
//! compensation, see `OpticsMap::size_compensation`: the draw's `scale` is its inverse) and can
//! encode the result through the panel's transfer table.

pub mod gpu;

use crate::error::{invalid, RenderError};
use crate::transfer::EncodeLut;
use dioptra_core::distortion::{ChannelModel, Coefficients, EyepieceModel, Intrinsics};
use dioptra_core::{Plane, RgbImage};
use rayon::prelude::*;

/// A vertex of the mesh (warp.wgsl's `VertexIn`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct WarpVertex {
    /// Panel pixel (OpenCV's convention: pixel (i, j)'s centre at (i, j)).
    pub position: [f32; 2],
    /// Where red, green and blue are read in the source image, source pixels.
    pub source: [[f32; 2]; 3],
    /// 1 where every channel's model reaches this pixel; 0 where one has no inverse (beyond
    /// the eyepiece's fold): triangles touching it are drawn black.
    pub valid: f32,
}

/// Default spacing of the mesh's vertices, panel pixels: at 1080p with a strong eyepiece
/// (k1 = -0.18, k2 = 0.03 over a 93 degree field) the interpolation is within 0.013 px of
/// the exact warp (0.029 at 6 px, 0.052 at 8, 0.21 at 16; a test checks). 130 000 vertices
/// at 1080p, 4.7 MB.
pub const DEFAULT_STEP_PX: usize = 4;

/// Most vertices a mesh may have (a 4K panel at the default step has 2.1 million).
pub const MAX_VERTICES: usize = 4 << 20;

/// The pre-warp mesh of one eye: built once from the eyepiece's model.
#[derive(Debug, Clone, PartialEq)]
pub struct WarpMesh {
    panel: [usize; 2],
    source: [usize; 2],
    /// The vertices' panel coordinates along x and along y.
    xs: Vec<f32>,
    ys: Vec<f32>,
    /// Row-major: `ys.len()` rows of `xs.len()`.
    vertices: Vec<WarpVertex>,
    indices: Vec<u32>,
    /// The optical centre in source pixels: the draw's scale is about it.
    centre: [f32; 2],
    unreachable: usize,
}

/// Vertex coordinates along one panel axis of `n` pixels: every `step` from -0.5, and the
/// panel's far edge.
fn grid(n: usize, step: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..)
        .map(|k| -0.5 + (k * step) as f32)
        .take_while(|&x| x < n as f32 - 0.5)
        .collect();
    v.push(n as f32 - 0.5);
    v
}

fn check_size(what: &str, s: [usize; 2]) -> Result<(), RenderError> {
    if s[0] == 0 || s[1] == 0 || s[0] > 16384 || s[1] > 16384 {
        return Err(invalid(format!(
            "{what} of {}x{} pixels: expected 1 to 16384 each way",
            s[0], s[1]
        )));
    }
    Ok(())
}

impl WarpMesh {
    /// The mesh for `model` on a `panel` (width, height) with the source rendered at `source`
    /// (width, height), vertices every `step_px` panel pixels.
    pub fn new(
        model: &EyepieceModel,
        panel: [usize; 2],
        source: [usize; 2],
        step_px: usize,
    ) -> Result<WarpMesh, RenderError> {
        check_size("a panel", panel)?;
        check_size("a source image", source)?;
        if step_px == 0 || step_px > 4096 {
            return Err(invalid(format!(
                "a mesh step of {step_px} px: expected 1 to 4096"
            )));
        }
        let (xs, ys) = (grid(panel[0], step_px), grid(panel[1], step_px));
        if xs.len() * ys.len() > MAX_VERTICES {
            return Err(invalid(format!(
                "a mesh every {step_px} px over a {}x{} panel has {} vertices, more than \
                 {MAX_VERTICES}: use a larger step",
                panel[0],
                panel[1],
                xs.len() * ys.len()
            )));
        }
        let to_source = source_scale(panel, source);
        let rows: Vec<(Vec<WarpVertex>, usize)> = ys
            .par_iter()
            .map(|&y| {
                let mut unreachable = 0;
                let row = xs
                    .iter()
                    .map(|&x| {
                        let mut v = WarpVertex {
                            position: [x, y],
                            source: [[0.0; 2]; 3],
                            valid: 1.0,
                        };
                        for (c, ch) in model.channels.iter().enumerate() {
                            match ch.unproject(f64::from(x), f64::from(y)) {
                                Some((dx, dy)) => {
                                    let (rx, ry) = model.render.to_pixel(dx, dy);
                                    v.source[c] = to_source(rx, ry);
                                }
                                None => v.valid = 0.0,
                            }
                        }
                        if v.valid == 0.0 {
                            // Triangles touching it are black (by `valid`); a modest position
                            // keeps it from swamping, through rounding, the pixels on the edge
                            // its neighbours share (a huge one moved them by 0.1 px).
                            v.source = [to_source(f64::from(x), f64::from(y)); 3];
                            unreachable += 1;
                        }
                        v
                    })
                    .collect();
                (row, unreachable)
            })
            .collect();
        let unreachable = rows.iter().map(|r| r.1).sum();
        let vertices: Vec<WarpVertex> = rows.into_iter().flat_map(|r| r.0).collect();
        let centre = to_source(model.render.cx, model.render.cy);
        Ok(Self::assemble(
            panel,
            source,
            xs,
            ys,
            vertices,
            centre,
            unreachable,
        ))
    }

    /// No eyepiece distortion: the source scaled onto the panel (one cell: the map is
    /// linear), with the optical centre at panel pixel `centre` (the panel's middle is
    /// `((w - 1) / 2, (h - 1) / 2)`). For the magnification compensation alone.
    pub fn identity(
        panel: [usize; 2],
        source: [usize; 2],
        centre: [f64; 2],
    ) -> Result<WarpMesh, RenderError> {
        check_size("a panel", panel)?;
        check_size("a source image", source)?;
        if !(centre[0].is_finite() && centre[1].is_finite()) {
            return Err(invalid("the optical centre is not a pair of numbers"));
        }
        let (xs, ys) = (
            vec![-0.5, panel[0] as f32 - 0.5],
            vec![-0.5, panel[1] as f32 - 0.5],
        );
        let to_source = source_scale(panel, source);
        let mut vertices = Vec::with_capacity(4);
        for &y in &ys {
            for &x in &xs {
                let s = to_source(f64::from(x), f64::from(y));
                vertices.push(WarpVertex {
                    position: [x, y],
                    source: [s; 3],
                    valid: 1.0,
                });
            }
        }
        let centre = to_source(centre[0], centre[1]);
        Ok(Self::assemble(panel, source, xs, ys, vertices, centre, 0))
    }

    fn assemble(
        panel: [usize; 2],
        source: [usize; 2],
        xs: Vec<f32>,
        ys: Vec<f32>,
        vertices: Vec<WarpVertex>,
        centre: [f32; 2],
        unreachable: usize,
    ) -> WarpMesh {
        let cols = xs.len() as u32;
        let mut indices = Vec::with_capacity(6 * (xs.len() - 1) * (ys.len() - 1));
        for j in 0..ys.len() as u32 - 1 {
            for i in 0..cols - 1 {
                let a = j * cols + i;
                let (b, c, d) = (a + 1, a + cols, a + cols + 1);
                // The diagonal a-d, as the CPU twin splits a cell.
                indices.extend_from_slice(&[a, b, d, a, d, c]);
            }
        }
        WarpMesh {
            panel,
            source,
            xs,
            ys,
            vertices,
            indices,
            centre,
            unreachable,
        }
    }

    /// The panel's size (width, height), pixels.
    pub fn panel(&self) -> [usize; 2] {
        self.panel
    }
    /// The source image's size it reads (width, height).
    pub fn source(&self) -> [usize; 2] {
        self.source
    }
    pub fn vertices(&self) -> &[WarpVertex] {
        &self.vertices
    }
    /// Triangles, three vertex indices each.
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }
    /// The optical centre in source pixels.
    pub fn centre(&self) -> [f32; 2] {
        self.centre
    }
    /// Vertices some channel's model cannot reach (drawn black around).
    pub fn unreachable(&self) -> usize {
        self.unreachable
    }

    /// Where channel `c` of panel pixel (x, y) is read in the source, interpolated as drawn,
    /// and whether its triangle is drawn (`None`: black).
    pub fn source_at(&self, x: f32, y: f32, c: usize) -> Option<[f32; 2]> {
        self.sources_in(cell(&self.xs, x), cell(&self.ys, y))
            .map(|s| s[c.min(2)])
    }

    /// Every channel's source position at the point `fx`, `fy` of cell (`i`, `j`) (as
    /// [`cell`] gives them), `None` where the triangle is black.
    fn sources_in(&self, (i, fx): (usize, f32), (j, fy): (usize, f32)) -> Option<[[f32; 2]; 3]> {
        let cols = self.xs.len();
        let at = |di: usize, dj: usize| &self.vertices[(j + dj) * cols + i + di];
        let (a, b, cc, d) = (at(0, 0), at(1, 0), at(0, 1), at(1, 1));
        let lerp = |va: f32, vb: f32, vc: f32, vd: f32| {
            if fx >= fy {
                va + fx * (vb - va) + fy * (vd - vb)
            } else {
                va + fy * (vc - va) + fx * (vd - vc)
            }
        };
        if lerp(a.valid, b.valid, cc.valid, d.valid) <= 0.999 {
            return None;
        }
        Some(std::array::from_fn(|c| {
            [
                lerp(
                    a.source[c][0],
                    b.source[c][0],
                    cc.source[c][0],
                    d.source[c][0],
                ),
                lerp(
                    a.source[c][1],
                    b.source[c][1],
                    cc.source[c][1],
                    d.source[c][1],
                ),
            ]
        }))
    }

    /// The largest distance, source pixels, between the mesh's interpolated source position
    /// and the model's exact one, over every cell's centre and edge midpoints and every
    /// channel (points the model cannot reach are skipped).
    pub fn interpolation_error(&self, model: &EyepieceModel) -> f64 {
        let to_source = source_scale(self.panel, self.source);
        let mut worst = 0.0f64;
        for j in 0..self.ys.len() - 1 {
            for i in 0..self.xs.len() - 1 {
                let (x0, x1) = (self.xs[i], self.xs[i + 1]);
                let (y0, y1) = (self.ys[j], self.ys[j + 1]);
                for (fx, fy) in [(0.5, 0.5), (0.5, 0.0), (0.0, 0.5), (0.25, 0.75)] {
                    let (x, y) = (x0 + fx * (x1 - x0), y0 + fy * (y1 - y0));
                    for (c, ch) in model.channels.iter().enumerate() {
                        let (Some(m), Some((dx, dy))) = (
                            self.source_at(x, y, c),
                            ch.unproject(f64::from(x), f64::from(y)),
                        ) else {
                            continue;
                        };
                        let (rx, ry) = model.render.to_pixel(dx, dy);
                        let e = to_source(rx, ry);
                        worst = worst.max(
                            f64::from(m[0] - e[0])
                                .abs()
                                .max(f64::from(m[1] - e[1]).abs()),
                        );
                    }
                }
            }
        }
        worst
    }
}

/// Panel pixel (render intrinsics' units) to source pixel, both with pixel centres at
/// integers.
fn source_scale(panel: [usize; 2], source: [usize; 2]) -> impl Fn(f64, f64) -> [f32; 2] {
    let sx = source[0] as f64 / panel[0] as f64;
    let sy = source[1] as f64 / panel[1] as f64;
    move |x, y| [((x + 0.5) * sx - 0.5) as f32, ((y + 0.5) * sy - 0.5) as f32]
}

/// The cell of `grid` holding `v` (clamped to the grid) and where in it, 0 to 1.
fn cell(grid: &[f32], v: f32) -> (usize, f32) {
    let n = grid.len();
    let i = grid.partition_point(|&g| g <= v).clamp(1, n - 1) - 1;
    let f = (v - grid[i]) / (grid[i + 1] - grid[i]);
    (i, f.clamp(0.0, 1.0))
}

/// How one draw reads the source and what it writes.
#[derive(Debug, Clone, Copy)]
pub struct WarpDraw<'a> {
    /// Source positions are scaled by this about the optical centre: 1 / the magnification
    /// compensation (`OpticsMap::size_compensation`), so that an image that must appear
    /// smaller on the panel is read from farther out.
    pub scale: f32,
    /// Encode through the panel's transfer table; `None`: linear light out.
    pub encode: Option<&'a EncodeLut>,
}

impl Default for WarpDraw<'_> {
    fn default() -> Self {
        WarpDraw {
            scale: 1.0,
            encode: None,
        }
    }
}

/// The source's value in channel `c` at `p`: bilinear, 0 outside (as warp.wgsl's `bilinear`).
fn bilinear(img: &Plane, p: [f32; 2]) -> f32 {
    if !(p[0].abs() < 1e7 && p[1].abs() < 1e7) {
        return 0.0;
    }
    let (w, h) = (img.width() as i64, img.height() as i64);
    let (x0, y0) = (p[0].floor(), p[1].floor());
    let (fx, fy) = (p[0] - x0, p[1] - y0);
    let (ix, iy) = (x0 as i64, y0 as i64);
    let data = img.data();
    let texel = |x: i64, y: i64| {
        if x < 0 || y < 0 || x >= w || y >= h {
            0.0
        } else {
            data[(y * w + x) as usize]
        }
    };
    let top = texel(ix, iy) * (1.0 - fx) + texel(ix + 1, iy) * fx;
    let bottom = texel(ix, iy + 1) * (1.0 - fx) + texel(ix + 1, iy + 1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// The pre-warp on the CPU: `source` (linear light, the mesh's source size) drawn onto the
/// panel through `mesh`. The GPU's twin is [`gpu::WarpPipeline`].
pub fn warp_cpu(
    source: &RgbImage,
    mesh: &WarpMesh,
    draw: &WarpDraw,
) -> Result<RgbImage, RenderError> {
    if [source.width(), source.height()] != mesh.source {
        return Err(crate::error::mismatch(format!(
            "the warp's mesh reads a {}x{} source, given {}x{}",
            mesh.source[0],
            mesh.source[1],
            source.width(),
            source.height()
        )));
    }
    if !(draw.scale.is_finite() && draw.scale > 0.0) {
        return Err(invalid(format!(
            "a warp scale of {}: expected a number above 0",
            draw.scale
        )));
    }
    let [pw, ph] = mesh.panel;
    let c = mesh.centre;
    let scaled = |p: [f32; 2]| {
        [
            c[0] + (p[0] - c[0]) * draw.scale,
            c[1] + (p[1] - c[1]) * draw.scale,
        ]
    };
    let mut out = vec![0.0f32; 3 * pw * ph];
    let (r, rest) = out.split_at_mut(pw * ph);
    let (g, b) = rest.split_at_mut(pw * ph);
    // Each column's cell, once.
    let columns: Vec<(usize, f32)> = (0..pw).map(|x| cell(&mesh.xs, x as f32)).collect();
    r.par_chunks_mut(pw)
        .zip(g.par_chunks_mut(pw))
        .zip(b.par_chunks_mut(pw))
        .enumerate()
        .for_each(|(y, ((r, g), b))| {
            let row = cell(&mesh.ys, y as f32);
            for (x, &column) in columns.iter().enumerate() {
                let mut rgb = [0.0f32; 3];
                if let Some(p) = mesh.sources_in(column, row) {
                    for (ch, v) in rgb.iter_mut().enumerate() {
                        // The vertices' positions are scaled before interpolation on the
                        // GPU; the map is affine, so scaling after is the same.
                        *v = bilinear(&source.channels[ch], scaled(p[ch]));
                    }
                }
                if let Some(lut) = draw.encode {
                    rgb = rgb.map(|v| lut.encode(v));
                }
                r[x] = rgb[0];
                g[x] = rgb[1];
                b[x] = rgb[2];
            }
        });
    let plane = |v: &[f32]| Plane::from_vec(pw, ph, v.to_vec()).expect("panel size");
    let (r, rest) = out.split_at(pw * ph);
    let (g, b) = rest.split_at(pw * ph);
    Ok(RgbImage::from_planes(plane(r), plane(g), plane(b))?)
}

/// A strong eyepiece on a 1920 x 1080 panel, 93 degrees across, for tests, benches and
/// examples: a magnifier's pincushion (eye direction to panel pixel: k1 < 0, so the pre-warp
/// is barrel), the red channel 1 % larger and blue 1 % smaller (lateral colour).
pub fn example_eyepiece() -> EyepieceModel {
    let cam = Intrinsics {
        fx: 900.0,
        fy: 900.0,
        cx: 959.5,
        cy: 539.5,
    };
    let k = Coefficients {
        k1: -0.18,
        k2: 0.03,
        p1: 0.0005,
        p2: -0.0004,
        ..Default::default()
    };
    let ch = |s: f64| ChannelModel {
        camera: Intrinsics {
            fx: cam.fx * s,
            fy: cam.fy * s,
            ..cam
        },
        coefficients: k,
    };
    EyepieceModel {
        render: cam,
        channels: [ch(1.01), ch(1.0), ch(0.99)],
    }
    .checked("optics.distortion")
    .expect("the example eyepiece is valid")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_step_follows_the_model_within_a_fiftieth_of_a_pixel_at_1080p() {
        let m = example_eyepiece();
        let mesh = WarpMesh::new(&m, [1920, 1080], [1920, 1080], DEFAULT_STEP_PX).unwrap();
        assert_eq!(mesh.unreachable(), 0);
        let e = mesh.interpolation_error(&m);
        assert!(e < 0.02, "{e} px");
        // A coarser mesh is measurably worse (8 px: 0.052, 16 px: 0.21): the check can fail.
        let coarse = WarpMesh::new(&m, [1920, 1080], [1920, 1080], 16).unwrap();
        assert!(coarse.interpolation_error(&m) > 0.1);
    }

    #[test]
    fn a_vertex_lands_where_the_model_says() {
        let m = example_eyepiece();
        // A source rendered at half the panel's size.
        let mesh = WarpMesh::new(&m, [1920, 1080], [960, 540], 16).unwrap();
        let v = mesh.vertices()[3 * 121 + 5];
        let (x, y) = (f64::from(v.position[0]), f64::from(v.position[1]));
        assert_eq!((x, y), (79.5, 47.5));
        for c in 0..3 {
            let (dx, dy) = m.channels[c].unproject(x, y).unwrap();
            // Project back through the channel's own model: the vertex's panel pixel.
            let (u, vv) = m.channels[c].project(dx, dy);
            assert!((u - x).abs() < 1e-6 && (vv - y).abs() < 1e-6);
            let (rx, ry) = m.render.to_pixel(dx, dy);
            let want = [
                ((rx + 0.5) / 2.0 - 0.5) as f32,
                ((ry + 0.5) / 2.0 - 0.5) as f32,
            ];
            assert!(
                (v.source[c][0] - want[0]).abs() < 1e-3,
                "{:?} {want:?}",
                v.source[c]
            );
            assert!((v.source[c][1] - want[1]).abs() < 1e-3);
        }
    }

    #[test]
    fn the_identity_mesh_copies_the_image_and_scales_about_the_centre() {
        let (w, h) = (40, 30);
        let data: Vec<f32> = (0..3 * w * h).map(|i| (i % 97) as f32 / 97.0).collect();
        let img = RgbImage::from_interleaved(w, h, &data).unwrap();
        let mesh = WarpMesh::identity([w, h], [w, h], [19.5, 14.5]).unwrap();
        let out = warp_cpu(&img, &mesh, &WarpDraw::default()).unwrap();
        for c in 0..3 {
            for (a, b) in out.channels[c].data().iter().zip(img.channels[c].data()) {
                assert!((a - b).abs() < 1e-5);
            }
        }
        // Scale 2 about the centre: panel pixel (19.5 + d) reads the source at 19.5 + 2 d.
        let one = {
            let mut d = vec![0.0f32; 3 * w * h];
            // Bright pixels at (29, 13) and (29, 14): 9.5 right of the centre's column, on
            // either side of its row.
            for c in 0..3 {
                d[3 * (13 * w + 29) + c] = 1.0;
                d[3 * (14 * w + 29) + c] = 1.0;
            }
            RgbImage::from_interleaved(w, h, &d).unwrap()
        };
        let out = warp_cpu(
            &one,
            &mesh,
            &WarpDraw {
                scale: 2.0,
                encode: None,
            },
        )
        .unwrap();
        // Pixel (24, 14) reads (19.5 + 2 * 4.5, 14.5 - 2 * 0.5) = (28.5, 13.5): half of
        // column 29's light.
        assert!((out.channels[1].get(24, 14).unwrap() - 0.5).abs() < 1e-5);
    }

    #[test]
    fn bad_sizes_and_scales_are_refused() {
        let m = example_eyepiece();
        assert!(WarpMesh::new(&m, [0, 10], [10, 10], 8).is_err());
        assert!(WarpMesh::new(&m, [10, 10], [10, 10], 0).is_err());
        let e = WarpMesh::new(&m, [16384, 16384], [10, 10], 1).unwrap_err();
        assert!(e.to_string().contains("larger step"), "{e}");
        let mesh = WarpMesh::identity([10, 10], [10, 10], [4.5, 4.5]).unwrap();
        let img = RgbImage::new(8, 8, [0.0; 3]);
        assert!(warp_cpu(&img, &mesh, &WarpDraw::default()).is_err());
        let img = RgbImage::new(10, 10, [0.0; 3]);
        for s in [0.0, -1.0, f32::NAN] {
            assert!(warp_cpu(
                &img,
                &mesh,
                &WarpDraw {
                    scale: s,
                    encode: None
                }
            )
            .is_err());
        }
    }
}
