//! The shipped C1, C4, C1R, C4R and C5R weights (`crates/net/weights/`): they load with their
//! provenance, and their accuracy on simulator test seeds is held against the classical
//! methods on the same scenes. The regression guards pin what the shipped weights measured (a
//! margin below it); the issues' targets (issue 7: C1 >= gather + 4 dB, C4 >= linear + 6 dB;
//! issue 21: C1R >= the 36-view light field + 0.5 dB, C4R >= optimized blending with 10
//! iterations; issue 41: C5R >= the classical light field + 1.5 dB) are the ignored tests, which fail until weights that meet them are shipped:
//! `cargo test --release -p dioptra-net --test shipped -- --include-ignored`.

use dioptra_core::{Diopters, EyeModel, Millimeters, RgbImage, Rgbd};
use dioptra_net::{load_net, CpuNet, Task};
use dioptra_render::gather::gather;
use dioptra_render::metrics::quality;
use dioptra_render::multifocal::linear_blend;
use dioptra_render::retina::retina_multifocal;
use dioptra_sim::scene::{render_pinhole, render_thin_lens, Camera, Scene, Split};

/// The eye the training data used (`train::data::DataSpec::default`), at `size` pixels.
fn eye(size: usize) -> EyeModel {
    EyeModel {
        pupil_diameter: Millimeters(4.0),
        fov_horizontal_deg: 20.0,
        ..EyeModel::default()
    }
    .with_width(size as u32)
    .validated()
    .unwrap()
}

fn test_scene(i: u64, size: usize) -> (Scene, Camera, Rgbd) {
    let scene = Scene::generate(Split::Test.seed(i));
    let cam = Camera::square(eye(size), size);
    let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 8).unwrap();
    (scene, cam, Rgbd::new(color, depth).unwrap())
}

fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    quality(a, b, None).unwrap().psnr
}

/// Mean PSNR over `scenes` test scenes and four foci: (C1 network, gather).
fn c1_vs_gather(net: &CpuNet, scenes: u64, size: usize, rays: u32) -> (f64, f64) {
    let e = eye(size);
    let (mut n, mut g, mut k) = (0.0, 0.0, 0.0);
    for i in 0..scenes {
        let (scene, cam, rgbd) = test_scene(i, size);
        for q in [0.1f32, 1.0, 2.0, 4.0].map(Diopters) {
            let truth = render_thin_lens(&scene, &cam, q, rays).unwrap();
            n += psnr(&net.defocus(&rgbd, q, &e).unwrap(), &truth);
            g += psnr(&gather(&rgbd, q, &e).unwrap(), &truth);
            k += 1.0;
        }
    }
    (n / k, g / k)
}

/// Mean retinal PSNR over `scenes` test scenes at the net's foci: (C4 network, linear).
fn c4_vs_linear(net: &CpuNet, scenes: u64, size: usize, rays: u32) -> (f64, f64) {
    let Task::C4 { planes, foci } = &net.arch().task else {
        panic!("not a C4 net");
    };
    let planes: Vec<Diopters> = planes.iter().copied().map(Diopters).collect();
    let foci: Vec<Diopters> = foci.iter().copied().map(Diopters).collect();
    let e = eye(size);
    let (mut n, mut l, mut k) = (0.0, 0.0, 0.0);
    for i in 0..scenes {
        let (scene, cam, rgbd) = test_scene(i, size);
        let seen_n = retina_multifocal(&net.decompose(&rgbd).unwrap(), &foci, &e).unwrap();
        let seen_l = retina_multifocal(&linear_blend(&rgbd, &planes).unwrap(), &foci, &e).unwrap();
        for (j, &q) in foci.iter().enumerate() {
            let truth = render_thin_lens(&scene, &cam, q, rays).unwrap();
            n += psnr(&seen_n[j], &truth);
            l += psnr(&seen_l[j], &truth);
            k += 1.0;
        }
    }
    (n / k, l / k)
}

#[test]
fn shipped_weights_load_with_their_provenance() {
    for config in ["c1", "c4", "c1r", "c4r", "c5r"] {
        let net = load_net(None, config).unwrap();
        assert_eq!(net.arch().task.name(), config);
        let w = dioptra_net::Weights::load(&dioptra_net::shipped_weights(config)).unwrap();
        for key in ["steps", "train_seeds", "data", "optimiser"] {
            assert!(
                w.provenance.contains_key(key),
                "{config}: no {key:?} in the provenance"
            );
        }
    }
}

/// What the shipped weights measured at 128 px on test scene 0 (C1 29.96 dB, C4 24.85 dB; see
/// `crates/net/weights/README.md`), less about 1 dB: the renders are seeded, so the margin is
/// for a retrained net that is no worse, not for noise.
const C1_GUARD_DB: f64 = 29.0;
const C4_GUARD_DB: f64 = 24.0;

#[test]
fn shipped_c1_holds_its_measured_accuracy() {
    let (n, g) = c1_vs_gather(&load_net(None, "c1").unwrap(), 1, 128, 32);
    eprintln!("C1 at 128 px, test scene 0: network {n:.2} dB, gather {g:.2} dB");
    assert!(
        n >= C1_GUARD_DB,
        "C1 fell to {n:.2} dB (guard {C1_GUARD_DB} dB)"
    );
}

#[test]
fn shipped_c4_holds_its_measured_accuracy() {
    let (n, l) = c4_vs_linear(&load_net(None, "c4").unwrap(), 1, 128, 32);
    eprintln!("C4 at 128 px, test scene 0: network {n:.2} dB, linear {l:.2} dB (retinal)");
    assert!(
        n >= C4_GUARD_DB,
        "C4 fell to {n:.2} dB (guard {C4_GUARD_DB} dB)"
    );
}

#[test]
#[ignore = "issue 7's target, not met by the shipped weights: C1 >= gather + 4 dB at 256 px"]
fn c1_beats_gather_by_4_db() {
    let (n, g) = c1_vs_gather(&load_net(None, "c1").unwrap(), 2, 256, 64);
    assert!(n >= g + 4.0, "network {n:.2} dB, gather {g:.2} dB");
}

#[test]
#[ignore = "issue 7's target, not met by the shipped weights: C4 >= linear + 6 dB at 256 px"]
fn c4_beats_linear_by_6_db() {
    let (n, l) = c4_vs_linear(&load_net(None, "c4").unwrap(), 2, 256, 64);
    assert!(n >= l + 6.0, "network {n:.2} dB, linear {l:.2} dB");
}

/// The foci `dioptra eval` scores varifocal methods at.
const EVAL_FOCI: [f32; 7] = [0.1, 0.5, 1.0, 1.5, 2.2, 3.0, 4.0];

/// The shipped C1R and its classical method.
fn c1r() -> (CpuNet, dioptra_net::Classical) {
    let net = load_net(None, "c1r").unwrap();
    let Task::C1r { classical } = net.arch().task else {
        panic!("not a c1r net");
    };
    (net, classical)
}

/// (classical, refined) for one input.
fn c1r_pair(
    net: &CpuNet,
    c: dioptra_net::Classical,
    rgbd: &Rgbd,
    q: Diopters,
    e: &EyeModel,
) -> (RgbImage, RgbImage) {
    let base = dioptra_net::refine::classical_defocus(&dioptra_render::Cpu, c, rgbd, q, e).unwrap();
    let r = net.refine_defocus(rgbd, &base, q, e).unwrap();
    (r.classical, r.image)
}

/// Every test scene of `dioptra eval` at every focus it scores, at 256 px (as eval renders
/// them: 4 x 4 supersampled colour, 64 rays of ground truth): (label, classical dB, refined
/// dB, the focus, the thin-lens truth, the input).
fn c1r_on_test_scenes() -> Vec<(String, f64, f64, Diopters, RgbImage, Rgbd)> {
    let (net, classical) = c1r();
    let e = eye(256);
    let mut out = Vec::new();
    for i in 0..2 {
        let scene = Scene::generate(Split::Test.seed(i));
        let cam = Camera::square(e, 256);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 4).unwrap();
        let rgbd = Rgbd::new(color, depth).unwrap();
        for q in EVAL_FOCI.map(Diopters) {
            let truth = render_thin_lens(&scene, &cam, q, 64).unwrap();
            let (base, refined) = c1r_pair(&net, classical, &rgbd, q, &e);
            let (b, r) = (psnr(&base, &truth), psnr(&refined, &truth));
            let label = format!("test scene {i} at {:.1} D", q.0);
            eprintln!(
                "{label}: {} {b:.2} dB, refined {r:.2} dB",
                classical.label()
            );
            out.push((label, b, r, q, truth, rgbd.clone()));
        }
    }
    out
}

/// One failure case's scores (dB), whole image and inside its region.
struct CaseScores {
    name: String,
    classical: f64,
    refined: f64,
    classical_region: f64,
    refined_region: f64,
    gather_region: f64,
}

/// Every failure case of `dioptra eval` (192 px, 48 rays).
fn c1r_on_failure_cases() -> Vec<CaseScores> {
    let (net, classical) = c1r();
    let mut out = Vec::new();
    for case in dioptra_sim::scene::failure::failure_cases(192).unwrap() {
        let (color, depth) = case.input(&case.scene).unwrap();
        let rgbd = Rgbd::new(color, depth).unwrap();
        let truth = render_thin_lens(&case.scene, &case.camera, case.focus, 48).unwrap();
        let (base, refined) = c1r_pair(&net, classical, &rgbd, case.focus, &case.camera.eye);
        let region = |img: &RgbImage| quality(img, &truth, Some(&case.mask)).unwrap().psnr;
        let g = gather(&rgbd, case.focus, &case.camera.eye).unwrap();
        let s = CaseScores {
            name: case.name.to_string(),
            classical: psnr(&base, &truth),
            refined: psnr(&refined, &truth),
            classical_region: region(&base),
            refined_region: region(&refined),
            gather_region: region(&g),
        };
        eprintln!(
            "{}: {:.2} -> {:.2} dB, region {:.2} -> {:.2} dB (gather {:.2})",
            s.name, s.classical, s.refined, s.classical_region, s.refined_region, s.gather_region
        );
        out.push(s);
    }
    out
}

/// Issue 21: never below the classical input on any test scene.
#[test]
fn shipped_c1r_is_never_below_its_classical_input_on_the_test_scenes() {
    let below: Vec<String> = c1r_on_test_scenes()
        .into_iter()
        .filter(|(_, b, r, ..)| r < b)
        .map(|(l, b, r, ..)| format!("{l}: refined {r:.2} dB < {b:.2} dB"))
        .collect();
    assert!(below.is_empty(), "{below:#?}");
}

/// Issue 21: never below the classical input on any failure case, whole image or region
/// (measured with the 3 px own-blur threshold: the nearest is depth noise's region, +0.00
/// dB); and where the net is meant to help it does.
#[test]
fn shipped_c1r_is_never_below_its_classical_input_on_the_failure_cases() {
    let cases = c1r_on_failure_cases();
    assert_eq!(cases.len(), 12, "the failure suite changed");
    let mut below = Vec::new();
    for c in &cases {
        if c.refined < c.classical {
            below.push(format!(
                "{}: {:.3} < {:.3} dB",
                c.name, c.refined, c.classical
            ));
        }
        if c.refined_region < c.classical_region {
            below.push(format!(
                "{} region: {:.3} < {:.3} dB",
                c.name, c.refined_region, c.classical_region
            ));
        }
    }
    assert!(below.is_empty(), "{below:#?}");
    // The blurred occluder's side of Yu et al.'s far-focus case (measured +2.0 dB).
    let yu = cases
        .iter()
        .find(|c| c.name == "yu-focus-far-point-near")
        .unwrap();
    assert!(
        yu.refined_region >= yu.classical_region + 1.0,
        "{:.2} -> {:.2} dB",
        yu.classical_region,
        yu.refined_region
    );
}

/// Issue 21's targets: the 36-view light field + 0.5 dB over the test scenes at 256 px, and
/// gather + 2 dB inside the regions of Yu et al.'s four occlusion cases.
#[test]
#[ignore = "issue 21 target, not met by the shipped C1R"]
fn c1r_beats_the_36_view_light_field_and_gather_in_the_occlusion_regions() {
    use dioptra_render::{Backend, Cpu, DefocusMethod, LightFieldParams};
    let lf36 = DefocusMethod::LightField(LightFieldParams {
        views: 36,
        mip: true,
    });
    let e = eye(256);
    let scenes = c1r_on_test_scenes();
    let n = scenes.len() as f64;
    let (mut refined, mut light_field) = (0.0, 0.0);
    for (_, _, r, q, truth, rgbd) in &scenes {
        refined += r / n;
        let img = Cpu
            .defocus(rgbd, &[*q], &e, lf36, &|_| {})
            .unwrap()
            .remove(0);
        light_field += psnr(&img, truth) / n;
    }
    let mut misses = Vec::new();
    if refined < light_field + 0.5 {
        misses.push(format!(
            "refined {refined:.2} dB < light field 36 views {light_field:.2} + 0.5 dB"
        ));
    }
    for c in c1r_on_failure_cases()
        .iter()
        .filter(|c| c.name.starts_with("yu-"))
    {
        if c.refined_region < c.gather_region + 2.0 {
            misses.push(format!(
                "{} region: refined {:.2} dB < gather {:.2} + 2 dB",
                c.name, c.refined_region, c.gather_region
            ));
        }
    }
    assert!(misses.is_empty(), "{misses:#?}");
}

/// Retinal PSNR (mean over the net's foci, 32 rays of truth) of a test scene at 256 px:
/// (linear, refined, optimized with 10 iterations), and the refined layers.
fn c4r_on_test_scene(net: &CpuNet, i: u64, optimized: bool) -> (f64, f64, f64, Vec<RgbImage>) {
    let Task::C4r { planes, foci, .. } = &net.arch().task else {
        panic!("not a c4r net");
    };
    let planes: Vec<Diopters> = planes.iter().copied().map(Diopters).collect();
    let foci: Vec<Diopters> = foci.iter().copied().map(Diopters).collect();
    let e = eye(256);
    let (scene, cam, rgbd) = test_scene(i, 256);
    let truth: Vec<RgbImage> = foci
        .iter()
        .map(|&q| render_thin_lens(&scene, &cam, q, 32).unwrap())
        .collect();
    let score = |layers: &dioptra_render::Layers| {
        let seen = retina_multifocal(layers, &foci, &e).unwrap();
        seen.iter()
            .zip(&truth)
            .map(|(s, t)| psnr(s, t))
            .sum::<f64>()
            / foci.len() as f64
    };
    let linear = linear_blend(&rgbd, &planes).unwrap();
    let refined = net.refine_decompose(&rgbd, &linear).unwrap();
    let opt = if optimized {
        let params = dioptra_render::OptimizeParams {
            iterations: 10,
            tolerance: 0.0,
        };
        let (l, _) = dioptra_render::multifocal::optimized_blend(
            &truth,
            &foci,
            &planes,
            &e,
            Some(&linear),
            params,
            |_| {},
        )
        .unwrap();
        score(&l)
    } else {
        f64::NAN
    };
    let (l, r) = (score(&linear), score(&refined));
    eprintln!("test scene {i}: linear {l:.2} dB, refined {r:.2} dB, optimized 10 it {opt:.2} dB (retinal, mean of {} foci)", foci.len());
    (l, r, opt, refined.images)
}

/// Issue 21: C4R never below linear blending on a test scene, its layers within [0, 1].
#[test]
fn shipped_c4r_is_never_below_linear_blending() {
    let net = load_net(None, "c4r").unwrap();
    // The file names no classical input: it refines linear blending.
    assert_eq!(
        dioptra_net::refine::c4r_input(&net.arch().task).unwrap().1,
        dioptra_net::ClassicalLayers::Linear
    );
    for i in 0..2 {
        let (l, r, _, layers) = c4r_on_test_scene(&net, i, false);
        assert!(
            layers
                .iter()
                .flat_map(|l| l.channels.iter().flat_map(|p| p.data()))
                .all(|v| (0.0..=1.0).contains(v)),
            "layers outside the display's [0, 1]"
        );
        assert!(
            r >= l,
            "test scene {i}: refined {r:.2} dB < linear {l:.2} dB"
        );
        // Guard: the shipped C4R measured +3.4 and +2.5 dB.
        assert!(
            r >= l + 1.5,
            "test scene {i}: refined {r:.2} dB, linear {l:.2} dB"
        );
    }
}

/// Issue 21's target: C4R's retinal PSNR at least optimized blending's with 10 iterations.
#[test]
#[ignore = "issue 21 target, not met by the shipped C4R"]
fn c4r_matches_optimized_blending_with_10_iterations() {
    let net = load_net(None, "c4r").unwrap();
    for i in 0..2 {
        let (_, r, opt, _) = c4r_on_test_scene(&net, i, true);
        assert!(
            r >= opt,
            "test scene {i}: refined {r:.2} dB < optimized 10 it {opt:.2} dB"
        );
    }
}

/// Mean PSNR over the novel views of test scene `i`'s 9 x 9 light field over 1 cm at `size`
/// px (as `dioptra eval --suite lightfield` renders it), synthesised from its 9 inputs:
/// (classical, refined by the shipped C5R).
fn c5r_on_test_scene(i: u64, size: usize) -> (f64, f64) {
    use dioptra_render::views::{light_field_positions, synthesize_light_field, RgbdView};
    let net = load_net(None, "c5r").unwrap();
    let e = EyeModel::default();
    let scene = Scene::generate(Split::Test.seed(i));
    let cam = Camera::square(e, size);
    let positions = light_field_positions(9, 0.01).unwrap();
    let truth: Vec<(RgbImage, Rgbd)> = positions
        .iter()
        .map(|&p| {
            let (c, d) = render_pinhole(&scene, &cam, p, 2).unwrap();
            (c.clone(), Rgbd::new(c, d).unwrap())
        })
        .collect();
    let picks = Task::C5 { views: 9, grid: 9 }.input_views();
    let inputs: Vec<RgbdView> = picks
        .iter()
        .map(|&k| RgbdView {
            position: positions[k],
            rgbd: truth[k].1.clone(),
        })
        .collect();
    let classical = synthesize_light_field(&inputs, 9, 0.01, &e, |_| {}).unwrap();
    let refined = dioptra_net::refine::refine_light_field(
        &inputs,
        9,
        0.01,
        &e,
        &|v, er| net.refine_view(v, er),
        &|_| {},
    )
    .unwrap();
    // PSNR of the mean squared error over the novel views.
    let novel_psnr = |views: &[dioptra_render::retina::LfView]| {
        let novel = (0..positions.len()).filter(|k| !picks.contains(k));
        let mse: f64 = novel
            .map(|k| 10f64.powf(-psnr(&views[k].image, &truth[k].0) / 10.0))
            .sum::<f64>()
            / (positions.len() - picks.len()) as f64;
        -10.0 * mse.log10()
    };
    (novel_psnr(&classical), novel_psnr(&refined))
}

/// Issue 41's rule for shipping C5R (never below the classical synthesis on any scene), held
/// on the simulator's test scenes too; the independent Mitsuba set's scores are in
/// `crates/net/weights/README.md`.
#[test]
fn shipped_c5r_is_never_below_the_classical_light_field() {
    for i in 0..2 {
        let (c, r) = c5r_on_test_scene(i, 128);
        eprintln!("C5R, test scene {i}, 128 px: classical {c:.2} dB, refined {r:.2} dB");
        assert!(
            r >= c,
            "test scene {i}: refined {r:.2} dB below classical {c:.2} dB"
        );
    }
}

#[test]
#[ignore = "issue 41's target, not met by the shipped weights: C5R >= classical + 1.5 dB"]
fn c5r_beats_the_classical_light_field_by_1_5_db() {
    for i in 0..2 {
        let (c, r) = c5r_on_test_scene(i, 256);
        assert!(
            r >= c + 1.5,
            "test scene {i}: refined {r:.2} dB, classical {c:.2} dB"
        );
    }
}
