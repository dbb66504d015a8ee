//! GPU against CPU: every GPU kernel on the same random and scene inputs as its CPU twin.
//! Without an adapter each test prints "skipped: no GPU adapter" and returns; with
//! DIOPTRA_REQUIRE_GPU=1 (set by .ci/run) it fails instead. Images are small (64-96 px) so
//! the suite runs in seconds on a software rasteriser.

use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::composite::{composite_stack, step_reach};
use dioptra_render::defocus::PyramidParams;
use dioptra_render::foveate::{log_polar_mask, LogPolar};
use dioptra_render::foveated::{Foveation, FoveationPlan};
use dioptra_render::hybrid::{window_for, HybridParams};
use dioptra_render::metrics::disk_mask;
use dioptra_render::multifocal::{linspace, Layers, DEFAULT_PLANES};
use dioptra_render::retina::LfView;
use dioptra_render::spectral::{SpectralPlan, SpectralReport, SpectralSolver, SpectralTargets};
use dioptra_render::spectral_coarse::scale_for;
use dioptra_render::views::RgbdView;
use dioptra_render::{
    Backend, Cpu, DefocusMethod, Gpu, GpuError, LightFieldParams, OptimizeParams, RenderError,
    SpectralParams,
};
use dioptra_sim::scene::{render_pinhole, Camera, Scene, Split};

fn gpu() -> Option<Gpu> {
    match Gpu::new(None) {
        Ok(g) => Some(g),
        Err(GpuError::NoAdapter) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("skipped: no GPU adapter");
            None
        }
        Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1) or failed to open: {e}"),
    }
}

/// xorshift64*: a fixed-seed generator so the random inputs are the same every run.
struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f32 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 40) as f32) / (1u64 << 24) as f32
    }
}

fn random_image(w: usize, h: usize, seed: u64) -> RgbImage {
    let mut r = Rng(seed);
    let d: Vec<f32> = (0..w * h * 3).map(|_| r.f()).collect();
    RgbImage::from_interleaved(w, h, &d).unwrap()
}

/// Random colour over blocky random depth (0 to 3 D): occlusion edges everywhere.
fn random_rgbd(w: usize, h: usize, seed: u64) -> Rgbd {
    let mut r = Rng(seed ^ 0x9e37_79b9);
    let blocks: Vec<f32> = (0..64).map(|_| 3.0 * r.f()).collect();
    let d: Vec<f32> = (0..w * h)
        .map(|i| blocks[((i % w) / 11 + 8 * ((i / w) / 9)) % 64])
        .collect();
    Rgbd::new(
        random_image(w, h, seed),
        DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
    )
    .unwrap()
}

fn scene_rgbd(size: usize) -> Rgbd {
    let cam = Camera::square(EyeModel::default(), size);
    let scene = Scene::generate(Split::Test.seed(3));
    let (c, d) = render_pinhole(&scene, &cam, [0.0, 0.0], 1).unwrap();
    Rgbd::new(c, d).unwrap()
}

/// Largest absolute difference over pixels and channels, and the fraction above `tol`.
fn diff(a: &RgbImage, b: &RgbImage, tol: f32) -> (f32, f64) {
    assert_eq!((a.width(), a.height()), (b.width(), b.height()));
    let mut max = 0.0f32;
    let mut over = 0usize;
    for c in 0..3 {
        for (x, y) in a.channels[c].data().iter().zip(b.channels[c].data()) {
            let d = (x - y).abs();
            assert!(d.is_finite(), "non-finite value: {x} vs {y}");
            max = max.max(d);
            over += (d > tol) as usize;
        }
    }
    (max, over as f64 / (3 * a.width() * a.height()) as f64)
}

fn inputs() -> Vec<(&'static str, Rgbd)> {
    vec![
        ("random 80x64", random_rgbd(80, 64, 7)),
        ("scene 96x96", scene_rgbd(96)),
    ]
}

/// The inputs under the default eye, and the scene under a 3 degree field.
fn cases() -> Vec<(&'static str, Rgbd, EyeModel)> {
    let narrow = EyeModel {
        fov_horizontal_deg: 3.0,
        ..EyeModel::default()
    };
    let mut v: Vec<_> = inputs()
        .into_iter()
        .map(|(n, i)| (n, i, EyeModel::default()))
        .collect();
    v.push(("scene 96x96, 3 degree field", scene_rgbd(96), narrow));
    v
}

#[test]
fn gather_matches_cpu() {
    let Some(g) = gpu() else { return };
    // Below 0 D too: the eye focused beyond optical infinity.
    let foci = [Diopters(-0.8), Diopters(0.3), Diopters(1.7)];
    // The default 20 degree field (blur of a few pixels at this size) and a 3 degree one
    // (blur of up to ~25 pixels: long tap lists, the max filter's reach).
    for (name, input, eye) in cases() {
        let c = Cpu.defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {});
        let q = g.defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {});
        for (a, b) in c.unwrap().iter().zip(&q.unwrap()) {
            let (max, _) = diff(a, b, 1e-3);
            eprintln!("gather {name}: max |gpu - cpu| = {max:e}");
            assert!(max < 1e-3, "gather {name}: {max}");
        }
    }
    let s = g.last_stats();
    assert_eq!(s.submissions, 3, "one submission per focus");
    assert_eq!(
        s.dispatches, 12,
        "prep, two max passes and the gather, per focus"
    );
}

#[test]
fn linear_blend_matches_cpu() {
    let Some(g) = gpu() else { return };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    for (name, input) in inputs() {
        let c = Cpu.linear_blend(&input, &planes).unwrap();
        let q = g.linear_blend(&input, &planes).unwrap();
        assert_eq!(c.planes, q.planes);
        for (a, b) in c.images.iter().zip(&q.images) {
            let (max, _) = diff(a, b, 1e-3);
            eprintln!("linear {name}: max |gpu - cpu| = {max:e}");
            assert!(max < 1e-5, "linear {name}: {max}");
        }
    }
    assert!(g
        .linear_blend(&inputs()[0].1, &[Diopters(1.0), Diopters(0.5)])
        .is_err());
}

#[test]
fn retina_varifocal_and_multifocal_match_cpu() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let img = random_image(72, 64, 11);
    for (display, focus) in [(1.0, 1.0), (2.5, 0.5), (0.2, 1.9)] {
        let c = Cpu
            .retina_varifocal(&img, Diopters(display), Diopters(focus), &eye)
            .unwrap();
        let q = g
            .retina_varifocal(&img, Diopters(display), Diopters(focus), &eye)
            .unwrap();
        let (max, _) = diff(&c, &q, 1e-3);
        eprintln!("retina varifocal {display}->{focus} D: max |gpu - cpu| = {max:e}");
        assert!(max < 1e-3, "{max}");
    }
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let layers = Layers {
        planes: planes.clone(),
        images: (0..4).map(|i| random_image(72, 64, 20 + i)).collect(),
    };
    let foci = linspace(0.1, 2.2, 5);
    let c = Cpu.retina_multifocal(&layers, &foci, &eye).unwrap();
    let q = g.retina_multifocal(&layers, &foci, &eye).unwrap();
    assert_eq!(c.len(), q.len());
    for (a, b) in c.iter().zip(&q) {
        let (max, _) = diff(a, b, 1e-3);
        eprintln!("retina multifocal: max |gpu - cpu| = {max:e}");
        assert!(max < 1e-3, "{max}");
    }
    assert_eq!(g.last_stats().dispatches, 1, "every focus in one dispatch");
    let bad = Layers {
        planes,
        images: vec![random_image(72, 64, 1)],
    };
    assert!(g.retina_multifocal(&bad, &foci, &eye).is_err());
}

#[test]
fn retina_lightfield_matches_cpu() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let (grid, span) = (5usize, 0.004f32);
    let step = span / (grid - 1) as f32;
    let views: Vec<LfView> = (0..grid * grid)
        .map(|k| LfView {
            position: [
                ((k % grid) as f32 - 2.0) * step,
                ((k / grid) as f32 - 2.0) * step,
            ],
            image: random_image(64, 48, 100 + k as u64),
        })
        .collect();
    for q in [0.0, 0.7, 2.0] {
        let c = Cpu
            .retina_lightfield(&views, step, Diopters(q), &eye)
            .unwrap();
        let r = g
            .retina_lightfield(&views, step, Diopters(q), &eye)
            .unwrap();
        let (max, _) = diff(&c, &r, 1e-3);
        eprintln!("retina lightfield {q} D: max |gpu - cpu| = {max:e}");
        assert!(max < 1e-3, "{max}");
    }
    assert!(g
        .retina_lightfield(&views, f32::NAN, Diopters(1.0), &eye)
        .is_err());
}

#[test]
fn psnr_and_ssim_match_cpu() {
    let Some(g) = gpu() else { return };
    let a = random_image(70, 52, 5);
    let mut b = a.clone();
    for (i, v) in b.channels[1].data_mut().iter_mut().enumerate() {
        *v = (*v + 0.05 * ((i % 7) as f32 - 3.0)).clamp(0.0, 1.0);
    }
    let fovea = disk_mask(70, 52, [30.0, 20.0], 15.0);
    for mask in [None, Some(&fovea)] {
        let c = Cpu.quality(&a, &b, mask).unwrap();
        let q = g.quality(&a, &b, mask).unwrap();
        eprintln!(
            "quality: psnr cpu {} gpu {} (diff {:e}); ssim cpu {} gpu {} (diff {:e})",
            c.psnr,
            q.psnr,
            (c.psnr - q.psnr).abs(),
            c.ssim,
            q.ssim,
            (c.ssim - q.ssim).abs()
        );
        assert!((c.psnr - q.psnr).abs() < 1e-3, "{c:?} {q:?}");
        assert!((c.ssim - q.ssim).abs() < 1e-5, "{c:?} {q:?}");
    }
    let same = g.quality(&a, &a, None).unwrap();
    assert_eq!(same.psnr, f64::INFINITY);
    assert!((same.ssim - 1.0).abs() < 1e-5);
    assert!(g.quality(&a, &random_image(69, 52, 1), None).is_err());
}

#[test]
fn lightfield_defocus_and_focal_stack_match_cpu() {
    let Some(g) = gpu() else { return };
    let foci = linspace(-0.9, 3.1, 3);
    for (name, input, eye) in cases() {
        for views in [12, 36] {
            let m = DefocusMethod::LightField(LightFieldParams { views, mip: true });
            let c = Cpu.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
            let q = g.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
            for (k, (a, b)) in c.iter().zip(&q).enumerate() {
                let (max, frac) = diff(a, b, 1e-3);
                eprintln!(
                    "lightfield {name} {views} views focus {:.2} D: max |gpu - cpu| = {max:e}, {:.4} % of values over 1e-3",
                    foci[k].0,
                    frac * 100.0
                );
                // Same keys, same order of views per pixel: only float rounding differs. A
                // splat target computed one ulp apart can move a source by one pixel; allow
                // that on at most 0.1 % of values.
                assert!(frac <= 1e-3, "lightfield {name}: {frac}");
            }
        }
    }
}

#[test]
fn optimized_blend_matches_cpu() {
    let Some(g) = gpu() else { return };
    // A 4 degree field over 48 px: disks up to ~9 px across (software rasterisers take
    // seconds per direct-convolution iteration beyond that).
    let eye = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let foci = linspace(0.1, 2.2, 6);
    let input = random_rgbd(48, 40, 9);
    let targets = Cpu
        .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
        .unwrap();
    let linear = Cpu.linear_blend(&input, &planes).unwrap();
    for (init, iterations) in [(None, 20), (Some(&linear), 12)] {
        let params = OptimizeParams {
            iterations,
            tolerance: 0.0,
        };
        let (cl, cr) = Cpu
            .optimized_blend(&targets, &foci, &planes, &eye, init, params, &|_| {})
            .unwrap();
        let done = std::sync::atomic::AtomicUsize::new(0);
        let (gl, gr) = g
            .optimized_blend(&targets, &foci, &planes, &eye, init, params, &|n| {
                done.store(n, std::sync::atomic::Ordering::SeqCst)
            })
            .unwrap();
        assert_eq!(done.into_inner(), iterations);
        assert_eq!(cr.iterations, gr.iterations);
        assert_eq!(cr.rms.len(), gr.rms.len());
        for ((ci, c), (gi, q)) in cr.rms.iter().zip(&gr.rms) {
            assert_eq!(ci, gi);
            assert!(
                (c - q).abs() <= 1e-3 * c.max(1e-6),
                "rms at {ci}: {c} vs {q}"
            );
        }
        // The objective must really fall, on both.
        assert!(gr.rms.last().unwrap().1 < 0.9 * gr.rms[0].1, "{:?}", gr.rms);
        for (a, b) in cl.images.iter().zip(&gl.images) {
            let (max, _) = diff(a, b, 1e-3);
            eprintln!(
                "optimized ({iterations} iterations, init {}): max |gpu - cpu| = {max:e}",
                if init.is_some() { "linear" } else { "mean" }
            );
            // FFT (CPU) against direct sums (GPU): rounding differs by ~1e-6 per product
            // and FISTA carries it through the iterations.
            assert!(max < 1e-3, "{max}");
        }
    }
    let s = g.last_stats();
    // 12 iterations: 2 RMS samples (0, 10) and 2 blocks of steps, then the final RMS.
    assert_eq!(s.submissions, 5, "{s:?}");
}

#[test]
fn view_synthesis_matches_cpu() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let size = 64;
    let cam = Camera::square(eye, size);
    let scene = Scene::generate(Split::Test.seed(5));
    let span = 0.01f32;
    // Five inputs (corners and centre) of a 3 x 3 grid over 1 cm, synthesised back to 3 x 3.
    let inputs: Vec<RgbdView> = [(0, 0), (0, 2), (1, 1), (2, 0), (2, 2)]
        .iter()
        .map(|&(r, c)| {
            let position = [(c as f32 - 1.0) * span / 2.0, (r as f32 - 1.0) * span / 2.0];
            let (color, depth) = render_pinhole(&scene, &cam, position, 1).unwrap();
            RgbdView {
                position,
                rgbd: Rgbd::new(color, depth).unwrap(),
            }
        })
        .collect();
    let c = Cpu
        .synthesize_light_field(&inputs, 3, span, &eye, &|_| {})
        .unwrap();
    let q = g
        .synthesize_light_field(&inputs, 3, span, &eye, &|_| {})
        .unwrap();
    assert_eq!(c.len(), 9);
    for (a, b) in c.iter().zip(&q) {
        assert_eq!(a.position, b.position);
        let (max, frac) = diff(&a.image, &b.image, 1e-3);
        eprintln!(
            "view synthesis at {:?}: max |gpu - cpu| = {max:e}, {:.4} % over 1e-3",
            a.position,
            frac * 100.0
        );
        assert!(max < 1e-3, "{max}");
    }
    assert_eq!(g.last_stats().submissions, 9, "one submission per view");
    assert!(g
        .synthesize_light_field(&inputs, 0, span, &eye, &|_| {})
        .is_err());
}

/// One RGB-D with occlusion edges everywhere, synthesised at each eye of a stereo rig (31.5 mm
/// aside, and up and down as far): wide disocclusions, where the crack fills that land on no
/// pixel of their surface are dropped and holes are filled from beyond the edge pixels.
#[test]
fn view_synthesis_across_wide_disocclusions_matches_cpu() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let inputs = [RgbdView {
        position: [0.0, 0.0],
        rgbd: random_rgbd(96, 64, 11),
    }];
    let span = 0.063f32;
    let c = Cpu
        .synthesize_light_field(&inputs, 3, span, &eye, &|_| {})
        .unwrap();
    let q = g
        .synthesize_light_field(&inputs, 3, span, &eye, &|_| {})
        .unwrap();
    for (a, b) in c.iter().zip(&q) {
        let (max, frac) = diff(&a.image, &b.image, 1e-3);
        eprintln!(
            "wide view synthesis at {:?}: max |gpu - cpu| = {max:e}, {:.4} % over 1e-3",
            a.position,
            frac * 100.0
        );
        assert!(max < 1e-3, "{max}");
    }
}

/// Each eye's RGB-D of a stereo rig synthesised from one RGB-D on the GPU and left there (the
/// rig's eye views): colour within 1e-3 of the CPU's `synthesize_rgbd_view`, depth the same,
/// both eyes from one upload in one submission; each method's render from the view in GPU
/// memory the same as from its copy on the host.
#[test]
fn rgbd_views_made_in_gpu_memory_match_cpu_and_render_as_their_copies() {
    use dioptra_render::views::synthesize_rgbd_view;
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let inputs = [RgbdView {
        position: [0.0, 0.0],
        rgbd: random_rgbd(96, 64, 11),
    }];
    let targets = [[-0.0315, 0.0], [0.0315, 0.0]];
    let on_gpu = g
        .synthesize_rgbd_views_on_gpu(&inputs, &targets, &eye)
        .unwrap();
    assert_eq!(g.last_stats().submissions, 1, "both eyes in one submission");
    let input_bytes = (16 * 96 * 64) as u64;
    let uploaded = g.last_stats().bytes_uploaded;
    assert!(
        (input_bytes..2 * input_bytes).contains(&uploaded),
        "the input uploaded once: {uploaded} bytes"
    );
    assert_eq!(g.images_read_back(), 0);
    for (view, &t) in on_gpu.iter().zip(&targets) {
        let cpu = synthesize_rgbd_view(&inputs, t, &eye).unwrap();
        let host = view.read().unwrap();
        let (max, frac) = diff(&cpu.color, &host.color, 1e-3);
        eprintln!(
            "RGB-D view at {t:?}: max |gpu - cpu| = {max:e}, {:.4} % over 1e-3",
            frac * 100.0
        );
        assert!(max < 1e-3, "{max}");
        assert_eq!(cpu.depth, host.depth, "depth at {t:?}");
        // Uploaded, it reads back as it was, its depth bound its own range.
        let uploaded = g.upload_rgbd(&host).unwrap();
        assert_eq!(uploaded.read().unwrap(), host);
        assert_eq!(Some(uploaded.depth_bound()), host.depth.range());
        let (lo, hi) = view.depth_bound();
        let (dlo, dhi) = host.depth.range().unwrap();
        assert!(
            lo.0 <= dlo.0 && dhi.0 <= hi.0,
            "{lo:?}..{hi:?} holds {dlo:?}..{dhi:?}"
        );
        // Every method that takes an input in GPU memory renders it as its host copy.
        let methods = [
            DefocusMethod::Gather,
            DefocusMethod::Pyramid(PyramidParams::default()),
            DefocusMethod::LightField(LightFieldParams {
                views: 16,
                mip: true,
            }),
        ];
        for m in methods {
            let a = g.defocus_on_gpu(view, Diopters(1.5), &eye, m).unwrap();
            let b = g.defocus_on_gpu(&host, Diopters(1.5), &eye, m).unwrap();
            let (max, _) = diff(&a.read().unwrap(), &b.read().unwrap(), 1e-5);
            assert!(max < 1e-5, "{m:?}: {max}");
        }
        let planes = [Diopters(0.2), Diopters(1.4), Diopters(2.6)];
        let a = g.linear_blend_on_gpu(view, &planes).unwrap();
        let b = g.linear_blend_on_gpu(&host, &planes).unwrap();
        for (a, b) in a.iter().zip(&b) {
            assert_eq!(a.read().unwrap(), b.read().unwrap(), "linear blending");
        }
    }
    assert!(g
        .synthesize_rgbd_views_on_gpu(&inputs, &[[f32::NAN, 0.0]], &eye)
        .is_err());
    assert!(g.synthesize_rgbd_views_on_gpu(&[], &targets, &eye).is_err());
}

#[test]
fn bad_input_is_an_error() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel::default();
    let input = random_rgbd(16, 16, 3);
    for q in [f32::NAN, 2000.0, -2000.0] {
        assert!(g
            .defocus(&input, &[Diopters(q)], &eye, DefocusMethod::Gather, &|_| {})
            .is_err());
    }
    let bad = LightFieldParams {
        views: 0,
        mip: true,
    };
    assert!(g
        .defocus(
            &input,
            &[Diopters(1.0)],
            &eye,
            DefocusMethod::LightField(bad),
            &|_| {}
        )
        .is_err());
    // An adapter name that matches nothing is an error naming what exists.
    let e = Gpu::new(Some("no-such-adapter-xyz"))
        .err()
        .expect("no match");
    assert!(
        matches!(
            e,
            GpuError::AdapterAlreadyChosen { .. } | GpuError::AdapterNotFound { .. }
        ),
        "{e}"
    );
}

/// Log-polar masks of a `w` x `h` image: centred at S = 2 and 4, off-centre with K and
/// per-view offsets, and a sparse random mask (many equidistant samples: the tie rule).
fn foveation_masks(w: usize, h: usize) -> Vec<(&'static str, Plane)> {
    let lp = |p: &LogPolar| log_polar_mask(w, h, p).unwrap().0;
    let mut r = Rng(99);
    let random: Vec<f32> = (0..w * h)
        .map(|_| if r.f() < 0.02 { 1.0 } else { 0.0 })
        .collect();
    vec![
        ("S=2 centred", lp(&LogPolar::centred(w, h, 2.0))),
        ("S=4 centred", lp(&LogPolar::centred(w, h, 4.0))),
        (
            "S=3 gaze (10,40), K=1.5, offsets",
            lp(&LogPolar {
                centre: [10.0, 40.0],
                scale: 3.0,
                kernel: 1.5,
                r_offset: 1.2,
                theta_offset: 0.4,
            }),
        ),
        ("2 % random", Plane::from_vec(w, h, random).unwrap()),
    ]
}

#[test]
fn foveated_interpolation_matches_cpu_on_the_same_mask() {
    let Some(g) = gpu() else { return };
    let (w, h) = (72, 56);
    let img = random_image(w, h, 21);
    for (name, mask) in foveation_masks(w, h) {
        let c = Cpu.foveate_interpolate(&img, &mask).unwrap();
        let q = g.foveate_interpolate(&img, &mask).unwrap();
        // Same four samples (same visiting order, same tie rule, exact integer distances);
        // only the 1 / d weights' rounding differs.
        let (max, _) = diff(&c, &q, 1e-4);
        eprintln!("foveate interpolation {name}: max |gpu - cpu| = {max:e}");
        assert!(max < 1e-4, "foveate interpolation {name}: {max}");
    }
    let s = g.last_stats();
    assert_eq!(
        (s.submissions, s.dispatches),
        (1, 2),
        "cells and interpolation in one submission"
    );
    assert!(g.foveate_interpolate(&img, &Plane::new(w, h, 0.0)).is_err());
    assert!(g
        .foveate_interpolate(&img, &Plane::new(w + 1, h, 1.0))
        .is_err());
}

#[test]
fn foveated_sampling_matches_cpu() {
    let Some(g) = gpu() else { return };
    let (w, h) = (80, 64);
    let img = scene_rgbd(96).color;
    let img = RgbImage::from_planes(
        crop(&img.channels[0], w, h),
        crop(&img.channels[1], w, h),
        crop(&img.channels[2], w, h),
    )
    .unwrap();
    for p in [
        LogPolar::centred(w, h, 2.0),
        LogPolar {
            centre: [60.0, 12.5],
            scale: 4.0,
            kernel: 1.3,
            r_offset: 1.1,
            theta_offset: 0.25,
        },
    ] {
        let c = Cpu.foveate(&img, &p).unwrap();
        let q = g.foveate(&img, &p).unwrap();
        // The host computes the transcendental tables exactly as the CPU does; the GPU only
        // does centre + rho * cos (which it may fuse into one FMA: a 1-ulp difference that
        // moves a sample only if it lies within 1 ulp of a pixel edge).
        let moved = c
            .mask
            .data()
            .iter()
            .zip(q.mask.data())
            .filter(|(a, b)| a != b)
            .count();
        eprintln!(
            "foveate {p:?}: {moved} mask pixels differ; sampled {:.3} % (cpu {:.3} %)",
            q.fraction * 100.0,
            c.fraction * 100.0
        );
        assert!(moved <= 2, "{moved} mask pixels differ");
        // The image is the interpolation of the GPU's own mask.
        let want = Cpu.foveate_interpolate(&img, &q.mask).unwrap();
        let (max, _) = diff(&want, &q.image, 1e-4);
        assert!(max < 1e-4, "foveate {p:?}: {max}");
    }
    let s = g.last_stats();
    assert_eq!((s.submissions, s.dispatches), (1, 3));
    let bad = LogPolar {
        scale: 0.0,
        ..LogPolar::centred(w, h, 2.0)
    };
    assert!(g.foveate(&img, &bad).is_err());
}

fn crop(p: &Plane, w: usize, h: usize) -> Plane {
    let d: Vec<f32> = (0..w * h)
        .map(|i| p.data()[(i / w) * p.width() + i % w])
        .collect();
    Plane::from_vec(w, h, d).unwrap()
}

/// The methods' images left in GPU memory are the images the same kernels read back, and
/// only reading one back copies it to the host (counted once per image).
#[test]
fn images_kept_on_the_gpu_read_back_as_the_readback_path_gives_them() {
    let Some(g) = gpu() else { return };
    let eye = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let input = random_rgbd(40, 32, 21);
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let reads = || g.images_read_back();
    let before = reads();
    let q = Diopters(1.3);
    for method in [
        DefocusMethod::Gather,
        DefocusMethod::LightField(LightFieldParams {
            views: 12,
            mip: true,
        }),
    ] {
        let n = reads();
        let kept = g.defocus_on_gpu(&input, q, &eye, method).unwrap();
        assert_eq!((kept.width(), kept.height()), (40, 32));
        assert_eq!(reads(), n, "{method:?}: nothing read back yet");
        let read = g.defocus(&input, &[q], &eye, method, &|_| {}).unwrap();
        assert_eq!(kept.read().unwrap(), read[0], "{method:?}");
    }
    let kept = g.linear_blend_on_gpu(&input, &planes).unwrap();
    let read = g.linear_blend(&input, &planes).unwrap();
    assert_eq!(kept.len(), planes.len());
    for (k, r) in kept.iter().zip(&read.images) {
        assert_eq!(&k.read().unwrap(), r);
    }
    let foci = linspace(0.1, 2.2, 4);
    let targets = Cpu
        .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
        .unwrap();
    let params = OptimizeParams {
        iterations: 5,
        tolerance: 0.0,
    };
    let (kept, _) = g
        .optimized_blend_on_gpu(&targets, &foci, &planes, &eye, None, params)
        .unwrap();
    let (read, _) = g
        .optimized_blend(&targets, &foci, &planes, &eye, None, params, &|_| {})
        .unwrap();
    for (k, r) in kept.iter().zip(&read.images) {
        assert_eq!(&k.read().unwrap(), r);
    }
    assert_eq!(reads(), before + 2 + 2 * planes.len() as u64);
}

/// Largest difference between two decompositions' layers.
fn layers_diff(a: &Layers, b: &Layers) -> f32 {
    assert_eq!(a.planes, b.planes);
    assert_eq!(a.images.len(), b.images.len());
    a.images
        .iter()
        .zip(&b.images)
        .map(|(x, y)| diff(x, y, 1e-3).0)
        .fold(0.0, f32::max)
}

fn same_report(c: &SpectralReport, q: &SpectralReport, what: &str) {
    assert_eq!(c.iterations, q.iterations, "{what}: {c:?} {q:?}");
    assert_eq!(c.refined, q.refined, "{what}: {c:?} {q:?}");
    for (x, y) in [
        (c.objective_clamped, q.objective_clamped),
        (c.objective_final, q.objective_final),
    ] {
        assert_eq!(x.is_nan(), y.is_nan(), "{what}: {c:?} {q:?}");
        if !x.is_nan() {
            assert!(
                (x - y).abs() <= 1e-3 * x.abs().max(1e-9),
                "{what}: {c:?} {q:?}"
            );
        }
    }
}

/// Issue 42: the spectral decomposition on the GPU (WGSL Stockham FFTs on the CPU's padded
/// grid, the plan's matrices resident) against the CPU's (realfft), whole: targets, solve,
/// clamp and projected steps. Targets rendered by gather (itself within 1e-3 of the CPU's) and
/// depth slices; padded grids of 2, 3 and 5 as factors.
#[test]
fn spectral_blend_matches_cpu() {
    let Some(g) = gpu() else { return };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let narrow = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let cases = [
        ("random 80x64", random_rgbd(80, 64, 7), EyeModel::default()),
        (
            "random 61x47, 4 degree field",
            random_rgbd(61, 47, 3),
            narrow,
        ),
        ("scene 96x96, 4 degree field", scene_rgbd(96), narrow),
    ];
    let mut factors = std::collections::BTreeSet::new();
    for (name, input, eye) in &cases {
        let plan = SpectralPlan::new(
            eye,
            &planes,
            input.width(),
            input.height(),
            SpectralParams::default(),
        )
        .unwrap();
        let (pw, ph) = plan.grid();
        eprintln!("spectral {name}: FFT grid {pw}x{ph}");
        for n in [pw, ph] {
            factors.extend([2, 3, 5].into_iter().filter(|f| n % f == 0));
        }
        for targets in [
            SpectralTargets::Defocus(DefocusMethod::Gather),
            SpectralTargets::Slices,
        ] {
            for (solver, iterations) in [
                (SpectralSolver::ProjectedGradient, 0),
                (SpectralSolver::ProjectedGradient, 5),
                (SpectralSolver::Admm { rho: 0.3 }, 3),
            ] {
                // Full resolution: the FFT grids above (the coarse grid is checked in
                // spectral_defaults_match_cpu).
                let params = SpectralParams {
                    targets,
                    iterations,
                    solver,
                    scale: 1,
                    ..SpectralParams::default()
                };
                let (cl, cr) = Cpu.spectral_blend(input, &planes, eye, params).unwrap();
                let (gl, gr) = g.spectral_blend(input, &planes, eye, params).unwrap();
                let max = layers_diff(&cl, &gl);
                let what = format!("{name}, {targets:?}, {solver:?}, {iterations} steps");
                eprintln!("spectral {what}: max |gpu - cpu| = {max:e}; {gr:?}");
                assert!(max < 1e-3, "spectral {what}: {max}");
                same_report(&cr, &gr, &what);
                if iterations > 0 {
                    assert!(gr.objective_final.is_finite(), "{what}: {gr:?}");
                }
                let s = g.last_stats();
                assert!(s.dispatches > 0, "{what}: {s:?}");
            }
        }
    }
    assert_eq!(
        factors.len(),
        3,
        "the grids' factors {factors:?}: every radix tried"
    );
}

/// The default settings (a composite stack: the 12-view light field where a blurred depth step
/// reaches, the smooth disk blur elsewhere): the solve from one given stack on both (the GPU's
/// and the CPU's light fields differ by a pixel at a few splat edges, see
/// lightfield_defocus_and_focal_stack_match_cpu), then the whole default on the GPU, seen
/// through the retina; on a scene without a depth step (no light field in its stack) the
/// whole default agrees within 1e-3.
#[test]
fn spectral_defaults_match_cpu() {
    let Some(g) = gpu() else { return };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let eye = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let input = scene_rgbd(96);
    // At full resolution (this eye's blur would have the default solve a 1/2 grid: below).
    let params = SpectralParams {
        scale: 1,
        ..SpectralParams::default()
    };
    let SpectralTargets::Composite(lf) = params.targets else {
        panic!(
            "the default targets are the composite: {:?}",
            params.targets
        )
    };
    let stack = composite_stack(&input, &params.foci(), &eye, lf).unwrap();
    let plan = SpectralPlan::new(&eye, &planes, 96, 96, params).unwrap();
    let (cl, cr) = plan
        .solve(&plan.targets_stack(&input, &stack).unwrap())
        .unwrap();
    let (gl, gr) = g
        .spectral_blend_stack(&input, &stack, &planes, &eye, params)
        .unwrap();
    let max = layers_diff(&cl, &gl);
    eprintln!("spectral defaults from one stack: max |gpu - cpu| = {max:e}; {gr:?}");
    assert!(max < 1e-3, "{max}");
    same_report(&cr, &gr, "defaults from one stack");
    assert!(gr.refined, "{gr:?}");
    // Whole, its stack rendered on the GPU: what the eye sees of the two agrees.
    let (whole, _) = g.spectral_blend(&input, &planes, &eye, params).unwrap();
    let foci = linspace(0.1, 2.2, 4);
    let a = Cpu.retina_multifocal(&cl, &foci, &eye).unwrap();
    let b = Cpu.retina_multifocal(&whole, &foci, &eye).unwrap();
    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
        let p = dioptra_render::metrics::psnr(x, y, None).unwrap();
        eprintln!(
            "spectral defaults whole on the GPU: focus {:.2} D, {p:.1} dB from the CPU's",
            foci[k].0
        );
        assert!(p > 50.0, "focus {}: {p} dB", foci[k].0);
    }
    // Kept in GPU memory, the same layers.
    let (kept, _) = g
        .spectral_blend_on_gpu(&input, &planes, &eye, params)
        .unwrap();
    assert_eq!(kept.len(), planes.len());
    for (k, img) in kept.iter().zip(&whole.images) {
        assert_eq!(&k.read().unwrap(), img);
    }
    // A smooth scene (a slanted plane, 0.3 to 1.9 D): no depth step blurs, so the composite
    // is the smooth disk blur alone on both and the whole default agrees within 1e-3.
    let (w, h) = (96, 80);
    let slanted = Rgbd::new(
        random_image(w, h, 11),
        DepthMap::from_diopters(
            Plane::from_vec(
                w,
                h,
                (0..w * h)
                    .map(|i| 0.3 + 1.6 * (i % w) as f32 / w as f32)
                    .collect(),
            )
            .unwrap(),
        )
        .unwrap(),
    )
    .unwrap();
    assert!(params
        .foci()
        .iter()
        .all(|&q| !step_reach(&slanted.depth, q, &eye, 0.0)
            .unwrap()
            .reached
            .contains(&true)));
    let (cl, cr) = Cpu.spectral_blend(&slanted, &planes, &eye, params).unwrap();
    let (gl, gr) = g.spectral_blend(&slanted, &planes, &eye, params).unwrap();
    let max = layers_diff(&cl, &gl);
    eprintln!("spectral defaults on a slanted plane: max |gpu - cpu| = {max:e}; {gr:?}");
    assert!(max < 1e-3, "{max}");
    same_report(&cr, &gr, "defaults on a slanted plane");
    // The default's own grid (1/2 here, chosen from the blur) plus linear detail: the same
    // on both, kept in GPU memory too.
    let coarse = SpectralParams::default();
    assert_eq!(
        scale_for(&eye, &planes, w, coarse.scale, coarse.focal_range).unwrap(),
        2
    );
    let (cl, cr) = Cpu.spectral_blend(&slanted, &planes, &eye, coarse).unwrap();
    let (gl, gr) = g.spectral_blend(&slanted, &planes, &eye, coarse).unwrap();
    let max = layers_diff(&cl, &gl);
    eprintln!("spectral defaults on a 1/2 grid: max |gpu - cpu| = {max:e}; {gr:?}");
    assert!(max < 1e-3, "{max}");
    same_report(&cr, &gr, "defaults on a 1/2 grid");
    let (kept, _) = g
        .spectral_blend_on_gpu(&slanted, &planes, &eye, coarse)
        .unwrap();
    for (k, img) in kept.iter().zip(&gl.images) {
        assert_eq!(&k.read().unwrap(), img);
    }
}

/// The gaze-contingent hybrid: the window's spectral solve on the GPU, the rest as the CPU's.
/// Gather targets (the GPU's gather is within 1e-3 of the CPU's; the default's light field
/// differs by a pixel at a few splat edges, as above), full resolution and a coarse grid,
/// the gaze in the middle, at a corner (the window shifted inside the image) and on a scene
/// with no depth step near the gaze (linear blending on both, the spectral solve not run).
#[test]
fn hybrid_blend_matches_cpu() {
    let Some(g) = gpu() else { return };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let eye = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let input = scene_rgbd(96);
    for scale in [1, 2] {
        for gaze in [None, Some([5.0, 90.0])] {
            let params = HybridParams {
                fovea_deg: 0.5,
                blend_deg: 0.2,
                scale,
                edges_only: false,
                spectral: SpectralParams {
                    targets: SpectralTargets::Defocus(DefocusMethod::Gather),
                    ..HybridParams::default().spectral
                },
            };
            let (cl, cr) = Cpu
                .hybrid_blend(&input, &planes, &eye, gaze, &params)
                .unwrap();
            let (gl, gr) = g
                .hybrid_blend(&input, &planes, &eye, gaze, &params)
                .unwrap();
            let what = format!("hybrid scale {scale}, gaze {gaze:?}");
            let max = layers_diff(&cl, &gl);
            eprintln!("{what}: max |gpu - cpu| = {max:e}; {gr:?}");
            assert!(max < 1e-3, "{what}: {max}");
            assert_eq!(cr.window, gr.window, "{what}");
            let win = cr.window.expect("edges_only is off: the window is solved");
            assert_eq!(win.scale, scale, "{what}");
            same_report(
                cr.spectral.as_ref().unwrap(),
                gr.spectral.as_ref().unwrap(),
                &what,
            );
        }
    }
    // Flat depth: no step reaches the fovea, so both give linear blending exactly.
    let flat = Rgbd::new(
        random_image(64, 48, 5),
        DepthMap::from_diopters(Plane::new(64, 48, 1.1)).unwrap(),
    )
    .unwrap();
    let params = HybridParams::default();
    let (cl, cr) = Cpu
        .hybrid_blend(&flat, &planes, &eye, None, &params)
        .unwrap();
    let (gl, gr) = g.hybrid_blend(&flat, &planes, &eye, None, &params).unwrap();
    assert_eq!((cr.window, gr.window), (None, None));
    assert_eq!(cl, Cpu.linear_blend(&flat, &planes).unwrap());
    assert!(layers_diff(&cl, &gl) < 1e-3);
    let w = window_for(64, 48, &eye.with_width(64), &planes, [32.0, 24.0], &params).unwrap();
    assert!(w.width <= 64 && w.height <= 48, "{w:?}");
}

#[test]
fn spectral_bad_input_is_an_error() {
    let Some(g) = gpu() else { return };
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let eye = EyeModel::default();
    let input = random_rgbd(40, 32, 5);
    let normalized = SpectralParams {
        targets: SpectralTargets::NormalizedSlices,
        ..SpectralParams::default()
    };
    assert!(matches!(
        g.spectral_blend(&input, &planes, &eye, normalized),
        Err(RenderError::Unsupported { backend: "gpu", .. })
    ));
    let params = SpectralParams::default();
    let short = vec![random_image(40, 32, 1); params.focal_samples - 1];
    assert!(g
        .spectral_blend_stack(&input, &short, &planes, &eye, params)
        .is_err());
    let wrong_size = vec![random_image(41, 32, 1); params.focal_samples];
    assert!(g
        .spectral_blend_stack(&input, &wrong_size, &planes, &eye, params)
        .is_err());
    let slices = SpectralParams {
        targets: SpectralTargets::Slices,
        ..params
    };
    let stack = vec![random_image(40, 32, 1); params.focal_samples];
    assert!(g
        .spectral_blend_stack(&input, &stack, &planes, &eye, slices)
        .is_err());
    let bad = SpectralParams {
        prior: 0.0,
        ..params
    };
    assert!(g.spectral_blend(&input, &planes, &eye, bad).is_err());
    assert!(g.spectral_blend(&input, &[], &eye, params).is_err());
}

/// The cases of [`cases`] and a 1 degree field (blur to ~40 px: four pyramid levels).
fn pyramid_cases() -> Vec<(&'static str, Rgbd, EyeModel)> {
    let mut v = cases();
    let one = EyeModel {
        fov_horizontal_deg: 1.0,
        ..EyeModel::default()
    };
    v.push(("random 80x64, 1 degree field", random_rgbd(80, 64, 11), one));
    v
}

#[test]
fn pyramid_defocus_matches_cpu() {
    let Some(g) = gpu() else { return };
    let foci = [Diopters(-0.8), Diopters(0.3), Diopters(1.7)];
    let m = DefocusMethod::Pyramid(PyramidParams::default());
    for (name, input, eye) in pyramid_cases() {
        let c = Cpu.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
        let q = g.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
        for (k, (a, b)) in c.iter().zip(&q).enumerate() {
            let (max, _) = diff(a, b, 1e-3);
            eprintln!("pyramid {name} at {}: max |gpu - cpu| = {max:e}", foci[k]);
            assert!(max < 1e-3, "pyramid {name} at {}: {max}", foci[k]);
        }
    }
}

#[test]
fn foveated_pyramid_matches_cpu() {
    let Some(g) = gpu() else { return };
    // 96 px over a 4 degree field (24 px/deg): a 1 degree fovea off centre, acuity falling
    // fast enough for four layers.
    let eye = EyeModel {
        fov_horizontal_deg: 4.0,
        ..EyeModel::default()
    };
    let input = scene_rgbd(96);
    let fov = Foveation {
        gaze: [30.0, 58.0],
        radius_deg: 1.0,
        mar_slope: 0.3,
    };
    let plan = FoveationPlan::new(96, 96, &eye, &fov).unwrap();
    assert!(plan.layers.len() >= 3, "{:?}", plan.layers);
    let m = DefocusMethod::Pyramid(PyramidParams {
        foveation: Some(fov),
    });
    let foci = [Diopters(0.3), Diopters(2.0)];
    let c = Cpu.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
    let q = g.defocus(&input, &foci, &eye, m, &|_| {}).unwrap();
    for (k, (a, b)) in c.iter().zip(&q).enumerate() {
        let (max, _) = diff(a, b, 1e-3);
        eprintln!("foveated pyramid at {}: max |gpu - cpu| = {max:e}", foci[k]);
        assert!(max < 1e-3, "foveated at {}: {max}", foci[k]);
    }
}
