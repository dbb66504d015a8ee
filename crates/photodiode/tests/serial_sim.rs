//! The serial-line photodiode driver against the simulated board (in-memory links on tokio's
//! paused clock, and a pty in real time), and against a hand-driven device end for what the
//! simulator does not do wrong by itself.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, LightEvent, Photodiode, Timestamp};
use dioptra_photodiode::SerialPhotodiode;
use dioptra_sim::light::ScriptedLight;
use dioptra_sim::photodiode::{SerialPhotodiodeSim, SerialPhotodiodeSimConfig};
use dioptra_sim::serve::serve;
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_transport::memory::{self, MemoryLink};
use dioptra_transport::ByteLink;

fn serve_sim(mut sim: SerialPhotodiodeSim, clock: TokioClock) -> MemoryLink {
    let (host, mut dev) = memory::pair(8192);
    tokio::spawn(async move {
        let _ = serve(&mut dev, &mut sim, &clock).await;
    });
    host
}

fn sim_with_light(cfg: SerialPhotodiodeSimConfig, light: &ScriptedLight) -> SerialPhotodiodeSim {
    SerialPhotodiodeSim::new(cfg).with_light(Arc::new(light.clone()))
}

/// True host times of a patch lit for `high` from each of `starts` (5 µs sensor response).
fn true_edges(starts: &[Timestamp], high: Duration) -> Vec<(Timestamp, bool)> {
    let r = Duration::from_micros(5);
    starts
        .iter()
        .flat_map(|t| [(*t + r, true), (*t + high + r, false)])
        .collect()
}

async fn edge(d: &mut impl Photodiode) -> (Timestamp, bool) {
    match d.next_light().await.unwrap() {
        LightEvent::Edge(e) => (e.host_time, e.rising),
        other => panic!("expected an edge, got {other:?}"),
    }
}

#[tokio::test(start_paused = true)]
async fn edges_map_to_the_host_time_the_light_changed() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    let starts: Vec<Timestamp> = (0..300)
        .map(|k| Timestamp::from_micros(200_000 + k * 16_667))
        .collect();
    let high = Duration::from_micros(8_333);
    light.pulses(starts.clone(), high, 0.9, 0.02);
    // Its clock: 3 s ahead of the host's and 35 ppm fast.
    let link = serve_sim(sim_with_light(Default::default(), &light), clock);
    let mut d = SerialPhotodiode::connect(link, Arc::new(clock))
        .await
        .unwrap();
    assert_eq!(d.status().about, "dioptra-sim serial photodiode");
    let (mut worst, mut worst_fitted) = (0u64, 0u64);
    for (at, rising) in true_edges(&starts, high) {
        let (t, r) = edge(&mut d).await;
        assert_eq!(r, rising);
        let error = t.as_micros().abs_diff(at.as_micros());
        worst = worst.max(error);
        if at > Timestamp::from_millis(3_000) {
            worst_fitted = worst_fitted.max(error);
        }
    }
    // Until its points span 2 s the mapper assumes no drift (35 ppm over 1.5 s: 52 us); from
    // then on it fits the drift, which over 5 s would be 175 us.
    assert!(worst <= 60, "host times off by up to {worst} us");
    assert!(
        worst_fitted <= 5,
        "after the drift fit, off by up to {worst_fitted} us"
    );
    let s = d.status();
    assert_eq!(
        (s.edges, s.lost, s.malformed_lines, s.restarts),
        (600, 0, 0, 0)
    );
}

#[tokio::test(start_paused = true)]
async fn an_overflow_is_a_loss_and_the_stream_goes_on() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    // 40 µs flicker against a board that writes two edges per step of its loop.
    let starts: Vec<Timestamp> = (0..100)
        .map(|k| Timestamp::from_micros(50_000 + k * 40))
        .collect();
    light.pulses(starts, Duration::from_micros(20), 1.0, 0.0);
    let cfg = SerialPhotodiodeSimConfig {
        queue: 2,
        ..Default::default()
    };
    let link = serve_sim(sim_with_light(cfg, &light), clock);
    let mut d = SerialPhotodiode::connect(link, Arc::new(clock))
        .await
        .unwrap();
    let (mut edges, mut lost) = (0, 0);
    let read = async {
        while edges + lost < 200 {
            match d.next_light().await.unwrap() {
                LightEvent::Edge(_) => edges += 1,
                LightEvent::Lost { count, .. } => lost += count,
            }
        }
    };
    // Simulated time: a miscount would wait for ever without this.
    tokio::time::timeout(Duration::from_secs(5), read)
        .await
        .expect("every edge seen or reported lost within 5 s");
    assert_eq!(edges + lost, 200);
    assert!(edges > 0 && lost > 0, "{edges} edges, {lost} lost");
    assert_eq!(d.status().lost, lost);
}

#[tokio::test(start_paused = true)]
async fn a_restarted_board_is_resynchronised() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    let starts: Vec<Timestamp> = (0..20)
        .map(|k| Timestamp::from_micros(100_000 + k * 100_000))
        .collect();
    let high = Duration::from_millis(10);
    light.pulses(starts.clone(), high, 0.9, 0.0);
    let sim = Arc::new(std::sync::Mutex::new(sim_with_light(
        Default::default(),
        &light,
    )));
    let (host, mut dev) = memory::pair(8192);
    let served = sim.clone();
    tokio::spawn(async move {
        let mut s = served;
        let _ = serve(&mut dev, &mut s, &clock).await;
    });
    let mut d = SerialPhotodiode::connect(host, Arc::new(clock))
        .await
        .unwrap();
    let want = true_edges(&starts, high);
    for w in &want[..10] {
        let (t, r) = edge(&mut d).await;
        assert_eq!(r, w.1);
        assert!(t.as_micros().abs_diff(w.0.as_micros()) <= 60);
    }
    // Between pulses 5 and 6 the board reboots: its clock starts again from zero.
    tokio::time::sleep_until(tokio::time::Instant::now() + Duration::from_millis(30)).await;
    sim.lock().unwrap().restart();
    for w in &want[10..] {
        let (t, r) = edge(&mut d).await;
        assert_eq!(r, w.1);
        assert!(
            t.as_micros().abs_diff(w.0.as_micros()) <= 60,
            "{t:?} vs {:?} after the restart",
            w.0
        );
    }
    assert_eq!(d.status().restarts, 1);
}

/// A hand-driven device: answers `v` with `hello` and `s` with its clock (the host's plus 1 s),
/// and writes `extra` once, after its first sync reply.
async fn answer(dev: &mut MemoryLink, clock: &TokioClock, hello: &str, extra: &[u8]) {
    let mut buf = [0u8; 64];
    let mut pending = Vec::new();
    let mut extra_sent = extra.is_empty();
    loop {
        let Ok(n) = dev.read(&mut buf, Duration::from_secs(30)).await else {
            return;
        };
        pending.extend_from_slice(&buf[..n]);
        while let Some(i) = pending.iter().position(|b| *b == b'\n') {
            let line: Vec<u8> = pending.drain(..=i).collect();
            let reply = match &line[..] {
                b"v\n" => format!("{hello}\n"),
                // The device clock is the host's plus 1 s.
                b"s\n" => format!("s,{}\n", clock.now().as_micros() + 1_000_000),
                _ => String::new(),
            };
            if dev.write_all(reply.as_bytes()).await.is_err() {
                return;
            }
            if reply.starts_with("s,") && !extra_sent {
                extra_sent = true;
                let _ = dev.write_all(extra).await;
            }
        }
    }
}

#[tokio::test(start_paused = true)]
async fn malformed_lines_are_counted_never_fatal() {
    let clock = TokioClock::new();
    let (host, mut dev) = memory::pair(8192);
    let garbage: &[u8] = b"1000500,1\n\xff\xfe\x00junk\n12,x\n!overflow,0\n!what\n#hi\n\
        1000400,0\n1000600,1\n1000700,1\n!overflow,2\n1000800,0\n";
    let mut long = vec![b'9'; 300];
    long.push(b'\n');
    let extra = [garbage, &long[..], b"1000900,1\n"].concat();
    let c = clock;
    tokio::spawn(async move {
        answer(&mut dev, &c, "dioptra-photodiode,1,hand", &extra).await;
    });
    let cfg = dioptra_photodiode::SerialPhotodiodeConfig {
        sync_burst: 1,
        ..Default::default()
    };
    let mut d = SerialPhotodiode::connect_with(host, cfg, Arc::new(clock))
        .await
        .unwrap();
    // The extra lines came after the burst's reply, so they are read now; mapped with the
    // device clock 1 s ahead of the host's.
    let mut got = Vec::new();
    while got.len() < 7 {
        got.push(d.next_light().await.unwrap());
    }
    let summary: Vec<String> = got
        .iter()
        .map(|e| match e {
            LightEvent::Edge(e) => format!("{}:{}", e.host_time.as_micros(), u8::from(e.rising)),
            LightEvent::Lost { count, .. } => format!("lost {count}"),
        })
        .collect();
    // 500:1; the 400:0 edge went back in time (skipped); 600:1 after a 1 means a lost 0;
    // 700:1 the same; the overflow's 2; then 800:0 and, after the long line, 900:1.
    assert_eq!(
        summary,
        ["500:1", "lost 1", "600:1", "lost 1", "700:1", "lost 2", "800:0"]
    );
    assert_eq!(edge(&mut d).await, (Timestamp::from_micros(900), true));
    let s = d.status();
    // junk (not text), 12,x, !overflow,0, !what, the backwards edge, the long line.
    assert_eq!(s.malformed_lines, 6, "{s:?}");
    assert_eq!(s.lost, 4);
}

#[tokio::test(start_paused = true)]
async fn another_version_or_no_hello_is_a_clear_error() {
    let clock = TokioClock::new();
    let (host, mut dev) = memory::pair(8192);
    tokio::spawn(async move {
        answer(&mut dev, &clock, "dioptra-photodiode,2,future", b"").await;
    });
    let e = SerialPhotodiode::connect(host, Arc::new(clock))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Invalid(m) if m.contains("version 2") && m.contains("update")),
        "{e}"
    );

    // A board running something else: lines, but never the hello.
    let (host, mut dev) = memory::pair(8192);
    tokio::spawn(async move {
        answer(&mut dev, &clock, "temperature 21.5", b"").await;
    });
    let e = SerialPhotodiode::connect(host, Arc::new(clock))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("no hello line") && m.contains("temperature 21.5")),
        "{e}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_dark_sensor_is_no_error_and_a_silent_board_is() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    light.pulses(
        [Timestamp::from_millis(9_000)],
        Duration::from_millis(1),
        0.9,
        0.0,
    );
    let link = serve_sim(sim_with_light(Default::default(), &light), clock);
    let faults = link.faults();
    let mut d = SerialPhotodiode::connect(link, Arc::new(clock))
        .await
        .unwrap();
    let quiet = tokio::time::timeout(Duration::from_secs(8), d.next_light()).await;
    assert!(quiet.is_err(), "{quiet:?}");
    let (t, rising) = edge(&mut d).await;
    assert!(rising && t.as_micros().abs_diff(9_000_005) <= 40, "{t:?}");
    // Pulled out: the next ping fails as a link error.
    faults.disconnect("USB cable pulled");
    let e = d.next_light().await.unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");
}

#[tokio::test]
async fn over_a_pty() {
    use dioptra_core::SystemClock;
    use dioptra_transport::pty::PtyPair;
    use dioptra_transport::serial::{SerialLink, SerialSettings};

    let clock = SystemClock::new();
    let light = ScriptedLight::new();
    // Pulses from 0.3 s after now, in the system clock's time.
    let t0 = clock.now() + Duration::from_millis(300);
    let starts: Vec<Timestamp> = (0..10)
        .map(|k| t0 + Duration::from_millis(20 * k))
        .collect();
    light.pulses(starts.clone(), Duration::from_millis(5), 0.9, 0.0);
    let pty = PtyPair::open().unwrap();
    let path = pty.slave_path.clone();
    let mut master = pty.master;
    let sim_clock = clock.clone();
    let mut sim = sim_with_light(Default::default(), &light);
    let server = tokio::spawn(async move {
        let _ = serve(&mut master, &mut sim, &sim_clock).await;
    });
    let link = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
    let mut d = SerialPhotodiode::connect(link, Arc::new(clock.clone()))
        .await
        .unwrap();
    // Real time: the edges' order is exact, their host times as good as the pty's round trip.
    for (at, rising) in true_edges(&starts, Duration::from_millis(5)) {
        let (t, r) = edge(&mut d).await;
        assert_eq!(r, rising);
        assert!(
            t.as_micros().abs_diff(at.as_micros()) <= 5_000,
            "{t:?} vs {at:?}"
        );
    }
    server.abort();
}
