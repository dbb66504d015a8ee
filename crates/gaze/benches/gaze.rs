//! Speed targets (issue 4): parse one report ≤ 1 µs median; link to GazeSource stream
//! ≤ 50 µs median. Also descriptor parsing. (The gaze processor's cost is in dioptra-sched's bench.)

use std::sync::Arc;

use criterion::{black_box, criterion_group, criterion_main, Criterion};
use dioptra_core::{GazeSource, SystemClock};
use dioptra_gaze::dioptra_tracker::protocol::decode_sample_report;
use dioptra_gaze::dioptra_tracker::{DioptraTracker, DioptraTrackerConfig};
use dioptra_gaze::eye_hid::protocol::{ModeRequest, TrackerLayout};
use dioptra_gaze::eye_hid::{HidEyeTracker, HidTrackerConfig};
use dioptra_gaze::hid_descriptor;
use dioptra_sim::gaze::csv::Replay;
use dioptra_sim::gaze::{dioptra_tracker as sim_dt, hid_tracker as sim_hid};
use dioptra_sim::gaze::{GazeGenerator, GeneratorConfig, Scene};

fn samples(n: usize) -> Vec<dioptra_protocol::BinocularSample> {
    let mut g = GazeGenerator::new(
        Scene::named("saccades").unwrap(),
        GeneratorConfig::default(),
    )
    .unwrap();
    (0..n).map(|_| g.next_truth().reported).collect()
}

fn parse_report(c: &mut Criterion) {
    let s = samples(1)[0];
    let dioptra = sim_dt::encode_sample_report(&s).unwrap();
    c.bench_function("dioptra tracker: decode one report", |b| {
        b.iter(|| decode_sample_report(black_box(&dioptra)).unwrap())
    });
    let d = hid_descriptor::parse(sim_hid::DESCRIPTOR).unwrap();
    let layout = TrackerLayout::locate(&d).unwrap();
    let report = sim_hid::encode_tracking_report(&Default::default(), 7, &s);
    c.bench_function("page 0x12: parse one Tracking Data report", |b| {
        b.iter(|| layout.tracking.parse(black_box(&report)).unwrap())
    });
    c.bench_function("page 0x12: parse descriptor and locate layout", |b| {
        b.iter(|| {
            let d = hid_descriptor::parse(black_box(sim_hid::DESCRIPTOR)).unwrap();
            TrackerLayout::locate(&d).unwrap()
        })
    });
}

fn link_to_stream(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let s = samples(1)[0];
    let clock = Arc::new(SystemClock::new());

    // The simulators play a two-sample trace (which sets their rate to 500 Hz); after that
    // the bench pushes each report itself.
    let trace = || Box::new(Replay::new(samples(2)));
    let (link, sim) = rt.block_on(async { sim_dt::spawn(trace()) });
    let mut tracker = rt
        .block_on(DioptraTracker::connect(
            link,
            DioptraTrackerConfig::default(),
            clock.clone(),
        ))
        .unwrap();
    let mut t = s.device_time_us;
    c.bench_function("dioptra tracker: report pushed -> GazeSample", |b| {
        b.iter(|| {
            // A fresh device time each time, so the clock mapper sees a real stream.
            t += 2_000;
            let mut s2 = s;
            s2.device_time_us = t;
            sim.inject(&sim_dt::encode_sample_report(&s2).unwrap());
            rt.block_on(tracker.next_sample()).unwrap()
        })
    });

    let (link, sim) =
        rt.block_on(async { sim_hid::spawn(Box::new(Replay::new(vec![])), Default::default()) });
    let cfg = HidTrackerConfig {
        modes: ModeRequest::GAZE_POINT.with(ModeRequest::EYE_POSITION),
        ..HidTrackerConfig::default()
    };
    let mut tracker = rt
        .block_on(HidEyeTracker::connect(link, cfg, clock))
        .unwrap();
    c.bench_function("page 0x12: report pushed -> GazeSample", |b| {
        b.iter(|| {
            t += 2_000;
            let mut s2 = s;
            s2.device_time_us = t;
            sim.inject(&sim_hid::encode_tracking_report(
                &Default::default(),
                3,
                &s2,
            ));
            rt.block_on(tracker.next_sample()).unwrap()
        })
    });
}

criterion_group!(benches, parse_report, link_to_stream);
criterion_main!(benches);
