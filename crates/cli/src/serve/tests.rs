//! The daemon on simulated devices: API (in-process and over real sockets), shutdown,
//! device loss and recovery, recording and replay. On tokio's paused clock (simulated time,
//! which moves only when every task waits), so a loaded machine cannot change what a test sees;
//! no test asserts how long anything took.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use http_body_util::BodyExt;
use serde_json::{json, Value};
use tower::ServiceExt;

use dioptra_rig::config::{RigConfig, EXAMPLE_SIM_RIG as SIM_RIG};
use dioptra_rig::devices::State;
use dioptra_rig::render::Renderer as _;

use super::{api, Daemon, Listening};

/// The first frame of `cfg`'s content (the procedural scene of the example rig).
fn scene_frame(cfg: &RigConfig) -> dioptra_rig::content::ContentFrame {
    let content = dioptra_rig::content::open(
        &cfg.content,
        &cfg.display,
        &cfg.eye,
        &cfg.api,
        dioptra_rig::content::scene::Pacing::RealTime,
    )
    .unwrap();
    content.poll(dioptra_core::Timestamp::ZERO).unwrap()
}

/// The example sim rig on an ephemeral port, recording into `dir` (from the start if `record`).
fn sim_config(dir: &Path, record: bool) -> RigConfig {
    let text = SIM_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace(
            "dir = \"recordings\"",
            &format!("dir = {:?}", dir.join("rec").display().to_string()),
        )
        .replace("start = false", &format!("start = {record}"))
        // No network weights, whether or not the shipped ones exist.
        + &format!(
            "\n[render]\nweights = {:?}\n",
            dir.join("no-weights").display().to_string()
        );
    RigConfig::parse(&text).unwrap()
}

/// The daemon of `cfg` and the TCP address its API listens on.
async fn start_tcp(cfg: RigConfig) -> (Daemon, std::net::SocketAddr) {
    let d = Daemon::start_config(cfg).await.unwrap();
    let Listening::Tcp(addr) = d.listening().clone() else {
        panic!("not TCP")
    };
    (d, addr)
}

/// Stops the daemon and checks it stopped cleanly (lens parked, files finished).
async fn stop(d: Daemon) {
    d.cancel_token().cancel();
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
}

/// Polls `f` every 10 ms until it returns `Some`, for at most 20 s.
async fn eventually<T>(what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    for _ in 0..2000 {
        if let Some(v) = f() {
            return v;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("timed out waiting for {what}");
}

async fn call(app: &axum::Router, method: &str, path: &str, body: &str) -> (StatusCode, Value) {
    call_with(
        app,
        method,
        path,
        "application/json",
        body.as_bytes().to_vec(),
    )
    .await
}

/// A request with any body and Content-Type; the answer must be JSON.
async fn call_with(
    app: &axum::Router,
    method: &str,
    path: &str,
    content_type: &str,
    body: Vec<u8>,
) -> (StatusCode, Value) {
    let req = Request::builder()
        .method(method)
        .uri(path)
        .header("content-type", content_type)
        .body(Body::from(body))
        .unwrap();
    let resp = app.clone().oneshot(req).await.unwrap();
    let status = resp.status();
    let bytes = resp.into_body().collect().await.unwrap().to_bytes();
    let v = serde_json::from_slice(&bytes).unwrap_or_else(|e| {
        panic!(
            "{method} {path}: body is not JSON ({e}): {:?}",
            String::from_utf8_lossy(&bytes)
        )
    });
    (status, v)
}

fn status_of(d: &Daemon) -> Value {
    d.shared().status_json()
}

#[tokio::test(start_paused = true)]
async fn the_api_rejects_malformed_requests_with_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let app = api::router(d.shared().clone());

    // (method, path, body, status, key, words in the error)
    type Case<'a> = (
        &'a str,
        &'a str,
        &'a str,
        StatusCode,
        Option<&'a str>,
        &'a str,
    );
    let cases: &[Case] = &[
        // (method, path, body, status, key, words in the error)
        (
            "POST",
            "/focus",
            "{\"diopters\": ",
            StatusCode::BAD_REQUEST,
            None,
            "not valid JSON",
        ),
        (
            "POST",
            "/focus",
            "",
            StatusCode::BAD_REQUEST,
            None,
            "needs a JSON body",
        ),
        (
            "POST",
            "/focus",
            "{\"diopters\": \"near\"}",
            StatusCode::UNPROCESSABLE_ENTITY,
            Some("diopters"),
            "invalid type: string",
        ),
        (
            "POST",
            "/focus",
            "{\"diopters\": 9.5}",
            StatusCode::UNPROCESSABLE_ENTITY,
            Some("diopters"),
            "outside what the lens reaches, -1..4 D",
        ),
        (
            "POST",
            "/focus",
            "{\"power\": 1}",
            StatusCode::UNPROCESSABLE_ENTITY,
            None,
            "unknown field `power`",
        ),
        (
            "POST",
            "/focus",
            "[1.0]",
            StatusCode::UNPROCESSABLE_ENTITY,
            None,
            "expected a JSON object",
        ),
        (
            "POST",
            "/focus",
            "{\"diopters\": 1.0} x",
            StatusCode::BAD_REQUEST,
            None,
            "trailing characters",
        ),
        (
            "POST",
            "/mode",
            "{\"mode\": \"holographic\"}",
            StatusCode::UNPROCESSABLE_ENTITY,
            Some("mode"),
            "expected varifocal, multifocal or lightfield",
        ),
        (
            "POST",
            "/mode",
            "{\"mode\": 3}",
            StatusCode::UNPROCESSABLE_ENTITY,
            Some("mode"),
            "invalid type: integer",
        ),
        (
            "POST",
            "/method",
            "{\"method\": \"magic\"}",
            StatusCode::UNPROCESSABLE_ENTITY,
            Some("method"),
            "expected auto or one of gather",
        ),
        (
            "POST",
            "/method",
            "{\"method\": \"network\"}",
            StatusCode::CONFLICT,
            None,
            "c1.safetensors does not exist",
        ),
        (
            "POST",
            "/method",
            "{\"method\": \"linear\"}",
            StatusCode::CONFLICT,
            None,
            "does not make varifocal frames",
        ),
        (
            "POST",
            "/recording/stop",
            "",
            StatusCode::CONFLICT,
            None,
            "not recording",
        ),
        (
            "GET",
            "/nowhere",
            "",
            StatusCode::NOT_FOUND,
            None,
            "no such endpoint",
        ),
        (
            "GET",
            "/focus",
            "",
            StatusCode::METHOD_NOT_ALLOWED,
            None,
            "wrong method",
        ),
    ];
    for (method, path, body, want, key, words) in cases {
        let (status, v) = call(&app, method, path, body).await;
        assert_eq!(status, *want, "{method} {path} {body}: {v}");
        let err = v["error"]
            .as_str()
            .unwrap_or_else(|| panic!("no error in {v}"));
        assert!(
            err.contains(words),
            "{method} {path} {body}: {err:?} lacks {words:?}"
        );
        if let Some(k) = key {
            assert_eq!(v["key"], json!(k), "{method} {path} {body}: {v}");
        }
    }
    // Nothing malformed reached the scheduler.
    assert_eq!(status_of(&d)["focus"]["manual_d"], Value::Null);
    // Well-formed requests work.
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.5}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(status_of(&d)["focus"]["manual_d"], json!(2.5));
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": null}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(status_of(&d)["focus"]["manual_d"], Value::Null);
    let (s, v) = call(
        &app,
        "POST",
        "/method",
        "{\"method\": \"lightfield-defocus\"}",
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(status_of(&d)["method"], json!("lightfield-defocus"));

    d.cancel_token().cancel();
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
}

/// Minimal HTTP/1.1 over a real socket: (status, JSON body).
async fn http(addr: std::net::SocketAddr, method: &str, path: &str, body: &str) -> (u16, Value) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).await.unwrap();
    parse_http(&out)
}

fn parse_http(out: &[u8]) -> (u16, Value) {
    let text = String::from_utf8_lossy(out);
    let status: u16 = text
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {text:?}"));
    let (head, body) = text.split_once("\r\n\r\n").unwrap();
    let body = if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        // One or more chunks: "len\r\ndata\r\n" ... "0\r\n\r\n".
        let mut rest = body;
        let mut joined = String::new();
        while let Some((len, tail)) = rest.split_once("\r\n") {
            let n = usize::from_str_radix(len.trim(), 16).unwrap_or(0);
            if n == 0 {
                break;
            }
            joined.push_str(&tail[..n]);
            rest = &tail[n + 2..];
        }
        joined
    } else {
        body.to_string()
    };
    (status, serde_json::from_str(&body).unwrap_or(Value::Null))
}

#[tokio::test(start_paused = true)]
async fn serve_answers_the_api_on_a_real_socket_and_stops_through_it() {
    let dir = tempfile::tempdir().unwrap();
    let (d, addr) = start_tcp(sim_config(dir.path(), false)).await;
    assert!(addr.ip().is_loopback() && addr.port() != 0);
    let lens_sim = d.shared().devices().sims().unwrap().lenses[0]
        .clone()
        .unwrap()
        .lens
        .unwrap();

    // The stream carries gaze samples from the simulated tracker.
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/stream"))
        .await
        .unwrap();
    let mut kinds = std::collections::BTreeSet::new();
    while kinds.len() < 2 {
        let text = next_text(&mut ws).await;
        let v: Value = serde_json::from_str(&text).unwrap();
        // Every message carries the host time and the wall-clock time it was sent.
        assert!(v["host_ns"].is_u64() && v["wall_ns"].is_u64(), "{v}");
        kinds.insert(v["type"].as_str().unwrap().to_string());
        kinds.retain(|k| k == "gaze" || k == "frame");
    }

    let (code, v) = http(addr, "GET", "/status", "").await;
    assert_eq!(code, 200);
    assert_eq!(v["mode"], json!("varifocal"));
    for dev in ["lens", "gaze", "sync"] {
        assert!(v["devices"][dev].is_object(), "{dev} missing in {v}");
    }
    // Every device comes up.
    let mut v = v;
    for _ in 0..2000 {
        if ["lens", "gaze", "sync"]
            .iter()
            .all(|dev| v["devices"][dev]["state"] == json!("ok"))
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
        v = http(addr, "GET", "/status", "").await.1;
    }
    assert_eq!(v["devices"]["lens"]["state"], json!("ok"), "{v}");

    // Manual focus reaches the simulated lens.
    let (code, v) = http(addr, "POST", "/focus", "{\"diopters\": 1.75}").await;
    assert_eq!(code, 200, "{v}");
    eventually("the lens to reach 1.75 D", || {
        let m = lens_sim.model();
        ((m.power().0 - 1.75).abs() < 0.02 && (m.target_power().0 - 1.75).abs() < 1e-4)
            .then_some(())
    })
    .await;
    let (code, v) = http(addr, "POST", "/focus", "{\"diopters\": -7}").await;
    assert_eq!(code, 422, "{v}");

    let (code, _) = http(addr, "POST", "/shutdown", "").await;
    assert_eq!(code, 202);
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
    let m = lens_sim.model();
    assert!((m.target_power().0 - 0.5).abs() < 1e-4, "{m:?}");
    assert!(
        (m.power().0 - 0.5).abs() < 0.03,
        "lens at {} D, not parked",
        m.power().0
    );
    // The port is closed.
    assert!(tokio::net::TcpStream::connect(addr).await.is_err());
}

/// Writes `req` as it is, then reads until the server closes: (status, JSON body or null).
async fn raw(addr: std::net::SocketAddr, req: &str) -> (u16, Value) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = Vec::new();
    // A 101 keeps the socket open: the head is enough.
    let _ = tokio::time::timeout(Duration::from_secs(20), s.read_to_end(&mut out)).await;
    let text = String::from_utf8_lossy(&out);
    let status: u16 = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {text:?}"));
    if status == 101 {
        return (101, Value::Null);
    }
    parse_http(&out)
}

#[tokio::test(start_paused = true)]
async fn a_web_page_cannot_drive_the_api() {
    let dir = tempfile::tempdir().unwrap();
    let (d, addr) = start_tcp(sim_config(dir.path(), false)).await;
    let port = addr.port();
    let post = |path: &str, headers: &str, body: &str| {
        format!(
            "POST {path} HTTP/1.1\r\n{headers}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
    };
    let focus = "{\"diopters\": 2}";
    // fetch(url, {mode: "no-cors", method: "POST", body}) from a page on another site.
    let (code, v) = raw(
        addr,
        &post(
            "/focus",
            &format!("Host: {addr}\r\nOrigin: http://evil.example\r\nContent-Type: text/plain;charset=UTF-8\r\n"),
            focus,
        ),
    )
    .await;
    assert_eq!(code, 403, "{v}");
    assert!(v["error"].as_str().unwrap().contains("web pages"), "{v}");
    // The same body without an Origin (a non-browser sending text/plain): 415.
    let (code, v) = raw(
        addr,
        &post(
            "/focus",
            &format!("Host: {addr}\r\nContent-Type: text/plain\r\n"),
            focus,
        ),
    )
    .await;
    assert_eq!(code, 415, "{v}");
    // A form post to a rebinding DNS name that resolves to 127.0.0.1.
    let (code, v) = raw(
        addr,
        &post(
            "/shutdown",
            &format!(
                "Host: evil.example:{port}\r\nContent-Type: application/x-www-form-urlencoded\r\n"
            ),
            "a=1",
        ),
    )
    .await;
    assert_eq!(code, 403, "{v}");
    assert!(v["error"].as_str().unwrap().contains("Host"), "{v}");
    // A bodiless POST (a simple request) is refused too.
    let (code, v) = raw(
        addr,
        &post("/shutdown", &format!("Host: localhost:{port}\r\n"), ""),
    )
    .await;
    assert_eq!(code, 415, "{v}");
    // WebSocket upgrades from a page (a foreign or "null" Origin) are refused; a script's
    // upgrade, with no Origin or the API's own, is accepted.
    let upgrade = |origin: &str| {
        format!(
            "GET /stream HTTP/1.1\r\nHost: {addr}\r\n{origin}Connection: Upgrade\r\nUpgrade: websocket\r\n\
             Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n"
        )
    };
    for origin in ["Origin: http://evil.example\r\n", "Origin: null\r\n"] {
        let (code, v) = raw(addr, &upgrade(origin)).await;
        assert_eq!(code, 403, "{origin}: {v}");
    }
    for origin in [
        "".to_string(),
        format!("Origin: http://localhost:{port}\r\n"),
    ] {
        let (code, _) = raw(addr, &upgrade(&origin)).await;
        assert_eq!(code, 101, "{origin}");
    }
    // Nothing above reached the rig.
    let v = status_of(&d);
    assert!(v["focus"]["manual_d"].is_null(), "{v}");
    assert!(!d.cancel_token().is_cancelled());
    // A script's request goes through.
    let (code, v) = http(addr, "POST", "/focus", focus).await;
    assert_eq!(code, 200, "{v}");

    // Oversized requests get JSON errors like every other refusal.
    let long = format!(
        "GET /status?{} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n",
        "a".repeat(5000)
    );
    let (code, v) = raw(addr, &long).await;
    assert_eq!(code, 414, "{v}");
    assert!(v["error"].is_string(), "{v}");
    let big_header = format!(
        "GET /status HTTP/1.1\r\nHost: {addr}\r\nX-Big: {}\r\nConnection: close\r\n\r\n",
        "a".repeat(20_000)
    );
    let (code, v) = raw(addr, &big_header).await;
    assert_eq!(code, 431, "{v}");
    assert!(v["error"].is_string(), "{v}");
    // Heads past hyper's own limits (its buffer, its header count) get JSON too, not
    // hyper's empty 431.
    let huge_header = format!(
        "GET /status HTTP/1.1\r\nHost: {addr}\r\nX-Big: {}\r\nConnection: close\r\n\r\n",
        "a".repeat(200_000)
    );
    let many_headers = format!(
        "GET /status HTTP/1.1\r\nHost: {addr}\r\n{}Connection: close\r\n\r\n",
        (0..150)
            .map(|i| format!("X-{i}: 1\r\n"))
            .collect::<String>()
    );
    for (what, req) in [("200 kB", &huge_header), ("150 headers", &many_headers)] {
        let (code, v) = raw(addr, req).await;
        assert_eq!(code, 431, "{what}: {v}");
        assert!(v["error"].is_string(), "{what}: {v}");
    }
    // The same on a kept-alive connection's second request.
    {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let first = format!("GET /status HTTP/1.1\r\nHost: {addr}\r\n\r\n");
        s.write_all(first.as_bytes()).await.unwrap();
        let mut got = Vec::new();
        let mut chunk = [0u8; 4096];
        // Read the first reply whole (its length from content-length).
        loop {
            let n = s.read(&mut chunk).await.unwrap();
            assert!(n > 0, "the daemon closed a kept-alive connection");
            got.extend_from_slice(&chunk[..n]);
            let text = String::from_utf8_lossy(&got).to_string();
            if let Some((head, body)) = text.split_once("\r\n\r\n") {
                let len: usize = head
                    .lines()
                    .find_map(|l| {
                        let l = l.to_ascii_lowercase();
                        l.strip_prefix("content-length:")
                            .map(|v| v.trim().parse().unwrap())
                    })
                    .expect("a content-length");
                if body.len() >= len {
                    break;
                }
            }
        }
        assert_eq!(parse_http(&got).0, 200);
        s.write_all(huge_header.as_bytes()).await.unwrap();
        let mut out = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(20), s.read_to_end(&mut out)).await;
        let (code, v) = parse_http(&out);
        assert_eq!(code, 431, "{v}");
        assert!(v["error"].is_string(), "{v}");
    }
    // (Headers only: a server that refuses a body unread resets the socket.)
    let big_body = format!(
        "POST /focus HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: 100000\r\nConnection: close\r\n\r\n"
    );
    let (code, v) = raw(addr, &big_body).await;
    assert_eq!(code, 413, "{v}");
    assert!(v["error"].is_string(), "{v}");

    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn slow_and_idle_clients_are_timed_out() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let (d, addr) = start_tcp(sim_config(dir.path(), false)).await;
    // Half a header section, then nothing: closed.
    let mut slow = tokio::net::TcpStream::connect(addr).await.unwrap();
    slow.write_all(format!("GET /status HTTP/1.1\r\nHost: {addr}\r\n").as_bytes())
        .await
        .unwrap();
    let start = tokio::time::Instant::now();
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(60), slow.read_to_end(&mut out))
        .await
        .expect("a slow header kept its connection for 60 s")
        .unwrap();
    assert!(start.elapsed() >= super::guard::HEADER_TIMEOUT);
    // A keep-alive connection that goes idle after one request: closed.
    let mut idle = tokio::net::TcpStream::connect(addr).await.unwrap();
    idle.write_all(format!("GET /status HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(60), idle.read_to_end(&mut out))
        .await
        .expect("an idle connection stayed open for 60 s")
        .unwrap();
    assert!(String::from_utf8_lossy(&out).starts_with("HTTP/1.1 200"));
    // A body that stops arriving: 408, as JSON.
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(
        format!(
            "POST /focus HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
             Content-Length: 40\r\nConnection: close\r\n\r\n{{\"diop"
        )
        .as_bytes(),
    )
    .await
    .unwrap();
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(60), s.read_to_end(&mut out))
        .await
        .expect("a stalled body kept its connection for 60 s")
        .unwrap();
    let (code, v) = parse_http(&out);
    assert_eq!(code, 408, "{v}");
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn with_a_token_every_request_carries_it() {
    let dir = tempfile::tempdir().unwrap();
    let token = "5f0c3a9e1b7d4c2a8e6f";
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, format!("{token}\n")).unwrap();
    let mut cfg = sim_config(dir.path(), false);
    cfg.api.token_file = Some(token_file);
    let (d, addr) = start_tcp(cfg).await;
    let get = |auth: &str| {
        format!("GET /status HTTP/1.1\r\nHost: {addr}\r\n{auth}Connection: close\r\n\r\n")
    };
    let (code, v) = raw(addr, &get("")).await;
    assert_eq!(code, 401, "{v}");
    let (code, _) = raw(
        addr,
        &get("Authorization: Bearer wrong-token-wrong-token\r\n"),
    )
    .await;
    assert_eq!(code, 401);
    let (code, v) = raw(addr, &get(&format!("Authorization: Bearer {token}\r\n"))).await;
    assert_eq!(code, 200, "{v}");
    assert_eq!(v["mode"], json!("varifocal"));
    stop(d).await;
}

/// The next text message of a WebSocket, within 20 s.
async fn next_text<S>(ws: &mut S) -> String
where
    S: futures_util::Stream<
            Item = Result<
                tokio_tungstenite::tungstenite::Message,
                tokio_tungstenite::tungstenite::Error,
            >,
        > + Unpin,
{
    use futures_util::StreamExt;
    loop {
        let m = tokio::time::timeout(Duration::from_secs(20), ws.next())
            .await
            .expect("no stream message within 20 s")
            .expect("stream ended")
            .expect("stream error");
        if let tokio_tungstenite::tungstenite::Message::Text(t) = m {
            return t.to_string();
        }
    }
}

#[tokio::test(start_paused = true)]
async fn shutdown_parks_the_lens_and_finishes_the_recording() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), true))
        .await
        .unwrap();
    let lens_sim = d.shared().devices().sims().unwrap().lenses[0]
        .clone()
        .unwrap()
        .lens
        .unwrap();
    let sh = d.shared().clone();
    // Run until gaze has moved the lens and frames have been shown.
    eventually("gaze-driven lens commands and frames", || {
        let v = sh.status_json();
        (v["counts"]["lens_commands"].as_u64() >= Some(2)
            && v["counts"]["frames_shown"].as_u64() >= Some(3))
        .then_some(())
    })
    .await;
    let rec_path = {
        let v = sh.status_json();
        std::path::PathBuf::from(v["recording"].as_str().unwrap())
    };
    d.cancel_token().cancel();
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
    // The lens is where the config parks it: the simulator's own state says so.
    let m = lens_sim.model();
    assert!((m.target_power().0 - 0.5).abs() < 1e-4, "{m:?}");
    assert!((m.power().0 - 0.5).abs() < 0.03, "{m:?}");
    let park = report.park.unwrap();
    assert!(
        (park.reported_power.unwrap() - 0.5).abs() < 0.03,
        "{park:?}"
    );
    // The recording is complete (summary and footer written) and holds the run.
    let stats = report.recording.unwrap().unwrap();
    assert_eq!(stats.path, rec_path);
    let back = dioptra_rig::recording::read(&rec_path).unwrap();
    assert!(back.complete);
    assert_eq!(back.messages.len() as u64, stats.messages);
    let count = |topic: &str| {
        back.messages
            .iter()
            .filter(|(_, r)| r.topic() == topic)
            .count()
    };
    assert!(count("/gaze") > 10, "{}", count("/gaze"));
    assert!(count("/lens/command") >= 2);
    assert!(count("/lens/state") > 0);
    assert!(count("/frame") >= 3);
    let bytes = std::fs::read(&rec_path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    assert_eq!(
        summary.stats.unwrap().message_count,
        stats.messages,
        "the summary counts every message"
    );
}

#[tokio::test(start_paused = true)]
async fn a_lost_lens_is_retried_while_the_rest_runs_and_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let state = |dev: &str| sh.devices().registry().snapshot().get(dev).map(|s| s.state);
    eventually("the lens to connect", || {
        (state("lens") == Some(State::Ok)).then_some(())
    })
    .await;
    let app = api::router(sh.clone());
    let (s, v) = call(&app, "POST", "/sim/lens/unplug", "").await;
    assert_eq!((s, &v["plugged"]), (StatusCode::OK, &json!(false)), "{v}");
    eventually("the lens to be lost", || {
        (state("lens") == Some(State::Lost)).then_some(())
    })
    .await;
    let lost = sh.devices().registry().snapshot()["lens"].clone();
    assert!(lost.last_error.is_some(), "{lost:?}");
    // Gaze keeps flowing while the lens is gone.
    let gaze_then = sh.status_json()["counts"]["gaze_samples"].as_u64().unwrap();
    eventually("gaze samples while the lens is lost", || {
        (sh.status_json()["counts"]["gaze_samples"].as_u64().unwrap() > gaze_then + 5).then_some(())
    })
    .await;
    // It keeps failing (with backoff) while unplugged ...
    eventually("a retry", || {
        (sh.devices().registry().snapshot()["lens"].failures > lost.failures).then_some(())
    })
    .await;
    assert_eq!(state("lens"), Some(State::Lost));
    let v = sh.status_json();
    assert!(
        v["devices"]["lens"]["last_error"]
            .as_str()
            .unwrap()
            .contains("unplugged"),
        "{v}"
    );
    // The lost lens's last read-back is not shown as where it is (issue 56: a stale lens_d).
    assert_eq!(v["focus"]["lens_d"], json!(null), "{v}");
    // ... and comes back when plugged in again.
    assert_eq!(sh.status_json()["sim_lens"]["plugged"], json!(false));
    let (s, v) = call(&app, "POST", "/sim/lens/replug", "").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    eventually("the lens to reconnect", || {
        (state("lens") == Some(State::Ok)).then_some(())
    })
    .await;
    assert_eq!(sh.devices().registry().snapshot()["lens"].connects, 2);
    // Back: the loss's error is gone from /status (it stayed after a recovery), and the lens
    // reports where it is again.
    assert_eq!(sh.devices().registry().snapshot()["lens"].last_error, None);
    eventually("a read-back after the reconnect", || {
        sh.status_json()["focus"]["lens_d"]
            .is_number()
            .then_some(())
    })
    .await;
    d.cancel_token().cancel();
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
}

/// The binocular example rig: a lens per eye, each its own device; `/status` shows each eye
/// under `focus` and names the lens that is lost when one is unplugged, while the other goes
/// on.
#[tokio::test(start_paused = true)]
async fn a_binocular_rig_shows_each_eye_and_which_lens_is_lost() {
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("[recording]\ndir = \"recordings\"\nstart = false\n", "");
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let sh = d.shared().clone();
    let state = |dev: &str| sh.devices().registry().snapshot().get(dev).map(|s| s.state);
    eventually("both lenses to connect and be commanded", || {
        let v = sh.status_json();
        let ok = state("lens_left") == Some(State::Ok)
            && state("lens_right") == Some(State::Ok)
            && v["focus"]["left"]["commanded_d"].is_number()
            && v["focus"]["right"]["commanded_d"].is_number()
            && v["focus"]["right"]["lens_d"].is_number();
        ok.then_some(())
    })
    .await;
    assert_eq!(state("lens"), None, "no one-lens device on a binocular rig");
    let app = api::router(sh.clone());
    let (s, v) = call(&app, "POST", "/sim/lens_right/unplug", "").await;
    assert_eq!((s, &v["plugged"]), (StatusCode::OK, &json!(false)), "{v}");
    let v = eventually("the right lens to be lost", || {
        let v = sh.status_json();
        (v["focus"]["right"]["link"] == json!("lost")).then_some(v)
    })
    .await;
    assert_eq!(v["focus"]["left"]["link"], json!("ok"), "{v}");
    assert_eq!(v["devices"]["lens_right"]["state"], json!("lost"), "{v}");
    assert_eq!(v["sim_lens"]["right"]["plugged"], json!(false), "{v}");
    assert_eq!(v["sim_lens"]["left"]["plugged"], json!(true), "{v}");
    let (s, _) = call(&app, "POST", "/sim/lens_right/replug", "").await;
    assert_eq!(s, StatusCode::OK);
    eventually("the right lens back", || {
        (sh.status_json()["focus"]["right"]["link"] == json!("ok")).then_some(())
    })
    .await;
    d.cancel_token().cancel();
    let report = d.wait().await;
    assert!(report.ok(), "{report:?}");
    assert!(
        report.summary().contains("right lens parked"),
        "{}",
        report.summary()
    );
}

/// The binocular example rig's headless panel: both eyes side by side on a 2 x 96 wide panel;
/// an eye's offset that moves its image past its half refuses every frame, and `/status`
/// says so (count and reason) though nothing is shown.
#[tokio::test(start_paused = true)]
async fn a_side_by_side_panel_shows_both_eyes_and_reports_a_misfit() {
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("[recording]\ndir = \"recordings\"\nstart = false\n", "");
    assert!(text.contains("layout = \"side-by-side\""));
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let v = eventually("frames shown", || {
        let v = status_of(&d);
        (v["counts"]["frames_shown"].as_u64() > Some(2)).then_some(v)
    })
    .await;
    let disp = &v["display"];
    assert_eq!(disp["layout"], json!("side-by-side"), "{disp}");
    assert_eq!(disp["surface"], json!([192, 96]), "{disp}");
    assert_eq!(disp["places"]["right"], json!([96, 0, 96, 96]), "{disp}");
    assert_eq!(disp["misfit"]["count"], json!(0), "{disp}");
    assert_eq!(
        disp["mono_on_stereo"],
        json!(0),
        "each eye rendered: {disp}"
    );
    stop(d).await;

    let text = text.replace(
        "layout = \"side-by-side\"",
        "layout = \"side-by-side\"\neye_offset_px = { left = [1, 0] }",
    );
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let v = eventually("misfits reported", || {
        let v = status_of(&d);
        (v["display"]["misfit"]["count"].as_u64() > Some(2)).then_some(v)
    })
    .await;
    assert_eq!(v["counts"]["frames_shown"], json!(0), "{v}");
    let newest = v["display"]["misfit"]["newest"]
        .as_str()
        .unwrap_or_default();
    assert!(
        newest.starts_with("the left eye's 96x96 image, offset [1, 0]")
            && newest.contains("1 px over its right edge"),
        "{newest}"
    );
    stop(d).await;
}

/// Eyes whose lenses reach no focus in common (prescriptions 6 D apart through a 5 D lens
/// range): a manual focus is refused saying so, with each eye's range, and `/status` gives no
/// common range; handing focus back to gaze still works.
#[tokio::test(start_paused = true)]
async fn manual_focus_on_eyes_with_no_common_focus_is_refused_saying_why() {
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("[recording]\ndir = \"recordings\"\nstart = false\n", "")
        .replace(
            "[eye]",
            "[optics.left]\nprescription_sphere_d = -3.0\nprescription_vertex_mm = 0.0\n\n\
             [optics.right]\nprescription_sphere_d = 3.0\nprescription_vertex_mm = 0.0\n\n[eye]",
        );
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let sh = d.shared().clone();
    assert_eq!(sh.optics().focus_range_d(), None);
    assert_eq!(sh.status_json()["focus"]["focus_range_d"], json!(null));
    let app = api::router(sh.clone());
    let (s, v) = call(&app, "POST", "/focus", r#"{"diopters": 1.0}"#).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    let msg = v["error"].as_str().unwrap_or_default().to_string() + &v.to_string();
    assert!(
        msg.contains("no focus in common") && msg.contains("left") && msg.contains("right"),
        "{v}"
    );
    let (s, v) = call(&app, "POST", "/focus", r#"{"diopters": null}"#).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    d.cancel_token().cancel();
    assert!(d.wait().await.ok());
}

#[tokio::test(start_paused = true)]
async fn a_device_missing_at_start_is_shown_and_retried_while_the_rest_runs() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = sim_config(dir.path(), false);
    let missing = dir.path().join("ttyACM-missing");
    cfg.devices.lens.first_mut().port = dioptra_rig::config::Port::Path(missing.clone());
    // Not required: the rig starts without it (a required one stops the start, below).
    cfg.devices.lens.first_mut().required = Some(false);
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    let lens = eventually("a failed lens connect", || {
        let s = sh.devices().registry().snapshot()["lens"].clone();
        (s.failures >= 2).then_some(s)
    })
    .await;
    assert_eq!(lens.state, State::Lost);
    let err = lens.last_error.unwrap();
    assert!(err.contains("ttyACM-missing"), "{err}");
    eventually("gaze samples", || {
        (sh.status_json()["counts"]["gaze_samples"].as_u64().unwrap() > 5).then_some(())
    })
    .await;
    d.cancel_token().cancel();
    let report = d.wait().await;
    // It could not park a lens it never reached, and says so.
    assert!(!report.ok());
    assert!(report.problems()[0].contains("not connected"), "{report:?}");
}

#[tokio::test(start_paused = true)]
async fn the_api_on_a_unix_socket_is_private() {
    use std::os::unix::fs::PermissionsExt;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let sock = dir.path().join("dioptra.sock");
    let text = SIM_RIG.replace(
        "listen = \"127.0.0.1:7420\"",
        &format!("unix = {:?}", sock.display().to_string()),
    );
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let mode = std::fs::metadata(&sock).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600);
    let mut s = tokio::net::UnixStream::connect(&sock).await.unwrap();
    s.write_all(b"GET /status HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).await.unwrap();
    let (code, v) = parse_http(&out);
    assert_eq!(code, 200);
    assert_eq!(v["mode"], json!("varifocal"));
    stop(d).await;
    assert!(!sock.exists(), "the socket is removed on shutdown");
}

/// Runs `cfg` (recording from the start) with gaze and a manual focus of `manual` D (whose
/// command is `power` D), calls `before_replay`, and checks that the recording replays to
/// the same commands.
async fn replays_to_the_same_commands(
    cfg: RigConfig,
    manual: f32,
    power: f32,
    before_replay: impl FnOnce(),
) {
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    eventually("a few gaze-driven lens commands", || {
        (sh.status_json()["counts"]["lens_commands"].as_u64() >= Some(3)).then_some(())
    })
    .await;
    // An API command is part of the run too.
    sh.control(dioptra_rig::Control::ManualFocus(Some(manual)))
        .await
        .unwrap();
    sh.control(dioptra_rig::Control::ManualFocus(None))
        .await
        .unwrap();
    eventually("frames", || {
        (sh.status_json()["counts"]["frames_shown"].as_u64() >= Some(5)).then_some(())
    })
    .await;
    d.cancel_token().cancel();
    let report = d.wait().await;
    let stats = report.recording.unwrap().unwrap();
    before_replay();
    let r = crate::replay::replay_file(&stats.path).unwrap();
    assert!(r.complete && r.from_start);
    let lens = r
        .recorded
        .iter()
        .filter(|c| matches!(c, crate::replay::Cmd::Lens { .. }))
        .count();
    assert!(lens >= 4, "{:?}", r.recorded);
    assert!(
        r.recorded.iter().any(
            |c| matches!(c, crate::replay::Cmd::Lens { power_d, .. } if (*power_d - power).abs() < 1e-5)
        ),
        "{:?}",
        r.recorded
    );
    assert!(
        r.identical(),
        "first difference {:?} after {}",
        r.first_difference,
        r.matching_prefix
    );
    assert_eq!(r.recorded, r.replayed);
    assert_eq!(r.verdict(), crate::replay::Verdict::Identical);
}

/// A binocular rig records each eye's lens on its own topics, and its recording replays to
/// the same commands, each to its eye's lens.
#[tokio::test(start_paused = true)]
async fn a_binocular_recording_has_each_eyes_lens_topics_and_replays() {
    let dir = tempfile::tempdir().unwrap();
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace(
            "dir = \"recordings\"",
            &format!("dir = {:?}", dir.path().join("rec").display().to_string()),
        )
        .replace("start = false", "start = true");
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let sh = d.shared().clone();
    eventually("gaze-driven lens commands to both lenses", || {
        (sh.status_json()["counts"]["lens_commands"].as_u64() >= Some(6)).then_some(())
    })
    .await;
    d.cancel_token().cancel();
    let report = d.wait().await;
    let stats = report.recording.unwrap().unwrap();
    let r = crate::replay::replay_file(&stats.path).unwrap();
    for t in [
        "/lens/left/command",
        "/lens/right/command",
        "/lens/left/state",
        "/lens/right/wire",
    ] {
        assert!(
            r.topics.get(t).is_some_and(|&n| n > 0),
            "{t}: {:?}",
            r.topics
        );
    }
    assert!(!r.topics.contains_key("/lens/command"), "{:?}", r.topics);
    use dioptra_core::Side;
    let to = |eye| {
        r.recorded
            .iter()
            .filter(|c| matches!(c, crate::replay::Cmd::Lens { eye: Some(e), .. } if *e == eye))
            .count()
    };
    assert!(to(Side::Left) >= 3 && to(Side::Left) == to(Side::Right));
    assert!(r.identical(), "first difference {:?}", r.first_difference);
    assert_eq!(r.recorded, r.replayed);
}

#[tokio::test(start_paused = true)]
async fn a_recorded_run_replays_to_the_same_commands() {
    let dir = tempfile::tempdir().unwrap();
    replays_to_the_same_commands(sim_config(dir.path(), true), 2.0, 2.0, || {}).await;
}

#[tokio::test(start_paused = true)]
async fn a_run_with_a_calibration_table_replays_with_the_table_it_read() {
    let dir = tempfile::tempdir().unwrap();
    // A table of demand 3 - command over the lens range: 2 D is a command of 1 D.
    let table = dir.path().join("cal.csv");
    let rows: String = (0..=10)
        .map(|k| {
            let c = -1.0 + 0.5 * f64::from(k);
            format!("{c},{}\n", 3.0 - c)
        })
        .collect();
    std::fs::write(&table, format!("command_d,demand_d\n{rows}")).unwrap();
    let mut cfg = sim_config(dir.path(), true);
    cfg.optics.calibration = Some(table.clone());
    let cfg = RigConfig::parse(&toml::to_string(&cfg).unwrap()).unwrap();
    assert_eq!(cfg.optics_map(None).unwrap().source_name(), "calibration");
    // The table is gone (or changed) by the time of the replay: the recording has it.
    replays_to_the_same_commands(cfg, 2.0, 1.0, || std::fs::remove_file(&table).unwrap()).await;
}

/// Item 5: a recording started through the API (a trial's) holds the scheduler's state
/// when it began, so `dioptra replay` starts there and every command compares: gaze-driven
/// ones, a manual focus and its release, renders and presents.
#[tokio::test(start_paused = true)]
async fn a_recording_started_through_the_api_replays_to_the_same_commands() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    eventually("a few gaze-driven lens commands", || {
        (sh.status_json()["counts"]["lens_commands"].as_u64() >= Some(3)).then_some(())
    })
    .await;
    let (s, v) = call(&app, "POST", "/recording/start", "{\"trial\": 7}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let shown = sh.status_json()["counts"]["frames_shown"].as_u64().unwrap();
    eventually("frames", || {
        (sh.status_json()["counts"]["frames_shown"].as_u64() >= Some(shown + 5)).then_some(())
    })
    .await;
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.0}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": null}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let lens = sh.status_json()["counts"]["lens_commands"]
        .as_u64()
        .unwrap();
    eventually("gaze-driven lens commands after the release", || {
        (sh.status_json()["counts"]["lens_commands"].as_u64() >= Some(lens + 2)).then_some(())
    })
    .await;
    let (s, v) = call(&app, "POST", "/recording/stop", "").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let r = crate::replay::replay_file(Path::new(v["path"].as_str().unwrap())).unwrap();
    assert!(r.complete && !r.from_start && r.restored);
    let lens = r
        .recorded
        .iter()
        .filter(|c| matches!(c, crate::replay::Cmd::Lens { .. }))
        .count();
    assert!(lens >= 3, "{:?}", r.recorded);
    assert!(r
        .recorded
        .iter()
        .any(|c| matches!(c, crate::replay::Cmd::Lens { power_d, .. } if *power_d == 2.0)));
    assert!(
        r.identical(),
        "first difference {:?} after {}",
        r.first_difference,
        r.matching_prefix
    );
    assert_eq!(r.recorded, r.replayed);
    assert_eq!(r.verdict(), crate::replay::Verdict::Identical);
    stop(d).await;
}

/// A recording started mid-run without the scheduler's state (older daemons; the rig's own
/// `start_recording`) is replayed but not compared.
#[tokio::test(start_paused = true)]
async fn a_recording_started_mid_run_is_not_compared() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    eventually("a few lens commands", || {
        (sh.status_json()["counts"]["lens_commands"].as_u64() >= Some(3)).then_some(())
    })
    .await;
    sh.start_recording(false).unwrap();
    eventually("frames", || {
        (sh.status_json()["counts"]["frames_shown"].as_u64() >= Some(10)).then_some(())
    })
    .await;
    let stats = sh.stop_recording().await.unwrap();
    let r = crate::replay::replay_file(&stats.path).unwrap();
    assert!(!r.from_start);
    assert_eq!(r.verdict(), crate::replay::Verdict::CannotCompare);
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn switching_to_multifocal_runs_the_sync_board_and_shows_layers() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    eventually("the sync board to connect", || {
        (sh.devices().registry().snapshot()["sync"].state == State::Ok).then_some(())
    })
    .await;
    // Varifocal: the board is connected but not sequencing.
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert_eq!(sh.status_json()["counts"]["sync_events"], json!(0));
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"multifocal\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let v = sh.status_json();
    assert_eq!(v["mode"], json!("multifocal"));
    // The scheduler picked a decomposition for the new mode.
    assert_eq!(v["method"], json!("linear"));
    let mut v = sh.status_json();
    for _ in 0..2000 {
        v = sh.status_json();
        if v["counts"]["sync_events"].as_u64() > Some(40)
            && v["scheduler"]["counters"]["frames_presented"].as_u64() > Some(4)
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(
        v["scheduler"]["counters"]["frames_presented"].as_u64() > Some(4),
        "no layered frames: {v:#}"
    );
    assert!(v["counts"]["frames_shown"].as_u64() > Some(2), "{v}");
    // The example rig's multifocal lens keeps up: sub-frames reach their planes, and
    // /status says how many did not.
    let sub = eventually("measured sub-frames", || {
        let v = sh.status_json();
        (v["subframes"]["measured"].as_u64() > Some(40)).then_some(v["subframes"].clone())
    })
    .await;
    let rate = sub["off_target_rate"].as_f64().unwrap();
    assert!(rate < 0.05, "{sub}");
    // Back to varifocal: the sequence stops.
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"varifocal\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    tokio::time::sleep(Duration::from_millis(50)).await;
    let before = sh.status_json()["counts"]["sync_events"].as_u64().unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let after = sh.status_json()["counts"]["sync_events"].as_u64().unwrap();
    assert_eq!(
        before, after,
        "the sync board kept sequencing after leaving multifocal"
    );
    // Light-field mode: the lenslet panel of the scene's light field is shown.
    let shown = sh.status_json()["counts"]["frames_shown"].as_u64().unwrap();
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"lightfield\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(sh.status_json()["method"], json!("views"));
    eventually("light-field frames", || {
        let v = sh.status_json();
        (v["counts"]["frames_shown"].as_u64() > Some(shown + 3)
            && v["counts"]["render_errors"] == json!(0))
        .then_some(())
    })
    .await;
    // The network does not render light fields (C5) in the daemon: refused, with why.
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"network\"}").await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn method_auto_renders_the_planners_choice_and_shows_it() {
    let dir = tempfile::tempdir().unwrap();
    let text = SIM_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("method = \"gather\"", "method = \"auto\"")
        .replace(
            "dir = \"recordings\"",
            &format!("dir = {:?}", dir.path().join("rec").display().to_string()),
        );
    let cfg = RigConfig::parse(&text).unwrap();
    assert!(cfg.auto_method);
    let d = Daemon::start_config(cfg).await.unwrap();
    let planned = eventually("a planned frame", || {
        let s = status_of(&d);
        (!s["planned"].is_null()).then_some(s)
    })
    .await;
    assert_eq!(planned["method"], "auto", "{planned}");
    let choice = planned["planned"]["method"].as_str().unwrap().to_string();
    assert!(
        choice == "none"
            || choice == "gather"
            || choice.starts_with("lightfield-")
            || choice.starts_with("pyramid"),
        "{planned}"
    );
    assert!(
        planned["planned"]["why"]
            .as_str()
            .unwrap()
            .contains("fovea"),
        "{planned}"
    );
    // Off and on again through the API, as the README documents it.
    let app = api::router(d.shared().clone());
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"gather\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let v = status_of(&d);
    assert_eq!(v["method"], json!("gather"), "{v}");
    assert!(v["planned"].is_null(), "{v}");
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"auto\"}").await;
    assert_eq!((s, &v["method"]), (StatusCode::OK, &json!("auto")), "{v}");
    eventually("a planned frame after auto", || {
        (!status_of(&d)["planned"].is_null()).then_some(())
    })
    .await;
    assert_eq!(status_of(&d)["method"], json!("auto"));
    // Multifocal frames are the hardware's planes: no planner, and a switch turns it off.
    let (s, _) = call(&app, "POST", "/mode", "{\"mode\": \"multifocal\"}").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(status_of(&d)["method"], json!("linear"));
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"auto\"}").await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    assert_eq!(v["key"], json!("method"));
    stop(d).await;
}

/// Random weights of every net the daemon loads (C1, C4, C1R, C4R, C5R) in `dir`, as
/// `render.weights` expects them.
fn random_weights(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    for (config, seed) in [
        ("c1", 11),
        ("c4", 12),
        ("c1r", 13),
        ("c4r", 14),
        ("c5r", 15),
    ] {
        let arch = dioptra_net::Arch::preset(config).unwrap();
        let mut w = dioptra_net::Weights::random(&arch, seed).unwrap();
        // A refinement net's last layer starts at zero; give it weights, so it corrects.
        let mut r = dioptra_net::weights::SplitMix(seed);
        for v in w.convs.iter_mut().flat_map(|c| c.weight.iter_mut()) {
            if *v == 0.0 {
                *v = 0.02 * r.uniform();
            }
        }
        w.save(&dir.join(format!("{config}.safetensors"))).unwrap();
    }
}

fn network_config(dir: &Path, weights: &Path) -> RigConfig {
    let mut cfg = sim_config(dir, false);
    cfg.method = dioptra_rig::config::Method(dioptra_sched::RenderMethod::Network);
    cfg.render.weights = Some(weights.to_path_buf());
    cfg
}

/// A frame's images on the host (read back when they were left in GPU memory).
fn on_host(images: Vec<dioptra_rig::render::FrameImage>) -> Vec<dioptra_core::RgbImage> {
    images
        .iter()
        .map(|i| i.to_host().unwrap().into_owned())
        .collect()
}

/// What the daemon shows with `method = "network"` is the network's output: C1 at the
/// frame's focus (varifocal), C4's layers (multifocal).
#[test]
fn the_network_renders_what_the_net_computes() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    let cfg = network_config(dir.path(), &weights);
    let r = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &cfg.render,
        &cfg.eye,
        &cfg.display,
        &cfg.optics,
    )
    .unwrap();
    let frame = scene_frame(&cfg);
    assert!(r.network_missing().is_empty());
    let c1 = dioptra_net::load_net(Some(&weights.join("c1.safetensors")), "c1").unwrap();
    let eye = dioptra_core::EyeModel {
        pupil_diameter: dioptra_core::Millimeters(cfg.eye.pupil_mm),
        fov_horizontal_deg: cfg.eye.fov_deg,
        width_px: cfg.display.width,
        ..Default::default()
    };
    let focus = dioptra_core::Diopters(1.5);
    let shown = r
        .render_frame(
            &frame,
            dioptra_rig::config::Mode::Varifocal,
            cfg.method,
            focus,
            None,
            false,
        )
        .unwrap()
        .images;
    let shown = on_host(shown);
    assert_eq!(shown, vec![c1.defocus(&frame.rgbd, focus, &eye).unwrap()]);
    // The focus reaches the net: another focus, another image.
    let other = r
        .render_frame(
            &frame,
            dioptra_rig::config::Mode::Varifocal,
            cfg.method,
            dioptra_core::Diopters(0.1),
            None,
            false,
        )
        .unwrap()
        .images;
    let other = on_host(other);
    assert_ne!(shown, other);
    let c4 = dioptra_net::load_net(Some(&weights.join("c4.safetensors")), "c4").unwrap();
    let layers = on_host(
        r.render_frame(
            &frame,
            dioptra_rig::config::Mode::Multifocal,
            cfg.method,
            focus,
            None,
            false,
        )
        .unwrap()
        .images,
    );
    assert_eq!(layers, c4.decompose(&frame.rgbd).unwrap().images);
    assert_eq!(layers.len(), cfg.optics.planes.len());
}

#[test]
fn c4_weights_for_other_planes_are_refused_for_multifocal_only() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    let mut cfg = network_config(dir.path(), &weights);
    cfg.optics.planes = vec![0.5, 1.5];
    let r = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &cfg.render,
        &cfg.eye,
        &cfg.display,
        &cfg.optics,
    )
    .unwrap();
    let missing = r.network_missing();
    // C4 and C4R, both made for other planes.
    assert_eq!(missing.len(), 2, "{missing:?}");
    for (mode, method, why) in &missing {
        assert_eq!(*mode, dioptra_rig::config::Mode::Multifocal);
        assert!(
            matches!(
                method,
                dioptra_sched::RenderMethod::Network | dioptra_sched::RenderMethod::Refine
            ),
            "{method:?}"
        );
        assert!(
            why.contains("planes [0.2, 0.8, 1.4, 2.0] D")
                && why.contains("optics.planes is [0.5, 1.5] D"),
            "{why}"
        );
    }
}

/// What the daemon shows with `method = "refine"` is the refinement nets' output: C1R on its
/// classical render at the frame's focus (varifocal), C4R on linear blending (multifocal).
#[test]
fn refine_renders_what_the_refinement_nets_compute() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    let mut cfg = network_config(dir.path(), &weights);
    cfg.method = dioptra_rig::config::Method(dioptra_sched::RenderMethod::Refine);
    cfg.render.backend = dioptra_rig::config::RenderBackend::Cpu;
    let r = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &cfg.render,
        &cfg.eye,
        &cfg.display,
        &cfg.optics,
    )
    .unwrap();
    let frame = scene_frame(&cfg);
    assert!(r.network_missing().is_empty());
    let eye = dioptra_core::EyeModel {
        pupil_diameter: dioptra_core::Millimeters(cfg.eye.pupil_mm),
        fov_horizontal_deg: cfg.eye.fov_deg,
        width_px: cfg.display.width,
        ..Default::default()
    };
    let focus = dioptra_core::Diopters(0.2);
    let render = |mode| {
        on_host(
            r.render_frame(&frame, mode, cfg.method, focus, None, false)
                .unwrap()
                .images,
        )
    };
    let shown = render(dioptra_rig::config::Mode::Varifocal);
    let c1r = dioptra_net::load_net(Some(&weights.join("c1r.safetensors")), "c1r").unwrap();
    let dioptra_net::Task::C1r { classical } = c1r.arch().task else {
        panic!("not c1r");
    };
    let input = frame.rgbd.clone();
    let base = dioptra_net::refine::classical_defocus(
        &dioptra_render::Cpu,
        classical,
        &input,
        focus,
        &eye,
    )
    .unwrap();
    let want = c1r.refine_defocus(&input, &base, focus, &eye).unwrap();
    assert!(
        want.tiles.fraction() > 0.0,
        "the scene has depth edges in the blur"
    );
    assert_ne!(want.image, base, "the net corrects the classical render");
    assert_eq!(shown, vec![want.image]);
    let status = r.backend_status();
    assert_eq!(
        status["refine_tiles_run"].as_f64(),
        Some(want.tiles.fraction()),
        "{status}"
    );
    let layers = render(dioptra_rig::config::Mode::Multifocal);
    let c4r = dioptra_net::load_net(Some(&weights.join("c4r.safetensors")), "c4r").unwrap();
    let planes: Vec<dioptra_core::Diopters> = cfg
        .optics
        .planes
        .iter()
        .map(|&p| dioptra_core::Diopters(p))
        .collect();
    let linear = dioptra_render::multifocal::linear_blend(&input, &planes).unwrap();
    assert_eq!(
        layers,
        c4r.refine_decompose(&input, &linear).unwrap().images
    );
}

#[tokio::test(start_paused = true)]
async fn the_daemon_renders_with_the_network_and_refuses_a_mode_without_weights() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    // Only C1: varifocal runs, multifocal is refused with the missing file named.
    std::fs::remove_file(weights.join("c4.safetensors")).unwrap();
    let d = Daemon::start_config(network_config(dir.path(), &weights))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    eventually("network frames", || {
        let v = sh.status_json();
        (v["counts"]["frames_shown"].as_u64() >= Some(5)).then_some(())
    })
    .await;
    let v = sh.status_json();
    assert_eq!(v["method"], json!("network"));
    assert_eq!(v["counts"]["render_errors"], json!(0), "{v}");
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"multifocal\"}").await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    let msg = v.to_string();
    assert!(msg.contains("c4.safetensors does not exist"), "{msg}");
    assert_eq!(sh.status_json()["mode"], json!("varifocal"));
    // Gather and back to the network, which the API accepts in varifocal mode.
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"gather\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"network\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn the_daemon_shows_c4_layers_in_multifocal_mode() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    let mut cfg = network_config(dir.path(), &weights);
    cfg.mode = dioptra_rig::config::Mode::Multifocal;
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    eventually("C4 layered frames", || {
        let v = sh.status_json();
        (v["scheduler"]["counters"]["frames_presented"].as_u64() > Some(4)).then_some(())
    })
    .await;
    let v = sh.status_json();
    assert_eq!(v["method"], json!("network"));
    assert_eq!(v["counts"]["render_errors"], json!(0), "{v}");
    stop(d).await;
}

/// Waits until `frames_shown` has grown by `n` (simulated time), returning the status.
async fn after_frames(d: &Daemon, n: u64) -> Value {
    let start = status_of(d)["counts"]["frames_shown"].as_u64().unwrap();
    eventually("frames to be shown", || {
        let v = status_of(d);
        (v["counts"]["frames_shown"].as_u64().unwrap() >= start + n).then_some(v)
    })
    .await
}

#[tokio::test(start_paused = true)]
async fn focus_at_and_beyond_optical_infinity_renders() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let app = api::router(d.shared().clone());
    after_frames(&d, 3).await;
    for method in ["gather", "lightfield-defocus"] {
        let (s, v) = call(
            &app,
            "POST",
            "/method",
            &format!("{{\"method\": \"{method}\"}}"),
        )
        .await;
        assert_eq!(s, StatusCode::OK, "{v}");
        // The example rig's lens reaches -1 D: 0 D and below are everyday values.
        for focus in [0.0, -1.0, -0.25] {
            let (s, v) = call(
                &app,
                "POST",
                "/focus",
                &format!("{{\"diopters\": {focus}}}"),
            )
            .await;
            assert_eq!(s, StatusCode::OK, "{v}");
            let v = after_frames(&d, 5).await;
            assert_eq!(
                v["counts"]["render_errors"],
                json!(0),
                "{method} at {focus} D: {v}"
            );
        }
    }
    stop(d).await;
}

/// The rig's renderer, but every render at a focus below 1 D fails, and the first at 2 D or
/// more panics.
struct FailingBelow1D(
    dioptra_rig::render::rgbd::RgbdRenderer,
    std::sync::atomic::AtomicBool,
);

impl dioptra_rig::render::Renderer for FailingBelow1D {
    fn render(
        &self,
        job: &dioptra_rig::render::RenderJob,
        content: &dioptra_rig::content::ContentFrame,
    ) -> Result<dioptra_rig::render::RenderOutput, dioptra_render::RenderError> {
        if job.focus.0 >= 2.0 && !self.1.swap(true, std::sync::atomic::Ordering::SeqCst) {
            panic!("a renderer bug");
        }
        if job.focus.0 < 1.0 {
            return Err(dioptra_render::RenderError::Unsupported {
                backend: "test",
                method: "focus below 1 D",
            });
        }
        self.0.render(job, content)
    }
}

#[tokio::test(start_paused = true)]
async fn a_failing_render_shows_the_unblurred_frame_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = sim_config(dir.path(), false);
    let scene = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &cfg.render,
        &cfg.eye,
        &cfg.display,
        &cfg.optics,
    )
    .unwrap();
    let mut setup = dioptra_rig::RigSetup::new(cfg);
    setup.renderer = Some(std::sync::Arc::new(FailingBelow1D(
        scene,
        Default::default(),
    )));
    let d = Daemon::start(setup).await.unwrap();
    let app = api::router(d.shared().clone());
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 0.5}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    // Frames keep coming: the failed ones are shown unblurred.
    let v = after_frames(&d, 20).await;
    let errors = v["counts"]["render_errors"].as_u64().unwrap();
    assert!(errors >= 10, "{v}");
    assert_eq!(
        v["render_errors"]["by_method"]["gather"].as_u64(),
        Some(errors),
        "{v}"
    );
    assert!(
        v["counts"]["fallback_frames"].as_u64().unwrap() >= errors,
        "{v}"
    );
    let last = &v["render_errors"]["last"];
    assert_eq!(last["method"], json!("gather"), "{v}");
    assert_eq!(last["kind"], json!("unsupported"), "{v}");
    assert!(
        last["error"].as_str().unwrap().contains("focus below 1 D"),
        "{v}"
    );
    // Back in range: one render panics, then frames render again and the count stops.
    let (s, _) = call(&app, "POST", "/focus", "{\"diopters\": 2}").await;
    assert_eq!(s, StatusCode::OK);
    let v = eventually("the panicking render counted", || {
        let v = status_of(&d);
        (v["render_errors"]["last"]["kind"] == json!("panic")).then_some(v)
    })
    .await;
    let before = v["counts"]["render_errors"].as_u64().unwrap();
    let v = after_frames(&d, 10).await;
    assert_eq!(v["counts"]["render_errors"].as_u64(), Some(before), "{v}");
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn a_recording_takes_the_experiments_names() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let app = api::router(d.shared().clone());
    for (body, key) in [
        ("{\"name\": \"../etc\"}", "name"),
        ("{\"subject\": \"\"}", "subject"),
        ("{\"trial\": \"a b\"}", "trial"),
        ("{\"run\": 1}", "run"),
    ] {
        let (s, v) = call(&app, "POST", "/recording/start", body).await;
        assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{body}: {v}");
        assert_eq!(v["key"], json!(key), "{body}: {v}");
    }
    let (s, v) = call(
        &app,
        "POST",
        "/recording/start",
        "{\"name\": \"vergence\", \"subject\": \"s01\", \"trial\": 3}",
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let path = v["recording"].as_str().unwrap().to_string();
    assert!(path.ends_with("-vergence-sub-s01-trial-3.mcap"), "{path}");
    eventually("frames", || {
        (status_of(&d)["counts"]["frames_shown"].as_u64() >= Some(3)).then_some(())
    })
    .await;
    let (s, _) = call(&app, "POST", "/recording/stop", "").await;
    assert_eq!(s, StatusCode::OK);
    let rec = dioptra_rig::recording::read(Path::new(&path)).unwrap();
    let Some((_, dioptra_rig::recording::Rec::Start(start))) = rec.messages.first() else {
        panic!("no /start first");
    };
    assert_eq!(
        (
            start.name.as_deref(),
            start.subject.as_deref(),
            start.trial.as_deref()
        ),
        (Some("vergence"), Some("s01"), Some("3"))
    );
    assert!(start.wall_zero_ns.is_some() && !start.clock.is_empty());
    stop(d).await;
}

/// Whether there is a GPU to test on; none fails the test under DIOPTRA_REQUIRE_GPU=1 (as CI).
fn gpu_available() -> bool {
    let ok = !dioptra_render::gpu::list_adapters().is_empty();
    if !ok && std::env::var("DIOPTRA_REQUIRE_GPU").as_deref() == Ok("1") {
        panic!("DIOPTRA_REQUIRE_GPU=1 and there is no GPU adapter");
    }
    if !ok {
        eprintln!("skipped: no GPU adapter");
    }
    ok
}

#[test]
fn the_gpu_backend_renders_what_the_cpu_renders() {
    if !gpu_available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut cpu_cfg = sim_config(dir.path(), false);
    cpu_cfg.render.backend = dioptra_rig::config::RenderBackend::Cpu;
    // The shipped networks.
    cpu_cfg.render.weights = None;
    let mut gpu_cfg = cpu_cfg.clone();
    gpu_cfg.render.backend = dioptra_rig::config::RenderBackend::Gpu;
    let cpu = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &cpu_cfg.render,
        &cpu_cfg.eye,
        &cpu_cfg.display,
        &cpu_cfg.optics,
    )
    .unwrap();
    let gpu = dioptra_rig::render::rgbd::RgbdRenderer::new(
        &gpu_cfg.render,
        &gpu_cfg.eye,
        &gpu_cfg.display,
        &gpu_cfg.optics,
    )
    .unwrap();
    let frame = scene_frame(&cpu_cfg);
    let status = gpu.backend_status();
    assert_eq!(status["backend"], json!("gpu"), "{status}");
    assert!(status["adapter"].is_string(), "{status}");
    assert_eq!(cpu.backend_status()["backend"], json!("cpu"));
    use dioptra_rig::config::{Method, Mode};
    for (mode, method, focus) in [
        (Mode::Varifocal, "gather", 0.4),
        (Mode::Varifocal, "gather", -0.5),
        (Mode::Varifocal, "lightfield-defocus", 1.7),
        (Mode::Varifocal, "pyramid", 0.4),
        (Mode::Multifocal, "linear", 1.0),
        (Mode::Varifocal, "network", 1.2),
        (Mode::Multifocal, "network", 1.0),
        (Mode::Multifocal, "optimized", 1.0),
        (Mode::Multifocal, "spectral", 1.0),
        (Mode::Multifocal, "hybrid", 1.0),
        // 2.2 D: no depth step blurs past the error map's threshold, so C1R runs on no tile;
        // 0.2 D, last, runs it on some (checked in /status below).
        (Mode::Varifocal, "refine", 2.2),
        (Mode::Varifocal, "refine", 0.2),
        (Mode::Multifocal, "refine", 1.0),
    ] {
        let m = Method::parse(method).unwrap();
        let q = dioptra_core::Diopters(focus);
        let a = cpu
            .render_frame(&frame, mode, m, q, None, false)
            .unwrap()
            .images;
        let b = gpu
            .render_frame(&frame, mode, m, q, None, false)
            .unwrap()
            .images;
        assert_eq!(a.len(), b.len());
        // The GPU's own methods leave their images on the GPU (the nets' come back through
        // dioptra-net, the hybrid's composed on the host); the headless sink reads them back
        // for its PNGs only.
        let kept = b
            .iter()
            .all(|i| matches!(i, dioptra_rig::render::FrameImage::Gpu(_)));
        assert_eq!(
            kept,
            !matches!(method, "network" | "refine" | "hybrid"),
            "{method}"
        );
        let png = |images: Vec<dioptra_rig::render::FrameImage>, to: &str| {
            let out = dir.path().join(format!("{method}-{focus}-{to}"));
            let mut sink = dioptra_rig::display::HeadlessSink::new(1, Some(out.clone())).unwrap();
            let n = images.len();
            let frame = dioptra_rig::display::Frame {
                number: 0,
                focus: q,
                layers: Arc::new(images),
                right: None,
                marker: None,
                size_compensation: [None; 2],
            };
            use dioptra_rig::display::DisplaySink as _;
            sink.present(&frame, dioptra_core::Timestamp::ZERO).unwrap();
            (0..n)
                .map(|i| {
                    let name = if n == 1 {
                        "frame_000000.png".to_string()
                    } else {
                        format!("frame_000000_plane{i}.png")
                    };
                    dioptra_render::io::read_color(&out.join(name)).unwrap()
                })
                .collect::<Vec<_>>()
        };
        let reads = gpu.backend_status()["images_read_back"].as_u64().unwrap();
        let (x, y) = (png(a, "cpu"), png(b, "gpu"));
        let read = gpu.backend_status()["images_read_back"].as_u64().unwrap() - reads;
        assert_eq!(read, if kept { x.len() as u64 } else { 0 }, "{method}");
        for (x, y) in x.iter().zip(&y) {
            let p = dioptra_render::metrics::psnr(x, y, None).unwrap();
            assert!(
                p >= 50.0,
                "{method} at {focus} D: GPU PNG {p} dB from the CPU's"
            );
        }
    }
    // The networks ran on the GPU; each method's GPU time is shown when the adapter can
    // time it.
    let status = gpu.backend_status();
    assert_eq!(status["network"]["varifocal"], json!("gpu"), "{status}");
    assert_eq!(status["network"]["multifocal"], json!("gpu"), "{status}");
    assert_eq!(status["refine"]["varifocal"], json!("gpu"), "{status}");
    assert_eq!(status["refine"]["multifocal"], json!("gpu"), "{status}");
    // The fraction is the last varifocal refine's (0.2 D).
    assert!(status["refine_tiles_run"].as_f64() > Some(0.0), "{status}");
    assert_eq!(status["spectral_on"], json!("gpu"), "{status}");
    assert_eq!(cpu.backend_status()["spectral_on"], json!("cpu"));
    if status["timestamps"] == json!(true) {
        for m in [
            "gather",
            "lightfield-16",
            "linear",
            "network",
            "optimized",
            "refine",
            "spectral",
        ] {
            assert!(
                status["gpu_time_us"][m]["count"].as_u64() >= Some(1),
                "{m}: {status}"
            );
        }
    }
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A daemon on the example sim rig (96 x 96) streaming its content (ring in `dir`), its shared
/// state and its API.
async fn stream_daemon(dir: &Path) -> (Daemon, Arc<dioptra_rig::RigState>, axum::Router) {
    let mut cfg = sim_config(dir, false);
    cfg.content.source = dioptra_rig::config::ContentSource::Stream;
    cfg.content.ring = Some(dir.join("frames"));
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    (d, sh, app)
}

/// The stream's `/frame` endpoints: good frames (raw and PNG files) are accepted and shown;
/// each bad one is refused with its reason in a JSON error, counted in `/status` under that
/// reason, and the frame on show stays.
#[tokio::test(start_paused = true)]
async fn every_bad_frame_is_refused_with_its_reason_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let (d, sh, app) = stream_daemon(dir.path()).await;
    let (w, h) = (96usize, 96usize);
    let color = vec![200u8; w * h * 3];
    let depth = f32_bytes(&vec![0.5; w * h]);
    let frame = [color.clone(), depth.clone()].concat();
    let octets = "application/octet-stream";
    let raw = |q: &str| format!("/frame?width={w}&height={h}&color=rgb8&depth=m{q}");
    let content = || sh.status_json()["content"].clone();
    let (s, v) = call_with(&app, "PUT", &raw("&seq=5"), octets, frame.clone()).await;
    assert_eq!((s, &v["seq"]), (StatusCode::OK, &json!(5)), "{v}");
    eventually("the frame on show", || {
        (content()["on_show_seq"] == json!(5)).then_some(())
    })
    .await;

    let mut nan_depth = vec![0.5f32; w * h];
    nan_depth[2 * w + 3] = f32::NAN;
    let nan = [color.clone(), f32_bytes(&nan_depth)].concat();
    let short = frame[..frame.len() - 1].to_vec();
    let long = [frame.clone(), vec![0]].concat();
    let not_png = vec![7u8; 64];
    // (method, path, Content-Type, body, status, reason counted, words in the error)
    type Case<'a> = (
        &'a str,
        String,
        &'a str,
        Vec<u8>,
        StatusCode,
        &'a str,
        &'a str,
    );
    let cases: Vec<Case> = vec![
        (
            "PUT",
            format!("/frame?width=95&height={h}&color=rgb8&depth=m"),
            octets,
            frame.clone(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "wrong_size",
            "the frame is 95x96; the display is 96x96",
        ),
        (
            "PUT",
            raw(""),
            octets,
            short,
            StatusCode::UNPROCESSABLE_ENTITY,
            "length",
            "the depth is 36863 bytes; a 96x96 frame's is 36864",
        ),
        (
            "PUT",
            raw(""),
            octets,
            long,
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_large",
            "larger than a 96x96 frame's 64512 bytes",
        ),
        (
            "PUT",
            raw(""),
            octets,
            nan,
            StatusCode::UNPROCESSABLE_ENTITY,
            "depth",
            "depth at pixel (3, 2) is NaN",
        ),
        (
            "PUT",
            raw("").replace("depth=m", "depth=vulkan"),
            octets,
            frame.clone(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid",
            "needs near and far planes",
        ),
        (
            "PUT",
            raw("&seq=5"),
            octets,
            frame.clone(),
            StatusCode::CONFLICT,
            "stale",
            "sequence number 5 is not newer than 5",
        ),
        (
            "PUT",
            raw("&color_bytes=32").replace("color=rgb8", "color=png"),
            octets,
            not_png,
            StatusCode::UNPROCESSABLE_ENTITY,
            "encoding",
            "color=png and the body does not start with one",
        ),
        (
            "PUT",
            raw("").replace("color=rgb8", "color=png"),
            octets,
            frame.clone(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "request",
            "color_bytes=N says where",
        ),
        (
            "PUT",
            raw("").replace("color=rgb8", "color=bgr8"),
            octets,
            frame.clone(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "request",
            "color=\"bgr8\": expected rgb8, rgba8 or rgbf32",
        ),
        (
            "PUT",
            raw(""),
            "text/plain",
            frame.clone(),
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "request",
            "needs Content-Type: application/octet-stream",
        ),
        (
            "POST",
            "/frame".into(),
            "application/json",
            br#"{"slot": 1, "seq": 9}"#.to_vec(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid",
            "slot 1 holds sequence number 0, not 9",
        ),
        (
            "POST",
            "/frame".into(),
            "application/json",
            br#"{"slot": 7, "seq": 9}"#.to_vec(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid",
            "the ring has slots 0 to 2",
        ),
        (
            "POST",
            "/frame".into(),
            "application/json",
            br#"{"slot": "first"}"#.to_vec(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "request",
            "invalid type: string",
        ),
    ];
    for (method, path, ctype, body, status, reason, words) in cases {
        // `last_error` names the frame (what the request said of it), then the reason.
        let named = match serde_json::from_slice::<Value>(&body) {
            Ok(v) if method == "POST" && v["seq"].is_u64() => {
                format!("ring slot {}'s frame {}", v["slot"], v["seq"])
            }
            _ if path.contains("seq=5") => "frame 5".to_string(),
            _ => "a frame without a sequence number".to_string(),
        };
        let before = content();
        let (s, v) = call_with(&app, method, &path, ctype, body).await;
        assert_eq!(s, status, "{method} {path}: {v}");
        let msg = v["error"].as_str().unwrap_or_default();
        assert!(
            msg.contains(words),
            "{method} {path}: {msg:?} lacks {words:?}"
        );
        let after = content();
        let count = |c: &Value| c["refused"][reason].as_u64().unwrap_or(0);
        assert_eq!(count(&after), count(&before) + 1, "{reason}: {after}");
        let want = format!("{named} refused: {msg}");
        assert_eq!(after["last_error"], json!(want), "{method} {path}: {after}");
        assert_eq!(after["received"], before["received"], "{after}");
        assert_eq!(
            after["on_show_seq"],
            json!(5),
            "the frame on show stays: {after}"
        );
    }

    // A frame as files: a PNG colour image and a 16-bit PNG of millimetres.
    let png = |name: &str, write: &dyn Fn(&Path)| {
        let p = dir.path().join(name);
        write(&p);
        std::fs::read(&p).unwrap()
    };
    let c = png("c.png", &|p| {
        dioptra_render::io::write_color(p, &dioptra_core::RgbImage::new(w, h, [0.2, 0.4, 0.6]))
            .unwrap()
    });
    let plane = dioptra_core::Plane::new(w, h, 2.0);
    let dm = png("d.png", &|p| {
        dioptra_render::io::write_depth(
            p,
            &dioptra_core::DepthMap::from_diopters(plane.clone()).unwrap(),
        )
        .unwrap()
    });
    let path = format!(
        "/frame?width={w}&height={h}&color=png&color_bytes={}&depth=mm&seq=6",
        c.len()
    );
    let (s, v) = call_with(&app, "PUT", &path, octets, [c, dm].concat()).await;
    assert_eq!((s, &v["seq"]), (StatusCode::OK, &json!(6)), "{v}");
    let v = eventually("the PNG frame on show", || {
        let c = content();
        (c["on_show_seq"] == json!(6)).then_some(c)
    })
    .await;
    assert_eq!((&v["received"], &v["shown"]), (&json!(2), &json!(2)), "{v}");
    stop(d).await;
}

/// On the GPU a headless daemon leaves every frame in GPU memory and reads back only the
/// frames it writes as PNG: one image per written frame (varifocal), none for the others.
#[tokio::test(start_paused = true)]
async fn on_the_gpu_only_the_frames_written_as_png_are_read_back() {
    if !gpu_available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = sim_config(dir.path(), false);
    cfg.render.backend = dioptra_rig::config::RenderBackend::Gpu;
    cfg.display.png_every = 4;
    cfg.display.png_dir = Some(dir.path().join("frames"));
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    after_frames(&d, 12).await;
    stop(d).await;
    let v = sh.status_json();
    assert_eq!(v["render"]["backend"], json!("gpu"), "{v}");
    let shown = v["display"]["shown"].as_u64().unwrap();
    let pngs = v["display"]["pngs_written"].as_u64().unwrap();
    assert!(shown >= 12, "{v}");
    // By frame number (issue 56): one PNG for each multiple of 4 up to the last frame shown.
    let last = v["display"]["last"]["frame"].as_u64().unwrap();
    assert_eq!(pngs, last / 4 + 1, "{v}");
    assert_eq!(v["render"]["images_read_back"].as_u64(), Some(pngs), "{v}");
    assert_eq!(v["counts"]["render_errors"], json!(0), "{v}");
}

/// Light-field mode on a stream: the daemon shows the lenslet panel of the streamed frame's
/// synthesised light field, without render errors.
#[tokio::test(start_paused = true)]
async fn light_field_mode_shows_streamed_content() {
    let dir = tempfile::tempdir().unwrap();
    let (d, _, app) = stream_daemon(dir.path()).await;
    let (w, h) = (96usize, 96usize);
    let color: Vec<u8> = (0..w * h * 3).map(|i| (i % 253) as u8).collect();
    let depth = f32_bytes(
        &(0..w * h)
            .map(|i| 0.5 + (i % w) as f32 / w as f32)
            .collect::<Vec<_>>(),
    );
    let path = format!("/frame?width={w}&height={h}&color=rgb8&depth=m");
    let body = [color, depth].concat();
    let (s, v) = call_with(&app, "PUT", &path, "application/octet-stream", body).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"lightfield\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let shown = status_of(&d)["counts"]["frames_shown"].as_u64().unwrap();
    let v = eventually("light-field frames of the stream", || {
        let v = status_of(&d);
        (v["counts"]["frames_shown"].as_u64() > Some(shown + 3)).then_some(v)
    })
    .await;
    assert_eq!(v["counts"]["render_errors"], json!(0), "{v}");
    assert_eq!(v["content"]["on_show_seq"], json!(1), "{v}");
    stop(d).await;
}

#[tokio::test(start_paused = true)]
async fn the_daemon_commands_its_lens_through_the_optics_map_and_says_which() {
    let dir = tempfile::tempdir().unwrap();
    // The example rig: nothing configured, and /status says so.
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let v = status_of(&d);
    assert_eq!(v["optics"]["source"], "identity", "{v}");
    assert!(v["optics"]["map"].as_str().unwrap().starts_with("identity"));
    assert_eq!(v["focus"]["focus_range_d"], json!([-1.0, 4.0]));
    stop(d).await;
    // Display 25 cm from the lens, pupil 15 mm behind: 2 D by hand is X = 2 / 0.97 =
    // 2.061856, a command of 4 - X = 1.938144 D; the lens range -1..4 D reaches focus
    // 0 D (command 4) to 5 / 1.075 = 4.651163 D (command -1).
    let mut cfg = sim_config(dir.path(), false);
    cfg.optics.layout = Some(dioptra_rig::config::Layout {
        display_distance_m: 0.25,
        eye_relief_m: 0.015,
        fixed_power_d: 0.0,
    });
    cfg.validate().unwrap();
    let d = Daemon::start_config(cfg).await.unwrap();
    let app = api::router(d.shared().clone());
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.0}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    tokio::time::sleep(Duration::from_millis(200)).await;
    let v = status_of(&d);
    assert_eq!(v["optics"]["source"], "layout", "{v}");
    let close = |x: &Value, want: f64| x.as_f64().is_some_and(|x| (x - want).abs() < 1e-4);
    assert!(close(&v["focus"]["commanded_d"], 1.938144), "{v}");
    assert!(close(&v["focus"]["commanded_focus_d"], 2.0), "{v}");
    // The simulated lens settled there: the focus it gives is the one asked for.
    let lens_focus = v["focus"]["lens_focus_d"].as_f64().unwrap();
    assert!((lens_focus - 2.0).abs() < 0.01, "{v}");
    assert!(v["optics"]["magnification"].as_f64().is_some(), "{v}");
    assert!(close(&v["focus"]["focus_range_d"][1], 4.651163), "{v}");
    // A focus beyond what the lens reaches is refused with the range it does reach.
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 5.0}").await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(v["error"].as_str().unwrap().contains("0..4.65"), "{v}");
    stop(d).await;
}

/// `POST /marker` toggles the marker patch at the next frame where `toggle_on` names
/// "api-marker" (seen here on the simulated panel a simulated photodiode watches), and is
/// refused, naming the key, where the patch would not show it.
#[tokio::test(start_paused = true)]
async fn an_api_marker_toggles_the_patch_once() {
    let dir = tempfile::tempdir().unwrap();
    use dioptra_rig::config::{Corner, MarkerEvent, MarkerPatch, PhotodiodeDevice};
    let with_patch = |toggle_on: MarkerEvent| {
        let mut cfg = sim_config(dir.path(), false);
        cfg.display.marker_patch = Some(MarkerPatch {
            corner: Corner::BottomRight,
            size: 8,
            toggle_on: vec![toggle_on],
        });
        cfg
    };
    let mut cfg = with_patch(MarkerEvent::ApiMarker);
    cfg.devices.photodiode = Some(PhotodiodeDevice {
        driver: dioptra_rig::config::PhotodiodeDriver::SerialLine,
        port: Some(dioptra_rig::config::Port::Sim),
        serial: None,
        threshold: None,
        hysteresis: None,
    });
    cfg.validate().unwrap();
    let d = Daemon::start_config(cfg).await.unwrap();
    let app = api::router(d.shared().clone());
    let panel = d.shared().devices().sims().unwrap().panel.clone().unwrap();
    let whites = |p: &dioptra_sim::panel::SharedPanel| -> Vec<bool> {
        p.lock().refreshes().map(|r| r.white).collect()
    };
    eventually("frames on the panel", || {
        (panel.lock().presents() >= 10).then_some(())
    })
    .await;
    assert!(whites(&panel).iter().all(|w| !w), "black until a marker");
    let before = panel.lock().presents() as usize;
    let (s, v) = call(&app, "POST", "/marker", "").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["markers"], json!(1));
    eventually("the patch white", || {
        (panel.lock().presents() as usize >= before + 10).then_some(())
    })
    .await;
    // From the next present on it stays white: one toggle, not one per frame.
    let w = whites(&panel);
    let first = w.iter().position(|w| *w).expect("never white");
    assert!((before..=before + 2).contains(&first), "{first} {before}");
    assert!(w[first..].iter().all(|w| *w), "{w:?}");
    stop(d).await;

    // A patch toggled on frames, or no patch at all: refused.
    for cfg in [
        with_patch(MarkerEvent::Frame),
        sim_config(dir.path(), false),
    ] {
        let d = Daemon::start_config(cfg).await.unwrap();
        let app = api::router(d.shared().clone());
        let (s, v) = call(&app, "POST", "/marker", "").await;
        assert_eq!(s, StatusCode::CONFLICT, "{v}");
        assert!(
            v["error"]
                .as_str()
                .unwrap()
                .contains("display.marker_patch"),
            "{v}"
        );
        stop(d).await;
    }
}

/// Every duration in `/status` is a number with its unit in its name (issue 39): none comes
/// out as serde's `{"secs", "nanos"}`.
#[tokio::test(start_paused = true)]
async fn status_durations_are_numbers_named_with_their_unit() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let v = after_frames(&d, 3).await;
    fn walk(v: &Value, at: &str, bad: &mut Vec<String>) {
        match v {
            Value::Object(o) => {
                if o.contains_key("secs") || o.contains_key("nanos") {
                    bad.push(at.to_string());
                }
                for (k, x) in o {
                    walk(x, &format!("{at}.{k}"), bad);
                }
            }
            Value::Array(a) => a
                .iter()
                .enumerate()
                .for_each(|(i, x)| walk(x, &format!("{at}[{i}]"), bad)),
            _ => {}
        }
    }
    let mut bad = Vec::new();
    walk(&v, "", &mut bad);
    assert!(bad.is_empty(), "durations as {{secs, nanos}} at {bad:?}");
    assert_eq!(v["device_tasks"]["lens_poll_ms"], json!(10.0), "{v}");
    assert_eq!(v["device_tasks"]["link"]["backoff_min_ms"], json!(100.0));
    stop(d).await;
}

/// Item 4: a required device (a real port, by default) that is not there stops `serve`
/// before it takes commands, naming the key; `required = false` starts without it.
#[tokio::test(start_paused = true)]
async fn a_required_device_that_is_absent_stops_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = sim_config(dir.path(), false);
    cfg.devices.lens.first_mut().port =
        dioptra_rig::config::Port::Path(dir.path().join("ttyACM-missing"));
    let e = match Daemon::start_config(cfg.clone()).await {
        Ok(_) => panic!("started without its required lens"),
        Err(e) => format!("{e:#}"),
    };
    assert!(
        e.contains("devices.lens.port") && e.contains("ttyACM-missing"),
        "{e}"
    );
    assert!(e.contains("devices.lens.required"), "{e}");
    cfg.devices.lens.first_mut().required = Some(false);
    let d = Daemon::start_config(cfg).await.unwrap();
    d.cancel_token().cancel();
    // It could not park a lens it never reached, and says so.
    assert!(!d.wait().await.ok());
}

/// Item 4: while a required lens is down, `POST /focus` answers 503 with why (the focus
/// would not be shown); handing focus back to gaze still works; once the lens is back,
/// focus works again.
#[tokio::test(start_paused = true)]
async fn while_a_required_lens_is_down_focus_answers_503() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = sim_config(dir.path(), false);
    cfg.devices.lens.first_mut().required = Some(true);
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    let state = || {
        sh.devices()
            .registry()
            .snapshot()
            .get("lens")
            .map(|s| s.state)
    };
    // A required device is up before the daemon takes commands.
    assert_eq!(state(), Some(State::Ok));
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 1.0}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(&app, "POST", "/sim/lens/unplug", "").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    eventually("the lens to be lost", || {
        (state() == Some(State::Lost)).then_some(())
    })
    .await;
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.0}").await;
    assert_eq!(s, StatusCode::SERVICE_UNAVAILABLE, "{v}");
    assert_eq!(v["key"], json!("diopters"));
    let err = v["error"].as_str().unwrap();
    assert!(
        err.contains("devices.lens") && err.contains("lost"),
        "{err}"
    );
    assert_eq!(status_of(&d)["focus"]["manual_d"], json!(1.0));
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": null}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(&app, "POST", "/sim/lens/replug", "").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    eventually("the lens to reconnect", || {
        (state() == Some(State::Ok)).then_some(())
    })
    .await;
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.0}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    stop(d).await;
}

/// Items 6 and 7: a negative trial and a focus body without `diopters` are refused, saying
/// what is expected.
#[tokio::test(start_paused = true)]
async fn a_bad_trial_and_a_focus_without_diopters_are_refused_with_the_fix() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let app = api::router(d.shared().clone());
    for (path, body, key, words) in [
        (
            "/recording/start",
            "{\"trial\": -1}",
            "trial",
            "a trial number",
        ),
        ("/recording/start", "{\"trial\": 2.5}", "trial", "0 or more"),
        ("/focus", "{}", "diopters", "diopters is required"),
    ] {
        let (s, v) = call(&app, "POST", path, body).await;
        assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{body}: {v}");
        assert_eq!(v["key"], json!(key), "{body}: {v}");
        let err = v["error"].as_str().unwrap();
        assert!(err.contains(words) && !err.contains("untagged"), "{err}");
    }
    assert!(status_of(&d)["recording"].is_null());
    let (s, v) = call(&app, "POST", "/recording/start", "{\"trial\": \"3b\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert!(v["recording"].as_str().unwrap().ends_with("-trial-3b.mcap"));
    let (s, _) = call(&app, "POST", "/recording/stop", "").await;
    assert_eq!(s, StatusCode::OK);
    stop(d).await;
}

/// The next `/stream` message of `type` (within 20 s of simulated time).
async fn next_of(rx: &mut tokio::sync::broadcast::Receiver<Arc<str>>, kind: &str) -> Value {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let m = tokio::time::timeout_at(deadline, rx.recv())
            .await
            .unwrap_or_else(|_| panic!("no {kind} message within 20 s"));
        let Ok(text) = m else { continue };
        let v: Value = serde_json::from_str(&text).unwrap();
        if v["type"] == json!(kind) {
            return v;
        }
    }
}

/// `POST /marker`: recorded (`/marker`), streamed, stamped with the host time it returns;
/// anything but a text or an object is refused.
#[tokio::test(start_paused = true)]
async fn a_marker_is_recorded_and_streamed_with_its_host_time() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    for body in [
        "{\"marker\": 3}",
        "{\"marker\": \"\"}",
        "{\"marker\": [1]}",
        "{\"marker\": null}",
        "{}",
    ] {
        let (s, v) = call(&app, "POST", "/marker", body).await;
        assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{body}: {v}");
    }
    let long = format!("{{\"marker\": \"{}\"}}", "x".repeat(1025));
    let (s, _) = call(&app, "POST", "/marker", &long).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY);
    let (s, v) = call(&app, "POST", "/recording/start", "{\"trial\": 1}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let path = v["recording"].as_str().unwrap().to_string();
    let mut rx = sh.websocket().subscribe();
    let (s, v) = call(&app, "POST", "/marker", "{\"marker\": \"stimulus_on\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let t1 = v["host_ns"].as_u64().unwrap();
    let streamed = next_of(&mut rx, "marker").await;
    assert_eq!(streamed["marker"], json!("stimulus_on"));
    assert_eq!(streamed["host_ns"], json!(t1));
    let (s, v) = call(
        &app,
        "POST",
        "/marker",
        "{\"marker\": {\"event\": \"response\", \"key\": \"left\"}}",
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let t2 = v["host_ns"].as_u64().unwrap();
    assert!(t2 >= t1);
    let (s, _) = call(&app, "POST", "/recording/stop", "").await;
    assert_eq!(s, StatusCode::OK);
    let rec = dioptra_rig::recording::read(Path::new(&path)).unwrap();
    let markers: Vec<_> = rec
        .messages
        .iter()
        .filter_map(|(t, r)| match r {
            dioptra_rig::recording::Rec::Marker(m) => Some((t.0, m.marker.clone())),
            _ => None,
        })
        .collect();
    assert_eq!(
        markers,
        [
            (t1, json!("stimulus_on")),
            (t2, json!({"event": "response", "key": "left"}))
        ]
    );
    stop(d).await;
}

/// `/stream` carries full gaze (pupil, eye position, phase, vergence) and lens read-backs
/// with their target and whether the lens settled there; a manual focus ends with a
/// read-back settled at it.
#[tokio::test(start_paused = true)]
async fn the_stream_has_full_gaze_and_lens_targets_and_settling() {
    let dir = tempfile::tempdir().unwrap();
    let d = Daemon::start_config(sim_config(dir.path(), false))
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    let mut rx = sh.websocket().subscribe();
    let g = next_of(&mut rx, "gaze").await;
    for eye in ["left", "right"] {
        assert_eq!(g[eye]["direction"].as_array().map(Vec::len), Some(3), "{g}");
        assert_eq!(g[eye]["origin_mm"].as_array().map(Vec::len), Some(3), "{g}");
        assert!(g[eye]["pupil_mm"].as_f64().unwrap() > 1.0, "{g}");
        assert!(g[eye]["valid"].is_boolean(), "{g}");
    }
    assert!(g["phase"].is_string() && g["device_ns"].is_u64(), "{g}");
    assert!(g.get("vergence_d").is_some(), "{g}");
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 2.5}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    // Read-backs on the way carry the new target; the lens gets there and says so.
    let settled = loop {
        let l = next_of(&mut rx, "lens").await;
        assert!(l["power_d"].is_f64(), "{l}");
        if l["target_d"] == json!(2.5) && l["settled"] == json!(true) {
            break l;
        }
    };
    assert!((settled["power_d"].as_f64().unwrap() - 2.5).abs() < 0.02);
    assert_eq!(status_of(&d)["focus"]["lens_settled"], json!(true));
    stop(d).await;
}

/// Items 8 and 9: multifocal mode holds the varifocal lens inside its range, frame messages
/// carry each layer's plane, `/focus` says what it does there, and the way out of
/// multifocal is direct (any mode; the methods it refuses are 409 like the rest).
#[tokio::test(start_paused = true)]
async fn multifocal_mode_says_what_it_shows_and_lets_the_rig_out() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = sim_config(dir.path(), false);
    cfg.mode = dioptra_rig::config::Mode::Multifocal;
    cfg.method = dioptra_rig::config::Method(dioptra_sched::RenderMethod::Linear);
    let planes = cfg.optics.planes.clone();
    let range = cfg.optics.lens_range;
    let d = Daemon::start_config(cfg).await.unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    let mut rx = sh.websocket().subscribe();
    let mut layers = std::collections::BTreeSet::new();
    while layers.len() < planes.len() {
        let f = next_of(&mut rx, "frame").await;
        let layer = f["layer"].as_u64().expect("a layer") as usize;
        assert_eq!(f["focus_d"].as_f64().unwrap() as f32, planes[layer], "{f}");
        layers.insert(layer);
    }
    let sub = next_of(&mut rx, "subframe").await;
    let plane = sub["plane"].as_u64().unwrap() as usize;
    assert_eq!(
        sub["plane_d"].as_f64().unwrap() as f32,
        planes[plane],
        "{sub}"
    );
    let lens = eventually("a lens read-back", || {
        status_of(&d)["focus"]["lens_d"].as_f64()
    })
    .await as f32;
    assert!(
        (range.min - 0.03..=range.max + 0.03).contains(&lens),
        "{lens} D outside {range:?}"
    );
    let v = status_of(&d);
    assert!(v["subframes"]["lens_measured_by"]
        .as_str()
        .unwrap()
        .contains("sync board"));
    let (s, v) = call(&app, "POST", "/focus", "{\"diopters\": 1.0}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert!(v["effect"].as_str().unwrap().contains("planes"), "{v}");
    for m in ["gather", "auto", "views"] {
        let (s, v) = call(&app, "POST", "/method", &format!("{{\"method\": \"{m}\"}}")).await;
        assert_eq!(s, StatusCode::CONFLICT, "{m}: {v}");
        assert!(v["error"].as_str().unwrap().contains("POST /mode"), "{v}");
    }
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"lightfield\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["method"], json!("views"));
    stop(d).await;
}

/// Item 8 with the network: from multifocal (C4), light-field mode is one request away
/// (it renders views: the daemon does not run C5), not a 409.
#[tokio::test(start_paused = true)]
async fn from_multifocal_with_the_network_lightfield_is_one_step() {
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("weights");
    random_weights(&weights);
    let mut cfg = network_config(dir.path(), &weights);
    cfg.mode = dioptra_rig::config::Mode::Multifocal;
    let d = Daemon::start_config(cfg).await.unwrap();
    let app = api::router(d.shared().clone());
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"lightfield\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["method"], json!("views"));
    let (s, v) = call(&app, "POST", "/mode", "{\"mode\": \"multifocal\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(&app, "POST", "/method", "{\"method\": \"network\"}").await;
    assert_eq!(s, StatusCode::OK, "{v}");
    stop(d).await;
}

/// `PUT /frame` on the binocular example rig (side by side, 96 x 96 per eye): each eye's half
/// of a pair (`eye=`, `seq=`) is shown only once its partner arrived, a late half is dropped
/// when a newer pair completes and refused after, a 192-wide frame carries both eyes; bad eyes
/// and sizes are refused with the reason and counted; on a mono rig `eye` is refused.
#[tokio::test(start_paused = true)]
async fn stereo_frames_are_paired_by_sequence_number_and_refused_with_reasons() {
    let dir = tempfile::tempdir().unwrap();
    let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
        .replace("127.0.0.1:7420", "127.0.0.1:0")
        .replace("[recording]\ndir = \"recordings\"\nstart = false\n", "")
        + "\n[content]\nsource = \"stream\"\nring = \"none\"\n";
    let d = Daemon::start_config(RigConfig::parse(&text).unwrap())
        .await
        .unwrap();
    let sh = d.shared().clone();
    let app = api::router(sh.clone());
    let content = || sh.status_json()["content"].clone();
    let octets = "application/octet-stream";
    let frame = |w: usize, v: u8| {
        [
            vec![v; w * 96 * 3],
            f32_bytes(&vec![0.5 + f32::from(v) / 255.0; w * 96]),
        ]
        .concat()
    };
    let put = |w: usize, q: &str, v: u8| {
        let app = app.clone();
        let path = format!("/frame?width={w}&height=96&color=rgb8&depth=m{q}");
        async move { call_with(&app, "PUT", &path, octets, frame(w, v)).await }
    };
    let shown = |seq: u64| {
        eventually("the pair on show", move || {
            (content()["on_show_seq"] == json!(seq)).then_some(())
        })
    };
    let (s, v) = put(96, "&eye=left&seq=1", 10).await;
    assert_eq!((s, &v["seq"]), (StatusCode::OK, &json!(1)), "{v}");
    let c = content();
    assert_eq!(
        (&c["stereo"], &c["halves_waiting"], &c["received"]),
        (&json!(true), &json!(1), &json!(0)),
        "{c}"
    );
    let frames = sh.status_json()["counts"]["frames_shown"].as_u64().unwrap();
    let (s, v) = put(96, "&eye=right&seq=1", 20).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    shown(1).await;
    // A late half: right 2 never comes before pair 3 completes.
    for q in ["&eye=left&seq=2", "&eye=left&seq=3", "&eye=right&seq=3"] {
        let (s, v) = put(96, q, 30).await;
        assert_eq!(s, StatusCode::OK, "{q}: {v}");
    }
    shown(3).await;
    assert_eq!(content()["halves_dropped"], json!(1));
    let (s, v) = put(96, "&eye=right&seq=2", 40).await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    assert!(
        v["error"]
            .as_str()
            .unwrap()
            .contains("right eye's sequence number 2"),
        "{v}"
    );
    // Both eyes side by side in one frame.
    let (s, v) = put(192, "&seq=4", 50).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    shown(4).await;
    // Refusals: (query, width, status, reason counted, words).
    for (q, w, status, reason, words) in [
        (
            "&eye=middle&seq=5",
            96,
            422,
            "eye",
            "eye=\"middle\": expected left or right",
        ),
        (
            "&eye=left",
            96,
            422,
            "request",
            "needs its sequence number (seq=N)",
        ),
        (
            "&eye=left&seq=5",
            192,
            422,
            "wrong_size",
            "left eye's frame is 192x96; one eye's image is 96x96",
        ),
        (
            "&seq=5",
            95,
            422,
            "wrong_size",
            "or 192x96 for both eyes side by side",
        ),
    ] {
        let before = content();
        let (s, v) = put(w, q, 60).await;
        assert_eq!(s.as_u16(), status, "{q}: {v}");
        let msg = v["error"].as_str().unwrap_or_default();
        assert!(msg.contains(words), "{q}: {msg:?} lacks {words:?}");
        let count = |c: &Value| c["refused"][reason].as_u64().unwrap_or(0);
        assert_eq!(count(&content()), count(&before) + 1, "{reason}");
        assert_eq!(content()["on_show_seq"], json!(4), "the pair on show stays");
    }
    let c = content();
    assert_eq!(
        (&c["received"], &c["halves_received"], &c["halves_waiting"]),
        (&json!(3), &json!(5), &json!(0)),
        "{c}"
    );
    // The pairs were rendered, each eye its own image.
    let v = eventually("frames of the pairs", || {
        let v = sh.status_json();
        (v["counts"]["frames_shown"].as_u64() > Some(frames + 3)).then_some(v)
    })
    .await;
    assert_eq!(v["counts"]["render_errors"], json!(0), "{v}");
    stop(d).await;

    // On a mono rig an eye is refused.
    let (d, sh, app) = stream_daemon(dir.path()).await;
    let path = "/frame?width=96&height=96&color=rgb8&depth=m&eye=left&seq=1";
    let (s, v) = call_with(&app, "PUT", path, octets, frame(96, 1)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(
        v["error"]
            .as_str()
            .unwrap()
            .contains("display.layout = \"one\""),
        "{v}"
    );
    assert_eq!(sh.status_json()["content"]["refused"]["eye"], json!(1));
    stop(d).await;
}

/// The done-when of the binocular issue: `dioptra serve` on the binocular example rig shows
/// side-by-side stereo frames (one 192 x 96 panel, the left eye's 96 x 96 image in its left
/// half) from the procedural scene, a lab's stereo files and a stream's pairs, each eye's
/// image in its own half.
#[tokio::test(start_paused = true)]
async fn the_binocular_rig_shows_side_by_side_stereo_from_the_scene_files_and_stream() {
    let dir = tempfile::tempdir().unwrap();
    let rig = |content: &str, frames: &Path| {
        let text = dioptra_rig::config::EXAMPLE_SIM_BINOCULAR_RIG
            .replace("127.0.0.1:7420", "127.0.0.1:0")
            .replace("[recording]\ndir = \"recordings\"\nstart = false\n", "")
            .replace(
                "frame_hz = 60.0",
                &format!(
                    "frame_hz = 60.0\npng_every = 1\npng_dir = {:?}",
                    frames.display().to_string()
                ),
            )
            + content;
        RigConfig::parse(&text).unwrap()
    };
    // The newest panel written, once the rig has shown `n` more frames.
    let newest_panel = |frames: &Path| {
        let mut pngs: Vec<_> = std::fs::read_dir(frames)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        pngs.sort();
        dioptra_render::io::read_color(pngs.last().expect("a panel written")).unwrap()
    };
    let halves = |panel: &dioptra_core::RgbImage, x: usize| {
        (
            panel.pixel(x, 48).unwrap(),
            panel.pixel(96 + x, 48).unwrap(),
        )
    };

    // The scene, each eye ray cast from its own place: the halves differ.
    let frames = dir.path().join("scene");
    let d = Daemon::start_config(rig("\n[content]\nanimate = false\n", &frames))
        .await
        .unwrap();
    after_frames(&d, 4).await;
    let v = status_of(&d);
    assert_eq!(v["eye_views"]["source"], json!("scene-ray-cast"), "{v}");
    stop(d).await;
    let panel = newest_panel(&frames);
    assert_eq!((panel.width(), panel.height()), (192, 96));
    let diff: f32 = (0..96)
        .flat_map(|y| (0..96).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (l, r) = (panel.pixel(x, y).unwrap(), panel.pixel(96 + x, y).unwrap());
            (0..3).map(|c| (l[c] - r[c]).abs()).sum::<f32>()
        })
        .sum::<f32>()
        / (96.0 * 96.0 * 3.0);
    assert!(
        diff > 0.02,
        "the eyes' views differ: mean |left - right| {diff}"
    );

    // Stereo files: a red left eye, a blue right eye, 1 m away.
    let stim = dir.path().join("stim");
    for (eye, rgb) in [("left", [0.8, 0.1, 0.1]), ("right", [0.1, 0.1, 0.8])] {
        std::fs::create_dir_all(stim.join(eye)).unwrap();
        let c = dioptra_core::RgbImage::new(96, 96, rgb);
        let depth = dioptra_core::DepthMap::from_meters(96, 96, &[1.0; 96 * 96]).unwrap();
        dioptra_render::io::write_color(&stim.join(format!("{eye}/c.exr")), &c).unwrap();
        dioptra_render::io::write_depth(&stim.join(format!("{eye}/d.exr")), &depth).unwrap();
    }
    let frames = dir.path().join("files");
    let files = format!(
        "\n[content]\nsource = \"files\"\ncolor = {:?}\ndepth = {:?}\n",
        stim.join("%e/c.exr").display().to_string(),
        stim.join("%e/d.exr").display().to_string()
    );
    let d = Daemon::start_config(rig(&files, &frames)).await.unwrap();
    after_frames(&d, 4).await;
    assert_eq!(status_of(&d)["eye_views"]["source"], json!("stereo"));
    stop(d).await;
    let (l, r) = halves(&newest_panel(&frames), 48);
    assert!(
        l[0] > 0.5 && l[2] < 0.3 && r[2] > 0.5 && r[0] < 0.3,
        "{l:?} {r:?}"
    );

    // The stream: a green left half and a magenta right half of one sequence number.
    let frames = dir.path().join("stream");
    let d = Daemon::start_config(rig(
        "\n[content]\nsource = \"stream\"\nring = \"none\"\n",
        &frames,
    ))
    .await
    .unwrap();
    let app = api::router(d.shared().clone());
    for (eye, rgb) in [("left", [20u8, 220, 20]), ("right", [220, 20, 220])] {
        let color: Vec<u8> = (0..96 * 96).flat_map(|_| rgb).collect();
        let body = [color, f32_bytes(&[1.0; 96 * 96])].concat();
        let path = format!("/frame?width=96&height=96&color=rgb8&depth=m&eye={eye}&seq=1");
        let (s, v) = call_with(&app, "PUT", &path, "application/octet-stream", body).await;
        assert_eq!(s, StatusCode::OK, "{v}");
    }
    eventually("the pair on show", || {
        (status_of(&d)["content"]["on_show_seq"] == json!(1)).then_some(())
    })
    .await;
    after_frames(&d, 4).await;
    stop(d).await;
    let (l, r) = halves(&newest_panel(&frames), 48);
    assert!(
        l[1] > 0.5 && l[0] < 0.3 && r[0] > 0.5 && r[1] < 0.3,
        "{l:?} {r:?}"
    );
}
