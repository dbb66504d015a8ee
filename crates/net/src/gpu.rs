//! Network inference on wgpu, on the renderer's GPU context: the same graph
//! ([`crate::graph::forward`]) over GPU tensors. Weights are uploaded once per loaded net;
//! a forward pass is one frame (one submission): the input is uploaded, every layer's
//! tensor stays on the GPU, and only the output is read back. Kernels: `shaders/net.wgsl`.

use crate::arch::Arch;
use crate::cpu::{check_input, Act};
use crate::error::{input, NetError};
use crate::graph::{forward, Ops};
use crate::infer::Infer;
use crate::refine::{self, Refined};
use crate::tasks;
use crate::tiles::TileMap;
use crate::weights::Weights;
use dioptra_core::{Diopters, EyeModel, RgbImage, Rgbd};
use dioptra_render::gpu::{BufRef, Frame, FrameStats, GpuContext, ShaderKernel};
use dioptra_render::views::WarpErrors;
use dioptra_render::{GpuError, Layers, RenderError};
use std::cell::RefCell;
use std::path::Path;
use std::sync::{Arc, Mutex};

const NET_WGSL: &str = include_str!("../shaders/net.wgsl");

const fn kernel(entry: &'static str, read_only: u32) -> ShaderKernel {
    ShaderKernel {
        source: NET_WGSL,
        entry,
        read_only,
        read_write: 1,
    }
}
const CONV: ShaderKernel = kernel("conv", 3);
const ADD: ShaderKernel = kernel("add", 2);
const TANH01: ShaderKernel = kernel("tanh01", 1);
const SPACE_TO_DEPTH: ShaderKernel = kernel("space_to_depth", 1);
const DEPTH_TO_SPACE: ShaderKernel = kernel("depth_to_space", 1);

/// Tile side and output channels per workgroup of the convolution (net.wgsl's TS, COT).
const CONV_TILE: u32 = 16;
const CONV_COUT: u32 = 8;
/// Invocations per workgroup of the elementwise kernels.
const ELEMENTWISE: u32 = 256;

/// The uniform every net kernel takes (net.wgsl's `Params`).
#[derive(Clone, Copy, Default)]
#[repr(C)]
struct Params {
    w: u32,
    h: u32,
    cin: u32,
    cout: u32,
    act: u32,
    r: u32,
    len: u32,
    stride: u32,
}

impl Params {
    fn words(&self) -> [u32; 8] {
        [
            self.w,
            self.h,
            self.cin,
            self.cout,
            self.act,
            self.r,
            self.len,
            self.stride,
        ]
    }
}

fn gpu_err(e: GpuError) -> NetError {
    NetError::Render(RenderError::from(e))
}

fn size(v: usize, what: &str) -> Result<u32, NetError> {
    u32::try_from(v).map_err(|_| input(format!("{what} {v} is too large for the GPU")))
}

/// A tensor on the GPU: CHW at interleaved resolution, or HWC at full resolution (`hwc`)
/// for the network's input and output.
#[derive(Clone)]
pub struct GpuTensor {
    pub h: usize,
    pub w: usize,
    pub c: usize,
    pub hwc: bool,
    buf: BufRef,
}

impl GpuTensor {
    fn len(&self) -> usize {
        self.h * self.w * self.c
    }
}

/// One convolution's weights, resident on the GPU.
struct GpuConv {
    cin: usize,
    cout: usize,
    weight: BufRef,
    bias: BufRef,
}

/// A network ready for GPU inference.
pub struct GpuNet {
    weights: Weights,
    ctx: Arc<GpuContext>,
    convs: Vec<GpuConv>,
    last: Mutex<FrameStats>,
}

/// Loads `weights` (or the shipped weights of `config`) as [`crate::load_net`] does, for
/// GPU inference on the adapter whose name contains `adapter` (or the first hardware one).
pub fn load_gpu_net(
    weights: Option<&Path>,
    config: &str,
    adapter: Option<&str>,
) -> Result<GpuNet, NetError> {
    let cpu = crate::load_net(weights, config)?;
    GpuNet::new(cpu.weights().clone(), adapter)
}

impl GpuNet {
    /// Uploads `weights` once to the process's GPU context.
    pub fn new(weights: Weights, adapter: Option<&str>) -> Result<GpuNet, NetError> {
        refuse_unet(&weights.arch)?;
        let ctx = GpuContext::shared(adapter).map_err(gpu_err)?;
        GpuNet::on(ctx, weights)
    }

    /// As [`GpuNet::new`], on a given context.
    pub fn on(ctx: Arc<GpuContext>, weights: Weights) -> Result<GpuNet, NetError> {
        weights.arch.validate()?;
        refuse_unet(&weights.arch)?;
        if weights.convs.len() != weights.arch.conv_count() {
            return Err(NetError::BadArch(format!(
                "{} convolutions for {} layers",
                weights.convs.len(),
                weights.arch.layers
            )));
        }
        let convs = weights
            .convs
            .iter()
            .enumerate()
            .map(|(i, c)| {
                if c.weight.len() != c.cout * c.cin * 9 || c.bias.len() != c.cout {
                    return Err(NetError::BadArch(format!(
                        "convolution {i}: {} weights and {} biases for {} -> {} channels",
                        c.weight.len(),
                        c.bias.len(),
                        c.cin,
                        c.cout
                    )));
                }
                Ok(GpuConv {
                    cin: c.cin,
                    cout: c.cout,
                    weight: ctx
                        .upload_resident("convolution weights", &c.weight)
                        .map_err(gpu_err)?,
                    bias: ctx
                        .upload_resident("convolution biases", &c.bias)
                        .map_err(gpu_err)?,
                })
            })
            .collect::<Result<Vec<_>, NetError>>()?;
        Ok(GpuNet {
            weights,
            ctx,
            convs,
            last: Mutex::new(FrameStats::default()),
        })
    }

    pub fn arch(&self) -> &Arch {
        &self.weights.arch
    }
    pub fn weights(&self) -> &Weights {
        &self.weights
    }
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// Dispatches, bytes moved and GPU time of the last forward pass.
    pub fn last_stats(&self) -> FrameStats {
        self.last.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// Runs the network on a full-resolution HWC input of `in_channels`; any size (padded
    /// to the interleave rate, cropped back), exactly as [`crate::CpuNet::forward`].
    pub fn forward(&self, x: &Act) -> Result<Act, NetError> {
        let arch = self.arch();
        check_input(arch, x)?;
        let padded = x.pad_to_multiple(arch.rate);
        let mut frame = Frame::new(&self.ctx).map_err(gpu_err)?;
        let buf = frame
            .upload("network input", &padded.data)
            .map_err(gpu_err)?;
        let t = GpuTensor {
            h: padded.h,
            w: padded.w,
            c: padded.c,
            hwc: true,
            buf,
        };
        let pass = Pass {
            net: self,
            frame: RefCell::new(frame),
        };
        let y = forward(arch, &pass, &t)?;
        let mut frame = pass.frame.into_inner();
        let r = frame.read(&y.buf, 4 * y.len() as u64);
        let (rb, stats) = frame.finish().map_err(gpu_err)?;
        if let Ok(mut l) = self.last.lock() {
            *l = stats;
        }
        let mut data = rb.f32s(r);
        data.truncate(y.len());
        Ok(Act::new(y.h, y.w, y.c, data)?.crop(x.h, x.w))
    }

    /// C1: what the eye focused at `focus` sees of `rgbd` (as [`crate::CpuNet::defocus`]).
    pub fn defocus(
        &self,
        rgbd: &Rgbd,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<RgbImage, NetError> {
        tasks::defocus(self, rgbd, focus, eye)
    }

    /// C4: multifocal layers for the network's display planes (as
    /// [`crate::CpuNet::decompose`]).
    pub fn decompose(&self, rgbd: &Rgbd) -> Result<Layers, NetError> {
        tasks::decompose(self, rgbd)
    }
}

impl Infer for GpuNet {
    fn arch(&self) -> &Arch {
        GpuNet::arch(self)
    }

    fn forward(&self, x: &Act) -> Result<Act, NetError> {
        GpuNet::forward(self, x)
    }

    /// The whole image: the GPU has no tiled evaluation.
    fn forward_on(&self, x: &Act, _: &TileMap) -> Result<Act, NetError> {
        GpuNet::forward(self, x)
    }
}

impl GpuNet {
    /// C1R on the GPU: the net runs on the whole image and its correction is kept on the
    /// pixels the error map corrects, so the result equals [`crate::CpuNet::refine_defocus`]
    /// (which evaluates only those tiles). The classical composite's smooth part
    /// ([`crate::refine::classical_composite`]) is computed on the CPU, as the map is.
    pub fn refine_defocus(
        &self,
        rgbd: &Rgbd,
        classical: &RgbImage,
        focus: Diopters,
        eye: &EyeModel,
    ) -> Result<Refined, NetError> {
        refine::refine_defocus(self, rgbd, classical, focus, eye)
    }

    /// C4R on the GPU (as [`crate::CpuNet::refine_decompose`]).
    pub fn refine_decompose(&self, rgbd: &Rgbd, classical: &Layers) -> Result<Layers, NetError> {
        refine::refine_decompose(self, rgbd, classical)
    }

    /// C5R on the GPU: the net on the whole view, its correction kept on the pixels the
    /// warp's error map marks, so the result equals [`crate::CpuNet::refine_view`] (which
    /// evaluates only those tiles).
    pub fn refine_view(&self, view: &Rgbd, errors: &WarpErrors) -> Result<RgbImage, NetError> {
        refine::refine_view(self, view, errors)
    }
}

/// One forward pass being recorded: every op appends dispatches to the same frame.
struct Pass<'a> {
    net: &'a GpuNet,
    frame: RefCell<Frame<'a>>,
}

impl Pass<'_> {
    fn scratch(&self, h: usize, w: usize, c: usize, hwc: bool) -> Result<GpuTensor, NetError> {
        let buf = self
            .frame
            .borrow_mut()
            .scratch("network activation", 4 * (h * w * c) as u64)
            .map_err(gpu_err)?;
        Ok(GpuTensor { h, w, c, hwc, buf })
    }

    fn dispatch(
        &self,
        k: &ShaderKernel,
        p: Params,
        bufs: &[&BufRef],
        groups: [u32; 3],
    ) -> Result<(), NetError> {
        self.frame
            .borrow_mut()
            .dispatch_shader(k, &p.words(), bufs, groups)
            .map_err(gpu_err)
    }

    /// An elementwise kernel over `len` values: rows of up to 32768 workgroups.
    fn elementwise(&self, k: &ShaderKernel, len: usize, bufs: &[&BufRef]) -> Result<(), NetError> {
        let groups = size(len, "tensor length")?.div_ceil(ELEMENTWISE);
        let gx = groups.clamp(1, 32768);
        let p = Params {
            len: len as u32,
            stride: gx * ELEMENTWISE,
            ..Params::default()
        };
        self.dispatch(k, p, bufs, [gx, groups.div_ceil(gx), 1])
    }
}

/// The GPU shaders have no pooling or upsampling yet, so FV's U-Net runs on the CPU only.
fn refuse_unet(arch: &Arch) -> Result<(), NetError> {
    if arch.unet_channels > 0 {
        return Err(NetError::Input(format!(
            "GPU inference does not run the {} network's U-Net (no pooling/upsampling shaders yet): use CPU inference",
            arch.task.name()
        )));
    }
    Ok(())
}

fn chw(t: &GpuTensor, what: &str) -> Result<(), NetError> {
    if t.hwc {
        return Err(input(format!(
            "{what} takes an interleaved tensor, not the full-resolution input"
        )));
    }
    Ok(())
}

impl Ops for Pass<'_> {
    type T = GpuTensor;
    type E = NetError;

    fn conv(&self, x: &GpuTensor, layer: usize, elu: bool) -> Result<GpuTensor, NetError> {
        chw(x, "convolution")?;
        let k = self
            .net
            .convs
            .get(layer)
            .ok_or_else(|| input(format!("no layer {layer}")))?;
        if x.c != k.cin {
            return Err(input(format!(
                "convolution expects {} input channels, got {}",
                k.cin, x.c
            )));
        }
        let y = self.scratch(x.h, x.w, k.cout, false)?;
        let (w, h) = (size(x.w, "width")?, size(x.h, "height")?);
        let p = Params {
            w,
            h,
            cin: k.cin as u32,
            cout: k.cout as u32,
            act: elu as u32,
            ..Params::default()
        };
        let groups = [
            w.div_ceil(CONV_TILE),
            h.div_ceil(CONV_TILE),
            (k.cout as u32).div_ceil(CONV_COUT),
        ];
        self.dispatch(&CONV, p, &[&x.buf, &k.weight, &k.bias, &y.buf], groups)?;
        Ok(y)
    }

    fn add(&self, a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor, NetError> {
        if (a.h, a.w, a.c, a.hwc) != (b.h, b.w, b.c, b.hwc) {
            return Err(input("residual shapes differ"));
        }
        let y = self.scratch(a.h, a.w, a.c, a.hwc)?;
        self.elementwise(&ADD, a.len(), &[&a.buf, &b.buf, &y.buf])?;
        Ok(y)
    }

    fn concat(&self, a: &GpuTensor, b: &GpuTensor) -> Result<GpuTensor, NetError> {
        chw(a, "concatenation")?;
        chw(b, "concatenation")?;
        if (a.h, a.w) != (b.h, b.w) {
            return Err(input("concatenated sizes differ"));
        }
        // CHW: concatenating channels is appending one buffer to the other, two GPU copies.
        let y = self.scratch(a.h, a.w, a.c + b.c, false)?;
        let (na, nb) = (4 * a.len() as u64, 4 * b.len() as u64);
        let mut f = self.frame.borrow_mut();
        f.copy(&a.buf, 0, &y.buf, 0, na);
        f.copy(&b.buf, 0, &y.buf, na, nb);
        Ok(y)
    }

    fn tanh01(&self, x: &GpuTensor) -> Result<GpuTensor, NetError> {
        let y = self.scratch(x.h, x.w, x.c, x.hwc)?;
        self.elementwise(&TANH01, x.len(), &[&x.buf, &y.buf])?;
        Ok(y)
    }

    fn space_to_depth(&self, x: &GpuTensor, r: usize) -> Result<GpuTensor, NetError> {
        if !x.hwc {
            return Err(input("space_to_depth takes the full-resolution input"));
        }
        if r == 0 || x.h % r != 0 || x.w % r != 0 {
            return Err(input(format!(
                "{}x{} is not a multiple of the interleave rate {r}",
                x.w, x.h
            )));
        }
        let (h, w, c) = (x.h / r, x.w / r, x.c * r * r);
        let y = self.scratch(h, w, c, false)?;
        let p = Params {
            w: size(w, "width")?,
            h: size(h, "height")?,
            cin: x.c as u32,
            r: r as u32,
            ..Params::default()
        };
        let groups = [
            p.w.div_ceil(CONV_TILE),
            p.h.div_ceil(CONV_TILE),
            size(c, "channels")?,
        ];
        self.dispatch(&SPACE_TO_DEPTH, p, &[&x.buf, &y.buf], groups)?;
        Ok(y)
    }

    fn depth_to_space(&self, x: &GpuTensor, r: usize) -> Result<GpuTensor, NetError> {
        chw(x, "depth_to_space")?;
        let rr = r * r;
        if r == 0 || x.c % rr != 0 {
            return Err(input(format!(
                "{} channels do not divide by r^2 = {rr}",
                x.c
            )));
        }
        let (h, w, c) = (x.h * r, x.w * r, x.c / rr);
        let y = self.scratch(h, w, c, true)?;
        let p = Params {
            w: size(x.w, "width")?,
            h: size(x.h, "height")?,
            cout: c as u32,
            r: r as u32,
            ..Params::default()
        };
        let groups = [
            size(w, "width")?.div_ceil(CONV_TILE),
            size(h, "height")?.div_ceil(CONV_TILE),
            1,
        ];
        self.dispatch(&DEPTH_TO_SPACE, p, &[&x.buf, &y.buf], groups)?;
        Ok(y)
    }

    // Unreachable: nets with a U-Net are refused when the GpuNet is made.
    fn avg_pool2(&self, _: &GpuTensor) -> Result<GpuTensor, NetError> {
        Err(input("GPU inference has no average pooling"))
    }
    fn upsample2(&self, _: &GpuTensor) -> Result<GpuTensor, NetError> {
        Err(input("GPU inference has no upsampling"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fv_is_refused_with_a_clear_error() {
        let mut a = Arch::preset("fv").unwrap();
        (a.layers, a.channels, a.unet_channels) = (2, 4, 2);
        let e = match GpuNet::new(Weights::random(&a, 0).unwrap(), None) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("GPU inference accepted an FV network"),
        };
        assert!(e.contains("fv") && e.contains("CPU"), "{e}");
    }
}
