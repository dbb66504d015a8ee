//! GPU against CPU inference: the C1 architecture at interleave rates 1, 2 and 4 and the C4
//! architecture, random weights (biases too) and random inputs, compared per value. Without
//! an adapter each test prints "skipped: no GPU adapter" and returns; with
//! DIOPTRA_REQUIRE_GPU=1 (set by .ci/run) it fails instead. Sizes are small (lavapipe) and
//! not multiples of the rate, so padding and cropping are exercised.

use dioptra_core::{DepthMap, Diopters, EyeModel, Plane, RgbImage, Rgbd};
use dioptra_net::gpu::GpuNet;
use dioptra_net::weights::SplitMix;
use dioptra_net::{Act, Arch, CpuNet, Weights};
use dioptra_render::GpuError;

fn gpu_ok() -> bool {
    match dioptra_render::gpu::GpuContext::shared(None) {
        Ok(_) => true,
        Err(GpuError::NoAdapter) if std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("skipped: no GPU adapter");
            false
        }
        Err(e) => panic!("GPU required (DIOPTRA_REQUIRE_GPU=1) or failed to open: {e}"),
    }
}

/// Random weights with random biases (Weights::random leaves them at zero).
fn weights(arch: &Arch, seed: u64) -> Weights {
    let mut w = Weights::random(arch, seed).unwrap();
    let mut r = SplitMix(seed ^ 0xb1a5);
    for c in &mut w.convs {
        for b in &mut c.bias {
            *b = 0.1 * r.uniform();
        }
    }
    w
}

fn random_act(h: usize, w: usize, c: usize, seed: u64) -> Act {
    let mut r = SplitMix(seed);
    Act::new(h, w, c, (0..h * w * c).map(|_| r.uniform()).collect()).unwrap()
}

fn max_diff(a: &Act, b: &Act) -> f32 {
    assert_eq!((a.h, a.w, a.c), (b.h, b.w, b.c));
    a.data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| {
            assert!(y.is_finite(), "non-finite GPU value");
            (x - y).abs()
        })
        .fold(0.0, f32::max)
}

#[test]
fn c1_at_every_rate_and_c4_match_cpu() {
    if !gpu_ok() {
        return;
    }
    let c4 = Arch::preset("c4").unwrap();
    let cases = [
        (
            "c1 r=1",
            Arch {
                rate: 1,
                ..Arch::c1_small()
            },
            21,
            18,
        ),
        ("c1 r=2", Arch::c1_small(), 37, 30),
        (
            "c1 r=4",
            Arch {
                rate: 4,
                ..Arch::c1_small()
            },
            45,
            38,
        ),
        ("c4 r=2", c4, 33, 26),
    ];
    for (i, (name, arch, w, h)) in cases.into_iter().enumerate() {
        let wts = weights(&arch, 10 + i as u64);
        let cpu = CpuNet::new(wts.clone()).unwrap();
        let gpu = GpuNet::new(wts, None).unwrap();
        // Inputs in [-1, 1): wider than real images, so the ELU and tanh both see both signs.
        let x = random_act(h, w, arch.in_channels(), 100 + i as u64);
        let want = cpu.forward(&x).unwrap();
        let got = gpu.forward(&x).unwrap();
        let err = max_diff(&want, &got);
        // Same graph and operations; only the summation order of each 3x3xC dot product
        // differs (GEMM on the CPU, 8-channel chunks on the GPU): f32 rounding, ~1e-6.
        eprintln!("{name} {w}x{h}: max |gpu - cpu| = {err:e}");
        assert!(err < 1e-3, "{name}: {err}");
        let s = gpu.last_stats();
        eprintln!(
            "{name}: {} dispatches, {} submissions, {} B up, {} B down",
            s.dispatches, s.submissions, s.bytes_uploaded, s.bytes_read_back
        );
        assert_eq!(s.submissions, 1, "one submission per forward pass");
        // Interleave, 8 convolutions, 3 residual adds, tanh, de-interleave.
        assert_eq!(s.dispatches, 14, "{name}");
        // One readback: the output only.
        let out_bytes = 4
            * (h.div_ceil(arch.rate) * arch.rate)
            * (w.div_ceil(arch.rate) * arch.rate)
            * arch.out_channels();
        assert_eq!(s.bytes_read_back, out_bytes as u64, "{name}");
    }
}

#[test]
fn concatenated_input_matches_cpu() {
    if !gpu_ok() {
        return;
    }
    // C5's wiring (the interleaved input concatenated before the last layer), kept small.
    let arch = Arch {
        layers: 4,
        channels: 8,
        ..Arch::preset("c5").unwrap()
    };
    let wts = weights(&arch, 7);
    let cpu = CpuNet::new(wts.clone()).unwrap();
    let gpu = GpuNet::new(wts, None).unwrap();
    let x = random_act(10, 14, arch.in_channels(), 8);
    let err = max_diff(&cpu.forward(&x).unwrap(), &gpu.forward(&x).unwrap());
    eprintln!("c5-like 14x10: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "{err}");
}

fn rgbd(w: usize, h: usize, seed: u64) -> Rgbd {
    let mut r = SplitMix(seed);
    let c: Vec<f32> = (0..w * h * 3).map(|_| 0.5 + 0.5 * r.uniform()).collect();
    let d: Vec<f32> = (0..w * h).map(|_| 1.5 + 1.5 * r.uniform()).collect();
    Rgbd::new(
        RgbImage::from_interleaved(w, h, &c).unwrap(),
        DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap(),
    )
    .unwrap()
}

#[test]
fn defocus_and_decompose_match_cpu_and_refuse_bad_input() {
    if !gpu_ok() {
        return;
    }
    let input = rgbd(30, 22, 3);
    let eye = EyeModel::default();
    let c1 = weights(&Arch::c1_small(), 1);
    let (cpu, gpu) = (
        CpuNet::new(c1.clone()).unwrap(),
        GpuNet::new(c1, None).unwrap(),
    );
    let a = cpu.defocus(&input, Diopters(1.0), &eye).unwrap();
    let b = gpu.defocus(&input, Diopters(1.0), &eye).unwrap();
    for c in 0..3 {
        let err = a.channels[c]
            .data()
            .iter()
            .zip(b.channels[c].data())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-3, "defocus channel {c}: {err}");
    }
    assert!(gpu.decompose(&input).is_err(), "a C1 net cannot decompose");
    assert!(
        gpu.forward(&random_act(8, 8, 4, 1)).is_err(),
        "C1 takes 5 channels"
    );
    let c4 = weights(&Arch::preset("c4").unwrap(), 2);
    let (cpu, gpu) = (
        CpuNet::new(c4.clone()).unwrap(),
        GpuNet::new(c4, None).unwrap(),
    );
    let a = cpu.decompose(&input).unwrap();
    let b = gpu.decompose(&input).unwrap();
    assert_eq!(a.planes, b.planes);
    for (la, lb) in a.images.iter().zip(&b.images) {
        for c in 0..3 {
            let err = la.channels[c]
                .data()
                .iter()
                .zip(lb.channels[c].data())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            assert!(err < 1e-3, "decompose: {err}");
        }
    }
}

#[test]
fn shipped_weights_run_on_the_gpu_like_on_the_cpu() {
    if !gpu_ok() {
        return;
    }
    // Through the loading code the CLI uses for --backend gpu, on a 40x34 RGB-D input.
    let input = rgbd(40, 34, 5);
    let eye = EyeModel::default();
    let cpu = dioptra_net::load_net(None, "c1").unwrap();
    let gpu = dioptra_net::gpu::load_gpu_net(None, "c1", None).unwrap();
    let a = cpu.defocus(&input, Diopters(2.0), &eye).unwrap();
    let b = gpu.defocus(&input, Diopters(2.0), &eye).unwrap();
    let err = (0..3)
        .flat_map(|c| a.channels[c].data().iter().zip(b.channels[c].data()))
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    eprintln!("shipped c1: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "shipped c1: {err}");
    let cpu = dioptra_net::load_net(None, "c4").unwrap();
    let gpu = dioptra_net::gpu::load_gpu_net(None, "c4", None).unwrap();
    let (a, b) = (
        cpu.decompose(&input).unwrap(),
        gpu.decompose(&input).unwrap(),
    );
    let err = a
        .images
        .iter()
        .zip(&b.images)
        .flat_map(|(la, lb)| {
            (0..3).flat_map(move |c| la.channels[c].data().iter().zip(lb.channels[c].data()))
        })
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    eprintln!("shipped c4: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "shipped c4: {err}");
}

/// Random weights throughout, the refinement nets' zero-initialised last layer included.
fn weights_all_random(arch: &Arch, seed: u64) -> Weights {
    let mut w = weights(arch, seed);
    let mut r = SplitMix(seed ^ 0x1a57);
    for v in w.convs.iter_mut().flat_map(|c| c.weight.iter_mut()) {
        if *v == 0.0 {
            *v = 0.05 * r.uniform();
        }
    }
    w
}

#[test]
fn refinement_nets_match_cpu() {
    if !gpu_ok() {
        return;
    }
    // A depth step at column 20 of 52: the error map runs the tiles near it only.
    let (w, h) = (52, 36);
    let mut input = rgbd(w, h, 7);
    let d: Vec<f32> = (0..w * h)
        .map(|i| if i % w < 20 { 3.0 } else { 0.5 })
        .collect();
    input.depth = DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap();
    // A 5 degree field: the far side blurs by about 6 px at this width, past the map's
    // own-blur threshold (refine::MIN_OWN_BLUR_PX).
    let eye = EyeModel {
        fov_horizontal_deg: 5.0,
        ..EyeModel::default()
    };
    let q = Diopters(3.0);
    let arch = Arch {
        rate: 4,
        ..Arch::preset("c1r").unwrap()
    };
    let c1r = weights_all_random(&arch, 3);
    let (cpu, gpu) = (
        CpuNet::new(c1r.clone()).unwrap(),
        GpuNet::new(c1r, None).unwrap(),
    );
    let base = dioptra_net::refine::classical_defocus(
        &dioptra_render::Cpu,
        dioptra_net::Classical::Lightfield { views: 12 },
        &input,
        q,
        &eye,
    )
    .unwrap();
    let a = cpu.refine_defocus(&input, &base, q, &eye).unwrap();
    let b = gpu.refine_defocus(&input, &base, q, &eye).unwrap();
    assert_eq!(a.tiles, b.tiles);
    assert!(
        a.tiles.fraction() > 0.0 && a.tiles.fraction() < 1.0,
        "{}",
        a.tiles.fraction()
    );
    assert_ne!(a.image, base, "the random net corrects");
    let err = (0..3)
        .flat_map(|c| {
            a.image.channels[c]
                .data()
                .iter()
                .zip(b.image.channels[c].data())
        })
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    eprintln!("c1r: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "c1r: {err}");
    let c4r = weights_all_random(&Arch::preset("c4r").unwrap(), 4);
    let (cpu, gpu) = (
        CpuNet::new(c4r.clone()).unwrap(),
        GpuNet::new(c4r, None).unwrap(),
    );
    let planes: Vec<Diopters> = [0.2, 0.8, 1.4, 2.0].map(Diopters).to_vec();
    let linear = dioptra_render::multifocal::linear_blend(&input, &planes).unwrap();
    let (a, b) = (
        cpu.refine_decompose(&input, &linear).unwrap(),
        gpu.refine_decompose(&input, &linear).unwrap(),
    );
    let err = a
        .images
        .iter()
        .zip(&b.images)
        .flat_map(|(la, lb)| {
            (0..3).flat_map(move |c| la.channels[c].data().iter().zip(lb.channels[c].data()))
        })
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    eprintln!("c4r: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "c4r: {err}");
    // A C4R on the spectral layers: each backend's spectral decomposition, then its net.
    let mut arch = Arch::preset("c4r").unwrap();
    if let dioptra_net::Task::C4r { classical, .. } = &mut arch.task {
        *classical = dioptra_net::ClassicalLayers::Spectral;
    }
    let spectral_c4r = weights_all_random(&arch, 5);
    let (cpu_s, gpu_s) = (
        CpuNet::new(spectral_c4r.clone()).unwrap(),
        GpuNet::new(spectral_c4r, None).unwrap(),
    );
    let spectral = dioptra_net::ClassicalLayers::Spectral;
    let base_cpu = dioptra_net::refine::classical_layers(
        &dioptra_render::Cpu,
        spectral,
        &input,
        &planes,
        &eye,
    )
    .unwrap();
    let base_gpu = dioptra_net::refine::classical_layers(
        &dioptra_render::Gpu::new(None).unwrap(),
        spectral,
        &input,
        &planes,
        &eye,
    )
    .unwrap();
    let (sa, sb) = (
        cpu_s.refine_decompose(&input, &base_cpu).unwrap(),
        gpu_s.refine_decompose(&input, &base_gpu).unwrap(),
    );
    assert_ne!(sa, base_cpu, "the random net corrects");
    let err = sa
        .images
        .iter()
        .zip(&sb.images)
        .flat_map(|(la, lb)| {
            (0..3).flat_map(move |c| la.channels[c].data().iter().zip(lb.channels[c].data()))
        })
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    eprintln!("c4r on spectral: max |gpu - cpu| = {err:e}");
    assert!(err < 1e-3, "c4r on spectral: {err}");
    assert!(a
        .images
        .iter()
        .flat_map(|l| l.channels.iter().flat_map(|p| p.data()))
        .all(|v| (0.0..=1.0).contains(v)));
}

#[test]
fn c5r_matches_cpu() {
    if !gpu_ok() {
        return;
    }
    use dioptra_render::views::{synthesize_view_with_errors, RgbdView};
    // Two inputs 1 cm apart of a box before a wall; the view between them has holes and
    // depth edges for the map to mark.
    let (w, h) = (44, 30);
    let mut near = rgbd(w, h, 9);
    let d: Vec<f32> = (0..w * h)
        .map(|i| {
            if (14..26).contains(&(i % w)) {
                3.0
            } else {
                0.3
            }
        })
        .collect();
    near.depth = DepthMap::from_diopters(Plane::from_vec(w, h, d).unwrap()).unwrap();
    let inputs = [-0.005, 0.005].map(|x| RgbdView {
        position: [x, 0.0],
        rgbd: near.clone(),
    });
    let eye = EyeModel::default();
    let (view, errors) = synthesize_view_with_errors(&inputs, [0.001, 0.0], &eye).unwrap();
    // Random weights throughout, and the shipped net.
    let shipped = Weights::load(&dioptra_net::shipped_weights("c5r")).unwrap();
    for (name, c5r) in [
        (
            "random",
            weights_all_random(&Arch::preset("c5r").unwrap(), 6),
        ),
        ("shipped", shipped),
    ] {
        let (cpu, gpu) = (
            CpuNet::new(c5r.clone()).unwrap(),
            GpuNet::new(c5r, None).unwrap(),
        );
        let (a, b) = (
            cpu.refine_view(&view, &errors).unwrap(),
            gpu.refine_view(&view, &errors).unwrap(),
        );
        assert_ne!(a, view.color, "the {name} net corrects");
        let err = (0..3)
            .flat_map(|c| a.channels[c].data().iter().zip(b.channels[c].data()))
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        eprintln!("c5r ({name}): max |gpu - cpu| = {err:e}");
        assert!(err < 1e-3, "c5r ({name}): {err}");
    }
}
