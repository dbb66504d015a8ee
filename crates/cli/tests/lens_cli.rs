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

fn lens(device: &str, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["lens", "--device", device])
        .args(args)
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

/// `handshake_resets`: a new session resets the lens (the Lens Driver 4's `Start` resets its
/// output current), so a `get` in a new process does not find the power set in the last one.
fn set_then_get(driver: &str, sim: &str, handshake_resets: bool) {
    let (_sim, path) = start_sim(sim);
    let device = format!("{driver}:{path}");
    let (ok, out) = lens(&device, &["set", "1.5", "--watch-ms", "100"]);
    assert!(ok, "{out}");
    assert!(
        out.lines().last().unwrap().contains("power 1.500 D"),
        "{out}"
    );
    let (ok, out) = lens(&device, &["get"]);
    assert!(ok, "{out}");
    assert_eq!(out.contains("power 1.500 D"), !handshake_resets, "{out}");
    let (ok, out) = lens(
        &device,
        &["sweep", "0:1", "--step", "0.5", "--dwell-ms", "40"],
    );
    assert!(ok, "{out}");
    assert_eq!(out.lines().count(), 3, "{out}");
    assert!(
        out.lines().last().unwrap().contains("power 1.000 D"),
        "{out}"
    );
    let (ok, out) = lens(&device, &["--refuse", "--max-d", "2", "set", "2.5"]);
    assert!(!ok && out.contains("nothing was sent"), "{out}");
    let (ok, out) = lens(&device, &["info"]);
    assert!(ok, "{out}");
    let (ok, out) = lens(&device, &["temp"]);
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

#[test]
fn bad_device_specs_say_what_is_accepted() {
    let (ok, out) = lens("nonsense", &["get"]);
    assert!(!ok && out.contains("DRIVER:PATH"), "{out}");
    let (ok, out) = lens("zoom:/dev/null", &["get"]);
    assert!(!ok && out.contains("unknown lens driver"), "{out}");
    let (ok, out) = lens("optotune:/dev/ttyACM_dioptra_absent", &["get"]);
    assert!(!ok && out.contains("no serial port"), "{out}");
    // The rig config's ports: the Lens Driver 4 has no USB bulk interface; "sim" is for rigs.
    let (ok, out) = lens("optotune:usb", &["get"]);
    assert!(!ok && out.contains("cannot be reached at usb"), "{out}");
    let (ok, out) = lens("lens:sim", &["get"]);
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
