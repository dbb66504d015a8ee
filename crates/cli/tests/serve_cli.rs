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
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
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

/// Runs `dioptra ARGS` to its end: (whether it succeeded, stdout, stderr).
fn dioptra<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn serve_answers_the_api_and_stops_through_it_then_replay_matches() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path(), true);
    let (daemon, mut stderr, addr) = start(&config);

    let (code, body) = http(addr, "GET", "/status", "");
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"mode\":\"varifocal\""), "{body}");
    // Host time t happened at wall_zero_ns + t: the anchor puts "now" at about now.
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    let zero = v["clock"]["wall_zero_ns"]
        .as_u64()
        .expect("no wall-clock anchor");
    let host_now = v["host_ns"].as_u64().unwrap();
    let wall_now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64;
    let off = (zero + host_now).abs_diff(wall_now);
    assert!(
        off < 5_000_000_000,
        "the anchor is {off} ns off the wall clock"
    );
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 1.25}");
    assert_eq!(code, 200, "{body}");
    // The lens follows: the simulated lens's own state reaches 1.25 D.
    wait_for(addr, "the simulated lens to settle at 1.25 D", |v| {
        let body = v.to_string();
        body.contains("\"target_d\":1.25") && body.contains("\"settled\":true")
    });
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
    let (ok, text, err) = dioptra(&["replay", &recording]);
    assert!(ok, "{text}{err}");
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
    let (ok, _, err) = dioptra(&["serve".as_ref(), "--config".as_ref(), path.as_os_str()]);
    assert!(!ok);
    assert!(
        err.contains("optics.lens_range: min must be below max"),
        "{err}"
    );
    let missing = dir.path().join("missing.toml");
    let (ok, _, err) = dioptra(&["serve".as_ref(), "--config".as_ref(), missing.as_os_str()]);
    assert!(!ok);
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

/// Starts `dioptra serve` on `config`: the daemon, its stderr after the API line, and the
/// API's address from that line.
fn start(config: &Path) -> (Daemon, BufReader<std::process::ChildStderr>, SocketAddr) {
    start_with_env(config, &[])
}

/// [`start`] with `env` set for the daemon.
fn start_with_env(
    config: &Path,
    env: &[(&str, &str)],
) -> (Daemon, BufReader<std::process::ChildStderr>, SocketAddr) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_dioptra"));
    cmd.args(["serve", "--config"])
        .arg(config)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    // The GPU probe (render.backend = "auto") may print the Vulkan loader's own lines first.
    let mut seen = String::new();
    let addr = loop {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            panic!("serve ended before it listened: {seen}");
        }
        if let Some(a) = line.trim().strip_prefix("dioptra serve: API on http://") {
            break a.parse::<SocketAddr>().unwrap();
        }
        seen += &line;
    };
    (Daemon(child), stderr, addr)
}

/// Polls `/status` until `done` holds for it (a wait for the daemon's state, not a timing
/// check: the bound, 60 s, is only there so that a broken daemon fails the test).
fn wait_for(
    addr: SocketAddr,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let until = std::time::Instant::now() + Duration::from_secs(60);
    while std::time::Instant::now() < until {
        let (_, body) = http(addr, "GET", "/status", "");
        let v: serde_json::Value = serde_json::from_str(&body).unwrap();
        if done(&v) {
            return v;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("waited 60 s for {what}");
}

/// Polls `/status` until the lens is `ok`.
fn wait_for_lens(addr: SocketAddr) {
    wait_for(addr, "the lens to come up", |v| {
        v["devices"]["lens"]["state"] == "ok"
    });
}

#[test]
fn sigterm_sigint_and_sighup_park_the_lens_and_finish_the_recording() {
    for (name, signal) in [
        ("SIGTERM", libc::SIGTERM),
        ("SIGINT", libc::SIGINT),
        ("SIGHUP", libc::SIGHUP),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let (mut daemon, mut stderr, addr) = start(&write_config(dir.path(), true));
        wait_for_lens(addr);
        let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 2.5}");
        assert_eq!(code, 200, "{body}");
        // SAFETY: kill(2) on our own child's pid.
        let pid = daemon.0.id() as libc::pid_t;
        assert_eq!(unsafe { libc::kill(pid, signal) }, 0);
        let mut rest = String::new();
        stderr.read_to_string(&mut rest).unwrap();
        let status = daemon.0.wait().unwrap();
        assert!(status.success(), "{name}: {status}: {rest}");
        assert!(
            rest.contains(&format!("stopping ({name})")),
            "{name}: {rest}"
        );
        assert!(rest.contains("lens parked at 0.5 D"), "{name}: {rest}");
        let recording = rest
            .split("recording ")
            .nth(1)
            .and_then(|r| r.split(" finished").next())
            .unwrap_or_else(|| panic!("{name}: no recording in {rest:?}"));
        // A finished file: it has its summary.
        let bytes = std::fs::read(recording).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap();
        assert!(summary.is_some_and(|s| s.stats.is_some_and(|st| st.message_count > 0)));
    }
}

#[test]
fn a_recording_killed_with_sigkill_is_recovered() {
    let dir = tempfile::tempdir().unwrap();
    let (mut daemon, _stderr, addr) = start(&write_config(dir.path(), true));
    wait_for_lens(addr);
    // Wait until some closed chunks are on disk (the daemon closes one every second of data).
    let rec_dir = dir.path().join("rec");
    let file = (0..6000)
        .find_map(|_| {
            std::thread::sleep(Duration::from_millis(10));
            let f = std::fs::read_dir(&rec_dir).ok()?.flatten().next()?.path();
            (std::fs::metadata(&f).ok()?.len() > 200_000).then_some(f)
        })
        .expect("the recording never grew past 200 kB");
    daemon.0.kill().unwrap();
    daemon.0.wait().unwrap();
    let out = dir.path().join("fixed.mcap");
    let (ok, text, err) = dioptra(&[
        "recording".as_ref(),
        "recover".as_ref(),
        file.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(ok, "{text}{err}");
    assert!(text.contains("cut off"), "{text}");
    let bytes = std::fs::read(&out).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().expect("no summary");
    let n = summary.stats.unwrap().message_count;
    assert!(n > 100, "{n} messages recovered");
    // Replay compares the recovered file up to the cut, and reads the cut file itself.
    let (ok, text, err) = dioptra(&["replay".as_ref(), out.as_os_str()]);
    assert!(
        ok && text.contains("replay identical to the recording"),
        "{text}{err}"
    );
    let (_, text, err) = dioptra(&["replay".as_ref(), file.as_os_str()]);
    assert!(text.contains("cut off"), "{text}{err}");

    // `| head`: a reader that goes away ends the command quietly, with no panic.
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["replay", "--json"])
        .arg(&out)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut head = [0u8; 16];
    child
        .stdout
        .as_mut()
        .unwrap()
        .read_exact(&mut head)
        .unwrap();
    drop(child.stdout.take());
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let status = child.wait().unwrap();
    assert!(!err.contains("panicked"), "{err}");
    use std::os::unix::process::ExitStatusExt;
    assert!(
        status.success() || status.signal() == Some(libc::SIGPIPE),
        "{status}: {err}"
    );
}

#[test]
fn the_daemon_shows_a_labs_files_as_dioptra_render_renders_them() {
    daemon_shows_files_as_dioptra_render("cpu");
}

#[test]
fn on_the_gpu_the_daemon_shows_a_labs_files_as_dioptra_render_renders_them() {
    let gpu = !dioptra_render::gpu::list_adapters().is_empty();
    if !gpu && std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() == Ok("1") {
        panic!("DIOPTRA_REQUIRE_GPU=1 and there is no GPU adapter");
    }
    if gpu {
        daemon_shows_files_as_dioptra_render("gpu");
    } else {
        eprintln!("skipped: no GPU adapter");
    }
}

/// A procedural test scene's files (96 x 96, `color.exr` and `depth.exr`) in `dir`/scene,
/// made by `dioptra sim scene` unless they are there already.
fn sim_scene(dir: &Path) -> std::path::PathBuf {
    let scene = dir.join("scene");
    if !scene.join("color.exr").exists() {
        let (ok, _, err) = dioptra(&[
            "sim".as_ref(),
            "scene".as_ref(),
            "--seed".as_ref(),
            "1000000".as_ref(),
            "--size".as_ref(),
            "96".as_ref(),
            "--out".as_ref(),
            scene.as_os_str(),
        ]);
        assert!(ok, "{err}");
    }
    scene
}

/// The daemon on `backend` shows a files source at a manual focus as `dioptra render
/// --backend <backend>` renders the same files at that focus.
fn daemon_shows_files_as_dioptra_render(backend: &str) {
    let dir = tempfile::tempdir().unwrap();
    let scene = sim_scene(dir.path());
    let (color, depth) = (scene.join("color.exr"), scene.join("depth.exr"));
    let frames = dir.path().join("frames");
    let text = std::fs::read_to_string(write_config(dir.path(), false))
        .unwrap()
        .replace("png_every = 0", "png_every = 1")
        .replace(
            "[display]",
            &format!("[display]\npng_dir = {:?}", frames.display().to_string()),
        )
        + &format!(
            "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\n\n[render]\nbackend = {backend:?}\n",
            color.display().to_string(),
            depth.display().to_string()
        );
    let config = dir.path().join("files.toml");
    std::fs::write(&config, text).unwrap();
    let (mut daemon, mut stderr, addr) = start(&config);
    wait_for_lens(addr);
    let (code, body) = http(addr, "GET", "/status", "");
    assert!(
        body.contains("\"content\":{") && body.contains("\"source\":\"files\""),
        "{code} {body}"
    );
    assert!(
        body.contains(&format!("\"backend\":\"{backend}\"")),
        "{code} {body}"
    );
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 1.5}");
    assert_eq!(code, 200, "{body}");
    // Frames at the manual focus: the lens has settled there and more frames came.
    let at = wait_for(addr, "the lens command to reach 1.5 D", |v| {
        v["focus"]["commanded_d"].as_f64() == Some(1.5)
    });
    let shown = at["counts"]["frames_shown"].as_u64().unwrap();
    wait_for(addr, "10 more frames", |v| {
        v["counts"]["frames_shown"].as_u64() > Some(shown + 10)
    });
    let (code, _) = http(addr, "POST", "/shutdown", "");
    assert_eq!(code, 202);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    assert!(daemon.0.wait().unwrap().success(), "{rest}");
    let mut pngs: Vec<_> = std::fs::read_dir(&frames)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    pngs.sort();
    let newest = pngs.last().expect("no frames written");
    let cli = dir.path().join("cli.png");
    let (ok, _, err) = dioptra(&[
        "render".as_ref(),
        "--method".as_ref(),
        "gather".as_ref(),
        "--focus".as_ref(),
        "1.5".as_ref(),
        "--backend".as_ref(),
        backend.as_ref(),
        "--color".as_ref(),
        color.as_os_str(),
        "--depth".as_ref(),
        depth.as_os_str(),
        "--out".as_ref(),
        cli.as_os_str(),
    ]);
    assert!(ok, "{err}");
    let a = dioptra_render::io::read_color(newest).unwrap();
    let b = dioptra_render::io::read_color(&cli).unwrap();
    let psnr = dioptra_render::metrics::psnr(&a, &b, None).unwrap();
    eprintln!(
        "{backend}: {}: {psnr} dB against dioptra render",
        newest.display()
    );
    assert!(
        psnr >= 50.0,
        "{}: {psnr} dB against dioptra render",
        newest.display()
    );
}

#[test]
fn a_second_signal_during_shutdown_exits_once_the_lens_is_parked() {
    let dir = tempfile::tempdir().unwrap();
    // A slow lens, so that parking it takes about half a second.
    let config = write_config(dir.path(), true);
    let text = std::fs::read_to_string(&config)
        .unwrap()
        .replace("sim_settle_ms = 15.0", "sim_settle_ms = 500.0");
    std::fs::write(&config, text).unwrap();
    let (mut daemon, mut stderr, addr) = start(&config);
    wait_for_lens(addr);
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 3.5}");
    assert_eq!(code, 200, "{body}");
    // Wait until the lens is far from its park power, so that parking takes a while.
    wait_for(addr, "the lens to reach 3 D", |v| {
        v["focus"]["lens_d"].as_f64().is_some_and(|d| d > 3.0)
    });
    let pid = daemon.0.id() as libc::pid_t;
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    let mut line = String::new();
    while !line.contains("stopping (SIGTERM)") {
        line.clear();
        assert!(stderr.read_line(&mut line).unwrap() > 0, "no stopping line");
    }
    assert_eq!(unsafe { libc::kill(pid, libc::SIGINT) }, 0);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    let status = daemon.0.wait().unwrap();
    assert_eq!(status.code(), Some(130), "{rest}");
    assert!(rest.contains("SIGINT during shutdown"), "{rest}");
    assert!(rest.contains("lens parked; exiting"), "{rest}");
}

/// A required lens on a path that does not exist ends the start with one error naming the
/// key, and nothing before it says the lens was lost and is being retried.
#[test]
fn a_missing_port_ends_the_start_without_a_lost_warning_first() {
    let dir = tempfile::tempdir().unwrap();
    for _ in 0..5 {
        let err = serve_fails(
            dir.path(),
            |t| t.replacen("port = \"sim\"", "port = \"/dev/dioptra-no-such-lens\"", 1),
            &[("RUST_LOG", None)],
        );
        assert!(
            err.contains(
                "devices.lens.port = \"/dev/dioptra-no-such-lens\": the lens device is not present"
            ),
            "{err}"
        );
        assert!(!err.contains("retrying") && !err.contains("lost"), "{err}");
    }
}

/// An invalid `RUST_LOG` is an error naming it, not a silent fall back to the default.
#[test]
fn an_invalid_rust_log_is_reported_as_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let err = serve_fails(
        dir.path(),
        |t| t,
        &[("RUST_LOG", Some("dioptra_rig=verbose"))],
    );
    assert!(
        err.starts_with("error: RUST_LOG=\"dioptra_rig=verbose\": "),
        "{err}"
    );
}

/// A virtual X server (Xvfb, from Debian's `xvfb`, which `.ci/run` installs) with a screen of
/// each size in `screens`, its framebuffers written as XWD files into its own directory.
struct Xvfb {
    server: XServer,
    fbdir: tempfile::TempDir,
}

/// A running X server on `display`, stopped when dropped.
struct XServer {
    child: Child,
    display: String,
}

impl XServer {
    /// `program` (an X server) on a free display with the arguments `configure` adds, once it
    /// listens.
    fn start(program: &str, configure: impl FnOnce(&mut Command)) -> XServer {
        let n = free_display();
        let mut cmd = Command::new(program);
        cmd.arg(format!(":{n}"));
        configure(&mut cmd);
        let child = cmd
            .args(["-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("{program} is installed but does not start: {e}"));
        let mut server = XServer {
            child,
            display: format!(":{n}"),
        };
        wait_for_x(&mut server.child, n, program);
        server
    }
}

impl Drop for XServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Xvfb {
    /// Started on a free display number; `None` (the test skips, saying why) only where Xvfb
    /// is not installed.
    fn start(screens: &[(u32, u32)]) -> Option<Xvfb> {
        if Command::new("Xvfb").arg("-help").output().is_err() {
            eprintln!("skipped: Xvfb is not installed (Debian's xvfb; .ci/run installs it)");
            return None;
        }
        let fbdir = tempfile::tempdir().unwrap();
        let server = XServer::start("Xvfb", |cmd| {
            for (i, (w, h)) in screens.iter().enumerate() {
                cmd.args(["-screen", &i.to_string(), &format!("{w}x{h}x24")]);
            }
            cmd.arg("-fbdir").arg(fbdir.path());
        });
        Some(Xvfb { server, fbdir })
    }

    /// Screen `i`'s framebuffer as (width, height, RGB bytes), read from its XWD file.
    fn screen(&self, i: usize) -> (u32, u32, Vec<u8>) {
        let bytes = std::fs::read(self.fbdir.path().join(format!("Xvfb_screen{i}"))).unwrap();
        parse_xwd(&bytes)
    }
}

/// An XWD file (X Window Dump: a header of 25 big-endian 32-bit fields, the window's name,
/// the colour map of `ncolors` 12-byte entries, then `height` rows of `bytes_per_line`) of a
/// 24- or 32-bit TrueColor image, as (width, height, RGB bytes).
fn parse_xwd(b: &[u8]) -> (u32, u32, Vec<u8>) {
    let field = |i: usize| u32::from_be_bytes(b[4 * i..4 * i + 4].try_into().unwrap());
    let (header_size, version) = (field(0) as usize, field(1));
    assert_eq!(version, 7, "XWD version");
    let (width, height) = (field(4), field(5));
    let byte_order = field(7); // 0: least significant byte first
    let bits_per_pixel = field(11);
    let bytes_per_line = field(12) as usize;
    let masks = [field(14), field(15), field(16)];
    let ncolors = field(19) as usize;
    assert_eq!(
        bits_per_pixel, 32,
        "a 24-bit screen is stored 32 bits a pixel"
    );
    let data = &b[header_size + 12 * ncolors..];
    let mut rgb = Vec::with_capacity((3 * width * height) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let p: [u8; 4] = data[y * bytes_per_line + 4 * x..][..4].try_into().unwrap();
            let v = if byte_order == 0 {
                u32::from_le_bytes(p)
            } else {
                u32::from_be_bytes(p)
            };
            for m in masks {
                rgb.push(((v & m) >> m.trailing_zeros()) as u8);
            }
        }
    }
    (width, height, rgb)
}

/// A free X display number (no server holds its lock file), from one per process; each call
/// starts past the numbers earlier calls gave, so that two tests starting servers at once do
/// not pick the same one before either server holds it.
fn free_display() -> u32 {
    static GIVEN: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let call = GIVEN.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let mut n = 200 + std::process::id() % 500 + 1000 * (call % 8);
    while Path::new(&format!("/tmp/.X{n}-lock")).exists() {
        n += 1;
    }
    n
}

/// Waits until the X server `child` listens on display `n` (bounded only so that a broken
/// server fails the test).
fn wait_for_x(child: &mut Child, n: u32, what: &str) {
    let socket = format!("/tmp/.X11-unix/X{n}");
    let until = std::time::Instant::now() + Duration::from_secs(30);
    while !Path::new(&socket).exists() {
        if let Ok(Some(s)) = child.try_wait() {
            panic!("{what} :{n} exited: {s}");
        }
        assert!(std::time::Instant::now() < until, "{what} did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// An X server whose one screen has two RandR outputs side by side, as a rig's two monitors:
/// Xorg with Debian's dummy video driver (`xserver-xorg-video-dummy`, which `.ci/run`
/// installs with `xserver-xorg-core`, `x11-xserver-utils` for xrandr and `x11-apps` for
/// xwd), its outputs DUMMY0 and DUMMY1 given a mode each with xrandr. This is what Xvfb
/// cannot give winit (see below).
struct XorgDummy {
    server: XServer,
    _dir: tempfile::TempDir,
}

impl XorgDummy {
    const DRIVER: &'static str = "/usr/lib/xorg/modules/drivers/dummy_drv.so";

    /// Two outputs of `size` each, DUMMY0 left of DUMMY1; `None` (the test skips, saying
    /// why) only where Xorg's dummy driver, xrandr or xwd is not installed.
    fn start(size: (u32, u32)) -> Option<XorgDummy> {
        let have = |tool: &str| Command::new(tool).arg("-version").output().is_ok();
        if !Path::new(Self::DRIVER).exists() || !have("xrandr") || !have("xwd") {
            eprintln!(
                "skipped: Xorg's dummy driver, xrandr or xwd is not installed (Debian's \
                 xserver-xorg-video-dummy, x11-xserver-utils, x11-apps; .ci/run installs them)"
            );
            return None;
        }
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = size;
        let conf = dir.path().join("xorg.conf");
        std::fs::write(
            &conf,
            format!(
                "Section \"Device\"\n Identifier \"dummy\"\n Driver \"dummy\"\n VideoRam 64000\nEndSection\n\
                 Section \"Monitor\"\n Identifier \"monitor\"\n HorizSync 1.0-1000.0\n VertRefresh 5.0-200.0\nEndSection\n\
                 Section \"Screen\"\n Identifier \"screen\"\n Device \"dummy\"\n Monitor \"monitor\"\n DefaultDepth 24\n\
                 SubSection \"Display\"\n  Depth 24\n  Virtual {} {}\n EndSubSection\nEndSection\n",
                (2 * w).max(640),
                h.max(480)
            ),
        )
        .unwrap();
        // Held from here, so that a failing step below stops the server.
        let server = XServer::start("Xorg", |cmd| {
            cmd.arg("-config")
                .arg(&conf)
                .arg("-logfile")
                .arg(dir.path().join("Xorg.log"))
                .arg("-noreset");
        });
        let display = server.display.clone();
        // A 60 Hz mode of `size` (blanking of a quarter line and 8 lines) on each output.
        let (ht, vt) = (w + w / 4 + 8, h + 8);
        let clock_mhz = f64::from(ht * vt) * 60.0 / 1e6;
        let xrandr = |args: &[String]| {
            let out = Command::new("xrandr")
                .arg("-display")
                .arg(&display)
                .args(args)
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "xrandr {args:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        };
        let mode = format!("dioptra{w}x{h}");
        let timing = [w, w + 2, w + 4, ht, h, h + 1, h + 2, vt].map(|v| v.to_string());
        let mut newmode = vec![
            "--newmode".to_string(),
            mode.clone(),
            format!("{clock_mhz:.4}"),
        ];
        newmode.extend(timing);
        xrandr(&newmode);
        let mut place = Vec::new();
        for (i, x) in [(0, 0), (1, w)] {
            xrandr(&["--addmode".into(), format!("DUMMY{i}"), mode.clone()]);
            place.extend([
                "--output".to_string(),
                format!("DUMMY{i}"),
                "--mode".into(),
                mode.clone(),
                "--pos".into(),
                format!("{x}x0"),
            ]);
        }
        xrandr(&place);
        Some(XorgDummy { server, _dir: dir })
    }

    /// The screen's root window (both outputs) as (width, height, RGB bytes), by xwd.
    fn screen(&self) -> (u32, u32, Vec<u8>) {
        let out = Command::new("xwd")
            .args(["-root", "-silent", "-display", &self.server.display])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "xwd: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        parse_xwd(&out.stdout)
    }
}

/// The worst difference (steps of 255) between `got`'s pixels from column `x0` of a `gw` wide
/// image and `want` (`ww` wide, all its rows), and how many of those pixels are lit.
fn worst_step(got: &[u8], gw: usize, x0: usize, want: &[u8], ww: usize) -> (u8, usize) {
    let mut worst = 0u8;
    let mut lit = 0;
    for (y, row) in want.chunks(3 * ww).enumerate() {
        let from = 3 * (y * gw + x0);
        let seen = &got[from..from + 3 * ww];
        worst = seen
            .iter()
            .zip(row)
            .map(|(a, b)| a.abs_diff(*b))
            .fold(worst, u8::max);
        lit += seen.chunks(3).filter(|p| p.iter().any(|&c| c > 16)).count();
    }
    (worst, lit)
}

/// Two monitors (Xorg's dummy driver: two RandR outputs, which winit lists as two monitors):
/// `layout = "two-outputs"` puts a window on each, and each monitor's pixels, read back from
/// the X server, are its eye's image as the headless sink writes that eye's output.
#[test]
fn on_two_monitors_each_window_shows_its_eye_as_the_headless_sink_writes_it() {
    let Some(x) = XorgDummy::start((96, 96)) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let two_outputs = |path: std::path::PathBuf| {
        let text = std::fs::read_to_string(&path)
            .unwrap()
            .replace("layout = \"side-by-side\"", "layout = \"two-outputs\"");
        std::fs::write(&path, text).unwrap();
        path
    };
    let frames = dir.path().join("frames");
    let headless = two_outputs(hmd_rig(
        dir.path(),
        "headless",
        &format!("png_every = 1\npng_dir = {:?}", frames),
    ));
    at_settled_focus(&headless, &[], |_| {});
    let newest = |eye: &str| {
        let mut pngs: Vec<_> = std::fs::read_dir(&frames)
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.to_string_lossy().ends_with(&format!("_{eye}.png")))
            .collect();
        pngs.sort();
        let (w, h, values) =
            dioptra_render::io::read_code_values(pngs.last().expect("no frames written")).unwrap();
        assert_eq!((w, h), (96, 96));
        values
    };
    let want = [newest("left"), newest("right")];

    let window = two_outputs(hmd_rig(
        dir.path(),
        "window",
        "monitor_left = \"DUMMY0\"\nmonitor_right = \"DUMMY1\"",
    ));
    at_settled_focus(&window, &[("DISPLAY", x.server.display.as_str())], |v| {
        eprintln!("display: {}", v["display"]);
        let (w, h, got) = x.screen();
        assert_eq!((w, h), (192, 96), "the two outputs side by side");
        for (eye, (want, x0)) in ["left", "right"].iter().zip(want.iter().zip([0, 96])) {
            let (worst, lit) = worst_step(&got, 192, x0, want, 96);
            eprintln!("{eye} monitor against the headless {eye} output: worst {worst} step(s), {lit} lit pixels");
            assert!(
                lit > 96 * 96 / 2,
                "{eye}: {lit} lit pixels: the eye is not drawn"
            );
            assert!(worst <= 1, "{eye}: a pixel differs by {worst} steps");
        }
    });
}

/// The simulated HMD example at 96 x 96 per eye (its eyepiece scaled to it), showing a
/// procedural scene's files at a manual focus: `kind` headless (with its PNGs in `frames`) or
/// a window (`extra` display keys).
fn hmd_rig(dir: &Path, kind: &str, extra: &str) -> std::path::PathBuf {
    let scene = sim_scene(dir);
    // The eyepiece at a fifth of the example's 480 pixels: focal lengths and centre scaled.
    let text = include_str!("../examples/rig-sim-hmd.toml")
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("dir = \"recordings\"", &format!("dir = {:?}", dir.join("rec")))
        .replace("fx = 225.0\nfy = 225.0\ncx = 239.5\ncy = 134.5", "fx = 45.0\nfy = 45.0\ncx = 47.5\ncy = 47.5")
        .replace("fx = 227.25\nfy = 227.25", "fx = 45.45\nfy = 45.45")
        .replace("fx = 222.75\nfy = 222.75", "fx = 44.55\nfy = 44.55")
        .replace("width = 480\nheight = 270", "width = 96\nheight = 96")
        .replace("kind = \"headless\"", &format!("kind = {kind:?}\n{extra}"))
        + &format!(
            "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\n\n[render]\nbackend = \"cpu\"\n",
            scene.join("color.exr"),
            scene.join("depth.exr"),
        );
    assert!(text.contains("fx = 45.45") && text.contains("width = 96"));
    let path = dir.join(format!("hmd-{kind}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

/// Runs the daemon on `config` (with `env`; a lens per eye) to a manual focus of 0.5 D and 10
/// frames after its command, calls `look` while it still shows them, then stops it.
fn at_settled_focus(config: &Path, env: &[(&str, &str)], look: impl FnOnce(&serde_json::Value)) {
    let (mut daemon, mut stderr, addr) = start_with_env(config, env);
    // A lens per eye: `lens_left` and `lens_right`.
    wait_for(addr, "both lenses to come up", |v| {
        ["lens_left", "lens_right"]
            .iter()
            .all(|l| v["devices"][l]["state"] == "ok")
    });
    let (code, body) = http(addr, "POST", "/focus", "{\"diopters\": 0.5}");
    assert_eq!(code, 200, "{body}");
    // The lens power the optics map gives for 0.5 D, commanded.
    let at = wait_for(addr, "the lens command for 0.5 D", |v| {
        v["focus"]["commanded_focus_d"]
            .as_f64()
            .is_some_and(|d| (d - 0.5).abs() < 1e-3)
    });
    let shown = at["counts"]["frames_shown"].as_u64().unwrap();
    let v = wait_for(addr, "10 more frames", |v| {
        v["counts"]["frames_shown"].as_u64() > Some(shown + 10)
            && v["display"]["presented"].as_u64() != Some(0)
    });
    look(&v);
    let (code, _) = http(addr, "POST", "/shutdown", "");
    assert_eq!(code, 202);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    assert!(daemon.0.wait().unwrap().success(), "{rest}");
}

/// Under a virtual X server: a window per eye where winit sees a monitor per eye, and the
/// image corrections drawn in the window as the headless sink writes them.
///
/// Xvfb gives each X screen one RandR CRTC, and winit 0.30 lists the CRTCs of the display's
/// default screen only (not RandR 1.5's `--setmonitor` monitors, and Xinerama hides RandR):
/// under Xvfb winit sees one monitor, whatever the screens. So here the two-output window is
/// checked for what that gives (stopped at start naming `display.monitor_right` and listing
/// the one monitor), and the one window's corrected image on screen 0 against the headless
/// sink's PNG for the same frame; two monitors' pixels are checked under Xorg's dummy driver
/// (`on_two_monitors_each_window_shows_its_eye_as_the_headless_sink_writes_it`).
#[test]
fn under_xvfb_the_window_shows_each_eye_as_the_headless_sink_writes_it() {
    let Some(x) = Xvfb::start(&[(192, 96), (96, 96)]) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let env = [("DISPLAY", x.server.display.as_str())];

    // Two outputs: winit sees screen 0's one monitor, so the right eye's is missing.
    let two = hmd_rig(dir.path(), "window", "monitor_left = 0\nmonitor_right = 1");
    let text = std::fs::read_to_string(&two)
        .unwrap()
        .replace("layout = \"side-by-side\"", "layout = \"two-outputs\"");
    std::fs::write(&two, text).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&two)
        .env("DISPLAY", &x.server.display)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("display.monitor_right: there is no monitor 1; available: 0: \"screen\" 192x96 at (0, 0)"),
        "{err}"
    );

    // The headless sink's panel at the settled focus.
    let frames = dir.path().join("frames");
    let headless = hmd_rig(
        dir.path(),
        "headless",
        &format!("png_every = 1\npng_dir = {:?}", frames),
    );
    at_settled_focus(&headless, &[], |_| {});
    let mut pngs: Vec<_> = std::fs::read_dir(&frames)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    pngs.sort();
    let (pw, ph, want) =
        dioptra_render::io::read_code_values(pngs.last().expect("no frames written")).unwrap();
    assert_eq!((pw, ph), (192, 96));

    // The window on screen 0 (192 x 96: the side-by-side panel, drawn 1:1).
    let window = hmd_rig(dir.path(), "window", "");
    at_settled_focus(&window, &env, |v| {
        let d = &v["display"];
        assert_eq!(d["surface_is_monitor_size"], true, "{d}");
        assert!(
            d["sink"]
                .as_str()
                .unwrap()
                .contains("pre-warped and encoded"),
            "{d}"
        );
        let (w, h, got) = x.screen(0);
        assert_eq!((w, h), (192, 96));
        let mut worst = (0u8, 0usize);
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            if a.abs_diff(*b) > worst.0 {
                worst = (a.abs_diff(*b), i / 3);
            }
        }
        let lit = got.chunks(3).filter(|p| p.iter().any(|&c| c > 16)).count();
        eprintln!(
            "window against headless: worst {} step(s) at pixel ({}, {}); {lit} lit pixels",
            worst.0,
            worst.1 % 192,
            worst.1 / 192
        );
        assert!(
            lit > 192 * 96 / 2,
            "{lit} lit pixels: the eyes are not drawn"
        );
        assert!(worst.0 <= 1, "pixel {} differs by {}", worst.1, worst.0);
    });
}
