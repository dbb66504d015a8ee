//! The network as candle variables, and Adam with state that can be checkpointed.

use crate::arch::Arch;
use crate::graph::{forward, Ops};
use crate::weights::Weights;
use candle_core::{backprop::GradStore, Device, Result, Tensor, Var};
use std::collections::HashMap;

/// Trainable network: weight [out, in, 3, 3] and bias [out] per layer, NCHW activations.
pub struct CandleNet {
    pub arch: Arch,
    pub convs: Vec<(Var, Var)>,
}

impl CandleNet {
    pub fn from_weights(w: &Weights, dev: &Device) -> Result<CandleNet> {
        let convs = w
            .convs
            .iter()
            .map(|c| {
                let wt = Tensor::from_vec(c.weight.clone(), (c.cout, c.cin, 3, 3), dev)?;
                let b = Tensor::from_vec(c.bias.clone(), c.cout, dev)?;
                Ok((Var::from_tensor(&wt)?, Var::from_tensor(&b)?))
            })
            .collect::<Result<_>>()?;
        Ok(CandleNet {
            arch: w.arch.clone(),
            convs,
        })
    }

    pub fn to_weights(&self) -> std::result::Result<Weights, crate::NetError> {
        let mut t = HashMap::new();
        for (i, (w, b)) in self.convs.iter().enumerate() {
            let n = self.arch.conv_name(i);
            for (name, v) in [(format!("{n}.weight"), w), (format!("{n}.bias"), b)] {
                let data = v.as_tensor().flatten_all()?.to_vec1::<f32>()?;
                t.insert(name, (v.as_tensor().dims().to_vec(), data));
            }
        }
        Weights::from_tensors(&self.arch, t)
    }

    pub fn vars(&self) -> Vec<Var> {
        self.convs
            .iter()
            .flat_map(|(w, b)| [w.clone(), b.clone()])
            .collect()
    }

    /// Full-resolution NCHW input (H, W multiples of [`Arch::size_multiple`]) to NCHW output
    /// in [0, 1].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        forward(&self.arch, self, x)
    }
}

impl Ops for CandleNet {
    type T = Tensor;
    type E = candle_core::Error;
    fn conv(&self, x: &Tensor, layer: usize, elu: bool) -> Result<Tensor> {
        let (w, b) = &self.convs[layer];
        super::conv::conv(x, w.as_tensor(), b.as_tensor(), elu)
    }
    fn add(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        a + b
    }
    fn concat(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        Tensor::cat(&[a, b], 1)
    }
    fn tanh01(&self, x: &Tensor) -> Result<Tensor> {
        x.tanh()?.affine(0.5, 0.5)
    }
    fn space_to_depth(&self, x: &Tensor, r: usize) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        x.reshape((b, c, h / r, r, w / r, r))?
            .permute((0, 1, 3, 5, 2, 4))?
            .reshape((b, c * r * r, h / r, w / r))
    }
    fn avg_pool2(&self, x: &Tensor) -> Result<Tensor> {
        x.avg_pool2d(2)
    }
    fn upsample2(&self, x: &Tensor) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        x.upsample_nearest2d(2 * h, 2 * w)
    }
    fn depth_to_space(&self, x: &Tensor, r: usize) -> Result<Tensor> {
        let (b, crr, h, w) = x.dims4()?;
        let c = crr / (r * r);
        x.reshape((b, c, r, r, h, w))?
            .permute((0, 1, 4, 2, 5, 3))?
            .reshape((b, c, h * r, w * r))
    }
}

/// A named tensor: name, shape, row-major values.
pub type NamedTensor = (String, Vec<usize>, Vec<f32>);

/// Adam (Kingma and Ba), with its moments exposed so a checkpoint can resume exactly.
pub struct Adam {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub t: u64,
    pub m: Vec<Tensor>,
    pub v: Vec<Tensor>,
}

impl Adam {
    pub fn new(vars: &[Var], lr: f64) -> Result<Adam> {
        let zeros = vars
            .iter()
            .map(|v| v.as_tensor().zeros_like())
            .collect::<Result<Vec<_>>>()?;
        Ok(Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            t: 0,
            m: zeros.clone(),
            v: zeros,
        })
    }

    pub fn step(&mut self, vars: &[Var], grads: &GradStore) -> Result<()> {
        self.t += 1;
        let c1 = 1.0 - self.beta1.powi(self.t as i32);
        let c2 = 1.0 - self.beta2.powi(self.t as i32);
        for (i, var) in vars.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else {
                continue;
            };
            // Gradients carry this step's graph; moments built from them would chain every
            // step's graph to the next and keep them all alive (24 GB after 300 C1 steps).
            let g = g.detach();
            self.m[i] = ((&self.m[i] * self.beta1)? + (&g * (1.0 - self.beta1))?)?;
            self.v[i] = ((&self.v[i] * self.beta2)? + (g.sqr()? * (1.0 - self.beta2))?)?;
            let mhat = (&self.m[i] / c1)?;
            let vhat = (&self.v[i] / c2)?;
            let upd = (mhat / (vhat.sqrt()? + self.eps)?)?;
            var.set(&(var.as_tensor() - (upd * self.lr)?)?)?;
        }
        Ok(())
    }

    /// Moments as named tensors (`m{i}`, `v{i}`) plus the step count, for checkpoints.
    pub fn state(&self) -> Result<Vec<NamedTensor>> {
        let mut out = vec![("t".to_string(), vec![1], vec![self.t as f32])];
        for (k, ts) in [("m", &self.m), ("v", &self.v)] {
            for (i, t) in ts.iter().enumerate() {
                out.push((
                    format!("{k}{i}"),
                    t.dims().to_vec(),
                    t.flatten_all()?.to_vec1::<f32>()?,
                ));
            }
        }
        Ok(out)
    }

    /// Restores moments saved by [`Adam::state`]; shapes must match the current variables.
    pub fn restore(&mut self, state: &HashMap<String, (Vec<usize>, Vec<f32>)>) -> Result<()> {
        let dev = self
            .m
            .first()
            .map(|t| t.device().clone())
            .unwrap_or(Device::Cpu);
        let get = |name: &str, like: &Tensor| -> Result<Tensor> {
            match state.get(name) {
                Some((s, d)) if s == like.dims() => Tensor::from_vec(d.clone(), s.clone(), &dev),
                _ => candle_core::bail!("optimizer state {name} is missing or has the wrong shape"),
            }
        };
        let m = self
            .m
            .iter()
            .enumerate()
            .map(|(i, t)| get(&format!("m{i}"), t))
            .collect::<Result<Vec<_>>>()?;
        let v = self
            .v
            .iter()
            .enumerate()
            .map(|(i, t)| get(&format!("v{i}"), t))
            .collect::<Result<Vec<_>>>()?;
        let t = state
            .get("t")
            .and_then(|(_, d)| d.first().copied())
            .unwrap_or(0.0);
        (self.m, self.v, self.t) = (m, v, t as u64);
        Ok(())
    }
}
