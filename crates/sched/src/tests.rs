//! The scheduler on synthetic events with known answers.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{
    DepthMap, Diopters, EyeRay, GazeSample, LensState, Plane, SequencerEvent, Timestamp,
};

use crate::*;

const IPD_MM: f64 = 64.0;

/// Both eyes on the point at (`yaw`, `pitch`) degrees and `diopters`; `valid` false = blink.
fn sample(t_us: u64, yaw: f64, pitch: f64, diopters: f64, valid: bool) -> GazeSample {
    let (y, p) = (yaw.to_radians(), pitch.to_radians());
    let dist = 1000.0 / diopters;
    let pt = [
        p.cos() * y.sin() * dist,
        p.sin() * dist,
        p.cos() * y.cos() * dist,
    ];
    let eye = |x: f64| {
        let d = [pt[0] - x, pt[1], pt[2]];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        EyeRay {
            origin_mm: [x as f32, 0.0, 0.0],
            direction: [(d[0] / n) as f32, (d[1] / n) as f32, (d[2] / n) as f32],
            pupil_mm: 4.0,
            valid,
        }
    };
    let t = Timestamp::from_micros(t_us);
    GazeSample {
        device_time: t,
        host_receive_time: t + Duration::from_micros(800),
        host_time: t,
        left: eye(-IPD_MM / 2.0),
        right: eye(IPD_MM / 2.0),
    }
}

/// Left half 2 D (0.5 m), right half 0.5 D (2 m).
fn split_depth() -> Arc<DepthMap> {
    let w = 256;
    let mut p = Plane::new(w, w, 0.5);
    for y in 0..w {
        for x in 0..w / 2 {
            p.data_mut()[y * w + x] = 2.0;
        }
    }
    Arc::new(DepthMap::from_diopters(p).unwrap())
}

fn lens_commands(out: &[Command]) -> Vec<(Diopters, FocusReason)> {
    out.iter()
        .filter_map(|c| match c {
            Command::SetLensPower { power, reason, .. } => Some((*power, *reason)),
            _ => None,
        })
        .collect()
}

/// Min-jerk position fraction.
fn min_jerk(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
}

/// Steps one 500 Hz gaze sample at its receive time; returns the commands it caused.
fn gaze(s: &mut Scheduler, g: GazeSample) -> Vec<Command> {
    let mut out = Vec::new();
    s.step(g.host_receive_time, Event::Gaze(g), &mut out);
    out
}

#[test]
fn saccade_between_depths_moves_focus_once_and_blinks_hold_it() {
    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let mut out = Vec::new();
    s.step(Timestamp::ZERO, Event::Depth(split_depth()), &mut out);
    let mut t = 0u64;
    let mut all = Vec::new();
    // 300 ms on the near object at -5 degrees.
    for _ in 0..150 {
        let c = gaze(&mut s, sample(t, -5.0, 0.0, 2.0, true));
        all.extend(lens_commands(&c).into_iter().map(|c| (t, c)));
        t += 2000;
    }
    assert_eq!(all.len(), 1, "{all:?}");
    assert_eq!(all[0].0, 0, "first fixation sample commands");
    assert_eq!(all[0].1, (Diopters(2.0), FocusReason::FixationOnset));
    // A 10 degree saccade to the far object (43 ms), then fixation there.
    let start = t;
    let dur = 43_000u64;
    let mut landed_at = None;
    while t < start + dur + 200_000 {
        let f = min_jerk((t - start) as f64 / dur as f64);
        let yaw = -5.0 + 10.0 * f;
        // Vergence follows slowly: still near at landing.
        let d = 2.0 - 1.5 * (1.0 - (-((t - start) as f64) / 150_000.0).exp());
        let c = gaze(&mut s, sample(t, yaw, 0.0, d, true));
        if t >= start + dur && landed_at.is_none() {
            landed_at = Some(t);
        }
        all.extend(lens_commands(&c).into_iter().map(|c| (t, c)));
        t += 2000;
    }
    let moved: Vec<_> = all[1..].to_vec();
    assert_eq!(moved.len(), 1, "one command per saccade: {moved:?}");
    let (when, (power, reason)) = moved[0];
    assert_eq!(power, Diopters(0.5));
    assert_eq!(reason, FocusReason::SaccadeLanding);
    // Commanded before the eye landed: during the saccade.
    assert!(
        when > start && when < landed_at.unwrap(),
        "{when} {landed_at:?}"
    );
    assert_eq!(s.status().counters.saccades, 1);
    // A 150 ms blink, then the eyes reopen on the same object: nothing to do.
    for _ in 0..75 {
        assert!(lens_commands(&gaze(&mut s, sample(t, 5.0, 0.0, 0.5, false))).is_empty());
        t += 2000;
    }
    assert_eq!(s.status().phase, crate::processing::EyePhase::Blink);
    for _ in 0..50 {
        assert!(lens_commands(&gaze(&mut s, sample(t, 5.0, 0.0, 0.5, true))).is_empty());
        t += 2000;
    }
    assert_eq!(s.status().counters.blinks, 1);
    assert_eq!(s.status().commanded_power, Some(Diopters(0.5)));
}

#[test]
fn without_landing_prediction_the_command_comes_at_fixation_onset() {
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.focus.predict_landing = false;
    let mut s = Scheduler::new(cfg).unwrap();
    let mut out = Vec::new();
    s.step(Timestamp::ZERO, Event::Depth(split_depth()), &mut out);
    let mut t = 0;
    for _ in 0..100 {
        gaze(&mut s, sample(t, -5.0, 0.0, 2.0, true));
        t += 2000;
    }
    let start = t;
    let mut cmd = None;
    let mut onset = None;
    while t < start + 200_000 {
        let f = min_jerk((t - start) as f64 / 43_000.0);
        let c = gaze(&mut s, sample(t, -5.0 + 10.0 * f, 0.0, 2.0, true));
        let fixating = s.status().phase == crate::processing::EyePhase::Fixation;
        if fixating && t > start + 10_000 && onset.is_none() {
            onset = Some(t);
        }
        if let Some(c) = lens_commands(&c).first() {
            cmd.get_or_insert((t, *c));
        }
        t += 2000;
    }
    let (when, (power, reason)) = cmd.expect("no command after the saccade");
    assert_eq!((power, reason), (Diopters(0.5), FocusReason::FixationOnset));
    assert_eq!(Some(when), onset, "on the sample the fixation was detected");
}

#[test]
fn frames_render_at_the_focus_the_lens_will_have_at_display_time() {
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.display.latency = Duration::from_millis(4);
    // A short render budget: a frame asked for just after a command shows mid-move.
    cfg.display.render_lead = Duration::from_millis(5);
    let mut s = Scheduler::new(cfg).unwrap();
    let mut requests = Vec::new();
    let mut t = Timestamp::ZERO;
    // Manual focus at 0.5 D, then 3 D at 96 ms; a renderer that takes 3 ms.
    let mut events = vec![
        (Timestamp::ZERO, Event::ManualFocus(Some(Diopters(0.5)))),
        (
            Timestamp::from_millis(96),
            Event::ManualFocus(Some(Diopters(3.0))),
        ),
    ];
    while t < Timestamp::from_millis(200) {
        events.sort_by_key(|e| e.0);
        let (at, ev) = match events.first() {
            Some(e) if e.0 <= t => events.remove(0),
            _ => (t, Event::Tick),
        };
        let mut out = Vec::new();
        s.step(at, ev, &mut out);
        for c in out {
            if let Command::RenderFrame(r) = c {
                // The focus is the model's prediction when the frame is asked for.
                let want = s.predicted_lens_power(r.display_time).unwrap();
                assert_eq!(r.lens_power, Some(want));
                assert_eq!(r.focus, Some(want));
                if at >= Timestamp::from_millis(96) {
                    requests.push(r);
                }
                events.push((
                    at + Duration::from_millis(3),
                    Event::RenderFinished {
                        frame: r.frame,
                        method: r.method,
                        render_time: Duration::from_millis(3),
                    },
                ));
            }
        }
        let next_event = events.iter().map(|e| e.0).min();
        t = s
            .next_wakeup()
            .into_iter()
            .chain(next_event)
            .min()
            .unwrap()
            .max(t);
    }
    assert!(requests.len() >= 5, "{}", requests.len());
    let mut moving = 0;
    for r in &requests {
        let p = r.lens_power.unwrap().0;
        if (p - 3.0).abs() > 0.05 {
            moving += 1;
            assert!(p > 0.5, "{r:?}");
        }
    }
    // The frame displayed while the lens moves is rendered for where the lens will be then,
    // not for the target.
    assert!(moving >= 1, "{requests:?}");
    assert_eq!(s.status().counters.misses, 0);
}

fn subframe(frame: u32, plane: u8, t: Timestamp) -> Event {
    Event::Sequencer(SequencerEvent::SubframeStart {
        frame,
        plane_index: plane,
        device_time: t,
        host_time: t,
        lens_power: None,
    })
}

/// Multifocal with 4 planes at 240 Hz and a renderer taking `render`: (misses, presented).
fn multifocal(render: Duration, cycles: u32) -> (u64, u64, Vec<(u64, bool)>) {
    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Multifocal)).unwrap();
    let period = Duration::from_nanos(4_166_667);
    let mut pending: Option<(Timestamp, FrameId)> = None;
    let mut shown = Vec::new();
    for f in 0..cycles {
        for plane in 0..4u8 {
            let t = Timestamp::from_millis(10) + period * (f * 4 + u32::from(plane));
            if let Some((done, frame)) = pending.filter(|p| p.0 <= t) {
                let mut o = Vec::new();
                s.step(
                    done,
                    Event::RenderFinished {
                        frame,
                        method: RenderMethod::Linear,
                        render_time: render,
                    },
                    &mut o,
                );
                pending = None;
            }
            let mut out = Vec::new();
            s.step(t, subframe(f, plane, t), &mut out);
            for c in out {
                match c {
                    Command::RenderFrame(r) => pending = Some((t + render, r.frame)),
                    Command::PresentLayer {
                        frame,
                        layer,
                        sync_frame,
                        start,
                        repeat,
                    } => {
                        // One sub-frame ahead: the next sub-frame's layer, for its start.
                        let next = (f * 4 + u32::from(plane) + 1, (plane + 1) % 4);
                        assert_eq!((sync_frame * 4 + u32::from(layer), layer), next);
                        assert_eq!(start, t + period);
                        if layer == 0 {
                            shown.push((frame.0, repeat));
                        }
                    }
                    _ => {}
                }
            }
        }
    }
    let c = s.status().counters;
    (c.misses, c.frames_presented, shown)
}

#[test]
fn multifocal_shows_layers_in_lockstep_and_counts_misses() {
    // Fast: every cycle shows the frame rendered for it.
    let (misses, presented, shown) = multifocal(Duration::from_millis(5), 200);
    assert_eq!(misses, 0);
    assert_eq!(presented, 199);
    assert!(shown.windows(2).all(|w| w[1].0 == w[0].0 + 1));
    // 1.5 frame periods: every other cycle repeats; 2.5: two of three.
    for (render_ms, want) in [(25u64, 1.0 / 2.0), (42, 2.0 / 3.0)] {
        let (misses, presented, shown) = multifocal(Duration::from_millis(render_ms), 300);
        let repeats = shown.iter().filter(|s| s.1).count() as u64;
        assert_eq!(misses, repeats);
        let share = misses as f64 / presented as f64;
        assert!((share - want).abs() < 0.02, "{render_ms} ms: {share}");
    }
}

#[test]
fn lost_link_holds_the_target_and_reconnect_sends_it_then_shutdown_parks() {
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.park_power = Diopters(0.25);
    let mut s = Scheduler::new(cfg).unwrap();
    let mut out = Vec::new();
    s.step(
        Timestamp::ZERO,
        Event::LensLink(LensId::FIRST, LinkStatus::Lost),
        &mut out,
    );
    s.step(
        Timestamp::from_millis(1),
        Event::ManualFocus(Some(Diopters(1.5))),
        &mut out,
    );
    assert!(lens_commands(&out).is_empty());
    assert_eq!(s.status().counters.lens_commands_held, 1);
    s.step(
        Timestamp::from_millis(2),
        Event::LensLink(LensId::FIRST, LinkStatus::Connected),
        &mut out,
    );
    assert_eq!(
        lens_commands(&out),
        [(Diopters(1.5), FocusReason::Reconnect)]
    );
    out.clear();
    s.step(Timestamp::from_millis(3), Event::Shutdown, &mut out);
    assert_eq!(lens_commands(&out), [(Diopters(0.25), FocusReason::Park)]);
    // Nothing moves the lens after shutdown, and no more frames are asked for.
    out.clear();
    s.step(
        Timestamp::from_millis(4),
        Event::ManualFocus(Some(Diopters(2.0))),
        &mut out,
    );
    s.step(Timestamp::from_millis(50), Event::Tick, &mut out);
    assert!(out.is_empty(), "{out:?}");
}

/// In multifocal mode gaze does not drive the varifocal lens: the first read-back of a lens
/// nothing commanded holds it at the park power, once (issue 39 item 9: it showed -2 D, where
/// a relaxed Lens Driver 4 sits, outside the rig's range).
#[test]
fn multifocal_holds_an_uncommanded_lens_at_the_park_power_once() {
    let mut cfg = SchedulerConfig::new(Mode::Multifocal);
    cfg.park_power = Diopters(0.5);
    let mut s = Scheduler::new(cfg).unwrap();
    let relaxed = |ms: u64| {
        Event::LensState(
            LensId::FIRST,
            LensState {
                power: Diopters(-2.0),
                current_ma: Some(0.0),
                temperature_c: None,
                settled: None,
                host_time: Timestamp::from_millis(ms),
            },
        )
    };
    let mut out = Vec::new();
    s.step(Timestamp::from_millis(1), relaxed(1), &mut out);
    assert_eq!(
        lens_commands(&out),
        [(Diopters(0.5), FocusReason::MultifocalHold)]
    );
    out.clear();
    s.step(Timestamp::from_millis(11), relaxed(11), &mut out);
    assert!(lens_commands(&out).is_empty(), "{out:?}");
    // A varifocal scheduler leaves the lens to gaze.
    let mut v = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    v.step(Timestamp::from_millis(1), relaxed(1), &mut out);
    assert!(lens_commands(&out).is_empty(), "{out:?}");
}

#[test]
fn settle_latency_is_measured_from_the_wire_to_a_settled_readback() {
    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let mut out = Vec::new();
    s.step(Timestamp::ZERO, Event::Depth(split_depth()), &mut out);
    let g = sample(0, -5.0, 0.0, 2.0, true);
    out.clear();
    s.step(g.host_receive_time, Event::Gaze(g), &mut out);
    let Some(Command::SetLensPower { id, .. }) = out.first().copied() else {
        panic!("{out:?}");
    };
    let wire = g.host_receive_time + Duration::from_micros(120);
    s.step(
        wire,
        Event::LensCommandWritten {
            lens: LensId::FIRST,
            id,
            wire_time: wire,
        },
        &mut out,
    );
    let state = |ms: u64, p: f32, settled| LensState {
        power: Diopters(p),
        current_ma: None,
        temperature_c: None,
        settled: Some(settled),
        host_time: wire + Duration::from_millis(ms),
    };
    for (ms, p, settled) in [
        (5, 1.2, false),
        (10, 1.99, false),
        (14, 2.0, true),
        (20, 2.0, true),
    ] {
        let st = state(ms, p, settled);
        s.step(st.host_time, Event::LensState(LensId::FIRST, st), &mut out);
    }
    let l = s.latency();
    assert_eq!(l.stage(Stage::HostToWire).len(), 1);
    assert!((119..=121).contains(&l.stage(Stage::HostToWire).max()));
    assert_eq!(l.stage(Stage::WireToSettled).len(), 1);
    assert!((13_990..=14_010).contains(&l.stage(Stage::WireToSettled).max()));
    // From the tracker's exposure: 0.8 ms to the host, 0.12 ms to the wire, 14 ms to settle.
    let g2s = l.stage(Stage::GazeToSettled).max();
    assert!((14_900..=14_940).contains(&g2s), "{g2s}");
    assert_eq!(s.status().last_settle, Some(Duration::from_millis(14)));
}

#[test]
fn config_errors_name_the_setting_and_bad_events_are_counted_not_fatal() {
    let mut cfg = SchedulerConfig::new(Mode::Multifocal);
    cfg.planes = None;
    let e = Scheduler::new(cfg).unwrap_err();
    assert!(e.to_string().contains("`planes`"), "{e}");
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.method = RenderMethod::Linear;
    assert!(Scheduler::new(cfg)
        .unwrap_err()
        .to_string()
        .contains("`method`"));
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.park_power = Diopters(9.0);
    assert!(Scheduler::new(cfg)
        .unwrap_err()
        .to_string()
        .contains("park_power"));

    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let mut out = Vec::new();
    s.step(
        Timestamp::ZERO,
        Event::RenderFinished {
            frame: FrameId(77),
            method: RenderMethod::Gather,
            render_time: Duration::ZERO,
        },
        &mut out,
    );
    s.step(
        Timestamp::ZERO,
        Event::SetMethod(RenderMethod::Views),
        &mut out,
    );
    s.step(
        Timestamp::ZERO,
        Event::ManualFocus(Some(Diopters(f32::NAN))),
        &mut out,
    );
    // Garbage gaze: NaN directions and times going backwards.
    let mut g = sample(1000, 0.0, 0.0, 1.0, true);
    g.left.direction = [f32::NAN; 3];
    g.right.origin_mm = [f32::INFINITY; 3];
    s.step(Timestamp::from_millis(1), Event::Gaze(g), &mut out);
    s.step(
        Timestamp::from_millis(1),
        Event::Gaze(sample(0, 0.0, 0.0, 1.0, true)),
        &mut out,
    );
    let st = s.status();
    assert_eq!(st.counters.ignored_events, 3);
    assert_eq!(st.method, RenderMethod::Gather);
    assert_eq!(st.counters.gaze_samples, 2);
    assert!(lens_commands(&out).is_empty());
}

#[test]
fn vsync_events_lock_the_frame_clock_to_the_display() {
    // The panel runs at 59.9 Hz, not the configured 60, with its first vsync 5 ms in: free
    // running, the scheduler's clock would drift 28 µs a frame (3.3 ms over 2 s).
    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let true_period = Duration::from_nanos(16_694_491);
    let vsync = |k: u32| Timestamp::from_millis(5) + true_period * k;
    let mut events: Vec<(Timestamp, Event)> = (0..120)
        .map(|k| (vsync(k), Event::Vsync(vsync(k))))
        .collect();
    events.push((Timestamp::ZERO, Event::ManualFocus(Some(Diopters(1.0)))));
    let mut t = Timestamp::ZERO;
    let mut presents = Vec::new();
    while t < vsync(119) {
        events.sort_by_key(|e| e.0);
        let (at, ev) = match events.first() {
            Some(e) if e.0 <= t => events.remove(0),
            _ => (t, Event::Tick),
        };
        let mut out = Vec::new();
        s.step(at, ev, &mut out);
        for c in out {
            match c {
                Command::RenderFrame(r) => events.push((
                    at + Duration::from_millis(2),
                    Event::RenderFinished {
                        frame: r.frame,
                        method: r.method,
                        render_time: Duration::from_millis(2),
                    },
                )),
                Command::Present { vsync, .. } => presents.push(vsync),
                _ => {}
            }
        }
        let next_event = events.iter().map(|e| e.0).min();
        t = s
            .next_wakeup()
            .into_iter()
            .chain(next_event)
            .min()
            .unwrap()
            .max(t);
    }
    assert!(presents.len() >= 100, "{} presents", presents.len());
    // After the first few frames every present is timed to a real vsync, to within 0.1 ms.
    for (i, &p) in presents.iter().enumerate().skip(5) {
        let off = (0..121)
            .map(|k| p.signed_diff_ns(vsync(k)).unsigned_abs())
            .min()
            .unwrap();
        assert!(
            off < 100_000,
            "present {i} at {p:?} is {off} ns from a vsync"
        );
    }
    assert_eq!(s.status().counters.misses, 0);
}

#[test]
fn content_latency_runs_from_arrival_to_the_first_frame_showing_it() {
    // 60 Hz varifocal frames rendered in 2 ms; content frames arrive at 30, 105 and 106 ms
    // (the last replaces the one before: no request comes between them), each ready 1 ms later
    // and given to the scheduler then, as the rig's executor does; the next frame requested
    // shows it.
    let mut s = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let arrivals = [30u64, 105, 106];
    // Arrivals before this index were taken up by a frame (or replaced).
    let mut taken = 0;
    let mut events: Vec<(Timestamp, Event)> =
        vec![(Timestamp::ZERO, Event::ManualFocus(Some(Diopters(1.0))))];
    events.extend(arrivals.iter().map(|&a| {
        (
            Timestamp::from_millis(a + 1),
            Event::Content {
                arrived: Timestamp::from_millis(a),
                ready: Timestamp::from_millis(a + 1),
            },
        )
    }));
    let mut t = Timestamp::ZERO;
    let mut presents = Vec::new();
    while t < Timestamp::from_millis(250) {
        events.sort_by_key(|e| e.0);
        let (at, ev) = match events.first() {
            Some(e) if e.0 <= t => events.remove(0),
            _ => (t, Event::Tick),
        };
        let mut out = Vec::new();
        s.step(at, ev, &mut out);
        for c in out {
            if let Command::RenderFrame(r) = c {
                // The newest arrival given before this request is what this frame shows.
                let due = arrivals[taken..]
                    .iter()
                    .filter(|&&a| Timestamp::from_millis(a + 1) <= at)
                    .count();
                if due > 0 {
                    taken += due;
                    presents.push((arrivals[taken - 1], r.display_time));
                }
                events.push((
                    at + Duration::from_millis(2),
                    Event::RenderFinished {
                        frame: r.frame,
                        method: r.method,
                        render_time: Duration::from_millis(2),
                    },
                ));
            }
        }
        let next_event = events.iter().map(|e| e.0).min();
        t = s
            .next_wakeup()
            .into_iter()
            .chain(next_event)
            .min()
            .unwrap()
            .max(t);
    }
    // Two content frames reached a frame (106 ms replaced 105 ms before any request).
    assert_eq!(
        presents.iter().map(|p| p.0).collect::<Vec<_>>(),
        [30, 106],
        "{presents:?}"
    );
    let l = s.latency();
    let received = l.stage(Stage::ContentReceived);
    assert_eq!(received.len(), 3, "one per content frame given");
    assert!((999..=1001).contains(&received.max()), "{}", received.max());
    let shown = l.stage(Stage::ContentToPresented);
    assert_eq!(shown.len(), 2, "one per content frame shown");
    // Each is its frame's display time less the arrival.
    for (a, display) in &presents {
        let us = display
            .saturating_since(Timestamp::from_millis(*a))
            .as_micros() as u64;
        assert!(
            shown.count_between(us.saturating_sub(us / 500 + 1), us + us / 500 + 1) >= 1,
            "no sample near {us} µs for the frame of {a} ms"
        );
    }
}

#[test]
fn focus_becomes_a_lens_command_through_the_optics_map_and_back_for_the_render() {
    use dioptra_core::optics_map::{Prescription, ThinLensLayout};
    use dioptra_core::{OpticsMap, PowerRange};
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    cfg.lens_range = PowerRange::new(Diopters(-2.0), Diopters(2.0)).unwrap();
    cfg.park_power = Diopters(0.0);
    // Display 5 cm from the lens, an 18 D eyepiece, the pupil 2 cm behind; a -1 D myope
    // (0 mm vertex). Looking at 2 D: shown 3 D; X = 3 / (1 - 0.06) = 3.191489; the command
    // is 20 - 18 - X = -1.191489 D.
    cfg.optics = OpticsMap::new(
        Some(ThinLensLayout::new(0.05, 0.02, 18.0).unwrap()),
        None,
        Prescription::new(-1.0, 0.0, 0.0).unwrap(),
        cfg.lens_range,
    )
    .unwrap();
    let mut wrong = cfg.clone();
    wrong.lens_range = PowerRange::new(Diopters(-1.0), Diopters(2.0)).unwrap();
    let e = Scheduler::new(wrong).unwrap_err().to_string();
    assert!(e.contains("optics") && e.contains("-2..2 D"), "{e}");
    let mut s = Scheduler::new(cfg).unwrap();
    // Steps `ev`, keeps its lens commands and frame requests, and renders each frame at once.
    let (mut cmds, mut frames) = (Vec::new(), Vec::new());
    let mut step = |s: &mut Scheduler, now: Timestamp, ev: Event| {
        let mut out = Vec::new();
        s.step(now, ev, &mut out);
        cmds.extend(lens_commands(&out));
        for c in out {
            if let Command::RenderFrame(r) = c {
                frames.push((r.display_time, r.focus));
                let done = Event::RenderFinished {
                    frame: r.frame,
                    method: r.method,
                    render_time: Duration::from_millis(1),
                };
                s.step(now, done, &mut Vec::new());
            }
        }
    };
    step(&mut s, Timestamp::ZERO, Event::Depth(split_depth()));
    // 400 ms of fixation on the near object, a gaze sample every 2 ms and ticks between.
    for t_us in (1000..400_000u64).step_by(1000) {
        if t_us % 2000 == 0 {
            let g = sample(t_us, -5.0, 0.0, 2.0, true);
            step(&mut s, g.host_receive_time, Event::Gaze(g));
        } else {
            step(&mut s, Timestamp::from_micros(t_us), Event::Tick);
        }
    }
    assert_eq!(cmds.len(), 1, "{cmds:?}");
    assert!((cmds[0].0 .0 + 1.191489).abs() < 1e-5, "{cmds:?}");
    // Frames shown once the lens model has settled render at the eye's focus, 2 D.
    let settled: Vec<_> = frames
        .iter()
        .filter(|f| f.0 > Timestamp::from_millis(200))
        .collect();
    assert!(!settled.is_empty(), "{frames:?}");
    for (_, f) in settled {
        assert!((f.unwrap().0 - 2.0).abs() < 1e-3, "{f:?}");
    }
    let now = Timestamp::from_millis(400);
    // Manual focus goes through the map too: 1 D is shown at 2 D, X = 2 / 0.96.
    let mut out = Vec::new();
    s.step(now, Event::ManualFocus(Some(Diopters(1.0))), &mut out);
    let c = lens_commands(&out);
    assert!((c[0].0 .0 - (2.0 - 2.0 / 0.96)).abs() < 1e-5, "{c:?}");
}

fn lens_commands_of(out: &[Command]) -> Vec<(LensId, Diopters, FocusReason)> {
    out.iter()
        .filter_map(|c| match c {
            Command::SetLensPower {
                lens,
                power,
                reason,
                ..
            } => Some((*lens, *power, *reason)),
            _ => None,
        })
        .collect()
}

/// Two lenses, one per eye: one fixation estimate commands both, back to back, each through
/// its own optics map; a lost lens is held while the other goes on, and gets its target when
/// it comes back; each eye's frame is rendered at its own lens's focus.
#[test]
fn two_lenses_follow_one_fixation_and_a_lost_one_holds_only_itself() {
    let mut cfg = SchedulerConfig::new(Mode::Varifocal);
    // The right lens is driven 0.25 D stronger for the same focus (its eye's own optics map),
    // settles more slowly and parks elsewhere.
    cfg.right_lens = Some(RightLens {
        lens: LensDynamics {
            settle_time: Duration::from_millis(30),
            ..LensDynamics::default()
        },
        // A -0.25 D myope's right eye (0 mm vertex): shown 0.25 D nearer than the focus.
        optics: dioptra_core::OpticsMap::new(
            None,
            None,
            dioptra_core::optics_map::Prescription::new(-0.25, 0.0, 0.0).unwrap(),
            cfg.lens_range,
        )
        .unwrap(),
        park_power: Diopters(0.75),
    });
    let mut s = Scheduler::new(cfg).unwrap();
    let mut out = Vec::new();
    s.step(Timestamp::ZERO, Event::Depth(split_depth()), &mut out);
    // The first frame, asked for at once: rendered at once, so that later ones are asked for.
    let first = out
        .iter()
        .find_map(|c| match c {
            Command::RenderFrame(r) => Some(*r),
            _ => None,
        })
        .unwrap();
    s.step(
        Timestamp::ZERO,
        Event::RenderFinished {
            frame: first.frame,
            method: first.method,
            render_time: Duration::ZERO,
        },
        &mut out,
    );
    // Fixating the near (2 D) half: both lenses, the left first.
    let c = gaze(&mut s, sample(0, -5.0, 0.0, 2.0, true));
    assert_eq!(
        lens_commands_of(&c),
        [
            (LensId(0), Diopters(2.0), FocusReason::FixationOnset),
            (LensId(1), Diopters(2.25), FocusReason::FixationOnset),
        ]
    );
    let ids: Vec<CommandId> = c
        .iter()
        .filter_map(|c| match c {
            Command::SetLensPower { id, .. } => Some(*id),
            _ => None,
        })
        .collect();
    assert_ne!(ids[0], ids[1]);
    // The right lens is lost; a manual focus moves the left lens only.
    s.step(
        Timestamp::from_millis(5),
        Event::LensLink(LensId(1), LinkStatus::Lost),
        &mut out,
    );
    out.clear();
    s.step(
        Timestamp::from_millis(6),
        Event::ManualFocus(Some(Diopters(1.0))),
        &mut out,
    );
    assert_eq!(
        lens_commands_of(&out),
        [(LensId(0), Diopters(1.0), FocusReason::Manual)]
    );
    let st = s.status();
    assert_eq!(st.counters.lens_commands_held, 1);
    let right = st.lenses[1].unwrap();
    assert_eq!(right.link, LinkStatus::Lost);
    assert_eq!(
        right.commanded_power,
        Some(Diopters(1.25)),
        "held, not sent"
    );
    assert_eq!(st.lenses[0].unwrap().link, LinkStatus::Connected);
    // Back: the right lens gets the focus it missed, the left nothing new.
    out.clear();
    s.step(
        Timestamp::from_millis(7),
        Event::LensLink(LensId(1), LinkStatus::Connected),
        &mut out,
    );
    assert_eq!(
        lens_commands_of(&out),
        [(LensId(1), Diopters(1.25), FocusReason::Reconnect)]
    );
    // Frames carry each eye's focus, from its own lens model, through its own map: once both
    // lenses settled, both eyes focus at 1 D (the right lens at 1.25 D).
    out.clear();
    let mut t = Timestamp::from_millis(7);
    let request = loop {
        assert!(t < Timestamp::from_millis(1000), "no frame asked for");
        t = s.next_wakeup().unwrap().max(t);
        out.clear();
        s.step(t, Event::Tick, &mut out);
        let Some(r) = out.iter().find_map(|c| match c {
            Command::RenderFrame(r) => Some(*r),
            _ => None,
        }) else {
            continue;
        };
        if r.display_time > Timestamp::from_millis(100) {
            break r;
        }
        // A renderer that finishes at once, so that the next frame is asked for.
        s.step(
            t,
            Event::RenderFinished {
                frame: r.frame,
                method: r.method,
                render_time: Duration::ZERO,
            },
            &mut out,
        );
    };
    let (l, r) = (request.focus.unwrap(), request.focus_right.unwrap());
    assert!(
        (l.0 - 1.0).abs() < 0.01 && (r.0 - 1.0).abs() < 0.01,
        "{l:?} {r:?}"
    );
    assert!((request.lens_power.unwrap().0 - 1.0).abs() < 0.01);
    // Shutdown parks each lens where its own section says.
    out.clear();
    s.step(t, Event::Shutdown, &mut out);
    assert_eq!(
        lens_commands_of(&out),
        [
            (LensId(0), Diopters(0.0), FocusReason::Park),
            (LensId(1), Diopters(0.75), FocusReason::Park),
        ]
    );
    // One lens: no right focus.
    let mut one = Scheduler::new(SchedulerConfig::new(Mode::Varifocal)).unwrap();
    let c = gaze(&mut one, sample(0, -5.0, 0.0, 2.0, true));
    assert_eq!(lens_commands_of(&c).len(), 1);
    assert!(one.status().lenses[1].is_none());
}

/// A scheduler restored from its state (through JSON, as a recording started mid-run carries
/// it) answers every later event with the same commands as the one it was taken from (issue
/// 39 item 5), through saccades, lens read-backs, renders, a manual focus and a method change.
#[test]
fn a_restored_scheduler_continues_exactly_where_its_state_was_taken() {
    let cfg = SchedulerConfig::new(Mode::Varifocal);
    let mut live = Scheduler::new(cfg.clone()).unwrap();
    // 3 s of events: fixations alternating between the 2 D and 0.5 D halves, a saccade
    // between them every 400 ms, read-backs every 10 ms, renders finishing 4 ms after each
    // request; manual focus at 1.2 s, back to gaze at 1.6 s, another method at 2.4 s.
    let mut events: Vec<(Timestamp, Event)> = vec![(Timestamp::ZERO, Event::Depth(split_depth()))];
    let mut requested: Vec<(Timestamp, FrameId)> = Vec::new();
    let yaw_at = |t_us: u64| {
        let k = t_us / 400_000;
        let (from, to) = if k % 2 == 0 {
            (-10.0, 10.0)
        } else {
            (10.0, -10.0)
        };
        let into = (t_us % 400_000) as f64 / 40_000.0;
        from + (to - from) * min_jerk(into)
    };
    for t_us in (0..3_000_000u64).step_by(2_000) {
        let g = sample(t_us, yaw_at(t_us), 0.0, 1.0, true);
        events.push((g.host_receive_time, Event::Gaze(g)));
        if t_us % 10_000 == 0 {
            let t = Timestamp::from_micros(t_us + 300);
            events.push((
                t,
                Event::LensState(
                    LensId::FIRST,
                    LensState {
                        power: Diopters(0.5 + (t_us % 70_000) as f32 * 1e-5),
                        current_ma: None,
                        temperature_c: None,
                        settled: None,
                        host_time: t,
                    },
                ),
            ));
        }
        match t_us {
            1_200_000 => events.push((
                Timestamp::from_micros(t_us + 500),
                Event::ManualFocus(Some(Diopters(1.5))),
            )),
            1_600_000 => {
                events.push((Timestamp::from_micros(t_us + 500), Event::ManualFocus(None)))
            }
            2_400_000 => events.push((
                Timestamp::from_micros(t_us + 500),
                Event::SetMethod(RenderMethod::LightFieldDefocus),
            )),
            _ => {}
        }
    }
    events.sort_by_key(|(t, _)| *t);
    // Steps `s` through `events`, finishing each render 4 ms after its request.
    let run = |s: &mut Scheduler,
               events: &[(Timestamp, Event)],
               pending: &mut Vec<(Timestamp, FrameId)>| {
        let mut all = Vec::new();
        for (t, e) in events {
            let mut out = Vec::new();
            while let Some(&(due, frame)) = pending.first().filter(|(due, _)| *due <= *t) {
                pending.remove(0);
                let method = s.status().method;
                s.step(
                    due,
                    Event::RenderFinished {
                        frame,
                        method,
                        render_time: Duration::from_millis(4),
                    },
                    &mut out,
                );
            }
            s.step(*t, e.clone(), &mut out);
            for c in &out {
                if let Command::RenderFrame(r) = c {
                    pending.push((*t + Duration::from_millis(4), r.frame));
                }
            }
            all.extend(out);
        }
        all
    };
    // Mid-fixation, after its lens command: the restored scheduler must know the lens is
    // there (within the deadband) and not command it again.
    let half = events
        .iter()
        .position(|(t, _)| *t >= Timestamp::from_millis(1_000))
        .unwrap();
    run(&mut live, &events[..half], &mut requested);
    let json = serde_json::to_string(live.state()).unwrap();
    let status = live.status();
    // The depth map is the content's: given again, as a replay gives it.
    let mut restored = Scheduler::restore(
        cfg,
        status.mode,
        status.method,
        Some(split_depth()),
        &mut serde_json::Deserializer::from_str(&json),
    )
    .unwrap();
    let mut requested_restored = requested.clone();
    let a = run(&mut live, &events[half..], &mut requested);
    let b = run(&mut restored, &events[half..], &mut requested_restored);
    assert!(lens_commands(&a).len() >= 4, "{:?}", lens_commands(&a));
    assert!(a.iter().any(|c| matches!(c, Command::RenderFrame(_))));
    assert_eq!(live.status().method, RenderMethod::LightFieldDefocus);
    assert_eq!(a, b);
    assert_eq!(live.status(), restored.status());
    // State of another shape is refused, saying so.
    let e = Scheduler::restore(
        SchedulerConfig::new(Mode::Varifocal),
        Mode::Varifocal,
        RenderMethod::Gather,
        None,
        &mut serde_json::Deserializer::from_str("{\"processor\": 3}"),
    )
    .unwrap_err();
    assert!(matches!(e, RestoreError::State(_)), "{e}");
}
