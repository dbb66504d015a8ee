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

/// `dioptra sim scene` of test seed `seed` into `dir`: `size` px, one slice, a 2 x 2 light field.
fn sim_scene(dir: &Path, seed: &str, size: &str) {
    let out = dir.display().to_string();
    let (ok, text) = dioptra(&[
        "sim",
        "scene",
        "--seed",
        seed,
        "--size",
        size,
        "--slices",
        "1",
        "--samples",
        "4",
        "--lf-grid",
        "2",
        "--out",
        &out,
    ]);
    assert!(ok, "{text}");
}

/// `dioptra CMD --color DIR/color.png --depth DIR/depth.exr ARGS...` on a `sim_scene` output.
fn on_scene(dir: &Path, args: &[&str]) -> (bool, String) {
    let (color, depth) = (dir.join("color.png"), dir.join("depth.exr"));
    let (color, depth) = (color.display().to_string(), depth.display().to_string());
    let mut all = vec![args[0], "--color", &color, "--depth", &depth];
    all.extend_from_slice(&args[1..]);
    dioptra(&all)
}

/// Whether a GPU run failed for want of an adapter: the test then skips, unless
/// `DIOPTRA_REQUIRE_GPU=1` (CI), where that fails it.
fn no_gpu(ok: bool, text: &str) -> bool {
    if ok || !text.contains("no GPU adapter") {
        return false;
    }
    assert!(
        std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() != Ok("1"),
        "DIOPTRA_REQUIRE_GPU=1 but: {text}"
    );
    eprintln!("skipped: no GPU adapter");
    true
}

/// PSNR of image `a` against image `b` (`inf` when equal), from `dioptra metrics`.
fn psnr(a: &str, b: &str) -> f64 {
    let (ok, text) = dioptra(&["metrics", "--a", a, "--b", b]);
    assert!(ok, "{text}");
    text.lines()
        .find_map(|l| l.strip_prefix("PSNR ")?.strip_suffix(" dB")?.parse().ok())
        .unwrap_or_else(|| panic!("no PSNR in: {text}"))
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
    let (ok, text) = on_scene(
        &dir,
        &[
            "render",
            "--focus",
            "2.0",
            "--method",
            "lightfield",
            "--views",
            "16",
            "--out",
            &d("o.png"),
        ],
    );
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

    // The spectral decomposition (issue 42), with its defaults and with slice targets; a bad
    // setting is refused naming it.
    for extra in [
        &[][..],
        &["--target-method", "slices", "--iterations", "3"][..],
    ] {
        let out = d(&format!("spectral{}", extra.len()));
        let mut args = vec!["decompose", "--method", "spectral", "--out", &out];
        args.extend_from_slice(extra);
        let (ok, text) = on_scene(&dir, &args);
        assert!(ok && text.contains("spectral decomposition"), "{text}");
        // At 32 px the blur is small: the default solves the image's own grid.
        assert!(text.contains("full resolution"), "{text}");
        for p in ["0.20", "0.80", "1.40", "2.00"] {
            assert!(
                Path::new(&format!("{out}/layer_{p}D.exr")).exists(),
                "{text}"
            );
        }
    }
    let (ok, text) = on_scene(
        &dir,
        &[
            "decompose",
            "--method",
            "spectral",
            "--prior",
            "0",
            "--out",
            &d("bad"),
        ],
    );
    assert!(!ok && text.contains("prior"), "{text}");
    // A coarser grid asked for says so; one beyond the largest divisor is refused naming --scale.
    let spectral_at = |scale: &str, out: &str| {
        on_scene(
            &dir,
            &[
                "decompose",
                "--method",
                "spectral",
                "--scale",
                scale,
                "--out",
                &d(out),
            ],
        )
    };
    let (ok, text) = spectral_at("2", "s2");
    assert!(ok && text.contains("1/2 grid"), "{text}");
    assert!(Path::new(&d("s2/layer_0.20D.exr")).exists(), "{text}");
    let (ok, text) = spectral_at("17", "bad");
    assert!(!ok && text.contains("--scale 17"), "{text}");

    // The gaze-contingent hybrid (issue 54): the window around the gaze is solved, or the
    // frame is linear blending where no depth step reaches the fovea; either way it says
    // which. A malformed --gaze is refused naming it.
    let out = d("hybrid");
    let (ok, text) = on_scene(
        &dir,
        &[
            "decompose",
            "--method",
            "hybrid",
            "--gaze",
            "30,20",
            "--out",
            &out,
        ],
    );
    assert!(ok && text.contains("hybrid decomposition"), "{text}");
    for p in ["0.20", "0.80", "1.40", "2.00"] {
        assert!(
            Path::new(&format!("{out}/layer_{p}D.exr")).exists(),
            "{text}"
        );
    }
    let (ok, text) = on_scene(
        &dir,
        &[
            "decompose",
            "--method",
            "hybrid",
            "--gaze",
            "30",
            "--out",
            &d("bad"),
        ],
    );
    assert!(!ok && text.contains("--gaze"), "{text}");

    // Light-field synthesis from the scene's 2 x 2 views into 3 x 3, plain and foveated
    // (issue 41): the foveated run says what fraction of the rays it kept and its PSNR per
    // region against the full synthesis; --gaze without --foveate and a bad S are refused.
    let lf_on = |backend: &str, extra: &[&str]| {
        let out = d("synth");
        let views = d("lightfield");
        let mut args = vec![
            "lightfield",
            "--views",
            &views,
            "--inputs",
            "5",
            "--grid",
            "3",
            "--backend",
            backend,
            "--out",
            &out,
        ];
        args.extend_from_slice(extra);
        dioptra(&args)
    };
    let lf = |extra: &[&str]| lf_on("cpu", extra);
    let (ok, text) = lf(&[]);
    assert!(ok && text.contains("synthesised 9 views"), "{text}");
    assert!(Path::new(&d("synth/view_02_02.png")).exists(), "{text}");
    assert!(!text.contains("rays kept"), "{text}");
    let (ok, text) = lf(&["--foveate", "2", "--gaze", "20,20"]);
    assert!(ok, "{text}");
    let kept: f64 = text
        .split_once("): ")
        .and_then(|(_, r)| r.split_once(" % of the rays kept"))
        .and_then(|(v, _)| v.parse().ok())
        .unwrap_or_else(|| panic!("no fraction in {text}"));
    assert!(kept > 0.0 && kept < 100.0, "{text}");
    for region in ["fovea", "periphery 1", "periphery 2"] {
        assert!(
            text.lines().any(|l| l.starts_with(region)),
            "{region} missing: {text}"
        );
    }
    assert!(text.contains("filled across"), "the default fill: {text}");
    let (ok, text) = lf(&["--foveate", "2", "--foveate-fill", "within"]);
    assert!(ok && text.contains("filled within"), "{text}");
    let (ok, text) = lf(&["--foveate", "2", "--foveate-fill", "nearest"]);
    assert!(!ok && text.contains("across or within"), "{text}");
    let (ok, text) = lf(&["--gaze", "20,20"]);
    assert!(!ok && text.contains("--foveate"), "{text}");
    let (ok, text) = lf(&["--foveate", "0"]);
    assert!(!ok && text.contains("--foveate"), "{text}");

    // --method refine (C5R): an untrained net (its last layer zero) writes the classical views
    // byte for byte; one with random weights throughout changes some, so the refinement ran;
    // without --weights the shipped net refines.
    let views = |dir: &str| -> Vec<Vec<u8>> {
        (0..9)
            .map(|k| std::fs::read(format!("{dir}/view_{:02}_{:02}.png", k / 3, k % 3)).unwrap())
            .collect()
    };
    let (ok, text) = lf(&[]);
    assert!(ok, "{text}");
    let classical = views(&d("synth"));
    let arch = dioptra_net::Arch::preset("c5r").unwrap();
    let mut nets = [
        dioptra_net::Weights::random(&arch, 1).unwrap(),
        dioptra_net::Weights::random(&arch, 2).unwrap(),
    ];
    let mut r = dioptra_net::weights::SplitMix(3);
    for v in nets[1].convs.iter_mut().flat_map(|c| c.weight.iter_mut()) {
        if *v == 0.0 {
            *v = 0.05 * r.uniform();
        }
    }
    for (k, net) in nets.iter().enumerate() {
        let path = d(&format!("c5r{k}.safetensors"));
        net.save(Path::new(&path)).unwrap();
        let (ok, text) = lf(&["--method", "refine", "--weights", &path]);
        assert!(ok && text.contains("synthesised 9 views"), "{text}");
        let refined = views(&d("synth"));
        if k == 0 {
            assert!(refined == classical, "the untrained net changed a view");
        } else {
            assert!(refined != classical, "the random net changed no view");
        }
    }
    let (ok, text) = lf(&["--method", "refine"]);
    assert!(ok && text.contains("% of the tiles"), "{text}");
    let shipped_cpu = views(&d("synth"));
    assert!(shipped_cpu != classical, "the shipped net changed no view");
    // The shipped net on the GPU backend: the same views within one 8-bit level.
    let (ok, text) = lf_on("gpu", &["--method", "refine"]);
    if !no_gpu(ok, &text) {
        assert!(ok, "{text}");
        for (k, (a, b)) in shipped_cpu.iter().zip(views(&d("synth"))).enumerate() {
            let decode = |bytes: &[u8]| {
                let mut r = png::Decoder::new(std::io::Cursor::new(bytes))
                    .read_info()
                    .unwrap();
                let mut buf = vec![0; r.output_buffer_size().unwrap()];
                r.next_frame(&mut buf).unwrap();
                buf
            };
            let (a, b) = (decode(a), decode(&b));
            let worst = a.iter().zip(&b).map(|(x, y)| x.abs_diff(*y)).max();
            assert!(
                worst <= Some(1),
                "view {k}: GPU and CPU differ by {worst:?} levels"
            );
        }
        // Refined and foveated on the GPU backend.
        let (ok, text) = lf_on("gpu", &["--method", "refine", "--foveate", "2"]);
        assert!(ok && text.contains("% of the rays kept"), "{text}");
    }
    let (ok, text) = lf(&["--method", "warp"]);
    assert!(!ok && text.contains("classical or refine"), "{text}");

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
    let (ok, text) = on_scene(
        &dir,
        &[
            "render",
            "--focus",
            "1",
            "--backend",
            "vulkan",
            "--out",
            &d("x.png"),
        ],
    );
    assert!(!ok && text.contains("backend"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn gpu_backend_matches_cpu_through_the_binary() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-gpu-{}", std::process::id()));
    let d = |p: &str| dir.join(p).display().to_string();
    sim_scene(&dir, "1000002", "48");
    let render = |backend: &str, out: &str| {
        on_scene(
            &dir,
            &[
                "render",
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
            ],
        )
    };
    let (ok, text) = render("gpu", "gpu.exr");
    if no_gpu(ok, &text) {
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    assert!(ok, "{text}");
    let (ok, text) = render("cpu", "cpu.exr");
    assert!(ok, "{text}");
    assert!(psnr(&d("gpu.exr"), &d("cpu.exr")) > 90.0);
    // Headless (no session, as in CI or over ssh): no libwayland complaint from Mesa's
    // device-selection layer on stderr (issue 39, item 10).
    let (color, depth) = (d("color.png"), d("depth.exr"));
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args([
            "render", "--color", &color, "--depth", &depth, "--focus", "1",
        ])
        .args(["--backend", "gpu", "--out", &d("headless.png")])
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("WAYLAND_DISPLAY")
        .env_remove("NODEVICE_SELECT")
        .env_remove("DRI_PRIME")
        .env_remove("MESA_VK_DEVICE_SELECT")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && !stderr.contains("XDG_RUNTIME_DIR"),
        "{stderr}"
    );
    // An adapter that does not exist is an error naming the ones that do.
    let (ok, text) = on_scene(
        &dir,
        &[
            "render",
            "--focus",
            "1",
            "--adapter",
            "no-such-adapter-xyz",
            "--out",
            &d("x.png"),
        ],
    );
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
    sim_scene(&dir, "1000003", "40");
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
        on_scene(
            &dir,
            &[
                "render",
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
            ],
        )
    };
    let (ok, text) = net("gpu", "gpu.exr");
    if no_gpu(ok, &text) {
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    assert!(ok, "{text}");
    let (ok, text) = net("cpu", "cpu.exr");
    assert!(ok, "{text}");
    let psnr_in = |a: &str, b: &str| psnr(&d(a), &d(b));
    assert!(psnr_in("gpu.exr", "cpu.exr") > 60.0);
    for backend in ["gpu", "cpu"] {
        let (ok, text) = on_scene(
            &dir,
            &[
                "decompose",
                "--method",
                "network",
                "--weights",
                &d("c4.safetensors"),
                "--backend",
                backend,
                "--out",
                &d(&format!("layers_{backend}")),
            ],
        );
        assert!(ok, "{text}");
    }
    assert!(psnr_in("layers_gpu/layer_0.80D.exr", "layers_cpu/layer_0.80D.exr") > 60.0);
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
    assert!(psnr_in("fov_gpu.exr", "fov_cpu.exr") > 60.0);
    std::fs::remove_dir_all(&dir).ok();
}

/// `render --method refine` (C1R) and `decompose --method refine` (C4R) with the shipped
/// weights, on the GPU and the CPU: the same images, and C1R's net ran on some tiles.
#[test]
fn refine_runs_with_the_shipped_weights_on_both_backends() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-refine-{}", std::process::id()));
    let d = |p: &str| dir.join(p).display().to_string();
    sim_scene(&dir, "1000004", "96");
    let render = |backend: &str| {
        on_scene(
            &dir,
            &[
                "render",
                "--focus",
                "0.1",
                "--method",
                "refine",
                "--backend",
                backend,
                "--out",
                &d(&format!("c1r_{backend}.exr")),
            ],
        )
    };
    let (ok, text) = render("gpu");
    if no_gpu(ok, &text) {
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    assert!(ok, "{text}");
    let (ok, cpu_text) = render("cpu");
    assert!(ok, "{cpu_text}");
    // "... refined on N % of the tiles": the net ran, so the comparison covers it.
    let tiles: f64 = cpu_text
        .split("refined on ")
        .nth(1)
        .and_then(|t| t.split(" %").next()?.parse().ok())
        .unwrap_or_else(|| panic!("no tile fraction in: {cpu_text}"));
    assert!(tiles > 0.0, "{cpu_text}");
    let psnr_in = |a: &str, b: &str| psnr(&d(a), &d(b));
    assert!(psnr_in("c1r_gpu.exr", "c1r_cpu.exr") > 60.0);
    for backend in ["gpu", "cpu"] {
        let (ok, text) = on_scene(
            &dir,
            &[
                "decompose",
                "--method",
                "refine",
                "--backend",
                backend,
                "--out",
                &d(&format!("c4r_{backend}")),
            ],
        );
        assert!(ok, "{text}");
    }
    for plane in ["0.20", "0.80", "1.40", "2.00"] {
        let f = |b: &str| format!("c4r_{b}/layer_{plane}D.exr");
        assert!(psnr_in(&f("gpu"), &f("cpu")) > 60.0, "layer {plane} D");
    }
    // A C4R whose weights name the spectral layers (untrained, so it returns them exactly)
    // refines the spectral decomposition, on either backend.
    let mut arch = dioptra_net::Arch::preset("c4r").unwrap();
    if let dioptra_net::Task::C4r { classical, .. } = &mut arch.task {
        *classical = dioptra_net::ClassicalLayers::Spectral;
    }
    let weights = d("c4r_spectral.safetensors");
    dioptra_net::Weights::random(&arch, 3)
        .unwrap()
        .save(Path::new(&weights))
        .unwrap();
    for backend in ["cpu", "gpu"] {
        for (method, out) in [("spectral", "spectral"), ("refine", "c4r_spectral")] {
            let out = d(&format!("{out}_{backend}"));
            let mut args = vec!["decompose", "--method", method, "--backend", backend];
            args.extend(["--out", &out]);
            if method == "refine" {
                args.extend(["--weights", &weights]);
            }
            let (ok, text) = on_scene(&dir, &args);
            assert!(ok, "{text}");
            if method == "refine" {
                assert!(text.contains("refining spectral layers"), "{text}");
            }
        }
        for plane in ["0.20", "0.80", "1.40", "2.00"] {
            let f = |m: &str| format!("{m}_{backend}/layer_{plane}D.exr");
            let p = psnr_in(&f("c4r_spectral"), &f("spectral"));
            assert!(p > 100.0, "{backend}: layer {plane} D: {p} dB");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Width and height of a PNG, from its IHDR chunk.
fn png_size(path: &Path) -> (u32, u32) {
    let b = std::fs::read(path).expect("png");
    let be = |i: usize| u32::from_be_bytes(b[i..i + 4].try_into().unwrap());
    assert_eq!(&b[12..16], b"IHDR", "{}", path.display());
    (be(16), be(20))
}

#[test]
fn sim_scene_takes_a_panel_shaped_size() {
    let dir = std::env::temp_dir().join(format!("dioptra-cli-scene-wxh-{}", std::process::id()));
    sim_scene(&dir, "1000002", "24x16");
    assert_eq!(png_size(&dir.join("color.png")), (24, 16));
    assert_eq!(png_size(&dir.join("depth.png")), (24, 16));
    assert_eq!(png_size(&dir.join("lightfield/view_00_00.png")), (24, 16));
    let toml = std::fs::read_to_string(dir.join("scene.toml")).unwrap();
    assert!(toml.contains("width = 24\nheight = 16"), "{toml}");
    // A non-square scene renders through the bounded-cost method at its own size.
    let out = dir.join("p.png").display().to_string();
    let (ok, text) = on_scene(
        &dir,
        &[
            "render",
            "--focus",
            "1.0",
            "--method",
            "pyramid",
            "--backend",
            "cpu",
            "--out",
            &out,
        ],
    );
    assert!(ok, "{text}");
    assert_eq!(png_size(Path::new(&out)), (24, 16));
    for bad in ["0x16", "24x", "24xfoo", "9000"] {
        let (ok, text) = dioptra(&[
            "sim",
            "scene",
            "--seed",
            "1",
            "--size",
            bad,
            "--out",
            &dir.join("bad").display().to_string(),
        ]);
        assert!(!ok && text.contains("--size"), "{bad}: {text}");
        assert!(text.contains("WIDTHxHEIGHT"), "{bad}: {text}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
