//! CPU inference at 512x512. Target (issue 7): the shipped C1 in <= 150 ms on the project's
//! 2-core machine. Random weights: speed depends only on the architecture.

use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_net::weights::SplitMix;
use dioptra_net::{Act, Arch, CpuNet, Weights};

fn bench(c: &mut Criterion) {
    // As the dioptra binary runs (see dioptra_render::alloc).
    dioptra_render::alloc::keep_freed_memory();
    let mut g = c.benchmark_group("cpu_inference_512");
    g.sample_size(10);
    let mut rng = SplitMix(1);
    let mut configs = vec![("c1_8x32_r2", Arch::c1_small())];
    for (name, layers, channels) in [("c1_12x32_r2", 12, 32), ("c1_8x64_r2", 8, 64)] {
        configs.push((
            name,
            Arch {
                layers,
                channels,
                ..Arch::c1_small()
            },
        ));
    }
    for name in ["c3", "c4", "c5"] {
        let a = Arch::preset(name).expect("preset");
        configs.push((name, a));
    }
    for (name, arch) in configs {
        let net = CpuNet::new(Weights::random(&arch, 3).expect("weights")).expect("net");
        let n = 512 * 512 * arch.in_channels();
        let x = Act::new(
            512,
            512,
            arch.in_channels(),
            (0..n).map(|_| rng.uniform()).collect(),
        )
        .expect("input");
        g.bench_function(name, |b| b.iter(|| net.forward(&x).expect("forward")));
        if name == "c1_8x32_r2" {
            // The im2col + GEMM fallback (CPUs without AVX2 + FMA), for comparison.
            let gemm = CpuNet::with_kernel(net.weights().clone(), false).expect("net");
            g.bench_function("c1_8x32_r2_gemm", |b| {
                b.iter(|| gemm.forward(&x).expect("forward"))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
