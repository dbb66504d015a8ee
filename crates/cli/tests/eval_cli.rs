//! `dioptra eval --quick` through the real binary: every method is in the CSV, every score
//! present is finite and plausible, the failure suite and the report are written; bad flags
//! get a clear error.

use std::collections::HashMap;
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

/// Rows of a CSV written by `dioptra eval` as column -> cell maps (cells hold no quoted commas
/// in the columns read here; quoted notes are kept whole).
fn read_csv(path: &Path) -> Vec<HashMap<String, String>> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .expect("a header")
        .split(',')
        .map(String::from)
        .collect();
    lines
        .map(|l| {
            // Split on commas outside quotes.
            let (mut cells, mut cur, mut quoted) = (Vec::new(), String::new(), false);
            for ch in l.chars() {
                match ch {
                    '"' => quoted = !quoted,
                    ',' if !quoted => cells.push(std::mem::take(&mut cur)),
                    c => cur.push(c),
                }
            }
            cells.push(cur);
            assert_eq!(cells.len(), header.len(), "row {l:?}");
            header.iter().cloned().zip(cells).collect()
        })
        .collect()
}

fn finite_in(cell: &str, lo: f64, hi: f64, what: &str) {
    let v: f64 = cell
        .parse()
        .unwrap_or_else(|_| panic!("{what}: {cell:?} is not a number"));
    assert!(
        v.is_finite() && (lo..=hi).contains(&v),
        "{what}: {v} not in {lo}..={hi}"
    );
}

#[test]
fn quick_eval_writes_every_method_and_the_failure_report() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("eval");
    let (ok, text) = dioptra(&["eval", "--quick", "--out", &out.display().to_string()]);
    assert!(ok, "{text}");

    let rows = read_csv(&out.join("eval.csv"));
    for method in [
        "gather",
        "lightfield",
        "network-c1",
        "linear",
        "optimized",
        "optimized-gather",
        "spectral",
        "network-c4",
        "refine-c1r",
        "refine-c4r",
    ] {
        let mine: Vec<_> = rows
            .iter()
            .filter(|r| r["method"] == method && r["backend"] == "cpu")
            .collect();
        assert!(!mine.is_empty(), "no CPU row for {method}");
        assert!(
            mine.iter().any(|r| !r["time_ms"].is_empty()),
            "{method} was never timed"
        );
        for r in &mine {
            if r["time_ms"].is_empty() {
                // Only a setting predicted to overrun --budget-s goes untimed, and it says so.
                assert!(r["note"].starts_with("skipped"), "{method}: {r:?}");
                continue;
            }
            finite_in(&r["time_ms"], 0.0, 1e7, &format!("{method} time_ms"));
            if r["psnr_db"].is_empty() {
                // Only an untrained network may go unscored, and it must say so.
                assert!(
                    (method.starts_with("network") || method.starts_with("refine"))
                        && r["note"].starts_with("untrained"),
                    "{method} has no score: {r:?}"
                );
            } else {
                finite_in(&r["psnr_db"], 10.0, 100.0, &format!("{method} psnr"));
                finite_in(&r["ssim"], 0.0, 1.0, &format!("{method} ssim"));
            }
        }
    }
    // A scored refinement net that failed the independent set says it is not the default.
    for r in rows
        .iter()
        .filter(|r| r["method"].starts_with("refine") && !r["psnr_db"].is_empty())
    {
        assert!(
            r["note"].contains("not the daemon's default"),
            "{} says nothing of its standing: {r:?}",
            r["method"]
        );
    }
    // C1R says on what fraction of the tiles its net ran; no other method has one.
    for r in rows.iter().filter(|r| !r["time_ms"].is_empty()) {
        if r["method"] == "refine-c1r" {
            finite_in(&r["tiles_run"], 0.0, 1.0, "refine-c1r tiles_run");
        } else {
            assert!(r["tiles_run"].is_empty(), "{r:?}");
        }
    }
    // Classical methods are scored at every focus of the quick plan.
    let gather_foci = rows
        .iter()
        .filter(|r| r["method"] == "gather" && r["backend"] == "cpu" && !r["psnr_db"].is_empty())
        .count();
    assert_eq!(gather_foci, 3, "gather is scored at 3 foci in --quick");
    // Optimized blending fits the ground truth better than linear blending.
    let mean_psnr = |m: &str, s: &str| {
        let v: Vec<f64> = rows
            .iter()
            .filter(|r| r["method"] == m && r["setting"] == s && r["backend"] == "cpu")
            .map(|r| r["psnr_db"].parse::<f64>().expect("a score"))
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    assert!(
        mean_psnr("optimized", "10 it") > mean_psnr("linear", ""),
        "optimized {} vs linear {}",
        mean_psnr("optimized", "10 it"),
        mean_psnr("linear", "")
    );
    // The rig's fit (a gathered stack, from linear) improves on its linear start, and the
    // oracle that fits the very stack it is scored against does better still.
    let gathered = mean_psnr("optimized-gather", "10 it");
    assert!(
        mean_psnr("linear", "") < gathered && gathered < mean_psnr("optimized", "10 it"),
        "linear {} < optimized-gather {gathered} < optimized {}",
        mean_psnr("linear", ""),
        mean_psnr("optimized", "10 it")
    );

    // The spectral decomposition (issue 42) is above linear blending.
    assert!(
        mean_psnr("spectral", "") > mean_psnr("linear", "") + 3.0,
        "spectral {} vs linear {}",
        mean_psnr("spectral", ""),
        mean_psnr("linear", "")
    );
    let failure = read_csv(&out.join("failure.csv"));
    let cases: std::collections::BTreeSet<&str> =
        failure.iter().map(|r| r["case"].as_str()).collect();
    assert_eq!(cases.len(), 12, "{cases:?}");
    for r in &failure {
        assert_eq!(r["nonfinite"], "0", "{r:?}");
        if !r["psnr_region_db"].is_empty() {
            finite_in(&r["psnr_region_db"], 5.0, 100.0, "region psnr");
        }
    }
    let lp = read_csv(&out.join("loop.csv"));
    assert_eq!(lp.len(), 7);
    let unplug = lp
        .iter()
        .find(|r| r["fault"] == "lens unplugged")
        .expect("unplug row");
    assert_eq!(unplug["lens_link_losses"], "1", "{unplug:?}");
    let misses = lp
        .iter()
        .find(|r| r["fault"] == "renderer deadline misses")
        .expect("misses row");
    let baseline = lp
        .iter()
        .find(|r| r["fault"].starts_with("none"))
        .expect("baseline");
    assert!(
        misses["deadline_misses"].parse::<u64>().unwrap()
            > baseline["deadline_misses"].parse::<u64>().unwrap(),
        "{misses:?} vs {baseline:?}"
    );

    // Light fields: the classical synthesis beats the nearest input on every scene and input
    // count; the GPU's views are the CPU's within 1e-3; foveation keeps fewer rays as S grows.
    let lf = read_csv(&out.join("lightfield.csv"));
    let psnr = |r: &HashMap<String, String>| r["psnr_novel_db"].parse::<f64>().unwrap();
    for k in ["5", "9"] {
        let of = |m: &str, b: &str| {
            lf.iter()
                .find(|r| r["method"] == m && r["backend"] == b && r["inputs"] == k)
                .unwrap_or_else(|| panic!("no {m} {b} row for {k} inputs: {lf:?}"))
        };
        let (near, cpu) = (of("nearest input", ""), of("classical", "cpu"));
        finite_in(
            &cpu["psnr_novel_db"],
            15.0,
            60.0,
            "classical light field PSNR",
        );
        assert!(psnr(cpu) > psnr(near) + 2.0, "{cpu:?} against {near:?}");
        for method in ["classical", "refine"] {
            if let Some(gpu) = lf
                .iter()
                .find(|r| r["method"] == method && r["backend"] == "gpu" && r["inputs"] == k)
            {
                finite_in(
                    &gpu["max_abs_diff_from_cpu"],
                    0.0,
                    1e-3,
                    "light field GPU - CPU",
                );
            }
        }
        // The shipped C5R refines the classical synthesis; it has rows whenever it ships.
        if dioptra_net::shipped_weights("c5r").exists() {
            let refine = of("refine", "cpu");
            finite_in(
                &refine["psnr_novel_db"],
                15.0,
                60.0,
                "refined light field PSNR",
            );
            assert!(
                (psnr(refine) - psnr(cpu)).abs() < 3.0,
                "{refine:?} against {cpu:?}"
            );
        }
    }
    let fov = read_csv(&out.join("lightfield_foveated.csv"));
    // The full synthesis, then each scale filled within views and across them.
    assert_eq!(fov.len(), 7, "{fov:?}");
    assert_eq!(
        (fov[0]["scale"].as_str(), fov[0]["rays_kept"].as_str()),
        ("full", "1.00000")
    );
    for fill in ["within", "across"] {
        let of: Vec<_> = fov.iter().filter(|r| r["fill"] == fill).collect();
        let kept: Vec<f64> = of.iter().map(|r| r["rays_kept"].parse().unwrap()).collect();
        assert!(
            kept.len() == 3 && kept.windows(2).all(|w| w[1] < w[0]) && kept[0] < 0.2,
            "{fill}: {kept:?}"
        );
    }
    // Both fills keep the same rays; across views is the better fovea at every scale.
    for pair in fov[1..].chunks(2) {
        assert_eq!(
            (pair[0]["fill"].as_str(), pair[1]["fill"].as_str()),
            ("within", "across")
        );
        assert_eq!(pair[0]["rays_kept"], pair[1]["rays_kept"]);
        let fovea = |r: &HashMap<String, String>| -> f64 { r["fovea_vs_full_db"].parse().unwrap() };
        assert!(fovea(&pair[1]) > fovea(&pair[0]), "{pair:?}");
    }

    // Panel sizes: every stage timed at the quick sizes on the CPU, each render method among
    // them; the rig run with each method at each size, its rates and latency measured.
    let stages = read_csv(&out.join("panel_stages.csv"));
    for method in ["gather", "pyramid", "pyramid-foveated", "lightfield-16"] {
        let rows: Vec<_> = stages
            .iter()
            .filter(|r| r["backend"] == "cpu" && r["method"] == method)
            .collect();
        assert_eq!(rows.len(), 4, "{method}: 2 sizes x 2 fields: {rows:?}");
        for r in rows {
            finite_in(&r["time_ms"], 0.0, 1e6, &format!("panel {method} time_ms"));
        }
    }
    let rig = read_csv(&out.join("panel_rig.csv"));
    assert_eq!(rig.len(), 8, "2 sizes x 4 methods: {rig:?}");
    for r in &rig {
        finite_in(&r["distinct_fps"], 0.0, 61.0, "panel rig distinct_fps");
        finite_in(&r["refresh_hz"], 0.0, 61.0, "panel rig refresh_hz");
        // Empty only where no frame was shown in the run (a loaded machine).
        if !r["gaze_to_display_p99_ms"].is_empty() {
            finite_in(
                &r["gaze_to_display_p99_ms"],
                0.0,
                1e5,
                "gaze to display p99",
            );
        }
    }
    let report = std::fs::read_to_string(out.join("report.md")).expect("report");
    assert!(report.contains("## Panel sizes"));
    assert!(report.contains("## Speed against accuracy"));
    assert!(report.contains("## Where methods fail"));
    assert!(report.contains("## Light fields from sparse views"));
    for chart in [
        "speed_accuracy_128",
        "psnr_by_focus_128",
        "failure_region_psnr",
        "failure_temporal",
        "loop_focus_error",
        "panel_fps",
    ] {
        for ext in ["png", "svg"] {
            let p = out.join(format!("{chart}.{ext}"));
            let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
            assert!(len > 1000, "{} is missing or empty", p.display());
        }
    }
}

#[test]
fn bad_flags_are_named() {
    for (flag, value) in [
        ("--sizes", "12,abc"),
        ("--sizes", "8"),
        ("--backend", "tpu"),
        ("--suite", "fast"),
        ("--runs", "0"),
        ("--panel-seconds", "0"),
    ] {
        let (ok, text) = dioptra(&["eval", flag, value, "--out", "/nonexistent/never"]);
        assert!(!ok, "{flag} {value} was accepted");
        assert!(text.contains(flag), "{flag} {value}: {text}");
    }
}
