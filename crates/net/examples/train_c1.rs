//! Library-level training entry point without the CLI's device dependencies (the same
//! `dioptra_net::train::train` as `dioptra train`), for long background runs:
//! `cargo run --release -p dioptra-net --example train_c1 -- OUT STEPS [SCENES] [FOCI] [SAMPLES] [BATCH]`
//! Rerunning with the same OUT resumes from its checkpoint.

use dioptra_net::train::{train, TrainConfig, TrainEvent};
use dioptra_net::Arch;
use std::path::PathBuf;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a: Vec<String> = std::env::args().collect();
    let out = PathBuf::from(
        a.get(1)
            .ok_or("usage: train_c1 OUT STEPS [SCENES] [FOCI] [SAMPLES] [BATCH]")?,
    );
    let num = |i: usize, d: u64| a.get(i).map_or(Ok(d), |s| s.parse::<u64>());
    let mut cfg = TrainConfig::new(Arch::c1_small(), out);
    cfg.steps = num(2, 20_000)?;
    cfg.scenes = num(3, 32)?;
    cfg.foci_per_scene = num(4, 4)? as usize;
    cfg.data.samples = num(5, 32)? as u32;
    cfg.batch = num(6, 4)? as usize;
    cfg.checkpoint_every = 50;
    let t = Instant::now();
    let mut ema: Option<f32> = None;
    train(&cfg, &mut |e| match e {
        TrainEvent::Data { done, total } => {
            println!("scene {done}/{total} {:.0}s", t.elapsed().as_secs_f64())
        }
        TrainEvent::Step { step, loss, .. } => {
            let m = ema.map_or(loss, |m| 0.98 * m + 0.02 * loss);
            ema = Some(m);
            if step % 10 == 0 || step <= 3 {
                println!(
                    "step {step} loss {loss:.5} avg {m:.5} {:.0}s",
                    t.elapsed().as_secs_f64()
                );
            }
        }
        e => println!("{e:?} {:.0}s", t.elapsed().as_secs_f64()),
    })?;
    Ok(())
}
