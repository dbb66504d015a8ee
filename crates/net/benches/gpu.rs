//! GPU network inference at 512x512 (random weights: speed depends only on the
//! architecture): per configuration, GPU wall time (input upload and output readback
//! included), GPU time from timestamp queries, dispatches and bytes moved per forward pass,
//! and the CPU's wall time beside it (median of 3 each). Without an adapter it says so.

use dioptra_net::gpu::GpuNet;
use dioptra_net::weights::SplitMix;
use dioptra_net::{Act, Arch, CpuNet, Weights};
use dioptra_render::timing::median_wall_ms;

fn main() {
    // `cargo test --benches` runs this with --bench absent: do nothing then.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let ctx = match dioptra_render::gpu::GpuContext::shared(None) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("skipped: no GPU adapter ({e})");
            return;
        }
    };
    let a = ctx.adapter();
    eprintln!(
        "adapter: {} ({}, {})",
        a.name,
        a.backend,
        if a.software { "software" } else { "hardware" }
    );
    eprintln!("| network (512x512) | GPU wall ms | GPU time ms (timestamps) | dispatches | submissions | MB up | MB down | CPU wall ms |");
    eprintln!("|---|---|---|---|---|---|---|---|");
    let mut rng = SplitMix(1);
    for name in ["c1", "c4"] {
        let arch = Arch::preset(name).expect("preset");
        let w = Weights::random(&arch, 3).expect("weights");
        let gpu = GpuNet::on(ctx.clone(), w.clone()).expect("gpu net");
        let cpu = CpuNet::new(w).expect("cpu net");
        let n = 512 * 512 * arch.in_channels();
        let x = Act::new(
            512,
            512,
            arch.in_channels(),
            (0..n).map(|_| rng.uniform()).collect(),
        )
        .expect("input");
        let g = median_wall_ms(3, || gpu.forward(&x).expect("gpu forward")).0;
        let s = gpu.last_stats();
        let c = median_wall_ms(3, || cpu.forward(&x).expect("cpu forward")).0;
        eprintln!(
            "| {name} ({} layers x {} ch, r={}) | {g:.1} | {} | {} | {} | {:.2} | {:.2} | {c:.1} |",
            arch.layers,
            arch.channels,
            arch.rate,
            s.gpu_ns
                .map_or("n/a".to_string(), |ns| format!("{:.1}", ns * 1e-6)),
            s.dispatches,
            s.submissions,
            s.bytes_uploaded as f64 / 1e6,
            s.bytes_read_back as f64 / 1e6,
        );
        for (label, ns) in &s.passes {
            eprintln!("    {label:<16} {:.2} ms", ns * 1e-6);
        }
    }
}
