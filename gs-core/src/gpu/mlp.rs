//! The MLP's forward and backward on the device ([`GpuMlp`]): the same network, parameter
//! layout and arithmetic as `crate::nn::mlp` (`Y = X W + b`, hidden ReLU or LeakyReLU,
//! sigmoid output), with every matrix product `shaders/mlp_gemm.wgsl` (one invocation per
//! output; the weight gradient's reduction over rows split into
//! [`WEIGHT_GRADIENT_CHUNK_ROWS`]-row chunks, added in order by `mlp_sum_chunks.wgsl`),
//! bias and activation (and their backward) a pointwise kernel (`mlp_pointwise.wgsl`) and
//! the bias gradient a column sum (`mlp_colsum.wgsl`).
//!
//! Invariants:
//! - forward uploads the input and the weights once (one buffer per layer's `W` and `b`)
//!   and reads back only the output; the input, the weights and every layer's activation
//!   stay on the device in the returned [`MlpTape`] for backward, which uploads only the
//!   output gradient and reads back the parameter gradient (in `nn::mlp`'s flat layout)
//!   and, when asked, the input gradient;
//! - each forward and each backward is one command buffer and one wait;
//! - every output value is one thread's in-order sum (GEMM over the reduction dimension or
//!   one chunk of it, the chunks in chunk order, the bias gradient over rows), so results
//!   are deterministic run to run;
//! - products are f32 whatever `Mlp::precision` says (no bf16 kernels on the device);
//! - bad shapes are [`GpuError::Invalid`], sizes past the dispatch or buffer limits
//!   [`GpuError::TooLarge`], before any device work. Finiteness is checked by the caller
//!   (`nn::mlp`), which runs the same checks for both places.

use super::{bytes_f32, dispatch_1d, f32_bytes, u32_bytes, GpuContext, GpuError};
use crate::nn::{HiddenActivation, Mlp};

const GEMM: &str = include_str!("shaders/mlp_gemm.wgsl");
const SUM_CHUNKS: &str = include_str!("shaders/mlp_sum_chunks.wgsl");

/// Rows per chunk of the weight gradient's split reduction (`X^T dZ` sums over every row
/// of the batch): each chunk is its own set of workgroups, the chunks are added in order
/// afterwards. Fixed, so the sums' order does not depend on the device.
pub const WEIGHT_GRADIENT_CHUNK_ROWS: usize = 256;
const POINTWISE: &str = include_str!("shaders/mlp_pointwise.wgsl");
const COLSUM: &str = include_str!("shaders/mlp_colsum.wgsl");

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

/// Compiled pipelines for the device MLP on one device.
pub struct GpuMlp {
    ctx: GpuContext,
    gemm: wgpu::ComputePipeline,
    sum_chunks: wgpu::ComputePipeline,
    pointwise: wgpu::ComputePipeline,
    colsum: wgpu::ComputePipeline,
}

impl std::fmt::Debug for GpuMlp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuMlp({})", self.ctx.describe())
    }
}

/// What a device forward keeps for its backward: the input, the weights it used and every
/// layer's output (hidden activations after the activation, then the sigmoid output),
/// all device buffers. Empty (no buffers) for zero rows.
pub struct MlpTape {
    rows: usize,
    widths: Vec<usize>,
    hidden: HiddenActivation,
    input: Option<wgpu::Buffer>,
    weights: Vec<wgpu::Buffer>,
    biases: Vec<wgpu::Buffer>,
    activations: Vec<wgpu::Buffer>,
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

impl GpuMlp {
    pub fn new(ctx: GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            gemm: ctx.pipeline("mlp gemm", GEMM)?,
            sum_chunks: ctx.pipeline("mlp sum chunks", SUM_CHUNKS)?,
            pointwise: ctx.pipeline("mlp pointwise", POINTWISE)?,
            colsum: ctx.pipeline("mlp colsum", COLSUM)?,
            ctx,
        })
    }

    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    fn check_sizes(&self, mlp: &Mlp, rows: usize) -> Result<(), GpuError> {
        let widest = mlp.widths().iter().copied().max().unwrap_or(0);
        let max = u32::MAX as usize / 4;
        if rows.div_ceil(16) > 65535
            || widest.div_ceil(16) > 65535
            || rows.saturating_mul(widest) > max
            || widest.saturating_mul(widest) > max
        {
            return Err(GpuError::TooLarge(format!(
                "MLP of {rows} rows and widths {:?}",
                mlp.widths()
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

    /// Records `C = op(A) op(B)` (m x n) into `pass` (see `gpu::gemm` for the strides),
    /// as `k.div_ceil(k_chunk)` partial products one after another in `c` (one when
    /// `k_chunk >= k`).
    #[allow(clippy::too_many_arguments)]
    fn gemm(
        &self,
        pass: &mut wgpu::ComputePass,
        op: super::GemmOp,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        c: &wgpu::Buffer,
        m: usize,
        k: usize,
        n: usize,
        k_chunk: usize,
    ) {
        let (a_rs, a_cs, b_rs, b_cs) = match op {
            super::GemmOp::AB => (k, 1, n, 1),
            super::GemmOp::AtB => (1, m, n, 1),
            super::GemmOp::ABt => (k, 1, 1, k),
        };
        let params = self.ctx.uniform_init(
            "mlp gemm params",
            &u32_bytes(&[
                m as u32,
                n as u32,
                k as u32,
                k_chunk as u32,
                a_rs as u32,
                a_cs as u32,
                b_rs as u32,
                b_cs as u32,
            ]),
        );
        let bind = self.ctx.bind_group(&self.gemm, &[&params, a, b, c]);
        pass.set_pipeline(&self.gemm);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(
            n.div_ceil(16) as u32,
            m.div_ceil(16) as u32,
            k.div_ceil(k_chunk) as u32,
        );
    }

    fn pointwise(
        &self,
        pass: &mut wgpu::ComputePass,
        op: Pointwise,
        x: &wgpu::Buffer,
        aux: &wgpu::Buffer,
        count: usize,
        n: usize,
    ) {
        let mut data = u32_bytes(&[count as u32, n as u32, op as u32]);
        data.extend_from_slice(&crate::nn::mlp::LEAKY_SLOPE.to_le_bytes());
        let params = self.ctx.uniform_init("mlp pointwise params", &data);
        let bind = self.ctx.bind_group(&self.pointwise, &[&params, x, aux]);
        dispatch_1d(pass, &self.pointwise, &bind, count as u64);
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
        self.check_sizes(mlp, rows)?;
        let mut tape = MlpTape {
            rows,
            widths: widths.clone(),
            hidden: mlp.hidden_activation(),
            input: None,
            weights: Vec::new(),
            biases: Vec::new(),
            activations: Vec::new(),
        };
        if rows == 0 {
            return Ok((Vec::new(), tape));
        }
        let params = mlp.params();
        let layers = mlp.num_layers();
        let x = self.upload("mlp input", input)?;
        for l in 0..layers {
            tape.weights
                .push(self.upload("mlp W", &params[mlp.weight_range(l)])?);
            tape.biases
                .push(self.upload("mlp b", &params[mlp.bias_range(l)])?);
            tape.activations.push(
                self.ctx
                    .storage("mlp activation", (rows * widths[l + 1] * 4) as u64)?,
            );
        }
        let mut encoder = self.ctx.encoder("mlp forward");
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            for l in 0..layers {
                let (n_in, n_out) = (widths[l], widths[l + 1]);
                let layer_input = if l == 0 { &x } else { &tape.activations[l - 1] };
                let out = &tape.activations[l];
                self.gemm(
                    &mut pass,
                    super::GemmOp::AB,
                    layer_input,
                    &tape.weights[l],
                    out,
                    rows,
                    n_in,
                    n_out,
                    n_in,
                );
                let op = if l + 1 == layers {
                    Pointwise::BiasSigmoid
                } else {
                    match tape.hidden {
                        HiddenActivation::Relu => Pointwise::BiasRelu,
                        HiddenActivation::LeakyRelu => Pointwise::BiasLeakyRelu,
                    }
                };
                self.pointwise(&mut pass, op, out, &tape.biases[l], rows * n_out, n_out);
            }
        }
        let n_out = widths[layers];
        let back = self.ctx.read_back(
            encoder,
            &[(&tape.activations[layers - 1], (rows * n_out * 4) as u64)],
        )?;
        tape.input = Some(x);
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
        let layers = widths.len() - 1;
        let n_out = widths[layers];
        if d_output.len() != rows * n_out {
            return Err(GpuError::Invalid(format!(
                "MLP output gradient: expected {} values, got {}",
                rows * n_out,
                d_output.len()
            )));
        }
        // The flat layout of nn::mlp: per layer W (in x out) then b (out).
        let mut starts = vec![0usize];
        for p in widths.windows(2) {
            starts.push(starts[starts.len() - 1] + p[0] * p[1] + p[1]);
        }
        let mut params = vec![0.0f32; starts[layers]];
        let Some(x) = tape.input.as_ref().filter(|_| rows > 0) else {
            let input = want_input_gradient.then(Vec::new);
            return Ok(MlpGradients { params, input });
        };
        let mut dz = self.upload("mlp dZ", d_output)?;
        let mut d_weights = Vec::with_capacity(layers);
        let mut d_biases = Vec::with_capacity(layers);
        let mut d_input = None;
        let mut encoder = self.ctx.encoder("mlp backward");
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            self.pointwise(
                &mut pass,
                Pointwise::SigmoidBackward,
                &dz,
                &tape.activations[layers - 1],
                rows * n_out,
                n_out,
            );
            for l in (0..layers).rev() {
                let (n_in, n_out) = (widths[l], widths[l + 1]);
                let layer_input = if l == 0 { x } else { &tape.activations[l - 1] };
                let d_w = self.ctx.storage("mlp dW", (n_in * n_out * 4) as u64)?;
                let chunks = rows.div_ceil(WEIGHT_GRADIENT_CHUNK_ROWS);
                let partials = if chunks > 1 {
                    let bytes = (chunks * n_in * n_out * 4) as u64;
                    self.ctx.storage("mlp dW chunks", bytes)?
                } else {
                    d_w.clone()
                };
                self.gemm(
                    &mut pass,
                    super::GemmOp::AtB,
                    layer_input,
                    &dz,
                    &partials,
                    n_in,
                    rows,
                    n_out,
                    WEIGHT_GRADIENT_CHUNK_ROWS,
                );
                if chunks > 1 {
                    let count = n_in * n_out;
                    let params = self.ctx.uniform_init(
                        "mlp sum chunks params",
                        &u32_bytes(&[count as u32, chunks as u32, 0, 0]),
                    );
                    let bind = self
                        .ctx
                        .bind_group(&self.sum_chunks, &[&params, &partials, &d_w]);
                    dispatch_1d(&mut pass, &self.sum_chunks, &bind, count as u64);
                }
                let d_b = self.ctx.storage("mlp db", (n_out * 4) as u64)?;
                let colsum = self.ctx.uniform_init(
                    "mlp colsum params",
                    &u32_bytes(&[rows as u32, n_out as u32, 0, 0]),
                );
                let bind = self.ctx.bind_group(&self.colsum, &[&colsum, &dz, &d_b]);
                pass.set_pipeline(&self.colsum);
                pass.set_bind_group(0, &bind, &[]);
                pass.dispatch_workgroups(n_out.div_ceil(64) as u32, 1, 1);
                d_weights.push(d_w);
                d_biases.push(d_b);
                if l == 0 && !want_input_gradient {
                    continue;
                }
                let d_prev = self.ctx.storage("mlp dX", (rows * n_in * 4) as u64)?;
                self.gemm(
                    &mut pass,
                    super::GemmOp::ABt,
                    &dz,
                    &tape.weights[l],
                    &d_prev,
                    rows,
                    n_out,
                    n_in,
                    n_out,
                );
                if l > 0 {
                    let op = match tape.hidden {
                        HiddenActivation::Relu => Pointwise::ReluBackward,
                        HiddenActivation::LeakyRelu => Pointwise::LeakyReluBackward,
                    };
                    self.pointwise(
                        &mut pass,
                        op,
                        &d_prev,
                        &tape.activations[l - 1],
                        rows * n_in,
                        n_in,
                    );
                    dz = d_prev;
                } else {
                    d_input = Some(d_prev);
                }
            }
        }
        // Gradients were pushed last layer first.
        d_weights.reverse();
        d_biases.reverse();
        let mut ranges: Vec<(&wgpu::Buffer, u64)> = Vec::with_capacity(2 * layers + 1);
        for l in 0..layers {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            ranges.push((&d_weights[l], (n_in * n_out * 4) as u64));
            ranges.push((&d_biases[l], (n_out * 4) as u64));
        }
        if let Some(d) = &d_input {
            ranges.push((d, (rows * widths[0] * 4) as u64));
        }
        let back = self.ctx.read_back(encoder, &ranges)?;
        for l in 0..layers {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            let w_at = starts[l];
            params[w_at..w_at + n_in * n_out].copy_from_slice(&bytes_f32(&back[2 * l]));
            params[w_at + n_in * n_out..starts[l + 1]]
                .copy_from_slice(&bytes_f32(&back[2 * l + 1]));
        }
        let input = d_input.map(|_| bytes_f32(&back[2 * layers]));
        Ok(MlpGradients { params, input })
    }
}
