//! `dioptra display calibrate` and `dioptra optics --distortion` as a user runs them.
//!
//! The transfer test: a simulated panel with gamma 2.4 and a black offset, calibrated
//! with `display calibrate` (its simulated photometer as the measure command), then two
//! linear-blended layers at half weight add to the luminance of one at full weight within 1 %.

use std::path::Path;
use std::process::Command;

use dioptra_core::transfer::{Transfer, TransferTable};
use dioptra_sim::eye_camera::PanelResponse;

fn dioptra(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

/// The simulated photometer as a measure command.
fn photometer(extra: &str) -> String {
    format!(
        "'{}' display sim-photometer --gamma 2.4 --black-cd-m2 0.3 --white-cd-m2 120 {extra}",
        env!("CARGO_BIN_EXE_dioptra")
    )
}

fn calibrate(out: &Path, measure: &str, extra: &[&str]) -> (bool, String, String) {
    let mut args = vec![
        "display",
        "calibrate",
        "--measure-cmd",
        measure,
        "--settle-ms",
        "0",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    dioptra(&args)
}

/// Over linear values v: the light of half + half against whole + nothing, on `panel`,
/// through `transfer`'s encoding, relative to whole's light above black.
fn worst_blend_error(transfer: &Transfer, panel: &PanelResponse) -> f64 {
    let light = |v: f64| panel.luminance(transfer.encode(v));
    [0.1, 0.2, 0.3, 0.5, 0.7, 1.0]
        .iter()
        .map(|&v| {
            let whole = light(v) + light(0.0);
            let split = 2.0 * light(v / 2.0);
            ((split - whole) / (whole - 2.0 * panel.black_cd_m2)).abs()
        })
        .fold(0.0, f64::max)
}

#[test]
fn a_calibrated_gamma_panel_adds_blended_layers_in_light() {
    let dir = tempfile::tempdir().unwrap();
    let table = dir.path().join("panel.csv");
    // A 10-bit panel (at 8 bits the code values' rounding alone costs up to 1.4 % at a
    // linear 0.1), the photometer with 0.2 % noise, two readings a level.
    let (ok, out, err) = calibrate(
        &table,
        &photometer("--bits 10 --noise-pct 0.2 --seed 9"),
        &[
            "--bits",
            "10",
            "--readings",
            "2",
            "--panel-name",
            "simulated",
        ],
    );
    assert!(ok, "{out}{err}");
    assert!(out.contains("residuals: rms"), "{out}");
    let text = std::fs::read_to_string(&table).unwrap();
    for provenance in [
        "# dioptra panel calibration",
        "# panel: simulated",
        "10 bits, 2 reading(s)",
        "sim-photometer",
    ] {
        assert!(text.contains(provenance), "{provenance}: {text}");
    }
    let measured = Transfer::Table(TransferTable::parse_csv("panel.csv", &text).unwrap());
    let panel = PanelResponse {
        bits: 10,
        ..PanelResponse::example()
    };
    let calibrated = worst_blend_error(&measured, &panel);
    let srgb = worst_blend_error(&Transfer::Srgb, &panel);
    eprintln!(
        "half + half against whole: {:.3} % calibrated, {:.2} % encoding sRGB",
        100.0 * calibrated,
        100.0 * srgb
    );
    assert!(calibrated < 0.01, "{calibrated}");
    assert!(srgb > 0.03, "{srgb}");
}

#[test]
fn a_bad_calibration_is_refused_and_nothing_written() {
    let dir = tempfile::tempdir().unwrap();
    let table = dir.path().join("panel.csv");
    // 3 % noise: beyond the 2 % a reading may be off.
    let (ok, _, err) = calibrate(&table, &photometer("--noise-pct 3"), &[]);
    assert!(!ok);
    assert!(
        err.contains("refused") && err.contains("too noisy"),
        "{err}"
    );
    assert!(!table.exists());
    // A command that fails, one that prints no number, too few levels.
    let (ok, _, err) = calibrate(&table, "echo photometer unplugged >&2; exit 3", &[]);
    assert!(
        !ok && err.contains("photometer unplugged") && err.contains("level 0"),
        "{err}"
    );
    let (ok, _, err) = calibrate(&table, "echo ready", &[]);
    assert!(!ok && err.contains("\"ready\""), "{err}");
    let (ok, _, err) = calibrate(&table, &photometer(""), &["--levels", "4"]);
    assert!(!ok && err.contains("--levels 4"), "{err}");
    assert!(!table.exists());
    // An existing table is kept unless --force.
    std::fs::write(&table, "keep").unwrap();
    let (ok, _, err) = calibrate(&table, &photometer(""), &[]);
    assert!(!ok && err.contains("--force"), "{err}");
    assert_eq!(std::fs::read_to_string(&table).unwrap(), "keep");
}

const EYEPIECE: &str = "[optics.distortion]\nfx = 300.0\nfy = 300.0\ncx = 159.5\ncy = 89.5\n\
                        k1 = -0.18\nk2 = 0.03\n[optics.distortion.red]\nfx = 303.0\nfy = 303.0\n";

#[test]
fn the_distortion_grid_and_points() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("eyepiece.toml");
    std::fs::write(&model, EYEPIECE).unwrap();
    let grid = dir.path().join("grid.png");
    let m = model.to_str().unwrap();
    let (ok, out, err) = dioptra(&[
        "optics",
        "--distortion",
        m,
        "--panel",
        "320x180",
        "--distortion-grid",
        grid.to_str().unwrap(),
    ]);
    assert!(ok, "{out}{err}");
    assert!(out.contains("field (green)"), "{out}");
    let img = dioptra_render::io::read_color(&grid).unwrap();
    assert_eq!((img.width(), img.height()), (320, 180));
    // The centre's cross is white; the corners, beyond the ideal image, black.
    assert!(img.pixel(159, 89).unwrap().iter().all(|&v| v > 0.9));
    assert_eq!(img.pixel(0, 0).unwrap(), [0.0; 3]);
    // Points: the axis lands on the centre in every channel; a direction to the right lands
    // farther out in red (its focal length is 1 % longer).
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["optics", "--distortion", m, "--points", "project"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    use std::io::Write;
    child
        .stdin
        .take()
        .unwrap()
        .write_all(b"0 0\n0.4 0\n")
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let rows: Vec<Vec<f64>> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| l.split(' ').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows[0], vec![159.5, 89.5, 159.5, 89.5, 159.5, 89.5]);
    // By hand: green 300 * 0.4 (1 - 0.18 * 0.16 + 0.03 * 0.0256) + 159.5.
    let green = 300.0 * 0.4 * (1.0 - 0.18 * 0.16 + 0.03 * 0.0256) + 159.5;
    assert!((rows[1][2] - green).abs() < 1e-9, "{:?}", rows[1]);
    assert!(rows[1][0] > rows[1][2] + 1.0);
    // A bad key is named.
    std::fs::write(&model, EYEPIECE.replace("k2 = 0.03", "k2 = \"big\"")).unwrap();
    let (ok, _, err) = dioptra(&["optics", "--distortion", m, "--points", "project"]);
    assert!(!ok && err.contains("optics.distortion.k2"), "{err}");
    std::fs::write(&model, EYEPIECE.replace("fx = 300.0", "fx = -3.0")).unwrap();
    let (ok, _, err) = dioptra(&["optics", "--distortion", m, "--points", "project"]);
    assert!(!ok && err.contains("optics.distortion.fx"), "{err}");
}
