//! `dioptra sim scene` then `dioptra render` then `dioptra metrics`, and the errors a user
//! meets first, through the real binary.

use std::path::Path;
use std::process::Command;

fn dioptra(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(args)
        .output()
        .expect("runs");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

#[test]
fn scene_render_metrics_round_trip() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-render-{}", std::process::id()));
    let d = |p: &str| dir.join(p).display().to_string();
    let (ok, text) = dioptra(&[
        "sim",
        "scene",
        "--seed",
        "1000001",
        "--size",
        "32",
        "--slices",
        "2",
        "--range",
        "0.5,2.0",
        "--samples",
        "16",
        "--lf-grid",
        "2",
        "--out",
        &d(""),
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("Test split"), "{text}");
    for f in [
        "color.png",
        "color.exr",
        "depth.exr",
        "depth.png",
        "focalstack/focus_2.00D.exr",
        "lightfield/view_01_01.png",
    ] {
        assert!(Path::new(&d(f)).exists(), "{f} missing");
    }
    let (ok, text) = dioptra(&[
        "render",
        "--color",
        &d("color.png"),
        "--depth",
        &d("depth.exr"),
        "--focus",
        "2.0",
        "--method",
        "lightfield",
        "--views",
        "16",
        "--out",
        &d("o.png"),
    ]);
    assert!(ok, "{text}");
    let (ok, text) = dioptra(&[
        "metrics",
        "--a",
        &d("o.png"),
        "--b",
        &d("focalstack/focus_2.00D.png"),
    ]);
    assert!(ok, "{text}");
    let psnr: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("PSNR ")?.strip_suffix(" dB")?.parse().ok())
        .unwrap_or_else(|| panic!("no PSNR in {text}"));
    assert!(psnr > 20.0 && psnr.is_finite(), "{text}");
    assert!(text.contains("SSIM 0."), "{text}");

    // Clear errors: a missing file, an unreadable format, an unknown backend.
    let (ok, text) = dioptra(&[
        "render",
        "--color",
        &d("none.png"),
        "--depth",
        &d("depth.exr"),
        "--focus",
        "1",
        "--out",
        &d("x.png"),
    ]);
    assert!(
        !ok && text.contains("none.png") && text.contains("not found"),
        "{text}"
    );
    std::fs::write(d("bad.png"), b"not a png").unwrap();
    let (ok, text) = dioptra(&["metrics", "--a", &d("color.png"), "--b", &d("bad.png")]);
    assert!(!ok && text.contains("bad.png"), "{text}");
    let (ok, text) = dioptra(&[
        "render",
        "--color",
        &d("color.png"),
        "--depth",
        &d("depth.exr"),
        "--focus",
        "1",
        "--backend",
        "vulkan",
        "--out",
        &d("x.png"),
    ]);
    assert!(!ok && text.contains("backend"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn gpu_backend_matches_cpu_through_the_binary() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-gpu-{}", std::process::id()));
    let d = |p: &str| dir.join(p).display().to_string();
    let (ok, text) = dioptra(&[
        "sim",
        "scene",
        "--seed",
        "1000002",
        "--size",
        "48",
        "--slices",
        "1",
        "--samples",
        "4",
        "--lf-grid",
        "2",
        "--out",
        &d(""),
    ]);
    assert!(ok, "{text}");
    let render = |backend: &str, out: &str| {
        dioptra(&[
            "render",
            "--color",
            &d("color.png"),
            "--depth",
            &d("depth.exr"),
            "--focus",
            "1.5",
            "--method",
            "lightfield",
            "--views",
            "16",
            "--backend",
            backend,
            "--out",
            &d(out),
        ])
    };
    let (ok, text) = render("gpu", "gpu.exr");
    if !ok && text.contains("no GPU adapter") {
        assert!(
            std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1"),
            "DIOPTRA_REQUIRE_GPU=1 but: {text}"
        );
        eprintln!("skipped: no GPU adapter");
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    assert!(ok, "{text}");
    let (ok, text) = render("cpu", "cpu.exr");
    assert!(ok, "{text}");
    let (ok, text) = dioptra(&["metrics", "--a", &d("gpu.exr"), "--b", &d("cpu.exr")]);
    assert!(ok, "{text}");
    let psnr: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("PSNR ")?.strip_suffix(" dB")?.parse().ok())
        .unwrap_or(f64::INFINITY);
    assert!(psnr > 90.0, "{text}");
    // An adapter that does not exist is an error naming the ones that do.
    let (ok, text) = dioptra(&[
        "render",
        "--color",
        &d("color.png"),
        "--depth",
        &d("depth.exr"),
        "--focus",
        "1",
        "--adapter",
        "no-such-adapter-xyz",
        "--out",
        &d("x.png"),
    ]);
    assert!(
        !ok && text.contains("no-such-adapter-xyz") && text.contains("available"),
        "{text}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn network_and_foveate_run_on_the_gpu_through_the_binary() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-gpu-net-{}", std::process::id()));
    let d = |p: &str| dir.join(p).display().to_string();
    let (ok, text) = dioptra(&[
        "sim",
        "scene",
        "--seed",
        "1000003",
        "--size",
        "40",
        "--slices",
        "1",
        "--samples",
        "4",
        "--lf-grid",
        "2",
        "--out",
        &d(""),
    ]);
    assert!(ok, "{text}");
    // Random C1 and C4 weights: the shipped ones may not exist in this tree.
    for (name, arch) in [
        ("c1", dioptra_net::Arch::c1_small()),
        ("c4", dioptra_net::Arch::preset("c4").unwrap()),
    ] {
        let w = dioptra_net::Weights::random(&arch, 5).unwrap();
        std::fs::write(
            dir.join(format!("{name}.safetensors")),
            w.to_bytes().unwrap(),
        )
        .unwrap();
    }
    let net = |backend: &str, out: &str| {
        dioptra(&[
            "render",
            "--color",
            &d("color.png"),
            "--depth",
            &d("depth.exr"),
            "--focus",
            "1.0",
            "--method",
            "network",
            "--weights",
            &d("c1.safetensors"),
            "--backend",
            backend,
            "--out",
            &d(out),
        ])
    };
    let (ok, text) = net("gpu", "gpu.exr");
    if !ok && text.contains("no GPU adapter") {
        assert!(
            std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1"),
            "DIOPTRA_REQUIRE_GPU=1 but: {text}"
        );
        eprintln!("skipped: no GPU adapter");
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    assert!(ok, "{text}");
    let (ok, text) = net("cpu", "cpu.exr");
    assert!(ok, "{text}");
    let psnr = |a: &str, b: &str| -> f64 {
        let (ok, text) = dioptra(&["metrics", "--a", &d(a), "--b", &d(b)]);
        assert!(ok, "{text}");
        text.lines()
            .find_map(|l| l.strip_prefix("PSNR ")?.strip_suffix(" dB")?.parse().ok())
            .unwrap_or(f64::INFINITY)
    };
    assert!(psnr("gpu.exr", "cpu.exr") > 60.0);
    for backend in ["gpu", "cpu"] {
        let (ok, text) = dioptra(&[
            "decompose",
            "--color",
            &d("color.png"),
            "--depth",
            &d("depth.exr"),
            "--method",
            "network",
            "--weights",
            &d("c4.safetensors"),
            "--backend",
            backend,
            "--out",
            &d(&format!("layers_{backend}")),
        ]);
        assert!(ok, "{text}");
    }
    assert!(psnr("layers_gpu/layer_0.80D.exr", "layers_cpu/layer_0.80D.exr") > 60.0);
    for backend in ["gpu", "cpu"] {
        let (ok, text) = dioptra(&[
            "foveate",
            "--color",
            &d("color.png"),
            "--scale",
            "2",
            "--backend",
            backend,
            "--out",
            &d(&format!("fov_{backend}.exr")),
        ]);
        assert!(
            ok && text.contains(&format!("on the {backend} backend")),
            "{text}"
        );
    }
    assert!(psnr("fov_gpu.exr", "fov_cpu.exr") > 60.0);
    std::fs::remove_dir_all(&dir).ok();
}
