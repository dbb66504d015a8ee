//! The DLPC350 driver against the simulated controller on the in-memory HID link, on tokio's
//! paused clock. The simulator decodes the bytes on its own (sim/src/dlpc350.rs), so these
//! tests check the driver's layouts; hand-assembled reports check what other clients send.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    DeviceError, Diopters, PlaneSchedule, PlaneSequencer, SequencerEvent, SequencerFault,
};
use dioptra_sim::dlpc350::{self as sim, Dlpc350SimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_sync::dlpc350::protocol::{PatternDisplay, SequenceAction, SetExposure};
use dioptra_sync::dlpc350::{Dlpc350, Dlpc350Config, FAULT_SEQUENCER_STOPPED};
use dioptra_transport::hid::memory::MemoryHidLink;
use dioptra_transport::HidLink;

fn rig() -> (Dlpc350<MemoryHidLink>, sim::Dlpc350Sim) {
    let (link, sim) = sim::new(Dlpc350SimConfig::default());
    let driver = Dlpc350::new(link, Arc::new(TokioClock::new()), Dlpc350Config::default());
    (driver, sim)
}

fn four_planes(period_us: u64, settle_us: u64) -> PlaneSchedule {
    PlaneSchedule::new(
        vec![Diopters(0.2), Diopters(0.8), Diopters(1.4), Diopters(2.0)],
        Duration::from_micros(period_us),
        Duration::from_micros(settle_us),
    )
    .unwrap()
}

#[tokio::test(start_paused = true)]
async fn programs_a_four_plane_sequence_in_order_and_runs_it() {
    let (mut d, sim) = rig();
    let v = d.version().await.unwrap();
    assert_eq!(v.application.to_string(), "3.0.0");
    d.program(&four_planes(4166, 1000)).await.unwrap();

    let codes: Vec<(bool, u16)> = sim.log().iter().map(|l| (l.read, l.code)).collect();
    assert!(
        sim.log().iter().skip(1).all(|l| !l.nack),
        "{:#?}",
        sim.log()
    );
    let expected: Vec<(bool, u16)> = vec![
        (true, 0x0205),
        (false, 0x1A24), // stop
        (true, 0x1A24),  // read back: stopped
        (false, 0x0200), // power: normal
        (true, 0x1A0A),  // hardware status
        (true, 0x1A1B),  // display mode: video
        (false, 0x1A1B), // pattern display mode
        (true, 0x1A1B),  // 100 ms later: pattern
        (false, 0x1A22), // video-port source
        (false, 0x1A31), // pattern config
        (false, 0x1A23), // VSYNC trigger
        (false, 0x1A29), // exposure and period
        (false, 0x1A1D), // TRIG_OUT_1
        (false, 0x1A1E), // TRIG_OUT_2
        (false, 0x1A33), // open pattern mailbox
        (false, 0x1A32), // address 0
        (false, 0x1A34), // entries
        (false, 0x1A33), // close
        (false, 0x1A33), // read back: open
        (false, 0x1A32),
        (true, 0x1A34),
        (false, 0x1A33), // close
        (false, 0x1A1A), // validate
        (true, 0x1A1A),  // busy
        (true, 0x1A1A),  // result
    ];
    assert_eq!(codes, expected);
    let log = sim.log();
    let payload = |code: u16, read: bool| {
        log.iter()
            .find(|l| l.code == code && l.read == read)
            .unwrap()
            .payload
            .clone()
    };
    // Byte vectors, from the programmer's guide layouts (the same TI's dlpc350_api.cpp and
    // pycrafter4500 build): pattern config = entries - 1, repeat, TRIG_OUT_2 every - 1,
    // images - 1; exposure and period as u32 LE; LUT entries 3 bytes each: trigger | pattern
    // << 2, depth | LEDs << 4, invert | black << 1 | swap << 2 | trig-out-prev << 3.
    assert_eq!(payload(0x1A31, false), vec![3, 1, 3, 0]);
    assert_eq!(
        payload(0x1A29, false),
        vec![0x5e, 0x0c, 0, 0, 0x46, 0x10, 0, 0],
        "3166 us exposure, 4166 us period"
    );
    assert_eq!(payload(0x0200, false), vec![0], "normal power");
    assert_eq!(payload(0x1A1B, false), vec![1], "pattern display mode");
    assert_eq!(
        payload(0x1A34, false),
        vec![0x01, 0x76, 0x06, 0x07, 0x76, 0x02, 0x0b, 0x76, 0x02, 0x0f, 0x76, 0x02],
        "pattern 0 on VSYNC with a buffer swap, 1-3 continuing; 6 bits, RGB; black fill"
    );
    let lut: Vec<_> = sim.lut().into_iter().map(Option::unwrap).collect();
    assert_eq!(lut.len(), 4);
    assert!(lut.iter().all(|e| e.bit_depth == 6 && e.leds == 0b111));
    assert_eq!(lut[0].trigger, sim::Trigger::ExternalPositive);
    assert!(lut[0].buffer_swap);
    // 1000 us of settle time is dark time: black-filled, as TI's SDK fills it.
    assert!(lut.iter().all(|e| e.insert_black));

    let mut patterns = sim.subscribe();
    let before = sim.log().len();
    d.start().await.unwrap();
    assert!(sim.running());
    // The first Start after leaving video mode is lost: the driver saw the sequencer stopped
    // in the main status and started again.
    let start: Vec<(bool, u16)> = sim.log()[before..]
        .iter()
        .map(|l| (l.read, l.code))
        .collect();
    assert_eq!(
        start,
        vec![
            (false, 0x1A24),
            (true, 0x1A0C),
            (false, 0x1A24),
            (true, 0x1A0C)
        ]
    );
    let mut host_times = Vec::new();
    for k in 0..8u32 {
        match d.next_event().await.unwrap() {
            SequencerEvent::SubframeStart {
                frame,
                plane_index,
                host_time,
                lens_power,
                ..
            } => {
                assert_eq!((frame, u32::from(plane_index)), (k / 4, k % 4));
                assert_eq!(lens_power, None);
                host_times.push(host_time);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    // Patterns 4166 us apart, each frame's first at a 60 Hz VSYNC.
    let us = |a: usize, b: usize| host_times[b].saturating_since(host_times[a]).as_micros();
    assert_eq!((us(0, 1), us(2, 3), us(5, 6)), (4166, 4166, 4166));
    assert_eq!(us(0, 4), 16_666);
    tokio::time::sleep(Duration::from_millis(20)).await;
    // The simulated projector: patterns 4166 us apart within a frame, frames 16666 us apart,
    // TRIG_OUT_2 once per frame on the first pattern.
    let seen: Vec<_> = (0..8).map(|_| patterns.try_recv().unwrap()).collect();
    for (k, e) in seen.iter().enumerate() {
        assert_eq!(usize::from(e.lut_index), k % 4);
        assert_eq!(e.trig_out2, k % 4 == 0, "{e:?}");
        assert!(e.trig_out1);
        assert_eq!(e.exposure_us, 3166);
    }
    assert_eq!(seen[1].device_time_us - seen[0].device_time_us, 4166);
    assert_eq!(seen[4].device_time_us - seen[0].device_time_us, 16_666);
    // The driver's predicted starts line up with what the projector did.
    let dev = |k: usize| seen[k].device_time_us - seen[0].device_time_us;
    assert_eq!(
        (0..8).map(dev).collect::<Vec<_>>(),
        (0..8).map(|k| us(0, k) as u64).collect::<Vec<_>>()
    );
    d.stop().await.unwrap();
    assert!(!sim.running());
}

#[tokio::test(start_paused = true)]
async fn impossible_schedules_are_refused_before_anything_is_sent() {
    let (mut d, sim) = rig();
    for schedule in [
        four_planes(4166, 100),  // dark gap under 230 us
        four_planes(5000, 1000), // 4 x 5 ms overruns the 60 Hz frame
        four_planes(200, 0),     // even 1-bit patterns need 235 us
    ] {
        let e = d.program(&schedule).await.unwrap_err();
        assert!(matches!(e, DeviceError::Invalid(_)), "{e:?}");
    }
    assert!(sim.log().is_empty());
    let e = d.start().await.unwrap_err();
    assert!(matches!(e, DeviceError::Invalid(m) if m.contains("program")));
    assert!(sim.log().is_empty());
}

/// A sub-frame too short for 6-bit patterns (2.5 ms) runs at the deepest depth it allows, and
/// the controller validates it.
#[tokio::test(start_paused = true)]
async fn a_short_sub_frame_trades_grey_levels_for_rate() {
    let (mut d, sim) = rig();
    d.program(&four_planes(2000, 0)).await.unwrap();
    let lut: Vec<_> = sim.lut().into_iter().map(Option::unwrap).collect();
    assert_eq!(lut.len(), 4);
    assert!(lut.iter().all(|e| e.bit_depth == 5), "{lut:?}");
    d.start().await.unwrap();
    assert!(sim.running());
}

#[tokio::test(start_paused = true)]
async fn the_controller_s_own_rules_come_back_as_refusals() {
    let (mut d, sim) = rig();
    // Start before any validation: nack.
    let e = d
        .execute(&PatternDisplay(SequenceAction::Start))
        .await
        .unwrap_err();
    assert!(
        matches!(e, DeviceError::Refused { code: 0x1A24, .. }),
        "{e:?}"
    );
    // An exposure 100 us short of the period passes the wire but fails validation.
    d.execute(&SetExposure {
        exposure_us: 4066,
        period_us: 4166,
    })
    .await
    .unwrap();
    let e = d.validate().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { code: 0x1A1A, detail } if detail.contains("230 us")),
        "{e:?}"
    );
    // Configuration while running is refused.
    d.program(&four_planes(4166, 1000)).await.unwrap();
    d.start().await.unwrap();
    let e = d
        .execute(&SetExposure {
            exposure_us: 4166,
            period_us: 4166,
        })
        .await
        .unwrap_err();
    assert!(matches!(e, DeviceError::Refused { code: 0x1A29, .. }));
    assert!(sim.log().last().unwrap().nack);
}

#[tokio::test(start_paused = true)]
async fn garbage_and_stale_replies_are_skipped() {
    let (mut d, sim) = rig();
    // Garbage to the controller: it ignores it and still answers the next command.
    d.link_mut()
        .write_output_report(&[0, 0x40, 0, 0xff, 0xff])
        .await
        .unwrap();
    assert_eq!(sim.garbage_reports(), 1);
    d.version().await.unwrap();
    // A reply with a header that cannot be valid, then one to a sequence nobody waits for:
    // the driver skips both and takes the real reply.
    let (link, sim2) = sim::new(Dlpc350SimConfig::default());
    let mut d2 = Dlpc350::new(link, Arc::new(TokioClock::new()), Dlpc350Config::default());
    let stale = {
        let mut r = [0u8; 65];
        r[1..5].copy_from_slice(&[0xc0, 99, 1, 0]);
        r
    };
    sim2.inject_input(&[0, 0xc0, 0, 0xff, 0xff]);
    sim2.inject_input(&stale);
    assert_eq!(d2.version().await.unwrap().api.to_string(), "2.1.0");
    // Only garbage and then silence: a protocol error naming it, not a bare timeout.
    sim2.inject_input(&[0, 0xc0, 0, 0xff, 0xff]);
    sim2.mute(true);
    let e = d2.version().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Protocol(m) if m.contains("512")),
        "{e:?}"
    );
    drop(sim);
}

#[tokio::test(start_paused = true)]
async fn unplug_is_a_link_error_and_reconnect_restores_the_sequence() {
    let (mut d, sim) = rig();
    d.program(&four_planes(4166, 1000)).await.unwrap();
    d.start().await.unwrap();
    sim.unplug("USB cable pulled");
    // The driver notices at its next status check, at the latest one frame later.
    let mut result = Ok(());
    for _ in 0..5 {
        if let Err(e) = d.next_event().await {
            result = Err(e);
            break;
        }
    }
    let e = result.unwrap_err();
    assert!(e.needs_reconnect(), "{e:?}");

    let (link, sim2) = sim::new(Dlpc350SimConfig::default());
    d.reconnect(link).await.unwrap();
    assert!(sim2.running());
    assert_eq!(sim2.lut().len(), 4);
    assert!(matches!(
        d.next_event().await.unwrap(),
        SequencerEvent::SubframeStart { plane_index: 0, .. }
    ));
}

#[tokio::test(start_paused = true)]
async fn a_sequencer_that_stops_on_its_own_is_a_fault() {
    let (mut d, sim) = rig();
    d.program(&four_planes(4166, 1000)).await.unwrap();
    d.start().await.unwrap();
    for _ in 0..4 {
        d.next_event().await.unwrap();
    }
    sim.abort_sequence();
    let ev = d.next_event().await.unwrap();
    assert!(
        matches!(
            ev,
            SequencerEvent::Fault {
                fault: SequencerFault::Other(FAULT_SEQUENCER_STOPPED),
                frame: 1,
                plane_index: 0,
                ..
            }
        ),
        "{ev:?}"
    );
    assert!(d.status().await.unwrap().hardware.sequence_abort());
    assert!(matches!(d.next_event().await, Err(DeviceError::Invalid(_))));
}

#[tokio::test(start_paused = true)]
async fn long_luts_travel_in_several_reports_both_ways() {
    use dioptra_sync::dlpc350::protocol::{
        LutEntry, Mailbox, MailboxControl, SetMailboxAddress, SetPatternConfig, TriggerType,
        WriteMailbox,
    };
    let (mut d, sim) = rig();
    // 40 one-bit entries: 120 bytes, two reports out and two back.
    let entries: Vec<LutEntry> = (0..40u8)
        .map(|i| LutEntry {
            trigger: TriggerType::Internal,
            pattern: i % 24,
            bit_depth: 1,
            leds: 0b100,
            invert: false,
            insert_black: false,
            buffer_swap: i % 24 == 0,
            trig_out_prev: false,
        })
        .collect();
    d.execute(&SetPatternConfig {
        lut_entries: 40,
        repeat: true,
        trig_out2_every: 40,
        images: 1,
    })
    .await
    .unwrap();
    d.execute(&MailboxControl(Mailbox::PatternLut))
        .await
        .unwrap();
    d.execute(&SetMailboxAddress(0)).await.unwrap();
    d.execute(&WriteMailbox(entries.clone())).await.unwrap();
    d.execute(&MailboxControl(Mailbox::Closed)).await.unwrap();
    let in_sim: Vec<_> = sim.lut().into_iter().flatten().collect();
    assert_eq!(in_sim.len(), 40);
    // The controller answers with its whole table (128 entries); what was written comes first.
    let back = d.read_lut().await.unwrap();
    assert_eq!(back.len(), 128);
    assert_eq!(back[..40], entries[..]);
    // Past entry 127, or with no mailbox open: nack, nothing written.
    d.execute(&MailboxControl(Mailbox::PatternLut))
        .await
        .unwrap();
    d.execute(&SetMailboxAddress(100)).await.unwrap();
    let e = d.execute(&WriteMailbox(entries.clone())).await.unwrap_err();
    assert!(
        matches!(e, DeviceError::Refused { code: 0x1A34, .. }),
        "{e:?}"
    );
    d.execute(&MailboxControl(Mailbox::Closed)).await.unwrap();
    let e = d.execute(&WriteMailbox(entries)).await.unwrap_err();
    assert!(
        matches!(e, DeviceError::Refused { code: 0x1A34, .. }),
        "{e:?}"
    );
}

fn rig_with(cfg: Dlpc350SimConfig) -> (Dlpc350<MemoryHidLink>, sim::Dlpc350Sim) {
    let (link, sim) = sim::new(cfg);
    let driver = Dlpc350::new(link, Arc::new(TokioClock::new()), Dlpc350Config::default());
    (driver, sim)
}

/// TI's validation bit 3: an exposure shorter than the period without black fill fails. The
/// driver's LUT passes it (see the first test); entries without the flag do not.
#[tokio::test(start_paused = true)]
async fn dark_time_without_black_fill_fails_validation() {
    use dioptra_sync::dlpc350::protocol::{
        LutEntry, Mailbox, MailboxControl, SetMailboxAddress, SetPatternConfig, TriggerType,
        WriteMailbox,
    };
    let (mut d, _sim) = rig();
    d.execute(&SetExposure {
        exposure_us: 3166,
        period_us: 4166,
    })
    .await
    .unwrap();
    d.execute(&SetPatternConfig {
        lut_entries: 2,
        repeat: true,
        trig_out2_every: 2,
        images: 1,
    })
    .await
    .unwrap();
    let entry = |pattern| LutEntry {
        trigger: TriggerType::Continue,
        pattern,
        bit_depth: 6,
        leds: 0b111,
        invert: false,
        insert_black: false,
        buffer_swap: false,
        trig_out_prev: false,
    };
    d.execute(&MailboxControl(Mailbox::PatternLut))
        .await
        .unwrap();
    d.execute(&SetMailboxAddress(0)).await.unwrap();
    d.execute(&WriteMailbox(vec![entry(0), entry(1)]))
        .await
        .unwrap();
    d.execute(&MailboxControl(Mailbox::Closed)).await.unwrap();
    let e = d.validate().await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { code: 0x1A1A, detail } if detail.contains("black vector")),
        "{e:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_controller_in_standby_is_woken_before_programming() {
    let (mut d, sim) = rig_with(Dlpc350SimConfig {
        standby: true,
        ..Dlpc350SimConfig::default()
    });
    d.program(&four_planes(4166, 1000)).await.unwrap();
    d.start().await.unwrap();
    assert!(sim.running());
    // Another client puts it in standby between sessions; reprogramming wakes it again.
    d.stop().await.unwrap();
    sim.set_standby(true);
    d.program(&four_planes(4166, 1000)).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn an_incompatible_controller_or_dmd_is_a_refusal() {
    let (mut d, sim) = rig_with(Dlpc350SimConfig {
        hardware_status: 0x03,
        ..Dlpc350SimConfig::default()
    });
    let e = d.program(&four_planes(4166, 1000)).await.unwrap_err();
    assert!(
        matches!(&e, DeviceError::Refused { code: 0x1A0A, detail } if detail.contains("incompatible")),
        "{e:?}"
    );
    // Nothing was configured.
    assert!(!sim.log().iter().any(|l| !l.read && l.code == 0x1A34));
}

/// Stop takes effect at the end of the pattern on show; the driver reads the state back
/// before it configures anything, so an immediate reprogram is not refused.
#[tokio::test(start_paused = true)]
async fn stop_is_confirmed_before_reprogramming() {
    let (mut d, sim) = rig();
    d.program(&four_planes(4166, 1000)).await.unwrap();
    d.start().await.unwrap();
    tokio::time::sleep(Duration::from_micros(1500)).await;
    d.stop().await.unwrap();
    assert!(!sim.running());
    let reads = sim
        .log()
        .iter()
        .filter(|l| l.read && l.code == 0x1A24)
        .count();
    assert!(reads >= 2, "{:#?}", sim.log());
    d.program(&four_planes(5000, 1000)).await.unwrap_err(); // 4 x 5 ms > 16.7 ms: refused by us
    d.program(&four_planes(4000, 1000)).await.unwrap();
    assert!(sim.log().iter().all(|l| !l.nack || l.code == 0x0205));
}

/// The reads other clients send (TI's GUI, pycrafter4500, Francesco Valla's dlpc350 library),
/// as hand-assembled reports: flags 0xC0, sequence, length 2 (LE), CMD3, CMD2.
#[tokio::test(start_paused = true)]
async fn the_simulator_answers_the_reads_other_clients_send() {
    let (mut link, _sim) = sim::new(Dlpc350SimConfig::default());
    // (CMD2, CMD3, reply data length)
    let reads: &[(u8, u8, usize)] = &[
        (0x1A, 0x0C, 1),  // main status
        (0x1A, 0x0A, 1),  // hardware status
        (0x1A, 0x0B, 1),  // system status
        (0x02, 0x05, 16), // version
        (0x1A, 0xFF, 32), // firmware tag
        (0x0B, 0x01, 3),  // LED currents
        (0x1A, 0x0E, 1),  // gamma
        (0x1A, 0x1B, 1),  // display mode
        (0x1A, 0x24, 1),  // pattern display state
        (0x02, 0x00, 1),  // power mode
    ];
    for (seq, &(cmd2, cmd3, n)) in reads.iter().enumerate() {
        let mut report = [0u8; 65];
        report[1..7].copy_from_slice(&[0xc0, seq as u8, 2, 0, cmd3, cmd2]);
        link.write_output_report(&report).await.unwrap();
        let mut buf = [0u8; 65];
        let got = link
            .read_input_report(&mut buf, Duration::from_secs(1))
            .await
            .unwrap();
        assert!(got >= 5, "{cmd2:02x}{cmd3:02x}");
        // Report id 0, flags echoed without the nack bit, sequence, length.
        assert_eq!(
            &buf[..5],
            &[0, 0xc0, seq as u8, n as u8, 0],
            "{cmd2:02x}{cmd3:02x}: {:?}",
            &buf[..8]
        );
    }
    // pycrafter4500's gamma write (bit 7 on), then main status shows gamma enabled (bit 3).
    let mut report = [0u8; 65];
    report[1..8].copy_from_slice(&[0x40, 20, 3, 0, 0x0e, 0x1a, 0x80]);
    link.write_output_report(&report).await.unwrap();
    let mut buf = [0u8; 65];
    link.read_input_report(&mut buf, Duration::from_secs(1))
        .await
        .unwrap();
    assert_eq!(&buf[1..5], &[0x40, 20, 0, 0]);
    report[1..7].copy_from_slice(&[0xc0, 21, 2, 0, 0x0c, 0x1a]);
    report[7] = 0;
    link.write_output_report(&report).await.unwrap();
    link.read_input_report(&mut buf, Duration::from_secs(1))
        .await
        .unwrap();
    assert_eq!(buf[5] & 0x08, 0x08, "{:?}", &buf[..6]);
}
