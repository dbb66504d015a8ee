//! Ground truth's cost: one thin-lens slice of a test scene (what `dioptra sim scene` renders
//! 40 times at 256 spp), and the rays a second that gives.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dioptra_core::{Diopters, EyeModel};
use dioptra_sim::scene::{render_thin_lens, Camera, Scene};

fn thin_lens(c: &mut Criterion) {
    let scene = Scene::generate(1_000_000);
    let (size, samples) = (64usize, 16u32);
    let cam = Camera::square(EyeModel::default(), size);
    let mut g = c.benchmark_group("thin_lens");
    g.throughput(Throughput::Elements(
        (size * size) as u64 * u64::from(samples),
    ));
    g.bench_function("64px_16spp", |b| {
        b.iter(|| render_thin_lens(black_box(&scene), &cam, Diopters(1.0), samples).unwrap())
    });
    g.finish();
}

criterion_group!(benches, thin_lens);
criterion_main!(benches);
