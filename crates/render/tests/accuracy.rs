//! Every method against the thin-lens ground truth rendered by dioptra-sim on test-split
//! scenes. The accuracy targets are checked at 256 x 256 with ground-truth sample
//! counts the test profile affords (each test states its own); the fuller sweep (40 foci,
//! 256 samples per pixel) is `cargo run --release -p dioptra-render --example accuracy`.

use dioptra_core::{Diopters, EyeModel, Plane, Rgbd};
use dioptra_render::defocus::PyramidParams;
use dioptra_render::metrics::{depth_edge_mask, psnr};
use dioptra_render::multifocal::{linspace, DEFAULT_PLANES};
use dioptra_render::retina::{retina_lightfield, LfView};
use dioptra_render::{backend, DefocusMethod, LightFieldParams, OptimizeParams, SpectralParams};
use dioptra_sim::scene::failure::{failure_cases, FailureCase};
use dioptra_sim::scene::{
    render_light_field, render_pinhole, render_thin_lens, render_thin_lens_scrambled,
    render_thin_lens_stack, Camera, Object, Pattern, Rot, Scene, Shape, Split, Texture,
};

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn ground_truth_own_error_is_small() {
    // 64 against an independent 256 rays per pixel at 256 x 256: the references below use
    // 48 to 64 samples, so their own error is about this figure.
    let cam = Camera::square(EyeModel::default(), 256);
    let scene = Scene::generate(Split::Test.seed(0));
    let a = render_thin_lens_scrambled(&scene, &cam, Diopters(0.1), 64, 1).unwrap();
    let b = render_thin_lens(&scene, &cam, Diopters(0.1), 256).unwrap();
    let p = psnr(&a, &b, None).unwrap();
    eprintln!("ground truth 64 vs 256 samples per pixel: {p:.2} dB");
    assert!(p > 45.0, "{p} dB");
}

#[test]
fn lightfield_beats_gather_near_occlusion_boundaries() {
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 256);
    let cpu = backend("cpu").unwrap();
    let foci = [Diopters(0.1), Diopters(1.0), Diopters(2.5), Diopters(4.0)];
    let lf = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    let (mut g_all, mut l_all, mut g_edge, mut l_edge) = (vec![], vec![], vec![], vec![]);
    for s in 0..2 {
        let scene = Scene::generate(Split::Test.seed(s));
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
        let input = Rgbd::new(color, depth).unwrap();
        let mask = depth_edge_mask(&input.depth, 0.3, 3);
        let gt = render_thin_lens_stack(&scene, &cam, &foci, 64, |_| {}).unwrap();
        let g = cpu
            .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
            .unwrap();
        let l = cpu.defocus(&input, &foci, &eye, lf, &|_| {}).unwrap();
        for k in 0..foci.len() {
            g_all.push(psnr(&g[k], &gt[k], None).unwrap());
            l_all.push(psnr(&l[k], &gt[k], None).unwrap());
            g_edge.push(psnr(&g[k], &gt[k], Some(&mask)).unwrap());
            l_edge.push(psnr(&l[k], &gt[k], Some(&mask)).unwrap());
        }
    }
    let (g, l, ge, le) = (mean(&g_all), mean(&l_all), mean(&g_edge), mean(&l_edge));
    eprintln!("gather {g:.2} dB, lightfield {l:.2} dB; boundaries gather {ge:.2} dB, lightfield {le:.2} dB");
    assert!(l >= 36.0, "lightfield {l} dB");
    assert!(
        le > ge,
        "near boundaries lightfield {le} dB vs gather {ge} dB"
    );
}

#[test]
fn optimized_multifocal_beats_linear() {
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 256);
    let cpu = backend("cpu").unwrap();
    let scene = Scene::generate(Split::Test.seed(2));
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
    let input = Rgbd::new(color, depth).unwrap();
    let foci = linspace(0.1, 2.2, 22);
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let gt = render_thin_lens_stack(&scene, &cam, &foci, 48, |_| {}).unwrap();
    let linear = cpu.linear_blend(&input, &planes).unwrap();
    let params = OptimizeParams {
        iterations: 100,
        tolerance: 0.0,
    };
    let (opt, rep) = cpu
        .optimized_blend(&gt, &foci, &planes, &eye, Some(&linear), params, &|_| {})
        .unwrap();
    assert_eq!(rep.iterations, 100);
    assert!(rep.rms.last().unwrap().1 < rep.rms[0].1, "{:?}", rep.rms);
    let score = |l| {
        let r = cpu.retina_multifocal(l, &foci, &eye).unwrap();
        mean(
            &r.iter()
                .zip(&gt)
                .map(|(a, b)| psnr(a, b, None).unwrap())
                .collect::<Vec<_>>(),
        )
    };
    let (pl, po) = (score(&linear), score(&opt));
    eprintln!("multifocal linear {pl:.2} dB, optimized {po:.2} dB");
    assert!(po >= 38.0, "optimized {po} dB");
    assert!(po > pl + 3.0, "optimized {po} dB vs linear {pl} dB");
    // Layers are displayable: within [0, 1].
    assert!(opt
        .images
        .iter()
        .flat_map(|i| i.channels.iter())
        .flat_map(|p| p.data())
        .all(|v| (0.0..=1.0).contains(v)));
}

/// Issue 42: the spectral decomposition with its defaults (what `decompose --method spectral`
/// and the daemon run) is above linear blending and at least optimized blending of a gathered
/// stack with 30 iterations (the daemon's `method = "optimized"`), on a test scene.
#[test]
fn spectral_multifocal_beats_linear_and_optimized_gather() {
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 256);
    let cpu = backend("cpu").unwrap();
    // The second of `dioptra eval`'s test scenes (the first is the easier one for both).
    let scene = Scene::generate(Split::Test.seed(1));
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
    let input = Rgbd::new(color, depth).unwrap();
    let foci = linspace(0.1, 2.2, 22);
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let gt = render_thin_lens_stack(&scene, &cam, &foci, 48, |_| {}).unwrap();
    let linear = cpu.linear_blend(&input, &planes).unwrap();
    let (spectral, rep) = cpu
        .spectral_blend(&input, &planes, &eye, SpectralParams::default())
        .unwrap();
    assert!(rep.refined, "{rep:?}");
    let gathered = cpu
        .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
        .unwrap();
    let params = OptimizeParams {
        iterations: 30,
        tolerance: 0.0,
    };
    let (opt, _) = cpu
        .optimized_blend(
            &gathered,
            &foci,
            &planes,
            &eye,
            Some(&linear),
            params,
            &|_| {},
        )
        .unwrap();
    let score = |l| {
        let r = cpu.retina_multifocal(l, &foci, &eye).unwrap();
        mean(
            &r.iter()
                .zip(&gt)
                .map(|(a, b)| psnr(a, b, None).unwrap())
                .collect::<Vec<_>>(),
        )
    };
    let (pl, ps, po) = (score(&linear), score(&spectral), score(&opt));
    eprintln!(
        "multifocal linear {pl:.2} dB, spectral {ps:.2} dB, optimized-gather 30 it {po:.2} dB"
    );
    assert!(ps > pl + 5.0, "spectral {ps} dB vs linear {pl} dB");
    assert!(
        ps >= po,
        "spectral {ps} dB vs optimized-gather 30 it {po} dB"
    );
    assert!(spectral
        .images
        .iter()
        .flat_map(|i| i.channels.iter())
        .flat_map(|p| p.data())
        .all(|v| (0.0..=1.0).contains(v)));
}

/// Issue 42: the spectral decomposition is above linear blending in every failure case but
/// one (the semi-transparent pane, whose input depth is wrong: see below), as the eye sees the
/// layers at the case's focus, over the whole image and inside the case's failure region (at
/// 96 px: the suite's cases, smaller).
#[test]
fn spectral_beats_linear_in_every_failure_case() {
    let cpu = backend("cpu").unwrap();
    let planes: Vec<Diopters> = DEFAULT_PLANES.iter().map(|&p| Diopters(p)).collect();
    let mut below = Vec::new();
    for case in failure_cases(96).unwrap() {
        let eye = case.camera.eye;
        let (color, depth) = case.input(&case.scene).unwrap();
        let input = Rgbd::new(color, depth).unwrap();
        let gt = render_thin_lens(&case.scene, &case.camera, case.focus, 32).unwrap();
        let linear = cpu.linear_blend(&input, &planes).unwrap();
        let (spectral, _) = cpu
            .spectral_blend(&input, &planes, &eye, SpectralParams::default())
            .unwrap();
        let seen = |l| {
            cpu.retina_multifocal(l, &[case.focus], &eye)
                .unwrap()
                .remove(0)
        };
        let (a, b) = (seen(&linear), seen(&spectral));
        let (pl, ps) = (psnr(&a, &gt, None).unwrap(), psnr(&b, &gt, None).unwrap());
        let (rl, rs) = (
            psnr(&a, &gt, Some(&case.mask)).unwrap(),
            psnr(&b, &gt, Some(&case.mask)).unwrap(),
        );
        eprintln!(
            "{}: linear {pl:.2} / region {rl:.2} dB, spectral {ps:.2} / region {rs:.2} dB",
            case.name
        );
        if case.name == "semi-transparent" {
            // The known exception: the input holds the pane's depth (3 D) for the wall seen
            // through it, so the stack spectral fits is blurred where the truth is sharp, and
            // fitting it faithfully is worse than linear blending's (also wrong) 2 D plane:
            // measured 27.0 against 28.7 dB. Guard that it stays near linear.
            assert!(
                ps > pl - 2.5,
                "{}: spectral {ps} dB vs linear {pl} dB",
                case.name
            );
            continue;
        }
        if ps <= pl || rs <= rl {
            below.push(case.name);
        }
    }
    assert!(below.is_empty(), "spectral at or below linear in {below:?}");
}

#[test]
fn light_field_display_retina_matches_thin_lens() {
    // A dense light field over the pupil, shift-and-added, is the thin-lens image.
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 64);
    let scene = Scene::generate(Split::Test.seed(3));
    let (grid, span) = (9, 0.004);
    let views = render_light_field(&scene, &cam, grid, span, 2).unwrap();
    let lf: Vec<LfView> = views
        .into_iter()
        .map(|v| LfView {
            position: v.position,
            image: v.color,
        })
        .collect();
    let step = span / (grid - 1) as f32;
    for q in [0.3f32, 2.0] {
        let r = retina_lightfield(&lf, step, Diopters(q), &eye).unwrap();
        let gt = render_thin_lens(&scene, &cam, Diopters(q), 128).unwrap();
        let p = psnr(&r, &gt, None).unwrap();
        assert!(p > 33.0, "focus {q}: {p} dB");
    }
}

#[test]
fn semi_transparent_surfaces_are_a_failure_case() {
    // RGB-D holds one depth per pixel. A textured wall seen through a half-transparent pane
    // at 3 D takes the pane's depth, so focusing on the wall blurs the texture the eye sees
    // sharp: the method fails inside the pane and not outside it.
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 64);
    let cpu = backend("cpu").unwrap();
    let scene = Scene {
        objects: vec![Object {
            shape: Shape::Box {
                center: [0.0, 0.0, 1.0 / 3.0],
                half: [0.03, 0.06, 1e-5],
                rot: Rot::IDENTITY,
            },
            texture: Texture {
                a: [0.5; 3],
                b: [0.5; 3],
                pattern: Pattern::Solid,
            },
            alpha: 0.5,
        }],
        wall_depth: 5.0,
        wall: Texture {
            a: [0.05, 0.1, 0.2],
            b: [0.9, 0.8, 0.6],
            pattern: Pattern::Checker { scale: 0.15 },
        },
        seed: 0,
    };
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
    let pane = {
        let mut m = Plane::new(64, 64, 0.0);
        for (v, d) in m.data_mut().iter_mut().zip(depth.data()) {
            *v = if *d > 1.0 { 1.0 } else { 0.0 };
        }
        m
    };
    let input = Rgbd::new(color, depth).unwrap();
    let q = Diopters(0.2);
    let gt = render_thin_lens(&scene, &cam, q, 64).unwrap();
    let out = cpu
        .defocus(
            &input,
            &[q],
            &eye,
            DefocusMethod::LightField(LightFieldParams::default()),
            &|_| {},
        )
        .unwrap();
    let inside = psnr(&out[0], &gt, Some(&pane)).unwrap();
    let outside = psnr(
        &out[0],
        &gt,
        Some(&dioptra_render::metrics::invert_mask(&pane)),
    )
    .unwrap();
    eprintln!("semi-transparent pane: inside {inside:.2} dB, outside {outside:.2} dB");
    assert!(
        inside < 32.0 && outside > inside + 8.0,
        "inside {inside} dB, outside {outside} dB"
    );
}

#[test]
fn sparse_views_synthesize_the_light_field() {
    // DeepFocus's C5 setting: a 9 x 9 light field over 1 cm from 5 and from 9 RGB-D views.
    use dioptra_render::views::{synthesize_view, RgbdView};
    let eye = EyeModel::default();
    let cam = Camera::square(eye, 64);
    let scene = Scene::generate(Split::Test.seed(4));
    let truth = render_light_field(&scene, &cam, 9, 0.01, 3).unwrap();
    let view = |k: usize| RgbdView {
        position: truth[k].position,
        rgbd: Rgbd::new(truth[k].color.clone(), truth[k].depth.clone()).unwrap(),
    };
    let five: Vec<RgbdView> = [0, 8, 40, 72, 80].into_iter().map(view).collect();
    let nine: Vec<RgbdView> = [0, 4, 8, 36, 40, 44, 72, 76, 80]
        .into_iter()
        .map(view)
        .collect();
    let (mut p5, mut p9, mut copy) = (vec![], vec![], vec![]);
    // Novel views only: none of the nine inputs.
    for (_, t) in truth
        .iter()
        .enumerate()
        .filter(|(k, _)| (k % 9) % 4 != 0 || (k / 9) % 4 != 0)
        .step_by(3)
    {
        p5.push(
            psnr(
                &synthesize_view(&five, t.position, &eye).unwrap(),
                &t.color,
                None,
            )
            .unwrap(),
        );
        p9.push(
            psnr(
                &synthesize_view(&nine, t.position, &eye).unwrap(),
                &t.color,
                None,
            )
            .unwrap(),
        );
        // Baseline: show the centre view everywhere.
        copy.push(psnr(&truth[40].color, &t.color, None).unwrap());
    }
    let (p5, p9, copy) = (mean(&p5), mean(&p9), mean(&copy));
    eprintln!("sparse-view light field: 5 views {p5:.2} dB, 9 views {p9:.2} dB, centre view copied {copy:.2} dB");
    assert!(p9 > copy + 5.0 && p5 > copy + 3.0, "{p5} {p9} {copy}");
    assert!(p9 >= p5 - 0.5, "9 views {p9} dB vs 5 views {p5} dB");
}

/// Issue 54: the pyramid method (bounded work per pixel) is within 0.3 dB of gather against
/// the thin-lens truth on test scenes, at the suite's 256 px over 20 degrees (blur under 6 px:
/// the exact pass alone, gather's sums) and at a panel's pixel density (256 px over 5 degrees,
/// 51 px/deg: blur up to 23 px, spread on two pyramid levels). Measured with 64 rays per pixel:
/// 20 degrees 39.49 against 39.49 dB; 5 degrees 36.84 against 36.88, worst frame -0.27 dB.
#[test]
fn pyramid_is_within_0_3_db_of_gather_against_the_truth() {
    let cpu = backend("cpu").unwrap();
    let foci = [Diopters(0.1), Diopters(1.0), Diopters(2.5), Diopters(4.0)];
    let pyr = DefocusMethod::Pyramid(PyramidParams::default());
    for fov in [20.0f32, 5.0] {
        let eye = EyeModel {
            fov_horizontal_deg: fov,
            ..EyeModel::default()
        };
        let cam = Camera::square(eye, 256);
        let (mut g_all, mut p_all) = (vec![], vec![]);
        for s in 0..2 {
            let scene = Scene::generate(Split::Test.seed(s));
            let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
            let input = Rgbd::new(color, depth).unwrap();
            let gt = render_thin_lens_stack(&scene, &cam, &foci, 64, |_| {}).unwrap();
            let g = cpu
                .defocus(&input, &foci, &eye, DefocusMethod::Gather, &|_| {})
                .unwrap();
            let p = cpu.defocus(&input, &foci, &eye, pyr, &|_| {}).unwrap();
            for k in 0..foci.len() {
                g_all.push(psnr(&g[k], &gt[k], None).unwrap());
                p_all.push(psnr(&p[k], &gt[k], None).unwrap());
            }
        }
        let (g, p) = (mean(&g_all), mean(&p_all));
        let worst = p_all
            .iter()
            .zip(&g_all)
            .map(|(a, b)| a - b)
            .fold(f64::INFINITY, f64::min);
        eprintln!(
            "{fov} degree field: gather {g:.2} dB, pyramid {p:.2} dB, worst frame {worst:+.2} dB"
        );
        assert!(
            p >= g - 0.3,
            "{fov} degrees: pyramid {p} dB vs gather {g} dB"
        );
        assert!(
            worst >= -0.4,
            "{fov} degrees: a frame {worst} dB below gather"
        );
    }
}

/// Issue 54: the pyramid method within 0.3 dB of gather on every failure case, at `dioptra
/// eval`'s 192 px over the cases' own field (overall and inside the case's failure region)
/// and over a 5 degree field (51 px/deg at 256 px: the same scenes' centres, blurred on the
/// pyramid's levels; overall only, the regions being drawn for the wide view).
#[test]
fn pyramid_is_within_0_3_db_of_gather_on_every_failure_case() {
    let cpu = backend("cpu").unwrap();
    let pyr = DefocusMethod::Pyramid(PyramidParams::default());
    let mut below = Vec::new();
    for case in failure_cases(192).unwrap() {
        let narrow = Camera::square(
            EyeModel {
                fov_horizontal_deg: 5.0,
                ..case.camera.eye
            },
            256,
        );
        for (what, cam) in [("own field", case.camera), ("5 degrees", narrow)] {
            let c = FailureCase {
                camera: cam,
                ..case.clone()
            };
            let eye = cam.eye;
            let (color, depth) = c.input(&c.scene).unwrap();
            let input = Rgbd::new(color, depth).unwrap();
            let gt = render_thin_lens(&c.scene, &cam, c.focus, 32).unwrap();
            let g = cpu
                .defocus(&input, &[c.focus], &eye, DefocusMethod::Gather, &|_| {})
                .unwrap();
            let p = cpu.defocus(&input, &[c.focus], &eye, pyr, &|_| {}).unwrap();
            let (pg, pp) = (
                psnr(&g[0], &gt, None).unwrap(),
                psnr(&p[0], &gt, None).unwrap(),
            );
            let (rg, rp) = if what == "own field" {
                (
                    psnr(&g[0], &gt, Some(&c.mask)).unwrap(),
                    psnr(&p[0], &gt, Some(&c.mask)).unwrap(),
                )
            } else {
                (pg, pp)
            };
            eprintln!(
                "{} ({what}): gather {pg:.2} / region {rg:.2} dB, pyramid {pp:.2} / region {rp:.2} dB",
                c.name
            );
            if pp < pg - 0.3 || rp < rg - 0.3 {
                below.push(format!("{} ({what})", c.name));
            }
        }
    }
    assert!(
        below.is_empty(),
        "pyramid over 0.3 dB below gather in {below:?}"
    );
}
