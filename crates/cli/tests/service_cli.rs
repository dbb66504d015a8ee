//! `dioptra serve` under a service manager: the systemd notify protocol as systemd speaks it
//! (a datagram socket named by `NOTIFY_SOCKET`, the watchdog's period in `WATCHDOG_USEC`), and
//! the unit file in packaging/systemd. Real time, short polls; nothing asserts how long
//! anything took (the bounds only end a broken run).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::unix::net::UnixDatagram;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const RIG: &str = include_str!("../examples/rig-sim.toml");
const UNIT: &str = include_str!("../../../packaging/systemd/dioptra.service");

struct Daemon(Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn write_config(dir: &Path) -> std::path::PathBuf {
    let text = RIG.replace("127.0.0.1:7420", "127.0.0.1:0").replace(
        "dir = \"recordings\"",
        &format!("dir = {:?}", dir.join("rec").display().to_string()),
    );
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// (status, body) of one HTTP/1.1 request.
fn http(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: 0\r\nConnection: close\r\n\r\n"
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

/// The next notify message, or None once `until` has passed.
fn next_message(sock: &UnixDatagram, until: Instant) -> Option<String> {
    let mut buf = [0u8; 4096];
    while Instant::now() < until {
        match sock.recv(&mut buf) {
            Ok(n) => return Some(String::from_utf8_lossy(&buf[..n]).into_owned()),
            Err(e)
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => panic!("reading the notify socket: {e}"),
        }
    }
    None
}

/// Messages until one has a line equal to `want`; all of them, in order.
fn until_line(sock: &UnixDatagram, want: &str, seen: &mut Vec<String>) {
    let until = Instant::now() + Duration::from_secs(60);
    while let Some(m) = next_message(sock, until) {
        let found = m.lines().any(|l| l == want);
        seen.push(m);
        if found {
            return;
        }
    }
    panic!("no {want} in 60 s; the daemon sent {seen:?}");
}

#[test]
fn serve_tells_systemd_it_is_ready_pings_the_watchdog_and_says_it_stops() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let socket = dir.path().join("notify.sock");
    let sock = UnixDatagram::bind(&socket).unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&config)
        .env("NOTIFY_SOCKET", &socket)
        // WatchdogSec=1s: a ping every half second while the loop turns.
        .env("WATCHDOG_USEC", "1000000")
        .env_remove("WATCHDOG_PID")
        .env_remove("JOURNAL_STREAM")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = BufReader::new(child.stderr.take().unwrap());
    let daemon = Daemon(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            if let Some(a) = line.strip_prefix("dioptra serve: API on http://") {
                let _ = tx.send(a.parse::<SocketAddr>().unwrap());
            }
        }
    });

    let mut seen = Vec::new();
    until_line(&sock, "READY=1", &mut seen);
    assert!(
        seen.iter().all(|m| !m.contains("WATCHDOG=1")),
        "a watchdog ping before READY=1: {seen:?}"
    );
    // READY=1 comes once the API answers: the address is printed before it, and it serves.
    // A limit for a stuck daemon, not a speed target: a loaded machine starts slowly.
    let addr = rx.recv_timeout(Duration::from_secs(60)).unwrap();
    let (code, status) = http(addr, "GET", "/status");
    assert_eq!(code, 200, "{status}");
    let ready = seen.last().unwrap();
    assert!(
        ready.contains(&format!("STATUS=API on http://{addr}")),
        "{ready}"
    );

    // Two pings: the loop turns (the sim rig runs), so the watchdog is fed more than once.
    until_line(&sock, "WATCHDOG=1", &mut seen);
    until_line(&sock, "WATCHDOG=1", &mut seen);

    let (code, body) = http(addr, "POST", "/shutdown");
    assert!(code < 300, "{code} {body}");
    until_line(&sock, "STOPPING=1", &mut seen);
    let mut child = daemon;
    let exit = child.0.wait().unwrap();
    assert!(exit.success(), "{exit:?}");
    // No ping once it has said it stops.
    let after = seen.iter().position(|m| m.contains("STOPPING=1")).unwrap();
    while let Some(m) = next_message(&sock, Instant::now() + Duration::from_millis(300)) {
        seen.push(m);
    }
    assert!(
        seen[after + 1..].iter().all(|m| !m.contains("WATCHDOG=1")),
        "pings after STOPPING=1: {seen:?}"
    );
}

#[test]
fn outside_systemd_serve_sends_nothing_and_logs_with_timestamps() {
    // Without NOTIFY_SOCKET nothing is sent (nothing to assert on a socket nobody named);
    // a JOURNAL_STREAM that is not stderr's keeps the timestamps (a shell under the service).
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let mut child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&config)
        .env_remove("NOTIFY_SOCKET")
        .env("JOURNAL_STREAM", "1:1")
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let _daemon = Daemon(child);
    let mut line = String::new();
    let mut lines = Vec::new();
    let addr = loop {
        line.clear();
        assert!(stderr.read_line(&mut line).unwrap() > 0, "{lines:?}");
        if let Some(a) = line.trim().strip_prefix("dioptra serve: API on http://") {
            break a.parse::<SocketAddr>().unwrap();
        }
        lines.push(line.clone());
    };
    let (code, _) = http(addr, "POST", "/shutdown");
    assert!(code < 300);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    lines.extend(rest.lines().map(str::to_string));
    let logged: Vec<&String> = lines
        .iter()
        .filter(|l| l.contains(" INFO ") || l.contains(" WARN "))
        .collect();
    assert!(!logged.is_empty(), "no log lines: {lines:?}");
    for l in logged {
        // tracing's default: an RFC 3339 timestamp first, no syslog priority.
        assert!(l.starts_with("20") && !l.starts_with('<'), "{l}");
    }
}

#[test]
fn under_the_journal_log_lines_carry_a_priority_and_no_timestamp() {
    // stderr is a file whose device and inode JOURNAL_STREAM names, as systemd's stream is.
    use std::os::unix::fs::MetadataExt;
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let log = dir.path().join("stderr.log");
    let file = std::fs::File::create(&log).unwrap();
    let meta = file.metadata().unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_dioptra"))
        .args(["serve", "--config"])
        .arg(&config)
        .env_remove("NOTIFY_SOCKET")
        .env("JOURNAL_STREAM", format!("{}:{}", meta.dev(), meta.ino()))
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(file)
        .spawn()
        .unwrap();
    let mut daemon = Daemon(child);
    let until = Instant::now() + Duration::from_secs(60);
    let addr = loop {
        let text = std::fs::read_to_string(&log).unwrap();
        if let Some(a) = text
            .lines()
            .find_map(|l| l.strip_prefix("dioptra serve: API on http://"))
        {
            break a.parse::<SocketAddr>().unwrap();
        }
        assert!(Instant::now() < until, "serve did not listen: {text}");
        std::thread::sleep(Duration::from_millis(20));
    };
    let (code, _) = http(addr, "POST", "/shutdown");
    assert!(code < 300);
    assert!(daemon.0.wait().unwrap().success());
    let text = std::fs::read_to_string(&log).unwrap();
    let lines: Vec<&str> = text.lines().filter(|l| l.starts_with('<')).collect();
    assert!(
        !lines.is_empty(),
        "no journal-formatted log line in {text:?}"
    );
    for l in lines {
        assert!(
            matches!(&l[..3], "<3>" | "<4>" | "<6>" | "<7>"),
            "a priority prefix: {l}"
        );
        let rest = l[3..].trim_start();
        assert!(
            !rest.starts_with("20") && !rest.contains('\x1b'),
            "a timestamp or colour codes under the journal: {l}"
        );
    }
}

#[test]
fn the_unit_file_is_a_notify_service_with_a_watchdog_restart_and_the_device_group() {
    let key = |k: &str| -> Vec<&str> {
        UNIT.lines()
            .filter_map(|l| l.strip_prefix(k)?.strip_prefix('='))
            .collect()
    };
    assert_eq!(key("Type"), ["notify"]);
    assert_eq!(key("Restart"), ["on-failure"]);
    assert_eq!(key("Group"), ["dioptra"]);
    assert!(key("WatchdogSec").len() == 1, "WatchdogSec");
    let exec = key("ExecStart");
    assert_eq!(exec.len(), 1);
    assert!(exec[0].contains(" serve --config "), "{exec:?}");
    // The group the unit runs in is the one `dioptra udev --group` gives the devices to: the
    // install lines in its header say so.
    assert!(UNIT.contains("dioptra udev --group dioptra"));

    // systemd's own check of the unit, with ExecStart pointing at the built binary.
    let Ok(verify) = Command::new("systemd-analyze").arg("--version").output() else {
        eprintln!("systemd-analyze is not installed: the unit's syntax is not checked here");
        return;
    };
    assert!(verify.status.success());
    let dir = tempfile::tempdir().unwrap();
    let unit = dir.path().join("dioptra.service");
    std::fs::write(
        &unit,
        UNIT.replace("/usr/local/bin/dioptra", env!("CARGO_BIN_EXE_dioptra")),
    )
    .unwrap();
    let out = Command::new("systemd-analyze")
        .args(["verify", "--man=no"])
        .arg(&unit)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    // Users and groups that do not exist here are the install's to create, not the unit's fault.
    let problems: Vec<&str> = err
        .lines()
        .filter(|l| !l.trim().is_empty())
        .filter(|l| !l.contains("user") && !l.contains("group"))
        .collect();
    assert!(
        out.status.success() && problems.is_empty(),
        "systemd-analyze verify: {err}"
    );
}
