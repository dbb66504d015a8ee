//! Network weights: safetensors (f32, little-endian) with the architecture as JSON in the
//! metadata key `dioptra.arch`. Loading checks the metadata, every tensor's shape and dtype,
//! and that no value is NaN or infinite.

use crate::arch::Arch;
use crate::error::NetError;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;
use std::path::Path;

/// Metadata key holding the architecture JSON.
pub const ARCH_KEY: &str = "dioptra.arch";
/// Metadata key naming the format, so foreign safetensors files are told apart.
pub const FORMAT_KEY: &str = "format";
pub const FORMAT: &str = "dioptra-net/1";

/// One 3x3 convolution: weight [out][in][3][3] and bias [out].
#[derive(Debug, Clone, PartialEq)]
pub struct Conv {
    pub cin: usize,
    pub cout: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Weights {
    pub arch: Arch,
    pub convs: Vec<Conv>,
    /// Free-form provenance (how the weights were made), kept in the metadata.
    pub provenance: HashMap<String, String>,
}

/// Deterministic splitmix64 stream, for initialisation and tests without a RNG dependency.
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [-1, 1).
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }
}

impl Weights {
    /// He-uniform initialisation from `seed`, the last layer scaled down so training starts
    /// near a grey output instead of a saturated tanh.
    pub fn random(arch: &Arch, seed: u64) -> Result<Weights, NetError> {
        arch.validate()?;
        let mut rng = SplitMix(seed);
        let convs = (0..arch.conv_count())
            .map(|i| {
                let (cin, cout) = (arch.conv_in(i), arch.conv_out(i));
                let mut bound = (6.0 / (9 * cin) as f32).sqrt();
                // Each branch's last convolution (the chain's and the U-Net's); a refinement
                // net's starts at zero, so untrained it returns the classical result.
                if i + 1 == arch.layers || i + 1 == arch.conv_count() {
                    bound *= if arch.task.residual() { 0.0 } else { 0.1 };
                }
                Conv {
                    cin,
                    cout,
                    weight: (0..cout * cin * 9).map(|_| bound * rng.uniform()).collect(),
                    bias: vec![0.0; cout],
                }
            })
            .collect();
        Ok(Weights {
            arch: arch.clone(),
            convs,
            provenance: HashMap::new(),
        })
    }

    /// Builds weights from named tensors (as the training framework exports them), checking
    /// every shape against `arch`.
    pub fn from_tensors(
        arch: &Arch,
        mut tensors: HashMap<String, (Vec<usize>, Vec<f32>)>,
    ) -> Result<Weights, NetError> {
        arch.validate()?;
        let mut convs = Vec::with_capacity(arch.conv_count());
        let mut take = |name: &str, shape: &[usize]| -> Result<Vec<f32>, NetError> {
            let (found, data) = tensors.remove(name).ok_or_else(|| NetError::Tensor {
                name: name.into(),
                what: "missing from the weights".into(),
            })?;
            if found != shape || data.len() != shape.iter().product::<usize>() {
                return Err(NetError::Shape {
                    name: name.into(),
                    expected: shape.to_vec(),
                    found,
                });
            }
            if let Some(v) = data.iter().find(|v| !v.is_finite()) {
                return Err(NetError::Tensor {
                    name: name.into(),
                    what: format!("holds a non-finite value ({v}); the training diverged"),
                });
            }
            Ok(data)
        };
        for i in 0..arch.conv_count() {
            let (cin, cout) = (arch.conv_in(i), arch.conv_out(i));
            let n = arch.conv_name(i);
            let weight = take(&format!("{n}.weight"), &[cout, cin, 3, 3])?;
            let bias = take(&format!("{n}.bias"), &[cout])?;
            convs.push(Conv {
                cin,
                cout,
                weight,
                bias,
            });
        }
        if let Some(extra) = tensors.keys().next() {
            return Err(NetError::Tensor {
                name: extra.clone(),
                what: "is not part of the architecture in the metadata".into(),
            });
        }
        Ok(Weights {
            arch: arch.clone(),
            convs,
            provenance: HashMap::new(),
        })
    }

    /// Serialises to safetensors bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, NetError> {
        let mut meta = self.provenance.clone();
        meta.insert(ARCH_KEY.into(), self.arch.to_json());
        meta.insert(FORMAT_KEY.into(), FORMAT.into());
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = self
            .convs
            .iter()
            .enumerate()
            .flat_map(|(i, c)| {
                let n = self.arch.conv_name(i);
                [
                    (format!("{n}.weight"), vec![c.cout, c.cin, 3, 3], &c.weight),
                    (format!("{n}.bias"), vec![c.cout], &c.bias),
                ]
            })
            .map(|(n, s, d)| (n, s, d.iter().flat_map(|v| v.to_le_bytes()).collect()))
            .collect();
        let views = bytes
            .iter()
            .map(|(n, s, d)| {
                TensorView::new(Dtype::F32, s.clone(), d)
                    .map(|v| (n.clone(), v))
                    .map_err(|e| NetError::Tensor {
                        name: n.clone(),
                        what: e.to_string(),
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        safetensors::serialize(views, Some(meta)).map_err(|e| NetError::Corrupt(e.to_string()))
    }

    /// Parses and validates safetensors bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Weights, NetError> {
        let (_, header) =
            SafeTensors::read_metadata(bytes).map_err(|e| NetError::Corrupt(e.to_string()))?;
        let meta = header.metadata().clone().unwrap_or_default();
        match meta.get(FORMAT_KEY) {
            Some(f) if f == FORMAT => {}
            Some(f) => {
                return Err(NetError::MissingMetadata(format!(
                    "format {f:?}, expected {FORMAT:?}"
                )))
            }
            None => return Err(NetError::MissingMetadata(format!("no {FORMAT_KEY:?} key"))),
        }
        let arch_json = meta
            .get(ARCH_KEY)
            .ok_or_else(|| NetError::MissingMetadata(format!("no {ARCH_KEY:?} key")))?;
        let arch = Arch::from_json(arch_json)?;
        let st = SafeTensors::deserialize(bytes).map_err(|e| NetError::Corrupt(e.to_string()))?;
        let mut tensors = HashMap::new();
        for (name, view) in st.tensors() {
            if view.dtype() != Dtype::F32 {
                return Err(NetError::Tensor {
                    name,
                    what: format!("dtype {:?}, expected F32", view.dtype()),
                });
            }
            let data: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            tensors.insert(name, (view.shape().to_vec(), data));
        }
        let mut w = Weights::from_tensors(&arch, tensors)?;
        w.provenance = meta
            .into_iter()
            .filter(|(k, _)| k != ARCH_KEY && k != FORMAT_KEY)
            .collect();
        Ok(w)
    }

    pub fn load(path: &Path) -> Result<Weights, NetError> {
        let bytes = std::fs::read(path).map_err(|source| NetError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Weights::from_bytes(&bytes).map_err(|e| match e {
            NetError::Corrupt(m) => NetError::Corrupt(format!("{}: {m}", path.display())),
            e => e,
        })
    }

    /// Writes atomically (temporary file, then rename), so an interrupted save never leaves
    /// a truncated weights file behind.
    pub fn save(&self, path: &Path) -> Result<(), NetError> {
        let bytes = self.to_bytes()?;
        let tmp = path.with_extension("safetensors.tmp");
        let io = |source| NetError::Io {
            path: path.display().to_string(),
            source,
        };
        std::fs::write(&tmp, &bytes).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    }

    /// Parameter count.
    pub fn parameters(&self) -> usize {
        self.convs
            .iter()
            .map(|c| c.weight.len() + c.bias.len())
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Weights {
        let mut a = Arch::c1_small();
        a.layers = 4;
        a.channels = 6;
        Weights::random(&a, 7).unwrap()
    }

    #[test]
    fn round_trip_is_exact() {
        let mut w = small();
        w.provenance
            .insert("command".into(), "dioptra train".into());
        let back = Weights::from_bytes(&w.to_bytes().unwrap()).unwrap();
        assert_eq!(back, w);
    }

    #[test]
    fn truncated_file_is_refused_as_corrupt() {
        let bytes = small().to_bytes().unwrap();
        for cut in [0, 4, 8, 40, bytes.len() / 2, bytes.len() - 1] {
            let e = Weights::from_bytes(&bytes[..cut]).unwrap_err();
            assert!(matches!(e, NetError::Corrupt(_)), "cut {cut}: {e}");
        }
    }

    #[test]
    fn wrong_shapes_are_refused() {
        let w = small();
        // Claim 8 channels in the metadata while the tensors hold 6.
        let mut lie = w.clone();
        lie.arch.channels = 8;
        let e = Weights::from_bytes(&lie.to_bytes().unwrap()).unwrap_err();
        assert!(
            matches!(&e, NetError::Shape { name, expected, found }
                if name == "conv0.weight" && expected[0] == 8 && found[0] == 6),
            "{e}"
        );
        // One tensor missing.
        let mut short = w.clone();
        short.convs.pop();
        let e = Weights::from_bytes(&short.to_bytes().unwrap()).unwrap_err();
        assert!(e.to_string().contains("conv3.weight"), "{e}");
    }

    #[test]
    fn missing_or_foreign_metadata_is_refused() {
        let data = vec![0u8; 4 * 9];
        let v = TensorView::new(Dtype::F32, vec![1, 1, 3, 3], &data).unwrap();
        let plain = safetensors::serialize(vec![("conv0.weight", v.clone())], None).unwrap();
        assert!(matches!(
            Weights::from_bytes(&plain).unwrap_err(),
            NetError::MissingMetadata(_)
        ));
        let meta: HashMap<String, String> = [(FORMAT_KEY.to_string(), FORMAT.to_string())].into();
        let no_arch =
            safetensors::serialize(vec![("conv0.weight", v.clone())], Some(meta)).unwrap();
        assert!(Weights::from_bytes(&no_arch)
            .unwrap_err()
            .to_string()
            .contains(ARCH_KEY));
        let meta: HashMap<String, String> = [
            (FORMAT_KEY.to_string(), FORMAT.to_string()),
            (ARCH_KEY.to_string(), "{not json".to_string()),
        ]
        .into();
        let bad_arch = safetensors::serialize(vec![("conv0.weight", v)], Some(meta)).unwrap();
        assert!(matches!(
            Weights::from_bytes(&bad_arch).unwrap_err(),
            NetError::BadArch(_)
        ));
    }

    #[test]
    fn fv_unet_weights_round_trip_and_are_checked() {
        let mut a = Arch::preset("fv").unwrap();
        (a.layers, a.channels, a.unet_channels) = (4, 6, 4);
        let w = Weights::random(&a, 3).unwrap();
        assert_eq!(w.convs.len(), 4 + crate::arch::UNET_CONVS);
        let bytes = w.to_bytes().unwrap();
        assert_eq!(Weights::from_bytes(&bytes).unwrap(), w);
        // A U-Net width that disagrees with the tensors names the first U-Net tensor.
        let mut lie = w.clone();
        lie.arch.unet_channels = 5;
        let e = Weights::from_bytes(&lie.to_bytes().unwrap()).unwrap_err();
        assert!(
            matches!(&e, NetError::Shape { name, .. } if name == "unet0.weight"),
            "{e}"
        );
        // The U-Net's last convolution missing.
        let mut short = w.clone();
        short.convs.pop();
        let e = Weights::from_bytes(&short.to_bytes().unwrap()).unwrap_err();
        assert!(e.to_string().contains("unet6.weight"), "{e}");
        // C1 weights read as FV (the arch key swapped) fail on the first input layer.
        let mut c1 = small();
        c1.arch = a.clone();
        assert!(Weights::from_bytes(&c1.to_bytes().unwrap()).is_err());
        assert!(Weights::from_bytes(&bytes[..bytes.len() - 3]).is_err());
    }

    #[test]
    fn non_finite_values_are_refused() {
        let mut w = small();
        w.convs[1].bias[0] = f32::NAN;
        let e = Weights::from_bytes(&w.to_bytes().unwrap()).unwrap_err();
        assert!(e.to_string().contains("conv1.bias"), "{e}");
    }

    #[test]
    fn load_reports_the_path() {
        let e = Weights::load(Path::new("/nonexistent/w.safetensors")).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/w.safetensors"));
    }
}
