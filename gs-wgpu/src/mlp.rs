//! The MLP's forward and backward on the device ([`GpuMlp`]): the same network, parameter
//! layout and arithmetic as `gs_core::nn::mlp` (`Y = X W + b`, hidden ReLU or LeakyReLU,
//! sigmoid output), with every matrix product `shaders/mlp_gemm.wgsl` (one invocation per
//! 8 x 8 block of outputs, each output its own in-order sum; the weight gradient's
//! reduction over rows split into [`WEIGHT_GRADIENT_CHUNK_ROWS`]-row chunks, added in order
//! by `mlp_sum_chunks.wgsl`),
//! bias and activation (and their backward) a pointwise kernel (`mlp_pointwise.wgsl`) and
//! the bias gradient a column sum (`mlp_colsum.wgsl`). Every kernel reads the weights in
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
//! Invariants:
//! - the batch's live row count is read on the device (word 0 of a `count` buffer; the
//!   host path writes its row count there): kernels dispatch over `max_rows` rows, rows
//!   `r >= count` read nothing (their input and output-gradient rows may hold anything,
//!   NaN included), their activations, outputs and input gradients are written 0, and
//!   every chunk of the weight gradient's split reduction past the count sums nothing, so
//!   it adds exactly 0: the gradients are those of the live rows only;
//! - every output value is one thread's in-order sum (GEMM over the reduction dimension or
//!   one chunk of it, the chunks in chunk order, the bias gradient over rows), no atomics,
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

use super::{
    bytes_f32, bytes_u32, dispatch_1d, f32_bytes, storage_in, u32_bytes, uniform_in, GpuContext,
    GpuError, Scratch,
};
use gs_core::nn::{HiddenActivation, Mlp};

const GEMM: &str = include_str!("shaders/mlp_gemm.wgsl");
const SUM_CHUNKS: &str = include_str!("shaders/mlp_sum_chunks.wgsl");
const POINTWISE: &str = include_str!("shaders/mlp_pointwise.wgsl");
const COLSUM: &str = include_str!("shaders/mlp_colsum.wgsl");
const ADAM: &str = include_str!("shaders/adam.wgsl");

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

/// Lengths and finiteness of a host network and its moments.
fn check_host_state(mlp: &Mlp, m: &[f32], v: &[f32]) -> Result<(), GpuError> {
    let n = mlp.num_params();
    if m.len() != n || v.len() != n {
        return Err(GpuError::Invalid(format!(
            "Adam moments of {} and {} values for a network of {n} parameters",
            m.len(),
            v.len()
        )));
    }
    for (name, values) in [("parameters", mlp.params()), ("Adam m", m), ("Adam v", v)] {
        if let Some(i) = values.iter().position(|x| !x.is_finite()) {
            return Err(GpuError::Invalid(format!(
                "network {name}: non-finite value {} at {i}",
                values[i]
            )));
        }
    }
    Ok(())
}

impl DeviceNetwork {
    /// The device copy of `mlp` with Adam moments `m`, `v` after `adam_step` steps; the
    /// gradient starts at zero.
    pub fn new(
        ctx: &GpuContext,
        mlp: &Mlp,
        m: &[f32],
        v: &[f32],
        adam_step: u64,
    ) -> Result<Self, GpuError> {
        check_host_state(mlp, m, v)?;
        let bytes = (mlp.num_params() * 4) as u64;
        let mut out = Self {
            widths: mlp.widths().to_vec(),
            hidden: mlp.hidden_activation(),
            len: mlp.num_params(),
            params: ctx.storage("mlp network params", bytes)?,
            grads: ctx.storage("mlp network grads", bytes)?,
            m: ctx.storage("mlp network adam m", bytes)?,
            v: ctx.storage("mlp network adam v", bytes)?,
            adam_step,
        };
        out.upload(ctx, mlp, m, v, adam_step)?;
        Ok(out)
    }

    fn check_same_network(&self, mlp: &Mlp) -> Result<(), GpuError> {
        if mlp.widths() != self.widths.as_slice() || mlp.hidden_activation() != self.hidden {
            return Err(GpuError::Invalid(format!(
                "network of widths {:?} ({:?}) differs from the device's {:?} ({:?})",
                mlp.widths(),
                mlp.hidden_activation(),
                self.widths,
                self.hidden
            )));
        }
        Ok(())
    }

    /// Overwrites the parameters, moments and step counter (same widths and activation,
    /// else [`GpuError::Invalid`]); takes effect at the next submission.
    pub fn upload(
        &mut self,
        ctx: &GpuContext,
        mlp: &Mlp,
        m: &[f32],
        v: &[f32],
        adam_step: u64,
    ) -> Result<(), GpuError> {
        self.check_same_network(mlp)?;
        check_host_state(mlp, m, v)?;
        ctx.queue
            .write_buffer(&self.params, 0, &f32_bytes(mlp.params()));
        ctx.queue.write_buffer(&self.m, 0, &f32_bytes(m));
        ctx.queue.write_buffer(&self.v, 0, &f32_bytes(v));
        self.adam_step = adam_step;
        Ok(())
    }

    /// Copies the parameters into `mlp` and the moments into `m`, `v` (one wait). A
    /// non-finite device value is [`GpuError::Invalid`] and changes nothing on the host.
    pub fn download(
        &self,
        ctx: &GpuContext,
        mlp: &mut Mlp,
        m: &mut [f32],
        v: &mut [f32],
    ) -> Result<(), GpuError> {
        self.check_same_network(mlp)?;
        if m.len() != self.len || v.len() != self.len {
            return Err(GpuError::Invalid(format!(
                "Adam moments of {} and {} values for a network of {} parameters",
                m.len(),
                v.len(),
                self.len
            )));
        }
        let bytes = (self.len * 4) as u64;
        let back = ctx.read_back(
            ctx.encoder("mlp network download"),
            &[(&self.params, bytes), (&self.m, bytes), (&self.v, bytes)],
        )?;
        let values: Vec<Vec<f32>> = back.iter().map(|b| bytes_f32(b)).collect();
        for (name, vals) in ["parameters", "Adam m", "Adam v"].iter().zip(&values) {
            if let Some(i) = vals.iter().position(|x| !x.is_finite()) {
                return Err(GpuError::Invalid(format!(
                    "device network {name}: non-finite value {} at {i}",
                    vals[i]
                )));
            }
        }
        mlp.params_mut().copy_from_slice(&values[0]);
        m.copy_from_slice(&values[1]);
        v.copy_from_slice(&values[2]);
        Ok(())
    }

    /// The gradient buffer's contents (tests; one wait).
    pub fn download_grads(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        let back = ctx.read_back(
            ctx.encoder("mlp network grads"),
            &[(&self.grads, (self.len * 4) as u64)],
        )?;
        Ok(bytes_f32(&back[0]))
    }

    /// Overwrites the gradient buffer (tests of the Adam step on its own).
    pub fn upload_grads(&self, ctx: &GpuContext, grads: &[f32]) -> Result<(), GpuError> {
        if grads.len() != self.len {
            return Err(GpuError::Invalid(format!(
                "gradient of {} values for a network of {} parameters",
                grads.len(),
                self.len
            )));
        }
        ctx.queue.write_buffer(&self.grads, 0, &f32_bytes(grads));
        Ok(())
    }

    /// Flat parameters (`nn::mlp` layout).
    pub fn params(&self) -> &wgpu::Buffer {
        &self.params
    }

    /// Flat parameter gradient (same layout), overwritten by each
    /// `GpuMlp::encode_backward`.
    pub fn grads(&self) -> &wgpu::Buffer {
        &self.grads
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Always false (a network has at least one weight); for clippy's `len` convention.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn widths(&self) -> &[usize] {
        &self.widths
    }

    pub fn hidden_activation(&self) -> HiddenActivation {
        self.hidden
    }

    /// Adam steps applied (the next step's bias correction uses `adam_step() + 1`).
    pub fn adam_step(&self) -> u64 {
        self.adam_step
    }

    /// Records that the caller's readback said the recorded Adam step was applied.
    pub fn mark_stepped(&mut self) {
        self.adam_step += 1;
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

impl DeviceBatch {
    /// Buffers for up to `max_rows` rows of `net`'s input and output widths.
    pub fn new(gpu: &GpuMlp, net: &DeviceNetwork, max_rows: usize) -> Result<Self, GpuError> {
        let ctx = &gpu.ctx;
        let (in_width, out_width) = (net.widths[0], net.widths[net.widths.len() - 1]);
        let bytes_in = (max_rows * in_width * 4) as u64;
        let bytes_out = (max_rows * out_width * 4) as u64;
        Ok(Self {
            max_rows,
            in_width,
            out_width,
            input: ctx.storage("mlp batch input", bytes_in)?,
            count: ctx.storage("mlp batch count", 4)?,
            d_output: ctx.storage("mlp batch d_output", bytes_out)?,
            output: ctx.storage("mlp batch output", bytes_out)?,
            d_input: ctx.storage("mlp batch d_input", bytes_in)?,
        })
    }

    /// Writes the batch: `max_rows x in` inputs, `max_rows x out` output gradients (rows
    /// from `live_rows` on are dead: never read, any value) and the live count.
    pub fn write(
        &self,
        gpu: &GpuMlp,
        input: &[f32],
        live_rows: usize,
        d_output: &[f32],
    ) -> Result<(), GpuError> {
        if input.len() != self.max_rows * self.in_width
            || d_output.len() != self.max_rows * self.out_width
            || live_rows > self.max_rows
        {
            return Err(GpuError::Invalid(format!(
                "batch of {} inputs, {} output gradients, {live_rows} live rows for {} rows \
                 of {} in, {} out",
                input.len(),
                d_output.len(),
                self.max_rows,
                self.in_width,
                self.out_width
            )));
        }
        let q = &gpu.ctx.queue;
        if !input.is_empty() {
            q.write_buffer(&self.input, 0, &f32_bytes(input));
            q.write_buffer(&self.d_output, 0, &f32_bytes(d_output));
        }
        q.write_buffer(&self.count, 0, &u32_bytes(&[live_rows as u32]));
        Ok(())
    }

    /// Reads back the output (`max_rows x out`) and the input gradient (`max_rows x in`;
    /// what the last run left there, zeros before any run asked for it).
    pub fn read(&self, gpu: &GpuMlp) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let back = gpu.ctx.read_back(
            gpu.ctx.encoder("mlp batch read"),
            &[
                (&self.output, (self.max_rows * self.out_width * 4) as u64),
                (&self.d_input, (self.max_rows * self.in_width * 4) as u64),
            ],
        )?;
        Ok((bytes_f32(&back[0]), bytes_f32(&back[1])))
    }
}

/// Checks that `buffer` holds at least `values` f32.
fn check_buffer(name: &str, buffer: &wgpu::Buffer, values: usize) -> Result<(), GpuError> {
    if buffer.size() < (values * 4) as u64 {
        return Err(GpuError::Invalid(format!(
            "{name}: buffer of {} bytes, {values} values needed",
            buffer.size()
        )));
    }
    Ok(())
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

    /// Records `C = op(A) op(B)` (see [`GemmShape`] and `GemmOp` for the strides) into
    /// `pass`, as `k.div_ceil(k_chunk)` partial products one after another in `c` (one
    /// when `k_chunk >= k`), the batch's live rows from `count`.
    #[allow(clippy::too_many_arguments)]
    fn gemm(
        &self,
        pass: &mut wgpu::ComputePass,
        scratch: Option<&Scratch>,
        label: &str,
        s: &GemmShape,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        c: &wgpu::Buffer,
        count: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (a_rs, a_cs, b_rs, b_cs) = match s.op {
            GemmOp::AB => (s.k, 1, s.n, 1),
            GemmOp::AtB => (1, s.m, s.n, 1),
            GemmOp::ABt => (s.k, 1, 1, s.k),
        };
        let words = [
            s.m, s.n, s.k, s.k_chunk, a_rs, a_cs, b_rs, b_cs, s.a_off, s.b_off, s.c_off,
        ]
        .map(|w| w as u32);
        let mut data = u32_bytes(&words);
        data.extend_from_slice(&(s.live as u32).to_le_bytes());
        let params = uniform_in(&self.ctx, scratch, label, &data)?;
        let bind = self.ctx.bind_group(&self.gemm, &[&params, a, b, c, count]);
        pass.set_pipeline(&self.gemm);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(
            s.n.div_ceil(GEMM_BLOCK) as u32,
            s.m.div_ceil(GEMM_BLOCK) as u32,
            s.k.div_ceil(s.k_chunk) as u32,
        );
        Ok(())
    }

    /// Records `mlp_pointwise.wgsl`'s `op` on the `values / n` x `n` matrix `x`, with
    /// `aux` read from word `aux_off`.
    #[allow(clippy::too_many_arguments)]
    fn pointwise(
        &self,
        pass: &mut wgpu::ComputePass,
        scratch: Option<&Scratch>,
        label: &str,
        op: Pointwise,
        x: &wgpu::Buffer,
        (aux, aux_off): (&wgpu::Buffer, usize),
        count: &wgpu::Buffer,
        (values, n): (usize, usize),
    ) -> Result<(), GpuError> {
        let mut data = u32_bytes(&[values as u32, n as u32, op as u32]);
        data.extend_from_slice(&gs_core::nn::mlp::LEAKY_SLOPE.to_le_bytes());
        data.extend_from_slice(&u32_bytes(&[aux_off as u32, 0, 0, 0]));
        let params = uniform_in(&self.ctx, scratch, label, &data)?;
        let bind = self
            .ctx
            .bind_group(&self.pointwise, &[&params, x, aux, count]);
        dispatch_1d(pass, &self.pointwise, &bind, values as u64);
        Ok(())
    }

    /// Records the forward of the network `widths`/`hidden` whose flat parameters are
    /// `params` over `max_rows` rows of `input` (live count in `count`), every layer's
    /// output into a fresh (host path) or scratch buffer of the returned tape.
    #[allow(clippy::too_many_arguments)]
    fn record_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        label: &str,
        (widths, hidden): (&[usize], HiddenActivation),
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        count: &wgpu::Buffer,
        max_rows: usize,
    ) -> Result<DeviceTape, GpuError> {
        self.check_sizes(widths, max_rows)?;
        let layers = widths.len() - 1;
        let starts = layer_starts(widths);
        let mut activations = Vec::with_capacity(layers);
        for l in 0..layers {
            activations.push(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} activation {l}"),
                (max_rows * widths[l + 1] * 4) as u64,
            )?);
        }
        if max_rows > 0 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            for l in 0..layers {
                let (n_in, n_out) = (widths[l], widths[l + 1]);
                let layer_input = if l == 0 { input } else { &activations[l - 1] };
                let shape = GemmShape {
                    op: GemmOp::AB,
                    m: max_rows,
                    k: n_in,
                    n: n_out,
                    k_chunk: n_in,
                    a_off: 0,
                    b_off: starts[l],
                    c_off: 0,
                    live: Live::OutputRows,
                };
                let gemm_label = format!("mlp {label} forward gemm {l}");
                let out = &activations[l];
                self.gemm(
                    &mut pass,
                    scratch,
                    &gemm_label,
                    &shape,
                    layer_input,
                    params,
                    out,
                    count,
                )?;
                let op = if l + 1 == layers {
                    Pointwise::BiasSigmoid
                } else {
                    match hidden {
                        HiddenActivation::Relu => Pointwise::BiasRelu,
                        HiddenActivation::LeakyRelu => Pointwise::BiasLeakyRelu,
                    }
                };
                self.pointwise(
                    &mut pass,
                    scratch,
                    &format!("mlp {label} forward pointwise {l}"),
                    op,
                    out,
                    (params, starts[l] + n_in * n_out),
                    count,
                    (max_rows * n_out, n_out),
                )?;
            }
        }
        Ok(DeviceTape {
            max_rows,
            widths: widths.to_vec(),
            hidden,
            input: input.clone(),
            count: count.clone(),
            activations,
        })
    }

    /// Records the backward of `tape` for `d_output` (copied, not modified): the flat
    /// parameter gradient into `grads` (overwritten) and, when given, the input gradient
    /// into `d_input`, reading the weights from `params`.
    #[allow(clippy::too_many_arguments)]
    fn record_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        label: &str,
        (params, grads): (&wgpu::Buffer, &wgpu::Buffer),
        tape: &DeviceTape,
        d_output: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let widths = &tape.widths;
        let rows = tape.max_rows;
        let layers = widths.len() - 1;
        let starts = layer_starts(widths);
        if rows == 0 {
            encoder.clear_buffer(grads, 0, Some((starts[layers] * 4) as u64));
            return Ok(());
        }
        let count = &tape.count;
        let n_out_last = widths[layers];
        let mut dz = storage_in(
            &self.ctx,
            scratch,
            &format!("mlp {label} dz {}", layers - 1),
            (rows * n_out_last * 4) as u64,
        )?;
        encoder.copy_buffer_to_buffer(d_output, 0, &dz, 0, (rows * n_out_last * 4) as u64);
        let chunks = rows.div_ceil(WEIGHT_GRADIENT_CHUNK_ROWS);
        // One partials buffer serves every layer (wgpu orders the dispatches using it).
        let partials = if chunks > 1 {
            let widest = widths.windows(2).map(|p| p[0] * p[1]).max().unwrap_or(0);
            Some(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} weight gradient chunks"),
                (chunks * widest * 4) as u64,
            )?)
        } else {
            None
        };
        // Hidden layers' input gradients, allocated before the pass borrows them.
        let mut d_hidden = Vec::with_capacity(layers);
        for l in 0..layers.saturating_sub(1) {
            d_hidden.push(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} dz {l}"),
                (rows * widths[l + 1] * 4) as u64,
            )?);
        }
        let mut pass = encoder.begin_compute_pass(&Default::default());
        self.pointwise(
            &mut pass,
            scratch,
            &format!("mlp {label} backward sigmoid"),
            Pointwise::SigmoidBackward,
            &dz,
            (&tape.activations[layers - 1], 0),
            count,
            (rows * n_out_last, n_out_last),
        )?;
        for l in (0..layers).rev() {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            let w_at = starts[l];
            let layer_input = if l == 0 {
                &tape.input
            } else {
                &tape.activations[l - 1]
            };
            let weight_gradient = GemmShape {
                op: GemmOp::AtB,
                m: n_in,
                k: rows,
                n: n_out,
                k_chunk: WEIGHT_GRADIENT_CHUNK_ROWS,
                a_off: 0,
                b_off: 0,
                c_off: if partials.is_some() { 0 } else { w_at },
                live: Live::ReductionRows,
            };
            self.gemm(
                &mut pass,
                scratch,
                &format!("mlp {label} backward dW {l}"),
                &weight_gradient,
                layer_input,
                &dz,
                partials.as_ref().unwrap_or(grads),
                count,
            )?;
            if let Some(partials) = &partials {
                let values = n_in * n_out;
                let uniform = uniform_in(
                    &self.ctx,
                    scratch,
                    &format!("mlp {label} backward dW sum {l}"),
                    &u32_bytes(&[values as u32, chunks as u32, w_at as u32, 0]),
                )?;
                let bind = self
                    .ctx
                    .bind_group(&self.sum_chunks, &[&uniform, partials, grads]);
                dispatch_1d(&mut pass, &self.sum_chunks, &bind, values as u64);
            }
            let colsum = uniform_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} backward db {l}"),
                &u32_bytes(&[rows as u32, n_out as u32, (w_at + n_in * n_out) as u32, 0]),
            )?;
            let bind = self
                .ctx
                .bind_group(&self.colsum, &[&colsum, &dz, grads, count]);
            pass.set_pipeline(&self.colsum);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(n_out.div_ceil(64) as u32, 1, 1);
            let d_prev = match (l, d_input) {
                (0, None) => break,
                (0, Some(d)) => d,
                _ => &d_hidden[l - 1],
            };
            let input_gradient = GemmShape {
                op: GemmOp::ABt,
                m: rows,
                k: n_out,
                n: n_in,
                k_chunk: n_out,
                a_off: 0,
                b_off: w_at,
                c_off: 0,
                live: Live::OutputRows,
            };
            self.gemm(
                &mut pass,
                scratch,
                &format!("mlp {label} backward dX {l}"),
                &input_gradient,
                &dz,
                params,
                d_prev,
                count,
            )?;
            if l > 0 {
                let op = match tape.hidden {
                    HiddenActivation::Relu => Pointwise::ReluBackward,
                    HiddenActivation::LeakyRelu => Pointwise::LeakyReluBackward,
                };
                self.pointwise(
                    &mut pass,
                    scratch,
                    &format!("mlp {label} backward activation {l}"),
                    op,
                    d_prev,
                    (&tape.activations[l - 1], 0),
                    count,
                    (rows * n_in, n_in),
                )?;
                dz = d_prev.clone();
            }
        }
        Ok(())
    }

    /// Records the forward of `net` over `max_rows` rows of `input` (row-major, input
    /// width), of which only the first `count[0]` (u32 read on the device) are live; output
    /// rows beyond the count are written as 0. Output: `max_rows * out_width` f32 into
    /// `output`. The tape's activations are `scratch` buffers under `mlp {label} ...`
    /// (one label per network and batch within a command buffer); `input` must still hold
    /// the batch when the backward runs.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn encode_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: &Scratch,
        label: &str,
        net: &DeviceNetwork,
        input: &wgpu::Buffer,
        count: &wgpu::Buffer,
        max_rows: usize,
        output: &wgpu::Buffer,
    ) -> Result<DeviceTape, GpuError> {
        let widths = net.widths();
        let n_out = widths[widths.len() - 1];
        check_buffer("MLP input", input, max_rows * widths[0])?;
        check_buffer("MLP output", output, max_rows * n_out)?;
        check_buffer("MLP row count", count, 1)?;
        let tape = self.record_forward(
            encoder,
            Some(scratch),
            label,
            (widths, net.hidden),
            &net.params,
            input,
            count,
            max_rows,
        )?;
        if max_rows > 0 {
            let last = &tape.activations[widths.len() - 2];
            encoder.copy_buffer_to_buffer(last, 0, output, 0, (max_rows * n_out * 4) as u64);
        }
        Ok(tape)
    }

    /// Records the backward for `d_output` (`max_rows * out_width`, rows beyond the count
    /// are ignored; the buffer is not modified): the parameter gradient into `net.grads()`
    /// (overwritten, not accumulated) and, when given, the input gradient into `d_input`
    /// (`max_rows * in_width`, rows beyond the count written 0). `net` must be the
    /// network of the tape's forward, its parameters unchanged since.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn encode_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: &Scratch,
        label: &str,
        net: &DeviceNetwork,
        tape: &DeviceTape,
        d_output: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        if tape.widths != net.widths || tape.hidden != net.hidden {
            return Err(GpuError::Invalid(format!(
                "MLP backward: tape of widths {:?} ({:?}) for a network of {:?} ({:?})",
                tape.widths, tape.hidden, net.widths, net.hidden
            )));
        }
        let widths = &tape.widths;
        check_buffer(
            "MLP output gradient",
            d_output,
            tape.max_rows * widths[widths.len() - 1],
        )?;
        if let Some(d) = d_input {
            check_buffer("MLP input gradient", d, tape.max_rows * widths[0])?;
        }
        self.record_backward(
            encoder,
            Some(scratch),
            label,
            (&net.params, &net.grads),
            tape,
            d_output,
            d_input,
        )
    }

    /// Records one Adam step on `net.params()` with `net.grads()` and learning rate `lr`:
    /// `FlatAdam::apply`'s rule for step `net.adam_step() + 1` (`shaders/adam.wgsl`, one
    /// group covering the whole vector), changing nothing at all when `flags[0] != 0` at
    /// the time it runs. The caller calls [`DeviceNetwork::mark_stepped`] when its
    /// readback of `flags` says the step applied. `lr` must be finite and non-negative.
    pub(crate) fn encode_adam(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: &Scratch,
        label: &str,
        net: &DeviceNetwork,
        lr: f32,
        flags: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(GpuError::Invalid(format!("MLP Adam learning rate {lr}")));
        }
        check_buffer("MLP Adam flags", flags, 1)?;
        let len = u32::try_from(net.len)
            .map_err(|_| GpuError::TooLarge(format!("{} network parameters", net.len)))?;
        // FlatAdam::apply, step t = adam_step + 1 (its counter is incremented first).
        let t = (net.adam_step + 1) as i32;
        let bias1 = 1.0 - (ADAM_BETA1 as f64).powi(t);
        let bias2 = 1.0 - (ADAM_BETA2 as f64).powi(t);
        let mut words = [0u32; 28];
        // adam.wgsl's group offsets: group 0 is [0, len), groups 1..7 empty at len.
        words[1..9].fill(len);
        words[12] = ((lr as f64 / bias1) as f32).to_bits();
        // Group 0 always active: FlatAdam moves the moments even at learning rate 0.
        words[20] = 1;
        words[21] = ADAM_BETA1.to_bits();
        words[22] = ADAM_BETA2.to_bits();
        words[23] = gs_core::optim::ADAM_EPS.to_bits();
        words[24] = ((1.0 / bias2.sqrt()) as f32).to_bits();
        let uniform =
            scratch.uniform(&self.ctx, &format!("mlp {label} adam"), &u32_bytes(&words))?;
        let bind = self.ctx.bind_group(
            &self.adam,
            &[&uniform, &net.params, &net.grads, &net.m, &net.v, flags],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.adam, &bind, net.len as u64);
        Ok(())
    }

    /// `GpuMlp::encode_forward` then `GpuMlp::encode_backward` on `batch` as one
    /// command buffer, submitted and waited for (no readback): the output and, when
    /// `input_gradient`, the input gradient land in `batch`, the parameter gradient in
    /// `net.grads()`. For tests and benchmarks outside the crate; its scratch is this
    /// `GpuMlp`'s, under one label, so runs must not overlap (one thread at a time).
    pub fn run_forward_backward(
        &self,
        net: &DeviceNetwork,
        batch: &DeviceBatch,
        input_gradient: bool,
    ) -> Result<(), GpuError> {
        if net.widths[0] != batch.in_width || net.widths[net.widths.len() - 1] != batch.out_width {
            return Err(GpuError::Invalid(format!(
                "{batch:?} for a network of widths {:?}",
                net.widths
            )));
        }
        let mut encoder = self.ctx.encoder("mlp run forward backward");
        let tape = self.encode_forward(
            &mut encoder,
            &self.scratch,
            "run",
            net,
            &batch.input,
            &batch.count,
            batch.max_rows,
            &batch.output,
        )?;
        self.encode_backward(
            &mut encoder,
            &self.scratch,
            "run",
            net,
            &tape,
            &batch.d_output,
            input_gradient.then_some(&batch.d_input),
        )?;
        self.ctx.queue.submit(Some(encoder.finish()));
        self.ctx
            .device
            .poll(wgpu::PollType::Wait)
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        Ok(())
    }

    /// `GpuMlp::encode_adam` on the gradient as it stands, with the refusal flag set to
    /// `refuse`, submitted with a readback of the flag; marks the step applied when the
    /// flag reads 0, as the resident step does. Returns whether it applied. For tests.
    pub fn run_adam(
        &self,
        net: &mut DeviceNetwork,
        lr: f32,
        refuse: bool,
    ) -> Result<bool, GpuError> {
        let flags = self.scratch.storage(&self.ctx, "mlp run flags", 4)?;
        self.ctx
            .queue
            .write_buffer(&flags, 0, &u32_bytes(&[refuse as u32]));
        let mut encoder = self.ctx.encoder("mlp run adam");
        self.encode_adam(&mut encoder, &self.scratch, "run", net, lr, &flags)?;
        let back = self.ctx.read_back(encoder, &[(&flags, 4)])?;
        let applied = bytes_u32(&back[0])[0] == 0;
        if applied {
            net.mark_stepped();
        }
        Ok(applied)
    }

    /// Forward of `mlp` on `rows` row-major inputs: the sigmoid outputs (`rows x out`)
    /// and the tape for [`GpuMlp::backward`].
    pub fn forward(
        &self,
        mlp: &Mlp,
        input: &[f32],
        rows: usize,
    ) -> Result<(Vec<f32>, MlpTape), GpuError> {
        let widths = mlp.widths().to_vec();
        if input.len() != rows * widths[0] {
            return Err(GpuError::Invalid(format!(
                "MLP input: expected {} values, got {}",
                rows * widths[0],
                input.len()
            )));
        }
        self.check_sizes(&widths, rows)?;
        if rows == 0 {
            let tape = MlpTape {
                rows,
                widths,
                device: None,
            };
            return Ok((Vec::new(), tape));
        }
        let params = self.upload("mlp params", mlp.params())?;
        let x = self.upload("mlp input", input)?;
        let count = self
            .ctx
            .storage_init("mlp row count", &u32_bytes(&[rows as u32]));
        let mut encoder = self.ctx.encoder("mlp forward");
        let tape = self.record_forward(
            &mut encoder,
            None,
            "host",
            (&widths, mlp.hidden_activation()),
            &params,
            &x,
            &count,
            rows,
        )?;
        let n_out = widths[widths.len() - 1];
        let back = self.ctx.read_back(
            encoder,
            &[(
                &tape.activations[widths.len() - 2],
                (rows * n_out * 4) as u64,
            )],
        )?;
        let tape = MlpTape {
            rows,
            widths,
            device: Some((tape, params)),
        };
        Ok((bytes_f32(&back[0]), tape))
    }

    /// Backward of [`GpuMlp::forward`]: the parameter gradient (flat layout, not added to
    /// anything) and, when `want_input_gradient`, the input gradient.
    pub fn backward(
        &self,
        tape: &MlpTape,
        d_output: &[f32],
        want_input_gradient: bool,
    ) -> Result<MlpGradients, GpuError> {
        let widths = &tape.widths;
        let rows = tape.rows;
        let n_out = widths[widths.len() - 1];
        if d_output.len() != rows * n_out {
            return Err(GpuError::Invalid(format!(
                "MLP output gradient: expected {} values, got {}",
                rows * n_out,
                d_output.len()
            )));
        }
        let num_params = layer_starts(widths)[widths.len() - 1];
        let Some((device_tape, params)) = tape.device.as_ref().filter(|_| rows > 0) else {
            let input = want_input_gradient.then(Vec::new);
            return Ok(MlpGradients {
                params: vec![0.0; num_params],
                input,
            });
        };
        let dz = self.upload("mlp dY", d_output)?;
        let grads = self.ctx.storage("mlp dparams", (num_params * 4) as u64)?;
        let d_input = if want_input_gradient {
            Some(self.ctx.storage("mlp dX", (rows * widths[0] * 4) as u64)?)
        } else {
            None
        };
        let mut encoder = self.ctx.encoder("mlp backward");
        self.record_backward(
            &mut encoder,
            None,
            "host",
            (params, &grads),
            device_tape,
            &dz,
            d_input.as_ref(),
        )?;
        let mut ranges: Vec<(&wgpu::Buffer, u64)> = vec![(&grads, (num_params * 4) as u64)];
        if let Some(d) = &d_input {
            ranges.push((d, (rows * widths[0] * 4) as u64));
        }
        let back = self.ctx.read_back(encoder, &ranges)?;
        Ok(MlpGradients {
            params: bytes_f32(&back[0]),
            input: d_input.map(|_| bytes_f32(&back[1])),
        })
    }
}
