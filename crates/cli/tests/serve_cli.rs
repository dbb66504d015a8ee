//! `dioptra serve` and `dioptra replay` as a user runs them: the binary with the example sim
//! rig on an ephemeral port, driven over HTTP, stopped through the API; a bad config refused
//! with the key to fix. Real time, short polls; nothing here asserts how long anything took.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

const RIG: &str = include_str!("../examples/rig-sim.toml");

struct Daemon(Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn write_config(dir: &Path, record: bool) -> std::path::PathBuf {
    let text = RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace(
            "dir = \"recordings\"",
            &format!("dir = {:?}", dir.join("rec").display().to_string()),
        )
        .replace("start = false", &format!("start = {record}"));
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// (status, body) of one HTTP/1.1 request.
fn http(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    let status = out.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = out
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

#[test]
fn serve_answers_the_api_and_stops_through_it_then_replay_matches() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), true);
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&config)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let daemon = Daemon(child);
    let mut line = String::new();
    stderr.read_line(&mut line).unwrap();
    let addr: SocketAddr = line
        .trim()
        .strip_prefix("dioptra serve: API on http://")
        .unwrap_or_else(|| panic!("first line {line:?}"))
        .parse()
        .unwrap();

    let (code, body) = http(addr, "GET", "/status", "");
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"mode\":\"varifocal\""), "{body}");
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 1.25}");
    assert_eq!(code, 200, "{body}");
    // The lens follows: the simulated lens's own state reaches 1.25 D.
    let mut reached = false;
    for _ in 0..2000 {
        let (_, body) = http(addr, "GET", "/status", "");
        if body.contains("\"target_d\":1.25") && body.contains("\"settled\":true") {
            reached = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(reached, "the simulated lens never settled at 1.25 D");
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": \"far\"}");
    assert_eq!(code, 422, "{body}");

    let (code, _) = http(addr, "POST", "/shutdown", "");
    assert_eq!(code, 202);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    let mut daemon = daemon;
    let status = daemon.0.wait().unwrap();
    assert!(status.success(), "{rest}");
    assert!(rest.contains("lens parked at 0.5 D"), "{rest}");
    let recording = rest
        .split("recording ")
        .nth(1)
        .and_then(|r| r.split(" finished").next())
        .unwrap_or_else(|| panic!("no recording in {rest:?}"))
        .to_string();

    // The recording replays to the same commands (exit 0 only when it does).
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["replay", &recording])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("replay identical to the recording"), "{text}");
    assert!(text.contains("/lens/command"), "{text}");
}

#[test]
fn serve_refuses_a_bad_config_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rig.toml");
    std::fs::write(
        &path,
        RIG.replace(
            "lens_range = { min = -1.0, max = 4.0 }",
            "lens_range = { min = 4.0, max = -1.0 }",
        ),
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("optics.lens_range: min must be below max"),
        "{err}"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(dir.path().join("missing.toml"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot read the rig config"), "{err}");
}

/// `dioptra serve` with the example rig edited by `edit`, run to exit (it must fail to start).
fn serve_fails(
    dir: &Path,
    edit: impl Fn(String) -> String,
    env: &[(&str, Option<&str>)],
) -> String {
    let path = dir.join("rig.toml");
    std::fs::write(&path, edit(RIG.replace("127.0.0.1:7420", "127.0.0.1:0"))).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_dioptra"));
    cmd.args(["serve", "--config"]).arg(&path);
    for (k, v) in env {
        match v {
            Some(v) => cmd.env(k, v),
            None => cmd.env_remove(k),
        };
    }
    let out = cmd.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "serve started: {err}");
    assert!(!err.contains("panicked"), "{err}");
    err
}

fn window_rig(text: String) -> String {
    text.replace(
        "kind = \"headless\"",
        "kind = \"window\"\nmonitor = \"HDMI-1\"",
    )
}

#[test]
fn the_window_sink_without_a_display_fails_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let no_display = [
        ("DISPLAY", None),
        ("WAYLAND_DISPLAY", None),
        ("WAYLAND_SOCKET", None),
    ];
    let err = serve_fails(dir.path(), window_rig, &no_display);
    assert!(
        err.contains(
            "no display: set DISPLAY/WAYLAND_DISPLAY or use [display] kind = \"headless\""
        ),
        "{err}"
    );
    // A display named but not there: winit's own failure, said as an error, not a panic.
    let gone = [
        ("DISPLAY", Some(":87")),
        ("WAYLAND_DISPLAY", None),
        ("WAYLAND_SOCKET", None),
    ];
    let err = serve_fails(dir.path(), window_rig, &gone);
    assert!(err.contains("cannot open the display"), "{err}");
    assert!(err.contains("kind = \"headless\""), "{err}");
}

#[test]
fn the_network_method_without_weights_names_the_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    let err = serve_fails(
        dir.path(),
        |t| {
            t.replace("method = \"gather\"", "method = \"network\"")
                + &format!(
                    "\n[render]\nweights = {:?}\n",
                    weights.display().to_string()
                )
        },
        &[],
    );
    let file = weights.join("c1.safetensors");
    assert!(
        err.contains(&format!("{} does not exist", file.display())),
        "{err}"
    );
    assert!(err.contains("render.weights"), "{err}");
}
