//! `dioptra doctor` as a lab runs it: on the example rigs (simulated devices), on a rig whose
//! lens is a simulator on a pty (a real device path), and on rigs with what doctor exists to
//! find: a lens that is not plugged in, an API address already taken, stale udev rules. Exit 0
//! when every check passed, 1 when one failed, each failure with its fix.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `dioptra doctor ARGS`: (exit code, stdout, stderr).
fn doctor(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .arg("doctor")
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn example(name: &str) -> String {
    format!("{}/examples/{name}", env!("CARGO_MANIFEST_DIR"))
}

/// The rules `dioptra udev ARGS` prints, written to `dir/rules`.
fn rules_file(dir: &Path, args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .arg("udev")
        .args(args)
        .output()
        .unwrap();
    assert!(out.status.success());
    let path = dir.join("70-dioptra.rules");
    std::fs::write(&path, out.stdout).unwrap();
    path.display().to_string()
}

/// A rig config in `dir`: the example sim rig with `edit` applied, its API on a free port.
fn rig(dir: &Path, edit: impl Fn(String) -> String) -> String {
    let text = std::fs::read_to_string(example("rig-sim.toml")).unwrap();
    let text = edit(text.replace("127.0.0.1:7420", "127.0.0.1:0"));
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

#[test]
fn the_example_rigs_pass_with_their_simulated_devices_said_so() {
    let dir = tempfile::tempdir().unwrap();
    let rules = rules_file(dir.path(), &[]);
    for name in [
        "rig-sim.toml",
        "rig-sim-binocular.toml",
        "rig-sim-photodiode.toml",
    ] {
        let config = example(name);
        let (code, out, err) = doctor(&["--config", &config, "--udev-rules", &rules]);
        // The example rigs listen on 7420/7421: a daemon running here would take them.
        let busy = out.contains("FAIL  api.listen");
        assert!(
            code == 0 || (busy && code == 1),
            "{name}: exit {code}\n{out}\n{err}"
        );
        assert!(out.contains("ok    config:"), "{out}");
        assert!(out.contains("ok    udev rules:"), "{out}");
        assert!(
            out.lines()
                .any(|l| l.starts_with("ok    devices.lens")
                    && l.contains("simulated (port = \"sim\")")),
            "{out}"
        );
        assert!(
            out.lines().any(|l| l.contains(" gpu: ")),
            "no GPU line: {out}"
        );
    }
}

#[test]
fn a_lens_on_a_pty_is_present_and_a_missing_one_fails_with_its_fix() {
    let dir = tempfile::tempdir().unwrap();
    let rules = rules_file(dir.path(), &[]);
    let mut sim = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["sim", "optotune", "--pty"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(sim.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let _sim = Process(sim);
    let pty = line.trim().to_string();
    let config = rig(dir.path(), |t| {
        t.replacen("port = \"sim\"", &format!("port = {pty:?}"), 1)
    });
    let (code, out, err) = doctor(&["--config", &config, "--udev-rules", &rules]);
    assert_eq!(code, 0, "{out}\n{err}");
    assert!(
        out.contains(&format!("ok    devices.lens: {pty}"))
            && out.contains("readable and writable"),
        "{out}"
    );
    // Found by its port: doctor says which serial number it would check, and that none is set.
    assert!(out.contains("note  devices.lens: serial number"), "{out}");

    let config = rig(dir.path(), |t| {
        t.replacen("port = \"sim\"", "port = \"/dev/ttyDIOPTRA-UNPLUGGED\"", 1)
    });
    let (code, out, err) = doctor(&["--config", &config, "--udev-rules", &rules]);
    assert_eq!(code, 1, "{out}\n{err}");
    assert!(
        out.contains(
            "FAIL  devices.lens: /dev/ttyDIOPTRA-UNPLUGGED (devices.lens.port) is not present"
        ),
        "{out}"
    );
    assert!(out.contains("fix: plug the device in"), "{out}");
    assert!(out.contains("/dev/serial/by-id/"), "{out}");
    assert!(err.contains("1 check failed"), "{err}");
}

#[test]
fn a_taken_api_address_and_stale_rules_fail_and_a_broken_config_names_its_key() {
    let dir = tempfile::tempdir().unwrap();
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap();
    let config = rig(dir.path(), |t| t.replace("127.0.0.1:0", &addr.to_string()));
    let rules = dir.path().join("stale.rules");
    std::fs::write(&rules, "# an old file\n").unwrap();
    // A rig of real devices would fail on stale rules; a sim rig only warns, as it needs none.
    let (code, out, err) = doctor(&["--config", &config, "--udev-rules", rules.to_str().unwrap()]);
    assert_eq!(code, 1, "{out}\n{err}");
    assert!(
        out.contains(&format!("FAIL  api.listen: cannot listen on {addr}")),
        "{out}"
    );
    assert!(
        out.contains("warn  udev rules:")
            && out.contains("differs from what `dioptra udev` prints"),
        "{out}"
    );

    let config = rig(dir.path(), |t| {
        t.replace("pupil_mm = 4.0", "pupil_mm = \"four\"")
    });
    let (code, out, _) = doctor(&["--config", &config]);
    assert_eq!(code, 1, "{out}");
    assert!(
        out.contains("FAIL  config:") && out.contains("eye.pupil_mm"),
        "{out}"
    );

    // The group variant: doctor reads the group from the file and checks it exists.
    let rules = rules_file(dir.path(), &["--group", "no-such-group-dioptra"]);
    let config = rig(dir.path(), |t| t);
    let (code, out, _) = doctor(&["--config", &config, "--udev-rules", &rules]);
    // Root opens any device whatever the group; anyone else is told to create it.
    let root = out.contains("is up to date and gives group no-such-group-dioptra access");
    assert!(
        root || (code == 1 && out.contains("sudo groupadd --system no-such-group-dioptra")),
        "{out}"
    );
}
