//! Ground-truth renders by CPU ray casting (rayon over rows).
//!
//! The thin-lens reference integrates the eye's pupil disk and each pixel's footprint with
//! quasi-random samples (Halton bases 2, 3 on the pupil, 5, 7 in the pixel), the same integral
//! an accumulation buffer of pinhole views over the pupil computes. Each pixel's sample set
//! is offset by its own hash (Cranley-Patterson rotation), so finite sampling leaves faint
//! noise instead of ghost copies of edges.

use super::Scene;
use dioptra_core::sampling::radical_inverse;
use dioptra_core::{DepthMap, Diopters, EyeModel, InputError, Plane, RgbImage};
use rayon::prelude::*;

/// Image geometry: the eye model (field and pupil) and the image size in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub eye: EyeModel,
    pub width: usize,
    pub height: usize,
}

impl Camera {
    /// A square image of `size` pixels with the given eye (its width is set to `size`).
    pub fn square(eye: EyeModel, size: usize) -> Camera {
        Camera::new(eye, size, size)
    }
    pub fn new(eye: EyeModel, width: usize, height: usize) -> Camera {
        Camera {
            eye: eye.with_width(width.min(u32::MAX as usize) as u32),
            width,
            height,
        }
    }
    fn check(&self) -> Result<f32, InputError> {
        self.eye.validated()?;
        if self.width == 0 || self.height == 0 || self.width.saturating_mul(self.height) > 1 << 28 {
            return Err(InputError::InvalidValue(format!(
                "image size {}x{} is invalid: expected 1 to 2^28 pixels",
                self.width, self.height
            )));
        }
        Ok(self.eye.pixel_pitch_tan())
    }
    /// Tangent-plane direction of image position `(x, y)` in pixels (pixel centres at +0.5).
    fn tangent(&self, pitch: f32, x: f32, y: f32) -> [f32; 2] {
        [
            (x - self.width as f32 * 0.5) * pitch,
            (y - self.height as f32 * 0.5) * pitch,
        ]
    }
}

/// One view of a light field: a pinhole camera displaced to `position` (metres, in the lens
/// plane), looking straight ahead, with its colour and z-depth.
#[derive(Debug, Clone, PartialEq)]
pub struct LightFieldView {
    pub position: [f32; 2],
    pub color: RgbImage,
    pub depth: DepthMap,
}

/// Shirley's concentric map of the unit square onto the unit disk (area preserving).
pub(crate) fn concentric_disk(u: f32, v: f32) -> [f32; 2] {
    let (a, b) = (2.0 * u - 1.0, 2.0 * v - 1.0);
    if a == 0.0 && b == 0.0 {
        return [0.0, 0.0];
    }
    let quarter = std::f32::consts::FRAC_PI_4;
    let (r, phi) = if a.abs() > b.abs() {
        (a, quarter * (b / a))
    } else {
        (b, 2.0 * quarter - quarter * (a / b))
    };
    [r * phi.cos(), r * phi.sin()]
}

fn pixel_hash(x: usize, y: usize, k: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x9e37_79b1)
        ^ (y as u32).wrapping_mul(0x85eb_ca77)
        ^ k.wrapping_mul(0xc2b2_ae3d);
    h ^= h >> 16;
    h = h.wrapping_mul(0x7feb_352d);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846c_a68b);
    h ^= h >> 16;
    (h >> 8) as f32 / (1u32 << 24) as f32
}

fn to_planes(width: usize, height: usize, rgb: Vec<[f32; 3]>) -> Result<RgbImage, InputError> {
    let mut ch = [
        Vec::with_capacity(rgb.len()),
        Vec::with_capacity(rgb.len()),
        Vec::with_capacity(rgb.len()),
    ];
    for px in rgb {
        for c in 0..3 {
            ch[c].push(px[c]);
        }
    }
    let [r, g, b] = ch;
    RgbImage::from_planes(
        Plane::from_vec(width, height, r)?,
        Plane::from_vec(width, height, g)?,
        Plane::from_vec(width, height, b)?,
    )
}

/// Antialiased pinhole render from lens-plane `position` (metres): colour averaged over
/// `supersample`² points per pixel (the thin lens's scrambled Halton pixel samples, whose
/// error at hard edges falls faster than a regular grid's); z-depth (diopters) of the
/// pixel-centre ray.
pub fn render_pinhole(
    scene: &Scene,
    cam: &Camera,
    position: [f32; 2],
    supersample: usize,
) -> Result<(RgbImage, DepthMap), InputError> {
    let pitch = cam.check()?;
    if !(1..=16).contains(&supersample) || !position.iter().all(|p| p.is_finite()) {
        return Err(InputError::InvalidValue(format!(
            "supersample {supersample} (expected 1..=16) or position {position:?} is invalid"
        )));
    }
    let o = [position[0], position[1], 0.0];
    let n = (supersample * supersample) as u32;
    let w = cam.width;
    let cull = Cull::new(scene, cam, pitch, position, 0.0, 0.0);
    // Red, green, blue and depth (diopters), a row per task.
    let mut planes: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0.0f32; w * cam.height]);
    {
        let [r, g, b, z] = &mut planes;
        r.par_chunks_mut(w)
            .zip(g.par_chunks_mut(w))
            .zip(b.par_chunks_mut(w))
            .zip(z.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, (((r, g), b), z))| {
                let mut cull = RowCull::new(&cull, y);
                for x in 0..w {
                    let objects = cull.at(x);
                    let trace = |t: [f32; 2]| {
                        scene.trace_among(o, [t[0], t[1], 1.0], objects.iter().copied())
                    };
                    let centre = cam.tangent(pitch, x as f32 + 0.5, y as f32 + 0.5);
                    let (acc, depth) = if n == 1 {
                        trace(centre)
                    } else {
                        let mut acc = [0.0f32; 3];
                        // Own scramble keys: independent of the thin-lens reference's samples.
                        let off = [pixel_hash(x, y, 1_000_001), pixel_hash(x, y, 1_000_002)];
                        for i in 0..n {
                            let jx = (radical_inverse(i + 1, 5) + off[0]).fract();
                            let jy = (radical_inverse(i + 1, 7) + off[1]).fract();
                            let t = cam.tangent(pitch, x as f32 + jx, y as f32 + jy);
                            let (c, _) = trace(t);
                            for k in 0..3 {
                                acc[k] += c[k];
                            }
                        }
                        let depth = scene.depth_among(
                            o,
                            [centre[0], centre[1], 1.0],
                            objects.iter().copied(),
                        );
                        (acc.map(|v| v / n as f32), depth)
                    };
                    (r[x], g[x], b[x], z[x]) = (acc[0], acc[1], acc[2], 1.0 / depth);
                }
            });
    }
    let (w, h) = (cam.width, cam.height);
    let [r, g, b, z] = planes;
    let color = RgbImage::from_planes(
        Plane::from_vec(w, h, r)?,
        Plane::from_vec(w, h, g)?,
        Plane::from_vec(w, h, b)?,
    )?;
    let depth = DepthMap::from_diopters(Plane::from_vec(w, h, z)?)?;
    Ok((color, depth))
}

/// Thin-lens ground truth: the eye focused at `focus` sees each pixel as the mean over the
/// pupil disk and the pixel footprint; `samples` rays per pixel.
pub fn render_thin_lens(
    scene: &Scene,
    cam: &Camera,
    focus: Diopters,
    samples: u32,
) -> Result<RgbImage, InputError> {
    render_thin_lens_scrambled(scene, cam, focus, samples, 0)
}

/// [`render_thin_lens`] with per-pixel sample offsets drawn from `scramble`: renders with
/// different scrambles are independent estimates (used to measure the reference's own error).
pub fn render_thin_lens_scrambled(
    scene: &Scene,
    cam: &Camera,
    focus: Diopters,
    samples: u32,
    scramble: u32,
) -> Result<RgbImage, InputError> {
    let pitch = cam.check()?;
    if samples == 0 || !(focus.0.is_finite() && focus.0 >= 0.0) {
        return Err(InputError::InvalidValue(format!(
            "samples {samples} (expected >= 1) or focus {focus} (expected finite, >= 0 D) is invalid"
        )));
    }
    let radius = 0.5 * cam.eye.pupil_diameter.to_meters().0;
    let q = focus.0;
    // The same quasi-random sequence for every pixel (each rotates it by its own offsets).
    let halton: Vec<[f32; 4]> = (1..=samples)
        .map(|i| [2, 3, 5, 7].map(|base| radical_inverse(i, base)))
        .collect();
    let halton = &halton;
    let cull = Cull::new(scene, cam, pitch, [0.0; 2], radius, q);
    let px: Vec<[f32; 3]> = (0..cam.height)
        .into_par_iter()
        .flat_map_iter(|y| {
            let mut cull = RowCull::new(&cull, y);
            (0..cam.width).map(move |x| {
                let off = [0, 1, 2, 3].map(|k| pixel_hash(x, y, k + 4 * scramble));
                let objects = cull.at(x);
                let mut acc = [0.0f32; 3];
                for h in halton {
                    let r = |k: usize| (h[k] + off[k]).fract();
                    let l = concentric_disk(r(0), r(1));
                    let (lx, ly) = (l[0] * radius, l[1] * radius);
                    let t = cam.tangent(pitch, x as f32 + r(2), y as f32 + r(3));
                    // The ray from lens point L through the point the pixel's chief ray meets
                    // on the focal plane z = 1/q: direction t - q L (z component 1).
                    let (c, _) = scene.trace_among(
                        [lx, ly, 0.0],
                        [t[0] - q * lx, t[1] - q * ly, 1.0],
                        objects.iter().copied(),
                    );
                    for k in 0..3 {
                        acc[k] += c[k];
                    }
                }
                acc.map(|v| v / samples as f32)
            })
        })
        .collect();
    to_planes(cam.width, cam.height, px)
}

/// What a render culls its pixels' objects by: the rays of a pixel leave a disk of
/// `lens_radius` around `origin` and meet on the focal plane at `focus_d` (a pinhole: radius
/// 0, any focus); for a pinhole, each object's tangent bounds too.
struct Cull<'a> {
    scene: &'a Scene,
    cam: &'a Camera,
    pitch: f32,
    origin: [f32; 2],
    lens_radius: f32,
    focus_d: f32,
    /// Per object, with a pinhole, the tangents (x and y lows, then highs) of every ray from
    /// it that can meet the object ([`tangent_bounds`]); `None`: not bounded.
    bounds: Vec<Option<[f32; 4]>>,
}

impl<'a> Cull<'a> {
    fn new(
        scene: &'a Scene,
        cam: &'a Camera,
        pitch: f32,
        origin: [f32; 2],
        lens_radius: f32,
        focus_d: f32,
    ) -> Cull<'a> {
        let bounds = scene
            .objects
            .iter()
            .map(|o| (lens_radius == 0.0).then(|| tangent_bounds(&o.shape, origin))?)
            .collect();
        Cull {
            scene,
            cam,
            pitch,
            origin,
            lens_radius,
            focus_d,
            bounds,
        }
    }

    /// The bundle of the rays through the pixels `x0..x1` x `y0..y1`.
    fn bundle(&self, [x0, x1]: [usize; 2], [y0, y1]: [usize; 2]) -> super::RayBundle {
        super::RayBundle {
            origin: self.origin,
            lens_radius: self.lens_radius,
            focus_d: self.focus_d,
            t_lo: self.cam.tangent(self.pitch, x0 as f32, y0 as f32),
            t_hi: self.cam.tangent(self.pitch, x1 as f32, y1 as f32),
        }
    }

    /// Whether some ray of bundle `b` may meet object `i`.
    fn may_meet(&self, i: usize, b: &super::RayBundle) -> bool {
        b.may_meet(&self.scene.objects[i].shape)
            && self.bounds[i].is_none_or(|r| {
                b.t_hi[0] >= r[0] && b.t_lo[0] <= r[2] && b.t_hi[1] >= r[1] && b.t_lo[1] <= r[3]
            })
    }

    /// The objects that some ray of pixel (x, y) can meet, in the scene's order.
    #[cfg(test)]
    fn pixel_objects(&self, x: usize, y: usize) -> Vec<&'a super::Object> {
        let b = self.bundle([x, x + 1], [y, y + 1]);
        (0..self.scene.objects.len())
            .filter(|&i| self.may_meet(i, &b))
            .map(|i| &self.scene.objects[i])
            .collect()
    }
}

/// The tangents (x and y lows, then highs) of every ray from a pinhole at `origin` (in the
/// z = 0 plane) that can meet `shape`: those of the corners of a box around it (the map from
/// a point to its tangents is linear-fractional, so it takes the convex box into the hull of
/// its corners' images), widened for rounding; `None` where a corner is not in front.
fn tangent_bounds(shape: &super::Shape, origin: [f32; 2]) -> Option<[f32; 4]> {
    let mut r = [
        f32::INFINITY,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NEG_INFINITY,
    ];
    for c in shape.corners() {
        if c[2].is_nan() || c[2] <= 1e-3 {
            return None;
        }
        for k in 0..2 {
            let t = (c[k] - origin[k]) / c[2];
            r[k] = r[k].min(t);
            r[k + 2] = r[k + 2].max(t);
        }
    }
    // A relative margin for rounding: culling a little less never changes an image.
    let m = [0, 1].map(|k| 1e-4 * (r[k].abs() + r[k + 2].abs()) + 1e-5);
    Some([r[0] - m[0], r[1] - m[1], r[2] + m[0], r[3] + m[1]])
}

/// Pixels of a row whose objects [`RowCull`] culls together first.
const CULL_SPAN: usize = 16;

/// Per pixel of one row, the objects some ray of the pixel can meet, in the scene's order
/// ([`Cull::pixel_objects`]): culled from those of the pixel's span of [`CULL_SPAN`] pixels,
/// which hold them (a wider bundle's tests pass whatever a narrower one's do), so a pixel
/// tests a few objects instead of all and nothing is allocated per pixel.
struct RowCull<'a, 'c> {
    cull: &'c Cull<'a>,
    y: usize,
    /// The span `span`'s objects (indices), and the last pixel's.
    span: usize,
    span_objects: Vec<usize>,
    objects: Vec<&'a super::Object>,
}

impl<'a, 'c> RowCull<'a, 'c> {
    fn new(cull: &'c Cull<'a>, y: usize) -> RowCull<'a, 'c> {
        RowCull {
            cull,
            y,
            span: usize::MAX,
            span_objects: Vec::new(),
            objects: Vec::new(),
        }
    }

    /// Pixel `x`'s objects.
    fn at(&mut self, x: usize) -> &[&'a super::Object] {
        let (cull, y) = (self.cull, self.y);
        if x / CULL_SPAN != self.span {
            self.span = x / CULL_SPAN;
            let x0 = self.span * CULL_SPAN;
            let b = cull.bundle([x0, (x0 + CULL_SPAN).min(cull.cam.width)], [y, y + 1]);
            self.span_objects.clear();
            self.span_objects
                .extend((0..cull.scene.objects.len()).filter(|&i| cull.may_meet(i, &b)));
        }
        let b = cull.bundle([x, x + 1], [y, y + 1]);
        self.objects.clear();
        self.objects.extend(
            self.span_objects
                .iter()
                .filter(|&&i| cull.may_meet(i, &b))
                .map(|&i| &cull.scene.objects[i]),
        );
        &self.objects
    }
}

/// Thin-lens ground truth at each focus in `foci`; `progress` is called after each slice.
pub fn render_thin_lens_stack(
    scene: &Scene,
    cam: &Camera,
    foci: &[Diopters],
    samples: u32,
    mut progress: impl FnMut(usize),
) -> Result<Vec<RgbImage>, InputError> {
    let mut out = Vec::with_capacity(foci.len());
    for (i, &q) in foci.iter().enumerate() {
        out.push(render_thin_lens(scene, cam, q, samples)?);
        progress(i + 1);
    }
    Ok(out)
}

/// A `grid` x `grid` light field of pinhole views spread evenly over a `span` metres square
/// centred on the eye (DeepFocus: 9 x 9 over 1 cm), row-major from the top-left view.
pub fn render_light_field(
    scene: &Scene,
    cam: &Camera,
    grid: usize,
    span: f32,
    supersample: usize,
) -> Result<Vec<LightFieldView>, InputError> {
    light_field_positions(grid, span)?
        .into_iter()
        .map(|position| render_light_field_view(scene, cam, position, supersample))
        .collect()
}

/// The view positions of [`render_light_field`], row-major from the top-left.
pub fn light_field_positions(grid: usize, span: f32) -> Result<Vec<[f32; 2]>, InputError> {
    if grid == 0 || grid > 64 || !(span.is_finite() && span >= 0.0) {
        return Err(InputError::InvalidValue(format!(
            "light field grid {grid} (expected 1..=64) or span {span} m is invalid"
        )));
    }
    let step = if grid > 1 {
        span / (grid - 1) as f32
    } else {
        0.0
    };
    let at = |k: usize| (k as f32 - (grid - 1) as f32 * 0.5) * step;
    Ok((0..grid)
        .flat_map(|j| (0..grid).map(move |i| [at(i), at(j)]))
        .collect())
}

/// One view of [`render_light_field`], at `position` (one of [`light_field_positions`]).
pub fn render_light_field_view(
    scene: &Scene,
    cam: &Camera,
    position: [f32; 2],
    supersample: usize,
) -> Result<LightFieldView, InputError> {
    let (color, depth) = render_pinhole(scene, cam, position, supersample)?;
    Ok(LightFieldView {
        position,
        color,
        depth,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Object, Pattern, Rot, Shape, Texture};

    fn two_planes() -> Scene {
        // A white square at 2 D over a black wall at 0.2 D.
        Scene {
            objects: vec![Object {
                shape: Shape::Box {
                    center: [0.0, 0.0, 0.5],
                    half: [0.02, 0.02, 1e-5],
                    rot: Rot::IDENTITY,
                },
                texture: Texture {
                    a: [1.0; 3],
                    b: [1.0; 3],
                    pattern: Pattern::Solid,
                },
                alpha: 1.0,
            }],
            wall_depth: 5.0,
            wall: Texture {
                a: [0.0; 3],
                b: [0.0; 3],
                pattern: Pattern::Solid,
            },
            seed: 0,
        }
    }

    #[test]
    fn disk_map_stays_in_disk() {
        for i in 0..100 {
            let p = concentric_disk(radical_inverse(i, 2), radical_inverse(i, 3));
            assert!(p[0] * p[0] + p[1] * p[1] <= 1.0 + 1e-5);
        }
    }

    /// A pixel's rays find the same colour and depth among the objects its bundle may meet
    /// as among all: random rays of random pixels (lens disk, pixel area, the edges of both
    /// included), scenes with semi-transparent surfaces, near and far foci, an 8 mm pupil.
    #[test]
    fn culling_objects_per_pixel_changes_no_ray() {
        let opts = crate::scene::SceneOptions {
            semi_transparent: true,
            ..Default::default()
        };
        let mut checked = 0usize;
        let mut culled = 0usize;
        for seed in [1_000_000u64, 1_000_001, 42] {
            let scene = Scene::generate_with(seed, &opts);
            // A pupil of 0: a pinhole, culled by its tangent bounds too.
            for (pupil_mm, q) in [(0.0, 0.0), (4.0f32, 0.1f32), (8.0, 2.5), (4.0, 6.0)] {
                let eye = EyeModel {
                    pupil_diameter: dioptra_core::Millimeters(pupil_mm.max(1.0)),
                    ..EyeModel::default()
                };
                let cam = Camera::square(eye, 64);
                let pitch = cam.check().unwrap();
                let radius = 0.5 * dioptra_core::Millimeters(pupil_mm).to_meters().0;
                let cull = Cull::new(&scene, &cam, pitch, [0.0; 2], radius, q);
                for p in 0..400u32 {
                    let (x, y) = ((p * 37 % 64) as usize, (p * 11 % 64) as usize);
                    let objects = cull.pixel_objects(x, y);
                    culled += scene.objects.len() - objects.len();
                    for i in 0..8u32 {
                        let u = |k: u32| pixel_hash(x, y, 100 + 8 * i + k);
                        // Lens points out to the rim, pixel points out to the edges.
                        let rim = if i == 0 { 1.0 } else { u(4).sqrt() };
                        let l = concentric_disk(u(0), u(1)).map(|v| v * rim);
                        let (lx, ly) = (l[0] * radius, l[1] * radius);
                        let edge = |v: f32| if i == 1 { v.round() } else { v };
                        let t = cam.tangent(pitch, x as f32 + edge(u(2)), y as f32 + edge(u(3)));
                        let (o, d) = ([lx, ly, 0.0], [t[0] - q * lx, t[1] - q * ly, 1.0]);
                        let all = scene.trace(o, d);
                        let some = scene.trace_among(o, d, objects.iter().copied());
                        assert_eq!(all, some, "seed {seed} pixel ({x}, {y}) ray {i}");
                        checked += 1;
                    }
                }
            }
        }
        // Culling happened (most objects are far from most pixels).
        assert!(culled > checked, "{culled} culled over {checked} rays");
    }

    /// FNV-1a over images' bits.
    fn checksum<'a>(planes: impl IntoIterator<Item = &'a Plane>) -> u64 {
        planes
            .into_iter()
            .flat_map(|p| p.data().iter())
            .flat_map(|v| v.to_bits().to_le_bytes())
            .fold(0xcbf2_9ce4_8422_2325, |h, b| {
                (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
            })
    }

    /// Pins the renders bit for bit: pinhole views (1 and 2 x 2 rays per pixel, off-centre,
    /// a width that ends a culling span early) and a thin-lens view of a semi-transparent
    /// scene. The values are the renders' before their culling by row spans (cpu54).
    #[test]
    fn the_renders_are_pinned() {
        let opts = crate::scene::SceneOptions {
            semi_transparent: true,
            ..Default::default()
        };
        let scene = Scene::generate_with(1_000_000, &opts);
        let cam = Camera::new(EyeModel::default(), 75, 44);
        let mut sums = Vec::new();
        for (position, ss) in [([0.0, 0.0], 1), ([0.0315, -0.002], 2)] {
            let (c, d) = render_pinhole(&scene, &cam, position, ss).unwrap();
            sums.push(checksum(c.channels.iter().chain([d.plane()])));
        }
        let t = render_thin_lens(&scene, &cam, Diopters(1.5), 16).unwrap();
        sums.push(checksum(&t.channels));
        assert_eq!(
            sums,
            [
                0xb31c_2cd1_075f_15e7,
                0x7bff_a8ad_9877_1f0b,
                0x22a7_ad67_ad64_e56f
            ],
            "the renders changed"
        );
    }

    /// A row's culling gives each pixel the objects its own bundle may meet, in the scene's
    /// order ([`Cull::pixel_objects`]): whole rows (a partial span at their end) of pinhole and
    /// thin-lens bundles, off-centre.
    #[test]
    fn culling_by_row_spans_gives_each_pixel_its_objects() {
        let scene = Scene::generate(1_000_000);
        let cam = Camera::new(EyeModel::default(), 100, 40);
        let pitch = cam.check().unwrap();
        let origin = [0.003, -0.001];
        for (radius, q) in [(0.0, 0.0), (0.002, 0.5), (0.004, 3.0)] {
            let mut total = 0;
            for y in [0, 7, 20, 39] {
                let cull = Cull::new(&scene, &cam, pitch, origin, radius, q);
                let mut row = RowCull::new(&cull, y);
                for x in 0..100 {
                    let want = cull.pixel_objects(x, y);
                    let got = row.at(x);
                    assert!(
                        got.len() == want.len()
                            && got.iter().zip(&want).all(|(a, b)| std::ptr::eq(*a, *b)),
                        "pixel ({x}, {y}), lens {radius} m at {q} D"
                    );
                    total += got.len();
                }
            }
            // Some objects, not all, per pixel.
            assert!(
                total > 0 && total < 400 * scene.objects.len(),
                "{total} objects over 400 pixels"
            );
        }
    }

    #[test]
    fn pinhole_depth_and_in_focus_thin_lens_match() {
        let mut s = two_planes();
        // the wall is dark grey so shading of the square does not matter
        s.wall.a = [0.2; 3];
        s.wall.b = [0.2; 3];
        let cam = Camera::square(EyeModel::default(), 32);
        let (c, d) = render_pinhole(&s, &cam, [0.0, 0.0], 2).unwrap();
        assert!((d.at(16, 16).unwrap().0 - 2.0).abs() < 1e-3);
        assert!((d.at(0, 0).unwrap().0 - 0.2).abs() < 1e-4);
        // focused on the square, its interior is as sharp as the pinhole render
        let t = render_thin_lens(&s, &cam, Diopters(2.0), 64).unwrap();
        let (a, b) = (c.pixel(16, 16).unwrap(), t.pixel(16, 16).unwrap());
        assert!((a[0] - b[0]).abs() < 1e-3, "{a:?} {b:?}");
    }

    #[test]
    fn defocus_blur_has_the_eye_models_diameter() {
        // Focused on the wall, the square's edge spreads over coc_px(2, 0.2) pixels.
        let s = two_planes();
        let cam = Camera::square(EyeModel::default(), 64);
        let coc = cam.eye.coc_px(Diopters(2.0), Diopters(0.2));
        let t = render_thin_lens(&s, &cam, Diopters(0.2), 256).unwrap();
        // Square spans +-0.04 tangent = +-0.04/pitch px around the centre.
        let half = 0.04 / cam.eye.pixel_pitch_tan();
        let row: Vec<f32> = (0..64).map(|x| t.pixel(x, 32).unwrap()[0]).collect();
        // Blurred edge width (10%..90% of the plateau) for a disk is about 0.8 * diameter.
        let plateau = row[32];
        let rising: Vec<usize> = (0..32)
            .filter(|&x| row[x] > 0.1 * plateau && row[x] < 0.9 * plateau)
            .collect();
        let width = rising.len() as f32;
        assert!(
            (width - 0.8 * coc).abs() < 2.0,
            "edge width {width} px for coc {coc} px"
        );
        let centre = 32.0 - half;
        let mid = rising.iter().map(|&x| x as f32 + 0.5).sum::<f32>() / width;
        assert!(
            (mid - centre).abs() < 1.0,
            "edge centred at {mid}, expected {centre}"
        );
    }

    #[test]
    fn rejects_bad_parameters() {
        let s = two_planes();
        let cam = Camera::square(EyeModel::default(), 8);
        assert!(render_thin_lens(&s, &cam, Diopters(f32::NAN), 4).is_err());
        assert!(render_thin_lens(&s, &cam, Diopters(1.0), 0).is_err());
        assert!(render_pinhole(&s, &Camera::square(EyeModel::default(), 0), [0.0; 2], 1).is_err());
        assert!(render_light_field(&s, &cam, 0, 0.01, 1).is_err());
        let lf = render_light_field(&s, &cam, 3, 0.01, 1).unwrap();
        assert_eq!(lf.len(), 9);
        assert_eq!(lf[0].position, [-0.005, -0.005]);
    }
}
