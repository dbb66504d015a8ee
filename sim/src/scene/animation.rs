//! Moving objects: a scene animated by sliding some of its objects side to side, as the demo
//! and the daemon's procedural content (`[content] source = "scene"`) show it.

use super::{Object, Scene, Shape};

/// One moving object: its index, resting centre, amplitude (m), frequency (Hz) and phase.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Mover {
    index: usize,
    rest: [f32; 3],
    amplitude: f32,
    hz: f32,
    phase: f32,
}

/// Which objects of a scene move, and how (`default()`: none).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Animation {
    movers: Vec<Mover>,
}

/// The centre of a shape.
pub fn centre(s: &Shape) -> [f32; 3] {
    match *s {
        Shape::Box { center, .. } | Shape::Sphere { center, .. } => center,
    }
}

fn set_centre(s: &mut Shape, c: [f32; 3]) {
    match s {
        Shape::Box { center, .. } | Shape::Sphere { center, .. } => *center = c,
    }
}

impl Animation {
    /// Up to `n` objects of `scene` for which `moves` holds slide side to side by 2 % of
    /// their distance, each at its own rate (0.3 Hz, then 0.15 Hz faster for each next one).
    pub fn pick(scene: &Scene, n: usize, moves: impl Fn(&Object) -> bool) -> Animation {
        let movers = scene
            .objects
            .iter()
            .enumerate()
            .filter(|(_, o)| moves(o))
            .take(n)
            .enumerate()
            .map(|(k, (index, o))| {
                let rest = centre(&o.shape);
                Mover {
                    index,
                    rest,
                    amplitude: 0.02 * rest[2],
                    hz: 0.3 + 0.15 * k as f32,
                    phase: k as f32 * 1.7,
                }
            })
            .collect();
        Animation { movers }
    }

    /// How many objects move.
    pub fn len(&self) -> usize {
        self.movers.len()
    }

    pub fn is_empty(&self) -> bool {
        self.movers.is_empty()
    }

    /// `base` as it is `secs` seconds into the animation.
    pub fn at(&self, base: &Scene, secs: f64) -> Scene {
        let mut s = base.clone();
        let secs = secs as f32;
        for m in &self.movers {
            if let Some(o) = s.objects.get_mut(m.index) {
                let dx = m.amplitude * (std::f32::consts::TAU * m.hz * secs + m.phase).sin();
                set_centre(&mut o.shape, [m.rest[0] + dx, m.rest[1], m.rest[2]]);
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn movers_slide_sideways_and_come_back() {
        let base = Scene::generate(1_000_001);
        let a = Animation::pick(&base, 4, |_| true);
        assert_eq!(a.len(), 4);
        assert_eq!(a.at(&base, 0.0).objects.len(), base.objects.len());
        let later = a.at(&base, 0.8);
        let moved: Vec<usize> = (0..base.objects.len())
            .filter(|&i| later.objects[i] != base.objects[i])
            .collect();
        assert_eq!(moved.len(), 4, "{moved:?}");
        for &i in &moved {
            let (c0, c1) = (
                centre(&base.objects[i].shape),
                centre(&later.objects[i].shape),
            );
            // Only x changes, by at most the amplitude.
            assert_eq!((c0[1], c0[2]), (c1[1], c1[2]));
            assert!((c1[0] - c0[0]).abs() <= 0.02 * c0[2] + 1e-6);
        }
        // The first mover (0.3 Hz) is back where it was at t = 0 after one period.
        let i = moved[0];
        let t0 = a.at(&base, 0.0);
        let t1 = a.at(&base, 1.0 / 0.3);
        let (x0, x1) = (
            centre(&t0.objects[i].shape)[0],
            centre(&t1.objects[i].shape)[0],
        );
        assert!((x0 - x1).abs() < 1e-4, "{x0} {x1}");
    }
}
