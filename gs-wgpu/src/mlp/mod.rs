//! The MLP's forward and backward on the device ([`GpuMlp`]): the same network, parameter
//! layout and arithmetic as `gs_core::nn::mlp` (`Y = X W + b`, hidden ReLU or LeakyReLU,
//! sigmoid output), with every matrix product `shaders/mlp_gemm.wgsl` (one invocation per
//! 8 x 8 block of outputs, each output its own in-order sum; the weight gradient's
//! reduction over rows split into [`WEIGHT_GRADIENT_CHUNK_ROWS`]-row chunks, added in order
//! by `mlp_sum_chunks.wgsl`),
//! bias and activation (and their backward) a pointwise kernel (`mlp_pointwise.wgsl`) and
//! the bias gradient a column sum (`mlp_colsum.wgsl`, split into the same row chunks and added
//! the same way). Every kernel reads the weights in
//! place from one flat parameter buffer in `nn::mlp`'s layout (word offsets in its
//! uniform) and writes the parameter gradient into one flat buffer of the same layout.
//!
//! Two ways in, one set of kernels and one recording (`record_forward`,
//! `record_backward`):
//! - the host path ([`GpuMlp::forward`], [`GpuMlp::backward`], used by `nn::Mlp` on a
//!   device): forward uploads the input and the flat parameters once per call and reads
//!   back only the output; the input, the parameters and every layer's activation stay on
//!   the device in the returned [`MlpTape`] for backward, which uploads only the output
//!   gradient and reads back the flat parameter gradient and, when asked, the input
//!   gradient. Each forward and each backward is one command buffer and one wait.
//! - the resident path (the device-resident Sun-aware step): a [`DeviceNetwork`] keeps the
//!   flat parameters, their gradient and the Adam moments on the device across steps;
//!   `GpuMlp::encode_forward`, `GpuMlp::encode_backward` and `GpuMlp::encode_adam`
//!   record into the caller's encoder on device buffers (never submitting or reading
//!   back), with scratch from the caller's `Scratch` under labels `mlp {label} ...`.
//!   [`DeviceBatch`], [`GpuMlp::run_forward_backward`] and [`GpuMlp::run_adam`] drive the
//!   same recording from the host, for tests and benchmarks outside the crate.
//!
//! Files: `record.rs` holds the one recording, `host.rs` the host path, `device.rs` the
//! resident path's state, entry points and host drivers; this one the types and kernels.
//!
//! Invariants:
//! - the batch's live row count is read on the device (word 0 of a `count` buffer; the
//!   host path writes its row count there): kernels dispatch over `max_rows` rows, rows
//!   `r >= count` read nothing (their input and output-gradient rows may hold anything,
//!   NaN included), their activations, outputs and input gradients are written 0, and
//!   every chunk of the weight gradient's split reduction past the count sums nothing, so
//!   it adds exactly 0: the gradients are those of the live rows only;
//! - every output value is one thread's in-order sum (GEMM over the reduction dimension or
//!   one chunk of it, the chunks in chunk order, the bias gradient likewise), no atomics,
//!   so results are deterministic run to run; the chunk boundaries depend only on the row
//!   index, so a resident run with `count` live rows gives the host path's bits for
//!   `count` rows;
//! - the parameter gradient is overwritten by each backward, never accumulated;
//! - Adam (`GpuMlp::encode_adam`) is `shaders/adam.wgsl` with one group covering the
//!   whole vector: `sunaware::trainer::FlatAdam`'s rule (b1 0.9, b2 0.999,
//!   `optim::ADAM_EPS`, step size and `1/sqrt(bias2)` in f64 on the host for step
//!   `adam_step + 1`; moments update even at learning rate 0, as there), changing nothing
//!   when `flags[0] != 0` when it runs; the host's step counter advances only through
//!   [`DeviceNetwork::mark_stepped`], when the caller's readback says the step applied;
//! - a tape's buffers are scratch under its label (resident path) or its own (host path):
//!   a second forward recorded under the same label before the backward reuses them, and
//!   the forward's `input` buffer must still hold the batch when the backward runs;
//! - products are f32 whatever `Mlp::precision` says (no bf16 kernels on the device);
//! - bad shapes are [`GpuError::Invalid`], sizes past the dispatch or buffer limits
//!   [`GpuError::TooLarge`], before any device work. Finiteness is checked by the caller
//!   (`nn::mlp`) on the host path; [`DeviceNetwork`] refuses non-finite parameters and
//!   moments on upload and on download (the model is left unchanged).

mod device;
mod host;
mod record;

pub(crate) use device::MlpRecording;

use super::{
    bytes_f32, bytes_u32, dispatch_1d, f32_bytes, storage_in, u32_bytes, uniform_in, GpuContext,
    GpuError, Scratch,
};
use gs_core::nn::{HiddenActivation, Mlp};

const GEMM: &str = include_str!("../shaders/mlp_gemm.wgsl");
const SUM_CHUNKS: &str = include_str!("../shaders/mlp_sum_chunks.wgsl");
const POINTWISE: &str = include_str!("../shaders/mlp_pointwise.wgsl");
const COLSUM: &str = include_str!("../shaders/mlp_colsum.wgsl");
const ADAM: &str = include_str!("../shaders/adam.wgsl");

/// Rows per chunk of the weight gradient's split reduction (`X^T dZ` sums over every row
/// of the batch): each chunk is its own set of workgroups, the chunks are added in order
/// afterwards. Fixed, so the sums' order does not depend on the device.
pub const WEIGHT_GRADIENT_CHUNK_ROWS: usize = 256;

/// Rows (and columns) of C one `mlp_gemm.wgsl` workgroup covers: 16 x 16 invocations of
/// 8 x 8 outputs each.
const GEMM_BLOCK: usize = 128;

/// `sunaware::trainer::FlatAdam`'s moment decay rates.
const ADAM_BETA1: f32 = 0.9;
const ADAM_BETA2: f32 = 0.999;

/// `mlp_pointwise.wgsl`'s operations.
#[derive(Clone, Copy)]
enum Pointwise {
    BiasRelu = 0,
    BiasLeakyRelu = 1,
    BiasSigmoid = 2,
    SigmoidBackward = 3,
    ReluBackward = 4,
    LeakyReluBackward = 5,
}

/// `mlp_gemm.wgsl`'s `live_dim`: which dimension runs over the batch's rows.
#[derive(Clone, Copy)]
enum Live {
    /// The rows of C are batch rows: dead ones are written 0.
    OutputRows = 1,
    /// The reduction runs over batch rows: it stops at the live count.
    ReductionRows = 2,
}

/// Which operands of a product are transposed, as in `gs_core::nn::matmul`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GemmOp {
    /// `C (m x n) = A (m x k) B (k x n)`.
    AB,
    /// `C (m x n) = A^T B`, `A` stored `k x m` (the weight-gradient product).
    AtB,
    /// `C (m x n) = A B^T`, `B` stored `n x k` (the input-gradient product).
    ABt,
}

/// One `mlp_gemm.wgsl` dispatch: `C (m x n) = op(A) op(B)` over `k`, split into
/// `k_chunk`-long partial sums, with word offsets into A, B and C.
struct GemmShape {
    op: GemmOp,
    m: usize,
    k: usize,
    n: usize,
    k_chunk: usize,
    a_off: usize,
    b_off: usize,
    c_off: usize,
    live: Live,
}

/// Word offsets of `nn::mlp`'s flat layout for `widths`: layer `l`'s `W` (in x out,
/// row-major) starts at `starts[l]`, its bias right after; `starts[layers]` is the total.
fn layer_starts(widths: &[usize]) -> Vec<usize> {
    let mut starts = vec![0usize];
    for p in widths.windows(2) {
        starts.push(starts[starts.len() - 1] + p[0] * p[1] + p[1]);
    }
    starts
}

/// Compiled pipelines for the device MLP on one device.
pub struct GpuMlp {
    ctx: GpuContext,
    gemm: wgpu::ComputePipeline,
    sum_chunks: wgpu::ComputePipeline,
    pointwise: wgpu::ComputePipeline,
    colsum: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    /// Scratch of the host-driven resident runs ([`GpuMlp::run_forward_backward`]).
    scratch: Scratch,
}

impl std::fmt::Debug for GpuMlp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuMlp({})", self.ctx.describe())
    }
}

/// Activations of one recorded forward (device buffers), for its backward: the input it
/// read, the live-row count buffer and every layer's output over `max_rows` rows (hidden
/// activations after the activation, then the sigmoid output; dead rows 0).
pub struct DeviceTape {
    max_rows: usize,
    widths: Vec<usize>,
    hidden: HiddenActivation,
    input: wgpu::Buffer,
    count: wgpu::Buffer,
    activations: Vec<wgpu::Buffer>,
}

impl std::fmt::Debug for DeviceTape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "DeviceTape({} rows at most, widths {:?})",
            self.max_rows, self.widths
        )
    }
}

impl DeviceTape {
    /// Rows the forward was recorded over (live or not).
    pub fn max_rows(&self) -> usize {
        self.max_rows
    }
}

/// What a host-path forward keeps for its backward: the device tape and the flat
/// parameters it used. No buffers for zero rows.
pub struct MlpTape {
    rows: usize,
    widths: Vec<usize>,
    device: Option<(DeviceTape, wgpu::Buffer)>,
}

impl std::fmt::Debug for MlpTape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "MlpTape({} rows, widths {:?})", self.rows, self.widths)
    }
}

impl MlpTape {
    pub fn rows(&self) -> usize {
        self.rows
    }
}

/// The device gradients of one backward.
#[derive(Clone, Debug, PartialEq)]
pub struct MlpGradients {
    /// Parameter gradient in `nn::mlp`'s flat layout (`Mlp::num_params` values).
    pub params: Vec<f32>,
    /// Input gradient, row-major `rows x in` (when asked for).
    pub input: Option<Vec<f32>>,
}

/// A network's flat parameters (`nn::mlp` layout: `Mlp::params()`, `weight_range(l)`,
/// `bias_range(l)`), its gradient (same layout) and Adam moments, resident on the device.
pub struct DeviceNetwork {
    widths: Vec<usize>,
    hidden: HiddenActivation,
    len: usize,
    params: wgpu::Buffer,
    grads: wgpu::Buffer,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    adam_step: u64,
}

impl std::fmt::Debug for DeviceNetwork {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "DeviceNetwork(widths {:?}, {:?}, {} Adam steps)",
            self.widths, self.hidden, self.adam_step
        )
    }
}

/// Device buffers of one batch for driving the resident path from the host
/// ([`GpuMlp::run_forward_backward`]; tests and benchmarks: the resident step has its own
/// buffers): input and output gradient, written by [`DeviceBatch::write`], the live-row
/// count, and the output and input gradient the run writes.
pub struct DeviceBatch {
    max_rows: usize,
    in_width: usize,
    out_width: usize,
    input: wgpu::Buffer,
    count: wgpu::Buffer,
    d_output: wgpu::Buffer,
    output: wgpu::Buffer,
    d_input: wgpu::Buffer,
}

impl std::fmt::Debug for DeviceBatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "DeviceBatch({} rows, {} in, {} out)",
            self.max_rows, self.in_width, self.out_width
        )
    }
}

impl GpuMlp {
    pub fn new(ctx: GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            gemm: ctx.pipeline("mlp gemm", GEMM)?,
            sum_chunks: ctx.pipeline("mlp sum chunks", SUM_CHUNKS)?,
            pointwise: ctx.pipeline("mlp pointwise", POINTWISE)?,
            colsum: ctx.pipeline("mlp colsum", COLSUM)?,
            adam: ctx.pipeline("mlp adam", ADAM)?,
            scratch: Scratch::default(),
            ctx,
        })
    }

    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    fn check_sizes(&self, widths: &[usize], rows: usize) -> Result<(), GpuError> {
        let widest = widths.iter().copied().max().unwrap_or(0);
        let max = u32::MAX as usize / 4;
        if rows.div_ceil(16) > 65535
            || widest.div_ceil(16) > 65535
            || rows.saturating_mul(widest) > max
            || widest.saturating_mul(widest) > max
            || layer_starts(widths).last().copied().unwrap_or(0) > max
        {
            return Err(GpuError::TooLarge(format!(
                "MLP of {rows} rows and widths {widths:?}"
            )));
        }
        Ok(())
    }

    /// A storage buffer holding `data` (through the size checks of `GpuContext::storage`).
    fn upload(&self, label: &str, data: &[f32]) -> Result<wgpu::Buffer, GpuError> {
        let buffer = self.ctx.storage(label, (data.len() * 4) as u64)?;
        if !data.is_empty() {
            self.ctx.queue.write_buffer(&buffer, 0, &f32_bytes(data));
        }
        Ok(buffer)
    }
}
