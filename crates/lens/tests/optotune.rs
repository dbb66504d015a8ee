//! The Optotune driver against the Lens Driver 4 simulator, over in-memory links (tokio's
//! paused clock: deterministic) and over a pty (real time, as another process would see it).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use dioptra_core::{DeviceError, Diopters, LinkError, PowerRange, VarifocalLens};
use dioptra_lens::optotune::protocol::{self, CurrentLimit, Mode};
use dioptra_lens::{LensLimits, Opener, Optotune, OptotuneConfig, OutOfRange};
use dioptra_sim::optotune::{serve, OptotuneSim, OptotuneSimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_transport::memory::{self, Faults, MemoryLink};
use dioptra_transport::ByteLink;

mod common;
use common::{Tap, TapCtl};

fn limits() -> LensLimits {
    LensLimits::new(PowerRange::new(Diopters(-1.0), Diopters(5.0)).unwrap())
}

fn cfg() -> OptotuneConfig {
    OptotuneConfig::new(limits())
}

/// A fresh simulator served on one end of a new in-memory link; returns the other end.
fn spawn_sim(cfg: OptotuneSimConfig) -> MemoryLink {
    let (host, mut dev) = memory::pair(4096);
    tokio::spawn(async move {
        let mut sim = OptotuneSim::new(cfg);
        let clock = TokioClock::new();
        let _ = serve(&mut dev, &mut sim, &clock).await;
    });
    host
}

async fn driver() -> (Optotune<Tap>, Arc<Mutex<TapCtl>>, Faults) {
    let host = spawn_sim(OptotuneSimConfig::default());
    let faults = host.faults();
    let ctl = Arc::new(Mutex::new(TapCtl::default()));
    let tap = Tap {
        inner: host,
        ctl: ctl.clone(),
    };
    let d = Optotune::connect(tap, cfg(), Arc::new(TokioClock::new()))
        .await
        .unwrap();
    (d, ctl, faults)
}

fn count(haystack: &[u8], needle: &[u8]) -> usize {
    haystack
        .windows(needle.len())
        .filter(|w| *w == needle)
        .count()
}

#[tokio::test(start_paused = true)]
async fn handshake_identifies_the_device_and_enters_focal_power_mode() {
    let (d, ctl, _) = driver().await;
    let info = d.info().unwrap();
    assert_eq!(info.firmware_type, b'A');
    assert_eq!(info.serial_number, "SIM00001");
    assert_eq!(info.device_id, "EL103000");
    assert_eq!(info.firmware_version.to_string(), "1.6.0.2");
    assert!((info.max_current_ma - 292.84).abs() < 1e-3);
    // Simulated EL-10-30 at 25 °C, limits 20..40 °C: about -1.9..6.49 D holdable.
    assert!(
        (info.device_range.min.0 + 1.9).abs() < 0.01,
        "{:?}",
        info.device_range
    );
    assert!(
        (info.device_range.max.0 - 6.485).abs() < 0.01,
        "{:?}",
        info.device_range
    );
    // The rig's range was the narrower one.
    assert_eq!(d.power_range(), limits().power);
    assert_eq!(d.mode(), Mode::FocalPower);
    let written = ctl.lock().unwrap().written.clone();
    assert!(written.starts_with(b"Start"));
    assert_eq!(count(&written, b"MwCA"), 1);
    // The default temperature limits (upper 40 °C = 0x0280, lower 20 °C = 0x0140) went out
    // before focal-power mode, which the device refuses without them; no PrTA.
    let limits_at = position(&written, b"PwTA\x02\x80\x01\x40").unwrap();
    assert!(limits_at < position(&written, b"MwCA").unwrap());
    assert_eq!(count(&written, b"PrTA"), 0);
    assert_eq!(d.fault(), None);
}

fn position(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

/// Without `PwTA` the simulated device stays in current mode, as the real one does: a client
/// that skips the limits (as the driver did) gets status bit 2 back and no focal-power mode.
#[tokio::test(start_paused = true)]
async fn the_device_refuses_focal_power_mode_without_temperature_limits() {
    let mut host = spawn_sim(OptotuneSimConfig::default());
    let frame = |body: &[u8]| {
        let mut v = body.to_vec();
        v.extend_from_slice(&protocol::crc16(body).to_le_bytes());
        v
    };
    host.write_all(b"Start").await.unwrap();
    let mut ready = [0u8; 7];
    host.read_exact(&mut ready, Duration::from_secs(1))
        .await
        .unwrap();
    host.write_all(&frame(b"MwCA")).await.unwrap();
    let mut r = [0u8; 12];
    host.read_exact(&mut r, Duration::from_secs(1))
        .await
        .unwrap();
    let range =
        protocol::decode::<protocol::SetFocalPowerMode>(&r, &protocol::Scaling::default()).unwrap();
    assert!(range
        .status
        .contains(protocol::Status::NO_TEMPERATURE_LIMITS));
    host.write_all(&frame(b"MMA")).await.unwrap();
    let mut r = [0u8; 8];
    host.read_exact(&mut r, Duration::from_secs(1))
        .await
        .unwrap();
    assert_eq!(r[3], 1, "still current mode: {r:?}");
}

#[tokio::test(start_paused = true)]
async fn configured_temperature_limits_are_what_is_sent() {
    let host = spawn_sim(OptotuneSimConfig::default());
    let ctl = Arc::new(Mutex::new(TapCtl::default()));
    let tap = Tap {
        inner: host,
        ctl: ctl.clone(),
    };
    let cool = cfg().with_temperature_limits_c(15.0, 30.0);
    Optotune::connect(tap, cool, Arc::new(TokioClock::new()))
        .await
        .unwrap();
    // 30 °C = 480 = 0x01E0 (upper first), 15 °C = 240 = 0x00F0.
    assert_eq!(
        count(&ctl.lock().unwrap().written, b"PwTA\x01\xe0\x00\xf0"),
        1
    );
    // Limits the device cannot take are refused before anything is sent.
    let host = spawn_sim(OptotuneSimConfig::default());
    let e = Optotune::connect(
        host,
        cfg().with_temperature_limits_c(40.0, 20.0),
        Arc::new(TokioClock::new()),
    )
    .await
    .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Invalid(m) if m.contains("temperature limits")),
        "{e:?}"
    );
}

/// A status warning is the caller's to report, typed and once per connect: the driver names
/// no lens (it does not know which eye it serves) and logs nothing above debug itself.
#[tokio::test(start_paused = true)]
async fn status_warnings_are_taken_once_per_connect_with_what_they_mean() {
    // A plain connect raises nothing, whatever power is then commanded within the range.
    let (mut d, _, _) = driver().await;
    assert_eq!(d.take_warnings(), vec![]);
    for p in [0.0, 0.5, 1.0] {
        d.set_power(Diopters(p)).await.unwrap();
        assert_eq!(d.status().await.unwrap(), protocol::Status(0), "{p} D");
    }
    assert_eq!(d.take_warnings(), vec![]);
    assert_eq!(d.warned(), protocol::Status(0));

    // Limits 30..40 °C on a lens at 25 °C: bit 7 in the PwTA, MwCA and Sr replies of one
    // connect, and in every later status read; one warning per (re)connect.
    let opens = Arc::new(Mutex::new(Vec::<Faults>::new()));
    let opens_in = opens.clone();
    let opener = Opener::new(move || {
        let host = spawn_sim(OptotuneSimConfig::default());
        opens_in.lock().unwrap().push(host.faults());
        async move { Ok::<_, LinkError>(host) }
    });
    let warm = cfg().with_temperature_limits_c(30.0, 40.0);
    let mut d = Optotune::connect_with(opener, warm, Arc::new(TokioClock::new()))
        .await
        .unwrap();
    let w = d.take_warnings();
    assert_eq!(w.len(), 1, "{w:?}");
    assert_eq!(
        w[0].condition,
        "the Lens Driver 4 reports temperature outside the user's limits"
    );
    assert!(
        w[0].meaning.contains("30..40 °C")
            && w[0].meaning.contains("devices.lens.temperature_limits_c"),
        "{}",
        w[0].meaning
    );
    assert_eq!(
        d.warned(),
        protocol::Status(protocol::Status::TEMPERATURE_OUTSIDE_LIMITS)
    );
    assert!(d
        .status()
        .await
        .unwrap()
        .contains(protocol::Status::TEMPERATURE_OUTSIDE_LIMITS));
    assert_eq!(d.take_warnings(), vec![], "reported once");
    // Unplugged and replugged: a new session reports it again, once.
    let first = opens.lock().unwrap()[0].clone();
    first.disconnect("unplugged");
    assert!(d.state().await.unwrap_err().needs_reconnect());
    d.state().await.unwrap();
    assert_eq!(d.reconnects(), 1);
    assert_eq!(d.take_warnings().len(), 1);
}

/// Status error bits at connect are refusals in the device's words, told apart from a broken
/// link.
#[tokio::test(start_paused = true)]
async fn status_errors_at_connect_are_refusals_naming_the_bits() {
    for (sim, words, code) in [
        (
            OptotuneSimConfig {
                eeprom_ok: false,
                ..OptotuneSimConfig::default()
            },
            "no or faulty lens EEPROM",
            protocol::Status::NO_EEPROM,
        ),
        (
            OptotuneSimConfig {
                hardware_complete: false,
                ..OptotuneSimConfig::default()
            },
            "not all hardware available",
            protocol::Status::NOT_ALL_HARDWARE,
        ),
    ] {
        let e = Optotune::connect(spawn_sim(sim), cfg(), Arc::new(TokioClock::new()))
            .await
            .unwrap_err();
        match &e {
            DeviceError::Refused { code: c, detail } => {
                assert!(detail.contains(words), "{detail}");
                assert!(u32::from(*c) & code != 0, "{c:#x}");
            }
            other => panic!("{other:?}"),
        }
        assert!(!e.needs_reconnect());
    }
    // An incompatible lens: MwCA answers E4.
    let sim = OptotuneSimConfig {
        lens_compatible: false,
        ..OptotuneSimConfig::default()
    };
    let e = Optotune::connect(spawn_sim(sim), cfg(), Arc::new(TokioClock::new()))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { code: 4, detail } if detail.contains("E4") && detail.contains("not compatible")),
        "{e:?}"
    );
    // Limits too wide for a 0..50 mA current window: the range inverts (bit 4): refused,
    // naming the inversion.
    let e = Optotune::connect(
        spawn_sim(OptotuneSimConfig::default()),
        narrow_current().with_temperature_limits_c(-30.0, 120.0),
        Arc::new(TokioClock::new()),
    )
    .await
    .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { detail, .. } if detail.contains("inversion")),
        "{e:?}"
    );
}

/// Rig current limits 0..50 mA: the holdable range is narrow (about -1.9..-0.8 D at 20..40 °C).
fn narrow_current() -> OptotuneConfig {
    OptotuneConfig::new(
        LensLimits::new(PowerRange::new(Diopters(-3.0), Diopters(5.0)).unwrap())
            .with_current_ma(0.0, 50.0),
    )
}

/// An error bit seen in a later status read stops focal-power control until one without it.
#[tokio::test(start_paused = true)]
async fn a_status_error_stops_focal_power_control_until_it_clears() {
    let host = spawn_sim(OptotuneSimConfig::default());
    let ctl = Arc::new(Mutex::new(TapCtl::default()));
    let tap = Tap {
        inner: host,
        ctl: ctl.clone(),
    };
    let mut d = Optotune::connect(tap, narrow_current(), Arc::new(TokioClock::new()))
        .await
        .unwrap();
    // Another client widens the limits until the range inverts.
    d.request(&protocol::SetTemperatureLimits {
        upper_c: 120.0,
        lower_c: -30.0,
    })
    .await
    .unwrap();
    let s = d.status().await.unwrap();
    assert!(s.contains(protocol::Status::FOCAL_POWER_INVERSION), "{s:?}");
    assert_eq!(
        d.fault(),
        Some(protocol::Status(protocol::Status::FOCAL_POWER_INVERSION))
    );
    let before = ctl.lock().unwrap().written.len();
    let e = d.set_power(Diopters(1.0)).await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { detail, .. } if detail.contains("focal-power control stopped")),
        "{e:?}"
    );
    assert_eq!(
        ctl.lock().unwrap().written.len(),
        before,
        "nothing was sent"
    );
    // The configured limits again: the range is back and so is control.
    d.refresh_range().await.unwrap();
    assert_eq!(d.status().await.unwrap().errors(), protocol::Status(0));
    d.set_power(Diopters(1.0)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn set_power_returns_on_the_wire_and_the_lens_settles() {
    let (mut d, ctl, _) = driver().await;
    let t = d.set_power(Diopters(1.5)).await.unwrap();
    // firmware type A: (1.5 + 5) * 200 = 1300 = 0x0514
    assert!(count(&ctl.lock().unwrap().written, b"PwDA\x05\x14\0\0") == 1);
    tokio::time::sleep(Duration::from_millis(3)).await;
    let early = d.state().await.unwrap();
    assert!(early.power.0 < 1.0, "{:?}", early.power);
    tokio::time::sleep(Duration::from_millis(100)).await;
    let s = d.state().await.unwrap();
    assert!((s.power.0 - 1.5).abs() <= 0.01, "{:?}", s.power);
    assert!(s.host_time > t);
    // 1.5 D needs (1.5 + 2) / 0.03 ≈ 117 mA on the simulated lens.
    let ma = s.current_ma.unwrap();
    assert!((ma - 116.7).abs() < 1.0, "{ma}");
    let temp = s.temperature_c.unwrap();
    assert!((24.0..30.0).contains(&temp), "{temp}");
    assert_eq!(s.settled, None);
}

#[tokio::test(start_paused = true)]
async fn every_command_round_trips() {
    let (mut d, _, _) = driver().await;
    assert_eq!(d.request(&protocol::GetFirmwareType).await.unwrap(), b'A');
    assert_eq!(d.request(&protocol::GetFirmwareBranch).await.unwrap(), 1);
    assert_eq!(
        d.request(&protocol::GetSerialNumber).await.unwrap(),
        "SIM00001"
    );
    assert_eq!(d.request(&protocol::GetDeviceId).await.unwrap(), "EL103000");
    let max = d
        .request(&protocol::SetMaxCurrent { ma: 250.0 })
        .await
        .unwrap();
    assert!((max - 250.0).abs() < 0.01);
    assert!((d.request(&protocol::GetMaxCurrent).await.unwrap() - 250.0).abs() < 0.01);
    // Scaling in the driver still uses the max read at connect; restore it.
    d.request(&protocol::SetMaxCurrent { ma: 292.84 })
        .await
        .unwrap();
    let up = d
        .request(&protocol::SetCurrentLimit {
            which: CurrentLimit::Upper,
            ma: 200.0,
        })
        .await
        .unwrap();
    assert!((up - 200.0).abs() < 0.1, "{up}");
    let lo = d
        .request(&protocol::SetCurrentLimit {
            which: CurrentLimit::Lower,
            ma: 10.0,
        })
        .await
        .unwrap();
    assert!((lo - 10.0).abs() < 0.1, "{lo}");
    assert!(
        (d.request(&protocol::GetCurrentLimit(CurrentLimit::Upper))
            .await
            .unwrap()
            - 200.0)
            .abs()
            < 0.1
    );
    assert!(
        (d.request(&protocol::GetCurrentLimit(CurrentLimit::Lower))
            .await
            .unwrap()
            - 10.0)
            .abs()
            < 0.1
    );
    let r = d
        .request(&protocol::SetTemperatureLimits {
            upper_c: 30.0,
            lower_c: 25.0,
        })
        .await
        .unwrap();
    assert_eq!(r.status, protocol::Status(0));
    // Upper current limit 200 mA caps the range: -2 + 0.03 * 200 = 4 D, less drift to 30 °C.
    assert!((r.max_d - 3.9).abs() < 0.02, "{r:?}");
    let t = d.temperature_c().await.unwrap();
    assert!((t - 25.0).abs() < 1.0, "{t}");
    assert_eq!(d.status().await.unwrap(), protocol::Status(0));

    d.use_current_mode().await.unwrap();
    assert_eq!(d.request(&protocol::GetMode).await.unwrap(), Mode::Current);
    d.set_current_ma(100.0).await.unwrap();
    let ma = d.request(&protocol::GetCurrent).await.unwrap();
    assert!((ma - 100.0).abs() < 0.2, "{ma}");
    // set_power is refused in current mode, before anything is sent.
    assert!(matches!(
        d.set_power(Diopters(1.0)).await,
        Err(DeviceError::Invalid(_))
    ));
    let range = d.use_focal_power_mode().await.unwrap();
    assert!(range.max.0 > 3.8);
    assert!(matches!(
        d.set_current_ma(1.0).await,
        Err(DeviceError::Invalid(_))
    ));
    d.request(&protocol::SetFocalPower { diopters: 2.0 })
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!((d.request(&protocol::GetFocalPower).await.unwrap() - 2.0).abs() < 0.01);
    // 5 D is beyond what the 200 mA limit reaches: the device clamps and says so (bit 3, a
    // warning: control goes on).
    d.request(&protocol::SetFocalPower { diopters: 5.0 })
        .await
        .unwrap();
    let s = d.status().await.unwrap();
    assert!(
        s.contains(protocol::Status::CANNOT_REACH_FOCAL_POWER),
        "{s:?}"
    );
    assert_eq!(s.errors(), protocol::Status(0));
    assert_eq!(d.fault(), None);
}

#[tokio::test(start_paused = true)]
async fn limits_clamp_or_refuse_and_refused_requests_are_never_sent() {
    let (mut d, ctl, _) = driver().await;
    // Clamp (default): 9 D becomes the rig's 5 D.
    d.set_power(Diopters(9.0)).await.unwrap();
    // (5 + 5) * 200 = 2000 = 0x07D0
    assert_eq!(count(&ctl.lock().unwrap().written, b"PwDA\x07\xD0\0\0"), 1);

    let host = spawn_sim(OptotuneSimConfig::default());
    let ctl = Arc::new(Mutex::new(TapCtl::default()));
    let cfg = OptotuneConfig::new(
        limits()
            .with_policy(OutOfRange::Refuse)
            .with_current_ma(0.0, 150.0),
    );
    let mut d = Optotune::connect(
        Tap {
            inner: host,
            ctl: ctl.clone(),
        },
        cfg,
        Arc::new(TokioClock::new()),
    )
    .await
    .unwrap();
    // The rig's current limits were programmed into the device.
    assert_eq!(count(&ctl.lock().unwrap().written, b"CwUA"), 1);
    let before = ctl.lock().unwrap().written.len();
    for bad in [9.0, -3.0, f32::NAN, f32::INFINITY] {
        let e = d.set_power(Diopters(bad)).await.unwrap_err();
        assert!(matches!(e, DeviceError::OutOfRange { .. }), "{e:?}");
    }
    assert_eq!(
        ctl.lock().unwrap().written.len(),
        before,
        "a refused request reached the wire"
    );
    // Current mode: 200 mA is over the rig's 150 mA.
    d.use_current_mode().await.unwrap();
    let before = ctl.lock().unwrap().written.len();
    assert!(matches!(
        d.set_current_ma(200.0).await,
        Err(DeviceError::OutOfRange { .. })
    ));
    assert_eq!(ctl.lock().unwrap().written.len(), before);
}

#[tokio::test(start_paused = true)]
async fn crc_errors_both_ways_are_typed_and_the_driver_recovers() {
    let (mut d, ctl, _) = driver().await;
    // Host to device: the device answers N.
    ctl.lock().unwrap().corrupt_next_write = true;
    let e = d.temperature_c().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("answered N")),
        "{e:?}"
    );
    assert!(d.temperature_c().await.is_ok());
    // Device to host: the reply's CRC fails.
    ctl.lock().unwrap().corrupt_next_read = true;
    let e = d.temperature_c().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("CRC") || m.contains("\\r\\n")),
        "{e:?}"
    );
    assert!(d.temperature_c().await.is_ok());
    // A corrupted PwDA has no reply of its own: its N arrives unsolicited and is counted.
    ctl.lock().unwrap().corrupt_next_write = true;
    d.set_power(Diopters(1.0)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(5)).await;
    d.temperature_c().await.unwrap();
    assert_eq!(d.stray_crc_errors(), 1);
}

#[tokio::test(start_paused = true)]
async fn garbage_from_the_device_is_drained_and_reported() {
    let (mut d, ctl, faults) = driver().await;
    faults.inject(b"\r\n\xFFgarbage N\r\nE\x01");
    assert!(d.temperature_c().await.is_ok());
    // Garbage that arrives after the command, where the reply should be (the command is
    // swallowed so that only the garbage comes back).
    ctl.lock().unwrap().swallow_writes = true;
    let injector = faults.clone();
    tokio::spawn(async move {
        tokio::time::sleep(Duration::from_micros(500)).await;
        injector.inject(b"\x00\x01\x02\x03\x04\x05\x06\x07\x08\x09");
    });
    let e = d.temperature_c().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("reply")),
        "{e:?}"
    );
    ctl.lock().unwrap().swallow_writes = false;
    assert!(d.temperature_c().await.is_ok());
}

/// A state read dropped after its command went out (as the rig's lens task drops one when a
/// new command arrives): its reply, still in flight, is let through and dropped, not read as
/// the next command's reply.
#[tokio::test(start_paused = true)]
async fn a_dropped_read_does_not_misframe_the_next_reply() {
    let (mut d, _, faults) = driver().await;
    faults.set_latency(Duration::from_millis(5));
    for _ in 0..3 {
        let cut = tokio::time::timeout(Duration::from_millis(1), d.state()).await;
        assert!(cut.is_err(), "the read was cut short");
        let t = d.temperature_c().await.unwrap();
        assert!((t - 25.0).abs() < 1.0, "{t}");
        d.set_power(Diopters(1.0)).await.unwrap();
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!((d.state().await.unwrap().power.0 - 1.0).abs() < 0.01);
    assert_eq!(d.reconnects(), 0);
}

#[tokio::test(start_paused = true)]
async fn timeout_is_typed_and_leaves_the_link_usable() {
    let (mut d, ctl, _) = driver().await;
    ctl.lock().unwrap().swallow_writes = true;
    let e = d.state().await.unwrap_err();
    assert_eq!(e, DeviceError::Link(LinkError::Timeout { ms: 200 }));
    assert!(d.is_connected());
    ctl.lock().unwrap().swallow_writes = false;
    assert!(d.state().await.is_ok());
}

#[tokio::test(start_paused = true)]
async fn unplug_mid_command_then_reconnect_on_the_next_call() {
    // Each open is a replug: a new link to a freshly powered simulator.
    let current: Arc<Mutex<Option<Faults>>> = Arc::default();
    let slot = current.clone();
    let opens = Arc::new(Mutex::new(0));
    let opens_in = opens.clone();
    let opener = Opener::new(move || {
        let host = spawn_sim(OptotuneSimConfig::default());
        *slot.lock().unwrap() = Some(host.faults());
        *opens_in.lock().unwrap() += 1;
        async move { Ok::<_, LinkError>(host) }
    });
    let mut d = Optotune::connect_with(opener, cfg(), Arc::new(TokioClock::new()))
        .await
        .unwrap();
    d.set_power(Diopters(2.0)).await.unwrap();

    // Replies take 5 ms; the cable is pulled 1 ms into a read.
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

    // The next call reopens and handshakes again, which resets the output current: the
    // driver re-sends the last commanded power before the call reports anything.
    let s = d.state().await.unwrap();
    assert_eq!(d.reconnects(), 1);
    assert_eq!(*opens.lock().unwrap(), 2);
    assert!(s.power.0 < 0.0, "{s:?}");
    tokio::time::sleep(Duration::from_millis(100)).await;
    let s = d.state().await.unwrap();
    assert!((s.power.0 - 2.0).abs() < 0.01, "{s:?}");
    d.set_power(Diopters(1.0)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!((d.state().await.unwrap().power.0 - 1.0).abs() < 0.01);
}

#[tokio::test(start_paused = true)]
async fn without_an_opener_a_lost_link_stays_lost() {
    let (mut d, _, faults) = driver().await;
    faults.disconnect("unplugged");
    assert!(d.state().await.unwrap_err().needs_reconnect());
    let e = d.set_power(Diopters(1.0)).await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Link(LinkError::Disconnected(m)) if m.contains("no way to reopen")),
        "{e:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_device_that_never_answers_the_handshake() {
    let (host, _dev) = memory::pair(64);
    let e = Optotune::connect(host, cfg(), Arc::new(TokioClock::new()))
        .await
        .unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("handshake")),
        "{e:?}"
    );
}

mod pty {
    use super::*;
    use dioptra_transport::discovery::SerialIdentity;
    use dioptra_transport::pty::PtyPair;
    use dioptra_transport::serial::{SerialLink, SerialSettings};

    /// Real time: the simulator is served as `dioptra sim optotune --pty` serves it.
    fn serve_on_pty() -> std::path::PathBuf {
        let PtyPair {
            mut master,
            slave_path,
        } = PtyPair::open().unwrap();
        tokio::spawn(async move {
            let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
            let clock = TokioClock::new();
            let _ = serve(&mut master, &mut sim, &clock).await;
        });
        slave_path
    }

    #[tokio::test]
    async fn driver_over_a_pty_sets_and_reads_back() {
        let path = serve_on_pty();
        let link = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
        let mut d = Optotune::connect(link, cfg(), Arc::new(TokioClock::new()))
            .await
            .unwrap();
        d.set_power(Diopters(1.5)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(150)).await;
        let s = d.state().await.unwrap();
        assert!((s.power.0 - 1.5).abs() <= 0.01, "{s:?}");
        // A second client after the first closes: its handshake resets the output current,
        // so the lens relaxes to its zero-current power (-2 D on the simulated lens).
        drop(d);
        let link = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
        let mut d = Optotune::connect(link, cfg(), Arc::new(TokioClock::new()))
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(150)).await;
        assert!((d.state().await.unwrap().power.0 + 2.0).abs() <= 0.01);
    }

    /// A simulator on a new pty, as [`serve_on_pty`], with the task serving it: aborting the
    /// task closes the pty's master, which hangs up the driver as an unplug does.
    fn plug_on_pty() -> (std::path::PathBuf, tokio::task::JoinHandle<()>) {
        let PtyPair {
            mut master,
            slave_path,
        } = PtyPair::open().unwrap();
        let task = tokio::spawn(async move {
            let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
            let clock = TokioClock::new();
            let _ = serve(&mut master, &mut sim, &clock).await;
        });
        (slave_path, task)
    }

    /// A sysfs tree in which the tty at `/dev/pts/N` belongs to a USB device with a serial
    /// number, as `/sys/class/tty/ttyACM0` belongs to a Lens Driver 4.
    struct FakeSys(tempfile::TempDir);

    impl FakeSys {
        fn new() -> Self {
            let d = tempfile::tempdir().unwrap();
            std::fs::create_dir_all(d.path().join("class/tty")).unwrap();
            FakeSys(d)
        }
        /// sysfs's name for the tty at `path` ("/dev/pts/5" is "pts!5").
        fn name(path: &std::path::Path) -> String {
            let rest = path.strip_prefix("/dev").unwrap();
            rest.to_string_lossy().replace('/', "!")
        }
        fn plug(&self, tty: &std::path::Path, usb_serial: &str) {
            let usb = self.0.path().join("devices/usb1").join(usb_serial);
            std::fs::create_dir_all(usb.join("if0")).unwrap();
            for (k, v) in [
                ("idVendor", "03eb"),
                ("idProduct", "2018"),
                ("serial", usb_serial),
            ] {
                std::fs::write(usb.join(k), format!("{v}\n")).unwrap();
            }
            let class = self
                .0
                .path()
                .join("devices/virtual/tty")
                .join(Self::name(tty));
            std::fs::create_dir_all(&class).unwrap();
            std::os::unix::fs::symlink(usb.join("if0"), class.join("device")).unwrap();
            std::os::unix::fs::symlink(
                &class,
                self.0.path().join("class/tty").join(Self::name(tty)),
            )
            .unwrap();
        }
        fn unplug(&self, tty: &std::path::Path) {
            std::fs::remove_file(self.0.path().join("class/tty").join(Self::name(tty))).unwrap();
        }
        fn root(&self) -> std::path::PathBuf {
            self.0.path().to_path_buf()
        }
    }

    /// Calls `state` until it answers: the first call after an unplug reports the loss, the
    /// next reopens (a deadline for a real pty, not a timing assertion).
    async fn until_answered(d: &mut Optotune<SerialLink>) -> dioptra_core::LensState {
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        loop {
            match d.state().await {
                Ok(s) => return s,
                Err(e) if std::time::Instant::now() < deadline => {
                    let _ = e;
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                Err(e) => panic!("no answer after the replug: {e}"),
            }
        }
    }

    #[tokio::test]
    async fn a_lens_known_by_its_serial_number_is_found_again_on_a_new_tty() {
        let sys = FakeSys::new();
        let (first, task) = plug_on_pty();
        sys.plug(&first, "LD4-RIGHT");
        let opener = Opener::serial_in(
            sys.root(),
            SerialIdentity::at(&first).with_usb_serial("LD4-RIGHT"),
            SerialSettings::baud(115_200),
        );
        let mut d = Optotune::connect_with(opener, cfg(), Arc::new(TokioClock::new()))
            .await
            .unwrap();
        assert!(
            format!("{d:?}").contains(&*first.to_string_lossy()),
            "{d:?}"
        );
        d.set_power(Diopters(1.5)).await.unwrap();
        // Unplugged; it comes back on another tty, and the old one is gone.
        task.abort();
        sys.unplug(&first);
        let (second, _task) = plug_on_pty();
        assert_ne!(first, second);
        sys.plug(&second, "LD4-RIGHT");
        until_answered(&mut d).await;
        assert_eq!(d.reconnects(), 1);
        assert!(
            format!("{d:?}").contains(&*second.to_string_lossy()),
            "{d:?}"
        );
        // The last commanded power was sent again after the new session's handshake.
        tokio::time::sleep(Duration::from_millis(150)).await;
        let s = d.state().await.unwrap();
        assert!((s.power.0 - 1.5).abs() <= 0.01, "{s:?}");
    }

    #[tokio::test]
    async fn another_unit_on_the_configured_path_is_refused_naming_both_serial_numbers() {
        let sys = FakeSys::new();
        let (path, _task) = plug_on_pty();
        sys.plug(&path, "LD4-LEFT");
        let opener = Opener::serial_in(
            sys.root(),
            SerialIdentity::at(&path).with_usb_serial("LD4-RIGHT"),
            SerialSettings::baud(115_200),
        );
        let e = Optotune::connect_with(opener, cfg(), Arc::new(TokioClock::new()))
            .await
            .unwrap_err();
        let m = e.to_string();
        assert!(
            m.contains(&*path.to_string_lossy())
                && m.contains("\"LD4-LEFT\"")
                && m.contains("\"LD4-RIGHT\""),
            "{m}"
        );
        assert!(
            e.needs_reconnect(),
            "the right unit may still be plugged in: {e:?}"
        );
    }

    /// The exact bytes the `opto`-family Python clients send, with the reply sizes their
    /// struct formats expect (payload + CRC + CRLF).
    #[tokio::test]
    async fn other_clients_bytes_work_unchanged() {
        let path = serve_on_pty();
        let mut port = SerialLink::open(&path, SerialSettings::baud(115_200)).unwrap();
        let wait = Duration::from_secs(2);
        port.write_all(b"Start").await.unwrap();
        let mut ready = [0u8; 7];
        port.read_exact(&mut ready, wait).await.unwrap();
        assert_eq!(&ready, b"Ready\r\n");
        let with_crc = |body: &[u8]| {
            let mut v = body.to_vec();
            v.extend_from_slice(&protocol::crc16(body).to_le_bytes());
            v
        };
        let exchanges: &[(&[u8], usize)] = &[
            (b"H", 2),                    // '>xs'
            (b"V\0", 7),                  // '>xBBHH', opto sends a zero byte after V
            (b"IR\0\0\0\0\0\0\0\0", 10),  // '>xx8s'
            (b"CrMA\0\0", 5),             // '>xxxh'
            (b"PwTA\x02\x80\x01\x40", 7), // 40 and 20 °C: '>xxBhh'
            (b"MMA", 4),                  // '>xxxB'
            (b"X", 9),                    // '>x8s'
            (b"MwCA", 8),                 // '>xxxBhh'
            (b"PrDA\0\0\0\0", 4),         // '>xxh'
            (b"TCA", 5),                  // '>xxxh'
            (b"Ar\0\0", 3),               // '>xh'
            (b"PrTA\0\0\0\0", 7),
            (b"MwDA", 3), // '>xxx'
        ];
        for (body, payload_len) in exchanges {
            port.write_all(&with_crc(body)).await.unwrap();
            let mut r = vec![0u8; payload_len + 4];
            port.read_exact(&mut r, wait).await.unwrap();
            assert!(protocol::check_frame(&r).is_ok(), "{body:?} -> {r:?}");
        }
        // Aw (their set_current packs '>H') has no reply; the next query still lines up.
        port.write_all(&with_crc(b"Aw\x05\x76")).await.unwrap();
        port.write_all(&with_crc(b"Ar\0\0")).await.unwrap();
        let mut r = [0u8; 7];
        port.read_exact(&mut r, wait).await.unwrap();
        assert_eq!(i16::from_be_bytes([r[1], r[2]]), 0x0576);
        // pyopto's mode(): 'Mw' + code + 'A', then it checks the echo's second byte is the
        // code (the echo is MSA for MwSA); an `E` reply makes it raise.
        for code in [b'S', b'T', b'Q', b'D', b'C'] {
            port.write_all(&with_crc(&[b'M', b'w', code, b'A']))
                .await
                .unwrap();
            let n = if code == b'C' { 8 } else { 3 };
            let mut r = vec![0u8; n + 4];
            port.read_exact(&mut r, wait).await.unwrap();
            assert_eq!((r[0], r[1], r[2]), (b'M', code, b'A'), "{r:?}");
        }
        // An unknown command: E3 ("command not recognised").
        port.write_all(&with_crc(b"Qq")).await.unwrap();
        let mut r = [0u8; 6];
        port.read_exact(&mut r, wait).await.unwrap();
        assert_eq!(
            protocol::check_frame(&r),
            Err(protocol::ProtocolError::CommandError { code: 3 })
        );
    }
}

/// A device that answers the handshake and then every command with random bytes: the driver
/// returns errors (or, by chance, values) and never panics.
#[tokio::test(start_paused = true)]
async fn random_replies_never_panic() {
    for seed in 1..=200u64 {
        let (host, mut dev) = memory::pair(4096);
        tokio::spawn(async move {
            let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
            let mut buf = [0u8; 64];
            while let Ok(n) = dev.read(&mut buf, Duration::from_secs(1)).await {
                if buf[..n].windows(5).any(|w| w == b"Start") {
                    let _ = dev.write_all(b"Ready\r\n").await;
                    continue;
                }
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let len = (x % 20) as usize;
                let noise: Vec<u8> = (0..len)
                    .map(|i| (x >> (i % 8 * 8)) as u8 ^ b"HN\r\nE"[i % 5])
                    .collect();
                let _ = dev.write_all(&noise).await;
            }
        });
        let clock = Arc::new(TokioClock::new());
        if let Ok(mut d) = Optotune::connect(host, cfg(), clock).await {
            let _ = d.set_power(Diopters(1.0)).await;
            let _ = d.state().await;
        }
    }
}

/// A previous client left half a command in the device; its `E`/`N` answers precede `Ready`.
#[tokio::test(start_paused = true)]
async fn handshake_skips_stale_replies_from_a_previous_client() {
    let mut host = spawn_sim(OptotuneSimConfig::default());
    host.write_all(b"MM").await.unwrap();
    let d = Optotune::connect(host, cfg(), Arc::new(TokioClock::new())).await;
    assert!(d.is_ok(), "{d:?}");
}

#[tokio::test(start_paused = true)]
async fn the_range_follows_the_temperature_limits() {
    let connect = |limits: (f32, f32)| async move {
        Optotune::connect(
            spawn_sim(OptotuneSimConfig::default()),
            cfg().with_temperature_limits_c(limits.0, limits.1),
            Arc::new(TokioClock::new()),
        )
        .await
        .unwrap()
    };
    // Compensating up to 80 °C costs 0.02 D/°C × 55 °C of the top of the device's range
    // (6.785 -> 5.685 D): still above the rig's 5 D.
    let d = connect((20.0, 80.0)).await;
    assert_eq!(d.power_range().max.0, 5.0);
    // Up to 120 °C: 6.785 - 0.02 × 95 = 4.885 D, now the binding limit; taken from the PwTA
    // reply.
    let mut d = connect((20.0, 120.0)).await;
    assert!(
        (d.power_range().max.0 - 4.885).abs() < 0.01,
        "{:?}",
        d.power_range()
    );
    let r = d.refresh_range().await.unwrap();
    assert!((r.max.0 - 4.885).abs() < 0.01, "{r:?}");
}

/// Thousands of state reads cut short at random points of their reply, which arrives a byte
/// at a time as on a 115200-baud line: before it, mid-frame, or just after. The next command
/// reads the rest of the cut frame and then its own reply; no reply is ever misattributed.
#[tokio::test(start_paused = true)]
async fn reads_cut_at_random_points_never_misattribute_a_reply() {
    let (mut d, _, faults) = driver().await;
    let byte = Duration::from_nanos(86_806);
    faults.set_latency(Duration::from_micros(300));
    faults.set_byte_time(byte);
    // xorshift: a fixed sequence of cut points.
    let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut next = || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    };
    let (mut cut, mut whole) = (0, 0);
    for i in 0..3000u32 {
        // From nothing read to past the whole state read (its exchanges' replies).
        let at = Duration::from_nanos(next() % 10_000_000);
        match tokio::time::timeout(at, d.state()).await {
            Err(_) => cut += 1,
            Ok(r) => {
                r.unwrap();
                whole += 1;
            }
        }
        if i % 10 == 0 {
            let target = Diopters(((i / 10) % 5) as f32 * 0.5);
            d.set_power(target).await.unwrap();
            tokio::time::sleep(Duration::from_millis(40)).await;
            let s = d.state().await.unwrap();
            assert!(
                (s.power.0 - target.0).abs() < 0.02,
                "{i}: {s:?} for {target:?}"
            );
        } else {
            // The simulated lens warms slowly with its current; another reply read as this
            // one would be far off (or not parse). The rest of a cut frame is read as what it
            // is, without waiting out the reply timeout (simulated time: exact).
            let t0 = tokio::time::Instant::now();
            let t = d.temperature_c().await.unwrap();
            assert!((20.0..40.0).contains(&t), "{i}: {t}");
            let took = t0.elapsed();
            assert!(
                took < Duration::from_millis(20),
                "{i}: the next read took {took:?}"
            );
        }
    }
    assert!(cut > 500 && whole > 500, "{cut} cut, {whole} whole");
    assert_eq!(d.reconnects(), 0);
}
