//! The training framework against CPU inference, and training itself on tiny problems.
#![cfg(feature = "train")]

use candle_core::{Device, Tensor};
use dioptra_core::{Diopters, EyeModel, Plane, RgbImage};
use dioptra_net::train::data::DataSpec;
use dioptra_net::train::retina::Retina;
use dioptra_net::train::{train, CandleNet, TrainConfig, TrainEvent};
use dioptra_net::weights::SplitMix;
use dioptra_net::{Act, Arch, CpuNet, Task, Weights};
use dioptra_render::Layers;
use std::collections::HashMap;
use std::path::Path;

/// Tolerance between candle's forward pass and ours: both f32, different summation orders.
const TOL: f32 = 1e-4;

fn vector_arch() -> Arch {
    // Odd layer count with a residual into the last layer, and the input concatenation.
    Arch {
        task: Task::C1,
        rate: 2,
        layers: 5,
        channels: 8,
        concat_input: true,
        unet_channels: 0,
    }
}

fn small_fv_arch() -> Arch {
    let mut a = Arch::preset("fv").unwrap();
    (a.layers, a.channels, a.unet_channels) = (5, 8, 6);
    a
}

fn nchw_to_act(t: &Tensor) -> Act {
    let (_, c, h, w) = t.dims4().unwrap();
    let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let mut data = vec![0.0; c * h * w];
    for ci in 0..c {
        for p in 0..h * w {
            data[p * c + ci] = v[ci * h * w + p];
        }
    }
    Act::new(h, w, c, data).unwrap()
}

fn random_input(c: usize, h: usize, w: usize, seed: u64) -> Tensor {
    let mut r = SplitMix(seed);
    let v: Vec<f32> = (0..c * h * w).map(|_| r.uniform()).collect();
    Tensor::from_vec(v, (1, c, h, w), &Device::Cpu).unwrap()
}

fn max_err(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn candle_forward_matches_cpu_inference() {
    for (arch, seed) in [
        (vector_arch(), 1),
        (Arch::preset("c4").unwrap(), 2),
        (small_fv_arch(), 3),
    ] {
        let w = Weights::random(&arch, seed).unwrap();
        // Larger weights than the init, so the tanh is exercised away from 0.5.
        let mut w = w;
        for c in &mut w.convs {
            c.weight.iter_mut().for_each(|v| *v *= 3.0);
        }
        let net = CandleNet::from_weights(&w, &Device::Cpu).unwrap();
        // Candle's input must be a multiple of the size multiple (8 with the U-Net).
        let (h, wd) = if arch.unet_channels > 0 {
            (16, 24)
        } else {
            (12, 16)
        };
        let x = random_input(arch.in_channels(), h, wd, seed);
        let want = nchw_to_act(&net.forward(&x).unwrap());
        assert_eq!((want.c, want.h, want.w), (arch.out_channels(), h, wd));
        let got = CpuNet::new(w).unwrap().forward(&nchw_to_act(&x)).unwrap();
        let spread = want.data.iter().fold(0.0f32, |m, v| m.max((v - 0.5).abs()));
        assert!(
            spread > 0.05,
            "outputs all near 0.5: the test would not see errors"
        );
        let e = max_err(&got.data, &want.data);
        assert!(e < TOL, "{}: max |cpu - candle| = {e}", arch.task.name());
    }
}

fn data_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data"))
}

/// Regenerates the committed vectors from candle's forward pass:
/// `cargo test -p dioptra-net --test train -- --ignored regenerate_vectors`.
#[test]
#[ignore]
fn regenerate_vectors() {
    let mut w = Weights::random(&vector_arch(), 42).unwrap();
    for c in &mut w.convs {
        c.weight.iter_mut().for_each(|v| *v *= 3.0);
    }
    w.provenance.insert("purpose".into(), "test vectors".into());
    let net = CandleNet::from_weights(&w, &Device::Cpu).unwrap();
    let x = random_input(5, 10, 14, 43);
    let y = net.forward(&x).unwrap();
    w.save(&data_dir().join("vectors_weights.safetensors"))
        .unwrap();
    let t: HashMap<String, Tensor> = [("input".into(), x), ("output".into(), y)].into();
    candle_core::safetensors::save(&t, data_dir().join("vectors_io.safetensors")).unwrap();
}

#[test]
fn cpu_inference_matches_committed_candle_vectors() {
    let w = Weights::load(&data_dir().join("vectors_weights.safetensors")).unwrap();
    assert_eq!(w.arch, vector_arch());
    let io =
        candle_core::safetensors::load(data_dir().join("vectors_io.safetensors"), &Device::Cpu)
            .unwrap();
    let (x, y) = (nchw_to_act(&io["input"]), nchw_to_act(&io["output"]));
    assert_eq!((x.h, x.w, x.c, y.c), (10, 14, 5, 3));
    let got = CpuNet::new(w).unwrap().forward(&x).unwrap();
    let e = max_err(&got.data, &y.data);
    assert!(e < TOL, "max |cpu - stored candle output| = {e}");
}

#[test]
fn differentiable_retina_matches_the_renderer() {
    let eye = EyeModel::default().with_width(192);
    let planes = [0.2f32, 0.8, 1.4, 2.0];
    let foci = [0.1f32, 1.0, 2.2];
    let mut r = SplitMix(5);
    let imgs: Vec<RgbImage> = (0..4)
        .map(|_| {
            let p = |r: &mut SplitMix| {
                Plane::from_vec(
                    192,
                    40,
                    (0..192 * 40).map(|_| 0.5 + 0.5 * r.uniform()).collect(),
                )
                .unwrap()
            };
            RgbImage::from_planes(p(&mut r), p(&mut r), p(&mut r)).unwrap()
        })
        .collect();
    let layers = Layers {
        planes: planes.iter().map(|&p| Diopters(p)).collect(),
        images: imgs.clone(),
    };
    let want = dioptra_render::retina::retina_multifocal(
        &layers,
        &foci.map(Diopters),
        &EyeModel::default(),
    )
    .unwrap();
    let ret = Retina::new(&planes, &foci, &eye, &Device::Cpu).unwrap();
    assert!(ret.radius >= 2, "kernels too small to test anything");
    let v: Vec<f32> = imgs
        .iter()
        .flat_map(|im| im.channels.iter().flat_map(|c| c.data().to_vec()))
        .collect();
    let x = Tensor::from_vec(v, (1, 12, 40, 192), &Device::Cpu).unwrap();
    let got = ret
        .apply(&x)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let rad = ret.radius;
    for (j, img) in want.iter().enumerate() {
        for c in 0..3 {
            for y in rad..40 - rad {
                for xx in rad..192 - rad {
                    let g = got[((3 * j + c) * 40 + y) * 192 + xx];
                    let w = img.channels[c].data()[y * 192 + xx];
                    assert!(
                        (g - w).abs() < 1e-3,
                        "focus {j} c {c} ({xx},{y}): {g} vs {w}"
                    );
                }
            }
        }
    }
}

fn tiny_config(task: &str, out: &Path, steps: u64) -> TrainConfig {
    let mut arch = Arch::preset(task).unwrap();
    arch.layers = 4;
    arch.channels = 12;
    let mut cfg = TrainConfig::new(arch, out.to_path_buf());
    cfg.steps = steps;
    cfg.batch = 4;
    cfg.patch = 24;
    cfg.lr = 3e-3;
    cfg.scenes = 2;
    cfg.foci_per_scene = 3;
    cfg.checkpoint_every = 5;
    cfg.data = DataSpec {
        size: 32,
        supersample: 1,
        samples: 4,
        ..DataSpec::default()
    };
    cfg
}

fn run(cfg: &TrainConfig) -> (Weights, Vec<f32>, Option<u64>) {
    let mut losses = vec![];
    let mut resumed = None;
    let w = train(cfg, &mut |e| match e {
        TrainEvent::Step { loss, .. } => losses.push(loss),
        TrainEvent::Resumed { step } => resumed = Some(step),
        _ => {}
    })
    .unwrap();
    (w, losses, resumed)
}

#[test]
fn c1_training_lowers_the_loss_and_exports_loadable_weights() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config("c1", dir.path(), 40);
    let (w, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[35..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.1, "loss went from {first} to {last}");
    let back = Weights::load(&dir.path().join("c1.safetensors")).unwrap();
    assert_eq!(back.convs, w.convs);
    assert_eq!(back.provenance["steps"], "40");
    assert_eq!(back.provenance["train_seeds"], "0..2");
}

#[test]
fn c4_training_through_the_retina_lowers_the_loss() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c4", dir.path(), 30);
    // Fewer focal samples keep the ground truth cheap.
    cfg.arch.task = Task::C4 {
        planes: vec![0.2, 0.8, 1.4, 2.0],
        foci: vec![0.1, 0.7, 1.4, 2.2],
    };
    let (_, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[25..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.1, "loss went from {first} to {last}");
}

#[test]
fn fv_training_over_several_sampling_rates_lowers_the_loss() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("fv", dir.path(), 40);
    cfg.arch.unet_channels = 4;
    let (w, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[35..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.1, "loss went from {first} to {last}");
    let back = Weights::load(&dir.path().join("fv.safetensors")).unwrap();
    assert_eq!(back.convs, w.convs);
    assert!(back.provenance["data"].contains("foveated"));
    // One view-grid cache file per training scene.
    let cached = std::fs::read_dir(dir.path().join("cache")).unwrap().count();
    assert_eq!(cached, 2);
}

#[test]
fn c5_training_on_view_grids_lowers_the_loss() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c5", dir.path(), 30);
    cfg.arch.task = Task::C5 { views: 5, grid: 3 };
    let (_, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[25..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.1, "loss went from {first} to {last}");
}

#[test]
fn fv_patches_must_fit_the_unet() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("fv", dir.path(), 1);
    cfg.patch = 20; // a multiple of the rate but not of 8
    let e = train(&cfg, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("multiple of 8"), "{e}");
}

#[test]
fn resumed_training_equals_uninterrupted_training() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let (straight, _, _) = run(&tiny_config("c1", a.path(), 10));
    // "Interrupted" after 5 steps (a checkpoint), then rerun with the full count.
    let (_, _, r0) = run(&tiny_config("c1", b.path(), 5));
    assert_eq!(r0, None);
    let (resumed, losses, r1) = run(&tiny_config("c1", b.path(), 10));
    assert_eq!(r1, Some(5));
    assert_eq!(losses.len(), 5);
    for (x, y) in straight.convs.iter().zip(&resumed.convs) {
        let e = max_err(&x.weight, &y.weight);
        assert!(e < 1e-6, "resumed weights differ by {e}");
    }
    // A different architecture in the same directory is refused, not silently mixed.
    let mut other = tiny_config("c1", b.path(), 12);
    other.arch.channels = 16;
    assert!(train(&other, &mut |_| {}).is_err());
}

#[test]
fn fv_unet_changes_the_output_and_odd_sizes_are_padded() {
    let arch = small_fv_arch();
    let w = Weights::random(&arch, 4).unwrap();
    let x = nchw_to_act(&random_input(arch.in_channels(), 13, 19, 5));
    let y = CpuNet::new(w.clone()).unwrap().forward(&x).unwrap();
    assert_eq!((y.h, y.w, y.c), (13, 19, 27));
    // Zeroing the U-Net's last convolution changes the output: the branch is wired in.
    let mut cut = w.clone();
    let last = cut.convs.last_mut().unwrap();
    last.weight.iter_mut().for_each(|v| *v = 0.0);
    let z = CpuNet::new(cut).unwrap().forward(&x).unwrap();
    assert!(max_err(&y.data, &z.data) > 1e-4);
}

#[test]
fn adam_moments_and_variables_hold_no_graph_after_a_step() {
    // A moment that kept its gradient's graph would chain every step's graph to the next and
    // grow without bound (it did: 24 GB after 300 C1 steps).
    let arch = vector_arch();
    let net = CandleNet::from_weights(&Weights::random(&arch, 3).unwrap(), &Device::Cpu).unwrap();
    let vars = net.vars();
    let mut adam = dioptra_net::train::Adam::new(&vars, 1e-3).unwrap();
    let x = random_input(arch.in_channels(), 8, 8, 4);
    for _ in 0..2 {
        let loss = net.forward(&x).unwrap().sqr().unwrap().mean_all().unwrap();
        adam.step(&vars, &loss.backward().unwrap()).unwrap();
    }
    assert!(adam.m.iter().chain(&adam.v).all(|t| !t.track_op()));
    assert!(vars.iter().all(|v| v.as_tensor().is_variable()));
}

#[test]
fn c1r_training_lowers_the_loss_from_the_classical_render() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c1r", dir.path(), 40);
    cfg.arch.task = Task::C1r {
        classical: dioptra_net::Classical::Gather,
    };
    cfg.arch.layers = 3;
    // Large blur on the tiny renders (as 512 px), the halo (3 layers x r 2) inside the patch.
    cfg.fovs = vec![5.0];
    cfg.patch = 32;
    // One scene of the occluder family, and the penalty on tiles made worse (both 16 x 16
    // tiles of a 32 px patch).
    cfg.occluder_scenes = 1;
    cfg.no_worse = 1.0;
    let (w, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[35..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.05, "loss went from {first} to {last}");
    let back = Weights::load(&dir.path().join("c1r.safetensors")).unwrap();
    assert_eq!(back.convs, w.convs);
    assert!(back.provenance["refines"].contains("gather"));
    assert!(back.provenance["fovs"].contains("5.0"));
    assert!(back.provenance["refines"].contains("16 x 16 tiles made worse"));
    assert!(back.provenance["train_occluder_seeds"].contains("generate_occluders"));
    let occluder_cache = std::fs::read_dir(&cfg.cache)
        .unwrap()
        .filter(|e| {
            let name = e.as_ref().unwrap().file_name();
            name.to_string_lossy().starts_with("occluders-")
        })
        .count();
    assert_eq!(
        occluder_cache, 1,
        "the occluder scene is cached under its own name"
    );
    // One of its foci is its wall's (looking through the occluders), the random scene's not.
    let scenes = dioptra_net::train::trainer::load_scenes(&cfg, &mut |_| {}).unwrap();
    let wall = |s: &dioptra_net::train::data::SceneData| {
        let d = 1.0 / dioptra_sim::scene::Scene::generate_occluders(s.seed).wall_depth;
        s.foci.contains(&d)
    };
    let (occluders, random) = scenes.split_last().unwrap();
    assert_eq!(random.len() as u64, cfg.scenes);
    assert!(wall(occluders), "{:?}", occluders.foci);
    assert!(!random.iter().any(wall));
    // A patch that cannot hold a tile inside the halo is refused, saying the size needed.
    cfg.patch = 24;
    let e = train(&cfg, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("at least 28"), "{e}");
}

#[test]
fn c5r_training_lowers_the_loss_from_the_classical_synthesis() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c5r", dir.path(), 40);
    // A 3 x 3 light field from its corners and centre: 4 novel views per scene; a narrow field
    // so the tiny renders have a few pixels of parallax.
    cfg.arch.task = Task::C5r { views: 5, grid: 3 };
    cfg.arch.layers = 3;
    cfg.fovs = vec![5.0];
    cfg.patch = 32;
    let (w, losses, _) = run(&cfg);
    let first: f32 = losses[..5].iter().sum::<f32>() / 5.0;
    let last: f32 = losses[35..].iter().sum::<f32>() / 5.0;
    assert!(last < first - 0.05, "loss went from {first} to {last}");
    let back = Weights::load(&dir.path().join("c5r.safetensors")).unwrap();
    assert_eq!(back.convs, w.convs);
    assert!(back.provenance["refines"].contains("warp's error map"));
    assert!(back.provenance["data"].contains("4 novel views per scene"));
}

/// Light-field nets train on every scene family: each training light field is its own
/// family's scene (seeds numbered per family, cached apart).
#[test]
fn light_field_training_scenes_come_from_their_family() {
    use dioptra_net::train::trainer::load_scenes;
    use dioptra_sim::scene::{render_pinhole, Camera, Family, Scene};
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c5r", dir.path(), 1);
    cfg.arch.task = Task::C5r { views: 5, grid: 3 };
    (cfg.scenes, cfg.occluder_scenes, cfg.wide_scenes) = (1, 1, 1);
    cfg.data.size = 16;
    let scenes = load_scenes(&cfg, &mut |_| {}).unwrap();
    let families: Vec<Family> = scenes.iter().map(|s| s.family).collect();
    assert_eq!(families, [Family::Random, Family::Occluders, Family::Wide]);
    for s in &scenes {
        let cam = Camera::square(cfg.data.eye().unwrap(), 16);
        let (centre, _) =
            render_pinhole(&Scene::of_family(s.family, s.seed), &cam, [0.0; 2], 1).unwrap();
        assert_eq!(s.rgbd.color, centre, "{:?}", s.family);
    }
    // All three share seed 0, so each family's scene differs from the random one.
    assert!(scenes[1].rgbd.color != scenes[0].rgbd.color);
    assert!(scenes[2].rgbd.color != scenes[0].rgbd.color);
    let cached = std::fs::read_dir(&cfg.cache).unwrap().count();
    assert_eq!(cached, 3, "one cache file per family's light field");
}

#[test]
fn c4r_training_distils_then_lowers_the_retinal_loss() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c4r", dir.path(), 30);
    cfg.arch.task = Task::C4r {
        planes: vec![0.2, 0.8, 1.4, 2.0],
        foci: vec![0.1, 0.7, 1.4, 2.2],
        classical: dioptra_net::ClassicalLayers::Linear,
    };
    cfg.distill_steps = 15;
    let (_, losses, _) = run(&cfg);
    // Each phase's loss falls (they measure different things).
    let mean = |s: &[f32]| s.iter().sum::<f32>() / s.len() as f32;
    assert!(
        mean(&losses[10..15]) < mean(&losses[..5]) - 0.05,
        "distillation: {losses:?}"
    );
    assert!(
        mean(&losses[25..30]) < mean(&losses[15..20]) - 0.02,
        "retina: {losses:?}"
    );
    // Optimized blending's layers are cached per scene.
    let cached = std::fs::read_dir(dir.path().join("cache"))
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with("distill-")
        })
        .count();
    assert_eq!(cached, 2);
}

#[test]
fn c4r_on_spectral_trains_on_the_wide_family_through_a_retina_per_field_of_view() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = tiny_config("c4r", dir.path(), 30);
    cfg.arch.task = Task::C4r {
        planes: vec![0.2, 0.8, 1.4, 2.0],
        foci: vec![0.1, 0.7, 1.4, 2.2],
        classical: dioptra_net::ClassicalLayers::Spectral,
    };
    // One random scene (field 5 degrees) and one of the wide family (10 degrees).
    cfg.scenes = 1;
    cfg.wide_scenes = 1;
    cfg.fovs = vec![5.0, 10.0];
    let (w, losses, _) = run(&cfg);
    let mean = |s: &[f32]| s.iter().sum::<f32>() / s.len() as f32;
    // The fields take turns step by step: compare like with like (even steps, odd steps).
    for (what, first) in [("5 degrees", 0), ("10 degrees", 1)] {
        let l: Vec<f32> = losses.iter().skip(first).step_by(2).copied().collect();
        assert!(mean(&l[l.len() - 4..]) < mean(&l[..4]), "{what}: {l:?}");
    }
    assert_eq!(
        w.arch.task, cfg.arch.task,
        "the weights name their classical input"
    );
    let back = Weights::load(&dir.path().join("c4r.safetensors")).unwrap();
    assert!(back.provenance["refines"].contains("spectral decomposition"));
    assert!(back.provenance["refines"].contains("taking turns"));
    assert!(back.provenance["train_wide_seeds"].contains("generate_wide"));
    // The spectral layers are cached per scene and family; nothing distilled.
    let names: Vec<String> = std::fs::read_dir(dir.path().join("cache"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    let count = |p: &str| names.iter().filter(|n| n.starts_with(p)).count();
    assert_eq!(
        (
            count("spectral-scene-"),
            count("spectral-wide-"),
            count("wide-")
        ),
        (1, 1, 1),
        "{names:?}"
    );
    assert_eq!(count("distill-"), 0, "{names:?}");
    // More fields of view than scenes: a field with no scene is refused, naming it.
    cfg.fovs = vec![5.0, 10.0, 15.0];
    cfg.out = dir.path().join("other");
    let e = train(&cfg, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("15 degrees"), "{e}");
}
