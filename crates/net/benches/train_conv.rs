//! One training step's convolutions, forward and backward, with candle's own `conv2d` (with
//! bias and ELU) against the im2col + GEMM custom op the trainer uses (`train::conv`): the
//! shipped C1R's net (6 layers x 16 channels at r = 2, 8 input channels) on a batch of 8
//! patches of 96 px, so 48 x 48 interleaved. Issue 21's "step time before and after" for the
//! part that dominated it.

use candle_core::{Device, Tensor, Var};
use criterion::{criterion_group, criterion_main, Criterion};
use dioptra_net::train::conv::conv;

/// (in, out) channels per layer: 8 x r^2 in, 3 x r^2 out.
const LAYERS: [(usize, usize); 6] = [(32, 16), (16, 16), (16, 16), (16, 16), (16, 16), (16, 12)];

fn stack(ours: bool, x: &Tensor, params: &[(Var, Var)]) -> Tensor {
    let mut h = x.clone();
    for (i, (w, b)) in params.iter().enumerate() {
        let elu = i + 1 < params.len();
        h = if ours {
            conv(&h, w.as_tensor(), b.as_tensor(), elu).expect("conv")
        } else {
            let cout = b.as_tensor().dim(0).expect("bias");
            let pre = h
                .conv2d(w.as_tensor(), 1, 1, 1, 1)
                .and_then(|y| y.broadcast_add(&b.as_tensor().reshape((1, cout, 1, 1))?))
                .expect("conv2d");
            if elu {
                pre.elu(1.0).expect("elu")
            } else {
                pre
            }
        };
    }
    h
}

fn bench(c: &mut Criterion) {
    let dev = Device::Cpu;
    let x = Tensor::randn(0f32, 1.0, (8, 32, 48, 48), &dev).expect("x");
    let params: Vec<(Var, Var)> = LAYERS
        .iter()
        .map(|&(cin, cout)| {
            let w = Tensor::randn(0f32, 0.1, (cout, cin, 3, 3), &dev).expect("w");
            let b = Tensor::zeros(cout, candle_core::DType::F32, &dev).expect("b");
            (
                Var::from_tensor(&w).expect("w"),
                Var::from_tensor(&b).expect("b"),
            )
        })
        .collect();
    let mut g = c.benchmark_group("train_step_convs_c1r_b8_96px");
    g.sample_size(10);
    for (name, ours) in [("candle_conv2d", false), ("im2col_gemm_op", true)] {
        g.bench_function(format!("{name}_forward"), |b| {
            b.iter(|| stack(ours, &x, &params).sum_all().expect("sum"))
        });
        g.bench_function(format!("{name}_forward_backward"), |b| {
            b.iter(|| {
                let loss = stack(ours, &x, &params).sqr().and_then(|y| y.mean_all());
                loss.expect("loss").backward().expect("backward")
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
