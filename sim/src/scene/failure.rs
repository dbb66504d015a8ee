//! Scenes built to break rendering methods: the failure-case suite of `dioptra eval`.
//!
//! Each [`FailureCase`] is a deterministic procedural scene with the eye (pupil) and focus it
//! is seen at, a defect applied to its RGB-D input (depth noise, holes) when it has one, a
//! short animation (one object sliding sideways) for temporal stability, and a mask of its
//! failure region: where the method is expected to go wrong. Ground truth is the thin-lens
//! render of [`super::render_thin_lens`]; masks come from the scene's own geometry, never from
//! a method's output.

use super::render::{render_pinhole, Camera};
use super::{Object, Pattern, Rot, Scene, Shape, Split, Texture};
use dioptra_core::{DepthMap, Diopters, EyeModel, InputError, Millimeters, Plane, RgbImage};

/// What is wrong with the RGB-D input a method gets (the ground truth never has it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InputDefect {
    None,
    /// Gaussian noise on every depth value, diopters (1 sd).
    DepthNoise {
        sd_diopters: f32,
        seed: u64,
    },
    /// Round holes reported as 0 D (no return: "infinitely far"), covering about `fraction`.
    DepthHoles {
        fraction: f32,
        seed: u64,
    },
}

/// One scene built to break a method.
#[derive(Debug, Clone)]
pub struct FailureCase {
    /// Short identifier (`yu-focus-near-point-far`, `thin-occluders`...).
    pub name: &'static str,
    /// What the case tests, one sentence.
    pub description: &'static str,
    pub scene: Scene,
    /// Image geometry and eye (a wide-pupil case has its own pupil).
    pub camera: Camera,
    pub focus: Diopters,
    /// The failure region: 1 inside, 0 outside.
    pub mask: Plane,
    pub defect: InputDefect,
    /// Score synthesised novel views (the large-disocclusion case).
    pub view_synthesis: bool,
    /// The object that moves in the animated sequence, and its step per frame in pixels.
    pub mover: Option<usize>,
    pub step_px: f32,
}

/// A deterministic generator for defects (SplitMix64).
struct Mix(u64);
impl Mix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Standard normal (Box-Muller).
    fn normal(&mut self) -> f32 {
        let u = self.unit().max(1e-7);
        let v = self.unit();
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}

fn centre_of(s: &Shape) -> [f32; 3] {
    match *s {
        Shape::Box { center, .. } | Shape::Sphere { center, .. } => center,
    }
}

fn shift(s: &mut Shape, dx: f32) {
    match s {
        Shape::Box { center, .. } | Shape::Sphere { center, .. } => center[0] += dx,
    }
}

impl FailureCase {
    /// The scene at frame `k` of the animated sequence (frame 0 is [`FailureCase::scene`]).
    pub fn frame(&self, k: usize) -> Scene {
        let mut s = self.scene.clone();
        if let Some(obj) = self.mover.and_then(|i| s.objects.get_mut(i)) {
            let z = centre_of(&obj.shape)[2];
            shift(
                &mut obj.shape,
                k as f32 * self.step_px * self.camera.eye.pixel_pitch_tan() * z,
            );
        }
        s
    }

    /// The RGB-D input a method gets for `scene` (a frame of this case): a supersampled
    /// pinhole render with the case's defect applied to its depth.
    pub fn input(&self, scene: &Scene) -> Result<(RgbImage, DepthMap), InputError> {
        let (color, depth) = render_pinhole(scene, &self.camera, [0.0, 0.0], 4)?;
        let (w, h) = (depth.width(), depth.height());
        let depth = match self.defect {
            InputDefect::None => depth,
            InputDefect::DepthNoise { sd_diopters, seed } => {
                let mut rng = Mix(seed);
                let d: Vec<f32> = depth
                    .data()
                    .iter()
                    .map(|&v| (v + sd_diopters * rng.normal()).max(0.0))
                    .collect();
                DepthMap::from_diopters(Plane::from_vec(w, h, d)?)?
            }
            InputDefect::DepthHoles { .. } => {
                let holes = self.holes(w, h);
                let d: Vec<f32> = depth
                    .data()
                    .iter()
                    .zip(holes.data())
                    .map(|(&v, &m)| if m > 0.5 { 0.0 } else { v })
                    .collect();
                DepthMap::from_diopters(Plane::from_vec(w, h, d)?)?
            }
        };
        Ok((color, depth))
    }

    /// Where the depth holes are (1 = hole), for a depth-holes case; empty mask otherwise.
    pub fn holes(&self, w: usize, h: usize) -> Plane {
        let mut m = Plane::new(w, h, 0.0);
        if let InputDefect::DepthHoles { fraction, seed } = self.defect {
            let mut rng = Mix(seed);
            let r = (w.min(h) as f32 * 0.04).max(1.5);
            let disk = std::f32::consts::PI * r * r;
            let n = ((fraction * (w * h) as f32) / disk).ceil().max(1.0) as usize;
            for _ in 0..n {
                let c = [rng.unit() * w as f32, rng.unit() * h as f32];
                paint_disk(&mut m, c, r);
            }
        }
        m
    }
}

fn paint_disk(m: &mut Plane, c: [f32; 2], r: f32) {
    let (w, h) = (m.width(), m.height());
    let (x0, x1) = (
        (c[0] - r).floor().max(0.0) as usize,
        (c[0] + r).ceil() as usize,
    );
    let (y0, y1) = (
        (c[1] - r).floor().max(0.0) as usize,
        (c[1] + r).ceil() as usize,
    );
    for y in y0..y1.min(h) {
        for x in x0..x1.min(w) {
            let (dx, dy) = (x as f32 + 0.5 - c[0], y as f32 + 0.5 - c[1]);
            if dx * dx + dy * dy <= r * r {
                m.data_mut()[y * w + x] = 1.0;
            }
        }
    }
}

/// Dilates `m` (values > 0.5) by a disk of radius `r` pixels.
fn dilate(m: &Plane, r: f32) -> Plane {
    let (w, h) = (m.width(), m.height());
    let mut out = Plane::new(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            if m.data()[y * w + x] > 0.5 {
                paint_disk(&mut out, [x as f32 + 0.5, y as f32 + 0.5], r.max(0.5));
            }
        }
    }
    out
}

/// Which side of a depth edge a band covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// The nearer surface's pixels.
    Near,
    /// The farther surface's pixels.
    Far,
    Both,
}

/// Pixels within `radius` of a depth edge (neighbours differing by more than `step` D), on
/// `side` of it.
pub fn edge_band(depth: &DepthMap, step: f32, radius: f32, side: Side) -> Plane {
    let (w, h) = (depth.width(), depth.height());
    let d = depth.data();
    // Edge pixels on each side: a pixel nearer (larger D) than a 4-neighbour is on the near side.
    let mut near = Plane::new(w, h, 0.0);
    let mut far = Plane::new(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let v = d[y * w + x];
            let mut ns = [None; 4];
            if x > 0 {
                ns[0] = Some(d[y * w + x - 1]);
            }
            if x + 1 < w {
                ns[1] = Some(d[y * w + x + 1]);
            }
            if y > 0 {
                ns[2] = Some(d[(y - 1) * w + x]);
            }
            if y + 1 < h {
                ns[3] = Some(d[(y + 1) * w + x]);
            }
            for n in ns.into_iter().flatten() {
                if v - n > step {
                    near.data_mut()[y * w + x] = 1.0;
                }
                if n - v > step {
                    far.data_mut()[y * w + x] = 1.0;
                }
            }
        }
    }
    // Grow each side's band into its own surface only: a band pixel must lie on the same side
    // of the local depth as the edge pixel that seeded it.
    let band = |seed: &Plane, want_near: bool| {
        let grown = dilate(seed, radius);
        let mut out = Plane::new(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if grown.data()[i] <= 0.5 {
                    continue;
                }
                // Compare with the depth range inside the neighbourhood: on the near side a pixel
                // is nearer than the midpoint of the local extremes.
                let r = radius.ceil() as isize + 1;
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (xx, yy) = (x as isize + dx, y as isize + dy);
                        if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                            let v = d[yy as usize * w + xx as usize];
                            lo = lo.min(v);
                            hi = hi.max(v);
                        }
                    }
                }
                let mid = 0.5 * (lo + hi);
                if (d[i] > mid) == want_near {
                    out.data_mut()[i] = 1.0;
                }
            }
        }
        out
    };
    match side {
        Side::Near => band(&near, true),
        Side::Far => band(&far, false),
        Side::Both => {
            let (a, b) = (band(&near, true), band(&far, false));
            let data = a
                .data()
                .iter()
                .zip(b.data())
                .map(|(x, y)| x.max(*y))
                .collect();
            Plane::from_vec(w, h, data).unwrap_or(a)
        }
    }
}

fn noise_texture(a: [f32; 3], b: [f32; 3], scale: f32, seed: u32) -> Texture {
    Texture {
        a,
        b,
        pattern: Pattern::Noise { scale, seed },
    }
}

const NEAR_D: f32 = 3.0;
const FAR_D: f32 = 0.25;

/// A textured plate at 3 D whose right edge runs down the image centre, over a textured wall
/// at 0.25 D: the two-layer occlusion boundary of Yu et al.'s four cases.
fn near_far_scene() -> Scene {
    let z = 1.0 / NEAR_D;
    let wall = 1.0 / FAR_D;
    Scene {
        objects: vec![Object {
            shape: Shape::Box {
                center: [-0.06 * z, 0.0, z],
                half: [0.06 * z, 0.1 * z, 1e-4 * z],
                rot: Rot::IDENTITY,
            },
            texture: noise_texture([0.85, 0.25, 0.1], [0.95, 0.85, 0.3], 0.004 * z, 11),
            alpha: 1.0,
        }],
        wall_depth: wall,
        wall: noise_texture([0.05, 0.15, 0.45], [0.5, 0.8, 0.9], 0.006 * wall, 12),
        seed: 0,
    }
}

/// A fence of thin rods (about 2 px wide at 256 px) at 2.5 D before a wall at 0.3 D.
fn fence_scene() -> Scene {
    let z = 1.0 / 2.5;
    let wall = 1.0 / 0.3;
    let rod = |x: f32, y: f32, vertical: bool| Object {
        shape: Shape::Box {
            center: [x * z, y * z, z],
            half: if vertical {
                [0.0014 * z, 0.2 * z, 0.0014 * z]
            } else {
                [0.2 * z, 0.0014 * z, 0.0014 * z]
            },
            rot: Rot::IDENTITY,
        },
        texture: Texture {
            a: [0.9, 0.9, 0.85],
            b: [0.9, 0.9, 0.85],
            pattern: Pattern::Solid,
        },
        alpha: 1.0,
    };
    let mut objects: Vec<Object> = [-0.12f32, -0.06, 0.0, 0.06, 0.12]
        .iter()
        .map(|&x| rod(x, 0.0, true))
        .collect();
    objects.extend([-0.09f32, 0.03, 0.1].iter().map(|&y| rod(0.0, y, false)));
    Scene {
        objects,
        wall_depth: wall,
        wall: noise_texture([0.1, 0.3, 0.1], [0.6, 0.5, 0.2], 0.005 * wall, 21),
        seed: 0,
    }
}

/// A large box at 2.5 D, close in front of a wall at 0.2 D: views 1 cm apart see wide strips
/// of wall that the centre view does not.
fn disocclusion_scene() -> Scene {
    let z = 1.0 / 2.5;
    let wall = 1.0 / 0.2;
    Scene {
        objects: vec![Object {
            shape: Shape::Box {
                center: [0.0, 0.0, z],
                half: [0.07 * z, 0.07 * z, 0.02 * z],
                rot: Rot::IDENTITY,
            },
            texture: noise_texture([0.7, 0.2, 0.5], [0.95, 0.7, 0.8], 0.005 * z, 31),
            alpha: 1.0,
        }],
        wall_depth: wall,
        wall: Texture {
            a: [0.05, 0.1, 0.2],
            b: [0.9, 0.8, 0.6],
            pattern: Pattern::Checker {
                scale: 0.012 * wall,
            },
        },
        seed: 0,
    }
}

/// A half-transparent pane at 3 D over a checker wall at 0.2 D: the input's one depth per
/// pixel is the pane's, but focused at the wall the eye sees the wall's texture sharp.
fn pane_scene() -> Scene {
    let z = 1.0 / 3.0;
    let wall = 1.0 / 0.2;
    Scene {
        objects: vec![Object {
            shape: Shape::Box {
                center: [0.0, 0.0, z],
                half: [0.08 * z, 0.1 * z, 1e-5],
                rot: Rot::IDENTITY,
            },
            texture: Texture {
                a: [0.5; 3],
                b: [0.5; 3],
                pattern: Pattern::Solid,
            },
            alpha: 0.5,
        }],
        wall_depth: wall,
        wall: Texture {
            a: [0.05, 0.1, 0.2],
            b: [0.9, 0.8, 0.6],
            pattern: Pattern::Checker { scale: 0.01 * wall },
        },
        seed: 0,
    }
}

/// Pixels whose depth lies at least `dist` D from `focus` (strongly defocused).
fn far_from_focus(depth: &DepthMap, focus: Diopters, dist: f32) -> Plane {
    let data = depth
        .data()
        .iter()
        .map(|&d| {
            if (d - focus.0).abs() >= dist {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    Plane::from_vec(depth.width(), depth.height(), data)
        .unwrap_or_else(|_| Plane::new(depth.width(), depth.height(), 0.0))
}

/// Pixels whose depth is above `d` D (nearer than 1/d m).
fn nearer_than(depth: &DepthMap, d: f32) -> Plane {
    let data = depth
        .data()
        .iter()
        .map(|&v| if v > d { 1.0 } else { 0.0 })
        .collect();
    Plane::from_vec(depth.width(), depth.height(), data)
        .unwrap_or_else(|_| Plane::new(depth.width(), depth.height(), 0.0))
}

/// Novel-view pixels that the reference (centre) view cannot see: the point a view's pixel
/// looks at is hidden from the centre by something nearer. `position` is the novel view's
/// place in the lens plane, metres.
pub fn disoccluded(scene: &Scene, cam: &Camera, position: [f32; 2]) -> Result<Plane, InputError> {
    let (_, depth) = render_pinhole(scene, cam, position, 1)?;
    let (w, h) = (cam.width, cam.height);
    let pitch = cam.eye.pixel_pitch_tan();
    let mut m = Plane::new(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let z = 1.0 / depth.data()[y * w + x].max(1e-6);
            let t = [
                (x as f32 + 0.5 - w as f32 * 0.5) * pitch,
                (y as f32 + 0.5 - h as f32 * 0.5) * pitch,
            ];
            let p = [position[0] + t[0] * z, position[1] + t[1] * z, z];
            let (_, seen_z) = scene.trace([0.0; 3], [p[0] / p[2], p[1] / p[2], 1.0]);
            if seen_z < p[2] * 0.98 {
                m.data_mut()[y * w + x] = 1.0;
            }
        }
    }
    Ok(m)
}

/// Lens-plane positions (metres) of the sparse input views of the disocclusion case (centre
/// and the corners of a 1 cm square, DeepFocus C5's span) and the novel views scored.
pub const SPARSE_SPAN_M: f32 = 0.01;
pub fn sparse_views() -> Vec<[f32; 2]> {
    let h = SPARSE_SPAN_M * 0.5;
    vec![[0.0, 0.0], [-h, -h], [h, -h], [-h, h], [h, h]]
}
pub fn novel_views() -> Vec<[f32; 2]> {
    let h = SPARSE_SPAN_M * 0.5;
    vec![[h, 0.0], [0.0, h], [-h, 0.0], [0.0, -h]]
}

/// Every failure case at `size` x `size` pixels.
pub fn failure_cases(size: usize) -> Result<Vec<FailureCase>, InputError> {
    let eye = EyeModel::default();
    let cam = Camera::square(eye, size);
    let mut out = Vec::new();

    // Yu et al.'s four occlusion-boundary cases.
    let nf = near_far_scene();
    let (_, nf_depth) = render_pinhole(&nf, &cam, [0.0, 0.0], 1)?;
    let coc = cam.eye.coc_px(Diopters(NEAR_D), Diopters(FAR_D));
    let band = |side| edge_band(&nf_depth, 0.3, 0.5 * coc + 1.5, side);
    type Yu = (&'static str, &'static str, f32, Side);
    let yu: [Yu; 4] = [
        (
            "yu-focus-near-point-near",
            "occlusion boundary, focused on the foreground, scored on the foreground's side: it must stay sharp, with no background blur bleeding over it",
            NEAR_D,
            Side::Near,
        ),
        (
            "yu-focus-near-point-far",
            "occlusion boundary, focused on the foreground, scored on the background's side: the blurred background must not take the sharp foreground's colour",
            NEAR_D,
            Side::Far,
        ),
        (
            "yu-focus-far-point-near",
            "occlusion boundary, focused on the background, scored on the foreground's side: the blurred foreground edge turns partly transparent, showing background the input never saw",
            FAR_D,
            Side::Near,
        ),
        (
            "yu-focus-far-point-far",
            "occlusion boundary, focused on the background, scored on the background's side: the blurred foreground spreads over the sharp background",
            FAR_D,
            Side::Far,
        ),
    ];
    for (name, description, focus, side) in yu {
        out.push(FailureCase {
            name,
            description,
            scene: nf.clone(),
            camera: cam,
            focus: Diopters(focus),
            mask: band(side),
            defect: InputDefect::None,
            view_synthesis: false,
            mover: Some(0),
            step_px: 0.75,
        });
    }

    let fence = fence_scene();
    let (_, fence_depth) = render_pinhole(&fence, &cam, [0.0, 0.0], 1)?;
    let fence_coc = cam.eye.coc_px(Diopters(2.5), Diopters(0.3));
    out.push(FailureCase {
        name: "thin-occluders",
        description: "a fence of rods about 2 px wide (at 256 px) at 2.5 D, focused at the wall behind it (0.3 D): the rods should nearly vanish into a veil",
        mask: dilate(&nearer_than(&fence_depth, 1.0), 0.5 * fence_coc + 1.0),
        scene: fence,
        camera: cam,
        focus: Diopters(0.3),
        defect: InputDefect::None,
        view_synthesis: false,
        mover: Some(0),
        step_px: 0.75,
    });

    let dis = disocclusion_scene();
    let mut dis_mask = Plane::new(size, size, 0.0);
    for p in novel_views() {
        let m = disoccluded(&dis, &cam, p)?;
        for (a, b) in dis_mask.data_mut().iter_mut().zip(m.data()) {
            *a = a.max(*b);
        }
    }
    out.push(FailureCase {
        name: "large-disocclusion",
        description: "a large box at 2.5 D before a wall at 0.2 D: novel views 5 mm from the centre see wall strips the centre view cannot (mask: the union of those strips); defocus at the wall with the 4 mm pupil",
        scene: dis,
        camera: cam,
        focus: Diopters(0.2),
        mask: dis_mask,
        defect: InputDefect::None,
        view_synthesis: true,
        mover: Some(0),
        step_px: 0.75,
    });

    let pane = pane_scene();
    let (_, pane_depth) = render_pinhole(&pane, &cam, [0.0, 0.0], 1)?;
    out.push(FailureCase {
        name: "semi-transparent",
        description: "a half-transparent pane at 3 D over a checker wall at 0.2 D, focused at the wall: RGB-D holds the pane's depth, so no single depth is right",
        mask: nearer_than(&pane_depth, 1.0),
        scene: pane,
        camera: cam,
        focus: Diopters(0.2),
        defect: InputDefect::None,
        view_synthesis: false,
        mover: Some(0),
        step_px: 0.75,
    });

    // Random test-split scenes for the depth defects and the extreme foci.
    let random = Scene::generate(Split::Test.seed(900));
    let (_, r_depth) = render_pinhole(&random, &cam, [0.0, 0.0], 1)?;
    out.push(FailureCase {
        name: "depth-noise",
        description: "a random test scene whose input depth carries Gaussian noise of 0.3 D (1 sd), focused at 1 D; region: pixels at least 0.5 D from focus, whose blur the noise changes",
        scene: random.clone(),
        camera: cam,
        focus: Diopters(1.0),
        mask: far_from_focus(&r_depth, Diopters(1.0), 0.5),
        defect: InputDefect::DepthNoise {
            sd_diopters: 0.3,
            seed: 41,
        },
        view_synthesis: false,
        mover: Some(1),
        step_px: 0.75,
    });
    let holes_case = FailureCase {
        name: "depth-holes",
        description: "the same scene with round holes in the input depth (about 8 % of pixels) reported as 0 D, focused at 1 D; region: the holes grown by the largest blur radius",
        scene: random.clone(),
        camera: cam,
        focus: Diopters(1.0),
        mask: Plane::new(size, size, 0.0),
        defect: InputDefect::DepthHoles {
            fraction: 0.08,
            seed: 42,
        },
        view_synthesis: false,
        mover: Some(1),
        step_px: 0.75,
    };
    let holes = holes_case.holes(size, size);
    let max_coc = cam.eye.coc_px(Diopters(0.0), Diopters(1.0)).max(2.0);
    out.push(FailureCase {
        mask: dilate(&holes, 0.5 * max_coc),
        ..holes_case
    });
    for (name, description, q) in [
        (
            "extreme-focus-0.1D",
            "a random test scene focused at 0.1 D (10 m): everything near is very blurred; region: pixels at least 2 D from focus",
            0.1f32,
        ),
        (
            "extreme-focus-4D",
            "a random test scene focused at 4 D (25 cm): the wall and most objects are very blurred; region: pixels at least 2 D from focus",
            4.0,
        ),
    ] {
        out.push(FailureCase {
            name,
            description,
            scene: random.clone(),
            camera: cam,
            focus: Diopters(q),
            mask: far_from_focus(&r_depth, Diopters(q), 2.0),
            defect: InputDefect::None,
            view_synthesis: false,
            mover: Some(1),
            step_px: 0.75,
        });
    }

    let wide_eye = EyeModel {
        pupil_diameter: Millimeters(8.0),
        ..eye
    };
    let wide = Camera::square(wide_eye, size);
    let wide_coc = wide.eye.coc_px(Diopters(NEAR_D), Diopters(FAR_D));
    out.push(FailureCase {
        name: "wide-pupil",
        description: "the occlusion-boundary scene seen through an 8 mm pupil (twice the default), focused on the background: blur twice as wide, more hidden background revealed",
        mask: edge_band(&nf_depth, 0.3, 0.5 * wide_coc + 1.5, Side::Both),
        scene: nf,
        camera: wide,
        focus: Diopters(FAR_D),
        defect: InputDefect::None,
        view_synthesis: false,
        mover: Some(0),
        step_px: 0.75,
    });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::render_thin_lens;

    fn selected(m: &Plane) -> usize {
        m.data().iter().filter(|&&v| v > 0.5).count()
    }

    #[test]
    fn every_case_has_a_proper_failure_region_and_finite_truth() {
        let size = 48;
        let cases = failure_cases(size).unwrap();
        let names: Vec<&str> = cases.iter().map(|c| c.name).collect();
        assert_eq!(cases.len(), 12, "{names:?}");
        for c in &cases {
            let n = selected(&c.mask);
            // Non-empty, and a region, not the whole image.
            assert!(n > 0, "{}: empty mask", c.name);
            assert!(n < size * size, "{}: mask covers everything", c.name);
            let truth = render_thin_lens(&c.scene, &c.camera, c.focus, 4).unwrap();
            assert!(
                truth
                    .channels
                    .iter()
                    .flat_map(|p| p.data())
                    .all(|v| v.is_finite() && (0.0..=1.0).contains(v)),
                "{}: ground truth not finite or out of range",
                c.name
            );
            let (color, depth) = c.input(&c.frame(1)).unwrap();
            assert_eq!((color.width(), depth.width()), (size, size));
        }
    }

    #[test]
    fn yu_bands_lie_on_their_own_side_of_the_edge() {
        let cases = failure_cases(64).unwrap();
        let cam = cases[0].camera;
        let (_, depth) = render_pinhole(&cases[0].scene, &cam, [0.0, 0.0], 1).unwrap();
        let near = &cases[0].mask;
        let far = &cases[1].mask;
        for (i, d) in depth.data().iter().enumerate() {
            if near.data()[i] > 0.5 {
                assert!(*d > 1.0, "near band on the wall at pixel {i}");
            }
            if far.data()[i] > 0.5 {
                assert!(*d < 1.0, "far band on the plate at pixel {i}");
            }
        }
        // The bands touch the edge: pixels on both sides of the image centre column.
        let w = cam.width;
        assert!((0..w).any(|y| near.data()[y * w + w / 2 - 1] > 0.5));
        assert!((0..w).any(|y| far.data()[y * w + w / 2 + 1] > 0.5));
    }

    #[test]
    fn defects_change_only_the_depth_and_are_deterministic() {
        let cases = failure_cases(32).unwrap();
        let noisy = cases.iter().find(|c| c.name == "depth-noise").unwrap();
        let holes = cases.iter().find(|c| c.name == "depth-holes").unwrap();
        let (c0, clean) = render_pinhole(&noisy.scene, &noisy.camera, [0.0; 2], 4).unwrap();
        let (c1, d1) = noisy.input(&noisy.scene).unwrap();
        assert_eq!(c0, c1);
        assert_ne!(clean, d1);
        assert_eq!(noisy.input(&noisy.scene).unwrap().1, d1);
        let (_, dh) = holes.input(&holes.scene).unwrap();
        let zeros = dh.data().iter().filter(|&&v| v == 0.0).count();
        assert!(zeros > 0 && zeros < 32 * 32 / 3, "{zeros} hole pixels");
    }

    #[test]
    fn disocclusions_are_found_beside_the_box() {
        let cam = Camera::square(EyeModel::default(), 64);
        let s = disocclusion_scene();
        // The centre view sees everything it sees.
        assert_eq!(selected(&disoccluded(&s, &cam, [0.0, 0.0]).unwrap()), 0);
        let m = disoccluded(&s, &cam, [0.005, 0.0]).unwrap();
        assert!(selected(&m) > 20, "{}", selected(&m));
    }

    #[test]
    fn animation_moves_the_mover_only() {
        let cases = failure_cases(32).unwrap();
        let c = &cases[0];
        let (a, b) = (c.frame(0), c.frame(3));
        assert_eq!(a, c.scene);
        assert_ne!(a.objects[0], b.objects[0]);
        assert_eq!(a.wall, b.wall);
    }
}
