//! The training path of Psi on folded rows: the Sun's encoding columns folded into the
//! first layer's bias, rows `[V_i | gamma_L(p_i) | l_i]` assembled block by block while in
//! cache, the forward and backward on them (see the parent module).
//!
//! Invariants: the parameter layout and the function are the full network's (up to f32
//! summation order); results do not depend on the thread count.

use rayon::prelude::*;

use crate::nn::error::{check_finite, check_len, NnError};
use crate::nn::gather::{check_indices, check_rows_finite, rows_of, unit_vector};
use crate::nn::mlp::{BlockTape, Mlp, TapeMode, BLOCK_ROWS};

use super::blocks::{
    backward_block, copy_short, forward_block, forward_block_layers, fresh_len, BlockScratch,
    BLOCK_SCRATCH,
};
use super::{SceneBox, ShadowNet, SHADOW_HIDDEN};

/// Rows per parallel task of the folded input assembly and its gradient scatter (fixed,
/// so nothing depends on the thread count; every row's values are computed alone anyway).
const ROWS_PER_TASK: usize = 512;

/// One batch of Psi's inputs: the listed Gaussians (any order, repeats allowed) and the
/// model's per-Gaussian arrays (`count` Gaussians: `visibility` `count`, `latents`
/// `count x latent_dim`, `means` `count x 3`), the image's Sun direction and the box.
#[derive(Clone, Copy, Debug)]
pub struct ShadowBatch<'a> {
    pub gaussians: &'a [u32],
    pub visibility: &'a [f32],
    pub latents: &'a [f32],
    pub means: &'a [f32],
    pub sun_dir: [f32; 3],
    pub scene_box: &'a SceneBox,
}

impl ShadowNet {
    /// Values per row of the folded input: `[V_i | gamma_L(p_i) | l_i]`, `1 + 6L +
    /// latent_dim` (the Sun's columns are folded into the first layer's bias).
    pub fn folded_input_width(&self) -> usize {
        1 + self.encoding.width(3) + self.latent_dim
    }

    /// Psi for one Sun direction with the Sun's encoding folded into the first layer: the
    /// same function of the folded row as `mlp` of the full row. Its first-layer weights
    /// are the full ones without the Sun's rows, its first bias is
    /// `b_0 + W_sun^T gamma_L(sun)` (summed in f64, rounded once). Outputs differ from
    /// the full network's by float summation order only (f32), or by the bf16 rounding of
    /// the Sun's product, which the fold no longer does (bf16).
    pub fn folded_mlp(&self, sun_dir: [f32; 3]) -> Result<Mlp, NnError> {
        let sun_code = self.sun_code(sun_dir)?;
        let full = &self.mlp;
        let widths = full.widths();
        let h1 = widths[1];
        let enc_width = self.encoding.width(3);
        let mut folded_widths = widths.to_vec();
        folded_widths[0] = self.folded_input_width();
        let w0 = &full.params()[full.weight_range(0)];
        let b0 = &full.params()[full.bias_range(0)];
        let mut params = Vec::with_capacity(full.num_params() - enc_width * h1);
        params.extend_from_slice(&w0[..h1]);
        params.extend_from_slice(&w0[(1 + enc_width) * h1..]);
        params.extend((0..h1).map(|j| {
            let sun: f64 = sun_code
                .iter()
                .enumerate()
                .map(|(i, &code)| code as f64 * w0[(1 + i) * h1 + j] as f64)
                .sum();
            (b0[j] as f64 + sun) as f32
        }));
        params.extend_from_slice(&full.params()[full.bias_range(0).end..]);
        let mut folded = Mlp::from_params(&folded_widths, full.hidden_activation(), params)?;
        folded.set_precision(full.precision())?;
        Ok(folded)
    }

    /// `gamma_L` of the unit Sun direction.
    fn sun_code(&self, sun_dir: [f32; 3]) -> Result<Vec<f32>, NnError> {
        let sun = unit_vector("Sun direction", sun_dir)?;
        let mut code = vec![0.0f32; self.encoding.width(3)];
        self.encoding.encode_unchecked(&sun, &mut code);
        Ok(code)
    }

    /// Adds the gradient of the folded network's parameters (`d_folded`, the layout of
    /// [`ShadowNet::folded_mlp`]) into `d_params` (the full layout): the Sun's rows of the
    /// first layer get `gamma_L(sun) d b_0^T` (the fold's chain rule), the other values
    /// move to their full positions.
    fn add_unfolded_grad(&self, sun_code: &[f32], d_folded: &[f32], d_params: &mut [f32]) {
        let full = &self.mlp;
        let h1 = full.widths()[1];
        let enc_width = self.encoding.width(3);
        let w_range = full.weight_range(0);
        let folded_w_len = self.folded_input_width() * h1;
        let (d_w_folded, rest) = d_folded.split_at(folded_w_len);
        let (d_b0, d_later) = rest.split_at(h1);
        let (d_w0, d_rest) = d_params[w_range.start..].split_at_mut(w_range.len());
        let (d_v, d_tail) = d_w_folded.split_at(h1);
        for (acc, &g) in d_w0[..h1].iter_mut().zip(d_v) {
            *acc += g;
        }
        for (i, &code) in sun_code.iter().enumerate() {
            for (acc, &g) in d_w0[(1 + i) * h1..(2 + i) * h1].iter_mut().zip(d_b0) {
                *acc += code * g;
            }
        }
        for (acc, &g) in d_w0[(1 + enc_width) * h1..].iter_mut().zip(d_tail) {
            *acc += g;
        }
        for (acc, &g) in d_rest.iter_mut().zip(d_b0.iter().chain(d_later)) {
            *acc += g;
        }
    }

    /// Checks a batch against this network: sizes, indices, finite rows of the listed
    /// Gaussians (the error names the Gaussian). Returns the model's Gaussian count.
    fn check_batch(&self, batch: &ShadowBatch) -> Result<usize, NnError> {
        let count = rows_of("shadow latents", batch.latents, self.latent_dim)?;
        check_len("Gaussian means", batch.means.len(), count * 3)?;
        check_len("Sun visibility", batch.visibility.len(), count)?;
        check_indices(batch.gaussians, count)?;
        Ok(count)
    }

    /// Fills `input` (resized to `rows x folded_input_width()`) with the folded rows
    /// `[V_i | gamma_L(p_i) | l_i]` of the listed Gaussians, in parallel over fixed row
    /// chunks; errors like [`ShadowNet::assemble_input`], naming the Gaussian.
    pub fn assemble_folded_input(
        &self,
        batch: &ShadowBatch,
        input: &mut Vec<f32>,
    ) -> Result<(), NnError> {
        self.check_batch(batch)?;
        let width = self.folded_input_width();
        fresh_len(input, batch.gaussians.len() * width);
        let all_finite = input
            .par_chunks_mut(ROWS_PER_TASK * width)
            .zip(batch.gaussians.par_chunks(ROWS_PER_TASK))
            .map(|(rows, list)| self.assemble_folded_rows(batch, list, rows))
            .reduce(|| true, |a, b| a & b);
        if all_finite {
            Ok(())
        } else {
            Err(self.source_error(batch))
        }
    }

    /// Writes the folded rows of the Gaussians `list` (at most [`ROWS_PER_TASK`] at a
    /// time) into `rows`; true when every value written is finite (one vectorised sweep
    /// while the rows are in cache).
    fn assemble_folded_rows(&self, batch: &ShadowBatch, list: &[u32], rows: &mut [f32]) -> bool {
        let width = self.folded_input_width();
        let enc_width = self.encoding.width(3);
        let latent_dim = self.latent_dim;
        for (list, rows) in list
            .chunks(ROWS_PER_TASK)
            .zip(rows.chunks_mut(ROWS_PER_TASK * width))
        {
            let mut points = [0.0f32; 3 * ROWS_PER_TASK];
            for ((row, &g), point) in rows
                .chunks_exact_mut(width)
                .zip(list)
                .zip(points.chunks_exact_mut(3))
            {
                let g = g as usize;
                row[0] = batch.visibility[g];
                point.copy_from_slice(&batch.scene_box.normalise(&batch.means[g * 3..g * 3 + 3]));
                copy_short(
                    &batch.latents[g * latent_dim..(g + 1) * latent_dim],
                    &mut row[1 + enc_width..],
                );
            }
            self.encoding
                .encode_rows_unchecked(&points[..3 * list.len()], 3, rows, width, 1);
        }
        rows.iter().fold(true, |ok, v| ok & v.is_finite())
    }

    /// The error for a batch whose assembled rows are not all finite: the same checks, in
    /// the same order, as [`ShadowNet::assemble_input`] (a finite mean can still overflow
    /// when normalised: then the input itself is named).
    fn source_error(&self, batch: &ShadowBatch) -> NnError {
        check_rows_finite(
            "shadow latent",
            batch.latents,
            self.latent_dim,
            batch.gaussians,
        )
        .and_then(|()| check_rows_finite("Gaussian mean", batch.means, 3, batch.gaussians))
        .and_then(|()| check_rows_finite("Sun visibility", batch.visibility, 1, batch.gaussians))
        .err()
        .unwrap_or(NnError::NonFinite {
            what: "shadow input",
            index: 0,
        })
    }

    /// Psi's training forward over a batch, for [`ShadowNet::backward`]. On the CPU each
    /// block of [`BLOCK_ROWS`] rows is assembled (folded rows,
    /// [`ShadowNet::assemble_folded_input`]) and run through [`ShadowNet::folded_mlp`]
    /// while it is in cache: the same arithmetic, block for block, as `Mlp::forward_train`
    /// of the folded network on the assembled input (the same bits). `pass.output` holds one
    /// value per listed Gaussian, in list order. On error the pass is left empty (zero rows).
    pub fn forward_train_into(
        &self,
        batch: &ShadowBatch,
        mode: TapeMode,
        pass: &mut ShadowPass,
    ) -> Result<(), NnError> {
        pass.rows = 0;
        pass.output.clear();
        pass.sun_dir = batch.sun_dir;
        let rows = batch.gaussians.len();
        self.check_batch(batch)?;
        let folded = self.folded_mlp(batch.sun_dir)?;
        let width = self.folded_input_width();
        let hidden_per_row: usize = SHADOW_HIDDEN.iter().sum();
        let keep = mode == TapeMode::Cache;
        fresh_len(&mut pass.input, rows * width);
        fresh_len(
            &mut pass.hidden,
            if keep { rows * hidden_per_row } else { 0 },
        );
        fresh_len(&mut pass.output, rows);
        let blocks = rows.div_ceil(BLOCK_ROWS);
        let mut tape: Vec<Option<&mut [f32]>> = if keep {
            pass.hidden
                .chunks_mut(BLOCK_ROWS * hidden_per_row)
                .map(Some)
                .collect()
        } else {
            (0..blocks).map(|_| None).collect()
        };
        let all_finite = pass
            .output
            .par_chunks_mut(BLOCK_ROWS)
            .zip(pass.input.par_chunks_mut(BLOCK_ROWS * width))
            .zip(batch.gaussians.par_chunks(BLOCK_ROWS))
            .zip(tape.par_iter_mut())
            .map(|(((y, x), list), tape)| {
                let inputs_finite = self.assemble_folded_rows(batch, list, x);
                match tape.take() {
                    Some(hidden) => forward_block(&folded, x, list.len(), hidden, y),
                    None => BLOCK_SCRATCH.with(|scratch| {
                        let hidden = &mut scratch.borrow_mut().hidden;
                        hidden.resize(list.len() * hidden_per_row, 0.0);
                        forward_block(&folded, x, list.len(), hidden, y);
                    }),
                }
                (
                    inputs_finite,
                    y.iter().fold(true, |ok, v| ok & v.is_finite()),
                )
            })
            .reduce(|| (true, true), |a, b| (a.0 & b.0, a.1 & b.1));
        match all_finite {
            (false, _) => Err(self.source_error(batch)),
            (true, false) => Err(NnError::NonFinite {
                what: "MLP output",
                index: pass.output.iter().position(|v| !v.is_finite()).unwrap_or(0),
            }),
            (true, true) => {
                pass.rows = rows;
                Ok(())
            }
        }
        .inspect_err(|_| pass.output.clear())
    }

    /// Backward of [`ShadowNet::forward_train_into`] for the same batch and pass
    /// (parameters unchanged since). Adds the parameter gradient (the full layout of
    /// `mlp`) into `d_params`, the latents' into `d_latents` (`count x latent_dim`) and,
    /// through the normalised mean, the means' into `d_means` (`count x 3`), in list order
    /// (repeated Gaussians accumulate). On the CPU each block runs the folded network's
    /// backward (as `Mlp::backward`: per-block weight gradients summed in block order) and
    /// its input gradient goes straight into the encoding's backward, no `rows x width`
    /// buffer. Nothing is written on error.
    pub fn backward(
        &self,
        batch: &ShadowBatch,
        pass: &ShadowPass,
        d_output: &[f32],
        d_params: &mut [f32],
        d_latents: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        let count = self.check_batch(batch)?;
        let latent_dim = self.latent_dim;
        check_len(
            "shadow latent gradient",
            d_latents.len(),
            count * latent_dim,
        )?;
        check_len("Gaussian mean gradient", d_means.len(), count * 3)?;
        check_len(
            "Psi parameter gradient",
            d_params.len(),
            self.mlp.num_params(),
        )?;
        let rows = batch.gaussians.len();
        check_len("Psi forward rows", pass.rows, rows)?;
        check_len("Psi output gradient", d_output.len(), rows)?;
        check_finite("Psi output gradient", d_output)?;
        if pass.sun_dir != batch.sun_dir {
            return Err(NnError::Config(
                "Psi backward: the batch's Sun direction is not the forward's".into(),
            ));
        }
        let width = self.folded_input_width();
        let hidden_per_row: usize = SHADOW_HIDDEN.iter().sum();
        check_len("Psi folded input", pass.input.len(), rows * width)?;
        let keep = !pass.hidden.is_empty() || rows == 0;
        if keep {
            check_len("Psi tape", pass.hidden.len(), rows * hidden_per_row)?;
        }
        let folded = self.folded_mlp(batch.sun_dir)?;
        let sun_code = self.sun_code(batch.sun_dir)?;
        let enc_width = self.encoding.width(3);
        let inverse_extent = batch.scene_box.inverse_extent();
        // Per row: the latent gradient then the mean gradient, scattered in list order.
        let per_row = latent_dim + 3;
        let mut row_grads = vec![0.0f32; rows * per_row];
        let blocks = rows.div_ceil(BLOCK_ROWS);
        let tape: Vec<Option<&[f32]>> = if keep {
            pass.hidden
                .chunks(BLOCK_ROWS * hidden_per_row)
                .map(Some)
                .collect()
        } else {
            (0..blocks).map(|_| None).collect()
        };
        let partials: Vec<Vec<f32>> = pass
            .output
            .par_chunks(BLOCK_ROWS)
            .zip(pass.input.par_chunks(BLOCK_ROWS * width))
            .zip(d_output.par_chunks(BLOCK_ROWS))
            .zip(row_grads.par_chunks_mut(BLOCK_ROWS * per_row))
            .zip(tape.par_iter())
            .map(|((((y, x), d_y), grads), tape)| {
                let block_rows = y.len();
                let mut partial = vec![0.0f32; folded.num_params()];
                BLOCK_SCRATCH.with(|scratch| {
                    let scratch = &mut *scratch.borrow_mut();
                    let BlockScratch {
                        hidden: hidden_again,
                        d_x,
                        d_z,
                        d_prev,
                    } = scratch;
                    // Recompute: the same activations, bit for bit, as forward.
                    let hidden: &[f32] = match tape {
                        Some(hidden) => hidden,
                        None => {
                            hidden_again.resize(block_rows * hidden_per_row, 0.0);
                            forward_block_layers(&folded, x, block_rows, hidden_again, None);
                            hidden_again
                        }
                    };
                    d_x.resize(block_rows * width, 0.0);
                    let tape = BlockTape {
                        x,
                        rows: block_rows,
                        hidden,
                        y,
                    };
                    backward_block(&folded, &tape, d_y, &mut partial, d_x, d_z, d_prev);
                    for ((out, d_row), row) in grads
                        .chunks_exact_mut(per_row)
                        .zip(d_x.chunks_exact(width))
                        .zip(x.chunks_exact(width))
                    {
                        let (d_latent, d_mean) = out.split_at_mut(latent_dim);
                        d_latent.copy_from_slice(&d_row[1 + enc_width..]);
                        let mut d_p = [0.0f32; 3];
                        self.encoding.backward_from_code(
                            &row[1..1 + enc_width],
                            &d_row[1..1 + enc_width],
                            &mut d_p,
                        );
                        for a in 0..3 {
                            d_mean[a] = d_p[a] * inverse_extent[a];
                        }
                    }
                });
                partial
            })
            .collect();
        // Fixed block order, as `Mlp::backward`.
        let mut d_folded = vec![0.0f32; folded.num_params()];
        for partial in &partials {
            for (t, p) in d_folded.iter_mut().zip(partial) {
                *t += p;
            }
        }
        check_finite("MLP parameter gradient", &d_folded)?;
        check_finite("shadow input gradient", &row_grads)?;
        for (grads, &g) in row_grads.chunks_exact(per_row).zip(batch.gaussians) {
            let g = g as usize;
            let (d_latent, d_mean) = grads.split_at(latent_dim);
            for (acc, &v) in d_latents[g * latent_dim..(g + 1) * latent_dim]
                .iter_mut()
                .zip(d_latent)
            {
                *acc += v;
            }
            for (acc, &v) in d_means[g * 3..g * 3 + 3].iter_mut().zip(d_mean) {
                *acc += v;
            }
        }
        self.add_unfolded_grad(&sun_code, &d_folded, d_params);
        Ok(())
    }
}

/// What Psi's training forward keeps for its backward (one batch; reuse across steps
/// spares allocation, every value is rewritten).
#[derive(Clone, Debug, Default)]
pub struct ShadowPass {
    rows: usize,
    sun_dir: [f32; 3],
    /// Folded input rows, `rows x folded_input_width()` (CPU).
    input: Vec<f32>,
    /// Hidden activations (`TapeMode::Cache` on the CPU): block after block of
    /// [`BLOCK_ROWS`] rows, each layer after layer (`block_rows x 32` each), like
    /// `MlpForward`'s tape. Empty under `Recompute`.
    hidden: Vec<f32>,
    /// Psi's output per listed Gaussian, in list order.
    pub output: Vec<f32>,
}

impl ShadowPass {
    /// Rows of the last successful forward (0 after an error).
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Floats kept for backward besides the input and output (0 in recompute mode).
    pub fn tape_len(&self) -> usize {
        self.hidden.len()
    }
}
