//! gs-wgpu: gs-core's GPU backend, as wgpu compute kernels (WGSL, `shaders/`): the
//! rasterizer's forward and backward passes ([`GpuRasterizer`]), the shadow pass
//! ([`GpuSunVisibility`]), the MLPs' forward and backward ([`GpuMlp`]) and the networks' input
//! assembly and scatters ([`network_io`]), checked against the CPU path (`tests/gpu_*.rs`).
//! The Sun-aware trainer trains device-resident on it in every configuration
//! ([`resident_sunaware::SunAwareResident`]: Gaussians, network weights, every Adam state
//! and the statistics on the device, one submission per step). [`WgpuEngine`] is the
//! whole backend behind gs-core's engine trait ([`gs_core::engine::Engine`]); the
//! binaries open it with [`open_engine`] (`DeviceEngines::wgpu`). [`GpuAdam`] runs the
//! resident step's optimiser kernels on their own (the kernel tests against
//! `gs_core::optim`).
//!
//! [`GpuContext::new`] opens a Vulkan adapter (the only backend compiled in, so wgpu can
//! never fall back to OpenGL) and reports its name, backend and whether it has
//! `SHADER_FLOAT32_ATOMIC`. No adapter is an error ([`GpuError::NoAdapter`]), never a
//! silent fallback to the CPU.
//!
//! Invariants:
//! - the CPU rasterizer (`gs_core::raster`) is the reference: same conventions, same
//!   outputs within the tolerances stated in the parity tests;
//! - bad input is a [`GpuError`] before any GPU work; validation errors raised by wgpu
//!   while building pipelines are caught and returned, not panicked on;
//! - every wait on the device is bounded by wgpu's own poll; results are read back only
//!   where the caller needs them (images, gradients, a 4-byte entry count; on the
//!   resident path a 16-byte step report).

pub mod engine;
pub mod loss;
pub mod mlp;
pub mod network_io;
mod packed;
pub mod raster;
pub mod resident_sunaware;
pub mod sun_visibility;

use std::sync::Arc;

pub use engine::{open_engine, WgpuEngine};
pub use loss::GpuLoss;
pub use mlp::{GemmOp, GpuMlp, MlpGradients, MlpTape};
pub use raster::{GpuForward, GpuRasterizer, GpuRenderOutput};
pub use resident_sunaware::GpuAdam;
pub use sun_visibility::{GpuSunVisibility, SunLight};

/// GPU backend error.
#[derive(Clone, Debug, PartialEq)]
pub enum GpuError {
    /// No Vulkan adapter (driver missing, or `WGPU_BACKEND` excludes Vulkan).
    NoAdapter(String),
    /// The adapter refused to open a device.
    Device(String),
    /// A shader or pipeline failed validation (a bug in this module).
    Pipeline(String),
    /// Reading results back from the device failed.
    Readback(String),
    /// Inputs the CPU rasterizer would also reject.
    Raster(gs_core::raster::RasterError),
    /// Sizes beyond the device's buffer limits or the kernels' fixed capacities.
    TooLarge(String),
    /// Bad arguments (lengths, shapes).
    Invalid(String),
}

impl std::fmt::Display for GpuError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            GpuError::NoAdapter(why) => write!(
                f,
                "no Vulkan GPU adapter: {why} (install a Vulkan driver, e.g. Mesa's \
                 software driver: apt-get install mesa-vulkan-drivers libvulkan1)"
            ),
            GpuError::Device(why) => write!(f, "GPU device request failed: {why}"),
            GpuError::Pipeline(why) => write!(f, "GPU pipeline creation failed: {why}"),
            GpuError::Readback(why) => write!(f, "GPU readback failed: {why}"),
            GpuError::Raster(e) => write!(f, "rasterizer input: {e}"),
            GpuError::TooLarge(why) => write!(f, "too large for the GPU backend: {why}"),
            GpuError::Invalid(why) => write!(f, "invalid GPU input: {why}"),
        }
    }
}

impl std::error::Error for GpuError {}

impl From<gs_core::raster::RasterError> for GpuError {
    fn from(e: gs_core::raster::RasterError) -> Self {
        GpuError::Raster(e)
    }
}

/// How the context is opened.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GpuOptions {
    /// Use the compare-and-swap loop on `atomic<u32>` for gradient accumulation even
    /// where the adapter has f32 atomics (to test the fallback path).
    pub force_cas_atomics: bool,
    /// Backward blending with one workgroup reduction per tile and key, then one atomic
    /// add per value (`true`), instead of atomic adds from every pixel (`false`). The
    /// reduction needs about 10 workgroup barriers per key, which software drivers run
    /// slowly; GPUs with many pixels per Gaussian may prefer it.
    pub workgroup_reduction: bool,
    /// Bit-identical backward passes: the per-tile reductions write one record per tile
    /// entry (no atomics) and a second kernel sums each Gaussian's records in tile order.
    /// Implies the workgroup reduction (slow on software drivers); the atomic paths' sums
    /// vary in their last bits from run to run.
    pub deterministic: bool,
}

/// An open device and queue, and what the adapter offers.
#[derive(Clone, Debug)]
pub struct GpuContext {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    adapter_name: String,
    backend: String,
    driver: String,
    has_float32_atomics: bool,
    use_float32_atomics: bool,
    /// Timestamp queries between commands (per-stage device times).
    has_timestamps: bool,
    pub(crate) options: GpuOptions,
    pub(crate) limits: wgpu::Limits,
}

/// The tests' and benchmarks' adapter policy, in one place: a context, or `None` with a
/// printed `SKIPPED` notice when no adapter opens; with `GS_REQUIRE_GPU=1` (CI) a missing
/// adapter panics instead, so a skip can never pass for a test that ran.
pub fn context_or_skip(options: GpuOptions) -> Option<GpuContext> {
    match GpuContext::with_options(options) {
        Ok(ctx) => {
            eprintln!("GPU: {}", ctx.describe());
            Some(ctx)
        }
        Err(e) => {
            gs_core::machine::skip_unless_required(
                "GS_REQUIRE_GPU",
                &format!("no usable GPU: {e}"),
            );
            None
        }
    }
}

impl GpuContext {
    /// Opens the first high-performance Vulkan adapter, with f32 atomics where it has them.
    pub fn new() -> Result<Self, GpuError> {
        Self::with_options(GpuOptions::default())
    }

    pub fn with_options(options: GpuOptions) -> Result<Self, GpuError> {
        // Only Vulkan is compiled in; WGPU_BACKEND may narrow it further (to nothing).
        let backends = wgpu::Backends::from_env().unwrap_or(wgpu::Backends::VULKAN);
        let instance = wgpu::Instance::new(&wgpu::InstanceDescriptor {
            backends,
            ..Default::default()
        });
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
        }))
        .map_err(|e| GpuError::NoAdapter(format!("{e} (backends {backends:?})")))?;
        let info = adapter.get_info();
        let has_float32_atomics = adapter
            .features()
            .contains(wgpu::Features::SHADER_FLOAT32_ATOMIC);
        let use_float32_atomics = has_float32_atomics && !options.force_cas_atomics;
        let mut required_features = if use_float32_atomics {
            wgpu::Features::SHADER_FLOAT32_ATOMIC
        } else {
            wgpu::Features::empty()
        };
        let timestamps =
            wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        let has_timestamps = adapter.features().contains(timestamps);
        if has_timestamps {
            required_features |= timestamps;
        }
        // Ask for what the adapter has: the storage-buffer size limits bound the scenes.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("gs-core"),
            required_features,
            required_limits: limits.clone(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(Self {
            device,
            queue,
            adapter_name: info.name.clone(),
            backend: format!("{:?}", info.backend),
            driver: format!("{} {}", info.driver, info.driver_info),
            has_float32_atomics,
            use_float32_atomics,
            has_timestamps,
            options,
            limits,
        })
    }

    /// Whether per-stage device times can be measured (`StageClock`).
    pub fn has_timestamps(&self) -> bool {
        self.has_timestamps
    }

    pub fn adapter_name(&self) -> &str {
        &self.adapter_name
    }

    /// Graphics API in use ("Vulkan").
    pub fn backend(&self) -> &str {
        &self.backend
    }

    pub fn driver(&self) -> &str {
        &self.driver
    }

    /// Whether the adapter offers `SHADER_FLOAT32_ATOMIC`.
    pub fn has_float32_atomics(&self) -> bool {
        self.has_float32_atomics
    }

    /// Whether gradient accumulation uses f32 atomics (else the compare-and-swap loop).
    pub fn uses_float32_atomics(&self) -> bool {
        self.use_float32_atomics
    }

    /// One line for logs: adapter, backend, driver, atomics.
    pub fn describe(&self) -> String {
        format!(
            "{} ({}, {}), f32 atomics: {}{}",
            self.adapter_name,
            self.backend,
            self.driver.trim(),
            if self.has_float32_atomics {
                "yes"
            } else {
                "no"
            },
            if self.has_float32_atomics && !self.use_float32_atomics {
                " (CAS loop forced)"
            } else {
                ""
            }
        )
    }

    /// Builds a compute pipeline from WGSL source, turning validation errors into
    /// [`GpuError::Pipeline`].
    pub(crate) fn pipeline(
        &self,
        label: &str,
        source: &str,
    ) -> Result<wgpu::ComputePipeline, GpuError> {
        self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: None,
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            });
        match pollster::block_on(self.device.pop_error_scope()) {
            None => Ok(pipeline),
            Some(e) => Err(GpuError::Pipeline(format!("{label}: {e}"))),
        }
    }

    /// A storage buffer holding `data` (at least 16 bytes, so empty inputs still bind).
    pub(crate) fn storage_init(&self, label: &str, data: &[u8]) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        let mut bytes = data.to_vec();
        bytes.resize(bytes.len().max(16).next_multiple_of(4), 0);
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: &bytes,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            })
    }

    /// A zeroed storage buffer of `bytes` (at least 16).
    pub(crate) fn storage(&self, label: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        let size = bytes.max(16).next_multiple_of(4);
        if size > self.limits.max_storage_buffer_binding_size as u64
            || size > self.limits.max_buffer_size
        {
            return Err(GpuError::TooLarge(format!(
                "{label}: {size} bytes exceeds the device's storage buffer limit ({} bytes)",
                self.limits.max_storage_buffer_binding_size
            )));
        }
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }))
    }

    pub(crate) fn uniform_init(&self, label: &str, data: &[u8]) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: data,
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    /// Copies `ranges` (buffer, byte length) to the host in one submission and one wait.
    pub(crate) fn read_back(
        &self,
        mut encoder: wgpu::CommandEncoder,
        ranges: &[(&wgpu::Buffer, u64)],
    ) -> Result<Vec<Vec<u8>>, GpuError> {
        let mut staging = Vec::with_capacity(ranges.len());
        for (src, len) in ranges {
            let size = (*len).max(4).next_multiple_of(4);
            let dst = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            encoder.copy_buffer_to_buffer(src, 0, &dst, 0, size);
            staging.push((dst, *len));
        }
        self.queue.submit(Some(encoder.finish()));
        let (tx, rx) = std::sync::mpsc::channel();
        for (i, (dst, _)) in staging.iter().enumerate() {
            let tx = tx.clone();
            dst.slice(..).map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send((i, r));
            });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::Wait)
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        for (i, r) in rx.iter() {
            r.map_err(|e| GpuError::Readback(format!("buffer {i}: {e}")))?;
        }
        Ok(staging
            .iter()
            .map(|(dst, len)| {
                let bytes = dst.slice(..).get_mapped_range()[..*len as usize].to_vec();
                dst.unmap();
                bytes
            })
            .collect())
    }

    pub(crate) fn encoder(&self, label: &str) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// A bind group with explicit binding numbers (for layouts with gaps).
    pub(crate) fn bind_group_at(
        &self,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: *i,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    pub(crate) fn bind_group(
        &self,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }
}

/// The per-step buffer pool that the recording functions (`encode_*`) take: device
/// buffers reused across steps, keyed by role (splats, keys, tile ranges, images,
/// accumulators, uniforms). Make one with `Scratch::default()` and pass it to every
/// recording of a step. A storage buffer grows, with 50% head room, when a step needs
/// more; kernels read only the extent they are told (uniform counts), and every buffer a
/// kernel does not overwrite entirely is cleared in the command stream, as a fresh zeroed
/// buffer would be. A uniform is written through the queue, so two recordings under the
/// same label before one submission both read the second one's.
#[derive(Debug, Default)]
pub struct Scratch {
    buffers: std::sync::Mutex<std::collections::HashMap<String, wgpu::Buffer>>,
}

impl Scratch {
    fn lock(
        &self,
    ) -> Result<std::sync::MutexGuard<'_, std::collections::HashMap<String, wgpu::Buffer>>, GpuError>
    {
        self.buffers
            .lock()
            .map_err(|_| GpuError::Device("scratch buffer pool lock poisoned".into()))
    }

    /// A storage buffer of at least `bytes` for `label` (contents unspecified).
    pub(crate) fn storage(
        &self,
        ctx: &GpuContext,
        label: &str,
        bytes: u64,
    ) -> Result<wgpu::Buffer, GpuError> {
        let size = bytes.max(16).next_multiple_of(4);
        let mut map = self.lock()?;
        if let Some(b) = map.get(label) {
            if b.size() >= size {
                return Ok(b.clone());
            }
        }
        let limit =
            (ctx.limits.max_storage_buffer_binding_size as u64).min(ctx.limits.max_buffer_size);
        let grown = (size + size / 2).min(limit.max(size)) / 4 * 4;
        let b = ctx.storage(label, grown.max(size))?;
        map.insert(label.to_string(), b.clone());
        Ok(b)
    }

    /// A uniform buffer for `label` holding `data` (written through the queue, so it
    /// takes effect at the next submission).
    pub(crate) fn uniform(
        &self,
        ctx: &GpuContext,
        label: &str,
        data: &[u8],
    ) -> Result<wgpu::Buffer, GpuError> {
        let mut map = self.lock()?;
        let b = match map.get(label) {
            Some(b) if b.size() == data.len() as u64 => b.clone(),
            _ => {
                let b = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: data.len() as u64,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                map.insert(label.to_string(), b.clone());
                b
            }
        };
        ctx.queue.write_buffer(&b, 0, data);
        Ok(b)
    }
}

/// Device times between marks recorded in command encoders (timestamp queries), for the
/// per-stage split of a step: `mark` after each stage, `resolve` into the readback, then
/// `stages_ms` gives each stage's time since the previous mark. Only where the adapter
/// has the timestamp features ([`GpuContext::has_timestamps`]); marking changes no result.
pub(crate) struct StageClock {
    set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
    labels: std::cell::RefCell<Vec<&'static str>>,
    capacity: u32,
    period_ns: f32,
}

impl StageClock {
    /// Room for `capacity` marks; `None` without timestamp support.
    pub(crate) fn new(ctx: &GpuContext, capacity: u32) -> Option<Self> {
        if !ctx.has_timestamps {
            return None;
        }
        let set = ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("stage clock"),
            ty: wgpu::QueryType::Timestamp,
            count: capacity,
        });
        let resolved = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("stage clock resolved"),
            size: capacity as u64 * 8,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Some(Self {
            set,
            resolved,
            labels: std::cell::RefCell::new(Vec::new()),
            capacity,
            period_ns: ctx.queue.get_timestamp_period(),
        })
    }

    /// Starts a new series of marks.
    pub(crate) fn reset(&self) {
        self.labels.borrow_mut().clear();
    }

    /// Records a mark ending stage `label` (the first mark starts the series). Marks past
    /// the capacity are ignored.
    pub(crate) fn mark(&self, encoder: &mut wgpu::CommandEncoder, label: &'static str) {
        let mut labels = self.labels.borrow_mut();
        let index = labels.len() as u32;
        if index < self.capacity {
            encoder.write_timestamp(&self.set, index);
            labels.push(label);
        }
    }

    /// Records the copy of the marks into a buffer for [`GpuContext::read_back`], and the
    /// byte count to read.
    pub(crate) fn resolve(&self, encoder: &mut wgpu::CommandEncoder) -> (&wgpu::Buffer, u64) {
        let count = self.labels.borrow().len() as u32;
        if count > 0 {
            encoder.resolve_query_set(&self.set, 0..count, &self.resolved, 0);
        }
        (&self.resolved, (count.max(1) as u64) * 8)
    }

    /// Each stage's device time from the read-back marks: `(label of the ending mark,
    /// ms since the previous mark)`, skipping the first mark.
    pub(crate) fn stages_ms(&self, bytes: &[u8]) -> Vec<(&'static str, f64)> {
        let ticks: Vec<u64> = bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
            .collect();
        self.labels
            .borrow()
            .iter()
            .enumerate()
            .skip(1)
            .filter_map(|(i, &label)| {
                let dt = ticks.get(i)?.checked_sub(*ticks.get(i - 1)?)?;
                Some((label, dt as f64 * self.period_ns as f64 * 1e-6))
            })
            .collect()
    }
}

/// A storage buffer from `scratch` when given, else a fresh zeroed one.
pub(crate) fn storage_in(
    ctx: &GpuContext,
    scratch: Option<&Scratch>,
    label: &str,
    bytes: u64,
) -> Result<wgpu::Buffer, GpuError> {
    match scratch {
        Some(s) => s.storage(ctx, label, bytes),
        None => ctx.storage(label, bytes),
    }
}

/// A uniform buffer from `scratch` when given, else a fresh one.
pub(crate) fn uniform_in(
    ctx: &GpuContext,
    scratch: Option<&Scratch>,
    label: &str,
    data: &[u8],
) -> Result<wgpu::Buffer, GpuError> {
    match scratch {
        Some(s) => s.uniform(ctx, label, data),
        None => Ok(ctx.uniform_init(label, data)),
    }
}

/// Threads per workgroup of the 1D kernels (must match `@workgroup_size` in the WGSL).
pub(crate) const WG_1D: u32 = 256;

/// Workgroup counts covering `threads` threads of 256: (x, y) with x <= 32768, since a
/// dispatch dimension is limited to 65535. Kernels rebuild the linear index as
/// `gid.x + gid.y * num_workgroups.x * 256`.
pub(crate) fn groups_1d(threads: u64) -> (u32, u32) {
    let groups = threads.div_ceil(WG_1D as u64).max(1);
    let x = groups.min(32768);
    (x as u32, groups.div_ceil(x) as u32)
}

pub(crate) fn dispatch_1d(
    pass: &mut wgpu::ComputePass,
    pipeline: &wgpu::ComputePipeline,
    bind: &wgpu::BindGroup,
    threads: u64,
) {
    let (x, y) = groups_1d(threads);
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind, &[]);
    pass.dispatch_workgroups(x, y, 1);
}

pub(crate) fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub(crate) fn u32_bytes(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

pub(crate) fn bytes_f32(b: &[u8]) -> Vec<f32> {
    b.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

pub(crate) fn bytes_u32(b: &[u8]) -> Vec<u32> {
    b.chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Shared handle used by the trainer's backend switch.
pub type SharedRasterizer = Arc<GpuRasterizer>;
