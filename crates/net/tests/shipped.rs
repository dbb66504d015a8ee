//! The shipped C1 and C4 weights (`crates/net/weights/`): they load with their provenance, and
//! their accuracy on simulator test seeds is held against the classical methods on the same
//! scenes. The regression guards pin what the shipped weights measured (a margin below it);
//! the targets (C1 >= gather + 4 dB, C4 >= linear + 6 dB) are the ignored tests, which
//! fail until weights that meet them are shipped: `cargo test -p dioptra-net --test shipped
//! -- --include-ignored`.

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
    for config in ["c1", "c4"] {
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
