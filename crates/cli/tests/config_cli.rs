//! `dioptra config check | schema | reference` as a lab runs them: the example rigs pass,
//! a wrong value and an unknown key are refused naming the key, the schema names every
//! section, and the committed key reference is what `dioptra config reference` prints now.

use std::process::Command;

/// `dioptra config ARGS`: (exit code, stdout, stderr).
fn config(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .arg("config")
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

const REFERENCE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../docs/guide/src/reference/rig-toml.md"
);

#[test]
fn the_example_rigs_check_and_say_what_they_run() {
    for name in [
        "rig-sim.toml",
        "rig-sim-binocular.toml",
        "rig-sim-photodiode.toml",
    ] {
        let (code, out, err) = config(&["check", &example(name)]);
        assert_eq!(code, 0, "{name}: {out}{err}");
        assert!(
            out.contains(": ok") && out.contains("devices.lens"),
            "{out}"
        );
    }
    let (_, out, _) = config(&["check", &example("rig-sim-binocular.toml")]);
    assert!(
        out.contains("devices.lens.left") && out.contains("devices.lens.right"),
        "{out}"
    );
}

#[test]
fn a_wrong_value_and_an_unknown_key_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let rig = std::fs::read_to_string(example("rig-sim.toml")).unwrap();
    let cases = [
        (
            rig.replace("pupil_mm = 4.0", "pupil_mm = \"four\""),
            "eye.pupil_mm",
        ),
        (
            rig.replace("ipd_mm = 63.0", "ipd_mm = 63.0\nipd_nm = 1"),
            "ipd_nm",
        ),
        (
            rig.replace(
                "lens_range = { min = -1.0, max = 4.0 }",
                "lens_range = { min = 4.0, max = -1.0 }",
            ),
            "optics.lens_range",
        ),
    ];
    for (text, key) in cases {
        let path = dir.path().join("rig.toml");
        std::fs::write(&path, text).unwrap();
        let (code, out, err) = config(&["check", path.to_str().unwrap()]);
        assert_eq!(code, 1, "{key}: {out}{err}");
        assert!(err.contains(key), "{key}: {err}");
        assert!(
            err.contains(path.to_str().unwrap()),
            "names the file: {err}"
        );
    }
    let (code, _, err) = config(&["check", "/nonexistent/rig.toml"]);
    assert_eq!(code, 1);
    assert!(err.contains("/nonexistent/rig.toml"), "{err}");
}

#[test]
fn the_schema_is_json_with_every_section_and_strict_tables() {
    let (code, out, err) = config(&["schema"]);
    assert_eq!(code, 0, "{err}");
    let schema: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(schema["$schema"]
        .as_str()
        .unwrap()
        .contains("json-schema.org"));
    let props = schema["properties"].as_object().unwrap();
    for section in [
        "mode",
        "method",
        "devices",
        "optics",
        "eye",
        "display",
        "api",
        "recording",
        "render",
        "content",
        "lsl",
    ] {
        assert!(props.contains_key(section), "no {section} in {props:?}");
    }
    // Unknown keys are refused by the daemon: the schema says so too, so editors flag typos.
    assert_eq!(schema["additionalProperties"], false);
    // Fields the config reader fills in itself are not keys.
    assert!(!props.contains_key("config_dir") && !props.contains_key("auto_method"));
}

#[test]
fn the_committed_reference_is_what_the_config_types_give() {
    let (code, fresh, err) = config(&["reference"]);
    assert_eq!(code, 0, "{err}");
    let committed = std::fs::read_to_string(REFERENCE).unwrap_or_default();
    assert!(
        committed == fresh,
        "docs/guide/src/reference/rig-toml.md is out of date: regenerate it with\n  \
         cargo run -q -p dioptra -- config reference > docs/guide/src/reference/rig-toml.md"
    );
    // Every key of the example rig is in it, by its section.
    for key in [
        "`park_power`",
        "`sim_scenario`",
        "## `[optics.lens_range]`",
        "`pupil_mm`",
        "`png_every`",
        "`listen`",
        "## `[devices.lens]`",
    ] {
        assert!(fresh.contains(key), "no {key} in the reference");
    }
}
