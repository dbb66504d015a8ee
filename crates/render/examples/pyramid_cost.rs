//! Calibrates the planner's cost model of the pyramid method and its foveated variant
//! (`planner::calibration::PYRAMID_CPU_MS_PER_MP`, `FOVEATED_BLEND_CPU_MS_PER_MP`): renders sim
//! test scenes at panel sizes and fields, measures each frame's CPU time (the process's user
//! time: on a machine shared with other work it is what the render itself consumed, where wall
//! time is not), and fits `cpu_ms = MP (a + b taps + c spread)` by least squares, `taps` being
//! the exact pass's mean taps per pixel and `spread` the fraction of pixels spread on levels,
//! both from the frame's depth histogram ([`FrameStats`]). Prints every frame and the fit.
//!
//!   cargo run --release -p dioptra-render --example pyramid_cost -- [scenes]

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveated::{foveated, Foveation};
use dioptra_render::planner::{pyramid_features, FrameStats};
use dioptra_render::pyramid::pyramid;
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};

fn cpu_ms() -> f64 {
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: getrusage writes the struct it is given.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    (u.ru_utime.tv_sec as f64 + u.ru_utime.tv_usec as f64 * 1e-6) * 1e3
}

/// Least squares for `y = X b` (normal equations, 3 unknowns).
fn fit(rows: &[([f64; 3], f64)]) -> [f64; 3] {
    let mut a = [[0.0f64; 4]; 3];
    for (x, y) in rows {
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += x[i] * x[j];
            }
            a[i][3] += x[i] * y;
        }
    }
    // Gauss-Jordan.
    for c in 0..3 {
        let p = (c..3)
            .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
            .unwrap_or(c);
        a.swap(c, p);
        let pivot = a[c];
        for (r, row) in a.iter_mut().enumerate() {
            if r != c {
                let f = row[c] / pivot[c];
                for (v, p) in row.iter_mut().zip(pivot).skip(c) {
                    *v -= f * p;
                }
            }
        }
    }
    [a[0][3] / a[0][0], a[1][3] / a[1][1], a[2][3] / a[2][2]]
}

fn main() {
    dioptra_render::alloc::keep_freed_memory();
    let scenes: u64 = std::env::args()
        .nth(1)
        .map_or(3, |s| s.parse().expect("a number"));
    let mut rows = Vec::new();
    let mut fov_rows = Vec::new();
    for (w, h) in [(480usize, 540usize), (960, 1080)] {
        for fov_deg in [20.0f32, 60.0] {
            let eye = EyeModel {
                fov_horizontal_deg: fov_deg,
                ..EyeModel::default()
            };
            let cam = Camera::new(eye, w, h);
            for s in 0..scenes {
                let scene = Scene::generate(Split::Test.seed(s));
                let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).expect("scene");
                let input = Rgbd::new(c, d).expect("rgbd");
                let gaze = [0.5 * w as f32, 0.5 * h as f32];
                for q in [0.3f32, 1.0, 2.5, 4.0] {
                    let stats = FrameStats::from_rgbd(&input, gaze, Diopters(q), &eye);
                    let f = pyramid_features(&stats);
                    let mp = (w * h) as f64 / 1e6;
                    // Best of two: the first pays for page faults of fresh buffers.
                    let mut best = f64::INFINITY;
                    for _ in 0..2 {
                        let t = cpu_ms();
                        std::hint::black_box(pyramid(&input, Diopters(q), &eye).expect("pyramid"));
                        best = best.min(cpu_ms() - t);
                    }
                    println!(
                        "{w}x{h} {fov_deg} deg scene {s} focus {q}: taps {:.1}, spread {:.3}: pyramid {best:.1} CPU ms",
                        f.taps, f.spread
                    );
                    rows.push(([mp, mp * f.taps, mp * f.spread], best));
                    let fov = Foveation::at(gaze);
                    let t = cpu_ms();
                    let out = foveated(&input, Diopters(q), &eye, &fov).expect("foveated");
                    let spent = cpu_ms() - t;
                    println!(
                        "    foveated: {:.0} % of the pixels, {spent:.1} CPU ms",
                        100.0 * out.plan.work_fraction()
                    );
                    fov_rows.push((stats, out.plan, spent));
                }
            }
        }
    }
    let [a, b, c] = fit(&rows);
    println!("pyramid: cpu_ms = MP ({a:.2} + {b:.4} taps + {c:.2} spread)");
    let err: Vec<f64> = rows
        .iter()
        .map(|(x, y)| (a * x[0] + b * x[1] + c * x[2]) / y)
        .collect();
    println!(
        "  predicted / measured: min {:.2}, max {:.2}",
        err.iter().copied().fold(f64::INFINITY, f64::min),
        err.iter().copied().fold(0.0, f64::max)
    );
    // The foveated variant: its layers by the same model, plus a per-megapixel blend.
    let mut extra = Vec::new();
    for (stats, plan, spent) in &fov_rows {
        let layers: f64 = plan
            .layers
            .iter()
            .map(|l| {
                let f = pyramid_features(&stats.scaled(l.level));
                l.pixels as f64 / 1e6 * (a + b * f.taps + c * f.spread)
            })
            .sum();
        let mp = (plan.width * plan.height) as f64 / 1e6;
        extra.push((spent - layers) / mp);
    }
    extra.sort_by(f64::total_cmp);
    println!(
        "foveated blend and downsampling: median {:.2} CPU ms per MP (range {:.2} to {:.2})",
        extra[extra.len() / 2],
        extra[0],
        extra[extra.len() - 1]
    );
}
