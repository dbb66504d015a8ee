//! The dioptra lens controller driver against its simulator, over in-memory links (tokio's
//! paused clock) and over a pty (real time).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, Diopters, LinkError, PowerRange, VarifocalLens};
use dioptra_lens::{ControllerConfig, LensController, LensLimits, Opener, OutOfRange};
use dioptra_protocol::{decode_frame, Message};
use dioptra_sim::lens_controller::{serve, LensControllerSim, LensControllerSimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_transport::memory::{self, Faults, MemoryLink};

mod common;
use common::{Tap, TapCtl};

fn cfg() -> ControllerConfig {
    ControllerConfig::new(LensLimits::new(
        PowerRange::new(Diopters(-1.0), Diopters(5.0)).unwrap(),
    ))
}

fn spawn_sim(cfg: LensControllerSimConfig, clock: TokioClock) -> MemoryLink {
    let (host, mut dev) = memory::pair(4096);
    tokio::spawn(async move {
        let mut sim = LensControllerSim::new(cfg);
        let _ = serve(&mut dev, &mut sim, &clock).await;
    });
    host
}

async fn driver(
    cfg: ControllerConfig,
) -> (LensController<Tap>, Arc<Mutex<TapCtl>>, Faults, TokioClock) {
    let clock = TokioClock::new();
    let host = spawn_sim(LensControllerSimConfig::default(), clock);
    let faults = host.faults();
    let ctl = Arc::new(Mutex::new(TapCtl::default()));
    let d = LensController::connect(
        Tap {
            inner: host,
            ctl: ctl.clone(),
        },
        cfg,
        Arc::new(clock),
    )
    .await
    .unwrap();
    (d, ctl, faults, clock)
}

/// The SetFocalPower requests the driver put on the wire.
fn powers_sent(ctl: &Mutex<TapCtl>) -> Vec<f32> {
    let written = ctl.lock().unwrap().written.clone();
    written
        .split_inclusive(|b| *b == 0)
        .filter_map(|f| decode_frame(f).ok())
        .filter_map(|f| match f.message {
            Message::SetFocalPower { diopters, .. } => Some(diopters),
            _ => None,
        })
        .collect()
}

#[tokio::test(start_paused = true)]
async fn hello_limits_and_clock_sync() {
    let (d, _, _, clock) = driver(cfg()).await;
    let info = d.info().unwrap();
    assert_eq!(info.serial.as_str(), "DLC-SIM-0001");
    let limits = d.device_limits().unwrap();
    assert_eq!(
        d.power_range(),
        PowerRange::new(Diopters(limits.min_power_d.max(-1.0)), Diopters(5.0)).unwrap()
    );
    // The simulated device clock starts 5 s ahead; mapping it back lands on host time.
    let now = clock.now();
    let device_now = LensControllerSim::new(LensControllerSimConfig::default()).device_time_us(now);
    let mapped = d.device_to_host(device_now).unwrap();
    assert!(
        mapped.signed_diff_ns(now).abs() < 200_000,
        "{mapped} vs {now}"
    );
}

#[tokio::test(start_paused = true)]
async fn set_power_settles_and_state_carries_both_clocks() {
    let (mut d, ctl, _, _) = driver(cfg()).await;
    let t = d.set_power(Diopters(1.5)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let s = d.state_detailed().await.unwrap();
    assert!((s.state.power.0 - 1.5).abs() < 0.02, "{s:?}");
    assert_eq!(s.state.settled, Some(true));
    assert!(s.state.temperature_c.is_some() && s.state.current_ma.is_some());
    assert!(s.state.host_time > t);
    let at = s.measured_at.unwrap();
    assert!(
        at.signed_diff_ns(s.state.host_time).abs() < 1_000_000,
        "{at} vs {}",
        s.state.host_time
    );
    assert_eq!(powers_sent(&ctl), [1.5]);
    assert!(d.take_refusal().is_none());
}

#[tokio::test(start_paused = true)]
async fn drift_is_tracked_over_time() {
    let (mut d, _, _, _) = driver(cfg()).await;
    for _ in 0..6 {
        tokio::time::sleep(Duration::from_secs(1)).await;
        d.state().await.unwrap();
    }
    let ppm = d.drift_ppm().unwrap();
    assert!((ppm - 30.0).abs() < 10.0, "{ppm}");
}

#[tokio::test(start_paused = true)]
async fn limits_clamp_or_refuse_before_the_wire() {
    let (mut d, ctl, _, _) = driver(cfg()).await;
    d.set_power(Diopters(9.0)).await.unwrap();
    assert_eq!(powers_sent(&ctl), [5.0]);
    let refuse = ControllerConfig::new(cfg().limits.with_policy(OutOfRange::Refuse));
    let (mut d, ctl, _, _) = driver(refuse).await;
    for bad in [9.0, -4.0, f32::NAN] {
        assert!(matches!(
            d.set_power(Diopters(bad)).await,
            Err(DeviceError::OutOfRange { .. })
        ));
    }
    assert!(powers_sent(&ctl).is_empty());
}

#[tokio::test(start_paused = true)]
async fn garbage_corruption_and_timeouts_are_typed() {
    let (mut d, ctl, faults, _) = driver(cfg()).await;
    // Garbage between frames is skipped by the stream decoder.
    faults.inject(b"\x01\x02garbage\x00\xff\xfe\x00");
    assert!(d.state().await.is_ok());
    // A corrupted reply: the request times out and says why.
    ctl.lock().unwrap().corrupt_next_read = true;
    let e = d.state().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("garbled")),
        "{e:?}"
    );
    // A device that stops answering.
    ctl.lock().unwrap().swallow_writes = true;
    let e = d.state().await.unwrap_err();
    assert!(
        matches!(
            e,
            DeviceError::Link(LinkError::Timeout { .. }) | DeviceError::Protocol(_)
        ),
        "{e:?}"
    );
    assert!(d.is_connected());
    ctl.lock().unwrap().swallow_writes = false;
    d.state().await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn unplug_mid_command_then_reconnect_on_the_next_call() {
    let clock = TokioClock::new();
    let current: Arc<Mutex<Option<Faults>>> = Arc::default();
    let slot = current.clone();
    let opener = Opener::new(move || {
        let host = spawn_sim(LensControllerSimConfig::default(), clock);
        *slot.lock().unwrap() = Some(host.faults());
        async move { Ok::<_, LinkError>(host) }
    });
    let mut d = LensController::connect_with(opener, cfg(), Arc::new(clock))
        .await
        .unwrap();
    let faults = current.lock().unwrap().clone().unwrap();
    faults.set_latency(Duration::from_millis(5));
    let puller = faults.clone();
    tokio::spawn(async move {
        tokio::time::sleep(Duration::from_millis(1)).await;
        puller.disconnect("cable pulled");
    });
    let e = d.state().await.unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");
    assert!(!d.is_connected());
    d.set_power(Diopters(2.0)).await.unwrap();
    assert_eq!(d.reconnects(), 1);
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!((d.state().await.unwrap().power.0 - 2.0).abs() < 0.02);
}

#[tokio::test]
async fn over_a_pty() {
    use dioptra_transport::pty::PtyPair;
    use dioptra_transport::serial::{SerialLink, SerialSettings};
    let PtyPair {
        mut master,
        slave_path,
    } = PtyPair::open().unwrap();
    tokio::spawn(async move {
        let mut sim = LensControllerSim::new(LensControllerSimConfig::default());
        let _ = serve(&mut master, &mut sim, &TokioClock::new()).await;
    });
    let link = SerialLink::open(&slave_path, SerialSettings::baud(115_200)).unwrap();
    let mut d = LensController::connect(link, cfg(), Arc::new(TokioClock::new()))
        .await
        .unwrap();
    d.set_power(Diopters(1.5)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(150)).await;
    let s = d.state().await.unwrap();
    assert!((s.power.0 - 1.5).abs() < 0.02, "{s:?}");
}

#[tokio::test(start_paused = true)]
async fn only_setting_powers_never_stalls_on_unread_replies() {
    // A small pipe: unread Acks would fill it within a few dozen sets.
    let clock = TokioClock::new();
    let (host, mut dev) = memory::pair(256);
    tokio::spawn(async move {
        let mut sim = LensControllerSim::new(LensControllerSimConfig::default());
        let _ = serve(&mut dev, &mut sim, &clock).await;
    });
    let mut d = LensController::connect(host, cfg(), Arc::new(clock))
        .await
        .unwrap();
    let sets = async {
        for k in 0..2_000 {
            d.set_power(Diopters(if k % 2 == 0 { 1.0 } else { 2.0 }))
                .await
                .unwrap();
            tokio::task::yield_now().await;
        }
    };
    // A stall shows as this timeout (paused time jumps to it once every task is blocked).
    tokio::time::timeout(Duration::from_secs(10), sets)
        .await
        .expect("set_power stalled");
    assert!(d.take_refusal().is_none());
    assert!(d.state().await.is_ok());
}

#[tokio::test(start_paused = true)]
async fn a_scheduled_power_applies_at_its_host_time() {
    let (mut d, _, _, clock) = driver(cfg()).await;
    d.set_power(Diopters(0.0)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    let at = clock.now() + Duration::from_millis(20);
    d.set_power_at(Diopters(2.0), at).await.unwrap();
    tokio::time::sleep(Duration::from_millis(15)).await;
    let before = d.state().await.unwrap();
    assert!(before.power.0.abs() < 0.02, "moved early: {before:?}");
    tokio::time::sleep(Duration::from_millis(60)).await;
    let after = d.state().await.unwrap();
    assert!((after.power.0 - 2.0).abs() < 0.02, "{after:?}");
    assert!(d.take_refusal().is_none());
    // More than 1 s ahead: the device refuses, after the call returned.
    d.set_power_at(Diopters(1.0), clock.now() + Duration::from_secs(5))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(5)).await;
    d.state().await.unwrap();
    assert!(matches!(
        d.take_refusal(),
        Some(DeviceError::Refused { .. })
    ));
}
