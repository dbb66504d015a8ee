//! `dioptra optics` as a user runs it, on the example rig with optics added, against values
//! computed by hand.

use std::path::{Path, PathBuf};
use std::process::Command;

fn example_rig() -> String {
    std::fs::read_to_string(format!(
        "{}/examples/rig-sim.toml",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap()
}

/// The example rig with `extra` at the end of its `[optics]` section, written into `dir`.
fn rig_with_optics(dir: &Path, extra: &str) -> PathBuf {
    let text = example_rig().replace(
        "subframe_hz = 240.0\n",
        &format!("subframe_hz = 240.0\n{extra}\n"),
    );
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn optics(config: &Path, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .arg("optics")
        .arg("--config")
        .arg(config)
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

fn json(config: &Path, args: &[&str]) -> serde_json::Value {
    let mut all = args.to_vec();
    all.push("--json");
    let (ok, out, err) = optics(config, &all);
    assert!(ok, "{out}{err}");
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
}

fn close(v: &serde_json::Value, want: f64, tol: f64) -> bool {
    v.as_f64().is_some_and(|x| (x - want).abs() <= tol)
}

#[test]
fn the_map_both_ways_through_a_thin_lens_layout() {
    let dir = tempfile::tempdir().unwrap();
    // Display 5 cm from the lens, an 18 D eyepiece, the pupil 2 cm behind: by hand,
    // focus 1 D -> X = 1 / (1 - 0.02) = 1.020408, command = 20 - 18 - X = 0.979592 D;
    // command 0 D -> X = 2, focus = 2 / 1.04 = 1.923077 D, magnification 0.07 / 0.052.
    let rig = rig_with_optics(
        dir.path(),
        "[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.02\nfixed_power_d = 18.0",
    );
    let v = json(&rig, &["--focus", "1.0"]);
    assert!(close(&v["lens_command_d"], 0.979592, 2e-6), "{v}");
    assert!(
        close(&v["magnification"], 0.07 / (0.07 - 0.001 * 18.979592), 1e-5),
        "{v}"
    );
    assert_eq!(v["source"], "layout");
    assert_eq!(v["clamped"], false);
    let v = json(&rig, &["--command", "0"]);
    assert!(close(&v["focus_d"], 1.923077, 2e-6), "{v}");
    assert!(close(&v["magnification"], 1.346154, 1e-6), "{v}");
    // The lens range -1..4 D reaches focus 2 - 4 / (1 + 0.02 * -2)... by the formula at each end:
    // command 4: X = -2, focus = -2 / 0.96 = -2.083333; command -1: X = 3, 3 / 1.06 = 2.830189.
    assert!(close(&v["focus_range_d"][0], -2.083333, 2e-6), "{v}");
    assert!(close(&v["focus_range_d"][1], 2.830189, 2e-6), "{v}");
    // A focus beyond the range: the nearest command, said so.
    let (ok, out, _) = optics(&rig, &["--focus", "5"]);
    assert!(
        ok && out.contains("lens command -1.0000 D (the nearest"),
        "{out}"
    );
    // The text form names the map.
    let (ok, out, _) = optics(&rig, &["--command", "0"]);
    assert!(ok, "{out}");
    assert!(out.contains("thin-lens layout: display 0.05 m"), "{out}");
    assert!(out.contains("focus 1.9231 D"), "{out}");
}

#[test]
fn identity_prescriptions_per_eye_and_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain.toml");
    std::fs::write(&plain, example_rig()).unwrap();
    let v = json(&plain, &["--focus", "1.5"]);
    assert_eq!(v["source"], "identity");
    assert!(close(&v["lens_command_d"], 1.5, 1e-6), "{v}");
    assert!(v["magnification"].is_null(), "{v}");
    // A monocular bench's right eye: a -1 D myope (0 mm vertex) at 1.5 D is shown 2.5 D.
    let rig = rig_with_optics(
        dir.path(),
        "[optics.right]\nprescription_sphere_d = -1.0\nprescription_vertex_mm = 0.0",
    );
    let v = json(&rig, &["--eye", "right", "--focus", "1.5"]);
    assert!(close(&v["lens_command_d"], 2.5, 1e-6), "{v}");
    assert_eq!(v["eye"], "right");
    // The left eye has no section: the shared (identity) settings.
    let v = json(&rig, &["--eye", "left", "--focus", "1.5"]);
    assert!(close(&v["lens_command_d"], 1.5, 1e-6), "{v}");
    // Refusals.
    let (ok, _, err) = optics(&rig, &["--command", "9"]);
    assert!(
        !ok && err.contains("outside optics.lens_range -1..4 D"),
        "{err}"
    );
    let (ok, _, err) = optics(&rig, &["--eye", "middle", "--focus", "1"]);
    assert!(!ok && err.contains("expected left or right"), "{err}");
    let (ok, _, err) = optics(&rig, &[]);
    assert!(!ok && err.contains("--focus"), "{err}");
    let bad = rig_with_optics(dir.path(), "prescription_cylinder_d = -0.5");
    let (ok, _, err) = optics(&bad, &["--focus", "1"]);
    assert!(
        !ok && err.contains("optics.prescription_cylinder_d"),
        "{err}"
    );
    // An old config's display_distance_m still loads, with a note.
    let old = dir.path().join("old.toml");
    std::fs::write(
        &old,
        example_rig().replace("[optics]\n", "[optics]\ndisplay_distance_m = 1.0\n"),
    )
    .unwrap();
    let (ok, out, err) = optics(&old, &["--focus", "1"]);
    assert!(ok && out.contains("identity"), "{out}{err}");
    assert!(err.contains("[optics.layout] display_distance_m"), "{err}");
}
