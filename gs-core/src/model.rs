//! Gaussian model storage: structure-of-arrays, one flat `Vec<f32>` per parameter group.
//!
//! The same [`ParamSet`] type holds the parameters, their gradients and the optimiser's
//! moments, so densify and prune apply one operation (`retain`, `append_rows`,
//! `push_zeros`) to every one of them and they can never fall out of step.
//!
//! Invariants:
//! - every group holds `len() * dim(group)` values; a group of width 0 is absent;
//! - means are world-frame metres, scales are natural-log scales, rotations are
//!   unnormalised quaternions stored `[w, x, y, z]` (the rasterizer normalises them and
//!   culls `|q|^2 < 1e-6`), opacities are logits;
//! - adding a parameter group is one variant in [`Param`] plus its width in
//!   [`ModelLayout::dims`]: nothing else walks the groups by hand.

/// A parameter group. The discriminant is the group's index in a [`ParamSet`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Param {
    /// Centre, world frame, 3 values.
    Mean,
    /// Natural log of the three standard deviations, 3 values.
    LogScale,
    /// Quaternion `[w, x, y, z]`, not necessarily unit, 4 values.
    Rotation,
    /// Opacity before the sigmoid, 1 value.
    OpacityLogit,
    /// Spherical-harmonic DC colour, 3 values (RGB).
    ShDc,
    /// Higher-order SH coefficients, `(coeffs(degree) - 1) * 3` values, coefficient-major
    /// (`[c1.r, c1.g, c1.b, c2.r, ...]`).
    ShRest,
    /// Appearance feature fed to the appearance MLP (configurations b-d).
    Feature,
    /// Shadow latent fed to the shadow MLP (configurations c-d).
    ShadowLatent,
    /// Learned shading normal, 3 values, used as `v / |v|` (`shading = "lambert_learned"`,
    /// `sunaware::shading`); last, so the other groups' packed offsets do not move.
    Normal,
}

impl Param {
    pub const COUNT: usize = 9;
    pub const ALL: [Param; Param::COUNT] = [
        Param::Mean,
        Param::LogScale,
        Param::Rotation,
        Param::OpacityLogit,
        Param::ShDc,
        Param::ShRest,
        Param::Feature,
        Param::ShadowLatent,
        Param::Normal,
    ];

    pub const fn index(self) -> usize {
        self as usize
    }

    pub const fn name(self) -> &'static str {
        match self {
            Param::Mean => "mean",
            Param::LogScale => "log_scale",
            Param::Rotation => "rotation",
            Param::OpacityLogit => "opacity_logit",
            Param::ShDc => "sh_dc",
            Param::ShRest => "sh_rest",
            Param::Feature => "feature",
            Param::ShadowLatent => "shadow_latent",
            Param::Normal => "normal",
        }
    }
}

/// Number of SH coefficients per colour channel for a degree (1, 4, 9, 16).
pub const fn sh_coeff_count(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Which optional groups a model carries and how wide they are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelLayout {
    /// Spherical-harmonic degree, 0..=3.
    pub sh_degree: u32,
    /// Width of the appearance feature (72 in the paper), 0 when absent.
    pub feature_dim: usize,
    /// Width of the shadow latent (6 in the paper), 0 when absent.
    pub shadow_latent_dim: usize,
    /// Width of the learned shading normal: 3 with `shading = "lambert_learned"`, else 0.
    pub normal_dim: usize,
}

impl ModelLayout {
    /// Plain 3DGS with SH colour of the given degree.
    pub const fn sh(sh_degree: u32) -> Self {
        Self {
            sh_degree,
            feature_dim: 0,
            shadow_latent_dim: 0,
            normal_dim: 0,
        }
    }

    pub const fn dims(&self) -> [usize; Param::COUNT] {
        [
            3,
            3,
            4,
            1,
            3,
            (sh_coeff_count(self.sh_degree) - 1) * 3,
            self.feature_dim,
            self.shadow_latent_dim,
            self.normal_dim,
        ]
    }
}

/// Error from building or editing a parameter set.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelError {
    /// A row had the wrong number of values for its group.
    RowWidth {
        param: Param,
        expected: usize,
        got: usize,
    },
    /// A mask or index list did not fit the set.
    Length { expected: usize, got: usize },
    /// SH degree above 3.
    ShDegree(u32),
}

impl std::fmt::Display for ModelError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ModelError::RowWidth {
                param,
                expected,
                got,
            } => write!(
                f,
                "parameter group {} takes {expected} values per Gaussian, got {got}",
                param.name()
            ),
            ModelError::Length { expected, got } => {
                write!(
                    f,
                    "expected {expected} entries (one per Gaussian), got {got}"
                )
            }
            ModelError::ShDegree(d) => write!(f, "SH degree {d} is not supported (0..=3)"),
        }
    }
}

impl std::error::Error for ModelError {}

/// One flat `Vec<f32>` per [`Param`] group, all with the same number of rows.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamSet {
    dims: [usize; Param::COUNT],
    data: [Vec<f32>; Param::COUNT],
    len: usize,
}

impl ParamSet {
    /// An empty set with the given group widths.
    pub fn new(dims: [usize; Param::COUNT]) -> Self {
        Self {
            dims,
            data: Default::default(),
            len: 0,
        }
    }

    /// `len` rows of zeros with the same widths as `self` (gradients, optimiser moments).
    pub fn zeros_like(&self) -> Self {
        let mut out = Self::new(self.dims);
        out.push_zeros(self.len);
        out
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn dims(&self) -> [usize; Param::COUNT] {
        self.dims
    }

    pub fn dim(&self, p: Param) -> usize {
        self.dims[p.index()]
    }

    pub fn get(&self, p: Param) -> &[f32] {
        &self.data[p.index()]
    }

    pub fn get_mut(&mut self, p: Param) -> &mut [f32] {
        &mut self.data[p.index()]
    }

    pub fn row(&self, p: Param, i: usize) -> &[f32] {
        let d = self.dims[p.index()];
        &self.data[p.index()][i * d..(i + 1) * d]
    }

    pub fn row_mut(&mut self, p: Param, i: usize) -> &mut [f32] {
        let d = self.dims[p.index()];
        &mut self.data[p.index()][i * d..(i + 1) * d]
    }

    /// Sets every value to zero, keeping the rows.
    pub fn fill_zero(&mut self) {
        for group in &mut self.data {
            group.fill(0.0);
        }
    }

    /// Appends one row; `row_of(p)` gives the values of group `p`.
    pub fn push_row<'a>(&mut self, row_of: impl Fn(Param) -> &'a [f32]) -> Result<(), ModelError> {
        for p in Param::ALL {
            let got = row_of(p).len();
            if got != self.dim(p) {
                return Err(ModelError::RowWidth {
                    param: p,
                    expected: self.dim(p),
                    got,
                });
            }
        }
        for p in Param::ALL {
            self.data[p.index()].extend_from_slice(row_of(p));
        }
        self.len += 1;
        Ok(())
    }

    /// Appends `n` rows of zeros.
    pub fn push_zeros(&mut self, n: usize) {
        for (group, &d) in self.data.iter_mut().zip(&self.dims) {
            group.resize(group.len() + n * d, 0.0);
        }
        self.len += n;
    }

    /// Appends copies of `src`'s rows `indices` (in that order). Widths must match.
    pub fn append_rows(&mut self, src: &ParamSet, indices: &[usize]) -> Result<(), ModelError> {
        for p in Param::ALL {
            if src.dim(p) != self.dim(p) {
                return Err(ModelError::RowWidth {
                    param: p,
                    expected: self.dim(p),
                    got: src.dim(p),
                });
            }
        }
        if let Some(&bad) = indices.iter().find(|&&i| i >= src.len) {
            return Err(ModelError::Length {
                expected: src.len,
                got: bad + 1,
            });
        }
        for p in Param::ALL {
            let group = &mut self.data[p.index()];
            group.reserve(indices.len() * src.dim(p));
            for &i in indices {
                group.extend_from_slice(src.row(p, i));
            }
        }
        self.len += indices.len();
        Ok(())
    }

    /// Keeps the rows whose `keep` entry is true, in order.
    pub fn retain(&mut self, keep: &[bool]) -> Result<(), ModelError> {
        if keep.len() != self.len {
            return Err(ModelError::Length {
                expected: self.len,
                got: keep.len(),
            });
        }
        for (group, &d) in self.data.iter_mut().zip(&self.dims) {
            let mut write = 0;
            for (read, &k) in keep.iter().enumerate() {
                if k {
                    group.copy_within(read * d..(read + 1) * d, write * d);
                    write += 1;
                }
            }
            group.truncate(write * d);
        }
        self.len = keep.iter().filter(|&&k| k).count();
        Ok(())
    }
}

/// A Gaussian model: its parameters and the SH degree they are laid out for.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianModel {
    pub params: ParamSet,
    layout: ModelLayout,
}

impl GaussianModel {
    pub fn new(layout: ModelLayout) -> Result<Self, ModelError> {
        if layout.sh_degree > 3 {
            return Err(ModelError::ShDegree(layout.sh_degree));
        }
        Ok(Self {
            params: ParamSet::new(layout.dims()),
            layout,
        })
    }

    pub fn layout(&self) -> ModelLayout {
        self.layout
    }

    pub fn len(&self) -> usize {
        self.params.len()
    }

    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model_with(n: usize) -> GaussianModel {
        let mut m = GaussianModel::new(ModelLayout {
            sh_degree: 1,
            feature_dim: 2,
            shadow_latent_dim: 0,
            normal_dim: 3,
        })
        .unwrap();
        for i in 0..n {
            let rows: Vec<Vec<f32>> = Param::ALL
                .iter()
                .map(|&p| (0..m.params.dim(p)).map(|k| (i * 100 + k) as f32).collect())
                .collect();
            m.params.push_row(|p| &rows[p.index()]).unwrap();
        }
        m
    }

    #[test]
    fn rows_stay_in_step_across_retain_and_append() {
        let mut m = model_with(4);
        m.params.retain(&[true, false, true, false]).unwrap();
        assert_eq!(m.len(), 2);
        assert_eq!(m.params.row(Param::Mean, 1), &[200.0, 201.0, 202.0]);
        assert_eq!(m.params.row(Param::ShRest, 1)[8], 208.0);
        let src = m.params.clone();
        m.params.append_rows(&src, &[1, 0]).unwrap();
        assert_eq!(m.len(), 4);
        assert_eq!(m.params.row(Param::Feature, 2), &[200.0, 201.0]);
        assert_eq!(m.params.row(Param::Feature, 3), &[0.0, 1.0]);
        assert!(m.params.get(Param::ShadowLatent).is_empty());
    }

    #[test]
    fn bad_rows_and_masks_are_errors() {
        let mut m = model_with(1);
        assert!(matches!(
            m.params.retain(&[true, true]),
            Err(ModelError::Length { .. })
        ));
        // Every group gets a row of the right width except the means, which get 2 values.
        let rows: Vec<Vec<f32>> = Param::ALL
            .iter()
            .map(|&p| vec![0.0; if p == Param::Mean { 2 } else { m.params.dim(p) }])
            .collect();
        let err = m.params.push_row(|p| &rows[p.index()]);
        assert!(matches!(
            err,
            Err(ModelError::RowWidth {
                param: Param::Mean,
                ..
            })
        ));
        assert_eq!(m.len(), 1);
        let src = m.params.clone();
        assert!(m.params.append_rows(&src, &[3]).is_err());
        assert!(GaussianModel::new(ModelLayout::sh(4)).is_err());
    }
}
