//! The Arduino sketch in firmware-protocol/photodiode/ against the driver: the sketch compiled
//! for this host with g++ and a stand-in for the Arduino API (tests/sketch_host/), its serial
//! port a pty, its sensor pin toggled on a schedule. The stand-in logs the time the sketch's
//! interrupt handler read for every edge; the driver must report exactly those times (through
//! the sketch's 64-bit extension of a 32-bit micros() that wraps during the run), or count
//! what the sketch's queue could not hold as lost.
//!
//! Needs g++ (CI installs build-essential); without it the test says so and passes by skipping.
//! It runs in real time for about 1.3 s and asserts nothing about timing.

use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::Arc;

use dioptra_core::{DeviceError, LightEvent, Photodiode, SystemClock};
use dioptra_photodiode::SerialPhotodiode;
use dioptra_transport::pty::PtyPair;

#[tokio::test]
async fn the_sketch_speaks_the_line_protocol_the_driver_reads() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let host = root.join("tests/sketch_host");
    let ino =
        root.join("../../firmware-protocol/photodiode/dioptra_photodiode/dioptra_photodiode.ino");
    let dir = tempfile::tempdir().unwrap();
    let bin = dir.path().join("sketch");
    let built = Command::new("g++")
        .args(["-std=c++17", "-O1", "-Wall", "-Wextra", "-Werror", "-I"])
        .arg(&host)
        .args(["-x", "c++"])
        .arg(&ino)
        .args(["-x", "none"])
        .arg(host.join("main.cpp"))
        .arg("-o")
        .arg(&bin)
        .output();
    let built = match built {
        Ok(b) => b,
        Err(e) => {
            eprintln!("skipped: no g++ to build the sketch for this host ({e})");
            return;
        }
    };
    assert!(
        built.status.success(),
        "the sketch does not build: {}",
        String::from_utf8_lossy(&built.stderr)
    );

    let pty = PtyPair::open().unwrap();
    let child = Command::new(&bin)
        .arg(&pty.slave_path)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut d = SerialPhotodiode::connect(pty.master, Arc::new(SystemClock::new()))
        .await
        .unwrap();
    assert_eq!(d.status().about, "arduino sketch 1.0");
    let mut events = Vec::new();
    let end = loop {
        match d.next_light().await {
            Ok(e) => events.push(e),
            Err(e) => break e,
        }
    };
    // The sketch exits at 1.3 s: the link goes away, or the next ping finds no one.
    assert!(
        matches!(end, DeviceError::Link(_)),
        "the run ended with {end:?}"
    );
    let out = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(log.contains("done"), "{log}");
    let given: Vec<(u64, bool)> = log
        .lines()
        .filter_map(|l| {
            let mut f = l.strip_prefix("edge ")?.split(' ');
            Some((f.next()?.parse().ok()?, f.next()? == "1"))
        })
        .collect();
    assert_eq!(given.len(), 150);

    let mut got = Vec::new();
    let mut lost = 0;
    for e in &events {
        match e {
            LightEvent::Edge(e) => got.push((e.device_time.as_micros(), e.rising)),
            LightEvent::Lost { count, .. } => lost += count,
        }
    }
    // Every edge reported is one the sketch was given, in order; with what was lost, all.
    let mut rest = given.iter();
    for g in &got {
        assert!(
            rest.any(|x| x == g),
            "{g:?} was not given (or out of order)"
        );
    }
    assert_eq!(
        got.len() as u64 + lost,
        150,
        "{} edges, {lost} lost",
        got.len()
    );
    // The burst overflowed the 64-slot queue: 63 kept, the rest reported, none missing.
    assert_eq!(lost, 37);
    assert_eq!(d.status().malformed_lines, 0);
    // Across micros()'s wrap at 2^32 us the times go on rising.
    assert!(got.iter().any(|g| g.0 < 1 << 32) && got.iter().any(|g| g.0 > 1 << 32));
    assert!(got.windows(2).all(|w| w[0].0 <= w[1].0));
}
