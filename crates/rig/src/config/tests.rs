use super::*;
use dioptra_core::Diopters;

/// A complete simulated rig; tests edit it.
pub const SIM_RIG: &str = EXAMPLE_SIM_RIG;

fn err(text: &str) -> ConfigError {
    match RigConfig::parse(text) {
        Ok(c) => panic!("config accepted: {c:?}"),
        Err(e) => e,
    }
}

#[test]
fn the_example_config_parses() {
    let c = RigConfig::parse(SIM_RIG).unwrap();
    assert_eq!(c.mode, Mode::Varifocal);
    assert_eq!(c.devices.lens.first().port, Port::Sim);
    assert_eq!(
        c.api.listen().unwrap(),
        Listen::Tcp("127.0.0.1:7420".parse().unwrap())
    );
}

/// The example rig with a photodiode (`photodiode` its section's lines) and `display`
/// lines added to [display].
fn with_photodiode(photodiode: &str, display: &str) -> String {
    let t = SIM_RIG.replace("png_every = 0 ", &format!("{display}\npng_every = 0 "));
    assert_ne!(t, SIM_RIG);
    format!("{t}\n[devices.photodiode]\n{photodiode}\n")
}

const PATCH: &str = "marker_patch = { corner = \"top-left\", size = 8 }";

#[test]
fn a_photodiode_and_its_marker_patch_are_checked_naming_the_key() {
    let ok = RigConfig::parse(&with_photodiode(
        "driver = \"serial-line\"\nport = \"sim\"",
        PATCH,
    ))
    .unwrap();
    let m = ok.display.marker_patch.as_ref().unwrap();
    assert_eq!((m.corner, m.size), (Corner::TopLeft, 8));
    assert_eq!(m.toggle_on, [MarkerEvent::Frame]);
    assert!(ok.devices.photodiode_simulated());
    // The sync board's input: no port of its own, and a band.
    let on_board = RigConfig::parse(&with_photodiode(
        "driver = \"sync\"\nthreshold = 0.3\nhysteresis = 0.02",
        PATCH,
    ))
    .unwrap();
    let p = on_board.devices.photodiode.as_ref().unwrap();
    assert!(p.on_sync_board());
    assert_eq!((p.band().threshold, p.band().hysteresis), (0.3, 0.02));
    assert!(on_board.devices.photodiode_simulated());

    for (photodiode, display, key, says) in [
        (
            "driver = \"serial-line\"",
            PATCH,
            "devices.photodiode.port",
            "needs the microcontroller's port",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"\nthreshold = 0.4",
            PATCH,
            "devices.photodiode.threshold",
            "trimmer",
        ),
        (
            "driver = \"sync\"\nthreshold = 0.98",
            PATCH,
            "devices.photodiode.threshold",
            "strictly inside",
        ),
        (
            "driver = \"serial-line\"\nport = \"127.0.0.1:5000\"",
            PATCH,
            "devices.photodiode.port",
            "device path",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            "",
            "display.marker_patch",
            "no marker patch",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            "marker_patch = { size = 0 }",
            "display.marker_patch.size",
            "1 to 96",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            "marker_patch = { size = 8, toggle_on = [] }",
            "display.marker_patch.toggle_on",
            "name what toggles",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            "marker_patch = { size = 8, toggle_on = [\"frame\", \"lens-command\"] }",
            "display.marker_patch.toggle_on",
            "alone",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            &format!("{PATCH}\nsim_persistence_ms = 20.0"),
            "display.sim_persistence_ms",
            "one refresh",
        ),
        (
            "driver = \"serial-line\"\nport = \"sim\"",
            &format!("{PATCH}\nsim_photon_latency_ms = -1.0"),
            "display.sim_photon_latency_ms",
            "0 to 200",
        ),
    ] {
        let e = err(&with_photodiode(photodiode, display));
        assert_eq!(e.key(), key, "{photodiode} / {display}: {e}");
        assert!(e.to_string().contains(says), "{e}");
    }
    // The board of [devices.sync] is not opened twice, and a DLPC350 has no input.
    let dlp = with_photodiode("driver = \"sync\"", PATCH).replace(
        "driver = \"sync\"             # sync (the dioptra",
        "driver = \"dlpc350\"          # sync (the dioptra",
    );
    assert_eq!(err(&dlp).key(), "devices.photodiode.driver");
    let same = with_photodiode("driver = \"sync\"\nport = \"/dev/ttyACM3\"", PATCH).replace(
        "port = \"sim\"\n# video_hz",
        "port = \"/dev/ttyACM3\"\n# video_hz",
    );
    let e = err(&same);
    assert_eq!(e.key(), "devices.photodiode.port", "{e}");
    assert!(e.to_string().contains("one link per board"), "{e}");
    // Unknown events are refused by name.
    let e = err(&with_photodiode(
        "driver = \"serial-line\"\nport = \"sim\"",
        "marker_patch = { size = 8, toggle_on = [\"vsync\"] }",
    ));
    assert!(e.to_string().contains("vsync"), "{e}");
}

#[test]
fn lens_range_min_must_be_below_max() {
    let e = err(&SIM_RIG.replace(
        "lens_range = { min = -1.0, max = 4.0 }",
        "lens_range = { min = 3.0, max = 1.0 }",
    ));
    assert_eq!(e.key(), "optics.lens_range");
    assert!(e.to_string().contains("min must be below max"), "{e}");
}

#[test]
fn dlpc350_settings_are_checked_against_the_schedule() {
    let dlp = SIM_RIG.replace("driver = \"sync\"", "driver = \"dlpc350\"");
    assert_ne!(dlp, SIM_RIG);
    let cfg = RigConfig::parse(&dlp).unwrap();
    let s = cfg.devices.sync.as_ref().unwrap();
    assert_eq!(s.driver, SyncDriver::Dlpc350);
    assert_eq!(s.dlpc350_config().vsync_hz, SyncDevice::DEFAULT_VIDEO_HZ);
    // 4 planes at 240 Hz fill one 60 Hz video frame, not a 120 Hz one.
    let fast = dlp.replace("# video_hz = 60.0", "video_hz = 120.0");
    assert_ne!(fast, dlp);
    let e = err(&fast);
    assert_eq!(e.key(), "optics.subframe_hz", "{e}");
    assert!(e.to_string().contains("do not fit"), "{e}");
    // 2 planes at 240 Hz fill one 120 Hz video frame.
    let ok = fast.replace("planes = [0.2, 0.8, 1.4, 2.0]", "planes = [0.5, 1.5]");
    assert_ne!(ok, fast);
    assert_eq!(
        RigConfig::parse(&ok)
            .unwrap()
            .devices
            .sync
            .unwrap()
            .video_hz,
        Some(120.0)
    );
    let e = err(&fast.replace("video_hz = 120.0", "video_hz = 0.0"));
    assert_eq!(e.key(), "devices.sync.video_hz", "{e}");
    // The sync board follows the display's vsync: a video rate there is a mistake.
    let e = err(&fast.replace("driver = \"dlpc350\"", "driver = \"sync\""));
    assert_eq!(e.key(), "devices.sync.video_hz", "{e}");
    assert!(e.to_string().contains("only the dlpc350 driver"), "{e}");
}

#[test]
fn content_animate_is_for_the_procedural_scene() {
    let still = SIM_RIG.to_string() + "\n[content]\nanimate = false\n";
    assert_eq!(
        RigConfig::parse(&still).unwrap().content.animate,
        Some(false)
    );
    let e = err(&(SIM_RIG.to_string()
        + "\n[content]\nsource = \"stream\"\nring = \"none\"\nanimate = true\n"));
    assert_eq!(e.key(), "content.animate", "{e}");
    assert!(e.to_string().contains("source = \"scene\""), "{e}");
}

#[test]
fn unknown_keys_are_named() {
    let e = err(&SIM_RIG.replace("[optics]", "[optics]\nfocal_lenght = 3"));
    assert_eq!(e.key(), "optics.focal_lenght", "{e}");
    let s = e.to_string();
    assert!(s.contains("unknown field `focal_lenght`"), "{s}");
    assert!(s.contains("expected one of `lens_range`"), "{s}");
}

#[test]
fn wrong_types_name_the_key_and_form() {
    let e = err(&SIM_RIG.replace("park_power = 0.5", "park_power = \"far\""));
    assert_eq!(e.key(), "devices.lens.park_power", "{e}");
    assert!(e.to_string().contains("expected f32"), "{e}");
    let line = SIM_RIG
        .lines()
        .position(|l| l.starts_with("park_power"))
        .unwrap()
        + 1;
    assert!(e.to_string().contains(&format!("(line {line})")), "{e}");
}

#[test]
fn method_auto_plans_varifocal_frames_only() {
    let cfg =
        RigConfig::parse(&SIM_RIG.replace("method = \"gather\"", "method = \"auto\"")).unwrap();
    assert!(cfg.auto_method);
    // The scheduler paces frames by the mode's default method.
    assert_eq!(cfg.method, Method(RenderMethod::Gather));
    assert!(!RigConfig::parse(SIM_RIG).unwrap().auto_method);
    let e = err(&SIM_RIG
        .replace("method = \"gather\"", "method = \"auto\"")
        .replace("mode = \"varifocal\"", "mode = \"multifocal\""));
    assert_eq!(e.key(), "method", "{e}");
    assert!(e.to_string().contains("varifocal mode only"), "{e}");
    // An unknown method's message offers auto.
    let e = err(&SIM_RIG.replace("method = \"gather\"", "method = \"fast\""));
    assert!(e.to_string().contains("auto"), "{e}");
}

#[test]
fn unknown_mode_lists_the_modes() {
    let e = err(&SIM_RIG.replace("mode = \"varifocal\"", "mode = \"holographic\""));
    assert_eq!(e.key(), "mode");
    let s = e.to_string();
    assert!(s.contains("varifocal") && s.contains("multifocal"), "{s}");
}

#[test]
fn bad_ports_say_the_accepted_forms() {
    let e = err(&SIM_RIG.replace("port = \"sim\"\npark_power", "port = \"COM3\"\npark_power"));
    assert_eq!(e.key(), "devices.lens.port", "{e}");
    assert!(e.to_string().contains("VID:PID"), "{e}");
    let ok = RigConfig::parse(&SIM_RIG.replace(
        "port = \"sim\"\npark_power",
        "port = \"/dev/ttyACM0\"\npark_power",
    ))
    .unwrap();
    assert_eq!(
        ok.devices.lens.first().port,
        Port::Path("/dev/ttyACM0".into())
    );
}

/// The lens controller's USB bulk endpoints, which `dioptra lens --device lens:usb`
/// reaches, can be named in a rig config; a driver without them is refused naming the key.
#[test]
fn a_usb_bulk_port_is_for_drivers_that_have_one() {
    let port = |s: &str| Port::try_from(s.to_string());
    assert_eq!(port("usb"), Ok(Port::Usb(None)));
    assert_eq!(port("usb:A1B2"), Ok(Port::Usb(Some("A1B2".into()))));
    assert_eq!(String::from(Port::Usb(Some("A1B2".into()))), "usb:A1B2");
    assert!(port("usb:").unwrap_err().contains("usb:SERIAL"));
    let lens = SIM_RIG
        .replace("driver = \"optotune\"", "driver = \"lens\"")
        .replace(
            "port = \"sim\"\npark_power",
            "port = \"usb:A1B2\"\npark_power",
        );
    let c = RigConfig::parse(&lens).unwrap();
    assert_eq!(c.devices.lens.first().port, Port::Usb(Some("A1B2".into())));
    let optotune = SIM_RIG.replace("port = \"sim\"\npark_power", "port = \"usb\"\npark_power");
    let e = err(&optotune);
    assert_eq!(e.key(), "devices.lens.port", "{e}");
    assert!(
        e.to_string()
            .contains("Lens Driver 4 is not reached over USB bulk"),
        "{e}"
    );
    let gaze = SIM_RIG.replace(
        "port = \"sim\"                # pupil",
        "port = \"usb\"                # pupil",
    );
    assert_ne!(gaze, SIM_RIG);
    assert_eq!(err(&gaze).key(), "devices.gaze.port");
}

/// `[devices.lens.left]` and `[devices.lens.right]`: a lens per eye, each a full lens
/// section checked under its own keys; half a pair, or one lens's keys beside the pair, is
/// refused naming the key; one `[devices.lens]` is one lens as before.
#[test]
fn a_lens_per_eye_is_two_full_sections() {
    let c = RigConfig::parse(EXAMPLE_SIM_BINOCULAR_RIG).unwrap();
    assert_eq!(c.devices.lens.count(), 2);
    assert_eq!(c.devices.lens.side(1), Some(Side::Right));
    assert_eq!(c.devices.lens.name(1), "lens_right");
    assert_eq!(c.devices.lens.key(0), "devices.lens.left");
    // It goes through TOML and back (recordings keep the config).
    let again = RigConfig::parse(&toml::to_string(&c).unwrap()).unwrap();
    assert_eq!(again.devices.lens, c.devices.lens);
    let one = RigConfig::parse(SIM_RIG).unwrap();
    assert!(matches!(one.devices.lens, Lenses::One(_)));
    assert_eq!(one.devices.lens.name(0), "lens");
    let again = RigConfig::parse(&toml::to_string(&one).unwrap()).unwrap();
    assert_eq!(again.devices.lens, one.devices.lens);
    // The right's own keys are checked under its own name.
    let bad = EXAMPLE_SIM_BINOCULAR_RIG.replace(
        "[devices.lens.right]\ndriver = \"optotune\"\nport = \"sim\"\npark_power = 0.5",
        "[devices.lens.right]\ndriver = \"optotune\"\nport = \"sim\"\npark_power = 9.5",
    );
    assert_ne!(bad, EXAMPLE_SIM_BINOCULAR_RIG);
    let e = err(&bad);
    assert_eq!(e.key(), "devices.lens.right.park_power", "{e}");
    let bad = EXAMPLE_SIM_BINOCULAR_RIG.replace(
        "sim_settle_ms = 15.0\n\n[devices.gaze]",
        "sim_settle_ms = 15.0\nbogus = 1\n\n[devices.gaze]",
    );
    assert_ne!(bad, EXAMPLE_SIM_BINOCULAR_RIG);
    let e = err(&bad);
    assert_eq!(e.key(), "devices.lens.right.bogus", "{e}");
    // A right lens without a left one; a left without a right; one lens's keys beside both.
    let right_only =
        EXAMPLE_SIM_BINOCULAR_RIG.replace("[devices.lens.left]", "[devices.lens.unused]");
    let e = err(&right_only);
    assert!(e.to_string().contains("unused"), "{e}");
    let start = EXAMPLE_SIM_BINOCULAR_RIG
        .find("[devices.lens.left]")
        .unwrap();
    let end = EXAMPLE_SIM_BINOCULAR_RIG
        .find("[devices.lens.right]")
        .unwrap();
    let no_left = format!(
        "{}{}",
        &EXAMPLE_SIM_BINOCULAR_RIG[..start],
        &EXAMPLE_SIM_BINOCULAR_RIG[end..]
    );
    let e = err(&no_left);
    assert_eq!(e.key(), "devices.lens", "{e}");
    assert!(
        e.to_string().contains("a right lens without a left one"),
        "{e}"
    );
    let gaze = EXAMPLE_SIM_BINOCULAR_RIG.find("[devices.gaze]").unwrap();
    let no_right = format!(
        "{}{}",
        &EXAMPLE_SIM_BINOCULAR_RIG[..end],
        &EXAMPLE_SIM_BINOCULAR_RIG[gaze..]
    );
    let e = err(&no_right);
    assert!(
        e.to_string().contains("a left lens without a right one"),
        "{e}"
    );
    let mixed = EXAMPLE_SIM_BINOCULAR_RIG.replace(
        "[devices.lens.left]",
        "[devices.lens]\npark_power = 0.5\n\n[devices.lens.left]",
    );
    let e = err(&mixed);
    assert!(
        e.to_string().contains("devices.lens.left.park_power"),
        "{e}"
    );
}

#[test]
fn ports_tell_vid_pids_from_network_addresses() {
    let port = |s: &str| Port::try_from(s.to_string());
    assert_eq!(port("1209:d10a"), Ok(Port::VidPid(0x1209, 0xd10a)));
    // Four digits each side are hex: a VID:PID, never a host.
    assert_eq!(port("1234:5678"), Ok(Port::VidPid(0x1234, 0x5678)));
    for a in [
        "127.0.0.1:50020",
        "localhost:50020",
        "[::1]:50020",
        "capture.lab:50020",
    ] {
        assert_eq!(port(a), Ok(Port::Net(a.into())), "{a}");
        assert_eq!(String::from(Port::Net(a.into())), a);
    }
    for bad in [
        "capture:50020",
        "127.0.0.1:0",
        "127.0.0.1:70000",
        "127.0.0.1:",
        "localhost",
        ".lab:1",
        "::1:50020",
        "1209:d10",
    ] {
        let e = port(bad).unwrap_err();
        assert!(
            e.contains("host:port") && e.contains("VID:PID"),
            "{bad}: {e}"
        );
    }
}

#[test]
fn the_pupil_driver_takes_an_address_and_a_confidence_threshold() {
    let pupil = SIM_RIG.replace("driver = \"dioptra-tracker\"", "driver = \"pupil\"");
    assert_ne!(pupil, SIM_RIG);
    let c = RigConfig::parse(&pupil).unwrap();
    assert_eq!(c.devices.gaze.driver, GazeDriver::Pupil);
    assert_eq!(c.devices.gaze.min_confidence, 0.6);
    let net = pupil.replace(
        "port = \"sim\"                # pupil",
        "port = \"127.0.0.1:50020\"\nmin_confidence = 0.8 # pupil",
    );
    assert_ne!(net, pupil);
    let c = RigConfig::parse(&net).unwrap();
    assert_eq!(c.devices.gaze.port, Port::Net("127.0.0.1:50020".into()));
    assert_eq!(c.devices.gaze.min_confidence, 0.8);
    let e = err(&net.replace("min_confidence = 0.8", "min_confidence = 1.2"));
    assert_eq!(e.key(), "devices.gaze.min_confidence", "{e}");
    // A path is not where Pupil Capture is; an address is not where a HID tracker is.
    let e = err(&pupil.replace(
        "port = \"sim\"                # pupil",
        "port = \"/dev/hidraw0\" # pupil",
    ));
    assert_eq!(e.key(), "devices.gaze.port", "{e}");
    let e = err(&SIM_RIG.replace(
        "port = \"sim\"                # pupil",
        "port = \"127.0.0.1:50020\" # pupil",
    ));
    assert_eq!(e.key(), "devices.gaze.port", "{e}");
    assert!(e.to_string().contains("pupil"), "{e}");
}

#[test]
fn missing_sections_are_named() {
    let start = SIM_RIG.find("[devices.gaze]").unwrap();
    let end = SIM_RIG.find("[optics]").unwrap();
    let text = format!("{}{}", &SIM_RIG[..start], &SIM_RIG[end..]);
    let e = err(&text);
    assert!(e.to_string().contains("missing field `gaze`"), "{e}");
    assert_eq!(e.key(), "devices");
}

#[test]
fn park_power_must_be_inside_the_lens_range() {
    let e = err(&SIM_RIG.replace("park_power = 0.5", "park_power = 9.0"));
    assert_eq!(e.key(), "devices.lens.park_power");
}

#[test]
fn multifocal_needs_a_sync_board_and_a_decomposition() {
    let text = SIM_RIG.replace("mode = \"varifocal\"", "mode = \"multifocal\"");
    let start = text.find("[devices.sync]").unwrap();
    let end = text.find("[optics]").unwrap();
    let no_sync = format!("{}{}", &text[..start], &text[end..]);
    assert_eq!(err(&no_sync).key(), "devices.sync");
    let e = err(&text);
    assert_eq!(e.key(), "method");
    assert!(e.to_string().contains("linear, optimized"), "{e}");
    let ok = RigConfig::parse(&text.replace("method = \"gather\"", "method = \"linear\""));
    assert!(ok.is_ok(), "{ok:?}");
}

/// Relative paths are the config file's folder's, from any working directory (issue 39
/// item 3); absolute ones stay.
#[test]
fn relative_paths_are_read_from_the_config_files_folder() {
    let dir = tempfile::tempdir().unwrap();
    let text = SIM_RIG.replace("dir = \"recordings\"", "dir = \"rec\"")
        + "\n[content]\nsource = \"files\"\ncolor = \"stim/c_%04d.png\"\n\
           depth = \"/abs/d.exr\"\n\n[render]\nweights = \"w\"\n";
    let path = dir.path().join("rig.toml");
    std::fs::write(&path, &text).unwrap();
    let cfg = RigConfig::load(&path).unwrap();
    let base = std::path::absolute(dir.path()).unwrap();
    assert_eq!(cfg.recording.as_ref().unwrap().dir, base.join("rec"));
    assert_eq!(
        cfg.content.color.as_deref(),
        Some(base.join("stim/c_%04d.png").to_str().unwrap())
    );
    assert_eq!(cfg.content.depth.as_deref(), Some("/abs/d.exr"));
    assert_eq!(cfg.render.weights, Some(base.join("w")));
    // Text without a file: the working directory's, as before.
    let cfg = RigConfig::parse(&text).unwrap();
    assert_eq!(cfg.recording.unwrap().dir, PathBuf::from("rec"));
}

/// `devices.*.required`: true for a real port by default, false for a simulator; the
/// config can say otherwise.
#[test]
fn devices_are_required_by_default_on_a_real_port() {
    let cfg = RigConfig::parse(SIM_RIG).unwrap();
    assert!(cfg.devices.list().iter().all(|d| !d.required));
    let real = SIM_RIG.replacen("port = \"sim\"", "port = \"/dev/ttyACM0\"", 1);
    let cfg = RigConfig::parse(&real).unwrap();
    let list = cfg.devices.list();
    assert_eq!((list[0].name.as_str(), list[0].required), ("lens", true));
    let optional = real.replacen("park_power", "required = false\npark_power", 1);
    assert!(!RigConfig::parse(&optional).unwrap().devices.list()[0].required);
}

#[test]
fn pupil_and_settle_times_are_checked_as_their_messages_say() {
    let e = err(&SIM_RIG.replace("pupil_mm = 4.0", "pupil_mm = 40.0"));
    assert_eq!(e.key(), "eye.pupil_mm", "{e}");
    assert!(e.to_string().contains("1 to 10 mm (got 40"), "{e}");
    assert!(RigConfig::parse(&SIM_RIG.replace("pupil_mm = 4.0", "pupil_mm = 8.0")).is_ok());
    // 0 is refused, and the message says so.
    let e = err(&SIM_RIG.replace("sim_settle_ms = 0.8", "sim_settle_ms = 0.0"));
    assert_eq!(e.key(), "devices.sync.sim_settle_ms", "{e}");
    assert!(
        e.to_string()
            .contains("above 0 and at most 1000 ms (got 0)"),
        "{e}"
    );
    let e = err(&SIM_RIG.replace("sim_settle_ms = 15.0", "sim_settle_ms = 0.0"));
    assert_eq!(e.key(), "devices.lens.sim_settle_ms", "{e}");
    assert!(e.to_string().contains("above 0 and at most 1000 ms"), "{e}");
}

#[test]
fn the_display_layout_and_its_monitors_and_offsets_are_checked() {
    let with = |extra: &str| {
        let (kind, rest) = match extra.strip_prefix("kind = \"window\"\n") {
            Some(rest) => ("window", rest),
            None => ("headless", extra),
        };
        SIM_RIG
            .replacen("kind = \"headless\"", &format!("kind = \"{kind}\""), 1)
            .replacen("[display]", &format!("[display]\n{rest}"), 1)
    };
    let c = RigConfig::parse(&with(
        "layout = \"side-by-side\"\neye_offset_px = { left = [-12, 0], right = [12, 3] }",
    ))
    .unwrap();
    assert_eq!(c.display.layout, DisplayLayout::SideBySide);
    assert!(c.display.stereo());
    assert_eq!(c.display.eye_offset_px.of(Side::Right), [12, 3]);
    assert_eq!(c.display.scale, Scale::Exact);
    let c = RigConfig::parse(&with("scale = \"fit\"")).unwrap();
    assert_eq!(c.display.scale, Scale::Fit);
    assert!(!c.display.stereo());
    // Headless two-outputs: an image per eye, no monitors.
    assert!(RigConfig::parse(&with("layout = \"two-outputs\"")).is_ok());
    for (extra, key) in [
        ("layout = \"sideways\"", "display.layout"),
        (
            "layout = \"two-outputs\"\nmonitor_left = 0",
            "display.monitor_left",
        ),
        (
            "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = 0",
            "display.monitor_right",
        ),
        (
            "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = 1\nmonitor_right = 1",
            "display.monitor_right",
        ),
        (
            "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor = 0",
            "display.monitor",
        ),
        (
            "kind = \"window\"\nlayout = \"side-by-side\"\nmonitor_right = 1",
            "display.monitor_right",
        ),
        (
            "eye_offset_px = { right = [4, 0] }",
            "display.eye_offset_px.right",
        ),
        (
            "layout = \"side-by-side\"\neye_offset_px = { left = [9000, 0] }",
            "display.eye_offset_px.left",
        ),
    ] {
        let e = err(&with(extra));
        assert_eq!(e.key(), key, "{extra}: {e}");
    }
    let two = RigConfig::parse(&with(
        "kind = \"window\"\nlayout = \"two-outputs\"\nmonitor_left = \"DP-1\"\nmonitor_right = \"DP-2\"",
    ))
    .unwrap();
    assert_eq!(
        two.display.monitor_right,
        Some(MonitorChoice::Name("DP-2".into()))
    );
}

#[test]
fn a_simulated_multifocal_lens_slower_than_the_dark_allowance_is_refused() {
    let slow = SIM_RIG.replace("sim_settle_ms = 0.8", "sim_settle_ms = 1.2");
    let e = err(&slow);
    assert_eq!(e.key(), "devices.sync.sim_settle_ms", "{e}");
    assert!(e.to_string().contains("optics.subframe_hz"), "{e}");
    // At 120 Hz sub-frames the dark quarter is 2.08 ms: 1.2 ms fits.
    assert!(RigConfig::parse(&slow.replace("subframe_hz = 240.0", "subframe_hz = 120.0")).is_ok());
}

#[test]
fn optotune_temperature_limits_are_checked() {
    let with = |v: &str| {
        SIM_RIG.replace(
            "park_power = 0.5",
            &format!("park_power = 0.5\ntemperature_limits_c = {v}"),
        )
    };
    let ok = RigConfig::parse(&with("[15.0, 45.0]")).unwrap();
    assert_eq!(
        ok.devices.lens.first().temperature_limits_c,
        Some([15.0, 45.0])
    );
    for bad in ["[45.0, 15.0]", "[-200.0, 40.0]", "[20.0, nan]"] {
        let e = err(&with(bad));
        assert_eq!(e.key(), "devices.lens.temperature_limits_c", "{bad}: {e}");
    }
    let other = with("[15.0, 45.0]").replace("driver = \"optotune\"", "driver = \"lens\"");
    assert_eq!(err(&other).key(), "devices.lens.temperature_limits_c");
}

#[test]
fn a_remote_listen_address_needs_allow_remote() {
    let text = SIM_RIG.replace("127.0.0.1:7420", "0.0.0.0:7420");
    let e = err(&text);
    assert_eq!(e.key(), "api.listen");
    assert!(e.to_string().contains("allow_remote"), "{e}");
    // Reachable from other machines: only with a token.
    let remote = text.replace("[api]", "[api]\nallow_remote = true");
    assert_eq!(err(&remote).key(), "api.token_file");
    let with_token = remote.replace("[api]", "[api]\ntoken = \"0123456789abcdef0123\"");
    let ok = RigConfig::parse(&with_token).unwrap();
    assert!(matches!(ok.api.listen().unwrap(), Listen::Tcp(a) if !a.ip().is_loopback()));
    assert_eq!(
        ok.api.bearer_token().unwrap().as_deref(),
        Some("0123456789abcdef0123")
    );
    let e = err(&remote.replace("[api]", "[api]\ntoken = \"short\""));
    assert_eq!(e.key(), "api.token");
    let e = err(&SIM_RIG.replace("127.0.0.1:7420", "localhost"));
    assert!(e.to_string().contains("IP:PORT"), "{e}");
}

#[test]
fn toml_syntax_errors_say_where() {
    let e = err("mode = varifocal");
    assert!(e.to_string().contains("line 1"), "{e}");
}

#[test]
fn the_display_kind_and_monitor_parse() {
    let win = |extra: &str| {
        RigConfig::parse(&SIM_RIG.replace(
            "kind = \"headless\"",
            &format!("kind = \"window\"\n{extra}"),
        ))
    };
    let c = win("monitor = \"HDMI-1\"").unwrap();
    assert_eq!(c.display.kind, SinkKind::Window);
    assert_eq!(
        c.display.monitor,
        Some(MonitorChoice::Name("HDMI-1".into()))
    );
    let c = win("monitor = 1").unwrap();
    assert_eq!(c.display.monitor, Some(MonitorChoice::Index(1)));
    assert_eq!(win("").unwrap().display.monitor, None);
    let e = win("monitor = 1.5").unwrap_err();
    assert_eq!(e.key(), "display.monitor", "{e}");
    assert!(e.to_string().contains("a monitor name such as"), "{e}");
    let e = err(&SIM_RIG.replace("kind = \"headless\"", "kind = \"screen\""));
    assert_eq!(e.key(), "display.kind", "{e}");
    assert!(
        e.to_string().contains("expected `headless` or `window`"),
        "{e}"
    );
    // A monitor without the window is a mistake worth naming.
    let e = err(&SIM_RIG.replace("kind = \"headless\"", "kind = \"headless\"\nmonitor = 0"));
    assert_eq!(e.key(), "display.monitor", "{e}");
    // The older key name still reads.
    let c = RigConfig::parse(&SIM_RIG.replace("kind = \"headless\"", "sink = \"window\"")).unwrap();
    assert_eq!(c.display.kind, SinkKind::Window);
}

/// `text` with `extra` added to the end of its `[optics]` section.
fn with_optics(text: &str, extra: &str) -> String {
    text.replace(
        "subframe_hz = 240.0\n",
        &format!("subframe_hz = 240.0\n{extra}\n"),
    )
}

#[test]
fn old_configs_with_display_distance_still_load_and_say_where_it_moved() {
    assert!(!SIM_RIG.contains("\ndisplay_distance_m"));
    let old = SIM_RIG.replace("[optics]\n", "[optics]\ndisplay_distance_m = 1.0\n");
    assert_ne!(old, SIM_RIG);
    let c = RigConfig::parse(&old).unwrap();
    assert!(c.optics_map(None).unwrap().is_identity());
    let notes = c.notices().join("\n");
    assert!(
        notes.contains("optics.display_distance_m is no longer read")
            && notes.contains("[optics.layout] display_distance_m"),
        "{notes}"
    );
    assert!(RigConfig::parse(SIM_RIG).unwrap().notices().is_empty());
    // Beside a layout it is a mistake.
    let e = err(&with_optics(
        &old,
        "[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.0",
    ));
    assert_eq!(e.key(), "optics.display_distance_m", "{e}");
    assert!(e.to_string().contains("moved to [optics.layout]"), "{e}");
}

#[test]
fn nothing_configured_is_the_identity_map() {
    let c = RigConfig::parse(SIM_RIG).unwrap();
    for side in [None, Some(Side::Left), Some(Side::Right)] {
        let m = c.optics_map(side).unwrap();
        assert!(m.is_identity());
        assert_eq!(m.command_for(Diopters(1.5)), Diopters(1.5));
    }
}

#[test]
fn optics_layouts_tables_and_prescriptions_resolve_per_eye() {
    let dir = tempfile::tempdir().unwrap();
    // A table measured on the left eye: demand 2 - command, every 0.5 D over the range.
    let rows: String = (0..=10)
        .map(|k| {
            let c = -1.0 + 0.5 * f64::from(k);
            format!("{c},{}\n", 2.0 - c)
        })
        .collect();
    std::fs::create_dir(dir.path().join("cal")).unwrap();
    std::fs::write(
        dir.path().join("cal/left.csv"),
        format!("# test\ncommand_d,demand_d\n{rows}"),
    )
    .unwrap();
    let text = with_optics(
        SIM_RIG,
        "prescription_sphere_d = -1.0\nprescription_vertex_mm = 0.0\n\
         [optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.02\nfixed_power_d = 18.0\n\
         [optics.left]\ncalibration = \"cal/left.csv\"\nprescription_sphere_d = 0.5",
    );
    let path = dir.path().join("rig.toml");
    std::fs::write(&path, &text).unwrap();
    // Loaded from another working directory: the table is found beside the config.
    let c = RigConfig::load(&path).unwrap();
    let left = c.optics_map(Some(Side::Left)).unwrap();
    assert_eq!(left.source_name(), "calibration");
    // Focus 1 D, Rx +0.5 at 0 mm: presented 0.5 D; the table gives command 1.5 D.
    assert!((left.command_for(Diopters(1.0)).0 - 1.5).abs() < 1e-5);
    // The layout still gives the magnification.
    assert!(left.magnification(Diopters(0.0)).is_some());
    // The right eye has the shared layout and prescription: focus 1 D with Rx -1 at 0 mm
    // is presented at 2 D; X = 2 / (1 - 0.04), command = 20 - 18 - X = -0.083333.
    let right = c.optics_map(Some(Side::Right)).unwrap();
    assert_eq!(right.source_name(), "layout");
    assert!((right.command_for(Diopters(1.0)).0 + 0.083333).abs() < 1e-5);
    // The one lens of this rig is the left eye's (the one per-eye section).
    assert_eq!(c.optics_map(None).unwrap(), left);
    // Parsed without a file, the relative path is read from the working directory.
    let e = err(&text);
    assert_eq!(e.key(), "optics.left.calibration", "{e}");
    assert!(
        e.to_string()
            .contains("relative paths are read from the config file's folder"),
        "{e}"
    );
}

#[test]
fn bad_optics_settings_name_the_key_the_file_and_the_points() {
    let dir = tempfile::tempdir().unwrap();
    let load = |extra: &str| {
        let path = dir.path().join("rig.toml");
        std::fs::write(&path, with_optics(SIM_RIG, extra)).unwrap();
        RigConfig::load(&path)
    };
    let e = load("[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = -0.01").unwrap_err();
    assert_eq!(e.key(), "optics.layout.eye_relief_m", "{e}");
    let e = load("[optics.layout]\ndisplay_distance_m = 0.05").unwrap_err();
    assert_eq!(e.key(), "optics.layout", "{e}");
    assert!(
        e.to_string().contains("missing field `eye_relief_m`"),
        "{e}"
    );
    // The image would reach the eye inside the lens range.
    let e = load(
        "[optics.layout]\ndisplay_distance_m = 0.05\neye_relief_m = 0.05\nfixed_power_d = 38.0",
    )
    .unwrap_err();
    assert_eq!(e.key(), "optics.layout", "{e}");
    let e = load("[optics.right]\nprescription_sphere_d = -2.0\nprescription_cylinder_d = -0.5")
        .unwrap_err();
    assert_eq!(e.key(), "optics.right.prescription_cylinder_d", "{e}");
    assert!(e.to_string().contains("spherical equivalent"), "{e}");
    let e = load("calibration = \"nope.csv\"").unwrap_err();
    assert_eq!(e.key(), "optics.calibration", "{e}");
    assert!(
        e.to_string()
            .contains(&dir.path().join("nope.csv").display().to_string()),
        "{e}"
    );
    std::fs::write(
        dir.path().join("bent.csv"),
        "command_d,demand_d\n-1,3\n0,2\n1,2.2\n2,0\n3,-1\n4,-2\n",
    )
    .unwrap();
    let e = load("calibration = \"bent.csv\"").unwrap_err();
    assert_eq!(e.key(), "optics.calibration", "{e}");
    let s = e.to_string();
    assert!(s.contains("bent.csv") && s.contains("not monotonic"), "{s}");
    assert!(
        s.contains("(command 0 D, demand 2 D) (line 3) -> (command 1 D, demand 2.2 D) (line 4)"),
        "{s}"
    );
    std::fs::write(
        dir.path().join("short.csv"),
        "command_d,demand_d\n-1,3\n0,2\n1,1\n2,0\n",
    )
    .unwrap();
    let e = load("calibration = \"short.csv\"").unwrap_err();
    assert!(
        e.to_string().contains("span -1..2 D") && e.to_string().contains("-1..4 D"),
        "{e}"
    );
    let e = load(
        "[optics.left]\nprescription_sphere_d = -1.0\n[optics.right]\nprescription_sphere_d = -2.0",
    )
    .unwrap_err();
    assert_eq!(e.key(), "optics.right", "{e}");
    assert!(e.to_string().contains("one lens"), "{e}");
    let e = load("[optics.left]\nfocal_power = 1").unwrap_err();
    assert_eq!(e.key(), "optics.left.focal_power", "{e}");
}

#[test]
fn the_lens_model_settles_as_the_lens_does() {
    let c = RigConfig::parse(SIM_RIG).unwrap();
    assert_eq!(c.devices.lens.first().model_settle_ms(), 15.0);
    let slow =
        RigConfig::parse(&SIM_RIG.replace("sim_settle_ms = 15.0", "sim_settle_ms = 40.0")).unwrap();
    assert_eq!(slow.devices.lens.first().model_settle_ms(), 40.0);
    // A real lens: its own settle_ms, not the simulator's.
    let real = SIM_RIG.replace(
        "port = \"sim\"\npark_power",
        "port = \"/dev/ttyACM0\"\npark_power",
    );
    assert_ne!(real, SIM_RIG);
    let c =
        RigConfig::parse(&real.replace("sim_settle_ms = 15.0", "sim_settle_ms = 40.0")).unwrap();
    assert_eq!(
        c.devices.lens.first().model_settle_ms(),
        LensDevice::DEFAULT_SETTLE_MS
    );
    assert!(c
        .notices()
        .join(" ")
        .contains("devices.lens.settle_ms is not set"));
    let c =
        RigConfig::parse(&real.replace("park_power = 0.5", "park_power = 0.5\nsettle_ms = 8.0"))
            .unwrap();
    assert_eq!(c.devices.lens.first().model_settle_ms(), 8.0);
    assert!(c.notices().is_empty());
    let e = err(&real.replace("park_power = 0.5", "park_power = 0.5\nsettle_ms = 0.0"));
    assert_eq!(e.key(), "devices.lens.settle_ms", "{e}");
}

#[test]
fn planes_outside_the_lens_range_are_refused() {
    let e = err(&SIM_RIG.replace("planes = [0.2, 0.8, 1.4, 2.0]", "planes = [0.2, 8.0]"));
    assert_eq!(e.key(), "optics.planes");
}

/// `%e` in the files' patterns: each eye's sequence on a stereo layout; refused on a mono
/// one and in one pattern without the other, naming the key.
#[test]
fn eye_patterns_need_a_stereo_layout_and_both_keys() {
    let files = |layout: &str, color: &str, depth: &str| {
        SIM_RIG.replacen("[display]", &format!("[display]\nlayout = \"{layout}\""), 1)
            + &format!("\n[content]\nsource = \"files\"\ncolor = {color:?}\ndepth = {depth:?}\n")
    };
    let ok = RigConfig::parse(&files("side-by-side", "s/%e/c_%04d.png", "s/%e/d_%04d.exr"));
    assert!(ok.is_ok(), "{ok:?}");
    // Without %e a stereo rig shows one view (each eye's synthesised).
    assert!(RigConfig::parse(&files("two-outputs", "c.png", "d.exr")).is_ok());
    let e = err(&files("one", "s/%e/c.png", "s/%e/d.exr"));
    assert_eq!(e.key(), "content.color", "{e}");
    assert!(e.to_string().contains("display.layout"), "{e}");
    let e = err(&files("one", "c.png", "d_%e.exr"));
    assert_eq!(e.key(), "content.depth", "{e}");
    let e = err(&files("side-by-side", "c_%e.png", "d.exr"));
    assert_eq!(e.key(), "content.depth", "{e}");
    assert!(e.to_string().contains("content.color names"), "{e}");
    let e = err(&files("side-by-side", "c.png", "d_%e.exr"));
    assert_eq!(e.key(), "content.color", "{e}");
}

/// `content.views`: a grid of 2 to 9 views a side with `%v` in both patterns and a span
/// of 0 to 100 mm; `%v` without it, or a grid with another source, names the key.
#[test]
fn a_view_grid_needs_its_mark_its_size_and_files() {
    let files = |extra: &str, color: &str, depth: &str| {
        format!(
            "{SIM_RIG}\n[content]\nsource = \"files\"\ncolor = {color:?}\ndepth = {depth:?}\n{extra}\n"
        )
    };
    let ok = RigConfig::parse(&files("views = 3", "lf/v_%v.png", "lf/v_%v.exr"));
    assert_eq!(ok.map(|c| c.content.views).ok(), Some(Some(3)));
    let ok = RigConfig::parse(&files(
        "views = 2\nview_span_mm = 4.5",
        "lf/%04d/v_%v.png",
        "lf/%04d/v_%v.exr",
    ));
    assert!(ok.is_ok(), "{ok:?}");
    for (extra, color, depth, key, says) in [
        ("", "v_%v.png", "v_%v.exr", "content.color", "content.views"),
        ("views = 3", "v.png", "v_%v.exr", "content.color", "%v"),
        ("views = 3", "v_%v.png", "v.exr", "content.depth", "%v"),
        (
            "views = 1",
            "v_%v.png",
            "v_%v.exr",
            "content.views",
            "2 to 9",
        ),
        (
            "views = 12",
            "v_%v.png",
            "v_%v.exr",
            "content.views",
            "2 to 9",
        ),
        (
            "view_span_mm = 4",
            "v.png",
            "v.exr",
            "content.view_span_mm",
            "views",
        ),
        (
            "views = 3\nview_span_mm = -1",
            "v_%v.png",
            "v_%v.exr",
            "content.view_span_mm",
            "0 to 100",
        ),
        (
            "views = 3\nview_span_mm = nan",
            "v_%v.png",
            "v_%v.exr",
            "content.view_span_mm",
            "0 to 100",
        ),
    ] {
        let e = err(&files(extra, color, depth));
        assert_eq!(e.key(), key, "{extra} {color} {depth}: {e}");
        assert!(e.to_string().contains(says), "{e}");
    }
    let e = err(&format!(
        "{SIM_RIG}\n[content]\nsource = \"scene\"\nviews = 3\n"
    ));
    assert_eq!(e.key(), "content.views", "{e}");
    // A stream takes a grid without patterns.
    let stream = |extra: &str| format!("{SIM_RIG}\n[content]\nsource = \"stream\"\n{extra}\n");
    assert!(RigConfig::parse(&stream("views = 3\nview_span_mm = 4")).is_ok());
    assert_eq!(err(&stream("views = 10")).key(), "content.views");
    assert_eq!(
        err(&stream("view_span_mm = 4")).key(),
        "content.view_span_mm"
    );
}

#[test]
fn a_serial_number_is_taken_for_a_real_port_and_refused_for_sim() {
    let with = |port: &str, serial: &str| {
        RigConfig::parse(&EXAMPLE_SIM_RIG.replacen(
            "port = \"sim\"",
            &format!("port = \"{port}\"\nserial = \"{serial}\"\nrequired = false"),
            1,
        ))
    };
    let cfg = with("/dev/serial/by-id/usb-Optotune_LD4-if00", "LD4-0042").unwrap();
    let lens = &cfg.devices.list()[0];
    assert_eq!(lens.serial.as_deref(), Some("LD4-0042"));
    for (port, serial, words) in [
        ("sim", "LD4-0042", "has no USB serial number"),
        ("/dev/ttyACM0", "two words", "printable ASCII"),
        ("usb:AAA", "BBB", "names another"),
    ] {
        let e = with(port, serial).unwrap_err();
        assert_eq!(e.key(), "devices.lens.serial", "{e}");
        assert!(e.to_string().contains(words), "{e}");
    }
}

/// The simulated HMD example (`crates/cli/examples/rig-sim-hmd.toml`).
const HMD_RIG: &str = include_str!("../../../cli/examples/rig-sim-hmd.toml");

#[test]
fn the_hmd_example_gives_each_eye_its_compensation_eyepiece_and_transfer() {
    let c = RigConfig::parse(HMD_RIG).unwrap();
    let images = c.eye_images().unwrap();
    assert_eq!(images.len(), 2);
    for (image, side) in images.iter().zip(Side::BOTH) {
        assert_eq!(image.eye, Some(side));
        assert_eq!(image.lens, usize::from(side == Side::Right));
        // The reference is the power of least magnification: the range's lower end.
        assert_eq!(image.reference, Some(Diopters(-1.0)));
        let e = image.eyepiece.as_ref().unwrap();
        assert_eq!(e.from, "optics.distortion");
        assert_eq!(e.model.channels[0].camera.fx, 227.25);
        assert_eq!(e.model.channels[1].coefficients.k1, -0.18);
        assert_eq!(
            image.transfer,
            dioptra_core::transfer::Transfer::gamma(2.4, 0.0).unwrap()
        );
    }
    // Without the key the compensation is on where a layout gives the magnification.
    let default = HMD_RIG.replace("compensate_magnification = true\n", "");
    assert_ne!(default, HMD_RIG);
    let c = RigConfig::parse(&default).unwrap();
    assert!(c
        .eye_images()
        .unwrap()
        .iter()
        .all(|i| i.reference.is_some()));
    // And off without one.
    let c = RigConfig::parse(SIM_RIG).unwrap();
    let images = c.eye_images().unwrap();
    assert_eq!(images.len(), 1);
    assert!(images[0].reference.is_none() && images[0].eyepiece.is_none());
    assert_eq!(images[0].transfer, dioptra_core::transfer::Transfer::Srgb);
}

#[test]
fn image_settings_are_checked_naming_the_key() {
    let no_layout = with_optics(SIM_RIG, "compensate_magnification = true");
    assert_ne!(no_layout, SIM_RIG);
    for (text, key, says) in [
        (
            no_layout,
            "optics.compensate_magnification",
            "not known without a thin-lens layout",
        ),
        (
            HMD_RIG.replace("k2 = 0.03", "k2 = \"x\""),
            "optics.distortion.k2",
            "",
        ),
        (
            HMD_RIG.replace("fx = 227.25", "fx = -1.0"),
            "optics.distortion.red.fx",
            "focal length above 0",
        ),
        (
            HMD_RIG.replace("cx = 239.5", "cx = 900.0"),
            "optics.distortion.cx",
            "off the eye's 480x270 image",
        ),
        (
            HMD_RIG.replace("transfer = { gamma = 2.4 }", "transfer = { gamma = 9.0 }"),
            "display.transfer.gamma",
            "0.2 to 5",
        ),
        (
            HMD_RIG.replace(
                "transfer = { gamma = 2.4 }",
                "transfer = { table = \"no-such-panel.csv\" }",
            ),
            "display.transfer.table",
            "cannot read the transfer table",
        ),
        (
            HMD_RIG.replace(
                "transfer = { gamma = 2.4 }",
                "transfer_left = { gamma = 2.2 }",
            ),
            "display.transfer_left",
            "two-outputs",
        ),
        (
            HMD_RIG.replace(
                "compensate_magnification = true\n",
                "compensate_magnification = true\ndistortion_file = \"eyepiece.toml\"\n",
            ),
            "optics.distortion_file",
            "cannot read the distortion file",
        ),
    ] {
        let e = err(&text);
        assert_eq!(e.key(), key, "{e}");
        assert!(e.to_string().contains(says), "{e}");
    }
}

#[test]
fn distortion_files_and_transfer_tables_are_read_from_the_config_files_folder() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("eyepiece.toml"),
        "[optics.distortion]\nfx = 225.0\nfy = 225.0\ncx = 239.5\ncy = 134.5\nk1 = -0.1\n",
    )
    .unwrap();
    let table: String = std::iter::once("level,luminance_cd_m2\n".to_string())
        .chain((0..=10).map(|i| {
            let c = f64::from(i) / 10.0;
            format!("{c},{}\n", 0.2 + 100.0 * c.powf(2.2))
        }))
        .collect();
    std::fs::write(dir.path().join("panel.csv"), table).unwrap();
    let text = HMD_RIG
        .replace(
            "compensate_magnification = true\n",
            "compensate_magnification = true\ndistortion_file = \"eyepiece.toml\"\n",
        )
        .replace("[optics.distortion]\n", "[unused]\n")
        .replace(
            "transfer = { gamma = 2.4 }",
            "transfer = { table = \"panel.csv\" }",
        );
    // The inline section is gone (its keys went under [unused], which is refused): keep only
    // the file.
    let text: String = {
        let start = text.find("[unused]").unwrap();
        let end = text.find("[eye]").unwrap();
        format!("{}{}", &text[..start], &text[end..])
    };
    let path = dir.path().join("rig.toml");
    std::fs::write(&path, text).unwrap();
    let c = RigConfig::load(&path).unwrap();
    let images = c.eye_images().unwrap();
    let e = images[1].eyepiece.as_ref().unwrap();
    assert_eq!(e.model.channels[2].coefficients.k1, -0.1);
    assert!(e.from.ends_with("eyepiece.toml"), "{}", e.from);
    assert!(matches!(
        images[0].transfer,
        dioptra_core::transfer::Transfer::Table(_)
    ));
    // Both kept with the config (a recording holds them).
    assert_eq!(c.calibration_tables.len(), 2);
}

/// `render.foveation`: off by default, a radius and a fall-off, errors naming the key.
#[test]
fn foveation_is_off_or_a_radius_and_a_falloff_for_the_pyramid() {
    let with = |method: &str, fov: &str| {
        SIM_RIG.replace("method = \"gather\"", &format!("method = \"{method}\""))
            + &format!("\n[render]\nfoveation = {fov}\n")
    };
    assert_eq!(
        RigConfig::parse(SIM_RIG)
            .unwrap()
            .render
            .foveation
            .settings(),
        None
    );
    let off = RigConfig::parse(&with("gather", "\"off\"")).unwrap();
    assert_eq!(off.render.foveation.settings(), None);
    let on = RigConfig::parse(&with(
        "pyramid",
        "{ radius_deg = 4.0, falloff_arcmin_per_deg = 3.0 }",
    ))
    .unwrap();
    let f = on.render.foveation.settings().unwrap();
    assert_eq!(f.radius_deg, 4.0);
    assert!((f.mar_slope - 0.05).abs() < 1e-6, "{f:?}");
    // The defaults: 5 degrees, Guenter et al.'s 1.32 arcmin per degree.
    let d = RigConfig::parse(&with("auto", "{}")).unwrap();
    let f = d.render.foveation.settings().unwrap();
    assert_eq!(f.radius_deg, 5.0);
    assert!((f.mar_slope * 60.0 - 1.32).abs() < 1e-5, "{f:?}");
    for (method, fov, key, says) in [
        (
            "pyramid",
            "{ radius_deg = -1.0 }",
            "render.foveation.radius_deg",
            "eye.fov_deg",
        ),
        (
            "pyramid",
            "{ radius_deg = 30.0 }",
            "render.foveation.radius_deg",
            "eye.fov_deg = 20",
        ),
        (
            "pyramid",
            "{ falloff_arcmin_per_deg = 0.0 }",
            "render.foveation.falloff_arcmin_per_deg",
            "1.32",
        ),
        (
            "gather",
            "{ radius_deg = 5.0 }",
            "render.foveation",
            "method = \"pyramid\"",
        ),
        ("pyramid", "\"on\"", "render.foveation", "radius_deg"),
        (
            "pyramid",
            "{ radius = 5.0 }",
            "render.foveation",
            "radius_deg",
        ),
    ] {
        let e = err(&with(method, fov));
        assert_eq!(e.key(), key, "{fov}: {e}");
        assert!(e.to_string().contains(says), "{fov}: {e}");
    }
    // Multifocal mode has no varifocal render to foveate.
    let e = err(&(SIM_RIG
        .replace("mode = \"varifocal\"", "mode = \"multifocal\"")
        .replace("method = \"gather\"", "method = \"linear\"")
        + "\n[render]\nfoveation = { radius_deg = 5.0 }\n"));
    assert_eq!(e.key(), "render.foveation", "{e}");
}

/// `method = "hybrid"` (multifocal) with `[render.hybrid]`: defaults, settings, and errors
/// naming the key.
#[test]
fn hybrid_is_a_multifocal_method_with_its_settings_under_render_hybrid() {
    let multifocal = |hybrid: &str| {
        SIM_RIG
            .replace("mode = \"varifocal\"", "mode = \"multifocal\"")
            .replace("method = \"gather\"", "method = \"hybrid\"")
            + &format!("\n[render]\nhybrid = {hybrid}\n")
    };
    let d = RigConfig::parse(&multifocal("{}")).unwrap();
    assert_eq!(d.method, Method(RenderMethod::Hybrid));
    let p = d.render.hybrid.params();
    let want = dioptra_render::hybrid::HybridParams::default();
    assert_eq!((p.fovea_deg, p.blend_deg, p.scale), (2.5, 0.5, 0));
    assert_eq!(p.spectral, want.spectral);
    assert!(p.edges_only);
    let set = RigConfig::parse(&multifocal(
        "{ fovea_deg = 4.0, blend_deg = 1.0, scale = 2 }",
    ))
    .unwrap();
    let p = set.render.hybrid.params();
    assert_eq!((p.fovea_deg, p.blend_deg, p.scale), (4.0, 1.0, 2));
    for (hybrid, key, says) in [
        (
            "{ fovea_deg = 0.0 }",
            "render.hybrid.fovea_deg",
            "eye.fov_deg",
        ),
        (
            "{ fovea_deg = 11.0 }",
            "render.hybrid.fovea_deg",
            "eye.fov_deg = 20",
        ),
        (
            "{ fovea_deg = nan }",
            "render.hybrid.fovea_deg",
            "more than 0",
        ),
        (
            "{ blend_deg = -0.5 }",
            "render.hybrid.blend_deg",
            "0 or more",
        ),
        ("{ scale = 17 }", "render.hybrid.scale", "up to 16"),
        ("{ scale = -1 }", "render.hybrid.scale", "expected u32"),
        (
            "{ radius_deg = 2.0 }",
            "render.hybrid.radius_deg",
            "fovea_deg",
        ),
    ] {
        let e = err(&multifocal(hybrid));
        assert_eq!(e.key(), key, "{hybrid}: {e}");
        assert!(e.to_string().contains(says), "{hybrid}: {e}");
    }
    // Not a varifocal method.
    let e = err(&SIM_RIG.replace("method = \"gather\"", "method = \"hybrid\""));
    assert_eq!(e.key(), "method", "{e}");
    assert!(e.to_string().contains("varifocal"), "{e}");
}

/// `[render.spectral]`: the grid the spectral decomposition solves on; errors name the key.
#[test]
fn spectral_takes_its_grid_under_render_spectral() {
    let multifocal = |spectral: &str| {
        SIM_RIG
            .replace("mode = \"varifocal\"", "mode = \"multifocal\"")
            .replace("method = \"gather\"", "method = \"spectral\"")
            + &format!("\n[render]\nspectral = {spectral}\n")
    };
    let d = RigConfig::parse(&multifocal("{}")).unwrap();
    assert_eq!(
        d.render.spectral.params(),
        dioptra_render::SpectralParams::default()
    );
    let full = RigConfig::parse(&multifocal("{ scale = 1 }")).unwrap();
    let p = full.render.spectral.params();
    assert_eq!(p.scale, 1);
    assert_eq!(
        dioptra_render::SpectralParams { scale: 0, ..p },
        dioptra_render::SpectralParams::default()
    );
    for (spectral, says) in [
        ("{ scale = 17 }", "up to 16"),
        ("{ scale = -1 }", "expected u32"),
        ("{ grid = 2 }", "scale"),
    ] {
        let e = err(&multifocal(spectral));
        let key = if spectral.contains("grid") {
            "render.spectral.grid"
        } else {
            "render.spectral.scale"
        };
        assert_eq!(e.key(), key, "{spectral}: {e}");
        assert!(e.to_string().contains(says), "{spectral}: {e}");
    }
}

#[test]
fn pyramid_is_a_varifocal_method() {
    let c =
        RigConfig::parse(&SIM_RIG.replace("method = \"gather\"", "method = \"pyramid\"")).unwrap();
    assert_eq!(c.method, Method(RenderMethod::Pyramid));
    let e = err(&SIM_RIG
        .replace("method = \"gather\"", "method = \"pyramid\"")
        .replace("mode = \"varifocal\"", "mode = \"multifocal\""));
    assert_eq!(e.key(), "method", "{e}");
    assert!(e.to_string().contains("linear"), "{e}");
}
