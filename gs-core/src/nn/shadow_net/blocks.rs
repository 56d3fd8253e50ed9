//! Per-block kernels of Psi's folded training path: one block of `BLOCK_ROWS` rows
//! through the 3 x 32 LeakyReLU layers forward and backward, with per-thread scratch.
//!
//! Invariants: the same arithmetic, in the same order, as `Mlp` on those rows.

use crate::nn::mlp::{BlockTape, Mlp, LEAKY_SLOPE};

/// Sets `v` to `len` values. A vector of another length is replaced by a zeroed one
/// (fresh zero pages, no serial fill); one of the right length keeps its stale contents,
/// which the caller overwrites before reading.
pub(super) fn fresh_len(v: &mut Vec<f32>, len: usize) {
    if v.len() != len {
        *v = vec![0.0f32; len];
    }
}

/// Per-thread buffers of the forward and backward blocks: recomputed activations and the
/// backward's gradients (contents never carry over: every value is
/// written before it is read).
#[derive(Default)]
pub(super) struct BlockScratch {
    pub(super) hidden: Vec<f32>,
    pub(super) d_x: Vec<f32>,
    pub(super) d_z: Vec<f32>,
    pub(super) d_prev: Vec<f32>,
}

thread_local! {
    pub(super) static BLOCK_SCRATCH: std::cell::RefCell<BlockScratch> =
        std::cell::RefCell::new(BlockScratch::default());
}

/// `dst.copy_from_slice(src)` for a few values: the paper's 6-value latent as two
/// register moves instead of a `memmove` call per row.
#[inline(always)]
pub(super) fn copy_short(src: &[f32], dst: &mut [f32]) {
    const PAPER_LATENT: usize = 6;
    if src.len() == PAPER_LATENT && dst.len() == PAPER_LATENT {
        let src: [f32; PAPER_LATENT] = std::array::from_fn(|i| src[i]);
        for (d, s) in dst.iter_mut().zip(src) {
            *d = s;
        }
    } else {
        dst.copy_from_slice(src);
    }
}

/// LeakyReLU as `Mlp` applies it.
#[inline]
pub(super) fn leaky_relu(z: f32) -> f32 {
    if z > 0.0 {
        z
    } else {
        LEAKY_SLOPE * z
    }
}

/// LeakyReLU's derivative from its output, as `Mlp` takes it.
#[inline]
pub(super) fn leaky_slope_from_output(a: f32) -> f32 {
    if a > 0.0 {
        1.0
    } else {
        LEAKY_SLOPE
    }
}

/// `Mlp`'s block forward for a LeakyReLU network (the same products, bias and activation
/// in the same order): output into `out`, hidden activations layer after layer into
/// `hidden`.
pub(super) fn forward_block(
    mlp: &Mlp,
    x: &[f32],
    rows: usize,
    hidden: &mut [f32],
    out: &mut [f32],
) {
    forward_block_layers(mlp, x, rows, hidden, Some(out));
}

/// [`forward_block`]; without `out` only the hidden layers run (a backward's recompute:
/// it has the output already).
pub(super) fn forward_block_layers(
    mlp: &Mlp,
    x: &[f32],
    rows: usize,
    hidden: &mut [f32],
    mut out: Option<&mut [f32]>,
) {
    let widths = mlp.widths();
    let layers = widths.len() - 1;
    let products = mlp.products();
    let params = mlp.params();
    let mut hidden_at = 0;
    for l in 0..layers {
        let (n_in, n_out) = (widths[l], widths[l + 1]);
        let w = &params[mlp.weight_range(l)];
        let b = &params[mlp.bias_range(l)];
        let (done, rest) = hidden.split_at_mut(hidden_at);
        let input: &[f32] = if l == 0 {
            x
        } else {
            &done[hidden_at - rows * n_in..]
        };
        if l + 1 == layers {
            let Some(out) = out.take() else {
                return;
            };
            products.matmul(input, w, out, rows, n_in, n_out, false);
            for row in out.chunks_exact_mut(n_out) {
                for (v, &bj) in row.iter_mut().zip(b) {
                    *v = 1.0 / (1.0 + (-(*v + bj)).exp());
                }
            }
        } else {
            let dst = &mut rest[..rows * n_out];
            products.matmul(input, w, dst, rows, n_in, n_out, false);
            for row in dst.chunks_exact_mut(n_out) {
                for (v, &bj) in row.iter_mut().zip(b) {
                    *v = leaky_relu(*v + bj);
                }
            }
            hidden_at += rows * n_out;
        }
    }
}

/// `Mlp`'s block backward for a LeakyReLU network: adds the weight gradients into
/// `d_params` and writes the input gradient into `d_x` (`rows x in`).
pub(super) fn backward_block(
    mlp: &Mlp,
    tape: &BlockTape,
    d_y: &[f32],
    d_params: &mut [f32],
    d_x: &mut [f32],
    d_z: &mut Vec<f32>,
    d_prev: &mut Vec<f32>,
) {
    let &BlockTape { x, rows, hidden, y } = tape;
    let widths = mlp.widths();
    let layers = widths.len() - 1;
    let products = mlp.products();
    let params = mlp.params();
    d_z.clear();
    d_z.extend(y.iter().zip(d_y).map(|(&v, &g)| v * (1.0 - v) * g));
    let mut hidden_end = rows * widths[1..layers].iter().sum::<usize>();
    for l in (0..layers).rev() {
        let (n_in, n_out) = (widths[l], widths[l + 1]);
        let layer_input: &[f32] = if l == 0 {
            x
        } else {
            &hidden[hidden_end - rows * n_in..hidden_end]
        };
        let w_range = mlp.weight_range(l);
        products.matmul_at_b(
            layer_input,
            d_z,
            &mut d_params[w_range.clone()],
            rows,
            n_in,
            n_out,
            true,
        );
        let d_b = &mut d_params[mlp.bias_range(l)];
        for row in d_z.chunks_exact(n_out) {
            for (acc, &g) in d_b.iter_mut().zip(row) {
                *acc += g;
            }
        }
        let w = &params[w_range];
        if l > 0 {
            d_prev.resize(rows * n_in, 0.0);
            products.matmul_a_bt(d_z, w, d_prev, rows, n_out, n_in, false);
            for (g, &a) in d_prev.iter_mut().zip(layer_input) {
                *g *= leaky_slope_from_output(a);
            }
            std::mem::swap(d_z, d_prev);
            hidden_end -= rows * n_in;
        } else {
            products.matmul_a_bt(d_z, w, d_x, rows, n_out, n_in, false);
        }
    }
}
