//! Procedural scenes and their ground-truth renders.
//!
//! Scenes are random layouts of textured planes, slanted plates, boxes, spheres and thin rods in
//! front of a textured far wall, with heavy occlusion (in the spirit of DeepFocus's procedural
//! scenes), generated from a seed. Seeds below [`TEST_SEEDS`]`.start` are for training and the
//! test range never overlaps them.
//!
//! The camera is the eye of [`dioptra_core::EyeModel`]: lens at the origin in the z = 0 plane,
//! x right, y down, z forward; pixel `(x, y)` looks along tangent `((x + 0.5 - W/2) p,
//! (y + 0.5 - H/2) p)` with `p` the eye's pixel pitch. Depth maps hold z-depth in diopters.

pub mod animation;
pub mod failure;
mod geom;
mod render;

pub use geom::{Pattern, RayBundle, Rot, Shape, Texture};
pub use render::{
    light_field_positions, render_light_field, render_light_field_view, render_pinhole,
    render_thin_lens, render_thin_lens_scrambled, render_thin_lens_stack, Camera, LightFieldView,
};

use std::ops::Range;

/// Seeds reserved for evaluation. Training seeds are `0..TEST_SEEDS.start`.
pub const TEST_SEEDS: Range<u64> = 1_000_000..2_000_000;

/// Which side of the train/test split a seed is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn of(seed: u64) -> Split {
        if TEST_SEEDS.contains(&seed) {
            Split::Test
        } else {
            Split::Train
        }
    }
    /// The `i`-th seed of this split (test seeds wrap inside [`TEST_SEEDS`]).
    pub fn seed(self, i: u64) -> u64 {
        match self {
            Split::Test => TEST_SEEDS.start + i % (TEST_SEEDS.end - TEST_SEEDS.start),
            // Training seeds skip the test range entirely.
            Split::Train if i < TEST_SEEDS.start => i,
            Split::Train => i.saturating_add(TEST_SEEDS.end - TEST_SEEDS.start),
        }
    }
}

/// One surface: a shape with a texture and an opacity (1 = opaque).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Object {
    pub shape: Shape,
    pub texture: Texture,
    pub alpha: f32,
}

/// What to put in a generated scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneOptions {
    /// Number of objects in front of the wall.
    pub objects: usize,
    /// Nearest and farthest object depth, diopters.
    pub depth_range: (f32, f32),
    /// Make some surfaces semi-transparent (a known failure case for RGB-D methods).
    pub semi_transparent: bool,
}

impl Default for SceneOptions {
    fn default() -> Self {
        SceneOptions {
            objects: 24,
            depth_range: (0.25, 3.9),
            semi_transparent: false,
        }
    }
}

/// A scene: objects in front of a textured wall at `wall_depth` metres (fronto-parallel, unbounded).
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub objects: Vec<Object>,
    pub wall_depth: f32,
    pub wall: Texture,
    pub seed: u64,
}

/// PCG32 (O'Neill): small, seeded, the same on every platform.
struct Pcg(u64);

impl Pcg {
    fn new(seed: u64) -> Pcg {
        let mut p = Pcg(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0x853c_49e6_748f_ea9b);
        p.next_u32();
        p
    }
    fn next_u32(&mut self) -> u32 {
        let old = self.0;
        self.0 = old
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        xorshifted.rotate_right((old >> 59) as u32)
    }
    fn unit(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 / (1u32 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
}

/// One random flat colour.
fn solid_texture(rng: &mut Pcg) -> Texture {
    let c = [0; 3].map(|_| rng.range(0.05, 0.95));
    Texture {
        a: c,
        b: c,
        pattern: Pattern::Solid,
    }
}

fn random_texture(rng: &mut Pcg, distance: f32) -> Texture {
    let mut colour = || [0; 3].map(|_| rng.range(0.02, 0.9));
    let (a, b) = (colour(), colour());
    // Feature sizes of about 3 to 14 mrad (2 to 10 pixels at 256 px over 20 degrees).
    let scale = distance * rng.range(0.003, 0.014);
    let pattern = match rng.next_u32() % 4 {
        0 => Pattern::Checker { scale },
        1 => Pattern::Stripes {
            scale: scale * 2.0,
            angle: rng.range(0.0, std::f32::consts::PI),
        },
        2 => Pattern::Noise {
            scale: scale * 2.0,
            seed: rng.next_u32(),
        },
        _ => Pattern::Noise {
            scale: scale * 4.0,
            seed: rng.next_u32(),
        },
    };
    Texture { a, b, pattern }
}

/// A texture of [`Scene::generate_wide`]: feature sizes of about 1.5 to 50 mrad, log-uniform
/// (1 to 35 px at 256 px over 20 degrees), and one in six smooth (one colour).
fn wide_texture(rng: &mut Pcg, distance: f32) -> Texture {
    let mut colour = || [0; 3].map(|_| rng.range(0.02, 0.95));
    let (a, b) = (colour(), colour());
    let scale = distance * 0.0015 * 33f32.powf(rng.unit());
    let pattern = match rng.next_u32() % 6 {
        0 => Pattern::Solid,
        1 => Pattern::Checker { scale },
        2 => Pattern::Stripes {
            scale: scale * 2.0,
            angle: rng.range(0.0, std::f32::consts::PI),
        },
        _ => Pattern::Noise {
            scale: scale * 2.0,
            seed: rng.next_u32(),
        },
    };
    Texture { a, b, pattern }
}

/// The generators of training scenes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Family {
    /// [`Scene::generate`]: boxes, plates, rods and spheres before a wall.
    Random,
    /// [`Scene::generate_occluders`]: thin rods and large boxes before a far wall.
    Occluders,
    /// [`Scene::generate_wide`]: large slanted and flat textured planes, spheres of mixed
    /// sizes, rods and small boxes, at mixed scales.
    Wide,
}

impl Family {
    /// The name used in caches and provenance.
    pub fn name(self) -> &'static str {
        match self {
            Family::Random => "scene",
            Family::Occluders => "occluders",
            Family::Wide => "wide",
        }
    }
}

impl Scene {
    /// The scene for `seed` with default options.
    pub fn generate(seed: u64) -> Scene {
        Scene::generate_with(seed, &SceneOptions::default())
    }

    pub fn generate_with(seed: u64, opts: &SceneOptions) -> Scene {
        let mut rng = Pcg::new(seed);
        let (dmin, dmax) = (
            opts.depth_range.0.min(opts.depth_range.1).max(0.05),
            opts.depth_range.0.max(opts.depth_range.1).max(0.05),
        );
        let wall_depth = 1.0 / rng.range(0.1, 0.2);
        let wall = random_texture(&mut rng, wall_depth);
        let half_field = 0.2f32; // a little beyond tan(10 deg) so objects cross the border
        let mut objects = Vec::with_capacity(opts.objects + 1);
        // A slanted floor-like plate running from near to far: a continuous depth ramp.
        let tilt = rng.range(1.1, 1.4);
        let floor_z = 1.0 / rng.range(0.5, 1.0);
        objects.push(Object {
            shape: Shape::Box {
                center: [0.0, floor_z * rng.range(0.12, 0.18), floor_z],
                half: [floor_z * 0.5, floor_z * 1.2, 1e-4 * floor_z],
                rot: Rot::euler(tilt, 0.0, rng.range(-0.2, 0.2)),
            },
            texture: random_texture(&mut rng, floor_z),
            alpha: 1.0,
        });
        for _ in 0..opts.objects {
            // Uniform in diopters, like the depth statistics of DeepFocus's scenes.
            let z = 1.0 / rng.range(dmin, dmax);
            // Cluster towards the centre so objects overlap.
            let cx = rng.range(-half_field, half_field) * rng.range(0.4, 1.0) * z;
            let cy = rng.range(-half_field, half_field) * rng.range(0.4, 1.0) * z;
            let size = z * rng.range(0.015, 0.07);
            let kind = rng.next_u32() % 6;
            let shape = match kind {
                0 => Shape::Box {
                    center: [cx, cy, z],
                    half: [
                        size * rng.range(0.7, 1.6),
                        size * rng.range(0.7, 1.6),
                        1e-4 * z,
                    ],
                    rot: Rot::euler(0.0, 0.0, rng.range(0.0, 3.2)),
                },
                1 => Shape::Box {
                    // slanted plate: big depth change across its face
                    center: [cx, cy, z],
                    half: [size * 1.5, size, 1e-4 * z],
                    rot: Rot::euler(
                        rng.range(-1.0, 1.0),
                        rng.range(-1.2, 1.2),
                        rng.range(0.0, 3.2),
                    ),
                },
                2 => Shape::Box {
                    center: [cx, cy, z],
                    half: [
                        size * rng.range(0.4, 1.0),
                        size * rng.range(0.4, 1.0),
                        size * rng.range(0.4, 1.0),
                    ],
                    rot: Rot::euler(
                        rng.range(0.0, 3.2),
                        rng.range(0.0, 3.2),
                        rng.range(0.0, 3.2),
                    ),
                },
                3 => Shape::Box {
                    // thin rod
                    center: [cx, cy, z],
                    half: [size * 3.0, size * 0.06, size * 0.06],
                    rot: Rot::euler(
                        rng.range(0.0, 3.2),
                        rng.range(-0.5, 0.5),
                        rng.range(0.0, 3.2),
                    ),
                },
                _ => Shape::Sphere {
                    center: [cx, cy, z],
                    radius: size * rng.range(0.5, 1.0),
                },
            };
            let texture = random_texture(&mut rng, z);
            let alpha = if opts.semi_transparent && rng.next_u32().is_multiple_of(3) {
                rng.range(0.3, 0.7)
            } else {
                1.0
            };
            objects.push(Object {
                shape,
                texture,
                alpha,
            });
        }
        Scene {
            objects,
            wall_depth,
            wall,
            seed,
        }
    }

    /// An occluder-before-wall scene for `seed`: a fence of thin rods (1 to 6 px wide at
    /// 256 px over 20 degrees), a large flat box, or both, at 1.2-4 D before a textured wall
    /// at 0.1-0.5 D. These are the occlusion boundaries a single RGB-D image handles worst
    /// (rods that should dissolve into a veil, wide strips of wall the input never saw);
    /// random scenes hold few of them, so refinement nets train on this family too. Nothing
    /// here is taken from the failure suite's fixed scenes beyond the kind of geometry.
    pub fn generate_occluders(seed: u64) -> Scene {
        // A different stream from `generate` for the same seed.
        let mut rng = Pcg::new(seed ^ 0x6f63_636c_7564_6572);
        let wall_depth = 1.0 / rng.range(0.1, 0.5);
        let wall = random_texture(&mut rng, wall_depth);
        let kind = rng.next_u32() % 3;
        let mut objects = Vec::new();
        if kind != 1 {
            let z = 1.0 / rng.range(1.2, 4.0);
            let rods = 2 + rng.next_u32() % 6;
            let angle = if rng.next_u32().is_multiple_of(2) {
                0.0
            } else {
                rng.range(0.0, std::f32::consts::PI)
            };
            let half_thick = z * rng.range(0.0007, 0.004);
            let spacing = z * rng.range(0.03, 0.08);
            let offset = rng.range(-0.05, 0.05) * z;
            let texture = if rng.next_u32().is_multiple_of(2) {
                solid_texture(&mut rng)
            } else {
                random_texture(&mut rng, z)
            };
            for k in 0..rods {
                let across = offset + (k as f32 - rods as f32 / 2.0) * spacing;
                let (c, s) = (angle.cos(), angle.sin());
                objects.push(Object {
                    shape: Shape::Box {
                        center: [across * c, across * s, z],
                        half: [half_thick, 0.25 * z, half_thick],
                        rot: Rot::euler(0.0, 0.0, angle),
                    },
                    texture,
                    alpha: 1.0,
                });
            }
        }
        if kind != 0 {
            let z = 1.0 / rng.range(1.2, 4.0);
            objects.push(Object {
                shape: Shape::Box {
                    center: [rng.range(-0.1, 0.1) * z, rng.range(-0.1, 0.1) * z, z],
                    half: [
                        z * rng.range(0.03, 0.1),
                        z * rng.range(0.03, 0.1),
                        z * rng.range(1e-4, 0.03),
                    ],
                    rot: Rot::euler(0.0, 0.0, rng.range(0.0, 3.2)),
                },
                texture: random_texture(&mut rng, z),
                alpha: 1.0,
            });
        }
        Scene {
            objects,
            wall_depth,
            wall,
            seed,
        }
    }

    /// A scene of the wide family for `seed`: what the random and occluder families hold
    /// little of, mixed at every scale, before a wall at 0.05-0.6 D. One or two large
    /// textured planes (the first slanted, its depth varying smoothly by tenths of a diopter
    /// or more across the view; a second slanted or fronto-parallel and covering much of the
    /// field); spheres of mixed sizes (radius 1 to
    /// 30 % of their distance), smooth (one colour, shaded by their curvature) or textured;
    /// thin rods (about 0.5 to 3 mrad across: 1 to 6 px at 256 px over 20 degrees); small
    /// boxes and plates. Textures span a wider range of feature sizes (about 1.5 to 50
    /// mrad) than [`Scene::generate`]'s, with smooth surfaces among them. Objects lie at
    /// 0.2-4 D. Nothing is taken from any validation scene beyond the kinds of geometry the
    /// issue names (slanted and curved smooth surfaces, spheres, large textured planes, thin
    /// structures, mixed scales).
    pub fn generate_wide(seed: u64) -> Scene {
        // A different stream from the other families for the same seed.
        let mut rng = Pcg::new(seed ^ 0x7769_6465_5f66_616d);
        let wall_depth = 1.0 / rng.range(0.05, 0.6);
        let wall = wide_texture(&mut rng, wall_depth);
        let mut objects = Vec::new();
        let mut push = |shape, texture| {
            objects.push(Object {
                shape,
                texture,
                alpha: 1.0,
            })
        };
        // Large planes: at least one slanted.
        let planes = 1 + rng.next_u32() % 2;
        for k in 0..planes {
            let slanted = k == 0 || rng.next_u32().is_multiple_of(2);
            if slanted {
                // Turned 0.6-1.3 rad out of the fronto-parallel plane about an axis in it
                // (at `d` D in the middle, its depth runs at d tan(tilt) D per unit of
                // tangent across the view), reaching 0.25-0.6 of its distance each way.
                let d = rng.range(0.5, 3.0);
                let z = 1.0 / d;
                let along = z * rng.range(0.25, 0.6);
                let tilt = rng.range(0.6, 1.3) * if rng.unit() < 0.5 { -1.0 } else { 1.0 };
                push(
                    Shape::Box {
                        center: [rng.range(-0.1, 0.1) * z, rng.range(-0.1, 0.1) * z, z],
                        half: [along, z * rng.range(0.15, 0.5), 1e-4 * z],
                        rot: Rot::euler(0.0, tilt, rng.range(0.0, std::f32::consts::PI)),
                    },
                    wide_texture(&mut rng, z),
                );
            } else {
                let z = 1.0 / rng.range(0.3, 2.0);
                push(
                    Shape::Box {
                        center: [rng.range(-0.15, 0.15) * z, rng.range(-0.15, 0.15) * z, z],
                        half: [z * rng.range(0.1, 0.3), z * rng.range(0.1, 0.3), 1e-4 * z],
                        rot: Rot::euler(0.0, 0.0, rng.range(0.0, 0.4)),
                    },
                    wide_texture(&mut rng, z),
                );
            }
        }
        // Spheres of mixed sizes.
        for _ in 0..rng.next_u32() % 6 {
            let z = 1.0 / rng.range(0.2, 4.0);
            // Log-uniform radius: 1 % to 30 % of the distance.
            let radius = z * 0.01 * 30f32.powf(rng.unit());
            let texture = if rng.next_u32().is_multiple_of(2) {
                solid_texture(&mut rng)
            } else {
                wide_texture(&mut rng, z)
            };
            push(
                Shape::Sphere {
                    center: [rng.range(-0.2, 0.2) * z, rng.range(-0.2, 0.2) * z, z],
                    radius,
                },
                texture,
            );
        }
        // Thin rods, a few parallel or at random angles.
        let rods = rng.next_u32() % 5;
        let angle = rng.range(0.0, std::f32::consts::PI);
        for _ in 0..rods {
            let z = 1.0 / rng.range(0.3, 4.0);
            let half_thick = z * rng.range(0.00025, 0.0015);
            let a = if rng.next_u32().is_multiple_of(2) {
                angle
            } else {
                rng.range(0.0, std::f32::consts::PI)
            };
            push(
                Shape::Box {
                    center: [rng.range(-0.2, 0.2) * z, rng.range(-0.2, 0.2) * z, z],
                    half: [half_thick, z * rng.range(0.1, 0.4), half_thick],
                    rot: Rot::euler(rng.range(-0.4, 0.4), 0.0, a),
                },
                wide_texture(&mut rng, z),
            );
        }
        // Small boxes and plates, some slanted.
        for _ in 0..rng.next_u32() % 7 {
            let z = 1.0 / rng.range(0.2, 4.0);
            let size = z * 0.01 * 8f32.powf(rng.unit());
            push(
                Shape::Box {
                    center: [rng.range(-0.2, 0.2) * z, rng.range(-0.2, 0.2) * z, z],
                    half: [
                        size * rng.range(0.5, 1.5),
                        size * rng.range(0.5, 1.5),
                        size * rng.range(0.001, 1.0),
                    ],
                    rot: Rot::euler(
                        rng.range(-1.0, 1.0),
                        rng.range(-1.0, 1.0),
                        rng.range(0.0, 3.2),
                    ),
                },
                wide_texture(&mut rng, z),
            );
        }
        Scene {
            objects,
            wall_depth,
            wall,
            seed,
        }
    }

    /// The scene of `family` for `seed`.
    pub fn of_family(family: Family, seed: u64) -> Scene {
        match family {
            Family::Random => Scene::generate(seed),
            Family::Occluders => Scene::generate_occluders(seed),
            Family::Wide => Scene::generate_wide(seed),
        }
    }

    /// Colour and z-depth (metres) of the first surface along `o + t d` (with `d.z = 1`),
    /// compositing semi-transparent surfaces front to back.
    pub fn trace(&self, o: [f32; 3], d: [f32; 3]) -> ([f32; 3], f32) {
        self.trace_among(o, d, self.objects.iter())
    }

    /// [`Scene::trace`] testing only `objects` (in the scene's order), which must hold every
    /// object the ray can meet: the renders pass those a pixel's bundle of rays can meet
    /// ([`RayBundle`]), so a ray tests a few objects instead of all.
    pub fn trace_among<'a>(
        &'a self,
        o: [f32; 3],
        d: [f32; 3],
        objects: impl Iterator<Item = &'a Object> + Clone,
    ) -> ([f32; 3], f32) {
        let mut colour = [0.0f32; 3];
        let mut transmit = 1.0f32;
        let mut first_z = None;
        let mut t_min = 1e-4f32;
        // A few layers of transparency are enough; the loop always ends at the wall.
        for _ in 0..6 {
            let wall_t = self.wall_depth - o[2];
            match nearest_hit(o, d, t_min, wall_t, objects.clone()) {
                Some((h, obj)) if h.t < wall_t => {
                    let ndl = glam::Vec3::from(h.normal)
                        .dot(glam::Vec3::new(-0.36, -0.6, -0.72))
                        .abs();
                    let shade = 0.55 + 0.45 * ndl;
                    let c = obj.texture.eval(h.uv);
                    let a = obj.alpha.clamp(0.0, 1.0);
                    for k in 0..3 {
                        colour[k] += transmit * a * c[k] * shade;
                    }
                    transmit *= 1.0 - a;
                    first_z.get_or_insert(o[2] + h.t);
                    t_min = h.t + 1e-4;
                    if transmit <= 1e-4 {
                        break;
                    }
                }
                _ => {
                    let p = [o[0] + d[0] * wall_t, o[1] + d[1] * wall_t];
                    let c = self.wall.eval(p);
                    for k in 0..3 {
                        colour[k] += transmit * c[k];
                    }
                    first_z.get_or_insert(self.wall_depth);
                    break;
                }
            }
        }
        (colour, first_z.unwrap_or(self.wall_depth))
    }

    /// The z-depth (metres) [`Scene::trace_among`] gives the ray, without its colour: the
    /// first surface's, opaque or not, else the wall's.
    pub fn depth_among<'a>(
        &'a self,
        o: [f32; 3],
        d: [f32; 3],
        objects: impl Iterator<Item = &'a Object>,
    ) -> f32 {
        let wall_t = self.wall_depth - o[2];
        match nearest_hit(o, d, 1e-4, wall_t, objects) {
            Some((h, _)) if h.t < wall_t => o[2] + h.t,
            _ => self.wall_depth,
        }
    }
}

/// The nearest hit beyond `t_min` of the ray `o + t d` among `objects` (the first in their
/// order of equally near ones); those beyond `wall_t` and the best so far are culled
/// ([`Shape::may_hit`]), so a hit at or beyond `wall_t` may or may not be found.
fn nearest_hit<'a>(
    o: [f32; 3],
    d: [f32; 3],
    t_min: f32,
    wall_t: f32,
    objects: impl Iterator<Item = &'a Object>,
) -> Option<(geom::Hit, &'a Object)> {
    let mut best: Option<(geom::Hit, &Object)> = None;
    for obj in objects {
        // Only a hit nearer than the best so far and the wall can change the result.
        let t_max = best.as_ref().map_or(wall_t, |(b, _)| b.t.min(wall_t));
        if !obj.shape.may_hit(o, d, t_min, t_max) {
            continue;
        }
        if let Some(h) = obj.shape.intersect(o, d, t_min) {
            if best.as_ref().is_none_or(|(b, _)| h.t < b.t) {
                best = Some((h, obj));
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_are_deterministic_and_distinct() {
        assert_eq!(Scene::generate(5), Scene::generate(5));
        assert_ne!(Scene::generate(5).objects, Scene::generate(6).objects);
    }

    #[test]
    fn occluder_scenes_put_an_occluder_well_before_the_wall() {
        let mut kinds = [false; 2];
        for seed in 0..12 {
            let s = Scene::generate_occluders(seed);
            assert_eq!(s, Scene::generate_occluders(seed));
            assert!(!s.objects.is_empty());
            let wall_d = 1.0 / s.wall_depth;
            assert!((0.1..=0.5).contains(&wall_d), "wall at {wall_d} D");
            for o in &s.objects {
                let Shape::Box { center, half, .. } = o.shape else {
                    panic!("boxes only");
                };
                let d = 1.0 / center[2];
                assert!((1.2..=4.0).contains(&d), "occluder at {d} D");
                // Rods: thin across (at most ~6 px at 256 px over 20 degrees).
                kinds[usize::from(half[1] > 10.0 * half[0])] = true;
            }
        }
        assert!(kinds[0] && kinds[1], "both rods and boxes among 12 seeds");
    }

    #[test]
    fn wide_scenes_hold_slanted_planes_spheres_of_mixed_sizes_and_rods() {
        use dioptra_core::EyeModel;
        let cam = Camera::square(EyeModel::default(), 64);
        let (mut radii, mut smooth_spheres, mut rods, mut flat_planes) = (Vec::new(), 0, 0, 0);
        for seed in 0..24 {
            let s = Scene::generate_wide(seed);
            assert_eq!(s, Scene::of_family(Family::Wide, seed));
            assert_ne!(s.objects, Scene::generate(seed).objects);
            let wall_d = 1.0 / s.wall_depth;
            assert!((0.05..=0.6).contains(&wall_d), "wall at {wall_d} D");
            // The first object is a large slanted plane: alone before a far wall, its depth
            // varies smoothly across the view by 0.1 D or more (one pinhole render).
            let Shape::Box { half, .. } = s.objects[0].shape else {
                panic!("seed {seed}: the first object is not a plane");
            };
            assert!(
                half[2] < 1e-3 * half[0].min(half[1]),
                "seed {seed}: {half:?}"
            );
            let alone = Scene {
                objects: vec![s.objects[0]],
                wall_depth: 1000.0,
                wall: s.wall,
                seed,
            };
            let (_, depth) = render_pinhole(&alone, &cam, [0.0, 0.0], 1).unwrap();
            let on: Vec<f32> = depth.data().iter().copied().filter(|&d| d > 0.01).collect();
            assert!(
                on.len() > 64 * 64 / 10,
                "seed {seed}: the plane covers {} px",
                on.len()
            );
            let (lo, hi) = on
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)));
            assert!(
                hi - lo >= 0.1,
                "seed {seed}: depth {lo}..{hi} D across the plane"
            );
            // Smooth: neighbouring plane pixels differ by a small part of the range.
            let d = depth.data();
            for y in 0..64 {
                for x in 0..63 {
                    let (a, b) = (d[y * 64 + x], d[y * 64 + x + 1]);
                    if a > 0.01 && b > 0.01 {
                        assert!((a - b).abs() < 0.25 * (hi - lo) + 0.02, "seed {seed}");
                    }
                }
            }
            for o in &s.objects[1..] {
                match o.shape {
                    Shape::Sphere { center, radius } => {
                        radii.push(radius / center[2]);
                        smooth_spheres += usize::from(o.texture.pattern == Pattern::Solid);
                    }
                    Shape::Box { center, half, .. } if half[1] > 50.0 * half[0] => {
                        // A rod: 0.5 to 3 mrad across.
                        let across = 2.0 * half[0] / center[2];
                        assert!((0.0005..=0.003).contains(&across), "rod {across} rad");
                        rods += 1;
                    }
                    Shape::Box { half, .. } if half[0] > 0.05 && half[2] < 1e-3 * half[0] => {
                        flat_planes += 1
                    }
                    _ => {}
                }
                let z = match o.shape {
                    Shape::Sphere { center, .. } | Shape::Box { center, .. } => center[2],
                };
                assert!((0.2..=4.0).contains(&(1.0 / z)), "object at {} D", 1.0 / z);
            }
        }
        // Mixed sizes: spheres from about 1 % to 30 % of their distance in radius.
        let (lo, hi) = radii
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &r| (a.min(r), b.max(r)));
        assert!(
            radii.len() >= 24 && hi / lo > 10.0,
            "{} radii {lo}..{hi}",
            radii.len()
        );
        assert!(smooth_spheres > 0 && rods >= 12 && flat_planes > 0);
    }

    #[test]
    fn train_and_test_seeds_never_overlap() {
        for i in [0u64, 1, 999_999, 1_000_000, 5_000_000, u64::MAX - 1] {
            assert_eq!(Split::of(Split::Train.seed(i)), Split::Train, "train {i}");
            assert_eq!(Split::of(Split::Test.seed(i)), Split::Test, "test {i}");
        }
    }

    #[test]
    fn transparency_composites_behind() {
        let opts = SceneOptions {
            semi_transparent: true,
            ..SceneOptions::default()
        };
        let s = Scene::generate_with(3, &opts);
        assert!(s.objects.iter().any(|o| o.alpha < 1.0));
        assert!(Scene::generate(3).objects.iter().all(|o| o.alpha == 1.0));
    }
}
