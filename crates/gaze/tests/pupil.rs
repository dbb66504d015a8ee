//! The Pupil Capture driver: its decoder on hand-written msgpack (Pupil's documented field
//! names, written with rmp's primitives, not with any encoder of ours), random bytes, a fake
//! Capture over real loopback ZeroMQ sockets that sends exactly what a test says (clock
//! offset, eye and axis conventions, dropouts, silence, a mute Pupil Remote), and the
//! simulated Capture of dioptra-sim (restart on the same port).
//!
//! These run on real time (real sockets): bounds on time are failure timeouts only.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, GazeSource, LinkError};
use dioptra_gaze::pupil::protocol::{decode_gaze, GazeTopic};
use dioptra_gaze::pupil::{PupilCapture, PupilConfig};
use dioptra_sim::gaze::pupil_capture::{CaptureFaults, PupilCaptureConfig, PupilCaptureSim};
use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene};
use dioptra_sim::tokio_clock::TokioClock;
use proptest::prelude::*;
use rmp::encode as w;
use zeromq::{PubSocket, RepSocket, Socket, SocketRecv, SocketSend, ZmqMessage};

// ---- hand-written msgpack -------------------------------------------------------------

fn key(b: &mut Vec<u8>, k: &str) {
    w::write_str(b, k).unwrap();
}

fn floats(b: &mut Vec<u8>, v: &[f64]) {
    w::write_array_len(b, v.len() as u32).unwrap();
    for x in v {
        w::write_f64(b, *x).unwrap();
    }
}

/// A per-eye map keyed "0"/"1" (current Capture) or 0/1 (older versions).
fn per_eye(b: &mut Vec<u8>, int_keys: bool, right: &[f64], left: &[f64]) {
    w::write_map_len(b, 2).unwrap();
    for (id, v) in [(0u8, right), (1u8, left)] {
        if int_keys {
            w::write_uint(b, u64::from(id)).unwrap();
        } else {
            key(b, &id.to_string());
        }
        floats(b, v);
    }
}

fn pupil_datum(b: &mut Vec<u8>, id: u8, diameter_3d: f64) {
    w::write_map_len(b, 4).unwrap();
    key(b, "topic");
    key(b, &format!("pupil.{id}.3d"));
    key(b, "id");
    w::write_uint(b, u64::from(id)).unwrap();
    key(b, "diameter_3d");
    w::write_f64(b, diameter_3d).unwrap();
    key(b, "confidence");
    w::write_f64(b, 0.99).unwrap();
}

/// What a test puts in a binocular datum.
#[derive(Clone, Copy)]
struct Binocular {
    timestamp: f64,
    confidence: f64,
    int_keys: bool,
    right_center: [f64; 3],
    left_center: [f64; 3],
    right_normal: [f64; 3],
    left_normal: [f64; 3],
}

impl Default for Binocular {
    fn default() -> Self {
        Binocular {
            timestamp: 1234.5,
            confidence: 0.9,
            int_keys: false,
            // Pupil's frame: the right eye is at +x; y down, so -10 is 10 mm up.
            right_center: [31.0, -10.0, -20.0],
            left_center: [-33.0, -10.0, -20.0],
            // Looking up and a little right (y negative is up).
            right_normal: [0.1, -0.3, 0.9487],
            left_normal: [0.12, -0.3, 0.9463],
        }
    }
}

fn binocular(d: Binocular) -> Vec<u8> {
    let mut b = Vec::new();
    w::write_map_len(&mut b, 8).unwrap();
    key(&mut b, "topic");
    key(&mut b, "gaze.3d.01.");
    key(&mut b, "eye_centers_3d");
    per_eye(&mut b, d.int_keys, &d.right_center, &d.left_center);
    key(&mut b, "gaze_normals_3d");
    per_eye(&mut b, d.int_keys, &d.right_normal, &d.left_normal);
    key(&mut b, "gaze_point_3d");
    floats(&mut b, &[40.0, -120.0, 500.0]);
    key(&mut b, "norm_pos");
    floats(&mut b, &[0.55, 0.7]);
    key(&mut b, "confidence");
    w::write_f64(&mut b, d.confidence).unwrap();
    key(&mut b, "timestamp");
    w::write_f64(&mut b, d.timestamp).unwrap();
    key(&mut b, "base_data");
    w::write_array_len(&mut b, 2).unwrap();
    pupil_datum(&mut b, 1, 3.25);
    pupil_datum(&mut b, 0, 3.5);
    b
}

fn monocular_left(timestamp: f64) -> Vec<u8> {
    let mut b = Vec::new();
    w::write_map_len(&mut b, 6).unwrap();
    key(&mut b, "topic");
    key(&mut b, "gaze.3d.1.");
    key(&mut b, "eye_center_3d");
    floats(&mut b, &[-33.0, 5.0, -20.0]);
    key(&mut b, "gaze_normal_3d");
    floats(&mut b, &[0.0, 0.0, 1.0]);
    key(&mut b, "confidence");
    w::write_f64(&mut b, 0.8).unwrap();
    key(&mut b, "timestamp");
    w::write_f64(&mut b, timestamp).unwrap();
    key(&mut b, "base_data");
    w::write_array_len(&mut b, 1).unwrap();
    pupil_datum(&mut b, 1, 4.0);
    b
}

// ---- decoding ---------------------------------------------------------------------------

#[test]
fn a_binocular_datum_decodes_with_eye_0_the_right_eye() {
    for int_keys in [false, true] {
        let d = decode_gaze(
            "gaze.3d.01.",
            &binocular(Binocular {
                int_keys,
                ..Default::default()
            }),
        )
        .unwrap();
        assert_eq!(d.topic, GazeTopic::Binocular);
        assert_eq!(d.timestamp_s, 1234.5);
        assert_eq!(d.confidence, Some(0.9));
        let (r, l) = (d.right.unwrap(), d.left.unwrap());
        assert_eq!(r.center_mm, [31.0, -10.0, -20.0], "int keys: {int_keys}");
        assert_eq!(l.center_mm, [-33.0, -10.0, -20.0]);
        // base_data lists eye 1 first: diameters are matched by id, not position.
        assert_eq!(r.diameter_3d_mm, Some(3.5));
        assert_eq!(l.diameter_3d_mm, Some(3.25));
        assert_eq!(d.gaze_point_3d_mm, Some([40.0, -120.0, 500.0]));
        assert_eq!(d.norm_pos, Some([0.55, 0.7]));
    }
}

#[test]
fn a_monocular_datum_fills_only_its_eye() {
    let d = decode_gaze("gaze.3d.1.", &monocular_left(7.0)).unwrap();
    assert_eq!(d.topic, GazeTopic::Monocular(1));
    assert!(d.right.is_none());
    assert_eq!(d.left.unwrap().center_mm, [-33.0, 5.0, -20.0]);
    assert_eq!(d.left.unwrap().diameter_3d_mm, Some(4.0));
}

#[test]
fn unusable_payloads_are_errors_and_bad_fields_are_missing_eyes() {
    assert!(decode_gaze("gaze.3d.01.", &[]).is_err());
    assert!(decode_gaze("gaze.3d.01.", &[0xc1]).is_err()); // never-used marker
    let mut not_map = Vec::new();
    floats(&mut not_map, &[1.0, 2.0]);
    assert!(decode_gaze("gaze.3d.01.", &not_map).is_err());
    let good = binocular(Binocular::default());
    assert!(decode_gaze("pupil.0.3d", &good).is_err());
    let mut trailing = good.clone();
    trailing.push(0xc0);
    assert!(decode_gaze("gaze.3d.01.", &trailing).is_err());
    // NaN timestamp: no time to put the sample at.
    let nan_time = binocular(Binocular {
        timestamp: f64::NAN,
        ..Default::default()
    });
    assert!(decode_gaze("gaze.3d.01.", &nan_time).is_err());
    // A NaN in one eye's centre drops that eye only.
    let nan_eye = binocular(Binocular {
        left_center: [f64::NAN, 0.0, 0.0],
        ..Default::default()
    });
    let d = decode_gaze("gaze.3d.01.", &nan_eye).unwrap();
    assert!(d.right.is_some() && d.left.is_none());
    // A string where the confidence goes: no confidence.
    let mut b = Vec::new();
    w::write_map_len(&mut b, 2).unwrap();
    key(&mut b, "timestamp");
    w::write_f64(&mut b, 1.0).unwrap();
    key(&mut b, "confidence");
    key(&mut b, "high");
    let d = decode_gaze("gaze.3d.01.", &b).unwrap();
    assert_eq!((d.confidence, d.right, d.left), (None, None, None));
}

proptest! {
    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600), topic in 0u8..4) {
        let topic = ["gaze.3d.01.", "gaze.3d.0.", "gaze.3d.1.", "gaze.2d.01."][usize::from(topic)];
        let _ = decode_gaze(topic, &bytes);
    }

    #[test]
    fn corrupted_datums_never_panic(at in 0usize..400, byte in any::<u8>(), cut in 0usize..400) {
        let mut b = binocular(Binocular::default());
        let n = b.len();
        b[at % n] = byte;
        b.truncate(cut.max(1) % (n + 1));
        if let Ok(d) = decode_gaze("gaze.3d.01.", &b) {
            prop_assert!(d.timestamp_s.is_finite());
        }
    }
}

// ---- a fake Capture over real sockets ---------------------------------------------------

/// Pupil Remote answering `v`, `SUB_PORT` and `t` (Pupil time = the test clock + `offset_s`,
/// exactly), and a publisher the test sends through.
struct FakeCapture {
    remote_port: u16,
    publisher: PubSocket,
    requests: Arc<Mutex<Vec<String>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for FakeCapture {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn fake_capture(clock: Arc<dyn Clock>, offset_s: f64) -> FakeCapture {
    let mut publisher = PubSocket::new();
    let sub_port = match publisher.bind("tcp://127.0.0.1:0").await.unwrap() {
        zeromq::Endpoint::Tcp(_, p) => p,
        e => panic!("{e:?}"),
    };
    let mut rep = RepSocket::new();
    let remote_port = match rep.bind("tcp://127.0.0.1:0").await.unwrap() {
        zeromq::Endpoint::Tcp(_, p) => p,
        e => panic!("{e:?}"),
    };
    let requests = Arc::new(Mutex::new(Vec::new()));
    let log = requests.clone();
    let task = tokio::spawn(async move {
        while let Ok(m) = rep.recv().await {
            let cmd = String::from_utf8_lossy(m.get(0).unwrap()).into_owned();
            log.lock().unwrap().push(cmd.clone());
            let reply = match cmd.as_str() {
                "v" => "3.5.1".to_string(),
                "SUB_PORT" => sub_port.to_string(),
                "t" => format!("{:?}", clock.now().as_secs_f64() + offset_s),
                _ => "Unknown command.".to_string(),
            };
            if rep.send(reply.into()).await.is_err() {
                break;
            }
        }
    });
    FakeCapture {
        remote_port,
        publisher,
        requests,
        task,
    }
}

impl FakeCapture {
    async fn publish(&mut self, topic: &str, payload: Vec<u8>) {
        let mut m = ZmqMessage::from(topic);
        m.push_back(payload.into());
        self.publisher.send(m).await.unwrap();
    }
}

fn config(port: u16) -> PupilConfig {
    PupilConfig {
        stall_timeout: Duration::from_millis(300),
        ..PupilConfig::new(format!("127.0.0.1:{port}"))
    }
}

/// Publishes `payload` until the driver yields a sample (a SUB only receives what is sent
/// after its subscription reached the publisher).
async fn first_sample(
    cap: &mut FakeCapture,
    driver: &mut PupilCapture,
    topic: &str,
    payload: impl Fn() -> Vec<u8>,
) -> dioptra_core::GazeSample {
    for _ in 0..200 {
        cap.publish(topic, payload()).await;
        match tokio::time::timeout(Duration::from_millis(50), driver.next_sample()).await {
            Ok(Ok(s)) => return s,
            Ok(Err(e)) if !e.needs_reconnect() => panic!("{e}"),
            _ => {}
        }
    }
    panic!("the driver never received a datum");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn host_time_is_the_pupil_timestamp_moved_by_the_measured_offset() {
    let clock: Arc<dyn Clock> = Arc::new(TokioClock::new());
    tokio::time::sleep(Duration::from_millis(20)).await;
    let mut cap = fake_capture(clock.clone(), 1000.0).await;
    let mut driver = PupilCapture::connect(config(cap.remote_port), clock.clone())
        .await
        .unwrap();
    assert_eq!(driver.version(), "3.5.1");
    let offset = driver.clock_offset();
    assert_eq!(offset.samples, 10);
    let asked = cap.requests.lock().unwrap().clone();
    assert_eq!(asked.iter().filter(|r| *r == "t").count(), 10, "{asked:?}");
    // Each measurement is off by at most half its round trip; loopback under load is slow,
    // so the bound only catches a wrong sign or a missing midpoint.
    assert!((offset.mean_s - 1000.0).abs() < 0.25, "{offset:?}");
    // A datum stamped 10 ms before it is sent.
    let sent_at = Arc::new(Mutex::new(0.0));
    let (c, at) = (clock.clone(), sent_at.clone());
    let s = first_sample(&mut cap, &mut driver, "gaze.3d.01.", move || {
        let now = c.now().as_secs_f64();
        *at.lock().unwrap() = now;
        binocular(Binocular {
            timestamp: now + 1000.0 - 0.010,
            ..Default::default()
        })
    })
    .await;
    let pupil_ts = s.device_time.as_secs_f64();
    let expected_host = pupil_ts - offset.mean_s;
    assert!(
        (s.host_time.as_secs_f64() - expected_host).abs() < 1e-6,
        "{s:?} {offset:?}"
    );
    let sent = *sent_at.lock().unwrap();
    // Mapped back to the host clock it is 10 ms before the send, give or take the estimate.
    assert!(
        (s.host_time.as_secs_f64() - (sent - 0.010)).abs() < 0.25,
        "{s:?}, sent at {sent}"
    );
    assert!(s.host_receive_time.as_secs_f64() >= sent);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eyes_and_axes_follow_dioptra_conventions() {
    let clock: Arc<dyn Clock> = Arc::new(TokioClock::new());
    let mut cap = fake_capture(clock.clone(), 50.0).await;
    let mut driver = PupilCapture::connect(config(cap.remote_port), clock.clone())
        .await
        .unwrap();
    let s = first_sample(&mut cap, &mut driver, "gaze.3d.01.", || {
        binocular(Binocular::default())
    })
    .await;
    assert!(s.left.valid && s.right.valid, "{s:?}");
    // Eye 0 (right): +x; Pupil's y = -10 (down axis) is 10 mm up in dioptra's frame.
    assert_eq!(s.right.origin_mm, [31.0, 10.0, -20.0]);
    assert_eq!(s.left.origin_mm, [-33.0, 10.0, -20.0]);
    // Looking up: +y in dioptra's frame; unit length.
    assert!(
        s.right.direction[1] > 0.25 && s.left.direction[1] > 0.25,
        "{s:?}"
    );
    for e in [&s.left, &s.right] {
        let n: f32 = e.direction.iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-5);
    }
    assert_eq!((s.right.pupil_mm, s.left.pupil_mm), (3.5, 3.25));

    // Below the threshold: both eyes dropped, the sample still timed.
    let low = first_sample(&mut cap, &mut driver, "gaze.3d.01.", || {
        binocular(Binocular {
            confidence: 0.59,
            timestamp: 77.0,
            ..Default::default()
        })
    })
    .await;
    assert!(!low.left.valid && !low.right.valid, "{low:?}");
    assert_eq!(low.device_time.as_secs_f64(), 77.0);

    // Monocular left: the right eye is a dropout.
    let mono = first_sample(&mut cap, &mut driver, "gaze.3d.1.", || monocular_left(78.0)).await;
    assert!(mono.left.valid && !mono.right.valid, "{mono:?}");
    assert_eq!(mono.left.origin_mm, [-33.0, -5.0, -20.0]);

    // Garbage is skipped and counted; the next good datum comes through.
    let before = driver.skipped().0;
    let good = first_sample(&mut cap, &mut driver, "gaze.3d.01.", || {
        vec![0xde, 0xad, 0xbe, 0xef]
    });
    // (Garbage alone never yields a sample: give it a bounded try, then send a good one.)
    let timed_out = tokio::time::timeout(Duration::from_millis(500), good).await;
    assert!(timed_out.is_err(), "garbage became a sample");
    assert!(driver.skipped().0 > before, "{:?}", driver.skipped());
    let ok = first_sample(&mut cap, &mut driver, "gaze.3d.01.", || {
        binocular(Binocular::default())
    })
    .await;
    assert!(ok.left.valid);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_capture_that_goes_quiet_is_a_lost_link() {
    let clock: Arc<dyn Clock> = Arc::new(TokioClock::new());
    let cap = fake_capture(clock.clone(), 0.0).await;
    let mut driver = PupilCapture::connect(config(cap.remote_port), clock)
        .await
        .unwrap();
    let e = tokio::time::timeout(Duration::from_secs(30), driver.next_sample())
        .await
        .expect("the stall timeout never fired")
        .unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");
    assert!(e.to_string().contains("no gaze"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nothing_listening_or_a_mute_remote_fails_the_connect_in_time() {
    let clock: Arc<dyn Clock> = Arc::new(TokioClock::new());
    // A port nobody listens on: zmq retries the connect forever; the driver gives up.
    let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = free.local_addr().unwrap().port();
    drop(free);
    let cfg = PupilConfig {
        request_timeout: Duration::from_millis(300),
        ..config(port)
    };
    let e = tokio::time::timeout(
        Duration::from_secs(30),
        PupilCapture::connect(cfg, clock.clone()),
    )
    .await
    .expect("connect hung")
    .unwrap_err();
    assert!(
        matches!(e, DeviceError::Link(LinkError::Unavailable(_))),
        "{e:?}"
    );

    // Pupil Remote that takes the request and never answers.
    let sim = PupilCaptureSim::spawn(PupilCaptureConfig::default(), generator()).unwrap();
    sim.set_faults(CaptureFaults {
        remote_mute: true,
        ..Default::default()
    });
    let cfg = PupilConfig {
        request_timeout: Duration::from_millis(300),
        ..config(sim.remote_addr().port())
    };
    let e = tokio::time::timeout(Duration::from_secs(30), PupilCapture::connect(cfg, clock))
        .await
        .expect("a request with no reply hung")
        .unwrap_err();
    assert!(
        matches!(e, DeviceError::Link(LinkError::Timeout { .. })),
        "{e:?}"
    );
}

#[test]
fn a_confidence_outside_0_to_1_is_refused_before_connecting() {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let e = rt
        .block_on(PupilCapture::connect(
            PupilConfig {
                min_confidence: 1.5,
                ..PupilConfig::new("127.0.0.1:1")
            },
            Arc::new(dioptra_core::SystemClock::new()),
        ))
        .unwrap_err();
    assert!(matches!(e, DeviceError::OutOfRange { .. }), "{e:?}");
}

// ---- the simulated Capture --------------------------------------------------------------

fn generator() -> Box<GazeGenerator> {
    Box::new(
        GazeGenerator::new(
            Scene::named("saccades").unwrap(),
            GeneratorConfig {
                rate_hz: 200.0,
                ..Default::default()
            },
        )
        .unwrap(),
    )
}

/// The next sample, skipping nothing: a failure names the error.
async fn sample(d: &mut PupilCapture) -> dioptra_core::GazeSample {
    tokio::time::timeout(Duration::from_secs(30), d.next_sample())
        .await
        .expect("no sample within 30 s")
        .unwrap()
}

/// A simulated Capture on `port`, retrying while the old one's port is still closing.
async fn capture_on(port: u16, base: f64) -> PupilCaptureSim {
    for _ in 0..300 {
        let cfg = PupilCaptureConfig {
            remote_port: port,
            pupil_time_at_start_s: base,
            ..Default::default()
        };
        match PupilCaptureSim::spawn(cfg, generator()) {
            Ok(s) => return s,
            Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
    panic!("port {port} never came free");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_driver_streams_the_simulated_capture_and_comes_back_after_a_restart() {
    let clock: Arc<dyn Clock> = Arc::new(TokioClock::new());
    let first = capture_on(0, 3000.0).await;
    let port = first.remote_addr().port();
    let mut driver = PupilCapture::connect(config(port), clock.clone())
        .await
        .unwrap();
    assert_eq!(driver.sub_port(), first.sub_port());
    // Pupil time runs about 3000 s ahead of this clock.
    assert!(
        (driver.clock_offset().mean_s - 3000.0).abs() < 1.0,
        "{:?}",
        driver.clock_offset()
    );
    let mut valid = 0;
    let mut last = 0.0;
    for _ in 0..100 {
        let s = sample(&mut driver).await;
        let t = s.device_time.as_secs_f64();
        assert!(
            t > last && (3000.0..3100.0).contains(&t),
            "{t} after {last}"
        );
        last = t;
        if s.right.valid && s.left.valid {
            valid += 1;
            // The generator's right eye sits at +x, as dioptra's frame has it.
            assert!(
                s.right.origin_mm[0] > 0.0 && s.left.origin_mm[0] < 0.0,
                "{s:?}"
            );
        }
        // Host time comes before receipt (publication trails exposure by 4 ms).
        assert!(
            s.host_time <= s.host_receive_time + Duration::from_millis(200),
            "{s:?}"
        );
    }
    assert!(valid > 50, "only {valid} of 100 samples had both eyes");

    // Capture restarts on the same Pupil Remote port with a new IPC port and time base.
    first.shutdown().await;
    let second = capture_on(port, 9000.0).await;
    let e = tokio::time::timeout(Duration::from_secs(30), async {
        loop {
            if let Err(e) = driver.next_sample().await {
                return e;
            }
        }
    })
    .await
    .expect("the old subscription never reported the loss");
    assert!(e.needs_reconnect(), "{e:?}");
    let mut driver = PupilCapture::connect(config(port), clock).await.unwrap();
    assert_eq!(driver.sub_port(), second.sub_port());
    assert!((driver.clock_offset().mean_s - 9000.0).abs() < 1.0);
    let s = sample(&mut driver).await;
    assert!(s.device_time.as_secs_f64() >= 9000.0, "{s:?}");
}
