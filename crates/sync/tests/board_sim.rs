//! The sync board driver against the simulated board, over in-memory links (tokio's paused
//! clock) and over a pty (real time).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    Clock, DeviceError, Diopters, LightEvent, LinkError, Photodiode, PlaneSchedule, PlaneSequencer,
    SequencerEvent, SequencerFault, Timestamp,
};
use dioptra_protocol::ErrorCode;
use dioptra_sim::lens_model::LensModelConfig;
use dioptra_sim::light::ScriptedLight;
use dioptra_sim::sync_board::{self, SyncBoardSim, SyncBoardSimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_sync::board::{BoardEvent, PhotodiodeBand, SyncBoard};
use dioptra_transport::memory::{self, Faults, MemoryLink};
use dioptra_transport::ByteLink;

fn fast_lens() -> SyncBoardSimConfig {
    SyncBoardSimConfig {
        lens: LensModelConfig {
            settle_time: Duration::from_micros(800),
            ..Default::default()
        },
        ..Default::default()
    }
}

/// Serves a simulated board on one end of a pair; returns the other end.
fn board_link(cfg: SyncBoardSimConfig, clock: TokioClock) -> MemoryLink {
    serve_board(SyncBoardSim::new(cfg), clock)
}

fn serve_board(mut sim: SyncBoardSim, clock: TokioClock) -> MemoryLink {
    let (host, mut dev) = memory::pair(8192);
    tokio::spawn(async move {
        let _ = sync_board::serve(&mut dev, &mut sim, &clock).await;
    });
    host
}

/// A board whose photodiode sees `light`.
fn board_with_light(
    cfg: SyncBoardSimConfig,
    light: &ScriptedLight,
    clock: TokioClock,
) -> MemoryLink {
    serve_board(
        SyncBoardSim::new(cfg).with_light(Arc::new(light.clone())),
        clock,
    )
}

/// The light's true host times: `starts`, each on for `high`, as the sensor sees them
/// (5 µs response, the simulator's default).
fn true_edges(starts: &[Timestamp], high: Duration) -> Vec<(Timestamp, bool)> {
    let response = Duration::from_micros(5);
    starts
        .iter()
        .flat_map(|t| [(*t + response, true), (*t + high + response, false)])
        .collect()
}

fn schedule(period_us: u64, settle_us: u64) -> PlaneSchedule {
    PlaneSchedule::new(
        vec![Diopters(0.2), Diopters(0.8), Diopters(1.4), Diopters(2.0)],
        Duration::from_micros(period_us),
        Duration::from_micros(settle_us),
    )
    .unwrap()
}

async fn subframes<S: PlaneSequencer>(
    s: &mut S,
    n: usize,
) -> Vec<(u32, u8, dioptra_core::Timestamp, Option<Diopters>)> {
    let mut out = Vec::new();
    while out.len() < n {
        if let SequencerEvent::SubframeStart {
            frame,
            plane_index,
            host_time,
            lens_power,
            ..
        } = s.next_event().await.unwrap()
        {
            out.push((frame, plane_index, host_time, lens_power));
        }
    }
    out
}

#[tokio::test(start_paused = true)]
async fn events_carry_planes_lens_power_and_host_times() {
    let clock = TokioClock::new();
    let mut b = SyncBoard::connect(board_link(fast_lens(), clock), Arc::new(clock))
        .await
        .unwrap();
    let status = b.status();
    assert_eq!(status.info.unwrap().serial.as_str(), "DSB-SIM-0001");
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    let got = subframes(&mut b, 12).await;
    for (k, (frame, plane, _, power)) in got.iter().enumerate() {
        assert_eq!((*frame as usize, *plane as usize), (k / 4, k % 4));
        let want = [0.2, 0.8, 1.4, 2.0][k % 4];
        assert!(
            (power.unwrap().0 - want).abs() < 0.02,
            "{power:?} for plane {plane}"
        );
    }
    // Host times come from the board's clock (7 s ahead, -20 ppm) mapped back: sub-frames
    // 4166 us apart give or take the display's 20 us jitter, and each sub-frame started the
    // settle allowance before its event was read.
    for w in got.windows(2) {
        let gap = w[1].2.saturating_since(w[0].2).as_micros() as i64;
        assert!((gap - 4166).abs() <= 45, "gap {gap} us");
    }
    // The event is sent when the settle allowance ends, by a serve loop on tokio's 1 ms timer.
    let lag = clock.now().saturating_since(got[11].2).as_micros();
    assert!(
        (1450..=2600).contains(&lag),
        "event read {lag} us after its sub-frame began"
    );
    b.stop().await.unwrap();
    assert!(!b.status().running);
}

#[tokio::test(start_paused = true)]
async fn a_sub_frame_shorter_than_the_lens_settle_time_gives_late_settle_faults() {
    let clock = TokioClock::new();
    let link = board_link(SyncBoardSimConfig::default(), clock);
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    b.program(&schedule(4166, 1000)).await.unwrap();
    b.start().await.unwrap();
    let mut late = 0;
    for _ in 0..16 {
        if let SequencerEvent::Fault {
            fault: SequencerFault::LateSettle,
            ..
        } = b.next_event().await.unwrap()
        {
            late += 1;
        }
    }
    assert!(late >= 6, "{late} late-settle faults in 16 events");
}

#[tokio::test(start_paused = true)]
async fn dropped_vsyncs_are_reported() {
    let clock = TokioClock::new();
    let cfg = SyncBoardSimConfig {
        missed_vsync_probability: 0.25,
        ..fast_lens()
    };
    let mut b = SyncBoard::connect(board_link(cfg, clock), Arc::new(clock))
        .await
        .unwrap();
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    let mut missed = 0;
    for _ in 0..40 {
        if let SequencerEvent::Fault {
            fault: SequencerFault::MissedVsync,
            ..
        } = b.next_event().await.unwrap()
        {
            missed += 1;
        }
    }
    assert!(missed >= 3, "{missed}");
}

/// Counts writes, to show that refused schedules send nothing.
struct Counting<L> {
    inner: L,
    writes: Arc<AtomicUsize>,
}

impl<L: ByteLink> ByteLink for Counting<L> {
    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.writes.fetch_add(1, Ordering::SeqCst);
        self.inner.write_all(bytes).await
    }
    async fn read(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        self.inner.read(buf, timeout).await
    }
    async fn discard_input(&mut self) -> Result<usize, LinkError> {
        self.inner.discard_input().await
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

#[tokio::test(start_paused = true)]
async fn invalid_schedules_send_nothing_and_the_board_s_refusals_are_typed() {
    let clock = TokioClock::new();
    let writes = Arc::new(AtomicUsize::new(0));
    let link = Counting {
        inner: board_link(fast_lens(), clock),
        writes: writes.clone(),
    };
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    let before = writes.load(Ordering::SeqCst);
    // 0.5 us periods round to 0 us on the wire.
    let sub_us = PlaneSchedule::new(
        vec![Diopters(1.0)],
        Duration::from_nanos(500),
        Duration::ZERO,
    )
    .unwrap();
    let e = b.program(&sub_us).await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Invalid(m) if m.contains("microseconds")),
        "{e}"
    );
    assert_eq!(writes.load(Ordering::SeqCst), before);
    // Starting before any schedule, and a power the lens cannot reach: the board refuses.
    let e = b.start().await.unwrap_err();
    assert!(
        matches!(e, DeviceError::Refused { code, .. } if code == ErrorCode::NotConfigured as u16)
    );
    let far = PlaneSchedule::new(
        vec![Diopters(40.0)],
        Duration::from_millis(4),
        Duration::from_millis(1),
    )
    .unwrap();
    let e = b.program(&far).await.unwrap_err();
    assert!(matches!(e, DeviceError::Refused { code, .. } if code == ErrorCode::OutOfRange as u16));
    // A new schedule while running: the board says Busy, the driver stops it and reloads.
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    b.program(&schedule(8333, 2000)).await.unwrap();
    assert!(!b.status().running);
    assert!(matches!(b.next_event().await, Err(DeviceError::Invalid(_))));
}

#[tokio::test(start_paused = true)]
async fn garbage_is_skipped_and_unplug_then_reconnect_resumes() {
    let clock = TokioClock::new();
    let link = board_link(fast_lens(), clock);
    let faults: Faults = link.faults();
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    subframes(&mut b, 2).await;
    faults.inject(&[0x13, 0x37, 0xff, 0x00, 0x05, 0x01, 0x02, 0x00]);
    subframes(&mut b, 4).await;
    assert!(b.status().garbled_frames >= 1);

    faults.disconnect("USB cable pulled");
    let e = b.next_event().await.unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");
    b.reconnect(board_link(fast_lens(), clock)).await.unwrap();
    assert!(b.status().running);
    let got = subframes(&mut b, 4).await;
    assert_eq!(got[0].0, 0, "a new session starts at frame 0");
    assert_eq!(
        got.iter().map(|g| g.1).collect::<Vec<_>>(),
        vec![0, 1, 2, 3]
    );
}

#[tokio::test]
async fn over_a_pty() {
    use dioptra_core::SystemClock;
    use dioptra_transport::pty::PtyPair;
    use dioptra_transport::serial::{SerialLink, SerialSettings};

    let clock = SystemClock::new();
    let pty = PtyPair::open().unwrap();
    let path = pty.slave_path.clone();
    let mut master = pty.master;
    let sim_clock = clock.clone();
    let server = tokio::spawn(async move {
        let mut sim = SyncBoardSim::new(fast_lens());
        let _ = sync_board::serve(&mut master, &mut sim, &sim_clock).await;
    });
    let link = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
    let mut b = SyncBoard::connect(link, Arc::new(clock.clone()))
        .await
        .unwrap();
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    let got = subframes(&mut b, 8).await;
    // Real time on a pty: order and plane indices are exact, powers near their targets.
    let first = got[0].1 as usize;
    for (k, g) in got.iter().enumerate() {
        assert_eq!(g.1 as usize, (first + k) % 4);
        let want = [0.2, 0.8, 1.4, 2.0][g.1 as usize];
        assert!((g.3.unwrap().0 - want).abs() < 0.05, "{g:?}");
    }
    // A session that leaves the board running: the next one reprograms it (the board answers
    // Busy, the driver stops it) and sees only its own run, from frame 0.
    drop(b);
    tokio::time::sleep(Duration::from_millis(30)).await;
    let link = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
    let mut b = SyncBoard::connect(link, Arc::new(clock.clone()))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(30)).await;
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    let got = subframes(&mut b, 4).await;
    assert_eq!((got[0].0, got[0].1), (0, 0), "{got:?}");
    b.stop().await.unwrap();
    server.abort();
}

#[tokio::test(start_paused = true)]
async fn photodiode_edges_come_at_the_host_time_the_light_changed() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    // A 90 Hz patch, white for 2 ms of each refresh, from 0.5 s on.
    let starts: Vec<Timestamp> = (0..100)
        .map(|k| Timestamp::from_micros(500_000 + k * 11_111))
        .collect();
    let high = Duration::from_millis(2);
    light.pulses(starts.clone(), high, 0.9, 0.02);
    let link = board_with_light(fast_lens(), &light, clock);
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    assert!(b.has_photodiode());
    b.set_photodiode(Some(PhotodiodeBand::default()))
        .await
        .unwrap();
    let want = true_edges(&starts, high);
    let mut worst_us = 0i64;
    for (at, rising) in &want {
        let LightEvent::Edge(e) = b.next_light().await.unwrap() else {
            panic!("a loss on a quiet link");
        };
        assert_eq!(e.rising, *rising);
        // The board's clock is 7 s ahead and runs 20 ppm slow; mapped back to the host's.
        worst_us = worst_us.max((e.host_time.as_micros() as i64 - at.as_micros() as i64).abs());
        let level = e.level.unwrap();
        assert!(
            (level - if *rising { 0.9 } else { 0.02 }).abs() < 1e-4,
            "{level}"
        );
        assert!(e.host_receive_time >= *at);
    }
    assert!(worst_us <= 30, "host times off by up to {worst_us} us");
    assert_eq!(b.status().light_edges_lost, 0);
    assert_eq!(b.status().photodiode, Some(PhotodiodeBand::default()));
}

#[tokio::test(start_paused = true)]
async fn sub_frames_and_light_share_the_link_and_neither_is_lost() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    let starts: Vec<Timestamp> = (0..40)
        .map(|k| Timestamp::from_micros(20_000 + k * 4_166))
        .collect();
    let high = Duration::from_millis(1);
    light.pulses(starts.clone(), high, 0.9, 0.02);
    let link = board_with_light(fast_lens(), &light, clock);
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    b.set_photodiode(Some(PhotodiodeBand::default()))
        .await
        .unwrap();
    b.program(&schedule(4166, 1500)).await.unwrap();
    b.start().await.unwrap();
    // The sequencer's reader keeps the edges it reads for the photodiode's.
    let got = subframes(&mut b, 40).await;
    assert_eq!(got.len(), 40);
    let want = true_edges(&starts, high);
    let mut edges = Vec::new();
    while edges.len() < want.len() {
        match b.next_light().await.unwrap() {
            LightEvent::Edge(e) => edges.push((e.host_time, e.rising)),
            lost => panic!("{lost:?}"),
        }
    }
    for ((t, rising), (want_t, want_rising)) in edges.iter().zip(&want) {
        assert_eq!(rising, want_rising);
        assert!(
            t.as_micros().abs_diff(want_t.as_micros()) <= 30,
            "{t:?} vs {want_t:?}"
        );
    }
    // And both kinds in arrival order from one reader.
    let mut kinds = (0, 0);
    for _ in 0..30 {
        match b.next_board_event().await.unwrap() {
            BoardEvent::Sequencer(_) => kinds.0 += 1,
            BoardEvent::Light(_) => kinds.1 += 1,
        }
    }
    assert!(
        kinds.0 > 0 && kinds.1 == 0,
        "{kinds:?}: the light has stopped by now"
    );
}

#[tokio::test(start_paused = true)]
async fn edges_the_board_dropped_are_reported_as_lost() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    // Flicker too fast for a board that sends one edge per step of its loop.
    let starts: Vec<Timestamp> = (0..100)
        .map(|k| Timestamp::from_micros(100_000 + k * 40))
        .collect();
    light.pulses(starts, Duration::from_micros(20), 1.0, 0.0);
    light.pulses(
        [Timestamp::from_millis(300)],
        Duration::from_millis(10),
        1.0,
        0.0,
    );
    let cfg = SyncBoardSimConfig {
        photodiode_queue: 1,
        ..fast_lens()
    };
    let mut b = SyncBoard::connect(board_with_light(cfg, &light, clock), Arc::new(clock))
        .await
        .unwrap();
    b.set_photodiode(Some(PhotodiodeBand::default()))
        .await
        .unwrap();
    // The board's counter shows a gap only with the next edge it sends: the slow pulse at
    // 300 ms (both of whose edges go out) reveals edges dropped at the end of the flicker.
    let (mut edges, mut lost) = (0u64, 0u64);
    let read = async {
        while edges + lost < 202 {
            match b.next_light().await.unwrap() {
                LightEvent::Edge(_) => edges += 1,
                LightEvent::Lost { count, .. } => lost += count,
            }
        }
    };
    // Simulated time: a miscount would wait for ever without this.
    tokio::time::timeout(Duration::from_secs(5), read)
        .await
        .expect("every edge seen or reported lost within 5 s");
    assert_eq!(edges + lost, 202);
    assert!(lost > 0 && edges > 0, "{edges} edges, {lost} lost");
    assert_eq!(b.status().light_edges_lost, lost);
}

#[tokio::test(start_paused = true)]
async fn a_dark_photodiode_keeps_the_link_checked_and_waits() {
    let clock = TokioClock::new();
    let light = ScriptedLight::new();
    light.pulses(
        [Timestamp::from_millis(8_000)],
        Duration::from_millis(5),
        0.9,
        0.0,
    );
    let link = board_with_light(fast_lens(), &light, clock);
    let mut b = SyncBoard::connect(link, Arc::new(clock)).await.unwrap();
    // Nothing to wait for yet, and a band that does not fit the scale: refused here.
    assert!(matches!(b.next_light().await, Err(DeviceError::Invalid(_))));
    let bad = PhotodiodeBand {
        threshold: 0.98,
        hysteresis: 0.05,
    };
    assert!(matches!(
        b.set_photodiode(Some(bad)).await,
        Err(DeviceError::Invalid(_))
    ));
    b.set_photodiode(Some(PhotodiodeBand::default()))
        .await
        .unwrap();
    // Seven quiet seconds are no error.
    let quiet = tokio::time::timeout(Duration::from_secs(7), b.next_light()).await;
    assert!(quiet.is_err(), "{quiet:?}");
    let LightEvent::Edge(e) = b.next_light().await.unwrap() else {
        panic!("expected the edge at 8 s");
    };
    assert!(e.rising);
    assert!(
        e.host_time.as_micros().abs_diff(8_000_005) <= 200,
        "{:?}",
        e.host_time
    );
    // Switched off, the light's falling edge never comes.
    b.set_photodiode(None).await.unwrap();
    assert!(matches!(b.next_light().await, Err(DeviceError::Invalid(_))));
}
