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
//!
//! Files: this one (the scene box, the network, its full input rows and their gradient
//! scatter), [`folded`] (the training path on folded rows), `blocks` (the per-block
//! forward and backward kernels of that path).

use rayon::prelude::*;

use super::encoding::PositionalEncoding;
use super::error::{check_finite, check_len, NnError};
use super::gather::{check_indices, check_rows_finite, rows_of, unit_vector};
use super::mlp::{HiddenActivation, Init, Mlp};

mod blocks;
pub mod folded;

pub use folded::{ShadowBatch, ShadowPass};

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
