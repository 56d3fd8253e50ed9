//! The shadow network Psi: refines each Gaussian's splatted Sun visibility `V_i`.
//!
//! Network: input -> 3 x 32 LeakyReLU (slope 0.01) -> 1 through a sigmoid, PyTorch-default
//! init. Input row of Gaussian `i` for image `j` (width `1 + 2 * 3 * 2L + latent_dim`):
//! `[V_i (1) | gamma_L(sun_j) (6L) | gamma_L(p_i) (6L) | l_i (latent_dim)]`, where
//! `p_i = (mu_i - box_min) / (box_max - box_min) - 0.5` is the mean normalised per axis to
//! `[-0.5, 0.5]` over the scene box. That half-period range keeps the lowest band
//! (period 2) from wrapping, so opposite faces of the box never share an encoding (with
//! `[-1, 1]` every band would map `-1` and `+1` to the same code). Means outside the box are
//! not clamped.
//!
//! `V_i` comes from the shadow pass and gets no gradient (DESIGN.md section 3). The input
//! gradient flows to the latents `l_i` and, through `p_i`, to the means.
//!
//! Training path ([`ShadowNet::forward_train_into`], [`ShadowNet::backward`]): the Sun's
//! `6L` columns are the same for every row of a step, so on the CPU they are folded into
//! the first layer's bias ([`ShadowNet::folded_mlp`]) and the rows carry only
//! `[V_i | gamma_L(p_i) | l_i]`; each block of `BLOCK_ROWS` rows is assembled and run while
//! in cache, with `Mlp`'s own arithmetic on the folded network (the same bits as `Mlp` on
//! those rows), and the backward hands the input gradient straight to the encoding's
//! backward. The function is the full network's up to f32 summation order (tested against
//! f64); gradients reach the Sun's weight rows through the fold's chain rule. The
//! parameter layout is the full network's (checkpoints unchanged).

use rayon::prelude::*;

use super::encoding::PositionalEncoding;
use super::error::{check_finite, check_len, NnError};
use super::gather::{check_indices, check_rows_finite, rows_of, unit_vector};
use super::mlp::{HiddenActivation, Init, Mlp, TapeMode, BLOCK_ROWS, LEAKY_SLOPE};

/// Hidden widths of Psi (paper: 3 x 32-D hidden layers).
pub const SHADOW_HIDDEN: [usize; 3] = [32, 32, 32];

/// Axis-aligned box that normalises the means for Psi (model frame, metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneBox {
    min_m: [f32; 3],
    max_m: [f32; 3],
}

impl SceneBox {
    /// A box with `max_m > min_m` on every axis, all finite.
    pub fn new(min_m: [f32; 3], max_m: [f32; 3]) -> Result<Self, NnError> {
        check_finite("scene box", &min_m)?;
        check_finite("scene box", &max_m)?;
        for axis in 0..3 {
            if max_m[axis] - min_m[axis] <= 0.0 || !(max_m[axis] - min_m[axis]).is_finite() {
                return Err(NnError::Config(format!(
                    "scene box must have positive finite extent on every axis, got {min_m:?}..{max_m:?}"
                )));
            }
        }
        Ok(Self { min_m, max_m })
    }

    pub fn min_m(&self) -> [f32; 3] {
        self.min_m
    }

    pub fn max_m(&self) -> [f32; 3] {
        self.max_m
    }

    /// `(mu - min) / (max - min) - 0.5` per axis.
    pub fn normalise(&self, mean_m: &[f32]) -> [f32; 3] {
        std::array::from_fn(|a| (mean_m[a] - self.min_m[a]) / (self.max_m[a] - self.min_m[a]) - 0.5)
    }

    /// `d normalised / d mean` per axis.
    fn inverse_extent(&self) -> [f32; 3] {
        std::array::from_fn(|a| 1.0 / (self.max_m[a] - self.min_m[a]))
    }
}

/// Psi with its encoding and the latent width it expects.
#[derive(Clone, Debug, PartialEq)]
pub struct ShadowNet {
    /// The network; its flat `params()` is one optimiser group.
    pub mlp: Mlp,
    encoding: PositionalEncoding,
    latent_dim: usize,
}

impl ShadowNet {
    /// A fresh Psi for latents of `latent_dim` values (6 in the paper).
    pub fn new(
        latent_dim: usize,
        encoding: PositionalEncoding,
        seed: u64,
    ) -> Result<Self, NnError> {
        if latent_dim == 0 {
            return Err(NnError::Config(
                "shadow latent width must be positive".into(),
            ));
        }
        let widths = Self::widths_for(latent_dim, encoding);
        let mlp = Mlp::new(
            &widths,
            HiddenActivation::LeakyRelu,
            Init::TorchLinearDefault,
            seed,
        )?;
        Ok(Self {
            mlp,
            encoding,
            latent_dim,
        })
    }

    /// Wraps a loaded network, checking that its shape is Psi's for these settings.
    pub fn from_mlp(
        mlp: Mlp,
        latent_dim: usize,
        encoding: PositionalEncoding,
    ) -> Result<Self, NnError> {
        let widths = Self::widths_for(latent_dim, encoding);
        if mlp.widths() != widths || mlp.hidden_activation() != HiddenActivation::LeakyRelu {
            return Err(NnError::Config(format!(
                "shadow network must be {widths:?} with LeakyReLU, got {:?} with {:?}",
                mlp.widths(),
                mlp.hidden_activation()
            )));
        }
        Ok(Self {
            mlp,
            encoding,
            latent_dim,
        })
    }

    /// Weights of Psi for these settings, without building it (checked).
    pub fn param_count(latent_dim: usize, encoding: PositionalEncoding) -> Result<usize, NnError> {
        super::mlp::param_count(&Self::widths_for(latent_dim, encoding))
    }

    fn widths_for(latent_dim: usize, encoding: PositionalEncoding) -> Vec<usize> {
        // Saturating: an absurd width then fails `param_count` instead of overflowing.
        let mut widths = vec![(1 + 2 * encoding.width(3)).saturating_add(latent_dim)];
        widths.extend(SHADOW_HIDDEN);
        widths.push(1);
        widths
    }

    pub fn latent_dim(&self) -> usize {
        self.latent_dim
    }

    pub fn encoding(&self) -> PositionalEncoding {
        self.encoding
    }

    /// Values per input row: `1 + 12 L + latent_dim`.
    pub fn input_width(&self) -> usize {
        self.mlp.input_width()
    }

    /// Fills `input` (resized to `gaussians.len() x input_width()`) with one row per listed
    /// Gaussian. `visibility` holds `V` for every Gaussian of the model (length `count`),
    /// `latents` the `count x latent_dim` group, `means` the `count x 3` group.
    #[allow(clippy::too_many_arguments)]
    pub fn assemble_input(
        &self,
        gaussians: &[u32],
        visibility: &[f32],
        latents: &[f32],
        means: &[f32],
        sun_dir: [f32; 3],
        scene_box: &SceneBox,
        input: &mut Vec<f32>,
    ) -> Result<(), NnError> {
        let count = rows_of("shadow latents", latents, self.latent_dim)?;
        check_len("Gaussian means", means.len(), count * 3)?;
        check_len("Sun visibility", visibility.len(), count)?;
        check_indices(gaussians, count)?;
        check_rows_finite("shadow latent", latents, self.latent_dim, gaussians)?;
        check_rows_finite("Gaussian mean", means, 3, gaussians)?;
        check_rows_finite("Sun visibility", visibility, 1, gaussians)?;
        let sun = unit_vector("Sun direction", sun_dir)?;

        let width = self.input_width();
        let enc_width = self.encoding.width(3);
        let latent_dim = self.latent_dim;
        let mut sun_code = vec![0.0f32; enc_width];
        self.encoding.encode_unchecked(&sun, &mut sun_code);
        input.clear();
        input.resize(gaussians.len() * width, 0.0);
        input
            .par_chunks_mut(width)
            .zip(gaussians.par_iter())
            .for_each(|(row, &g)| {
                let g = g as usize;
                row[0] = visibility[g];
                row[1..1 + enc_width].copy_from_slice(&sun_code);
                let p = scene_box.normalise(&means[g * 3..g * 3 + 3]);
                self.encoding
                    .encode_unchecked(&p, &mut row[1 + enc_width..1 + 2 * enc_width]);
                row[1 + 2 * enc_width..]
                    .copy_from_slice(&latents[g * latent_dim..(g + 1) * latent_dim]);
            });
        Ok(())
    }

    /// Adds the gradient of the assembled input (`d_input`, `gaussians.len() x input_width()`)
    /// into `d_latents` (`count x latent_dim`) and, through the normalised mean, into
    /// `d_means` (`count x 3`). The visibility column is ignored (no gradient through `V`).
    /// Repeated indices accumulate. Nothing is written on error.
    pub fn scatter_input_grad(
        &self,
        gaussians: &[u32],
        means: &[f32],
        scene_box: &SceneBox,
        d_input: &[f32],
        d_latents: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        let count = rows_of("shadow latent gradient", d_latents, self.latent_dim)?;
        check_len("Gaussian means", means.len(), count * 3)?;
        check_indices(gaussians, count)?;
        check_rows_finite("Gaussian mean", means, 3, gaussians)?;
        self.scatter(
            gaussians,
            Codes::FromMeans(means, scene_box),
            scene_box,
            d_input,
            d_latents,
            d_means,
        )
    }

    /// [`ShadowNet::scatter_input_grad`] reading the position encoding from `input`, this
    /// network's [`ShadowNet::assemble_input`] output for the same `gaussians` and means,
    /// instead of recomputing its sines and cosines: the same bits, cheaper. An input that
    /// was not assembled so gives a wrong gradient, not an error.
    pub fn scatter_input_grad_from_input(
        &self,
        gaussians: &[u32],
        input: &[f32],
        scene_box: &SceneBox,
        d_input: &[f32],
        d_latents: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        check_len(
            "shadow input",
            input.len(),
            gaussians.len() * self.input_width(),
        )?;
        self.scatter(
            gaussians,
            Codes::FromInput(input),
            scene_box,
            d_input,
            d_latents,
            d_means,
        )
    }

    fn scatter(
        &self,
        gaussians: &[u32],
        codes: Codes,
        scene_box: &SceneBox,
        d_input: &[f32],
        d_latents: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        let count = rows_of("shadow latent gradient", d_latents, self.latent_dim)?;
        check_len("Gaussian mean gradient", d_means.len(), count * 3)?;
        let width = self.input_width();
        check_len(
            "shadow input gradient",
            d_input.len(),
            gaussians.len() * width,
        )?;
        check_indices(gaussians, count)?;
        check_finite("shadow input gradient", d_input)?;

        let enc_width = self.encoding.width(3);
        let code_range = 1 + enc_width..1 + 2 * enc_width;
        let latent_dim = self.latent_dim;
        let inverse_extent = scene_box.inverse_extent();
        let d_mean_rows: Vec<[f32; 3]> = d_input
            .par_chunks(width)
            .zip(gaussians.par_iter())
            .enumerate()
            .map(|(r, (row, &g))| {
                let mut d_p = [0.0f32; 3];
                let d_code = &row[code_range.clone()];
                match codes {
                    Codes::FromInput(input) => self.encoding.backward_from_code(
                        &input[r * width..(r + 1) * width][code_range.clone()],
                        d_code,
                        &mut d_p,
                    ),
                    Codes::FromMeans(means, scene_box) => {
                        let g = g as usize;
                        let p = scene_box.normalise(&means[g * 3..g * 3 + 3]);
                        self.encoding.backward_unchecked(&p, d_code, &mut d_p);
                    }
                }
                std::array::from_fn(|a| d_p[a] * inverse_extent[a])
            })
            .collect();
        check_finite("shadow mean gradient", d_mean_rows.as_flattened())?;
        for ((row, &g), d_mean) in d_input.chunks_exact(width).zip(gaussians).zip(&d_mean_rows) {
            let g = g as usize;
            for (acc, &v) in d_latents[g * latent_dim..(g + 1) * latent_dim]
                .iter_mut()
                .zip(&row[1 + 2 * enc_width..])
            {
                *acc += v;
            }
            for (acc, &v) in d_means[g * 3..g * 3 + 3].iter_mut().zip(d_mean) {
                *acc += v;
            }
        }
        Ok(())
    }
}

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
    /// of the folded network on the assembled input (the same bits). `pass.output` holds one value
    /// per listed Gaussian, in list order. On error the pass is left empty (zero rows).
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
                        forward_block(&folded, x, list.len(), hidden, y)
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
                    backward_block(
                        &folded,
                        x,
                        block_rows,
                        hidden,
                        y,
                        d_y,
                        &mut partial,
                        d_x,
                        d_z,
                        d_prev,
                    );
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

/// Sets `v` to `len` values. A vector of another length is replaced by a zeroed one
/// (fresh zero pages, no serial fill); one of the right length keeps its stale contents,
/// which the caller overwrites before reading.
fn fresh_len(v: &mut Vec<f32>, len: usize) {
    if v.len() != len {
        *v = vec![0.0f32; len];
    }
}

/// Per-thread buffers of the forward and backward blocks: recomputed activations and the
/// backward's gradients (contents never carry over: every value is
/// written before it is read).
#[derive(Default)]
struct BlockScratch {
    hidden: Vec<f32>,
    d_x: Vec<f32>,
    d_z: Vec<f32>,
    d_prev: Vec<f32>,
}

thread_local! {
    static BLOCK_SCRATCH: std::cell::RefCell<BlockScratch> =
        std::cell::RefCell::new(BlockScratch::default());
}

/// `dst.copy_from_slice(src)` for a few values: the paper's 6-value latent as two
/// register moves instead of a `memmove` call per row.
#[inline(always)]
fn copy_short(src: &[f32], dst: &mut [f32]) {
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
fn leaky_relu(z: f32) -> f32 {
    if z > 0.0 {
        z
    } else {
        LEAKY_SLOPE * z
    }
}

/// LeakyReLU's derivative from its output, as `Mlp` takes it.
#[inline]
fn leaky_slope_from_output(a: f32) -> f32 {
    if a > 0.0 {
        1.0
    } else {
        LEAKY_SLOPE
    }
}

/// `Mlp`'s block forward for a LeakyReLU network (the same products, bias and activation
/// in the same order): output into `out`, hidden activations layer after layer into
/// `hidden`.
fn forward_block(mlp: &Mlp, x: &[f32], rows: usize, hidden: &mut [f32], out: &mut [f32]) {
    forward_block_layers(mlp, x, rows, hidden, Some(out));
}

/// [`forward_block`]; without `out` only the hidden layers run (a backward's recompute:
/// it has the output already).
fn forward_block_layers(
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
#[allow(clippy::too_many_arguments)]
fn backward_block(
    mlp: &Mlp,
    x: &[f32],
    rows: usize,
    hidden: &[f32],
    y: &[f32],
    d_y: &[f32],
    d_params: &mut [f32],
    d_x: &mut [f32],
    d_z: &mut Vec<f32>,
    d_prev: &mut Vec<f32>,
) {
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

/// Where the scatter gets the position encoding's sines and cosines.
#[derive(Clone, Copy)]
enum Codes<'a> {
    /// Recomputed from the means (count x 3) and the box.
    FromMeans(&'a [f32], &'a SceneBox),
    /// Read from the assembled input (rows x input width).
    FromInput(&'a [f32]),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    #[test]
    fn scatter_from_the_assembled_input_gives_the_same_bits() {
        let net = ShadowNet::new(6, PositionalEncoding::default(), 3).unwrap();
        let scene_box = SceneBox::new([-1.5, -0.8, -0.7], [1.4, 0.9, 0.6]).unwrap();
        let mut rng = SplitMix64::new(21);
        let count = 300;
        let means: Vec<f32> = (0..count * 3).map(|_| rng.uniform(-1.6, 1.6)).collect();
        let latents: Vec<f32> = (0..count * 6).map(|_| rng.normal()).collect();
        let visibility: Vec<f32> = (0..count).map(|_| rng.next_f32()).collect();
        // Any order, with repeats.
        let gaussians: Vec<u32> = (0..500).map(|_| rng.below(count) as u32).collect();
        let mut input = Vec::new();
        let sun = [0.2, -0.5, 0.8];
        net.assemble_input(
            &gaussians,
            &visibility,
            &latents,
            &means,
            sun,
            &scene_box,
            &mut input,
        )
        .unwrap();
        let d_input: Vec<f32> = (0..input.len()).map(|_| rng.normal()).collect();
        let seed_grads = |rng: &mut SplitMix64| -> (Vec<f32>, Vec<f32>) {
            (
                (0..count * 6).map(|_| rng.normal()).collect(),
                (0..count * 3).map(|_| rng.normal()).collect(),
            )
        };
        let (mut d_lat_a, mut d_mean_a) = seed_grads(&mut SplitMix64::new(1));
        let (mut d_lat_b, mut d_mean_b) = seed_grads(&mut SplitMix64::new(1));
        net.scatter_input_grad(
            &gaussians,
            &means,
            &scene_box,
            &d_input,
            &mut d_lat_a,
            &mut d_mean_a,
        )
        .unwrap();
        net.scatter_input_grad_from_input(
            &gaussians,
            &input,
            &scene_box,
            &d_input,
            &mut d_lat_b,
            &mut d_mean_b,
        )
        .unwrap();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&d_lat_a), bits(&d_lat_b));
        assert_eq!(bits(&d_mean_a), bits(&d_mean_b));
        assert_ne!(d_mean_a, seed_grads(&mut SplitMix64::new(1)).1);
        // A short input is a shape error, nothing written.
        let before = d_mean_b.clone();
        let err = net.scatter_input_grad_from_input(
            &gaussians,
            &input[1..],
            &scene_box,
            &d_input,
            &mut d_lat_b,
            &mut d_mean_b,
        );
        assert!(matches!(err, Err(NnError::Shape { .. })));
        assert_eq!(d_mean_b, before);
    }
}
