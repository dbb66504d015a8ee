//! `dioptra hil` as a user runs it: on the example sim rig it measures, writes its summaries
//! and histograms, and says everywhere that the devices were simulated; a config naming a
//! serial port that is not there exits non-zero naming the port and its config key; with a
//! DLPC350, which reports no sub-frame times, it skips that measurement and says why; with
//! the example photodiode rig it measures in photons.

use std::path::Path;
use std::process::Command;

const RIG: &str = include_str!("../examples/rig-sim.toml");
const PHOTODIODE_RIG: &str = include_str!("../examples/rig-sim-photodiode.toml");

fn write_config(dir: &Path, text: &str) -> std::path::PathBuf {
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `dioptra hil --config <config> --trials <trials> --out <out>`.
fn hil(config: &Path, trials: u32, out: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["hil", "--config"])
        .arg(config)
        .args(["--trials", &trials.to_string(), "--out"])
        .arg(out)
        .output()
        .unwrap()
}

fn summary_json(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

#[test]
fn hil_on_the_sim_rig_writes_outputs_that_say_simulated() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), RIG);
    let out = dir.path().join("hil");
    let run = hil(&config, 20, &out);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stdout.contains("SIMULATED"), "{stdout}");
    let txt = std::fs::read_to_string(out.join("summary.txt")).unwrap();
    assert!(txt.contains("SIMULATED"), "{txt}");
    let js = summary_json(&out);
    assert_eq!(js["simulated"], true, "{js}");
    let m = &js["measurements"];
    // Every lens step settled and was timed; the sim rig has a sync board, so sub-frames too.
    assert_eq!(m["command_to_settled"]["count"], 20, "{js}");
    assert!(
        m["command_to_settled"]["p50_us"].as_u64().unwrap() > 0,
        "{js}"
    );
    assert!(
        m["command_to_wire"]["count"].as_u64().unwrap() >= 20,
        "{js}"
    );
    assert_eq!(m["subframe_timing_error"]["count"], 20, "{js}");
    let gaze = m["gaze_to_command"]["count"].as_u64().unwrap();
    assert!(gaze > 0, "{js}");
    // Fewer focus changes than --trials (gaze decides how many): said, with why.
    if gaze < 20 {
        assert!(
            stdout.contains(&format!(
                "{gaze} of the 20 asked for: this phase ends after 30 s"
            )),
            "{stdout}"
        );
    }
    // No photodiode: it says so, and measures nothing in photons.
    assert!(stdout.contains("no optical measurement"), "{stdout}");
    assert_eq!(js["optical_frames"]["measured"], false, "{js}");
    assert!(m.get("vsync_to_photons").is_none(), "{js}");
    for png in [
        "gaze_to_command",
        "command_to_wire",
        "command_to_settled",
        "subframe_timing_error",
    ] {
        let bytes = std::fs::read(out.join(format!("{png}.png"))).unwrap();
        assert!(bytes.starts_with(b"\x89PNG"), "{png}.png is not a PNG");
    }
}

/// On the binocular example rig (a lens per eye): the host path runs to both lenses' commands
/// written, the inter-eye skew is measured for each of those focus changes, and every step
/// settles both lenses.
#[test]
fn hil_on_the_binocular_sim_rig_times_both_lenses_and_their_skew() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(
        dir.path(),
        include_str!("../examples/rig-sim-binocular.toml"),
    );
    let out = dir.path().join("hil");
    let run = hil(&config, 6, &out);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    let js = summary_json(&out);
    let m = &js["measurements"];
    let changes = m["gaze_to_command"]["count"].as_u64().unwrap();
    assert!(changes > 0, "{js}");
    assert!(
        m["gaze_to_command"]["title"]
            .as_str()
            .unwrap()
            .contains("both lens commands"),
        "{js}"
    );
    assert_eq!(m["inter_eye_skew"]["count"].as_u64(), Some(changes), "{js}");
    assert_eq!(m["command_to_settled"]["count"], 6, "{js}");
    // Two commands on the wire per step (at least), each timed.
    assert!(
        m["command_to_wire"]["count"].as_u64().unwrap() >= 12,
        "{js}"
    );
    assert!(out.join("inter_eye_skew.png").exists());
}

#[test]
fn hil_with_an_absent_serial_port_names_it_and_fails() {
    let dir = tempfile::tempdir().unwrap();
    let absent = "/dev/ttyACM-dioptra-absent";
    let text = RIG.replacen("port = \"sim\"", &format!("port = \"{absent}\""), 1);
    let config = write_config(dir.path(), &text);
    let run = hil(&config, 5, &dir.path().join("hil"));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{stderr}");
    assert!(stderr.contains(absent), "{stderr}");
    assert!(stderr.contains("devices.lens.port"), "{stderr}");
    assert!(!dir.path().join("hil").join("summary.txt").exists());
}

#[test]
fn hil_with_a_dlpc350_says_it_cannot_time_sub_frames() {
    let dir = tempfile::tempdir().unwrap();
    let rig = RIG.replace("driver = \"sync\"", "driver = \"dlpc350\"");
    assert_ne!(rig, RIG);
    let config = write_config(dir.path(), &rig);
    let out = dir.path().join("hil");
    let run = hil(&config, 3, &out);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(
        stdout.contains("sub-frame timing: skipped (the DLPC350 reports no sub-frame times"),
        "{stdout}"
    );
    let js = summary_json(&out);
    assert!(
        js["measurements"].get("subframe_timing_error").is_none(),
        "{js}"
    );
    assert_eq!(js["measurements"]["command_to_settled"]["count"], 3, "{js}");
}

#[test]
fn hil_on_a_stream_rig_measures_content_to_presented() {
    let dir = tempfile::tempdir().unwrap();
    let text = RIG.replace(
        "# [content]\n",
        "[content]\nsource = \"stream\"\nring = \"none\"\n",
    );
    assert!(text.contains("source = \"stream\""));
    let config = write_config(dir.path(), &text);
    let out = dir.path().join("hil");
    let run = hil(&config, 30, &out);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(
        stdout.contains("30 of 30 stream frames accepted"),
        "{stdout}"
    );
    let js = summary_json(&out);
    let m = &js["measurements"];
    // At 60 Hz frames and 60 Hz content most frames show (some are replaced by the next
    // before a frame is requested); each shown one is timed both ways. A frame is at least
    // a render and a frame period's lead from arrival to display.
    // How many are replaced or still on their way when the run stops depends on how busy the
    // machine is (wall clock: seen 30 received and 27 shown, and 26 and 24), so only what
    // holds however slow it runs is asserted: every shown frame was received, none twice.
    let shown = m["content_to_presented"]["count"].as_u64().unwrap();
    let received = m["content_received"]["count"].as_u64().unwrap();
    assert!(shown >= 1, "{js}");
    assert!((shown..=30).contains(&received), "{js}");
    assert!(
        m["content_to_presented"]["p50_us"].as_u64().unwrap() > 1000,
        "{js}"
    );
    assert!(out.join("content_to_presented.png").exists());
}

#[test]
fn hil_on_the_photodiode_rig_measures_in_photons() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), PHOTODIODE_RIG);
    let out = dir.path().join("hil");
    let run = hil(&config, 20, &out);
    let stdout = String::from_utf8_lossy(&run.stdout);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stdout.contains("photodiode (sim)"), "{stdout}");
    for line in [
        "vsync to photons: n = ",
        "frame presented to photons: n = ",
        "gaze sample to photons: n = ",
        "frames seen optically: ",
    ] {
        assert!(stdout.contains(line), "{line:?} missing:\n{stdout}");
    }
    let js = summary_json(&out);
    let m = &js["measurements"];
    // The simulated panel lights 6 ms after each vsync (sim_photon_latency_ms): the median
    // is that, give or take the wall clock's jitter on a busy machine (the simulated-clock
    // loop test holds it to 0.2 ms).
    assert!(
        m["vsync_to_photons"]["count"].as_u64().unwrap() > 20,
        "{js}"
    );
    let p50 = m["vsync_to_photons"]["p50_us"].as_u64().unwrap();
    assert!((5_000..=16_000).contains(&p50), "{js}");
    assert!(
        m["frame_presented_to_photons"]["count"].as_u64().unwrap() > 20,
        "{js}"
    );
    assert!(m["gaze_to_photons"]["count"].as_u64().unwrap() > 0, "{js}");
    let optical = &js["optical_frames"];
    assert_eq!(optical["measured"], true, "{js}");
    assert!(optical["refreshes_checked"].as_u64().unwrap() > 20, "{js}");
    // How many a loaded machine's real-time simulators light late varies; that they are
    // counted does not.
    for key in ["refreshes_duplicated", "frames_missed", "frames_checked"] {
        assert!(optical[key].is_u64(), "{key}: {js}");
    }
    let txt = std::fs::read_to_string(out.join("summary.txt")).unwrap();
    for line in [
        "## vsync to photons (vsync_to_photons)",
        "## frame presented to photons (frame_presented_to_photons)",
        "## gaze sample to photons (gaze_to_photons)",
        "frames seen optically:",
    ] {
        assert!(txt.contains(line), "{line:?} missing:\n{txt}");
    }
    for png in [
        "vsync_to_photons",
        "frame_presented_to_photons",
        "gaze_to_photons",
    ] {
        let bytes = std::fs::read(out.join(format!("{png}.png"))).unwrap();
        assert!(bytes.starts_with(b"\x89PNG"), "{png}.png is not a PNG");
    }
}

/// `dioptra demo --eyes 2` (the binocular example rig) runs, prints each eye's figures and
/// writes each eye's images and their side-by-side panel, the eyes' views apart by disparity.
#[test]
fn the_demo_with_two_eyes_prints_and_writes_each_eye() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let run = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args([
            "demo",
            "--eyes",
            "2",
            "--seconds",
            "1.5",
            "--size",
            "48",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    for line in [
        "left eye: lens commands",
        "right eye: lens commands",
        "lens command pairs",
    ] {
        assert!(text.contains(line), "{line}: {text}");
    }
    let left = dioptra_render::io::read_color(&out.join("frame_0_left_input.png")).unwrap();
    let right = dioptra_render::io::read_color(&out.join("frame_0_right_input.png")).unwrap();
    let stereo = dioptra_render::io::read_color(&out.join("frame_0_stereo.png")).unwrap();
    assert_eq!((stereo.width(), stereo.height()), (96, 48));
    assert_ne!(left, right, "each eye sees from its own place");
    let rendered = dioptra_render::io::read_color(&out.join("frame_0_right_rendered.png")).unwrap();
    assert_eq!(
        stereo.pixel(48 + 10, 20),
        rendered.pixel(10, 20),
        "the right half is the right eye"
    );
    // Other modes are refused with the reason.
    let refused = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["demo", "--eyes", "2", "--mode", "multifocal", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--eyes 2"));
}
