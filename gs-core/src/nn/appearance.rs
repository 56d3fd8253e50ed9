//! The appearance network Phi of the paper: per-Gaussian colour from the Gaussian's
//! appearance feature, the Sun direction and the viewing direction.
//!
//! Network: input -> 3 x H ReLU -> 3 (RGB through a sigmoid), PyTorch-default init, with
//! hidden width `H` (paper: 256; `SunAwareConfig::appearance_hidden_width`).
//! Input row of Gaussian `i` for image `j` (width `feature_dim + 2 * 3 * 2L`):
//! `[f_i (feature_dim) | gamma_L(sun_j) (6L) | gamma_L(view_ij) (6L)]`, with
//! `view_ij = (camera_centre_j - mu_i) / |camera_centre_j - mu_i|`, the unit vector from the
//! Gaussian to the camera. Means, camera centre and Sun direction must be in one frame (the
//! target body frame); the Sun direction is normalised here.
//!
//! With [`AppearanceInputs::Local`] or [`AppearanceInputs::LocalNoSun`] the row ends in
//! [`LOCAL_INPUTS`] more values, `[n.s, n.v, n.h]` of the Gaussian's local frame (width
//! `feature_dim + 12 L + 3`): [`AppearanceNet::assemble_input`] leaves them 0 and the
//! caller, which owns the normals, fills them (`crate::sunaware::shading::local_inputs`) and
//! routes their gradient itself; [`AppearanceNet::scatter_input_grad`] ignores them.
//! `LocalNoSun` writes zeros in the `gamma_L(sun)` block (Phi then sees the Sun only
//! through `n.s` and `n.h`).
//!
//! Rows are assembled only for the listed Gaussians (e.g. those that survived culling), in
//! list order; [`AppearanceNet::scatter_input_grad`] routes the input gradient back to the
//! features and, through the view direction, to the means. The Sun direction is data, so it
//! gets no gradient.

use rayon::prelude::*;

use super::encoding::PositionalEncoding;
use super::error::{check_finite, check_len, NnError};
use super::gather::{check_indices, check_rows_finite, rows_of, unit_vector};
use super::mlp::{HiddenActivation, Init, Mlp};

/// Hidden width of Phi in the paper (3 x 256-D hidden layers).
pub const DEFAULT_APPEARANCE_HIDDEN_WIDTH: usize = 256;

/// Hidden layers of Phi (all of one width).
pub const APPEARANCE_HIDDEN_LAYERS: usize = 3;

/// RGB.
pub const APPEARANCE_OUTPUT: usize = 3;

/// Values of the local-frame block `[n.s, n.v, n.h]` at the end of a local input row.
pub const LOCAL_INPUTS: usize = 3;

/// What Phi's input row holds beyond the feature (`SunAwareConfig::appearance_inputs`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum AppearanceInputs {
    /// The paper's row: `[f_i | gamma(sun) | gamma(view_i)]`.
    #[default]
    Paper,
    /// The paper's row and `[n.s, n.v, n.h]` in the Gaussian's local frame.
    Local,
    /// As `Local` with the `gamma(sun)` block zeroed.
    LocalNoSun,
}

impl AppearanceInputs {
    pub const ALL: [AppearanceInputs; 3] = [
        AppearanceInputs::Paper,
        AppearanceInputs::Local,
        AppearanceInputs::LocalNoSun,
    ];

    pub fn name(self) -> &'static str {
        match self {
            AppearanceInputs::Paper => "paper",
            AppearanceInputs::Local => "local",
            AppearanceInputs::LocalNoSun => "local_no_sun",
        }
    }

    /// Values appended after the view encoding (0 or [`LOCAL_INPUTS`]).
    pub fn local_width(self) -> usize {
        match self {
            AppearanceInputs::Paper => 0,
            AppearanceInputs::Local | AppearanceInputs::LocalNoSun => LOCAL_INPUTS,
        }
    }

    /// The row carries `gamma(sun)` (else that block is zeros).
    pub fn encodes_sun(self) -> bool {
        self != AppearanceInputs::LocalNoSun
    }

    pub fn code(self) -> u8 {
        self as u8
    }

    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.get(code as usize).copied()
    }
}

impl std::fmt::Display for AppearanceInputs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Phi with its encoding and the feature width it expects.
#[derive(Clone, Debug, PartialEq)]
pub struct AppearanceNet {
    /// The network; its flat `params()` is one optimiser group.
    pub mlp: Mlp,
    encoding: PositionalEncoding,
    feature_dim: usize,
    inputs: AppearanceInputs,
}

/// Unit vector from `mean` to `camera_centre` and the distance, in f32 (also the local
/// inputs' view, `sunaware::shading`, so both see the same bits).
pub(crate) fn view_direction(mean: &[f32], camera_centre: [f32; 3]) -> ([f32; 3], f32) {
    let d = [
        camera_centre[0] - mean[0],
        camera_centre[1] - mean[1],
        camera_centre[2] - mean[2],
    ];
    let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    ([d[0] / r, d[1] / r, d[2] / r], r)
}

impl AppearanceNet {
    /// A fresh Phi for features of `feature_dim` values (72 in the paper), hidden layers of
    /// the paper's width.
    pub fn new(
        feature_dim: usize,
        encoding: PositionalEncoding,
        seed: u64,
    ) -> Result<Self, NnError> {
        Self::with_hidden_width(feature_dim, DEFAULT_APPEARANCE_HIDDEN_WIDTH, encoding, seed)
    }

    /// A fresh Phi whose three hidden layers are `hidden_width` wide.
    pub fn with_hidden_width(
        feature_dim: usize,
        hidden_width: usize,
        encoding: PositionalEncoding,
        seed: u64,
    ) -> Result<Self, NnError> {
        Self::with_inputs(
            feature_dim,
            hidden_width,
            encoding,
            AppearanceInputs::Paper,
            seed,
        )
    }

    /// A fresh Phi of `hidden_width` whose input rows are laid out per `inputs`.
    pub fn with_inputs(
        feature_dim: usize,
        hidden_width: usize,
        encoding: PositionalEncoding,
        inputs: AppearanceInputs,
        seed: u64,
    ) -> Result<Self, NnError> {
        if feature_dim == 0 {
            return Err(NnError::Config(
                "appearance feature width must be positive".into(),
            ));
        }
        if hidden_width == 0 {
            return Err(NnError::Config(
                "appearance hidden width must be positive".into(),
            ));
        }
        let widths = Self::widths_for(feature_dim, hidden_width, encoding, inputs);
        let mlp = Mlp::new(
            &widths,
            HiddenActivation::Relu,
            Init::TorchLinearDefault,
            seed,
        )?;
        Ok(Self {
            mlp,
            encoding,
            feature_dim,
            inputs,
        })
    }

    /// Wraps a loaded network, checking that its shape is Phi's for these settings (with
    /// any hidden width, taken from the network's first hidden layer).
    pub fn from_mlp(
        mlp: Mlp,
        feature_dim: usize,
        encoding: PositionalEncoding,
    ) -> Result<Self, NnError> {
        let hidden_width = mlp.widths().get(1).copied().unwrap_or(0);
        let inputs = AppearanceInputs::Paper;
        let widths = Self::widths_for(feature_dim, hidden_width, encoding, inputs);
        if mlp.widths() != widths || mlp.hidden_activation() != HiddenActivation::Relu {
            return Err(NnError::Config(format!(
                "appearance network must be {widths:?} with ReLU, got {:?} with {:?}",
                mlp.widths(),
                mlp.hidden_activation()
            )));
        }
        Ok(Self {
            mlp,
            encoding,
            feature_dim,
            inputs,
        })
    }

    /// Weights of Phi for these settings, without building it (checked: an error for
    /// sizes no network may have).
    pub fn param_count(
        feature_dim: usize,
        hidden_width: usize,
        encoding: PositionalEncoding,
        inputs: AppearanceInputs,
    ) -> Result<usize, NnError> {
        super::mlp::param_count(&Self::widths_for(
            feature_dim,
            hidden_width,
            encoding,
            inputs,
        ))
    }

    fn widths_for(
        feature_dim: usize,
        hidden_width: usize,
        encoding: PositionalEncoding,
        inputs: AppearanceInputs,
    ) -> Vec<usize> {
        // Saturating: an absurd width then fails `param_count` instead of overflowing.
        let mut widths = vec![feature_dim
            .saturating_add(2 * encoding.width(3))
            .saturating_add(inputs.local_width())];
        widths.extend([hidden_width; APPEARANCE_HIDDEN_LAYERS]);
        widths.push(APPEARANCE_OUTPUT);
        widths
    }

    pub fn feature_dim(&self) -> usize {
        self.feature_dim
    }

    /// Width of each hidden layer.
    pub fn hidden_width(&self) -> usize {
        self.mlp.widths()[1]
    }

    pub fn encoding(&self) -> PositionalEncoding {
        self.encoding
    }

    /// What the input rows hold beyond the feature.
    pub fn inputs(&self) -> AppearanceInputs {
        self.inputs
    }

    /// Values per input row: `feature_dim + 12 L` (+ [`LOCAL_INPUTS`] for local inputs).
    pub fn input_width(&self) -> usize {
        self.mlp.input_width()
    }

    /// Column of a row where the local-frame block `[n.s, n.v, n.h]` starts (the row's
    /// end, `input_width()`, for [`AppearanceInputs::Paper`]).
    pub fn local_start(&self) -> usize {
        self.feature_dim + 2 * self.encoding.width(3)
    }

    /// Fills `input` (resized to `gaussians.len() x input_width()`) with one row per listed
    /// Gaussian. `features` is the model's `count x feature_dim` group, `means` its
    /// `count x 3` group.
    pub fn assemble_input(
        &self,
        gaussians: &[u32],
        features: &[f32],
        means: &[f32],
        sun_dir: [f32; 3],
        camera_centre: [f32; 3],
        input: &mut Vec<f32>,
    ) -> Result<(), NnError> {
        let count = rows_of("appearance features", features, self.feature_dim)?;
        check_len("Gaussian means", means.len(), count * 3)?;
        check_indices(gaussians, count)?;
        check_rows_finite("appearance feature", features, self.feature_dim, gaussians)?;
        check_rows_finite("Gaussian mean", means, 3, gaussians)?;
        let sun = unit_vector("Sun direction", sun_dir)?;
        check_finite("camera centre", &camera_centre)?;
        for &g in gaussians {
            let (_, r) = view_direction(&means[g as usize * 3..g as usize * 3 + 3], camera_centre);
            if !(r > 0.0 && r.is_finite()) {
                return Err(NnError::Degenerate {
                    what: "view direction (Gaussian at the camera centre)",
                    index: g as usize,
                });
            }
        }

        let width = self.input_width();
        let f_dim = self.feature_dim;
        let enc_width = self.encoding.width(3);
        let mut sun_code = vec![0.0f32; enc_width];
        if self.inputs.encodes_sun() {
            self.encoding.encode_unchecked(&sun, &mut sun_code);
        }
        input.clear();
        input.resize(gaussians.len() * width, 0.0);
        input
            .par_chunks_mut(width)
            .zip(gaussians.par_iter())
            .for_each(|(row, &g)| {
                let g = g as usize;
                row[..f_dim].copy_from_slice(&features[g * f_dim..(g + 1) * f_dim]);
                row[f_dim..f_dim + enc_width].copy_from_slice(&sun_code);
                let (view, _) = view_direction(&means[g * 3..g * 3 + 3], camera_centre);
                self.encoding
                    .encode_unchecked(&view, &mut row[f_dim + enc_width..f_dim + 2 * enc_width]);
            });
        Ok(())
    }

    /// Adds the gradient of the assembled input (`d_input`, `gaussians.len() x input_width()`)
    /// into `d_features` (`count x feature_dim`) and, through the view direction, into
    /// `d_means` (`count x 3`). Repeated indices accumulate. Nothing is written on error.
    pub fn scatter_input_grad(
        &self,
        gaussians: &[u32],
        means: &[f32],
        camera_centre: [f32; 3],
        d_input: &[f32],
        d_features: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        self.scatter(
            gaussians,
            None,
            means,
            camera_centre,
            d_input,
            d_features,
            d_means,
        )
    }

    /// [`AppearanceNet::scatter_input_grad`] reading the view-direction encoding from
    /// `input`, this network's [`AppearanceNet::assemble_input`] output for the same
    /// `gaussians`, means and camera, instead of recomputing its sines and cosines: the
    /// same bits, cheaper. An input that was not assembled so gives a wrong gradient, not
    /// an error.
    pub fn scatter_input_grad_from_input(
        &self,
        gaussians: &[u32],
        input: &[f32],
        means: &[f32],
        camera_centre: [f32; 3],
        d_input: &[f32],
        d_features: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        check_len(
            "appearance input",
            input.len(),
            gaussians.len() * self.input_width(),
        )?;
        self.scatter(
            gaussians,
            Some(input),
            means,
            camera_centre,
            d_input,
            d_features,
            d_means,
        )
    }

    /// The scatter; `input` (when given) supplies the view encoding's sines and cosines.
    fn scatter(
        &self,
        gaussians: &[u32],
        input: Option<&[f32]>,
        means: &[f32],
        camera_centre: [f32; 3],
        d_input: &[f32],
        d_features: &mut [f32],
        d_means: &mut [f32],
    ) -> Result<(), NnError> {
        let count = rows_of("appearance feature gradient", d_features, self.feature_dim)?;
        check_len("Gaussian means", means.len(), count * 3)?;
        check_len("Gaussian mean gradient", d_means.len(), count * 3)?;
        let width = self.input_width();
        check_len(
            "appearance input gradient",
            d_input.len(),
            gaussians.len() * width,
        )?;
        check_indices(gaussians, count)?;
        check_finite("appearance input gradient", d_input)?;
        check_rows_finite("Gaussian mean", means, 3, gaussians)?;
        check_finite("camera centre", &camera_centre)?;

        let f_dim = self.feature_dim;
        let view_start = f_dim + self.encoding.width(3);
        // The local-frame block after the view code belongs to the caller.
        let view_end = self.local_start();
        // Per-row mean gradients in parallel, then a sequential scatter (fixed order).
        let d_mean_rows: Vec<[f32; 3]> = d_input
            .par_chunks(width)
            .zip(gaussians.par_iter())
            .enumerate()
            .map(|(r, (row, &g))| {
                let g = g as usize;
                let (view, r_m) = view_direction(&means[g * 3..g * 3 + 3], camera_centre);
                let mut d_view = [0.0f32; 3];
                let d_code = &row[view_start..view_end];
                match input {
                    Some(input) => self.encoding.backward_from_code(
                        &input[r * width + view_start..r * width + view_end],
                        d_code,
                        &mut d_view,
                    ),
                    None => self.encoding.backward_unchecked(&view, d_code, &mut d_view),
                }
                // d view / d mean = -(I - v v^T) / r.
                let along = d_view[0] * view[0] + d_view[1] * view[1] + d_view[2] * view[2];
                [
                    -(d_view[0] - along * view[0]) / r_m,
                    -(d_view[1] - along * view[1]) / r_m,
                    -(d_view[2] - along * view[2]) / r_m,
                ]
            })
            .collect();
        check_finite("appearance mean gradient", d_mean_rows.as_flattened())?;
        for ((row, &g), d_mean) in d_input.chunks_exact(width).zip(gaussians).zip(&d_mean_rows) {
            let g = g as usize;
            for (acc, &v) in d_features[g * f_dim..(g + 1) * f_dim].iter_mut().zip(row) {
                *acc += v;
            }
            for (acc, &v) in d_means[g * 3..g * 3 + 3].iter_mut().zip(d_mean) {
                *acc += v;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    #[test]
    fn local_rows_append_three_zeros_and_no_sun_zeroes_its_code() {
        let enc = PositionalEncoding::default();
        let nets = AppearanceInputs::ALL
            .map(|inputs| AppearanceNet::with_inputs(4, 8, enc, inputs, 3).unwrap());
        let [paper, local, no_sun] = &nets;
        let e = enc.width(3);
        assert_eq!(paper.input_width(), 4 + 2 * e);
        assert_eq!(local.input_width(), 4 + 2 * e + LOCAL_INPUTS);
        assert_eq!(no_sun.input_width(), local.input_width());
        assert_eq!(local.local_start(), paper.input_width());
        assert_eq!(
            AppearanceNet::param_count(4, 8, enc, AppearanceInputs::Local).unwrap(),
            local.mlp.num_params()
        );
        let features = [0.1f32, -0.2, 0.3, 0.4, 0.5, 0.6, -0.7, 0.8];
        let means = [0.1f32, 0.2, 0.3, -0.4, 0.5, 0.0];
        let (sun, camera) = ([0.3, 0.4, -0.8], [0.5, -1.0, 6.0]);
        let rows = |net: &AppearanceNet| {
            let mut input = Vec::new();
            net.assemble_input(&[1, 0], &features, &means, sun, camera, &mut input)
                .unwrap();
            input
        };
        let (p, l, n) = (rows(paper), rows(local), rows(no_sun));
        let w = local.input_width();
        for r in 0..2 {
            let pr = &p[r * paper.input_width()..(r + 1) * paper.input_width()];
            let (lr, nr) = (&l[r * w..(r + 1) * w], &n[r * w..(r + 1) * w]);
            assert_eq!(&lr[..pr.len()], pr);
            assert_eq!(&lr[pr.len()..], &[0.0; LOCAL_INPUTS]);
            assert!(pr[4..4 + e].iter().any(|&x| x != 0.0));
            assert!(nr[4..4 + e].iter().all(|&x| x == 0.0));
            assert_eq!(&nr[..4], &pr[..4]);
            assert_eq!(&nr[4 + e..], &lr[4 + e..]);
        }
        // The scatter leaves the local block to the caller: a gradient there moves nothing.
        let mut d_input = vec![0.0f32; 2 * w];
        d_input[w - 1] = 1.0;
        d_input[2 * w - 3] = -2.0;
        let (mut d_f, mut d_m) = (vec![0.0f32; 8], vec![0.0f32; 6]);
        local
            .scatter_input_grad_from_input(
                &[1, 0],
                &l,
                &means,
                camera,
                &d_input,
                &mut d_f,
                &mut d_m,
            )
            .unwrap();
        assert!(d_f.iter().chain(&d_m).all(|&x| x == 0.0));
    }

    #[test]
    fn scatter_from_the_assembled_input_gives_the_same_bits() {
        let net =
            AppearanceNet::with_hidden_width(8, 16, PositionalEncoding::default(), 3).unwrap();
        let mut rng = SplitMix64::new(22);
        let count = 300;
        let means: Vec<f32> = (0..count * 3).map(|_| rng.uniform(-1.5, 1.5)).collect();
        let features: Vec<f32> = (0..count * 8).map(|_| rng.normal()).collect();
        let gaussians: Vec<u32> = (0..500).map(|_| rng.below(count) as u32).collect();
        let (sun, camera) = ([0.3, 0.4, -0.8], [0.5, -1.0, 6.0]);
        let mut input = Vec::new();
        net.assemble_input(&gaussians, &features, &means, sun, camera, &mut input)
            .unwrap();
        let d_input: Vec<f32> = (0..input.len()).map(|_| rng.normal()).collect();
        let mut d_feat_a = vec![0.5f32; count * 8];
        let mut d_mean_a = vec![-0.25f32; count * 3];
        let (mut d_feat_b, mut d_mean_b) = (d_feat_a.clone(), d_mean_a.clone());
        net.scatter_input_grad(
            &gaussians,
            &means,
            camera,
            &d_input,
            &mut d_feat_a,
            &mut d_mean_a,
        )
        .unwrap();
        net.scatter_input_grad_from_input(
            &gaussians,
            &input,
            &means,
            camera,
            &d_input,
            &mut d_feat_b,
            &mut d_mean_b,
        )
        .unwrap();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&d_feat_a), bits(&d_feat_b));
        assert_eq!(bits(&d_mean_a), bits(&d_mean_b));
        assert!(d_mean_a.iter().any(|&v| v != -0.25));
        let err = net.scatter_input_grad_from_input(
            &gaussians,
            &input[..input.len() - 1],
            &means,
            camera,
            &d_input,
            &mut d_feat_b,
            &mut d_mean_b,
        );
        assert!(matches!(err, Err(NnError::Shape { .. })));
    }
}
