//! The GPU context (one per process): adapter choice, limits, pipelines built once, a buffer
//! pool, and [`Frame`], which records a frame's uploads, dispatches and readbacks into one
//! command buffer and one submission.

use super::GpuError;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Storage buffers the kernels bind at most (read-only plus read-write).
const MAX_BINDINGS: u32 = 8;
/// 2-D kernels run 16 x 16 workgroups (256 invocations: 8 warps or 4 wavefronts).
pub(crate) const WG: u32 = 16;
/// 1-D reductions run 256 invocations per workgroup.
pub(crate) const WG1: u32 = 256;

/// One compute kernel: shader file, entry point, and its bindings (a uniform at 0, then the
/// read-only storage buffers, then the read-write ones).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) enum Kernel {
    GatherPrep,
    MaxH,
    MaxV,
    Gather,
    LinearBlend,
    Convolve,
    ShiftAdd,
    BlurH,
    BlurV,
    PsnrSum,
    SsimPrep,
    SsimSum,
    LfPrefilter,
    LfSplatDepth,
    LfSplatIndex,
    LfAccumulate,
    LfFinish,
    OptResidual,
    OptStep,
    OptSqSum,
    ViewResolve,
    FillRows,
    FillCols,
    Lenslet,
    FovMask,
    FovCells,
    FovInterp,
    SpPad,
    SpSlices,
    SpPack,
    SpFftPass,
    SpRowsToHalf,
    SpHalfToRows,
    SpRowsToReal,
    SpApply,
    SpGradStep,
    SpAdmmStep,
    SpAdmmUpdate,
    PyAggregate,
    PySpread,
    PyCompose,
    FvDownsample,
    FvBlend,
}

const GATHER_WGSL: &str = include_str!("../../shaders/gather.wgsl");
const MULTIFOCAL_WGSL: &str = include_str!("../../shaders/multifocal.wgsl");
const RETINA_WGSL: &str = include_str!("../../shaders/retina.wgsl");
const BLUR_WGSL: &str = include_str!("../../shaders/blur.wgsl");
const METRICS_WGSL: &str = include_str!("../../shaders/metrics.wgsl");
const LIGHTFIELD_WGSL: &str = include_str!("../../shaders/lightfield.wgsl");
const OPTIMIZE_WGSL: &str = include_str!("../../shaders/optimize.wgsl");
const VIEWS_WGSL: &str = include_str!("../../shaders/views.wgsl");
const LENSLET_WGSL: &str = include_str!("../../shaders/lenslet.wgsl");
const BILINEAR_WGSL: &str = include_str!("../../shaders/bilinear.wgsl");
const FOVEATE_WGSL: &str = include_str!("../../shaders/foveate.wgsl");
const SPECTRAL_WGSL: &str = include_str!("../../shaders/spectral.wgsl");
const PYRAMID_WGSL: &str = include_str!("../../shaders/pyramid.wgsl");
const FOVEATED_WGSL: &str = include_str!("../../shaders/foveated.wgsl");

impl Kernel {
    pub(crate) const ALL: [Kernel; 43] = [
        Kernel::GatherPrep,
        Kernel::MaxH,
        Kernel::MaxV,
        Kernel::Gather,
        Kernel::LinearBlend,
        Kernel::Convolve,
        Kernel::ShiftAdd,
        Kernel::BlurH,
        Kernel::BlurV,
        Kernel::PsnrSum,
        Kernel::SsimPrep,
        Kernel::SsimSum,
        Kernel::LfPrefilter,
        Kernel::LfSplatDepth,
        Kernel::LfSplatIndex,
        Kernel::LfAccumulate,
        Kernel::LfFinish,
        Kernel::OptResidual,
        Kernel::OptStep,
        Kernel::OptSqSum,
        Kernel::ViewResolve,
        Kernel::FillRows,
        Kernel::FillCols,
        Kernel::Lenslet,
        Kernel::FovMask,
        Kernel::FovCells,
        Kernel::FovInterp,
        Kernel::SpPad,
        Kernel::SpSlices,
        Kernel::SpPack,
        Kernel::SpFftPass,
        Kernel::SpRowsToHalf,
        Kernel::SpHalfToRows,
        Kernel::SpRowsToReal,
        Kernel::SpApply,
        Kernel::SpGradStep,
        Kernel::SpAdmmStep,
        Kernel::SpAdmmUpdate,
        Kernel::PyAggregate,
        Kernel::PySpread,
        Kernel::PyCompose,
        Kernel::FvDownsample,
        Kernel::FvBlend,
    ];

    /// (shader source, entry point, read-only buffers, read-write buffers)
    pub(crate) fn spec(self) -> (&'static str, &'static str, u32, u32) {
        use Kernel::*;
        match self {
            GatherPrep => (GATHER_WGSL, "prep", 2, 2),
            MaxH => (GATHER_WGSL, "max_h", 1, 1),
            MaxV => (GATHER_WGSL, "max_v", 1, 1),
            Gather => (GATHER_WGSL, "gather", 4, 1),
            LinearBlend => (MULTIFOCAL_WGSL, "linear_blend", 3, 1),
            Convolve => (RETINA_WGSL, "convolve", 3, 1),
            ShiftAdd => (RETINA_WGSL, "shift_add", 2, 1),
            BlurH => (BLUR_WGSL, "blur_h", 2, 1),
            BlurV => (BLUR_WGSL, "blur_v", 2, 1),
            PsnrSum => (METRICS_WGSL, "psnr_sum", 3, 1),
            SsimPrep => (METRICS_WGSL, "ssim_prep", 2, 1),
            SsimSum => (METRICS_WGSL, "ssim_sum", 2, 1),
            LfPrefilter => (LIGHTFIELD_WGSL, "prefilter", 2, 1),
            LfSplatDepth => (LIGHTFIELD_WGSL, "splat_depth", 2, 1),
            LfSplatIndex => (LIGHTFIELD_WGSL, "splat_index", 3, 1),
            LfAccumulate => (LIGHTFIELD_WGSL, "accumulate", 4, 1),
            LfFinish => (LIGHTFIELD_WGSL, "finish", 2, 1),
            OptResidual => (OPTIMIZE_WGSL, "residual", 4, 1),
            OptStep => (OPTIMIZE_WGSL, "step", 3, 2),
            OptSqSum => (OPTIMIZE_WGSL, "sq_sum", 1, 1),
            ViewResolve => (VIEWS_WGSL, "resolve", 5, 1),
            FillRows => (VIEWS_WGSL, "fill_rows", 1, 1),
            FillCols => (VIEWS_WGSL, "fill_cols", 1, 1),
            Lenslet => (LENSLET_WGSL, "elemental", 3, 1),
            FovMask => (FOVEATE_WGSL, "mask", 2, 1),
            FovCells => (FOVEATE_WGSL, "cells", 1, 2),
            FovInterp => (FOVEATE_WGSL, "interp", 4, 1),
            SpPad => (SPECTRAL_WGSL, "pad", 1, 1),
            SpSlices => (SPECTRAL_WGSL, "slices", 3, 1),
            SpPack => (SPECTRAL_WGSL, "pack", 1, 1),
            SpFftPass => (SPECTRAL_WGSL, "fft_pass", 2, 1),
            SpRowsToHalf => (SPECTRAL_WGSL, "rows_to_half", 1, 1),
            SpHalfToRows => (SPECTRAL_WGSL, "half_to_rows", 1, 1),
            SpRowsToReal => (SPECTRAL_WGSL, "rows_to_real", 1, 2),
            SpApply => (SPECTRAL_WGSL, "apply", 2, 1),
            SpGradStep => (SPECTRAL_WGSL, "grad_step", 2, 2),
            SpAdmmStep => (SPECTRAL_WGSL, "admm_step", 3, 2),
            SpAdmmUpdate => (SPECTRAL_WGSL, "admm_update", 1, 3),
            PyAggregate => (PYRAMID_WGSL, "aggregate", 2, 1),
            PySpread => (PYRAMID_WGSL, "spread", 1, 1),
            PyCompose => (PYRAMID_WGSL, "compose", 4, 1),
            FvDownsample => (FOVEATED_WGSL, "downsample", 2, 2),
            FvBlend => (FOVEATED_WGSL, "blend", 2, 1),
        }
    }
}

/// What a frame cost: the two numbers that decide speed on a real GPU (dispatches and bytes
/// moved between host and device), and GPU time per pass where timestamps are supported.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameStats {
    pub submissions: u32,
    pub dispatches: u32,
    pub bytes_uploaded: u64,
    pub bytes_read_back: u64,
    /// Total GPU time of the timed passes, nanoseconds; `None` without timestamp queries.
    pub gpu_ns: Option<f64>,
    /// GPU time per pass label, nanoseconds (summed over passes with the same label).
    pub passes: Vec<(&'static str, f64)>,
}

impl FrameStats {
    pub(crate) fn add(&mut self, o: &FrameStats) {
        self.submissions += o.submissions;
        self.dispatches += o.dispatches;
        self.bytes_uploaded += o.bytes_uploaded;
        self.bytes_read_back += o.bytes_read_back;
        self.gpu_ns = match (self.gpu_ns, o.gpu_ns) {
            (Some(a), Some(b)) => Some(a + b),
            (a, b) => a.or(b),
        };
        for &(l, t) in &o.passes {
            match self.passes.iter_mut().find(|p| p.0 == l) {
                Some(p) => p.1 += t,
                None => self.passes.push((l, t)),
            }
        }
    }
}

/// The adapter a context runs on.
#[derive(Debug, Clone)]
pub struct AdapterSummary {
    pub name: String,
    pub backend: String,
    pub software: bool,
}

type PoolKey = (u64, u32);
type ShaderPipelines =
    HashMap<(usize, &'static str), (wgpu::ComputePipeline, wgpu::BindGroupLayout)>;

/// A compute kernel in another crate's WGSL (the network's, for one): the bindings follow
/// the same convention as this crate's kernels, a uniform at binding 0, then `read_only`
/// storage buffers, then `read_write` ones.
#[derive(Debug, Clone, Copy)]
pub struct ShaderKernel {
    pub source: &'static str,
    pub entry: &'static str,
    pub read_only: u32,
    pub read_write: u32,
}

/// A pooled buffer: returned to its pool when the last handle drops.
pub struct Buf {
    pub(crate) buffer: wgpu::Buffer,
    key: PoolKey,
    pool: Arc<Mutex<HashMap<PoolKey, Vec<wgpu::Buffer>>>>,
}

impl Drop for Buf {
    fn drop(&mut self) {
        if let Ok(mut p) = self.pool.lock() {
            let list = p.entry(self.key).or_default();
            // Keep a few per size; more would only hold memory.
            if list.len() < 8 {
                list.push(self.buffer.clone());
            }
        }
    }
}

/// A GPU buffer handle (pooled; reused once every handle is dropped).
pub type BufRef = Arc<Buf>;

pub struct GpuContext {
    /// Kept so that a window on this machine can draw with this device (a surface made from
    /// the same instance and checked against the same adapter).
    instance: wgpu::Instance,
    raw_adapter: wgpu::Adapter,
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) adapter: AdapterSummary,
    pub(crate) limits: wgpu::Limits,
    timestamps: bool,
    timestamp_period: f32,
    pipelines: HashMap<Kernel, (wgpu::ComputePipeline, wgpu::BindGroupLayout)>,
    pool: Arc<Mutex<HashMap<PoolKey, Vec<wgpu::Buffer>>>>,
    /// Pipelines of other crates' shaders, by (source address, entry point).
    shader_pipelines: Mutex<ShaderPipelines>,
    lost: Arc<AtomicBool>,
    errors: Arc<Mutex<Vec<String>>>,
}

/// Names of the adapters this machine offers (Vulkan, Metal, DX12), with whether each is a
/// software rasteriser.
pub fn list_adapters() -> Vec<AdapterSummary> {
    let instance = instance();
    pollster::block_on(instance.enumerate_adapters(backends()))
        .iter()
        .map(|a| summary(&a.get_info()))
        .collect()
}

/// Whether a hardware (non-software) adapter exists: decides the CLI's default backend.
pub fn hardware_adapter_exists() -> bool {
    list_adapters().iter().any(|a| !a.software)
}

fn backends() -> wgpu::Backends {
    wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12
}

fn instance() -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = backends();
    wgpu::Instance::new(desc)
}

fn summary(info: &wgpu::AdapterInfo) -> AdapterSummary {
    AdapterSummary {
        name: info.name.clone(),
        backend: format!("{:?}", info.backend),
        software: info.device_type == wgpu::DeviceType::Cpu,
    }
}

/// The process's context, created on first use with the adapter named then.
static SHARED: Mutex<Option<Arc<GpuContext>>> = Mutex::new(None);

impl GpuContext {
    /// The process-wide context. `adapter` picks an adapter whose name contains it
    /// (case-insensitive); without it the first hardware adapter, else a software one (said
    /// on stderr). Once created, later calls get the same context whatever they ask.
    pub fn shared(adapter: Option<&str>) -> Result<Arc<GpuContext>, GpuError> {
        let mut slot = SHARED.lock().map_err(|_| GpuError::Poisoned)?;
        if let Some(c) = slot.as_ref() {
            if let Some(want) = adapter {
                if !c.adapter.name.to_lowercase().contains(&want.to_lowercase()) {
                    return Err(GpuError::AdapterAlreadyChosen {
                        have: c.adapter.name.clone(),
                        want: want.to_string(),
                    });
                }
            }
            return Ok(c.clone());
        }
        let c = Arc::new(GpuContext::new(adapter)?);
        *slot = Some(c.clone());
        Ok(c)
    }

    fn new(want: Option<&str>) -> Result<GpuContext, GpuError> {
        let instance = instance();
        let adapters = pollster::block_on(instance.enumerate_adapters(backends()));
        let names: Vec<String> = adapters.iter().map(|a| a.get_info().name).collect();
        let adapter = match want {
            Some(w) => adapters
                .into_iter()
                .find(|a| a.get_info().name.to_lowercase().contains(&w.to_lowercase()))
                .ok_or_else(|| GpuError::AdapterNotFound {
                    want: w.to_string(),
                    available: names.join(", "),
                })?,
            None => {
                let (hw, sw): (Vec<_>, Vec<_>) = adapters
                    .into_iter()
                    .partition(|a| a.get_info().device_type != wgpu::DeviceType::Cpu);
                match (hw.into_iter().next(), sw.into_iter().next()) {
                    (Some(a), _) => a,
                    (None, Some(a)) => {
                        eprintln!(
                            "dioptra: no hardware GPU adapter; using the software adapter {} (correct but slow)",
                            a.get_info().name
                        );
                        a
                    }
                    (None, None) => return Err(GpuError::NoAdapter),
                }
            }
        };
        let info = adapter.get_info();
        let have = adapter.limits();
        check_limits(&have)?;
        let timestamps = adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let required_features = if timestamps {
            wgpu::Features::TIMESTAMP_QUERY
        } else {
            wgpu::Features::empty()
        };
        // Ask for what the adapter offers: large images need large storage bindings.
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("dioptra-render"),
            required_features,
            required_limits: have.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let lost = Arc::new(AtomicBool::new(false));
        let l2 = lost.clone();
        device.set_device_lost_callback(move |_, _| l2.store(true, Ordering::SeqCst));
        let errors = Arc::new(Mutex::new(Vec::new()));
        let e2 = errors.clone();
        // wgpu's default handler panics; record instead and fail the frame.
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = e2.lock() {
                v.push(e.to_string());
            }
        }));
        let timestamp_period = queue.get_timestamp_period();
        let mut modules: HashMap<&'static str, wgpu::ShaderModule> = HashMap::new();
        let mut layouts: HashMap<(u32, u32), wgpu::BindGroupLayout> = HashMap::new();
        let mut pipelines = HashMap::new();
        for k in Kernel::ALL {
            let (src, entry, ro, rw) = k.spec();
            let module = modules
                .entry(src)
                .or_insert_with(|| {
                    device.create_shader_module(wgpu::ShaderModuleDescriptor {
                        label: None,
                        source: wgpu::ShaderSource::Wgsl(with_shared(src).into()),
                    })
                })
                .clone();
            let bgl = layouts
                .entry((ro, rw))
                .or_insert_with(|| bind_group_layout(&device, ro, rw))
                .clone();
            let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: None,
                bind_group_layouts: &[Some(&bgl)],
                immediate_size: 0,
            });
            let p = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            });
            pipelines.insert(k, (p, bgl));
        }
        let ctx = GpuContext {
            instance,
            raw_adapter: adapter,
            device,
            queue,
            adapter: summary(&info),
            limits: have,
            timestamps,
            timestamp_period,
            pipelines,
            pool: Arc::new(Mutex::new(HashMap::new())),
            shader_pipelines: Mutex::new(HashMap::new()),
            lost,
            errors,
        };
        ctx.take_errors()?;
        Ok(ctx)
    }

    pub fn adapter(&self) -> &AdapterSummary {
        &self.adapter
    }

    /// The wgpu instance, adapter, device and queue, for drawing on the same device (a
    /// window presenting the images kept here).
    pub fn instance(&self) -> &wgpu::Instance {
        &self.instance
    }
    pub fn wgpu_adapter(&self) -> &wgpu::Adapter {
        &self.raw_adapter
    }
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// A storage buffer holding `data` that lives as long as its handle, outside any frame
    /// (weights uploaded once). The copy is queued and lands before the next submission.
    pub fn upload_resident(&self, what: &str, data: &[f32]) -> Result<BufRef, GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        self.check_size(what, bytes.len() as u64)?;
        let b = self.acquire(bytes.len() as u64, Frame::STORAGE);
        if !bytes.is_empty() {
            self.queue.write_buffer(&b.buffer, 0, bytes);
        }
        Ok(b)
    }

    /// The pipeline of `k`, built on first use (its shader module compiled then).
    fn shader_pipeline(
        &self,
        k: &ShaderKernel,
    ) -> Result<(wgpu::ComputePipeline, wgpu::BindGroupLayout), GpuError> {
        if k.read_only + k.read_write > MAX_BINDINGS {
            return Err(GpuError::Validation(format!(
                "{} binds {} storage buffers; at most {MAX_BINDINGS}",
                k.entry,
                k.read_only + k.read_write
            )));
        }
        let key = (k.source.as_ptr() as usize, k.entry);
        let mut map = self
            .shader_pipelines
            .lock()
            .map_err(|_| GpuError::Poisoned)?;
        if let Some(p) = map.get(&key) {
            return Ok(p.clone());
        }
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(k.entry),
                source: wgpu::ShaderSource::Wgsl(k.source.into()),
            });
        let bgl = bind_group_layout(&self.device, k.read_only, k.read_write);
        let pl = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: None,
                bind_group_layouts: &[Some(&bgl)],
                immediate_size: 0,
            });
        let p = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(k.entry),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(k.entry),
                compilation_options: Default::default(),
                cache: None,
            });
        self.take_errors()?;
        map.insert(key, (p.clone(), bgl.clone()));
        Ok((p, bgl))
    }

    fn take_errors(&self) -> Result<(), GpuError> {
        if self.lost.load(Ordering::SeqCst) {
            return Err(GpuError::DeviceLost);
        }
        let mut e = self.errors.lock().map_err(|_| GpuError::Poisoned)?;
        if e.is_empty() {
            Ok(())
        } else {
            let msg = e.join("; ");
            e.clear();
            Err(GpuError::Validation(msg))
        }
    }

    /// Checks that one buffer of `bytes` fits the device's storage-binding limit.
    pub(crate) fn check_size(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let max = self.max_binding();
        if bytes > max {
            return Err(GpuError::TooLarge {
                what: what.to_string(),
                bytes,
                max,
            });
        }
        Ok(())
    }

    /// The largest buffer one binding may hold on this device.
    pub(crate) fn max_binding(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    fn acquire(&self, bytes: u64, usage: wgpu::BufferUsages) -> BufRef {
        // Round up so nearby sizes share buffers: powers of two up to 1 MiB, then 1 MiB steps.
        let size = bytes.max(16);
        let size = if size <= 1 << 20 {
            size.next_power_of_two()
        } else {
            size.div_ceil(1 << 20) << 20
        };
        let key = (size, usage.bits());
        let reused = self
            .pool
            .lock()
            .ok()
            .and_then(|mut p| p.get_mut(&key).and_then(|v| v.pop()));
        let buffer = reused.unwrap_or_else(|| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: None,
                size,
                usage,
                mapped_at_creation: false,
            })
        });
        Arc::new(Buf {
            buffer,
            key,
            pool: self.pool.clone(),
        })
    }
}

/// The constants the CPU twins and the shaders share, as WGSL, from their one definition in
/// the CPU code: the shader files use them and never define them.
pub(crate) fn shared_wgsl() -> String {
    use crate::foveate::FOV_CELL;
    use crate::lightfield::{LEVEL_SIGMA, PREFILTER};
    use crate::multifocal::MAX_PLANES;
    let sigma: Vec<String> = LEVEL_SIGMA.iter().map(|s| format!("{s:?}")).collect();
    format!(
        "const PREFILTER: f32 = {PREFILTER:?};\nconst LEVEL_SIGMA = array<f32, {}>({});\nconst FOV_CELL: u32 = {FOV_CELL}u;\nconst WG1: u32 = {WG1}u;\nconst MAX_PLANES: u32 = {MAX_PLANES}u;\n{}",
        LEVEL_SIGMA.len(),
        sigma.join(", "),
        crate::pyramid::shared_wgsl() + &crate::foveated::shared_wgsl() + BILINEAR_WGSL
    )
}

/// A shader file of this crate with the shared constants before it.
pub(crate) fn with_shared(src: &str) -> String {
    format!("{}\n{src}", shared_wgsl())
}

fn check_limits(have: &wgpu::Limits) -> Result<(), GpuError> {
    let need = [
        (
            "max_compute_invocations_per_workgroup",
            have.max_compute_invocations_per_workgroup,
            WG * WG,
        ),
        (
            "max_compute_workgroup_size_x",
            have.max_compute_workgroup_size_x,
            WG1,
        ),
        (
            "max_compute_workgroup_size_y",
            have.max_compute_workgroup_size_y,
            WG,
        ),
        (
            "max_storage_buffers_per_shader_stage",
            have.max_storage_buffers_per_shader_stage,
            MAX_BINDINGS,
        ),
        (
            "max_compute_workgroup_storage_size",
            have.max_compute_workgroup_storage_size,
            4 * WG1,
        ),
    ];
    for (what, have, need) in need {
        if have < need {
            return Err(GpuError::Limit { what, have, need });
        }
    }
    Ok(())
}

fn bind_group_layout(device: &wgpu::Device, ro: u32, rw: u32) -> wgpu::BindGroupLayout {
    let mut entries = vec![wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }];
    for i in 0..ro + rw {
        entries.push(wgpu::BindGroupLayoutEntry {
            binding: 1 + i,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: i < ro },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        });
    }
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: None,
        entries: &entries,
    })
}

/// A readback slot: the bytes arrive when the frame finishes.
#[derive(Debug, Clone, Copy)]
pub struct Readback(usize);

/// One frame: uploads (queued writes), dispatches and copies recorded into one command
/// buffer, submitted once, then every readback mapped together.
pub struct Frame<'c> {
    ctx: &'c GpuContext,
    encoder: wgpu::CommandEncoder,
    held: Vec<BufRef>,
    reads: Vec<(BufRef, u64)>,
    labels: Vec<&'static str>,
    queries: Option<wgpu::QuerySet>,
    stats: FrameStats,
}

/// Timestamp queries per frame (two per pass); passes beyond this go untimed.
const MAX_QUERIES: u32 = 512;

impl<'c> Frame<'c> {
    pub fn new(ctx: &'c GpuContext) -> Result<Frame<'c>, GpuError> {
        ctx.take_errors()?;
        let queries = ctx.timestamps.then(|| {
            ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: None,
                ty: wgpu::QueryType::Timestamp,
                count: MAX_QUERIES,
            })
        });
        Ok(Frame {
            ctx,
            encoder: ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None }),
            held: Vec::new(),
            reads: Vec::new(),
            labels: Vec::new(),
            queries,
            stats: FrameStats::default(),
        })
    }

    const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
        .union(wgpu::BufferUsages::COPY_DST)
        .union(wgpu::BufferUsages::COPY_SRC);

    /// A storage buffer holding `data`.
    pub fn upload<T: bytemuck::Pod>(&mut self, what: &str, data: &[T]) -> Result<BufRef, GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        self.ctx.check_size(what, bytes.len() as u64)?;
        let b = self.ctx.acquire(bytes.len() as u64, Self::STORAGE);
        if !bytes.is_empty() {
            self.ctx.queue.write_buffer(&b.buffer, 0, bytes);
        }
        self.stats.bytes_uploaded += bytes.len() as u64;
        self.held.push(b.clone());
        Ok(b)
    }

    /// A storage buffer of `bytes` cleared to zero on the GPU (no transfer).
    pub fn zeroed(&mut self, what: &str, bytes: u64) -> Result<BufRef, GpuError> {
        let b = self.scratch(what, bytes)?;
        self.encoder.clear_buffer(&b.buffer, 0, None);
        Ok(b)
    }

    /// A storage buffer of `bytes` with undefined contents (every element will be written).
    pub fn scratch(&mut self, what: &str, bytes: u64) -> Result<BufRef, GpuError> {
        self.ctx.check_size(what, bytes)?;
        let b = self.ctx.acquire(bytes, Self::STORAGE);
        self.held.push(b.clone());
        Ok(b)
    }

    /// Copies `bytes` from `src` at `src_off` to `dst` at `dst_off`, on the GPU.
    pub fn copy(&mut self, src: &BufRef, src_off: u64, dst: &BufRef, dst_off: u64, bytes: u64) {
        self.encoder
            .copy_buffer_to_buffer(&src.buffer, src_off, &dst.buffer, dst_off, bytes);
    }

    /// Clears `b` to zero on the GPU.
    pub fn clear(&mut self, b: &BufRef) {
        self.encoder.clear_buffer(&b.buffer, 0, None);
    }

    /// Records `kernel` over `groups` workgroups with uniform `params` and buffers `bufs`
    /// (read-only ones first, as the kernel's spec lists them).
    pub(crate) fn dispatch<P: bytemuck::Pod>(
        &mut self,
        kernel: Kernel,
        params: &P,
        bufs: &[&BufRef],
        groups: [u32; 3],
    ) -> Result<(), GpuError> {
        let (pipeline, bgl) = self
            .ctx
            .pipelines
            .get(&kernel)
            .cloned()
            .ok_or(GpuError::Validation(format!("no pipeline for {kernel:?}")))?;
        let (_, entry, ro, rw) = kernel.spec();
        self.record(
            &pipeline,
            &bgl,
            entry,
            ro + rw,
            bytemuck::bytes_of(params),
            bufs,
            groups,
        )
    }

    /// Records a kernel of another crate's shader (see [`ShaderKernel`]): its pipeline is
    /// built on first use and kept in the context.
    pub fn dispatch_shader<P: bytemuck::Pod>(
        &mut self,
        kernel: &ShaderKernel,
        params: &P,
        bufs: &[&BufRef],
        groups: [u32; 3],
    ) -> Result<(), GpuError> {
        let (pipeline, bgl) = self.ctx.shader_pipeline(kernel)?;
        self.record(
            &pipeline,
            &bgl,
            kernel.entry,
            kernel.read_only + kernel.read_write,
            bytemuck::bytes_of(params),
            bufs,
            groups,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn record(
        &mut self,
        pipeline: &wgpu::ComputePipeline,
        bgl: &wgpu::BindGroupLayout,
        entry: &'static str,
        nbufs: u32,
        pbytes: &[u8],
        bufs: &[&BufRef],
        groups: [u32; 3],
    ) -> Result<(), GpuError> {
        if bufs.len() != nbufs as usize {
            return Err(GpuError::Validation(format!(
                "{entry} takes {} buffers, given {}",
                nbufs,
                bufs.len()
            )));
        }
        let max = self.ctx.limits.max_compute_workgroups_per_dimension;
        if groups.iter().any(|&g| g > max) {
            return Err(GpuError::TooLarge {
                what: format!("{entry} dispatch of {groups:?} workgroups"),
                bytes: groups.iter().copied().max().unwrap_or(0) as u64,
                max: max as u64,
            });
        }
        if groups.contains(&0) {
            return Ok(());
        }
        let u = self.ctx.acquire(
            pbytes.len() as u64,
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        );
        self.ctx.queue.write_buffer(&u.buffer, 0, pbytes);
        self.stats.bytes_uploaded += pbytes.len() as u64;
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: u.buffer.as_entire_binding(),
        }];
        for (i, b) in bufs.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: 1 + i as u32,
                resource: b.buffer.as_entire_binding(),
            });
        }
        let bg = self
            .ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: bgl,
                entries: &entries,
            });
        self.held.push(u);
        let q = 2 * self.labels.len() as u32;
        let timestamp_writes = match &self.queries {
            Some(qs) if q + 1 < MAX_QUERIES => {
                self.labels.push(entry);
                Some(wgpu::ComputePassTimestampWrites {
                    query_set: qs,
                    beginning_of_pass_write_index: Some(q),
                    end_of_pass_write_index: Some(q + 1),
                })
            }
            _ => None,
        };
        // One pass per dispatch so each can be timed; a real GPU needs the barrier anyway,
        // since every dispatch here reads what the one before wrote.
        let mut pass = self
            .encoder
            .begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(entry),
                timestamp_writes,
            });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
        drop(pass);
        self.stats.dispatches += 1;
        Ok(())
    }

    /// Copies the first `bytes` of `b` back to the host when the frame finishes.
    pub fn read(&mut self, b: &BufRef, bytes: u64) -> Readback {
        self.read_range(b, 0, bytes)
    }

    /// Copies `bytes` of `b` from `offset` (a multiple of 4) back to the host when the frame
    /// finishes.
    pub fn read_range(&mut self, b: &BufRef, offset: u64, bytes: u64) -> Readback {
        let bytes = bytes.div_ceil(4) * 4;
        let staging = self.ctx.acquire(
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        if bytes > 0 {
            self.encoder
                .copy_buffer_to_buffer(&b.buffer, offset, &staging.buffer, 0, bytes);
        }
        self.reads.push((staging, bytes));
        self.stats.bytes_read_back += bytes;
        Readback(self.reads.len() - 1)
    }

    /// Submits the frame, waits for it, and returns every readback and the frame's stats.
    pub fn finish(mut self) -> Result<(Readbacks, FrameStats), GpuError> {
        let n_ts = 2 * self.labels.len() as u64;
        let ts = match (&self.queries, n_ts) {
            (Some(qs), n) if n > 0 => {
                let resolve = self.ctx.acquire(
                    n * 8,
                    wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                );
                self.encoder
                    .resolve_query_set(qs, 0..n as u32, &resolve.buffer, 0);
                let staging = self.ctx.acquire(
                    n * 8,
                    wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                );
                self.encoder
                    .copy_buffer_to_buffer(&resolve.buffer, 0, &staging.buffer, 0, n * 8);
                self.held.push(resolve);
                Some(staging)
            }
            _ => None,
        };
        let cmd = self.encoder.finish();
        let submitted = self.ctx.queue.submit([cmd]);
        self.stats.submissions += 1;
        let mut all: Vec<(&BufRef, u64)> = self.reads.iter().map(|(b, n)| (b, *n)).collect();
        if let Some(t) = &ts {
            all.push((t, n_ts * 8));
        }
        let failed = Arc::new(AtomicBool::new(false));
        for (b, n) in &all {
            if *n == 0 {
                continue;
            }
            let f = failed.clone();
            b.buffer.map_async(wgpu::MapMode::Read, 0..*n, move |r| {
                if r.is_err() {
                    f.store(true, Ordering::SeqCst);
                }
            });
        }
        // This frame's work only: a window drawing on the same device submits too.
        self.ctx
            .device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submitted),
                timeout: None,
            })
            .map_err(|e| match e {
                wgpu::PollError::Timeout => GpuError::Validation("GPU wait timed out".into()),
                _ => GpuError::DeviceLost,
            })?;
        self.ctx.take_errors()?;
        if failed.load(Ordering::SeqCst) {
            return Err(GpuError::Validation(
                "mapping a readback buffer failed".into(),
            ));
        }
        let mut out = Vec::with_capacity(self.reads.len());
        for (b, n) in &self.reads {
            if *n == 0 {
                out.push(Vec::new());
                continue;
            }
            let v = b
                .buffer
                .get_mapped_range(0..*n)
                .map_err(|e| GpuError::Validation(e.to_string()))?
                .to_vec();
            b.buffer.unmap();
            out.push(v);
        }
        if let Some(t) = ts {
            let raw: Vec<u64> = {
                let v = t
                    .buffer
                    .get_mapped_range(0..n_ts * 8)
                    .map_err(|e| GpuError::Validation(e.to_string()))?;
                bytemuck::pod_collect_to_vec::<u8, u64>(&v)
            };
            t.buffer.unmap();
            let period = self.ctx.timestamp_period as f64;
            let mut total = 0.0;
            for (i, &l) in self.labels.iter().enumerate() {
                let dt = raw[2 * i + 1].saturating_sub(raw[2 * i]) as f64 * period;
                total += dt;
                match self.stats.passes.iter_mut().find(|p| p.0 == l) {
                    Some(p) => p.1 += dt,
                    None => self.stats.passes.push((l, dt)),
                }
            }
            self.stats.gpu_ns = Some(total);
        }
        Ok((Readbacks(out), self.stats))
    }
}

/// The bytes of a finished frame's readbacks.
pub struct Readbacks(Vec<Vec<u8>>);

impl Readbacks {
    pub fn u32s(&self, r: Readback) -> Vec<u32> {
        self.0
            .get(r.0)
            .map(|v| bytemuck::pod_collect_to_vec::<u8, u32>(v))
            .unwrap_or_default()
    }

    pub fn f32s(&self, r: Readback) -> Vec<f32> {
        self.0
            .get(r.0)
            .map(|v| bytemuck::pod_collect_to_vec::<u8, f32>(v))
            .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shared_constants_are_defined_once() {
        // The shaders get PREFILTER, LEVEL_SIGMA and FOV_CELL from the CPU code: a file that
        // defined its own copy would not compile with the prelude (a redefinition), and one
        // that used a literal instead would drift; both are refused here.
        let prelude = shared_wgsl();
        assert!(
            prelude.contains("const PREFILTER: f32 = 0.35;"),
            "{prelude}"
        );
        assert!(prelude.contains("array<f32, 7>(0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)"));
        assert!(prelude.contains("const FOV_CELL: u32 = 8u;"));
        assert!(prelude.contains("const WG1: u32 = 256u;"));
        assert!(prelude.contains("const MAX_PLANES: u32 = 16u;"));
        for k in Kernel::ALL {
            let (src, entry, _, _) = k.spec();
            for name in [
                "PREFILTER",
                "LEVEL_SIGMA",
                "FOV_CELL",
                "WG1",
                "MAX_PLANES",
                "EXACT_RADIUS",
                "BANDS_PER_OCTAVE",
                "SPREAD_REACH",
                "GRID",
                "BLEND",
            ] {
                assert!(
                    !src.contains(&format!("const {name}")),
                    "{entry}'s shader defines {name} itself"
                );
            }
        }
        assert!(LIGHTFIELD_WGSL.contains("PREFILTER * coc"));
        assert!(FOVEATE_WGSL.contains("@workgroup_size(FOV_CELL, FOV_CELL)"));
        // The 1-D workgroups and their shared arrays are WG1 wide, as the host dispatches them.
        for src in [SPECTRAL_WGSL, OPTIMIZE_WGSL, METRICS_WGSL] {
            assert!(!src.contains("256"), "a literal workgroup width");
            assert!(src.contains("@workgroup_size(WG1)"));
        }
        assert!(SPECTRAL_WGSL.contains("array<vec2<f32>, MAX_PLANES>"));
        // A butterfly for every radix the host's FFT plans use.
        for r in std::iter::once(4).chain(crate::fft2::FFT_PRIMES) {
            assert!(
                SPECTRAL_WGSL.contains(&format!("case {r}u: {{")),
                "radix {r}"
            );
        }
    }
}
