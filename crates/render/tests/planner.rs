//! The planner: its decision rules on built frames, and its predictions checked against
//! measured accuracy on held-out sim test scenes (seeds 1 000 200 onwards; the calibration
//! table was measured on 1 000 100 onwards). `cargo test -p dioptra-render --test planner --
//! --nocapture` prints how often the plan meets its target and the cost it saves.

#[path = "support/fovea_truth.rs"]
mod fovea_truth;

use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_render::defocus::PyramidParams;
use dioptra_render::foveated::{Foveation, DEFAULT_MAR_SLOPE};
use dioptra_render::gather::gather;
use dioptra_render::lightfield::lightfield;
use dioptra_render::multifocal::linear_blend;
use dioptra_render::planner::{
    place_planes, predict_frame_cost, Choice, Deadline, FoveationSettings, FrameSpec, FrameStats,
    Planner, Setting, Target,
};
use dioptra_render::retina::retina_multifocal;
use dioptra_render::DefocusMethod;
use dioptra_render::LightFieldParams;
use dioptra_sim::scene::{render_pinhole, Camera, Scene};
use fovea_truth::{fovea_psnr, truth_crop};

const SIZE: usize = 160;

/// A textured frame whose depth (diopters) is `depth(x, y)`: a checker of 3 px squares and
/// contrast 0.1, whose region gradient (about 0.007) is near the sim test scenes' median
/// (0.006), so the planner's texture scaling treats it as a typical scene.
fn frame(depth: impl Fn(usize, usize) -> f32) -> Rgbd {
    frame_with_contrast(0.1, depth)
}

fn frame_with_contrast(contrast: f32, depth: impl Fn(usize, usize) -> f32) -> Rgbd {
    let n = SIZE * SIZE;
    let tex: Vec<f32> = (0..n * 3)
        .map(|i| {
            (((i / 3) % SIZE / 3 + (i / 3) / SIZE / 3) % 2) as f32 * contrast
                + 0.5 * (1.0 - contrast)
        })
        .collect();
    let d: Vec<f32> = (0..n).map(|i| depth(i % SIZE, i / SIZE)).collect();
    Rgbd::new(
        RgbImage::from_interleaved(SIZE, SIZE, &tex).unwrap(),
        DepthMap::from_diopters(Plane::from_vec(SIZE, SIZE, d).unwrap()).unwrap(),
    )
    .unwrap()
}

fn centre() -> [f32; 2] {
    [SIZE as f32 * 0.5, SIZE as f32 * 0.5]
}

fn stats(f: &Rgbd, focus: f32) -> FrameStats {
    FrameStats::from_rgbd(f, centre(), Diopters(focus), &EyeModel::default())
}

#[test]
fn flat_scene_in_focus_needs_no_blur() {
    let f = frame(|_, _| 1.0);
    let p = Planner.plan(&stats(&f, 1.0), &Target::default());
    assert_eq!(p.choice, Choice::None, "{}", p.why);
    assert!(p.meets_target, "{}", p.why);
    // The same flat scene far out of focus is not passed through.
    let p = Planner.plan(&stats(&f, 3.0), &Target::default());
    assert_ne!(p.choice, Choice::None, "{}", p.why);
}

#[test]
fn texture_lowers_the_prediction_but_not_in_focus() {
    let edge = |x: usize, _| if x < SIZE / 2 { 2.0 } else { 0.5 };
    let (mild, harsh) = (frame(edge), frame_with_contrast(0.6, edge));
    let (sm, sh) = (stats(&mild, 0.5), stats(&harsh, 0.5));
    assert!(
        sh.region_gradient > 10.0 * sm.region_gradient,
        "{sm:?} / {sh:?}"
    );
    for c in Choice::all() {
        let (pm, ph) = (Planner.predict_psnr(&sm, c), Planner.predict_psnr(&sh, c));
        assert!(ph < pm - 5.0, "{c}: {ph:.1} dB harsh vs {pm:.1} dB mild");
    }
    // A flat harsh texture in focus: passing it through is right whatever its texture.
    let flat = frame_with_contrast(0.6, |_, _| 1.0);
    let p = Planner.plan(&stats(&flat, 1.0), &Target::default());
    assert_eq!(p.choice, Choice::None, "{}", p.why);
}

#[test]
fn content_outside_the_fovea_does_not_count() {
    // Far content well away from the gaze, whose blur cannot reach the fovea.
    let f = frame(|x, _| if x < 20 { 3.5 } else { 1.0 });
    let s = stats(&f, 1.0);
    assert!(s.region_disparity_px < 0.01, "{s:?}");
    assert_eq!(Planner.plan(&s, &Target::default()).choice, Choice::None);
}

#[test]
fn small_disparity_costs_less_than_large() {
    // An occlusion edge through the gaze point: near half at `near` D, far half at 0.5 D,
    // focused on the far half.
    let edge = |near: f32| frame(move |x, _| if x < SIZE / 2 { near } else { 0.5 });
    let small = Planner.plan(&stats(&edge(0.65), 0.5), &Target::default());
    let large = Planner.plan(&stats(&edge(3.5), 0.5), &Target::default());
    assert!(
        small.predicted_cost_ms < large.predicted_cost_ms,
        "small: {}; large: {}",
        small.why,
        large.why
    );
    if let (Choice::LightField { views: a }, Choice::LightField { views: b }) =
        (small.choice, large.choice)
    {
        assert!(
            a < b,
            "{a} views for a small disparity, {b} for a large one"
        );
    }
}

#[test]
fn narrow_depth_span_gets_fewer_planes_at_the_content() {
    let target = Target::default();
    let range = (Diopters(0.0), Diopters(3.0));
    let narrow = frame(|x, y| 0.6 + 0.2 * ((x + y) as f32 / (2 * SIZE) as f32));
    let wide = frame(|x, y| 0.2 + 3.0 * ((x * 7 + y * 13) % SIZE) as f32 / SIZE as f32);
    let n = Planner.plan_planes(&stats(&narrow, 0.7), &target, range, 4);
    let w = Planner.plan_planes(&stats(&wide, 0.7), &target, range, 4);
    assert!(n.planes.len() < 4, "{}", n.why);
    assert!(n.planes.len() < w.planes.len(), "{} / {}", n.why, w.why);
    assert!(
        n.planes.iter().all(|p| (0.55..=0.85).contains(&p.0)),
        "{}",
        n.why
    );
    // Wide content is clamped into the lens range.
    assert!(
        w.planes.iter().all(|p| (0.0..=3.0).contains(&p.0)),
        "{}",
        w.why
    );
    assert!(w.planes.windows(2).all(|p| p[0].0 < p[1].0), "{}", w.why);
}

#[test]
fn planes_go_where_the_mass_is() {
    let f = frame(|x, _| if x < SIZE / 3 { 0.5 } else { 2.0 });
    let planes = place_planes(&stats(&f, 1.0), 2, (Diopters(0.0), Diopters(4.0)));
    assert_eq!(planes.len(), 2);
    assert!((planes[0].0 - 0.5).abs() < 0.05, "{planes:?}");
    assert!((planes[1].0 - 2.0).abs() < 0.05, "{planes:?}");
}

#[test]
fn foveation_is_sparser_for_a_lower_periphery_target() {
    let at = |db| {
        Planner
            .foveation(&Target {
                periphery_psnr_db: Some(db),
                ..Target::default()
            })
            .unwrap()
    };
    assert!(
        at(18.0).scale > at(26.0).scale,
        "{:?} / {:?}",
        at(18.0),
        at(26.0)
    );
    assert!(Planner.foveation(&Target::default()).is_none());
}

fn run(input: &Rgbd, choice: Choice, q: Diopters, eye: &EyeModel) -> RgbImage {
    match choice {
        Choice::None => input.color.clone(),
        Choice::Gather => gather(input, q, eye).unwrap(),
        Choice::LightField { views } => {
            lightfield(input, q, eye, LightFieldParams { views, mip: true }).unwrap()
        }
    }
}

/// Held-out scenes: the plan's measured fovea PSNR against its target, and its cost against
/// always using the most expensive setting (light field, 48 views).
#[test]
fn plans_meet_their_target_on_held_out_scenes() {
    let eye = EyeModel::default().with_width(SIZE as u32);
    let cam = Camera::square(eye, SIZE);
    let target = Target::default();
    let (mut cases, mut met, mut mf_cases, mut mf_met) = (0, 0, 0, 0);
    // Frames the plan predicted to meet the target, those of them that did, and frames where
    // always using lightfield-48 met it.
    let (mut promised, mut kept, mut best_met) = (0, 0, 0);
    let (mut cost_plan, mut cost_max, mut mf_cost, mut mf_cost_max) = (0.0, 0.0, 0.0, 0.0);
    let (mut t_plan, mut t_max) = (0.0, 0.0);
    let mut chosen = std::collections::BTreeMap::new();
    for seed in 1_000_200..1_000_206u64 {
        let scene = Scene::generate(seed);
        let (color, depth) = render_pinhole(&scene, &cam, [0.0, 0.0], 6).unwrap();
        let input = Rgbd::new(color, depth).unwrap();
        let gazed = input.depth.at(SIZE / 2, SIZE / 2).unwrap();
        for q in [gazed, Diopters(0.5), Diopters(2.5)] {
            let truth = truth_crop(&scene, &eye, SIZE, q, 512).unwrap();
            let st = FrameStats::from_rgbd(&input, centre(), q, &eye);
            let plan = Planner.plan(&st, &target);
            let t = std::time::Instant::now();
            let img = run(&input, plan.choice, q, &eye);
            t_plan += t.elapsed().as_secs_f64();
            let t = std::time::Instant::now();
            let best = run(&input, Choice::MOST_EXPENSIVE, q, &eye);
            t_max += t.elapsed().as_secs_f64();
            let (p, pb) = (
                fovea_psnr(&img, &truth, SIZE),
                fovea_psnr(&best, &truth, SIZE),
            );
            eprintln!(
                "seed {seed} focus {:.2} D: {} predicted {:.1} measured {p:.2} dB (lightfield-48 {pb:.2} dB); {}",
                q.0, plan.choice, plan.predicted_psnr, plan.why
            );
            cases += 1;
            met += usize::from(p >= target.fovea_psnr_db);
            best_met += usize::from(pb >= target.fovea_psnr_db);
            if plan.meets_target {
                promised += 1;
                kept += usize::from(p >= target.fovea_psnr_db);
            }
            *chosen.entry(plan.choice.to_string()).or_insert(0) += 1;
            cost_plan += plan.predicted_cost_ms;
            cost_max += Planner.predict_cost_ms(&st, Choice::MOST_EXPENSIVE);
            if q == gazed {
                // Multifocal: the planner's planes (at most 4 within 0-4 D) against 4 default.
                let pp = Planner.plan_planes(&st, &target, (Diopters(0.0), Diopters(4.0)), 4);
                let layers = linear_blend(&input, &pp.planes).unwrap();
                let seen = retina_multifocal(&layers, &[q], &eye).unwrap().remove(0);
                let pm = fovea_psnr(&seen, &truth, SIZE);
                eprintln!(
                    "  multifocal: {} planes, predicted {:.1} measured {pm:.2} dB; {}",
                    pp.planes.len(),
                    pp.predicted_psnr,
                    pp.why
                );
                mf_cases += 1;
                mf_met += usize::from(pm >= target.fovea_psnr_db);
                mf_cost += pp.planes.len() as f64;
                mf_cost_max += 4.0;
            }
        }
    }
    let rate = kept as f64 / promised.max(1) as f64;
    let saved = 1.0 - cost_plan / cost_max;
    eprintln!(
        "planner: predicted to meet {:.1} dB in the fovea on {promised}/{cases} frames and met it on {kept} of those ({:.0} %); met it on {met}/{cases} frames in all (always lightfield-48: {best_met}/{cases}); chose {chosen:?}; predicted cost {cost_plan:.1} ms vs {cost_max:.1} ms always lightfield-48 (saves {:.0} %); measured CPU time here {:.2} s vs {:.2} s (saves {:.0} %)",
        target.fovea_psnr_db,
        100.0 * rate,
        100.0 * saved,
        t_plan,
        t_max,
        100.0 * (1.0 - t_plan / t_max)
    );
    eprintln!(
        "multifocal: met the target on {mf_met}/{mf_cases} frames with {mf_cost} planes in all vs {mf_cost_max} always 4 (saves {:.0} %)",
        100.0 * (1.0 - mf_cost / mf_cost_max)
    );
    // The stated fraction: 80 % of the promises kept (split by scene, the calibration
    // data kept 95 %), and the target met on all but one of the frames where always using
    // lightfield-48 meets it. Measured when this test was written: promised on 12 of 18
    // frames and kept on all 12; met on 17 of 18 (always lightfield-48: 17); chose none 7,
    // gather 5 and lightfield-48 6 (the fallback when nothing is predicted to reach the
    // target); predicted cost 60 % below always lightfield-48. Before the tables were
    // scaled by texture the plan kept 12 of 18 promises, all of them lightfield-12.
    assert!(
        promised >= cases / 3,
        "the plan promised the target on only {promised}/{cases} frames"
    );
    assert!(
        rate >= 0.8,
        "met the target on {kept} of the {promised} frames the plan promised"
    );
    assert!(
        met + 1 >= best_met,
        "the plan met the target on {met} frames, always lightfield-48 on {best_met}"
    );
    assert!(saved > 0.0, "no cost saved: {cost_plan} vs {cost_max} ms");
}

/// A 960 x 1080 textured frame (a panel's eye at 20 degrees) with an occlusion edge through
/// its centre: near half at `near` D, far half at 0.5 D.
fn panel_frame(near: f32) -> Rgbd {
    let (w, h) = (960usize, 1080usize);
    let tex: Vec<f32> = (0..w * h * 3)
        .map(|i| ((((i / 3) % w) / 4 + ((i / 3) / w) / 4) % 2) as f32 * 0.1 + 0.45)
        .collect();
    let d: Vec<f32> = (0..w * h)
        .map(|i| if i % w < w / 2 { near } else { 0.5 })
        .collect();
    Rgbd::new(
        RgbImage::from_interleaved(w, h, &tex).unwrap(),
        DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
    )
    .unwrap()
}

/// Issue 54: under a frame period too short for the most accurate settings, the planner picks
/// a cheaper one whose predicted time fits; with no budget to speak of it picks the cheapest
/// and says it will be late.
#[test]
fn under_a_short_budget_the_planner_picks_a_cheaper_setting_that_fits() {
    let input = panel_frame(2.5);
    let stats = FrameStats::from_rgbd(&input, [480.0, 540.0], Diopters(0.5), &EyeModel::default());
    let target = Target::default();
    let fov = Some(FoveationSettings {
        radius_deg: 5.0,
        mar_slope: DEFAULT_MAR_SLOPE,
    });
    let generous = Deadline {
        budget_ms: 1e9,
        cores: 2,
    };
    let free = Planner.plan_within(&stats, &target, &generous, fov);
    assert!(free.meets_deadline, "{}", free.why);
    // Every setting's prediction: the pyramid, full and foveated, is far cheaper than gather
    // at this blur (a 13 px radius) and panel size.
    let ms = |s: Setting| Planner.predict_setting_ms(&stats, &s, 2);
    let foveated = Setting::Foveated(Foveation {
        gaze: stats.gaze,
        radius_deg: 5.0,
        mar_slope: DEFAULT_MAR_SLOPE,
    });
    let (gather, pyramid, fov_ms) = (
        ms(Setting::Classic(Choice::Gather)),
        ms(Setting::Pyramid),
        ms(foveated),
    );
    eprintln!(
        "960 x 1080: gather {gather:.0} ms, pyramid {pyramid:.1} ms, foveated {fov_ms:.1} ms; unconstrained: {}",
        free.why
    );
    assert!(
        pyramid < 0.2 * gather,
        "pyramid {pyramid} ms, gather {gather} ms"
    );
    // A budget under the unconstrained choice's time but over the pyramid's.
    let short = Deadline {
        budget_ms: 0.5 * (free.predicted_ms + pyramid.min(fov_ms)),
        cores: 2,
    };
    assert!(short.budget_ms < free.predicted_ms, "{}", free.why);
    let p = Planner.plan_within(&stats, &target, &short, fov);
    eprintln!("budget {:.1} ms: {}", short.budget_ms, p.why);
    assert!(p.meets_deadline, "{}", p.why);
    assert!(p.predicted_ms <= short.budget_ms, "{}", p.why);
    assert!(p.predicted_ms < free.predicted_ms, "{}", p.why);
    assert!(p.setting.method().is_some(), "{}", p.why);
    // A long budget keeps the rig's own settings and the most accuracy on offer (this
    // texture is beyond every method's 35 dB).
    assert!(
        free.predicted_psnr >= p.predicted_psnr,
        "{} / {}",
        free.why,
        p.why
    );
    assert!(!free.why.contains("coarser"), "{}", free.why);
    // No budget at all: the cheapest, late.
    let none = Deadline {
        budget_ms: 1e-6,
        cores: 2,
    };
    let p = Planner.plan_within(&stats, &target, &none, fov);
    assert!(!p.meets_deadline, "{}", p.why);
    assert_eq!(p.setting, Setting::Classic(Choice::None), "{}", p.why);
    assert!(p.why.contains("none fits the deadline"), "{}", p.why);
}

#[test]
fn foveation_is_offered_only_where_its_full_resolution_covers_the_fovea() {
    let input = panel_frame(2.5);
    let stats = FrameStats::from_rgbd(&input, [480.0, 540.0], Diopters(0.5), &EyeModel::default());
    // The planner's fovea: 5 degrees around the gaze (`planner::FOVEA_RADIUS_DEG`, the
    // foveated render's default radius), in degrees of the eye's field at any size.
    let at = |radius_deg| {
        Setting::Foveated(Foveation {
            gaze: stats.gaze,
            radius_deg,
            mar_slope: DEFAULT_MAR_SLOPE,
        })
    };
    assert!(Planner.predict_setting_psnr(&stats, &at(5.0)).is_some());
    assert!(Planner.predict_setting_psnr(&stats, &at(1.0)).is_none());
    assert_eq!(
        Planner.predict_setting_psnr(&stats, &at(5.0)),
        Planner.predict_setting_psnr(&stats, &Setting::Pyramid)
    );
    assert!(matches!(
        at(5.0).method(),
        Some(DefocusMethod::Pyramid(PyramidParams { foveation: Some(_) }))
    ));
    assert_eq!(Setting::Classic(Choice::None).method(), None);
}

/// Under a budget that the rig's own foveation misses, the planner coarsens the periphery
/// (keeping the fovea's full-resolution radius) rather than dropping the blur.
#[test]
fn a_budget_between_the_rigs_foveation_and_a_coarser_one_coarsens_the_periphery() {
    // 90 degrees over 2160 px, focused far with content to 4 D: the periphery is most of the
    // image and much of it blurred by 6 px or more.
    let eye = EyeModel {
        fov_horizontal_deg: 90.0,
        ..EyeModel::default()
    };
    let stats = FrameStats::typical(
        2160,
        2160,
        &eye,
        (Diopters(4.0), Diopters(0.0)),
        Diopters(0.0),
    );
    // The planner's fovea is 5 degrees around the gaze: a full-resolution radius of 10
    // degrees covers it.
    let rig = FoveationSettings {
        radius_deg: 10.0,
        mar_slope: DEFAULT_MAR_SLOPE,
    };
    let at = |slope| {
        Setting::Foveated(Foveation {
            gaze: stats.gaze,
            radius_deg: 10.0,
            mar_slope: slope,
        })
    };
    let ms = |s: Setting| Planner.predict_setting_ms(&stats, &s, 2);
    let (own, coarse) = (ms(at(DEFAULT_MAR_SLOPE)), ms(at(4.0 * DEFAULT_MAR_SLOPE)));
    eprintln!(
        "2160 x 2160 over 90 deg: pyramid {:.1} ms, foveated {own:.1} ms, 4x coarser periphery {coarse:.1} ms",
        ms(Setting::Pyramid)
    );
    assert!(
        coarse < own && own < ms(Setting::Pyramid),
        "{coarse} vs {own}"
    );
    // A target only the pyramid family meets (no pass-through): 1 dB under its prediction.
    let target = Target {
        fovea_psnr_db: Planner
            .predict_setting_psnr(&stats, &Setting::Pyramid)
            .unwrap()
            - 1.0,
        periphery_psnr_db: None,
    };
    assert!(
        Planner
            .predict_setting_psnr(&stats, &Setting::Classic(Choice::None))
            .unwrap()
            < target.fovea_psnr_db
    );
    let deadline = Deadline::from_period(0.5 * (own + coarse) + 1.0, 1.0, 2);
    let p = Planner.plan_within(&stats, &target, &deadline, Some(rig));
    eprintln!("{}", p.why);
    assert!(p.meets_deadline && p.meets_target, "{}", p.why);
    let Setting::Foveated(f) = p.setting else {
        panic!("{}", p.why)
    };
    assert!(f.mar_slope > DEFAULT_MAR_SLOPE, "{}", p.why);
    assert_eq!(f.radius_deg, 10.0);
    assert!(p.why.contains("coarser"), "{}", p.why);
    // A target on the periphery forbids it: the rig's slope or nothing foveated.
    let strict = Target {
        periphery_psnr_db: Some(30.0),
        ..target
    };
    let p = Planner.plan_within(&stats, &strict, &deadline, Some(rig));
    if let Setting::Foveated(f) = p.setting {
        assert_eq!(f.mar_slope, DEFAULT_MAR_SLOPE, "{}", p.why);
    }
    assert!(!p.meets_deadline || !p.meets_target, "{}", p.why);
}

/// The daemon's start-up figure: the predicted cost of a frame at the rig's size, method,
/// backend and foveation.
#[test]
fn predict_frame_cost_scales_with_eyes_and_size_and_refuses_what_it_cannot_model() {
    let eye = EyeModel::default();
    let mono = FrameSpec {
        cores: 2,
        ..FrameSpec::new(960, 1080, eye)
    };
    let one = predict_frame_cost(&mono).unwrap();
    let two = predict_frame_cost(&FrameSpec {
        eyes: 2,
        ..mono.clone()
    })
    .unwrap();
    eprintln!("{}\n{}", one.summary, two.summary);
    assert!((two.wall_ms - 2.0 * one.wall_ms).abs() < 1e-9);
    assert!((one.cpu_ms - 2.0 * one.wall_ms).abs() < 1e-9);
    assert!(one.wall_ms > 0.0 && one.summary.contains("960 x 1080"));
    let big = predict_frame_cost(&FrameSpec {
        width: 1440,
        height: 1600,
        ..mono.clone()
    })
    .unwrap();
    assert!(big.wall_ms > one.wall_ms);
    // Four cores halve the wall time of the same CPU time.
    let four = predict_frame_cost(&FrameSpec {
        cores: 4,
        ..mono.clone()
    })
    .unwrap();
    assert!((four.wall_ms - 0.5 * one.wall_ms).abs() < 1e-9);
    // Gather costs more than the pyramid at a panel's blur; foveation over a wide field less.
    let gather = predict_frame_cost(&FrameSpec {
        method: DefocusMethod::Gather,
        ..mono.clone()
    })
    .unwrap();
    assert!(
        gather.wall_ms > 3.0 * one.wall_ms,
        "{} / {}",
        gather.summary,
        one.summary
    );
    let wide = EyeModel {
        fov_horizontal_deg: 90.0,
        ..eye
    };
    let fov = Some(FoveationSettings {
        radius_deg: 5.0,
        mar_slope: DEFAULT_MAR_SLOPE,
    });
    let full = predict_frame_cost(&FrameSpec {
        eye: wide,
        ..mono.clone()
    })
    .unwrap();
    let foveated = predict_frame_cost(&FrameSpec {
        eye: wide,
        foveation: fov,
        ..mono.clone()
    })
    .unwrap();
    eprintln!("{}\n{}", full.summary, foveated.summary);
    assert!(foveated.wall_ms < full.wall_ms);
    assert!(matches!(foveated.setting, Setting::Foveated(_)));
    // The budget check.
    assert!(one.fits(&Deadline::from_period(one.wall_ms + 2.0, 1.0, 2)));
    assert!(!one.fits(&Deadline::from_period(one.wall_ms, 1.0, 2)));
    // What it cannot model is an error that says so.
    for (spec, want) in [
        (
            FrameSpec {
                backend: "gpu".into(),
                ..mono.clone()
            },
            "gpu",
        ),
        (
            FrameSpec {
                backend: "tpu".into(),
                ..mono.clone()
            },
            "unknown backend",
        ),
        (
            FrameSpec {
                method: DefocusMethod::Gather,
                foveation: fov,
                ..mono.clone()
            },
            "pyramid",
        ),
        (
            FrameSpec {
                width: 0,
                ..mono.clone()
            },
            "nothing to render",
        ),
        (
            FrameSpec {
                depths: (Diopters(f32::NAN), Diopters(0.0)),
                ..mono.clone()
            },
            "not finite",
        ),
        (
            FrameSpec {
                foveation: Some(FoveationSettings {
                    radius_deg: 5.0,
                    mar_slope: -1.0,
                }),
                ..mono.clone()
            },
            "foveation",
        ),
    ] {
        let e = predict_frame_cost(&spec).unwrap_err().to_string();
        assert!(e.contains(want), "{e}");
    }
}

/// The planner's fovea is degrees of the eye's field, the same at every panel size: a depth
/// step 4 degrees from the gaze is inside a 5-degree fovea and outside a 2-degree one.
#[test]
fn the_fovea_is_degrees_of_the_eyes_field() {
    let eye = EyeModel::default();
    for size in [160usize, 480] {
        let step = size / 2 + (4.0 * size as f32 / eye.fov_horizontal_deg) as usize;
        let tex = vec![0.5f32; size * size * 3];
        let d: Vec<f32> = (0..size * size)
            .map(|i| if i % size >= step { 3.0 } else { 1.0 })
            .collect();
        let input = Rgbd::new(
            RgbImage::from_interleaved(size, size, &tex).unwrap(),
            DepthMap::from_diopters(Plane::from_vec(size, size, d).unwrap()).unwrap(),
        )
        .unwrap();
        let gaze = [0.5 * size as f32, 0.5 * size as f32];
        let region =
            |deg| FrameStats::from_rgbd_around(&input, gaze, deg, Diopters(1.0), &eye).region_range;
        assert_eq!(region(2.0), (Diopters(1.0), Diopters(1.0)), "{size} px");
        assert_eq!(region(5.0), (Diopters(3.0), Diopters(1.0)), "{size} px");
        let st = FrameStats::from_rgbd(&input, gaze, Diopters(1.0), &eye);
        assert_eq!(
            st.fovea_radius_deg,
            dioptra_render::planner::FOVEA_RADIUS_DEG
        );
        assert_eq!(st.region_range, region(5.0));
    }
}
