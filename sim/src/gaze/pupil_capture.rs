//! A simulated Pupil Capture on loopback TCP, speaking its network API with real ZeroMQ
//! sockets: Pupil Remote (REP, on the given port or any), the IPC backbone's publisher
//! (PUB: what `SUB_PORT` names, where clients subscribe) and its subscriber (SUB: what
//! `PUB_PORT` names, where clients publish into Capture). The gaze it publishes comes from a
//! [`SampleSource`] (the eye-movement generator): binocular `gaze.3d.01.` datums while both
//! eyes are seen, monocular `gaze.3d.0.` / `gaze.3d.1.` while one is, and low-confidence
//! binocular datums while neither is (a blink), with the pupil datums of `base_data`.
//!
//! Payloads are msgpack maps written here with rmp-serde from this module's own structs
//! (never the driver's code), in Pupil's world-camera frame: x right, y down, z forward, mm.
//! Eye 0 is the right eye, eye 1 the left. Time is Pupil time: its own base (seconds since
//! the simulator started plus [`PupilCaptureConfig::pupil_time_at_start_s`]), which
//! Pupil Remote's `T <seconds>` resets as Capture's does.
//!
//! Pupil Remote answers what Capture's `pupil_remote.py` answers: `SUB_PORT`, `PUB_PORT`,
//! `t`, `T <s>`, `v`, `R [name]`, `r`, `C`, `c`, a multipart message (forwarded onto the
//! backbone: "Message forwarded."), and "Unknown command." to anything else.

use std::collections::BTreeMap;
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpListener};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::{sleep_until, Instant};
use zeromq::{PubSocket, RepSocket, Socket, SocketRecv, SocketSend, SubSocket, ZmqMessage};

use super::{lock, SampleSource};
use dioptra_protocol::{BinocularSample, EyeSample};

/// How the simulated Capture is set up.
#[derive(Debug, Clone, PartialEq)]
pub struct PupilCaptureConfig {
    /// Interface to bind (loopback by default).
    pub host: IpAddr,
    /// Pupil Remote's port; 0 binds any free port.
    pub remote_port: u16,
    /// Pupil time when the simulator starts, s: an arbitrary base, as Capture's is.
    pub pupil_time_at_start_s: f64,
    /// What `v` answers.
    pub version: String,
    /// Confidence of a datum whose eyes were seen (Capture's is 0 to 1).
    pub confidence: f64,
    /// From exposure to publication (Capture's detection and mapping), ms.
    pub latency_ms: f64,
}

impl Default for PupilCaptureConfig {
    fn default() -> Self {
        PupilCaptureConfig {
            host: IpAddr::V4(Ipv4Addr::LOCALHOST),
            remote_port: 0,
            pupil_time_at_start_s: 3_000.0,
            version: "3.5.1".into(),
            confidence: 0.95,
            latency_ms: 4.0,
        }
    }
}

/// What a test can make the simulated Capture do wrong.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CaptureFaults {
    /// Publish no gaze (eye processes stopped).
    pub silent: bool,
    /// Pupil Remote takes requests and never answers.
    pub remote_mute: bool,
}

/// State shared by the simulator's tasks.
struct Shared {
    start: Instant,
    /// Pupil time at `start`, s (moved by `T`).
    base_s: f64,
    faults: CaptureFaults,
    published: u64,
    requests: Vec<String>,
}

impl Shared {
    fn pupil_time(&self, at: Instant) -> f64 {
        self.base_s + at.saturating_duration_since(self.start).as_secs_f64()
    }
}

/// A running simulated Pupil Capture. Dropping it stops it (its ports close shortly after);
/// [`PupilCaptureSim::shutdown`] waits until they are closed.
pub struct PupilCaptureSim {
    remote: SocketAddr,
    sub_port: u16,
    pub_port: u16,
    shared: Arc<Mutex<Shared>>,
    stop: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for PupilCaptureSim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PupilCaptureSim")
            .field("remote", &self.remote)
            .field("sub_port", &self.sub_port)
            .field("pub_port", &self.pub_port)
            .finish_non_exhaustive()
    }
}

impl PupilCaptureSim {
    /// Binds the three ports now (so they are known when this returns) and serves them on
    /// tasks of the current tokio runtime. Errors: a port is taken, or no runtime.
    pub fn spawn(
        cfg: PupilCaptureConfig,
        source: Box<dyn SampleSource>,
    ) -> std::io::Result<PupilCaptureSim> {
        let runtime = tokio::runtime::Handle::try_current()
            .map_err(|e| std::io::Error::other(format!("no tokio runtime: {e}")))?;
        let remote_l = TcpListener::bind((cfg.host, cfg.remote_port))?;
        let publisher_l = TcpListener::bind((cfg.host, 0))?;
        let subscriber_l = TcpListener::bind((cfg.host, 0))?;
        let remote = remote_l.local_addr()?;
        let sub_port = publisher_l.local_addr()?.port();
        let pub_port = subscriber_l.local_addr()?.port();
        let shared = Arc::new(Mutex::new(Shared {
            start: Instant::now(),
            base_s: cfg.pupil_time_at_start_s,
            faults: CaptureFaults::default(),
            published: 0,
            requests: Vec::new(),
        }));
        let (stop, stopped) = watch::channel(false);
        // Everything goes out through the one PUB task: gaze, forwarded messages, notifications.
        let (to_backbone, backbone) = mpsc::channel::<ZmqMessage>(1024);
        let ports = Ports { sub_port, pub_port };
        let tasks = vec![
            runtime.spawn(serve_publisher(
                publisher_l,
                backbone,
                source,
                cfg.clone(),
                shared.clone(),
                stopped.clone(),
            )),
            runtime.spawn(serve_remote(
                remote_l,
                cfg,
                ports,
                shared.clone(),
                to_backbone.clone(),
                stopped.clone(),
            )),
            runtime.spawn(serve_subscriber(subscriber_l, to_backbone, stopped)),
        ];
        Ok(PupilCaptureSim {
            remote,
            sub_port,
            pub_port,
            shared,
            stop,
            tasks,
        })
    }

    /// Pupil Remote's address ("127.0.0.1:PORT").
    pub fn remote_addr(&self) -> SocketAddr {
        self.remote
    }
    /// The IPC publisher's port (`SUB_PORT`'s answer).
    pub fn sub_port(&self) -> u16 {
        self.sub_port
    }
    /// The IPC subscriber's port (`PUB_PORT`'s answer).
    pub fn pub_port(&self) -> u16 {
        self.pub_port
    }
    /// Pupil time now, s.
    pub fn pupil_time(&self) -> f64 {
        lock(&self.shared).pupil_time(Instant::now())
    }
    /// Gaze datums published so far.
    pub fn published(&self) -> u64 {
        lock(&self.shared).published
    }
    /// Every Pupil Remote request so far, as text (multipart: the first frame).
    pub fn requests(&self) -> Vec<String> {
        lock(&self.shared).requests.clone()
    }
    pub fn set_faults(&self, faults: CaptureFaults) {
        lock(&self.shared).faults = faults;
    }

    /// Stops serving and waits until the ports are closed.
    pub async fn shutdown(mut self) {
        let _ = self.stop.send(true);
        for t in self.tasks.drain(..) {
            let _ = t.await;
        }
    }
}

impl Drop for PupilCaptureSim {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
        for t in &self.tasks {
            t.abort();
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Ports {
    sub_port: u16,
    pub_port: u16,
}

/// Waits until the simulator is told to stop.
async fn stopped(mut rx: watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

async fn serve_remote(
    listener: TcpListener,
    cfg: PupilCaptureConfig,
    ports: Ports,
    shared: Arc<Mutex<Shared>>,
    backbone: mpsc::Sender<ZmqMessage>,
    stop: watch::Receiver<bool>,
) {
    let mut rep = RepSocket::new();
    if rep.bind_listener(listener).await.is_err() {
        return;
    }
    loop {
        let msg = tokio::select! {
            _ = stopped(stop.clone()) => break,
            m = rep.recv() => m,
        };
        let Ok(msg) = msg else {
            // A peer that broke mid-request; the socket serves the others.
            tokio::time::sleep(Duration::from_millis(1)).await;
            continue;
        };
        let frames = msg.into_vec();
        let first = frames
            .first()
            .map(|f| String::from_utf8_lossy(f).into_owned())
            .unwrap_or_default();
        let mute = {
            let mut s = lock(&shared);
            s.requests.push(first.clone());
            s.faults.remote_mute
        };
        if mute {
            // A REP that never answers: the client's request times out.
            stopped(stop.clone()).await;
            break;
        }
        let reply = if frames.len() > 1 {
            let mut fwd = ZmqMessage::from(frames[0].clone());
            for f in &frames[1..] {
                fwd.push_back(f.clone());
            }
            let _ = backbone.try_send(fwd);
            "Message forwarded.".to_string()
        } else {
            answer(&first, &cfg, ports, &shared, &backbone)
        };
        if rep.send(ZmqMessage::from(reply)).await.is_err() {
            continue;
        }
    }
    let _ = rep.close().await;
}

/// Pupil Remote's answer to a one-frame request, in the order Capture tests for them.
fn answer(
    msg: &str,
    cfg: &PupilCaptureConfig,
    ports: Ports,
    shared: &Mutex<Shared>,
    backbone: &mpsc::Sender<ZmqMessage>,
) -> String {
    let notify = |subject: &str, extra: Option<(&str, &str)>| {
        if let Some(m) = notification(subject, extra) {
            let _ = backbone.try_send(m);
        }
    };
    match msg {
        "SUB_PORT" => return ports.sub_port.to_string(),
        "PUB_PORT" => return ports.pub_port.to_string(),
        "C" => {
            notify("calibration.should_start", None);
            return "OK".into();
        }
        "c" => {
            notify("calibration.should_stop", None);
            return "OK".into();
        }
        _ => {}
    }
    match msg.chars().next() {
        Some('R') => {
            notify(
                "recording.should_start",
                Some(("session_name", msg.get(2..).unwrap_or(""))),
            );
            "OK".into()
        }
        Some('r') => {
            notify("recording.should_stop", None);
            "OK".into()
        }
        Some('T') => {
            let arg = msg.get(2..).unwrap_or("");
            match arg.trim().parse::<f64>() {
                Ok(target) if target.is_finite() => {
                    let mut s = lock(shared);
                    let elapsed = Instant::now()
                        .saturating_duration_since(s.start)
                        .as_secs_f64();
                    s.base_s = target - elapsed;
                    "Timesync successful.".into()
                }
                _ => format!("'{arg}' cannot be converted to float."),
            }
        }
        Some('t') => python_float_repr(lock(shared).pupil_time(Instant::now())),
        Some('v') => cfg.version.clone(),
        _ => "Unknown command.".into(),
    }
}

/// A float as Python's `repr` writes it in the range Pupil time takes ("12.0", "3000.25").
fn python_float_repr(x: f64) -> String {
    let s = format!("{x}");
    if s.contains(['.', 'e', 'n', 'N']) {
        s
    } else {
        s + ".0"
    }
}

#[derive(Serialize)]
struct Notification<'a> {
    topic: String,
    subject: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    session_name: Option<&'a str>,
}

/// A notification as Capture puts it on the backbone: topic "notify.<subject>".
fn notification(subject: &str, extra: Option<(&str, &str)>) -> Option<ZmqMessage> {
    let topic = format!("notify.{subject}");
    let payload = rmp_serde::to_vec_named(&Notification {
        topic: topic.clone(),
        subject,
        session_name: extra.map(|(_, v)| v),
    })
    .ok()?;
    let mut m = ZmqMessage::from(topic);
    m.push_back(payload.into());
    Some(m)
}

/// The IPC subscriber (`PUB_PORT`): what clients publish into Capture goes onto the backbone.
async fn serve_subscriber(
    listener: TcpListener,
    backbone: mpsc::Sender<ZmqMessage>,
    stop: watch::Receiver<bool>,
) {
    let mut sub = SubSocket::new();
    if sub.bind_listener(listener).await.is_err() || sub.subscribe("").await.is_err() {
        return;
    }
    loop {
        tokio::select! {
            _ = stopped(stop.clone()) => break,
            m = sub.recv() => match m {
                Ok(m) => { let _ = backbone.try_send(m); }
                Err(_) => tokio::time::sleep(Duration::from_millis(1)).await,
            },
        }
    }
    let _ = sub.close().await;
}

/// The IPC publisher: gaze at each sample's time, and whatever else reaches the backbone.
async fn serve_publisher(
    listener: TcpListener,
    mut backbone: mpsc::Receiver<ZmqMessage>,
    mut source: Box<dyn SampleSource>,
    cfg: PupilCaptureConfig,
    shared: Arc<Mutex<Shared>>,
    stop: watch::Receiver<bool>,
) {
    let mut publisher = PubSocket::new();
    if publisher.bind_listener(listener).await.is_err() {
        return;
    }
    let start = lock(&shared).start;
    let latency = Duration::from_secs_f64(cfg.latency_ms.max(0.0) / 1000.0);
    let mut eyes = LastSeen::default();
    let mut next = source.next_sample();
    loop {
        let due = next.as_ref().and_then(|(t_us, _)| {
            start.checked_add(Duration::from_micros(*t_us).saturating_add(latency))
        });
        let wake = async {
            match due {
                Some(at) => sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        let out = tokio::select! {
            _ = stopped(stop.clone()) => break,
            m = backbone.recv() => match m {
                Some(m) => m,
                None => continue,
            },
            _ = wake => {
                let Some((t_us, sample)) = next.take() else { continue };
                next = source.next_sample();
                let (base_s, silent) = {
                    let s = lock(&shared);
                    (s.base_s, s.faults.silent)
                };
                if silent {
                    continue;
                }
                let timestamp = base_s + t_us as f64 / 1e6;
                let Some(m) = gaze_message(&sample, timestamp, cfg.confidence, &mut eyes) else {
                    continue;
                };
                lock(&shared).published += 1;
                m
            }
        };
        if publisher.send(out).await.is_err() {
            break;
        }
    }
    let _ = publisher.close().await;
}

/// Each eye's last seen ray, in Pupil's frame, for datums sent while it is not seen.
#[derive(Debug, Clone, Copy)]
struct LastSeen {
    eyes: [([f64; 3], [f64; 3]); 2],
}

impl Default for LastSeen {
    fn default() -> Self {
        LastSeen {
            eyes: [
                ([-32.0, 0.0, -20.0], [0.0, 0.0, 1.0]),
                ([32.0, 0.0, -20.0], [0.0, 0.0, 1.0]),
            ],
        }
    }
}

/// dioptra's head frame (y up) to Pupil's world camera (y down).
fn to_pupil_frame(v: [f32; 3]) -> [f64; 3] {
    [f64::from(v[0]), -f64::from(v[1]), f64::from(v[2])]
}

/// Whether an eye was seen, and its ray in Pupil's frame (the last seen one if not).
fn pupil_eye(e: &EyeSample, last: &mut ([f64; 3], [f64; 3])) -> bool {
    let finite = e
        .origin_mm
        .iter()
        .chain(&e.direction)
        .all(|v| v.is_finite());
    let seen = e.valid && finite;
    if seen {
        *last = (to_pupil_frame(e.origin_mm), to_pupil_frame(e.direction));
    }
    seen
}

#[derive(Serialize)]
struct Ellipse {
    center: [f64; 2],
    axes: [f64; 2],
    angle: f64,
}

#[derive(Serialize)]
struct Sphere {
    center: [f64; 3],
    radius: f64,
}

#[derive(Serialize)]
struct Circle3d {
    center: [f64; 3],
    normal: [f64; 3],
    radius: f64,
}

/// A pupil datum (`pupil.<id>.3d`, from the 3D detector), as `base_data` carries it.
#[derive(Serialize)]
struct PupilDatum {
    topic: String,
    id: u8,
    method: &'static str,
    timestamp: f64,
    confidence: f64,
    norm_pos: [f64; 2],
    diameter: f64,
    diameter_3d: f64,
    ellipse: Ellipse,
    sphere: Sphere,
    circle_3d: Circle3d,
    theta: f64,
    phi: f64,
    model_confidence: f64,
}

#[derive(Serialize)]
struct BinocularGaze {
    topic: &'static str,
    eye_centers_3d: BTreeMap<&'static str, [f64; 3]>,
    gaze_normals_3d: BTreeMap<&'static str, [f64; 3]>,
    gaze_point_3d: [f64; 3],
    norm_pos: [f64; 2],
    confidence: f64,
    timestamp: f64,
    base_data: Vec<PupilDatum>,
}

#[derive(Serialize)]
struct MonocularGaze {
    topic: &'static str,
    eye_center_3d: [f64; 3],
    gaze_normal_3d: [f64; 3],
    gaze_point_3d: [f64; 3],
    norm_pos: [f64; 2],
    confidence: f64,
    timestamp: f64,
    base_data: Vec<PupilDatum>,
}

fn pupil_datum(id: u8, eye: &([f64; 3], [f64; 3]), pupil_mm: f32, t: f64, conf: f64) -> PupilDatum {
    // A pupil datum is in its eye camera's frame: only the direction carries over.
    let normal = eye.1;
    let diameter_3d = if pupil_mm.is_finite() && pupil_mm > 0.0 {
        f64::from(pupil_mm)
    } else {
        4.0
    };
    // In the eye camera's frame the eye sits ~35 mm in front of it; a 192x192 image.
    let theta = normal[1].clamp(-1.0, 1.0).acos();
    let phi = normal[2].atan2(normal[0]);
    let norm = [0.5 + normal[0] * 0.3, 0.5 - normal[1] * 0.3];
    PupilDatum {
        topic: format!("pupil.{id}.3d"),
        id,
        method: "pye3d 0.3.0 real-time",
        timestamp: t,
        confidence: conf,
        norm_pos: norm,
        diameter: diameter_3d * 8.0,
        diameter_3d,
        ellipse: Ellipse {
            center: [norm[0] * 192.0, (1.0 - norm[1]) * 192.0],
            axes: [diameter_3d * 7.0, diameter_3d * 8.0],
            angle: 90.0,
        },
        sphere: Sphere {
            center: [0.0, 0.0, 35.0],
            radius: 10.39,
        },
        circle_3d: Circle3d {
            center: [
                normal[0] * 10.39,
                normal[1] * 10.39,
                35.0 - normal[2] * 10.39,
            ],
            normal: [normal[0], normal[1], -normal[2]],
            radius: diameter_3d / 2.0,
        },
        theta,
        phi,
        model_confidence: 1.0,
    }
}

/// The point both rays pass closest to (vergence); 500 mm along their mean without one.
fn gaze_point(a: &([f64; 3], [f64; 3]), b: &([f64; 3], [f64; 3])) -> [f64; 3] {
    let (p, u) = *a;
    let (q, v) = *b;
    let dot = |x: [f64; 3], y: [f64; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
    let w = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
    let (aa, bb, cc, dd, ee) = (dot(u, u), dot(u, v), dot(v, v), dot(u, w), dot(v, w));
    let denom = aa * cc - bb * bb;
    if denom.abs() > 1e-9 {
        let s = (bb * ee - cc * dd) / denom;
        let t = (aa * ee - bb * dd) / denom;
        if s > 0.0 && t > 0.0 && s < 1e5 {
            let x = |i: usize| (p[i] + s * u[i] + q[i] + t * v[i]) / 2.0;
            return [x(0), x(1), x(2)];
        }
    }
    let m = |i: usize| (p[i] + q[i]) / 2.0 + 250.0 * (u[i] + v[i]);
    [m(0), m(1), m(2)]
}

/// Where a world-camera point falls in the image, normalised with the origin bottom left
/// (a 1280x720 camera with a 1000 px focal length).
fn norm_pos(p: [f64; 3]) -> [f64; 2] {
    if p[2] <= 1.0 {
        return [0.5, 0.5];
    }
    let u = 640.0 + 1000.0 * p[0] / p[2];
    let v = 360.0 + 1000.0 * p[1] / p[2];
    [u / 1280.0, 1.0 - v / 720.0]
}

/// The gaze message for one sample: [topic, msgpack payload].
fn gaze_message(
    s: &BinocularSample,
    t: f64,
    confidence: f64,
    last: &mut LastSeen,
) -> Option<ZmqMessage> {
    // Pupil's eye 0 films the right eye, eye 1 the left.
    let right_seen = pupil_eye(&s.right, &mut last.eyes[0]);
    let left_seen = pupil_eye(&s.left, &mut last.eyes[1]);
    let (right, left) = (last.eyes[0], last.eyes[1]);
    let (topic, payload) = match (right_seen, left_seen) {
        (true, false) | (false, true) => {
            let (id, eye, pupil) = if right_seen {
                (0u8, right, s.right.pupil_mm)
            } else {
                (1u8, left, s.left.pupil_mm)
            };
            let topic = if id == 0 { "gaze.3d.0." } else { "gaze.3d.1." };
            let point = [
                eye.0[0] + 500.0 * eye.1[0],
                eye.0[1] + 500.0 * eye.1[1],
                eye.0[2] + 500.0 * eye.1[2],
            ];
            let datum = MonocularGaze {
                topic,
                eye_center_3d: eye.0,
                gaze_normal_3d: eye.1,
                gaze_point_3d: point,
                norm_pos: norm_pos(point),
                confidence,
                timestamp: t,
                base_data: vec![pupil_datum(id, &eye, pupil, t, confidence)],
            };
            (topic, rmp_serde::to_vec_named(&datum).ok()?)
        }
        (both, _) => {
            // Neither seen: a blink; Capture still maps the pupils, with low confidence.
            let c = if both { confidence } else { 0.05 };
            let point = gaze_point(&right, &left);
            let datum = BinocularGaze {
                topic: "gaze.3d.01.",
                eye_centers_3d: BTreeMap::from([("0", right.0), ("1", left.0)]),
                gaze_normals_3d: BTreeMap::from([("0", right.1), ("1", left.1)]),
                gaze_point_3d: point,
                norm_pos: norm_pos(point),
                confidence: c,
                timestamp: t,
                base_data: vec![
                    pupil_datum(0, &right, s.right.pupil_mm, t, c),
                    pupil_datum(1, &left, s.left.pupil_mm, t, c),
                ],
            };
            ("gaze.3d.01.", rmp_serde::to_vec_named(&datum).ok()?)
        }
    };
    let mut m = ZmqMessage::from(topic);
    m.push_back(payload.into());
    Some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floats_are_written_as_python_writes_them() {
        assert_eq!(python_float_repr(3000.0), "3000.0");
        assert_eq!(python_float_repr(3000.25), "3000.25");
        assert_eq!(python_float_repr(-1.5), "-1.5");
    }

    #[test]
    fn converging_rays_meet_where_they_cross() {
        let r = ([-30.0, 0.0, 0.0], [0.0599, 0.0, 0.9982]);
        let l = ([30.0, 0.0, 0.0], [-0.0599, 0.0, 0.9982]);
        let p = gaze_point(&r, &l);
        assert!(p[0].abs() < 1e-6 && (p[2] - 500.0).abs() < 1.0, "{p:?}");
        assert_eq!(norm_pos([0.0, 0.0, 500.0]), [0.5, 0.5]);
        // Looking up (y negative in Pupil's frame) is high in the image.
        assert!(norm_pos([0.0, -100.0, 500.0])[1] > 0.5);
    }
}
