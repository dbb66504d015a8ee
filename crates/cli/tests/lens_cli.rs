//! The lens commands as a user runs them: `dioptra sim ... --pty` in one process, `dioptra lens`
//! in others, talking through the pty. Real time (separate processes); nothing here asserts
//! how long anything took.

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

fn set_then_get(driver: &str, sim: &str) {
    let (_sim, path) = start_sim(sim);
    let device = format!("{driver}:{path}");
    let (ok, out) = lens(&device, &["set", "1.5"]);
    assert!(ok, "{out}");
    std::thread::sleep(std::time::Duration::from_millis(100));
    let (ok, out) = lens(&device, &["get"]);
    assert!(ok, "{out}");
    assert!(out.contains("power 1.500 D"), "{out}");
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
    set_then_get("optotune", "optotune");
}

#[test]
fn lens_controller_simulator_set_then_get() {
    set_then_get("lens", "lens");
}

#[test]
fn bad_device_specs_say_what_is_accepted() {
    let (ok, out) = lens("nonsense", &["get"]);
    assert!(!ok && out.contains("DRIVER:PATH"), "{out}");
    let (ok, out) = lens("zoom:/dev/null", &["get"]);
    assert!(!ok && out.contains("unknown lens driver"), "{out}");
    let (ok, out) = lens("optotune:/dev/ttyACM_dioptra_absent", &["get"]);
    assert!(!ok && out.contains("no serial port"), "{out}");
}
