//! Driver overhead of `set_power` over an in-memory link to the simulators (target: ≤ 20 µs
//! median), and the wire time each Optotune command costs at 115200 baud, which a real port
//! adds on top.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_core::{Diopters, PowerRange, SystemClock, VarifocalLens};
use dioptra_lens::optotune::protocol::{self as p, Command, Scaling};
use dioptra_lens::{ControllerConfig, LensController, LensLimits, Optotune, OptotuneConfig};
use dioptra_protocol::{encode_frame, Message, MAX_FRAME_LEN};
use dioptra_sim::lens_controller::{self, LensControllerSim, LensControllerSimConfig};
use dioptra_sim::optotune::{self, OptotuneSim, OptotuneSimConfig};
use dioptra_sim::tokio_clock::TokioClock;
use dioptra_transport::memory;

/// Seconds per byte at 115200 baud, 8N1 (10 bits on the line per byte).
const BYTE_S: f64 = 10.0 / 115_200.0;

fn limits() -> LensLimits {
    LensLimits::new(PowerRange::new(Diopters(-1.0), Diopters(5.0)).unwrap())
}

fn wire_line<C: Command>(name: &str, cmd: C) {
    let mut out = Vec::new();
    p::encode(&cmd, &Scaling::default(), &mut out).unwrap();
    let reply = if C::REPLY_LEN == 0 {
        0
    } else {
        C::REPLY_LEN + p::TRAILER_LEN
    };
    let us = (out.len() + reply) as f64 * BYTE_S * 1e6;
    println!(
        "  {name:<28} {:>2} B out {:>2} B back  {us:7.0} µs",
        out.len(),
        reply
    );
}

fn print_wire_times() {
    println!("Optotune Lens Driver 4 wire time per command at 115200 baud (8N1):");
    wire_line("PwDA set focal power", p::SetFocalPower { diopters: 1.5 });
    wire_line("Aw set current", p::SetCurrent { ma: 100.0 });
    wire_line("PrDA read focal power", p::GetFocalPower);
    wire_line("Ar read current", p::GetCurrent);
    wire_line("TCA temperature", p::GetTemperature);
    wire_line("MwCA focal-power mode", p::SetFocalPowerMode);
    wire_line("MMA mode", p::GetMode);
    wire_line(
        "PwTA temperature limits",
        p::SetTemperatureLimits {
            upper_c: 40.0,
            lower_c: 20.0,
        },
    );
    wire_line("H firmware type", p::GetFirmwareType);
    wire_line("V firmware version", p::GetFirmwareVersion);
    wire_line("IR device id", p::GetDeviceId);
    wire_line("Sr status", p::GetStatus);
    let mut buf = [0u8; MAX_FRAME_LEN];
    let n = encode_frame(
        1,
        &Message::SetFocalPower {
            diopters: 1.5,
            apply_at_us: 0,
        },
        &mut buf,
    )
    .unwrap();
    println!(
        "dioptra lens controller SetFocalPower frame: {n} B, {:.0} µs at 115200 baud (0 on USB bulk)",
        n as f64 * BYTE_S * 1e6
    );
}

fn bench(c: &mut Criterion) {
    print_wire_times();
    // The simulators run on a worker thread; the driver runs on the benchmark's thread.
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let mut opto = rt.block_on(async {
        let (host, mut dev) = memory::pair(1 << 20);
        tokio::spawn(async move {
            let mut sim = OptotuneSim::new(OptotuneSimConfig::default());
            let _ = optotune::serve(&mut dev, &mut sim, &TokioClock::new()).await;
        });
        Optotune::connect(
            host,
            OptotuneConfig::new(limits()),
            Arc::new(SystemClock::new()),
        )
        .await
        .unwrap()
    });
    let mut ctl = rt.block_on(async {
        let (host, mut dev) = memory::pair(1 << 20);
        tokio::spawn(async move {
            let mut sim = LensControllerSim::new(LensControllerSimConfig::default());
            let _ = lens_controller::serve(&mut dev, &mut sim, &TokioClock::new()).await;
        });
        LensController::connect(
            host,
            ControllerConfig::new(limits()),
            Arc::new(SystemClock::new()),
        )
        .await
        .unwrap()
    });
    let mut k = 0u32;
    c.bench_function(
        "optotune set_power (in-memory link, driver overhead)",
        |b| {
            b.iter(|| {
                k = k.wrapping_add(1);
                let d = Diopters(if k % 2 == 0 { 1.0 } else { 1.5 });
                black_box(rt.block_on(opto.set_power(d)).unwrap())
            })
        },
    );
    c.bench_function(
        "lens controller set_power (in-memory link, driver overhead)",
        |b| {
            b.iter(|| {
                k = k.wrapping_add(1);
                let d = Diopters(if k % 2 == 0 { 1.0 } else { 1.5 });
                black_box(rt.block_on(ctl.set_power(d)).unwrap())
            })
        },
    );
}

criterion_group!(benches, bench);
criterion_main!(benches);
