//! A dense MLP with a flat parameter vector, batched forward and analytic backward.
//!
//! Shape: `widths = [in, h_1, ..., h_{L-1}, out]` gives `L` affine layers; every layer but
//! the last is followed by the hidden activation (ReLU or LeakyReLU with slope
//! [`LEAKY_SLOPE`]), the last by a sigmoid.
//!
//! Parameter layout (one flat `Vec<f32>`, so an Adam optimiser treats it as one group):
//! layer after layer, each as its weight matrix then its bias,
//! `[W_0 (in x h_1, row-major), b_0 (h_1), W_1 (h_1 x h_2), b_1, ..., W_{L-1}, b_{L-1}]`.
//! `W_l[i * out_l + j]` connects input `i` to output `j`, so a layer is `Y = X W + b` on
//! row-major batches (this is the transpose of PyTorch's `nn.Linear.weight`).
//!
//! Batches are row-major `rows x width`. Work is split into fixed blocks of
//! [`BLOCK_ROWS`] rows, processed in parallel with rayon; each block runs single-threaded
//! GEMMs and the per-block weight gradients are summed in block order. Block boundaries do
//! not depend on the thread count, so results are bit-identical on any number of threads.
//!
//! Memory: [`TapeMode::Cache`] keeps every hidden activation (`rows * sum(hidden widths)`
//! floats) from forward to backward; [`TapeMode::Recompute`] keeps only the output and
//! recomputes a block's hidden activations inside backward (one extra forward, but peak
//! memory is a few blocks instead of the whole batch).
//!
//! Precision: f32 products by default; [`Mlp::set_precision`] switches every product of
//! forward and backward to bfloat16 inputs with f32 accumulation (`bf16.rs`), checked
//! against the CPU when set. Bias, activations and the block-order sums stay f32.
//!
//! Errors instead of panics: every size is checked, inputs, parameters and upstream
//! gradients must be finite, and a non-finite result is reported, never returned.

use std::cell::RefCell;
use std::ops::Range;

use rayon::prelude::*;

use super::error::{check_finite, check_len, NnError};
use super::matmul::{MatmulPrecision, Products};
use crate::rng::SplitMix64;

/// Negative-side slope of LeakyReLU (PyTorch's default; the paper does not give one).
pub const LEAKY_SLOPE: f32 = 0.01;

/// Rows per parallel block. Fixed, so results do not depend on the thread count.
pub const BLOCK_ROWS: usize = 2048;

/// Blocks whose weight-gradient partials are held at once in backward.
const BLOCKS_PER_WAVE: usize = 8;

thread_local! {
    /// Output-gradient buffers of `Mlp::backward_block` (this layer's dZ and the previous
    /// one's), kept per thread: fresh ones cost page faults on every block (~10 % of a
    /// backward). Contents never carry over (each value is written before it is read).
    static GRADIENT_SCRATCH: RefCell<(Vec<f32>, Vec<f32>)> =
        const { RefCell::new((Vec::new(), Vec::new())) };
}

/// What the forward of one block of rows left for its backward: the block's input
/// (`rows x in`), its hidden activations (every hidden layer's `rows x width`, in layer
/// order) and its output (`rows x out`).
#[derive(Clone, Copy)]
pub(crate) struct BlockTape<'a> {
    pub(crate) x: &'a [f32],
    pub(crate) rows: usize,
    pub(crate) hidden: &'a [f32],
    pub(crate) y: &'a [f32],
}

/// Activation after every hidden layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HiddenActivation {
    Relu,
    /// `max(z, LEAKY_SLOPE * z)`.
    LeakyRelu,
}

impl HiddenActivation {
    #[inline]
    fn apply(self, z: f32) -> f32 {
        match self {
            HiddenActivation::Relu => z.max(0.0),
            HiddenActivation::LeakyRelu => {
                if z > 0.0 {
                    z
                } else {
                    LEAKY_SLOPE * z
                }
            }
        }
    }

    /// Derivative from the post-activation value (the sign of `a` equals the sign of `z`).
    #[inline]
    fn slope_from_output(self, a: f32) -> f32 {
        match self {
            HiddenActivation::Relu => {
                if a > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            HiddenActivation::LeakyRelu => {
                if a > 0.0 {
                    1.0
                } else {
                    LEAKY_SLOPE
                }
            }
        }
    }

    /// Gain of Kaiming initialisation: `sqrt(2 / (1 + slope^2))`.
    fn kaiming_gain(self) -> f32 {
        match self {
            HiddenActivation::Relu => 2.0f32.sqrt(),
            HiddenActivation::LeakyRelu => (2.0 / (1.0 + LEAKY_SLOPE * LEAKY_SLOPE)).sqrt(),
        }
    }
}

/// Weight initialisation scheme (all draws from one seeded SplitMix64, in parameter order).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Init {
    /// PyTorch's `nn.Linear` default: weights and biases `U(-1/sqrt(fan_in), 1/sqrt(fan_in))`.
    TorchLinearDefault,
    /// Kaiming/He uniform for the hidden activation: weights
    /// `U(-gain sqrt(3/fan_in), +gain sqrt(3/fan_in))`, gain 1 for the sigmoid output layer,
    /// zero biases.
    KaimingUniform,
}

/// Whether forward keeps hidden activations for backward or backward recomputes them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TapeMode {
    Cache,
    Recompute,
}

/// Result of [`Mlp::forward_train`]: the output and what backward needs.
#[derive(Clone, Debug, Default)]
pub struct MlpForward {
    rows: usize,
    /// Sigmoid outputs, row-major `rows x out`.
    pub output: Vec<f32>,
    /// Per block: that block's hidden activations, layer after layer (`Cache` mode only).
    hidden_by_block: Option<Vec<Vec<f32>>>,
}

impl MlpForward {
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Floats held for backward besides the output (0 in `Recompute` mode).
    pub fn tape_len(&self) -> usize {
        self.hidden_by_block
            .as_ref()
            .map_or(0, |blocks| blocks.iter().map(Vec::len).sum())
    }
}

/// A dense network `in -> hidden ... -> out` with sigmoid output. See the module docs.
#[derive(Clone, Debug, PartialEq)]
pub struct Mlp {
    widths: Vec<usize>,
    hidden: HiddenActivation,
    params: Vec<f32>,
    /// Start of each layer's weight matrix in `params`; one extra entry for the total.
    layer_starts: Vec<usize>,
    /// Arithmetic of every matrix product (f32 unless [`Mlp::set_precision`] says else).
    products: Products,
}

fn layer_starts_for(widths: &[usize]) -> Vec<usize> {
    let mut starts = Vec::with_capacity(widths.len());
    let mut at = 0;
    starts.push(0);
    for pair in widths.windows(2) {
        at += pair[0] * pair[1] + pair[1];
        starts.push(at);
    }
    starts
}

/// Largest weight count of one network (256 MiB of f32): a size from a file or a
/// configuration beyond it is an error, not an allocation.
pub const MAX_MLP_PARAMS: usize = 1 << 26;

/// Weights and biases of a network of `widths`, with checked arithmetic; an error for
/// fewer than two widths, a zero width, or more than [`MAX_MLP_PARAMS`] weights.
pub fn param_count(widths: &[usize]) -> Result<usize, NnError> {
    validate_widths(widths)?;
    let total = widths.windows(2).try_fold(0usize, |total, pair| {
        pair[0]
            .checked_mul(pair[1])
            .and_then(|w| w.checked_add(pair[1]))
            .and_then(|layer| total.checked_add(layer))
    });
    match total {
        Some(n) if n <= MAX_MLP_PARAMS => Ok(n),
        _ => Err(NnError::Config(format!(
            "an MLP of widths {widths:?} has more than {MAX_MLP_PARAMS} weights"
        ))),
    }
}

fn validate_widths(widths: &[usize]) -> Result<(), NnError> {
    if widths.len() < 2 {
        return Err(NnError::Config(format!(
            "an MLP needs at least input and output widths, got {widths:?}"
        )));
    }
    if widths.contains(&0) {
        return Err(NnError::Config(format!(
            "MLP widths must be positive, got {widths:?}"
        )));
    }
    Ok(())
}

impl Mlp {
    /// A freshly initialised network. `widths = [in, hidden..., out]`.
    pub fn new(
        widths: &[usize],
        hidden: HiddenActivation,
        init: Init,
        seed: u64,
    ) -> Result<Self, NnError> {
        // Bounds the sizes first: `layer_starts_for` cannot overflow after this.
        param_count(widths)?;
        let layer_starts = layer_starts_for(widths);
        let mut params = vec![0.0f32; *layer_starts.last().unwrap_or(&0)];
        let mut rng = SplitMix64::new(seed);
        let layers = widths.len() - 1;
        for l in 0..layers {
            let fan_in = widths[l] as f32;
            let is_output = l + 1 == layers;
            let (w_bound, b_bound) = match init {
                Init::TorchLinearDefault => (1.0 / fan_in.sqrt(), 1.0 / fan_in.sqrt()),
                Init::KaimingUniform => {
                    let gain = if is_output {
                        1.0
                    } else {
                        hidden.kaiming_gain()
                    };
                    (gain * (3.0 / fan_in).sqrt(), 0.0)
                }
            };
            let start = layer_starts[l];
            let w_len = widths[l] * widths[l + 1];
            for w in &mut params[start..start + w_len] {
                *w = rng.uniform_symmetric(w_bound);
            }
            for b in &mut params[start + w_len..layer_starts[l + 1]] {
                *b = if b_bound > 0.0 {
                    rng.uniform_symmetric(b_bound)
                } else {
                    0.0
                };
            }
        }
        Ok(Self {
            widths: widths.to_vec(),
            hidden,
            params,
            layer_starts,
            products: Products::default(),
        })
    }

    /// A network with given parameters (checkpoint load). The layout is the module's.
    pub fn from_params(
        widths: &[usize],
        hidden: HiddenActivation,
        params: Vec<f32>,
    ) -> Result<Self, NnError> {
        // Bounds the sizes first: `layer_starts_for` cannot overflow after this.
        param_count(widths)?;
        let layer_starts = layer_starts_for(widths);
        check_len(
            "MLP parameters",
            params.len(),
            *layer_starts.last().unwrap_or(&0),
        )?;
        check_finite("MLP parameters", &params)?;
        Ok(Self {
            widths: widths.to_vec(),
            hidden,
            params,
            layer_starts,
            products: Products::default(),
        })
    }

    /// Runs every later product in `precision`. An error (and no change) when this CPU
    /// cannot: `Bf16` needs AMX-BF16 or AVX-512 BF16.
    pub fn set_precision(&mut self, precision: MatmulPrecision) -> Result<(), NnError> {
        self.products = Products::new(precision)?;
        Ok(())
    }

    /// Runs every later product on `products` (benchmarks compare the f32 kernels; a
    /// `Products` value exists only for what this CPU runs).
    pub fn set_products(&mut self, products: Products) {
        self.products = products;
    }

    pub fn precision(&self) -> MatmulPrecision {
        self.products.precision()
    }

    /// The products this network runs (benchmarks time the same kernels on its shapes).
    pub fn products(&self) -> Products {
        self.products
    }

    pub fn widths(&self) -> &[usize] {
        &self.widths
    }

    pub fn hidden_activation(&self) -> HiddenActivation {
        self.hidden
    }

    pub fn input_width(&self) -> usize {
        self.widths[0]
    }

    pub fn output_width(&self) -> usize {
        self.widths[self.widths.len() - 1]
    }

    pub fn num_layers(&self) -> usize {
        self.widths.len() - 1
    }

    pub fn num_params(&self) -> usize {
        self.params.len()
    }

    /// The flat parameter vector (layout in the module docs).
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Mutable parameters for the optimiser. Forward rejects non-finite values written here.
    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }

    /// Range of layer `l`'s weight matrix (`widths[l] x widths[l + 1]`, row-major) in `params`.
    pub fn weight_range(&self, l: usize) -> Range<usize> {
        let start = self.layer_starts[l];
        start..start + self.widths[l] * self.widths[l + 1]
    }

    /// Range of layer `l`'s bias in `params`.
    pub fn bias_range(&self, l: usize) -> Range<usize> {
        self.weight_range(l).end..self.layer_starts[l + 1]
    }

    /// Multiply-adds per row of one forward pass (for throughput reports).
    pub fn flops_per_row_forward(&self) -> usize {
        self.widths.windows(2).map(|p| 2 * p[0] * p[1]).sum()
    }

    fn hidden_floats_per_row(&self) -> usize {
        self.widths[1..self.widths.len() - 1].iter().sum()
    }

    fn check_input(&self, input: &[f32], rows: usize) -> Result<(), NnError> {
        check_len("MLP input", input.len(), rows * self.input_width())?;
        check_finite("MLP input", input)?;
        check_finite("MLP parameters", &self.params)
    }

    /// Forward for one block: writes the output and, into `hidden`, the hidden activations
    /// layer after layer (`rows * hidden_floats_per_row()` floats).
    fn forward_block(&self, x: &[f32], rows: usize, hidden: &mut [f32], out: &mut [f32]) {
        let layers = self.num_layers();
        let mut hidden_at = 0;
        for l in 0..layers {
            let (n_in, n_out) = (self.widths[l], self.widths[l + 1]);
            let w = &self.params[self.weight_range(l)];
            let b = &self.params[self.bias_range(l)];
            let (input, dst): (&[f32], &mut [f32]) = if l == 0 && layers == 1 {
                (x, &mut *out)
            } else if l == 0 {
                (x, &mut hidden[..rows * n_out])
            } else {
                let prev = rows * n_in;
                let (done, rest) = hidden.split_at_mut(hidden_at);
                let input = &done[hidden_at - prev..];
                if l + 1 == layers {
                    (input, &mut *out)
                } else {
                    (input, &mut rest[..rows * n_out])
                }
            };
            self.products
                .matmul(input, w, dst, rows, n_in, n_out, false);
            // Bias and activation fused in one pass over the GEMM result.
            if l + 1 == layers {
                for row in dst.chunks_exact_mut(n_out) {
                    for (v, &bj) in row.iter_mut().zip(b) {
                        *v = sigmoid(*v + bj);
                    }
                }
            } else {
                let act = self.hidden;
                for row in dst.chunks_exact_mut(n_out) {
                    for (v, &bj) in row.iter_mut().zip(b) {
                        *v = act.apply(*v + bj);
                    }
                }
                hidden_at += rows * n_out;
            }
        }
    }

    fn block_ranges(rows: usize) -> impl Iterator<Item = Range<usize>> + Clone {
        (0..rows.div_ceil(BLOCK_ROWS))
            .map(move |b| b * BLOCK_ROWS..((b + 1) * BLOCK_ROWS).min(rows))
    }

    /// Forward into `dest`, reusing its buffers (their capacity survives from call to call,
    /// which spares the page faults of fresh tape memory every training step).
    fn forward_into(
        &self,
        input: &[f32],
        rows: usize,
        keep_hidden: bool,
        dest: &mut MlpForward,
    ) -> Result<(), NnError> {
        // Invalid until the forward succeeds: a failed call leaves an empty result.
        dest.rows = 0;
        dest.output.clear();
        let mut blocks = dest.hidden_by_block.take().unwrap_or_default();
        self.check_input(input, rows)?;
        let (n_in, n_out) = (self.input_width(), self.output_width());
        let hidden_per_row = self.hidden_floats_per_row();
        dest.output.resize(rows * n_out, 0.0);
        let run_block = |b: usize, out_block: &mut [f32], hidden: &mut Vec<f32>| {
            let block_rows = out_block.len() / n_out;
            let start = b * BLOCK_ROWS;
            let x = &input[start * n_in..(start + block_rows) * n_in];
            hidden.clear();
            hidden.resize(block_rows * hidden_per_row, 0.0);
            self.forward_block(x, block_rows, hidden, out_block);
        };
        let out_blocks = dest.output.par_chunks_mut(BLOCK_ROWS * n_out).enumerate();
        if keep_hidden {
            blocks.resize_with(rows.div_ceil(BLOCK_ROWS), Vec::new);
            out_blocks
                .zip(blocks.par_iter_mut())
                .for_each(|((b, out_block), hidden)| run_block(b, out_block, hidden));
        } else {
            out_blocks.for_each(|(b, out_block)| run_block(b, out_block, &mut Vec::new()));
        }
        if let Err(e) = check_finite("MLP output", &dest.output) {
            dest.output.clear();
            return Err(e);
        }
        dest.rows = rows;
        dest.hidden_by_block = keep_hidden.then_some(blocks);
        Ok(())
    }

    /// Inference: sigmoid outputs, row-major `rows x out`. Keeps nothing for backward.
    pub fn forward(&self, input: &[f32], rows: usize) -> Result<Vec<f32>, NnError> {
        let mut dest = MlpForward::default();
        self.forward_into(input, rows, false, &mut dest)?;
        Ok(dest.output)
    }

    /// Forward for training; `mode` decides what is kept for [`Mlp::backward`].
    pub fn forward_train(
        &self,
        input: &[f32],
        rows: usize,
        mode: TapeMode,
    ) -> Result<MlpForward, NnError> {
        let mut dest = MlpForward::default();
        self.forward_into(input, rows, mode == TapeMode::Cache, &mut dest)?;
        Ok(dest)
    }

    /// [`Mlp::forward_train`] into a previous result, reusing its memory (the training loop
    /// keeps one `MlpForward` per network). Bit-identical to `forward_train`. On error
    /// `dest` is left empty (zero rows).
    pub fn forward_train_into(
        &self,
        input: &[f32],
        rows: usize,
        mode: TapeMode,
        dest: &mut MlpForward,
    ) -> Result<(), NnError> {
        self.forward_into(input, rows, mode == TapeMode::Cache, dest)
    }

    /// Backward of one block: adds the weight gradients into `d_params` (zeroed by the
    /// caller) and writes the input gradient into `d_x` when given.
    fn backward_block(
        &self,
        tape: &BlockTape,
        d_y: &[f32],
        d_params: &mut [f32],
        d_x: Option<&mut [f32]>,
    ) {
        GRADIENT_SCRATCH.with(|scratch| {
            let (d_z, d_prev) = &mut *scratch.borrow_mut();
            self.backward_block_in(tape, d_y, d_params, d_x, d_z, d_prev);
        });
    }

    /// [`Mlp::backward_block`] with the layers' output gradients in `d_z` and `d_prev`
    /// (any contents; every value read is written first).
    fn backward_block_in(
        &self,
        tape: &BlockTape,
        d_y: &[f32],
        d_params: &mut [f32],
        d_x: Option<&mut [f32]>,
        d_z: &mut Vec<f32>,
        d_prev: &mut Vec<f32>,
    ) {
        let &BlockTape { x, rows, hidden, y } = tape;
        let layers = self.num_layers();
        // dZ of the output layer through the sigmoid: y (1 - y) dY.
        d_z.clear();
        d_z.extend(y.iter().zip(d_y).map(|(&v, &g)| v * (1.0 - v) * g));
        let mut hidden_end = hidden.len();
        let mut d_x = d_x;
        for l in (0..layers).rev() {
            let (n_in, n_out) = (self.widths[l], self.widths[l + 1]);
            let layer_input: &[f32] = if l == 0 {
                x
            } else {
                &hidden[hidden_end - rows * n_in..hidden_end]
            };
            let w_range = self.weight_range(l);
            let b_range = self.bias_range(l);
            self.products.matmul_at_b(
                layer_input,
                d_z,
                &mut d_params[w_range.clone()],
                rows,
                n_in,
                n_out,
                true,
            );
            let d_b = &mut d_params[b_range];
            for row in d_z.chunks_exact(n_out) {
                for (acc, &g) in d_b.iter_mut().zip(row) {
                    *acc += g;
                }
            }
            let w = &self.params[w_range];
            if l > 0 {
                // Overwritten by the product (no accumulation), so stale values are fine.
                d_prev.resize(rows * n_in, 0.0);
                self.products
                    .matmul_a_bt(d_z, w, d_prev, rows, n_out, n_in, false);
                let act = self.hidden;
                for (g, &a) in d_prev.iter_mut().zip(layer_input) {
                    *g *= act.slope_from_output(a);
                }
                std::mem::swap(d_z, d_prev);
                hidden_end -= rows * n_in;
            } else if let Some(d_x) = d_x.take() {
                self.products
                    .matmul_a_bt(d_z, w, d_x, rows, n_out, n_in, false);
            }
        }
    }

    /// Backward of [`Mlp::forward_train`]. `input` must be the same batch and the parameters
    /// must not have changed since that forward (take the optimiser step after backward).
    /// Adds the parameter gradient into `d_params` (length `num_params()`); overwrites
    /// `d_input` (row-major `rows x in`) when given. On error `d_params` is untouched and
    /// `d_input` is either untouched (bad shapes or inputs) or zeroed (non-finite result).
    pub fn backward(
        &self,
        input: &[f32],
        forward: &MlpForward,
        d_output: &[f32],
        d_params: &mut [f32],
        d_input: Option<&mut [f32]>,
    ) -> Result<(), NnError> {
        let rows = forward.rows;
        let (n_in, n_out) = (self.input_width(), self.output_width());
        check_len("MLP input", input.len(), rows * n_in)?;
        check_len("MLP forward output", forward.output.len(), rows * n_out)?;
        check_len("MLP output gradient", d_output.len(), rows * n_out)?;
        check_len("MLP parameter gradient", d_params.len(), self.num_params())?;
        if let Some(d_input) = &d_input {
            check_len("MLP input gradient", d_input.len(), rows * n_in)?;
        }
        check_finite("MLP output gradient", d_output)?;
        check_finite("MLP parameters", &self.params)?;
        let hidden_per_row = self.hidden_floats_per_row();
        if let Some(blocks) = &forward.hidden_by_block {
            let want = rows.div_ceil(BLOCK_ROWS);
            check_len("MLP tape blocks", blocks.len(), want)?;
            for (block, range) in blocks.iter().zip(Self::block_ranges(rows)) {
                check_len("MLP tape", block.len(), range.len() * hidden_per_row)?;
            }
        } else {
            // Recompute from the input: it must be valid like in forward.
            check_finite("MLP input", input)?;
        }

        let mut d_input = d_input;
        let mut total = vec![0.0f32; self.num_params()];
        let mut d_input_rest: Option<&mut [f32]> = d_input.as_deref_mut();
        let ranges: Vec<Range<usize>> = Self::block_ranges(rows).collect();
        for (wave_index, wave) in ranges.chunks(BLOCKS_PER_WAVE).enumerate() {
            let wave_rows = wave.iter().map(Range::len).sum::<usize>();
            let d_input_wave: Option<&mut [f32]> = match d_input_rest.take() {
                Some(rest) => {
                    let (now, later) = rest.split_at_mut(wave_rows * n_in);
                    d_input_rest = Some(later);
                    Some(now)
                }
                None => None,
            };
            let mut d_input_blocks: Vec<Option<&mut [f32]>> = match d_input_wave {
                Some(d) => d.chunks_mut(BLOCK_ROWS * n_in).map(Some).collect(),
                None => (0..wave.len()).map(|_| None).collect(),
            };
            let partials: Vec<Vec<f32>> = wave
                .par_iter()
                .zip(d_input_blocks.par_iter_mut())
                .enumerate()
                .map(|(i, (range, d_x))| {
                    let block_index = wave_index * BLOCKS_PER_WAVE + i;
                    let block_rows = range.len();
                    let x = &input[range.start * n_in..range.end * n_in];
                    let y = &forward.output[range.start * n_out..range.end * n_out];
                    let d_y = &d_output[range.start * n_out..range.end * n_out];
                    let recomputed;
                    let hidden: &[f32] = match &forward.hidden_by_block {
                        Some(blocks) => &blocks[block_index],
                        None => {
                            let mut h = vec![0.0f32; block_rows * hidden_per_row];
                            let mut y_again = vec![0.0f32; block_rows * n_out];
                            self.forward_block(x, block_rows, &mut h, &mut y_again);
                            recomputed = h;
                            &recomputed
                        }
                    };
                    let mut partial = vec![0.0f32; self.num_params()];
                    let tape = BlockTape {
                        x,
                        rows: block_rows,
                        hidden,
                        y,
                    };
                    self.backward_block(&tape, d_y, &mut partial, d_x.take());
                    partial
                })
                .collect();
            // Fixed block order: independent of how rayon scheduled the wave.
            for partial in &partials {
                for (t, p) in total.iter_mut().zip(partial) {
                    *t += p;
                }
            }
        }
        let finite = check_finite("MLP parameter gradient", &total).and_then(|()| {
            d_input
                .as_deref()
                .map_or(Ok(()), |d| check_finite("MLP input gradient", d))
        });
        if let Err(e) = finite {
            // Never hand back a partial or non-finite input gradient.
            if let Some(d) = d_input {
                d.fill(0.0);
            }
            return Err(e);
        }
        for (d, t) in d_params.iter_mut().zip(&total) {
            *d += t;
        }
        Ok(())
    }
}

#[inline]
fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + (-z).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative distance `|a - b| / |b|` over whole vectors.
    fn rel(a: &[f32], b: &[f32]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
        let den: f64 = b.iter().map(|y| (*y as f64).powi(2)).sum();
        (num / den).sqrt()
    }

    #[test]
    fn bf16_forward_and_backward_stay_near_f32() {
        let mut mlp = Mlp::new(
            &[37, 64, 64, 3],
            HiddenActivation::Relu,
            Init::KaimingUniform,
            4,
        )
        .unwrap();
        assert_eq!(mlp.precision(), MatmulPrecision::F32);
        if let Err(e) = mlp.set_precision(MatmulPrecision::Bf16) {
            assert_eq!(mlp.precision(), MatmulPrecision::F32, "unchanged on error");
            crate::machine::skip_unless_required("GS_REQUIRE_BF16", &e.to_string());
            return;
        }
        // Rows over two blocks, so the block-order reduction runs too.
        let rows = BLOCK_ROWS + 301;
        let mut rng = SplitMix64::new(8);
        let input: Vec<f32> = (0..rows * 37).map(|_| rng.normal()).collect();
        let d_out: Vec<f32> = (0..rows * 3).map(|_| rng.normal()).collect();
        let run = |mlp: &Mlp| {
            let fwd = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
            let mut d_params = vec![0.0f32; mlp.num_params()];
            let mut d_input = vec![0.0f32; input.len()];
            mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
                .unwrap();
            (fwd.output, d_params, d_input)
        };
        let (y_b, dp_b, dx_b) = run(&mlp);
        mlp.set_precision(MatmulPrecision::F32).unwrap();
        let (y_f, dp_f, dx_f) = run(&mlp);
        // Measured: output 1.6e-3, parameter gradient 2.9e-2, input gradient 5.7e-2. The
        // gradients are this sensitive to 2^-8 rounding whatever the kernel: an f32 run
        // of a [37, 64, 3] net on bf16-rounded inputs alone moves them by 1.2e-2 and
        // 3.3e-2 (each product alone is within 2.4e-3 of f64, see bf16.rs). A wrong
        // layout or a missed product gives O(1) (uncorrelated vectors: ~1.4).
        let (ry, rp, rx) = (rel(&y_b, &y_f), rel(&dp_b, &dp_f), rel(&dx_b, &dx_f));
        eprintln!("bf16 vs f32 relative: output {ry:.2e}, params {rp:.2e}, input {rx:.2e}");
        assert!(ry > 0.0 && ry < 5e-3, "{ry}");
        assert!(rp > 0.0 && rp < 0.1, "{rp}");
        assert!(rx > 0.0 && rx < 0.15, "{rx}");
    }
}
