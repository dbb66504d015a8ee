//! Ray-primitive intersection and procedural textures for the scene simulator.
//! Camera space: x right, y down, z forward (metres); the eye's lens is the z = 0 plane.

use glam::{Mat3, Vec3};

/// A point or direction as the scene's public types hold it.
pub type V3 = [f32; 3];

/// The unit vector along `a` (zero stays zero).
fn normalize(a: Vec3) -> Vec3 {
    a / a.length().max(1e-20)
}

/// A rotation (local = R * world).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rot(Mat3);

impl Rot {
    pub const IDENTITY: Rot = Rot(Mat3::IDENTITY);

    /// Rotation by Euler angles (radians) about x, then y, then z.
    pub fn euler(ax: f32, ay: f32, az: f32) -> Rot {
        Rot(Mat3::from_rotation_z(az) * (Mat3::from_rotation_y(ay) * Mat3::from_rotation_x(ax)))
    }
    fn apply(&self, v: Vec3) -> Vec3 {
        self.0 * v
    }
    fn apply_transpose(&self, v: Vec3) -> Vec3 {
        self.0.transpose() * v
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// An oriented box; planes and rods are boxes with one or two thin sides.
    Box {
        center: V3,
        half: V3,
        rot: Rot,
    },
    Sphere {
        center: V3,
        radius: f32,
    },
}

/// Where a ray meets a shape: distance along the ray, surface coordinates and normal.
#[derive(Debug, Clone, Copy)]
pub struct Hit {
    pub t: f32,
    pub uv: [f32; 2],
    pub normal: V3,
}

/// Every ray a pixel casts: from a point of a disk of radius `lens_radius` around `origin`
/// (in the z = 0 plane) through the pixel's footprint on the focal plane z = 1 / `focus_d`,
/// i.e. at depth z the points `origin + L (1 - z q) + z t` for L in the disk and t in the
/// pixel's tangent rectangle `t_lo..t_hi`. A pinhole is a lens of radius 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayBundle {
    pub origin: [f32; 2],
    pub lens_radius: f32,
    pub focus_d: f32,
    pub t_lo: [f32; 2],
    pub t_hi: [f32; 2],
}

impl RayBundle {
    /// False when no ray of the bundle can meet `shape` (checked on its bounding sphere): at
    /// every depth the sphere spans, the bundle lies in a rectangle (linear in depth, so its
    /// extremes are at the span's ends) that the sphere's disk does not reach.
    pub fn may_meet(&self, shape: &Shape) -> bool {
        let (c, r) = shape.bounding_sphere();
        let (z0, z1) = ((c[2] - r).max(0.0), c[2] + r);
        if z1 < 0.0 {
            return false;
        }
        let q = self.focus_d;
        let spread = self.lens_radius * (1.0 - z0 * q).abs().max((1.0 - z1 * q).abs());
        let gap = |k: usize| {
            let lo = (z0 * self.t_lo[k]).min(z1 * self.t_lo[k]) - spread + self.origin[k];
            let hi = (z0 * self.t_hi[k]).max(z1 * self.t_hi[k]) + spread + self.origin[k];
            (lo - c[k]).max(c[k] - hi).max(0.0)
        };
        let gap2 = gap(0) * gap(0) + gap(1) * gap(1);
        // A relative margin for rounding: culling a little less never changes an image.
        let reach = r * 1.001 + 1e-4 * (c[2].abs() + r) + 1e-6;
        gap2 <= reach * reach
    }
}

impl Shape {
    /// A sphere holding the shape: centre and radius.
    pub fn bounding_sphere(&self) -> (V3, f32) {
        match *self {
            Shape::Box { center, half, .. } => (center, Vec3::from(half).length()),
            Shape::Sphere { center, radius } => (center, radius),
        }
    }

    /// The corners of a box holding the shape (its own, or a sphere's axis-aligned one).
    pub fn corners(&self) -> [V3; 8] {
        let (center, half, rot) = match *self {
            Shape::Box { center, half, rot } => (center, half, rot),
            Shape::Sphere { center, radius } => (center, [radius; 3], Rot::IDENTITY),
        };
        std::array::from_fn(|i| {
            let local =
                Vec3::from([0, 1, 2].map(|k| if i >> k & 1 == 0 { -half[k] } else { half[k] }));
            (Vec3::from(center) + rot.apply_transpose(local)).to_array()
        })
    }

    /// False when the ray `o + t d` certainly meets the shape nowhere in `t_min < t < t_max`:
    /// it misses a sphere around it (a box's, a little larger than its corners), or meets
    /// that sphere only outside the interval. A few multiplies instead of a box's rotation
    /// and slabs, so a ray tests most objects of a scene at that cost; never false for a
    /// shape the ray hits in the interval, so what [`Shape::intersect`] finds is unchanged.
    #[inline]
    pub fn may_hit(&self, o: V3, d: V3, t_min: f32, t_max: f32) -> bool {
        let Shape::Box { center, half, .. } = *self else {
            // A sphere's own test is as cheap.
            return true;
        };
        let (o, d) = (Vec3::from(o), Vec3::from(d));
        let r2 = Vec3::from(half).length_squared() * 1.001 + 1e-12;
        let oc = o - Vec3::from(center);
        let a = d.dot(d);
        let b = oc.dot(d);
        let c = oc.dot(oc) - r2;
        let disc = b * b - a * c;
        if disc < 0.0 {
            return false;
        }
        let s = disc.sqrt();
        // Entry and exit of the sphere, widened by a relative margin for rounding.
        let (near, far) = ((-b - s) / a, (-b + s) / a);
        let slack = 1e-4 * (near.abs() + far.abs()) + 1e-6;
        far + slack > t_min && near - slack < t_max
    }

    /// Nearest intersection with `t > t_min` of the ray `o + t d`.
    pub fn intersect(&self, o: V3, d: V3, t_min: f32) -> Option<Hit> {
        let (o, d) = (Vec3::from(o), Vec3::from(d));
        match *self {
            Shape::Box { center, half, rot } => {
                let lo = rot.apply(o - Vec3::from(center));
                let ld = rot.apply(d);
                let (mut t0, mut t1) = (f32::NEG_INFINITY, f32::INFINITY);
                let (mut axis0, mut axis1) = (0usize, 0usize);
                for a in 0..3 {
                    if ld[a].abs() < 1e-12 {
                        if lo[a].abs() > half[a] {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / ld[a];
                    let mut ta = (-half[a] - lo[a]) * inv;
                    let mut tb = (half[a] - lo[a]) * inv;
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis0 = a;
                    }
                    if tb < t1 {
                        t1 = tb;
                        axis1 = a;
                    }
                }
                if t0 > t1 {
                    return None;
                }
                let (t, axis) = if t0 > t_min {
                    (t0, axis0)
                } else if t1 > t_min {
                    (t1, axis1)
                } else {
                    return None;
                };
                let p = lo + ld * t;
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let mut n = Vec3::ZERO;
                n[axis] = if p[axis] > 0.0 { 1.0 } else { -1.0 };
                Some(Hit {
                    t,
                    // Offsetting by the face axis keeps textures on adjacent faces unrelated.
                    uv: [p[u] + axis as f32 * 3.1, p[v] - axis as f32 * 1.7],
                    normal: rot.apply_transpose(n).to_array(),
                })
            }
            Shape::Sphere { center, radius } => {
                let oc = o - Vec3::from(center);
                let a = d.dot(d);
                let b = oc.dot(d);
                let c = oc.dot(oc) - radius * radius;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t = [(-b - s) / a, (-b + s) / a]
                    .into_iter()
                    .find(|&t| t > t_min)?;
                let n = normalize(oc + d * t);
                // Arc-length surface coordinates, so texture scale is metres as for boxes.
                let u = n[0].atan2(-n[2]) * radius;
                let v = n[1].clamp(-1.0, 1.0).asin() * radius;
                Some(Hit {
                    t,
                    uv: [u, v],
                    normal: n.to_array(),
                })
            }
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pattern {
    Solid,
    /// Squares `scale` metres on a side.
    Checker {
        scale: f32,
    },
    /// Stripes of period `scale` metres at `angle` radians.
    Stripes {
        scale: f32,
        angle: f32,
    },
    /// Three octaves of value noise with base feature size `scale` metres.
    Noise {
        scale: f32,
        seed: u32,
    },
}

/// Two colours (linear RGB) mixed by a pattern.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Texture {
    pub a: [f32; 3],
    pub b: [f32; 3],
    pub pattern: Pattern,
}

impl Texture {
    pub fn eval(&self, uv: [f32; 2]) -> [f32; 3] {
        let m = match self.pattern {
            Pattern::Solid => 0.0,
            Pattern::Checker { scale } => {
                let i = (uv[0] / scale).floor() as i64 + (uv[1] / scale).floor() as i64;
                (i & 1) as f32
            }
            Pattern::Stripes { scale, angle } => {
                let (s, c) = angle.sin_cos();
                let w = (uv[0] * c + uv[1] * s) / scale;
                // Smooth stripes: a square wave would alias at every edge.
                0.5 + 0.5 * (w * std::f32::consts::TAU).sin()
            }
            Pattern::Noise { scale, seed } => {
                let mut acc = 0.0;
                let mut amp = 0.5;
                let mut f = 1.0 / scale;
                for o in 0..3 {
                    acc += amp * value_noise(uv[0] * f, uv[1] * f, seed.wrapping_add(o * 977));
                    amp *= 0.5;
                    f *= 2.0;
                }
                acc / 0.875
            }
        };
        [0, 1, 2].map(|c| self.a[c] + (self.b[c] - self.a[c]) * m)
    }
}

fn lattice(x: i32, y: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ seed.wrapping_mul(0xcb1a_b31f);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0xffff) as f32 / 65535.0
}

fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let (xf, yf) = (x.floor(), y.floor());
    let (xi, yi) = (xf as i32, yf as i32);
    let smooth = |t: f32| t * t * (3.0 - 2.0 * t);
    let (fx, fy) = (smooth(x - xf), smooth(y - yf));
    let a = lattice(xi, yi, seed) + (lattice(xi + 1, yi, seed) - lattice(xi, yi, seed)) * fx;
    let b = lattice(xi, yi + 1, seed)
        + (lattice(xi + 1, yi + 1, seed) - lattice(xi, yi + 1, seed)) * fx;
    a + (b - a) * fy
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_and_sphere_hit_distances() {
        let b = Shape::Box {
            center: [0.0, 0.0, 2.0],
            half: [0.5, 0.5, 0.5],
            rot: Rot::IDENTITY,
        };
        let h = b.intersect([0.0; 3], [0.0, 0.0, 1.0], 1e-4).unwrap();
        assert!((h.t - 1.5).abs() < 1e-5);
        assert_eq!(h.normal, [0.0, 0.0, -1.0]);
        assert!(b.intersect([0.0; 3], [1.0, 0.0, 1.0], 1e-4).is_none());
        let s = Shape::Sphere {
            center: [0.0, 0.0, 3.0],
            radius: 1.0,
        };
        let h = s.intersect([0.0; 3], [0.0, 0.0, 1.0], 1e-4).unwrap();
        assert!((h.t - 2.0).abs() < 1e-5);
        // a rotated thin plate seen edge-on is missed, face-on is hit
        let plate = Shape::Box {
            center: [0.0, 0.0, 1.0],
            half: [0.2, 0.2, 1e-4],
            rot: Rot::euler(0.0, 0.6, 0.0),
        };
        let h = plate.intersect([0.0; 3], [0.0, 0.0, 1.0], 1e-4).unwrap();
        assert!((h.t - 1.0).abs() < 1e-3);
    }

    /// The cull never drops a hit: rays aimed at points all over boxes (corners and edges,
    /// just inside and just outside, where rounding matters most), from points on a 4 mm lens.
    #[test]
    fn the_bounding_sphere_cull_never_drops_a_hit() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let (mut hits, mut culled) = (0, 0);
        for _ in 0..300 {
            let z = 0.3 + 9.0 * rnd();
            let center = [(rnd() - 0.5) * z * 0.3, (rnd() - 0.5) * z * 0.3, z];
            let half = [
                z * 0.07 * rnd() + 1e-4 * z,
                z * 0.07 * rnd() + 1e-4 * z,
                if rnd() < 0.5 {
                    1e-4 * z
                } else {
                    z * 0.05 * rnd()
                },
            ];
            let rot = Rot::euler(rnd() * 3.2, rnd() * 3.2, rnd() * 3.2);
            let shape = Shape::Box { center, half, rot };
            for _ in 0..200 {
                // A point on the box's surface region: each coordinate at -1, 0 or +1 of its
                // half-size, scaled by 1 +- 1e-4 (just inside or outside), in world space.
                let local: V3 = [0, 1, 2].map(|k| {
                    let side = (rnd() * 3.0).floor() - 1.0;
                    half[k] * side * (1.0 + (rnd() - 0.5) * 2e-4) + half[k] * 0.2 * (rnd() - 0.5)
                });
                let target = Vec3::from(center) + rot.apply_transpose(Vec3::from(local));
                let o = [(rnd() - 0.5) * 0.004, (rnd() - 0.5) * 0.004, 0.0];
                let d = target - Vec3::from(o);
                let d = [d.x / d.z, d.y / d.z, 1.0];
                let t_min = 1e-4;
                match shape.intersect(o, d, t_min) {
                    Some(h) => {
                        hits += 1;
                        let t_max = f32::from_bits(h.t.to_bits() + 1);
                        assert!(
                            shape.may_hit(o, d, t_min, t_max),
                            "culled a hit at t = {}: {shape:?} o {o:?} d {d:?}",
                            h.t
                        );
                    }
                    None => culled += usize::from(!shape.may_hit(o, d, t_min, f32::MAX)),
                }
            }
        }
        // Both cases happened (the test is not vacuous).
        assert!(
            hits > 10_000 && culled > 1_000,
            "{hits} hits, {culled} culled"
        );
    }

    #[test]
    fn textures_stay_between_their_colours() {
        let t = Texture {
            a: [0.1, 0.2, 0.3],
            b: [0.9, 0.5, 0.4],
            pattern: Pattern::Noise {
                scale: 0.1,
                seed: 7,
            },
        };
        for i in 0..200 {
            let c = t.eval([i as f32 * 0.013, i as f32 * -0.021]);
            for ((v, a), b) in c.iter().zip(t.a).zip(t.b) {
                assert!(*v >= a.min(b) - 1e-5 && *v <= a.max(b) + 1e-5);
            }
        }
    }
}
