//! The device commands as a user runs them: `dioptra sim ... --pty` in one process, `dioptra lens`
//! in others, talking through the pty; `dioptra gaze inspect` on descriptor files. Real time
//! (separate processes); nothing here asserts how long anything took.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};

struct Sim(Child);

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `dioptra sim <which> --pty` and returns it with the pty path from its first line.
fn start_sim(which: &str) -> (Sim, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["sim", which, "--pty"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let path = line.trim().to_string();
    assert!(path.starts_with("/dev/pts/"), "first line {line:?}");
    (Sim(child), path)
}

/// Whether the command succeeded, its stdout and stderr together, and its stdout alone (the
/// lines it prints; stderr also carries the driver's logged warnings).
fn lens(device: &str, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["lens", "--device", device])
        .args(args)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    let text = stdout.clone() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text, stdout)
}

/// `handshake_resets`: a new session resets the lens (the Lens Driver 4's `Start` resets its
/// output current), so a `get` in a new process does not find the power set in the last one.
fn set_then_get(driver: &str, sim: &str, handshake_resets: bool) {
    let (_sim, path) = start_sim(sim);
    let device = format!("{driver}:{path}");
    let (ok, out, stdout) = lens(&device, &["set", "1.5", "--watch-ms", "100"]);
    assert!(ok, "{out}");
    assert!(
        stdout.lines().last().unwrap().contains("power 1.500 D"),
        "{out}"
    );
    let (ok, out, _) = lens(&device, &["get"]);
    assert!(ok, "{out}");
    assert_eq!(out.contains("power 1.500 D"), !handshake_resets, "{out}");
    let (ok, out, stdout) = lens(
        &device,
        &["sweep", "0:1", "--step", "0.5", "--dwell-ms", "40"],
    );
    assert!(ok, "{out}");
    assert_eq!(stdout.lines().count(), 3, "{out}");
    assert!(
        stdout.lines().last().unwrap().contains("power 1.000 D"),
        "{out}"
    );
    let (ok, out, _) = lens(&device, &["--refuse", "--max-d", "2", "set", "2.5"]);
    assert!(!ok && out.contains("nothing was sent"), "{out}");
    // A clamped request: the line says what went out, and the lens gets there.
    let (ok, out, stdout) = lens(
        &device,
        &["--max-d", "2", "set", "2.5", "--watch-ms", "100"],
    );
    assert!(ok, "{out}");
    assert!(
        stdout
            .lines()
            .next()
            .unwrap()
            .starts_with("set 2.000 D (asked 2.500 D, clamped to the driving range"),
        "{out}"
    );
    assert!(
        stdout.lines().last().unwrap().contains("power 2.000 D"),
        "{out}"
    );
    let (ok, out, _) = lens(&device, &["info"]);
    assert!(ok, "{out}");
    let (ok, out, _) = lens(&device, &["temp"]);
    assert!(ok && out.contains("temperature"), "{out}");
}

#[test]
fn optotune_simulator_set_then_get() {
    set_then_get("optotune", "optotune", true);
}

#[test]
fn lens_controller_simulator_set_then_get() {
    set_then_get("lens", "lens", false);
}

/// The sync board through the drivers' table, as a rig config names it (`sync` on a path).
#[test]
fn sync_board_simulator_programs_and_reports() {
    let (_sim, path) = start_sim("sync");
    let sync = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
            .args(["sync", "--device", &format!("sync:{path}")])
            .args(args)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).to_string()
            + &String::from_utf8_lossy(&out.stderr);
        (out.status.success(), text)
    };
    let (ok, out) = sync(&["status"]);
    assert!(ok && out.contains("dioptra sync board"), "{out}");
    let (ok, out) = sync(&["events", "--count", "8"]);
    assert!(ok, "{out}");
    assert!(out.contains("plane"), "{out}");
}

/// README's `sim sync` then `sync ... events` example, as written: with the default settle
/// time every sub-frame reaches its plane (issue 39, item 11: it faulted on each).
#[test]
fn sync_simulator_as_readme_runs_it_reaches_every_plane() {
    let (_sim, path) = start_sim("sync");
    let device = format!("sync:{path}");
    let sync = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
            .args(["sync", "--device", &device])
            .args(args)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).to_string()
            + &String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{text}");
        text
    };
    sync(&["program", "--planes", "0.2,0.8,1.4,2.0", "--rate", "240"]);
    sync(&["start"]);
    let events = sync(&["events", "--count", "16"]);
    assert_eq!(events.lines().count(), 16, "{events}");
    assert!(!events.contains("FAULT"), "{events}");
    assert!(events.lines().all(|l| l.contains("lens ")), "{events}");
}

#[test]
fn bad_device_specs_say_what_is_accepted() {
    let (ok, out, _) = lens("nonsense", &["get"]);
    assert!(!ok && out.contains("DRIVER:PATH"), "{out}");
    let (ok, out, _) = lens("zoom:/dev/null", &["get"]);
    assert!(!ok && out.contains("unknown lens driver"), "{out}");
    let (ok, out, _) = lens("optotune:/dev/ttyACM_dioptra_absent", &["get"]);
    assert!(!ok && out.contains("no serial port"), "{out}");
    // The rig config's ports: the Lens Driver 4 has no USB bulk interface; "sim" is for rigs.
    let (ok, out, _) = lens("optotune:usb", &["get"]);
    assert!(!ok && out.contains("cannot be reached at usb"), "{out}");
    let (ok, out, _) = lens("lens:sim", &["get"]);
    assert!(!ok && out.contains("dioptra sim"), "{out}");
}

fn gaze_inspect(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["gaze", "inspect"])
        .args(args)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

/// Microsoft's reference descriptors (crates/gaze/tests/data, sources in its README).
fn reference_descriptor(name: &str) -> String {
    format!("{}/../gaze/tests/data/{name}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn gaze_inspect_reads_the_reference_descriptors_and_names_what_is_missing() {
    for (file, head) in [
        ("gazehid_report_descriptor.bin", false),
        ("dmf_virtual_eye_gaze_report_descriptor.bin", true),
    ] {
        let (ok, out) = gaze_inspect(&["--descriptor", &reference_descriptor(file)]);
        assert!(ok, "{out}");
        assert!(out.contains("dioptra can drive this device"), "{out}");
        // Report ids and lengths: Tracking Data 0x10 is 65 bytes.
        assert!(out.contains("0x10 input   65"), "{out}");
        assert!(out.contains("0x13 feature 4"), "{out}");
        // The Constant gaze point, at bit 64, 32 bits, cm with exponent -4 (1 µm per count).
        let gaze = out.lines().find(|l| l.contains("Gaze Point X")).unwrap();
        assert!(
            gaze.contains(" 64 ")
                && gaze.contains(" 32 ")
                && gaze.contains("0x11")
                && gaze.contains("1 µm")
                && gaze.contains("constant"),
            "{gaze}"
        );
        assert!(out.contains("Left Eye Position Z"), "{out}");
        assert_eq!(out.contains("note: Head Direction ignored"), head, "{out}");
    }
    // Only the Tracking Data part of the GazeHid descriptor: the feature reports are missing.
    let full = std::fs::read(reference_descriptor("gazehid_report_descriptor.bin")).unwrap();
    let end = full
        .windows(4)
        .position(|w| w == [0x09, 0x11, 0xa1, 0x02])
        .unwrap();
    let mut part = full[..end].to_vec();
    part.push(0xc0);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tracking_only.bin");
    std::fs::write(&path, part).unwrap();
    let (ok, out) = gaze_inspect(&["--descriptor", path.to_str().unwrap()]);
    assert!(!ok, "{out}");
    assert!(out.contains("cannot drive this device"), "{out}");
    for what in ["Capabilities", "Configuration Status", "Mode Request"] {
        assert!(out.contains(what), "{out}");
    }
    // The simulator's own descriptor, and a spec that is not a descriptor source.
    let (ok, out) = gaze_inspect(&["--device", "sim-hid"]);
    assert!(ok && out.contains("can drive"), "{out}");
    let (ok, out) = gaze_inspect(&["--device", "hid:/dev/not_a_node"]);
    assert!(!ok && out.contains("hidrawN"), "{out}");
}

/// `dioptra lens ... calibrate` with `input` on its stdin.
fn lens_with_input(device: &str, args: &[&str], input: &str) -> (bool, String) {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["lens", "--device", device])
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(input.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

/// The map the scripted measurement reports: the thin-lens layout of an 18 D eyepiece with the
/// display 5 cm in front and the pupil 2 cm behind (X = 2 - p, A = X / (1 + 0.02 X)), plus a
/// lens nonlinearity of 0.03 D per D squared.
fn true_demand(p: f64) -> f64 {
    let x = 2.0 - p;
    x / (1.0 + 0.02 * x) + 0.03 * p * p
}

/// `true_demand` of the commanded power plus up to ±0.015 D of noise, as a camera sweep or
/// an autorefractor script would print it.
const MEASURE: &str = r#"awk -v p="$DIOPTRA_LENS_POWER_D" 'BEGIN { x = 2 - p; printf "%.4f\n", x / (1 + 0.02 * x) + 0.03 * p * p + 0.015 * sin(37.1 * p + 0.3) }'"#;

#[test]
fn calibrate_against_the_simulator_reproduces_a_nonlinear_map_through_noise() {
    let (_sim, path) = start_sim("optotune");
    let device = format!("optotune:{path}");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal.csv");
    let out_s = out.to_str().unwrap();
    let args = [
        "calibrate",
        "--powers=-1:4:0.25",
        "--settle-ms",
        "20",
        "--measure-cmd",
        MEASURE,
        "--out",
        out_s,
    ];
    let (ok, text, _) = lens(&device, &args);
    assert!(ok, "{text}");
    assert_eq!(
        text.lines().filter(|l| l.starts_with("step ")).count(),
        21,
        "{text}"
    );
    assert!(text.contains("residuals: rms"), "{text}");
    let table = std::fs::read_to_string(&out).unwrap();
    for want in [
        "# date: ",
        "# lens: Optotune Lens Driver 4, serial ",
        "# device: optotune:/dev/pts/",
        "# lens temperature: ",
        "# measured by: the command `awk",
        "command_d,demand_d,measured_d,readback_d,temperature_c\n",
    ] {
        assert!(table.contains(want), "{want:?} in\n{table}");
    }
    // The written table against the true map, everywhere over the range.
    let t = dioptra_core::optics_map::CalibrationTable::parse_csv("cal.csv", &table).unwrap();
    for k in 0..=500 {
        let c = -1.0 + 0.01 * f64::from(k);
        let err = (t.demand_at(c) - true_demand(c)).abs();
        assert!(
            err < 0.03,
            "{c} D: table {} vs {}",
            t.demand_at(c),
            true_demand(c)
        );
    }
    // The rig reads it: `dioptra optics` gives the true focus of a command.
    let rig = std::fs::read_to_string(format!(
        "{}/examples/rig-sim.toml",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap()
    .replace("[optics]\n", "[optics]\ncalibration = \"cal.csv\"\n");
    std::fs::write(dir.path().join("rig.toml"), rig).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["optics", "--config"])
        .arg(dir.path().join("rig.toml"))
        .args(["--command", "1.3", "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(
        (v["focus_d"].as_f64().unwrap() - true_demand(1.3)).abs() < 0.03,
        "{v}"
    );
    // An existing table is not replaced without --force.
    let (ok, text, _) = lens(&device, &args);
    assert!(!ok && text.contains("--force"), "{text}");
}

#[test]
fn calibrate_refuses_what_it_cannot_trust_and_writes_nothing() {
    let (_sim, path) = start_sim("optotune");
    let device = format!("optotune:{path}");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal.csv");
    let out_s = out.to_str().unwrap();
    let calibrate = |powers: &str, cmd: &str| {
        lens(
            &device,
            &[
                "calibrate",
                powers,
                "--settle-ms",
                "5",
                "--measure-cmd",
                cmd,
                "--out",
                out_s,
            ],
        )
    };
    // Up, then down again: a parabola over the commands.
    let (ok, text, _) = calibrate(
        "--powers=0:3:0.25",
        r#"awk -v p="$DIOPTRA_LENS_POWER_D" 'BEGIN { printf "%.4f\n", 2 - (p - 1.5) * (p - 1.5) }'"#,
    );
    assert!(!ok && text.contains("not monotonic"), "{text}");
    // Too few points, refused before the lens moves.
    let (ok, text, _) = calibrate("--powers=0:1:0.5", MEASURE);
    assert!(!ok && text.contains("at least 5"), "{text}");
    assert!(!text.contains("step "), "{text}");
    // A measure command that fails: its status and stderr, at the command it failed on.
    let (ok, text, _) = calibrate("--powers=-1:1:0.25", "echo camera not found >&2; exit 3");
    assert!(!ok, "{text}");
    assert!(
        text.contains("failed at command -1 D") && text.contains("camera not found"),
        "{text}"
    );
    // One that prints no number.
    let (ok, text, _) = calibrate("--powers=-1:1:0.25", "echo blurry");
    assert!(!ok && text.contains("printed \"blurry\""), "{text}");
    // Noise of ±0.1 D: too noisy.
    let (ok, text, _) = calibrate(
        "--powers=-1:2:0.25",
        r#"awk -v p="$DIOPTRA_LENS_POWER_D" 'BEGIN { k = int((p + 1) * 4 + 0.5); printf "%.4f\n", 2 - p + (k % 2 ? 0.1 : -0.1) }'"#,
    );
    assert!(!ok && text.contains("too noisy"), "{text}");
    // Too sparse a step, and a range beyond the lens's.
    let (ok, text, _) = calibrate("--powers=0:4:1.5", MEASURE);
    assert!(!ok && text.contains("at most 1 D"), "{text}");
    let (ok, text, _) = calibrate("--powers=0:40:0.5", MEASURE);
    assert!(
        !ok && text.contains("outside the range this lens is driven within"),
        "{text}"
    );
    assert!(
        !out.exists(),
        "a refused calibration wrote {}",
        out.display()
    );
}

#[test]
fn calibrate_takes_measurements_from_the_operator_or_a_csv() {
    let (_sim, path) = start_sim("optotune");
    let device = format!("optotune:{path}");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cal.csv");
    let out_s = out.to_str().unwrap();
    // `calibrate` into `out` (replacing it) with `args`, `input` on stdin.
    let calibrate = |args: &[&str], input: &str| {
        let mut all = vec!["calibrate", "--settle-ms", "5", "--out", out_s, "--force"];
        all.extend_from_slice(args);
        lens_with_input(&device, &all, input)
    };
    // At a prompt: a demand of 2 - p at each of 0, 0.25, ..., 1.5, one skipped, one typo.
    let answers = "2\n1.75\nnot sure\n1.5\nskip\n1.0\n0.75\n0.5\n";
    let (ok, text) = calibrate(&["--powers=0:1.5:0.25", "--prompt"], answers);
    assert!(ok, "{text}");
    assert!(text.contains("\"not sure\" is not a number"), "{text}");
    let written = std::fs::read_to_string(&out).unwrap();
    let t = dioptra_core::optics_map::CalibrationTable::parse_csv("cal.csv", &written).unwrap();
    assert_eq!(t.len(), 6);
    assert!(
        (t.demand_at(0.75) - 1.25).abs() < 1e-3,
        "{}",
        t.demand_at(0.75)
    );
    // Input that ends early stops it.
    let (ok, text) = calibrate(&["--powers=0:1.5:0.25", "--prompt"], "2\n1.75\n");
    assert!(!ok && text.contains("input ended at step 3"), "{text}");
    // From a CSV (e.g. an autorefractor's readings typed into a spreadsheet).
    let csv = dir.path().join("readings.csv");
    std::fs::write(
        &csv,
        "# autorefractor, 2 readings averaged\ncommand_d,measured_d\n0,2.01\n0.5,1.49\n1,1.0\n1.5,0.51\n2,0.0\n",
    )
    .unwrap();
    let csv = csv.to_str().unwrap();
    let (ok, text) = calibrate(&["--powers=0:2:0.5", "--from-csv", csv], "");
    assert!(ok, "{text}");
    assert!(std::fs::read_to_string(&out)
        .unwrap()
        .contains("# measured by: the file"));
    let (ok, text) = calibrate(&["--powers=0:2.5:0.5", "--from-csv", csv], "");
    assert!(!ok && text.contains("no row for command 2.5 D"), "{text}");
}
