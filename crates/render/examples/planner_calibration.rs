//! Measures the planner's calibration table (crates/render/src/planner.rs, `calibration`).
//!
//! cargo run --release -p dioptra-render --example planner_calibration -- [size] [scenes]
//! [samples] (defaults 160 64 512; at most 100 scenes, so the planner tests' seeds from
//! 1 000 200 stay held out). On sim test scenes 1 000 100 onwards (every other one with 6
//! objects instead of 24), gaze at the centre, foci 0.1, 0.5, 1,
//! 2, 3.5 D, the gazed depth and 0.15 D beyond it, and the scene's wall alone focused 0 to
//! 0.7 D from it: the fovea
//! PSNR of no blur, gather and the light-field method (12-48 views) against the thin-lens
//! ground truth with each frame's blur figure; linear multifocal blending into the planner's
//! planes (1-4) and the default four; the CPU time of each; periphery-1 PSNR of log-polar
//! foveation by scale. Prints the table as Rust constants, and every measurement as a
//! `sample,method,blur px,region gradient,PSNR dB` line on stderr.

use dioptra_core::{Diopters, EyeModel, Rgbd};
use dioptra_render::foveate::{interpolate, log_polar_mask, LogPolar};
use dioptra_render::lightfield::lightfield;
use dioptra_render::metrics::{psnr, FovealRegion};
use dioptra_render::multifocal::{linear_blend, DEFAULT_PLANES};
use dioptra_render::planner::calibration::{texture_db, BIN_EDGES_PX, IN_FOCUS_COC_PX};
use dioptra_render::planner::{place_planes, FrameStats, LF_VIEWS};
use dioptra_render::retina::retina_multifocal;
use dioptra_render::{gather::gather, LightFieldParams};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, SceneOptions};
use std::time::Instant;

const NB: usize = BIN_EDGES_PX.len();

fn bin(px: f32) -> usize {
    BIN_EDGES_PX.iter().position(|&e| px < e).unwrap_or(NB - 1)
}

/// Fewest measurements a bin needs to count as measured.
const MIN_SAMPLES: usize = 8;
/// The percentile of a bin's texture-normalised PSNRs its entry takes.
const PERCENTILE: f64 = 0.2;

/// [`PERCENTILE`] per bin of the samples' texture-normalised PSNR. A bin with fewer than
/// [`MIN_SAMPLES`] takes the next measured bin's value to its right (larger blur:
/// conservative), or beyond the last measured bin that value less 3 dB per bin; then the
/// table is made non-increasing.
fn table(samples: &[(f32, f64)]) -> [f64; NB] {
    let mut out = [f64::NAN; NB];
    for (b, o) in out.iter_mut().enumerate() {
        let mut v: Vec<f64> = samples
            .iter()
            .filter(|s| bin(s.0) == b)
            .map(|s| s.1.min(60.0))
            .collect();
        if v.len() < MIN_SAMPLES {
            continue;
        }
        v.sort_by(f64::total_cmp);
        *o = v[((v.len() - 1) as f64 * PERCENTILE) as usize];
    }
    for i in 0..NB {
        if out[i].is_nan() {
            out[i] = match out[i..].iter().find(|v| !v.is_nan()) {
                Some(&v) => v,
                None => {
                    out[..i]
                        .iter()
                        .rev()
                        .find(|v| !v.is_nan())
                        .copied()
                        .unwrap_or(30.0)
                        - 3.0
                }
            };
        }
    }
    for i in 1..NB {
        out[i] = out[i].min(out[i - 1]);
    }
    out.map(|v| (v * 10.0).round() / 10.0)
}

fn counts(samples: &[(f32, f64)]) -> [usize; NB] {
    let mut c = [0; NB];
    for s in samples {
        c[bin(s.0)] += 1;
    }
    c
}

/// Least squares y = a + b x.
fn fit(pts: &[(f64, f64)]) -> (f64, f64) {
    let n = pts.len() as f64;
    let (sx, sy) = pts.iter().fold((0.0, 0.0), |a, p| (a.0 + p.0, a.1 + p.1));
    let (mx, my) = (sx / n, sy / n);
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for p in pts {
        sxy += (p.0 - mx) * (p.1 - my);
        sxx += (p.0 - mx) * (p.0 - mx);
    }
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    (my - b * mx, b)
}

#[path = "../tests/support/fovea_truth.rs"]
mod fovea_truth;
use fovea_truth::{fovea_psnr, truth_crop};

/// The largest distance from the fovea region's content to the nearest plane, as a CoC (px).
fn planes_blur_px(st: &FrameStats, planes: &[Diopters]) -> f32 {
    let worst = st
        .region_histogram
        .mass()
        .map(|(d, _)| {
            planes
                .iter()
                .map(|p| (p.0 - d).abs())
                .fold(f32::INFINITY, f32::min)
        })
        .fold(0.0f32, f32::max);
    st.eye.coc_px(Diopters(worst), Diopters(0.0))
}

/// One measurement as a CSV line on stderr: method, blur figure (px), region gradient,
/// fovea PSNR (dB).
fn sample_line(method: &str, blur: f32, st: &FrameStats, psnr: f64) {
    eprintln!(
        "sample,{method},{blur:.3},{:.6},{psnr:.3}",
        st.region_gradient
    );
}

/// A measurement as the tables hold it: blur figure, PSNR at the reference texture.
fn normalised(method: &str, blur: f32, st: &FrameStats, psnr: f64) -> (f32, f64) {
    sample_line(method, blur, st, psnr);
    (blur, psnr + texture_db(st.region_gradient))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let size = *args.first().unwrap_or(&160);
    let scenes = (*args.get(1).unwrap_or(&64)).min(100) as u64;
    let samples = *args.get(2).unwrap_or(&512) as u32;
    let eye = EyeModel::default().with_width(size as u32);
    let cam = Camera::square(eye, size);
    let mp = (size * size) as f64 / 1e6;
    let s = size as f32;
    let gazes = [[0.5 * s, 0.5 * s], [0.3 * s, 0.35 * s], [0.7 * s, 0.65 * s]];
    let mut none = Vec::new();
    // Pass-through's raw PSNRs, for the in-focus entry.
    let mut none_raw: Vec<(f32, f64)> = Vec::new();
    let mut gath = Vec::new();
    let mut lf: Vec<Vec<(f32, f64)>> = vec![Vec::new(); LF_VIEWS.len()];
    let mut lin = Vec::new();
    let mut t_none = Vec::new();
    let mut t_gather = Vec::new();
    let mut t_lf = Vec::new();
    let mut t_lin = Vec::new();
    let mut periphery: Vec<(f32, Vec<f64>)> = [1.5f32, 2.0, 3.0, 4.0]
        .iter()
        .map(|&k| (k, Vec::new()))
        .collect();
    let t0 = Instant::now();
    for sc in 0..scenes {
        let seed = 1_000_100 + sc;
        // Every other scene sparse (6 objects), so some foveas hold one surface.
        let scene = if sc % 2 == 0 {
            Scene::generate(seed)
        } else {
            Scene::generate_with(
                seed,
                &SceneOptions {
                    objects: 6,
                    ..SceneOptions::default()
                },
            )
        };
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6)?;
        let input = Rgbd::new(color, depth)?;
        // Foveation: interpolation error only, against the full image.
        for g in gazes {
            for (scale, v) in periphery.iter_mut() {
                let p = LogPolar {
                    centre: g,
                    ..LogPolar::centred(size, size, *scale)
                };
                let (mask, _) = log_polar_mask(size, size, &p)?;
                let img = interpolate(&input.color, &mask)?;
                let m = FovealRegion::Periphery1.mask(size, size, g);
                v.push(psnr(&img, &input.color, Some(&m))?);
            }
        }
        // Accuracy is measured at the image centre, where a centred crop of the thin-lens
        // reference (same pixel pitch) can afford many rays; the methods run on the whole frame.
        let g = [0.5 * s, 0.5 * s];
        let gazed = input.depth.at(size / 2, size / 2).unwrap_or(Diopters(1.0));
        let st_any = FrameStats::from_rgbd(&input, g, gazed, &eye);
        for q in [0.1, 0.5, 1.0, 2.0, 3.5, gazed.0, gazed.0 + 0.15].map(Diopters) {
            let truth = truth_crop(&scene, &eye, size, q, samples)?;
            let st = FrameStats::from_rgbd(&input, g, q, &eye);
            let t = Instant::now();
            let passed = input.color.clone();
            t_none.push(t.elapsed().as_secs_f64() * 1e3 / mp);
            let p = fovea_psnr(&passed, &truth, size);
            none_raw.push((st.region_coc_px, p));
            none.push(normalised("none", st.region_coc_px, &st, p));
            let t = Instant::now();
            let g_img = gather(&input, q, &eye)?;
            let r = f64::from(0.5 * st.frame_coc_px);
            t_gather.push((r * r, t.elapsed().as_secs_f64() * 1e3 / mp));
            gath.push(normalised(
                "gather",
                st.region_disparity_px,
                &st,
                fovea_psnr(&g_img, &truth, size),
            ));
            for (k, &views) in LF_VIEWS.iter().enumerate() {
                let t = Instant::now();
                let img = lightfield(&input, q, &eye, LightFieldParams { views, mip: true })?;
                t_lf.push((views as f64, t.elapsed().as_secs_f64() * 1e3 / mp));
                lf[k].push(normalised(
                    &format!("lf{views}"),
                    st.region_disparity_px,
                    &st,
                    fovea_psnr(&img, &truth, size),
                ));
            }
            eprintln!(
                "scene {seed} focus {q}: CoC {:.2} px, disparity {:.2} px; at the reference texture none {:.2}, gather {:.2}, lf-48 {:.2} dB",
                st.region_coc_px,
                st.region_disparity_px,
                none.last().map_or(0.0, |v| v.1),
                gath.last().map_or(0.0, |v| v.1),
                lf[LF_VIEWS.len() - 1].last().map_or(0.0, |v| v.1)
            );
            // Multifocal: the eye focuses on what it looks at.
            if q == gazed {
                let mut sets: Vec<Vec<Diopters>> = (1..=4)
                    .map(|k| place_planes(&st_any, k, (Diopters(0.0), Diopters(4.0))))
                    .collect();
                sets.push(DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect());
                for planes in sets {
                    let t = Instant::now();
                    let layers = linear_blend(&input, &planes)?;
                    t_lin.push((planes.len() as f64, t.elapsed().as_secs_f64() * 1e3 / mp));
                    let seen = retina_multifocal(&layers, &[q], &eye)?.remove(0);
                    let px = planes_blur_px(&st, &planes);
                    let p = fovea_psnr(&seen, &truth, size);
                    // Linear blending is tabled raw (see planner::calibration::PSNR_LINEAR).
                    sample_line("linear", px, &st, p);
                    lin.push((px, p));
                }
            }
        }
        // The same seed's wall alone, focused on it and up to 0.7 D off: foveas with one
        // depth, which the scenes above rarely give (something nearer blurs into them).
        let wall = Scene::generate_with(
            seed,
            &SceneOptions {
                objects: 0,
                ..SceneOptions::default()
            },
        );
        let (color, depth) = render_pinhole(&wall, &cam, [0.0, 0.0], 6)?;
        let input = Rgbd::new(color, depth)?;
        let d_wall = 1.0 / wall.wall_depth;
        for dq in [0.0f32, 0.2, 0.4, 0.7] {
            let q = Diopters(d_wall + dq);
            let truth = truth_crop(&wall, &eye, size, q, samples)?;
            let st = FrameStats::from_rgbd(&input, g, q, &eye);
            let p = fovea_psnr(&input.color, &truth, size);
            none_raw.push((st.region_coc_px, p));
            none.push(normalised("none", st.region_coc_px, &st, p));
            let img = gather(&input, q, &eye)?;
            gath.push(normalised(
                "gather",
                st.region_disparity_px,
                &st,
                fovea_psnr(&img, &truth, size),
            ));
            for (k, &views) in LF_VIEWS.iter().enumerate() {
                let img = lightfield(&input, q, &eye, LightFieldParams { views, mip: true })?;
                lf[k].push(normalised(
                    &format!("lf{views}"),
                    st.region_disparity_px,
                    &st,
                    fovea_psnr(&img, &truth, size),
                ));
            }
            eprintln!(
                "scene {seed} wall only, focus {q}: CoC {:.2} px; at the reference texture none {:.2}, gather {:.2} dB",
                st.region_coc_px,
                none.last().map_or(0.0, |v| v.1),
                gath.last().map_or(0.0, |v| v.1)
            );
        }
        eprintln!("scene {seed} done ({:.0} s)", t0.elapsed().as_secs_f64());
    }
    let show = |name: &str, v: &[(f32, f64)]| {
        println!("// {name}: samples per bin {:?}", counts(v));
        println!("pub const {name}: [f64; {NB}] = {:?};", table(v));
    };
    println!("// measured: {size} px, {scenes} scenes from seed 1000100, {samples} rays/px ground truth, {:.0} s", t0.elapsed().as_secs_f64());
    show("PSNR_NONE", &none);
    let mut in_focus: Vec<f64> = none_raw
        .iter()
        .filter(|s| s.0 < IN_FOCUS_COC_PX)
        .map(|s| s.1)
        .collect();
    in_focus.sort_by(f64::total_cmp);
    if let Some(&v) = in_focus.get(((in_focus.len().max(1) - 1) as f64 * PERCENTILE) as usize) {
        println!(
            "// {} frames with a CoC under {IN_FOCUS_COC_PX} px\npub const PSNR_NONE_IN_FOCUS: f64 = {:.1};",
            in_focus.len(),
            v
        );
    }
    show("PSNR_GATHER", &gath);
    for (k, v) in lf.iter().enumerate() {
        show(&format!("PSNR_LIGHTFIELD_{}", LF_VIEWS[k]), v);
    }
    show("PSNR_LINEAR", &lin);
    let per: Vec<(f32, f64)> = periphery
        .iter()
        .map(|(s, v)| {
            let mut v = v.clone();
            v.sort_by(f64::total_cmp);
            (*s, (v[(v.len() - 1) / 10] * 10.0).round() / 10.0)
        })
        .collect();
    println!("pub const PERIPHERY_BY_SCALE: [(f32, f64); 4] = {per:?};");
    let g = fit(&t_gather);
    let l = fit(&t_lf);
    let n = fit(&t_lin);
    let med = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "pub const GATHER_MS_PER_MP: (f64, f64) = ({:.1}, {:.3});",
        g.0, g.1
    );
    println!(
        "pub const LIGHTFIELD_MS_PER_MP: (f64, f64) = ({:.1}, {:.2});",
        l.0, l.1
    );
    println!("pub const NONE_MS_PER_MP: f64 = {:.2};", med(&mut t_none));
    println!(
        "// linear blending fit a + b planes: ({:.1}, {:.2})",
        n.0, n.1
    );
    println!(
        "pub const LINEAR_MS_PER_MP_PER_PLANE: f64 = {:.2};",
        t_lin.iter().map(|p| p.1 / p.0).sum::<f64>() / t_lin.len().max(1) as f64
    );
    Ok(())
}
