//! Adaptive density control: clone, split, prune, opacity reset (3DGS).
//!
//! Between densification steps [`DensifyStats`] accumulates, per Gaussian, the norm of
//! the 2D mean gradient in NDC units and how often it was visible, and its largest
//! screen radius. [`densify_and_prune`] then, on the mean gradient `accum / count`:
//! - clones Gaussians with mean gradient above the threshold and max scale at most
//!   `percent_dense * extent` (an exact copy, fresh optimiser moments);
//! - splits those above the threshold with a larger max scale into two children whose
//!   centres are drawn from N(0, diag(scale^2)) rotated by the Gaussian's rotation, with
//!   scales divided by 1.6 (3DGS `0.8 * N`, N = 2); the parent is removed;
//! - prunes Gaussians with opacity below `min_opacity`, and (when a limit is set) those
//!   whose screen radius exceeded `max_screen_radius_px` or whose max world scale exceeds
//!   `max_world_scale_fraction * extent`.
//!
//! Invariants:
//! - the model's parameters and the optimiser's two moment sets see the same row edits in
//!   the same order: new rows have zero moments, removed rows take theirs with them;
//! - the stats are reset (to the new row count) after each densification, as 3DGS does;
//! - deterministic: the only randomness is the caller's seeded [`SplitMix64`].

use glam::{Quat, Vec3};

use crate::init::{inverse_sigmoid, sigmoid, SplitMix64};
use crate::model::{GaussianModel, ModelError, Param};
use crate::optim::Adam;

/// Densification thresholds (3DGS defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifyConfig {
    /// Mean NDC gradient norm above which a Gaussian is densified.
    pub grad_threshold: f32,
    /// Clone/split boundary as a fraction of the scene extent.
    pub percent_dense: f32,
    /// Prune below this opacity.
    pub min_opacity: f32,
    /// Screen-space radius limit, pixels (3DGS: 20, applied only after the first opacity
    /// reset; the caller passes `None` before that).
    pub max_screen_radius_px: f32,
    /// World-space limit on the max scale, fraction of the extent (3DGS: 0.1).
    pub max_world_scale_fraction: f32,
    /// Scale divisor for split children (3DGS `0.8 * 2`).
    pub split_scale_divisor: f32,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        Self {
            grad_threshold: 2e-4,
            percent_dense: 0.01,
            min_opacity: 0.005,
            max_screen_radius_px: 20.0,
            max_world_scale_fraction: 0.1,
            split_scale_divisor: 1.6,
        }
    }
}

/// Error from densification.
#[derive(Debug, Clone, PartialEq)]
pub enum DensifyError {
    /// Stats, model and optimiser disagree on the number of Gaussians.
    RowCount {
        model: usize,
        stats: usize,
        optimiser: usize,
    },
    /// A per-Gaussian input to [`DensifyStats::accumulate`] has the wrong length.
    Length {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// Scene extent not finite and positive.
    Extent(f32),
    Model(ModelError),
}

impl std::fmt::Display for DensifyError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DensifyError::RowCount {
                model,
                stats,
                optimiser,
            } => write!(
                f,
                "row counts disagree: model {model}, stats {stats}, optimiser {optimiser}"
            ),
            DensifyError::Length {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            DensifyError::Extent(e) => write!(f, "scene extent {e} is not finite and positive"),
            DensifyError::Model(e) => write!(f, "model: {e}"),
        }
    }
}

impl std::error::Error for DensifyError {}

impl From<ModelError> for DensifyError {
    fn from(e: ModelError) -> Self {
        DensifyError::Model(e)
    }
}

/// Per-Gaussian statistics gathered between densification steps.
#[derive(Clone, Debug, PartialEq)]
pub struct DensifyStats {
    /// Sum of the NDC 2D mean gradient norms over the views where it was visible.
    pub grad_accum: Vec<f32>,
    /// Number of those views.
    pub visible_count: Vec<u32>,
    /// Largest screen radius seen, pixels.
    pub max_radius_px: Vec<f32>,
}

impl DensifyStats {
    pub fn new(n: usize) -> Self {
        Self {
            grad_accum: vec![0.0; n],
            visible_count: vec![0; n],
            max_radius_px: vec![0.0; n],
        }
    }

    pub fn len(&self) -> usize {
        self.grad_accum.len()
    }

    pub fn is_empty(&self) -> bool {
        self.grad_accum.is_empty()
    }

    /// Adds one view's per-Gaussian NDC gradient norms, visibility and radii. Non-finite
    /// gradient norms are skipped for that Gaussian (returned as a count).
    pub fn accumulate(
        &mut self,
        mean2d_grad_ndc: &[f32],
        visible: &[bool],
        radii_px: &[f32],
    ) -> Result<usize, DensifyError> {
        let n = self.len();
        for (what, got) in [
            ("mean2d_grad_ndc", mean2d_grad_ndc.len()),
            ("visible", visible.len()),
            ("radii_px", radii_px.len()),
        ] {
            if got != n {
                return Err(DensifyError::Length {
                    what,
                    expected: n,
                    got,
                });
            }
        }
        let mut skipped = 0;
        for i in 0..n {
            if !visible[i] {
                continue;
            }
            if !mean2d_grad_ndc[i].is_finite() || !radii_px[i].is_finite() {
                skipped += 1;
                continue;
            }
            self.grad_accum[i] += mean2d_grad_ndc[i];
            self.visible_count[i] += 1;
            self.max_radius_px[i] = self.max_radius_px[i].max(radii_px[i]);
        }
        Ok(skipped)
    }

    /// Mean gradient per Gaussian (0 where never visible).
    pub fn mean_grad(&self) -> Vec<f32> {
        self.grad_accum
            .iter()
            .zip(&self.visible_count)
            .map(|(&g, &c)| if c == 0 { 0.0 } else { g / c as f32 })
            .collect()
    }
}

/// What one densification step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensifyReport {
    pub before: usize,
    pub cloned: usize,
    /// Parents split (each became two children).
    pub split: usize,
    pub pruned: usize,
    pub after: usize,
}

fn max_scale(model: &GaussianModel, i: usize) -> f32 {
    let s = model.params.row(Param::LogScale, i);
    s[0].max(s[1]).max(s[2]).exp()
}

fn check_rows(
    model: &GaussianModel,
    adam: &Adam,
    stats: &DensifyStats,
) -> Result<(), DensifyError> {
    let n = model.len();
    if stats.len() != n || adam.m.len() != n || adam.v.len() != n {
        return Err(DensifyError::RowCount {
            model: n,
            stats: stats.len(),
            optimiser: adam.m.len(),
        });
    }
    Ok(())
}

/// One 3DGS densify-and-prune step. `screen_limit` enables the screen-radius prune
/// (3DGS enables it once the first opacity reset has happened). Resets `stats`.
pub fn densify_and_prune(
    model: &mut GaussianModel,
    adam: &mut Adam,
    stats: &mut DensifyStats,
    config: &DensifyConfig,
    scene_extent: f32,
    screen_limit: bool,
    rng: &mut SplitMix64,
) -> Result<DensifyReport, DensifyError> {
    if !scene_extent.is_finite() || scene_extent <= 0.0 {
        return Err(DensifyError::Extent(scene_extent));
    }
    check_rows(model, adam, stats)?;
    let n = model.len();
    let grads = stats.mean_grad();
    let dense_limit = config.percent_dense * scene_extent;
    let mut clone_idx = Vec::new();
    let mut split_idx = Vec::new();
    for (i, &g) in grads.iter().enumerate() {
        if g >= config.grad_threshold {
            if max_scale(model, i) <= dense_limit {
                clone_idx.push(i);
            } else {
                split_idx.push(i);
            }
        }
    }

    // New rows: clones (exact copies), then two children per split parent.
    let source = model.params.clone();
    model.params.append_rows(&source, &clone_idx)?;
    let children: Vec<usize> = split_idx.iter().flat_map(|&i| [i, i]).collect();
    let first_child = model.len();
    model.params.append_rows(&source, &children)?;
    let log_divisor = config.split_scale_divisor.ln();
    for (k, &parent) in children.iter().enumerate() {
        let row = first_child + k;
        let s = source.row(Param::LogScale, parent);
        let scale = Vec3::new(s[0].exp(), s[1].exp(), s[2].exp());
        let q = source.row(Param::Rotation, parent);
        // The stored quaternion is [w, x, y, z] and not necessarily unit.
        let rot = Quat::from_xyzw(q[1], q[2], q[3], q[0]);
        let rot = if rot.length_squared() > 1e-12 && rot.is_finite() {
            rot.normalize()
        } else {
            Quat::IDENTITY
        };
        let sample = Vec3::new(rng.normal(), rng.normal(), rng.normal()) * scale;
        let offset = rot * sample;
        let mean = model.params.row_mut(Param::Mean, row);
        for c in 0..3 {
            mean[c] += offset[c];
        }
        for v in model.params.row_mut(Param::LogScale, row) {
            *v -= log_divisor;
        }
    }
    let added = clone_idx.len() + children.len();
    adam.m.push_zeros(added);
    adam.v.push_zeros(added);

    // Keep mask over the grown set: split parents go, then the prune criteria apply to
    // everything (children included, as in 3DGS; their screen radius is not known yet).
    let total = model.len();
    let mut keep = vec![true; total];
    for &i in &split_idx {
        keep[i] = false;
    }
    let world_limit = config.max_world_scale_fraction * scene_extent;
    let mut pruned = 0;
    for (i, k) in keep.iter_mut().enumerate() {
        let opacity = sigmoid(model.params.row(Param::OpacityLogit, i)[0]);
        let radius = if i < n { stats.max_radius_px[i] } else { 0.0 };
        let too_big = screen_limit
            && (radius > config.max_screen_radius_px || max_scale(model, i) > world_limit);
        if *k && (opacity < config.min_opacity || too_big) {
            *k = false;
            pruned += 1;
        }
    }
    model.params.retain(&keep)?;
    adam.m.retain(&keep)?;
    adam.v.retain(&keep)?;
    *stats = DensifyStats::new(model.len());
    Ok(DensifyReport {
        before: n,
        cloned: clone_idx.len(),
        split: split_idx.len(),
        pruned,
        after: model.len(),
    })
}

/// Clamps every opacity to at most `max_opacity` (3DGS: 0.01) and zeroes the opacity
/// group's optimiser moments, as 3DGS's `reset_opacity`.
pub fn reset_opacity(model: &mut GaussianModel, adam: &mut Adam, max_opacity: f32) {
    let cap = inverse_sigmoid(max_opacity);
    for v in model.params.get_mut(Param::OpacityLogit) {
        *v = v.min(cap);
    }
    adam.reset_group(Param::OpacityLogit);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::ModelLayout;

    /// Gaussian i: mean (i, 0, 0), isotropic scale `scales[i]`, opacity `opacities[i]`,
    /// rotation 90 degrees about z, and recognisable values in every other group.
    fn model(scales: &[f32], opacities: &[f32]) -> GaussianModel {
        let mut m = GaussianModel::new(ModelLayout {
            sh_degree: 1,
            feature_dim: 2,
            shadow_latent_dim: 1,
            normal_dim: 3,
        })
        .unwrap();
        let n = scales.len();
        m.params.push_zeros(n);
        let h = std::f32::consts::FRAC_1_SQRT_2;
        for i in 0..n {
            let p = &mut m.params;
            p.row_mut(Param::Mean, i)
                .copy_from_slice(&[i as f32, 0.0, 0.0]);
            p.row_mut(Param::LogScale, i).fill(scales[i].ln());
            p.row_mut(Param::Rotation, i)
                .copy_from_slice(&[2.0 * h, 0.0, 0.0, 2.0 * h]);
            p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(opacities[i]);
            p.row_mut(Param::ShDc, i).fill(i as f32 + 0.5);
            p.row_mut(Param::Feature, i).fill(i as f32 + 0.25);
            p.row_mut(Param::Normal, i)
                .copy_from_slice(&[i as f32 + 0.75, 1.0, 0.0]);
        }
        m
    }

    /// Moments tagged with each row's index so their movement can be tracked.
    fn tagged_adam(m: &GaussianModel) -> Adam {
        let mut adam = Adam::new(&m.params);
        for i in 0..m.len() {
            adam.m.row_mut(Param::Mean, i).fill(100.0 + i as f32);
            adam.v.row_mut(Param::OpacityLogit, i)[0] = 200.0 + i as f32;
        }
        adam
    }

    #[test]
    fn clone_split_prune_keep_params_and_moments_in_step() {
        let extent = 10.0; // dense limit 0.1, world limit 1.0
                           //         0 clone, 1 split, 2 quiet, 3 quiet + faint, 4 quiet + huge on screen
        let scales = [0.05, 0.5, 0.05, 0.05, 0.05];
        let opac = [0.5, 0.5, 0.5, 0.001, 0.5];
        let mut m = model(&scales, &opac);
        let mut adam = tagged_adam(&m);
        let mut stats = DensifyStats::new(5);
        let vis = [true; 5];
        // Mean over two views: 3e-4 for 0 and 1, 1e-4 for the others.
        stats
            .accumulate(
                &[4e-4, 2e-4, 1e-4, 1e-4, 1e-4],
                &vis,
                &[1.0, 2.0, 3.0, 4.0, 30.0],
            )
            .unwrap();
        stats
            .accumulate(&[2e-4, 4e-4, 1e-4, 1e-4, 1e-4], &vis, &[1.0; 5])
            .unwrap();
        let mut rng = SplitMix64::new(3);
        let cfg = DensifyConfig::default();
        let r =
            densify_and_prune(&mut m, &mut adam, &mut stats, &cfg, extent, true, &mut rng).unwrap();
        assert_eq!(
            r,
            DensifyReport {
                before: 5,
                cloned: 1,
                split: 1,
                pruned: 2,
                after: 5
            }
        );
        // Order: kept originals 0, 2; clone of 0; two children of 1.
        let dc: Vec<f32> = m.params.get(Param::ShDc).chunks(3).map(|c| c[0]).collect();
        assert_eq!(dc, vec![0.5, 2.5, 0.5, 1.5, 1.5]);
        let feat: Vec<f32> = m
            .params
            .get(Param::Feature)
            .chunks(2)
            .map(|c| c[0])
            .collect();
        assert_eq!(feat, vec![0.25, 2.25, 0.25, 1.25, 1.25]);
        // The learned shading normal travels with its Gaussian: clone and children copy it.
        let normal: Vec<f32> = m
            .params
            .get(Param::Normal)
            .chunks(3)
            .map(|c| c[0])
            .collect();
        assert_eq!(normal, vec![0.75, 2.75, 0.75, 1.75, 1.75]);
        // Moments: survivors keep theirs, new rows start at zero.
        let mm: Vec<f32> = adam.m.get(Param::Mean).chunks(3).map(|c| c[0]).collect();
        assert_eq!(mm, vec![100.0, 102.0, 0.0, 0.0, 0.0]);
        let vo = adam.v.get(Param::OpacityLogit).to_vec();
        assert_eq!(vo, vec![200.0, 202.0, 0.0, 0.0, 0.0]);
        assert_eq!((adam.m.len(), adam.v.len(), stats.len()), (5, 5, 5));
        assert!(stats.grad_accum.iter().all(|&g| g == 0.0));
        // Clone is an exact copy; children have scale / 1.6, same rotation and opacity,
        // and centres displaced from the parent's.
        assert_eq!(m.params.row(Param::Mean, 2), m.params.row(Param::Mean, 0));
        for child in [3, 4] {
            let s = m.params.row(Param::LogScale, child)[0].exp();
            assert!((s - 0.5 / 1.6).abs() < 1e-6);
            assert_eq!(
                m.params.row(Param::Rotation, child),
                m.params.row(Param::Rotation, 1)
            );
            let mean = m.params.row(Param::Mean, child);
            assert_ne!(mean, &[1.0, 0.0, 0.0]);
            assert!(mean.iter().all(|v| v.is_finite()));
        }
    }

    /// Split children are distributed as N(parent, R diag(s^2) R^T): check the sample
    /// covariance for an anisotropic, rotated parent against the analytic one.
    #[test]
    fn split_samples_follow_the_rotated_gaussian() {
        let n_parents = 4000;
        let mut m = model(&vec![0.5; n_parents], &vec![0.5; n_parents]);
        let q = Quat::from_rotation_z(0.6) * Quat::from_rotation_x(0.3);
        let s = [2.0f32, 0.5, 0.25];
        for i in 0..n_parents {
            m.params.row_mut(Param::Mean, i).fill(0.0);
            m.params.row_mut(Param::LogScale, i).copy_from_slice(&[
                s[0].ln(),
                s[1].ln(),
                s[2].ln(),
            ]);
            m.params
                .row_mut(Param::Rotation, i)
                .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        }
        let mut adam = Adam::new(&m.params);
        let mut stats = DensifyStats::new(n_parents);
        stats
            .accumulate(
                &vec![1.0; n_parents],
                &vec![true; n_parents],
                &vec![1.0; n_parents],
            )
            .unwrap();
        let mut rng = SplitMix64::new(11);
        // Large extent limits so nothing is pruned for size.
        let cfg = DensifyConfig {
            max_world_scale_fraction: 1e3,
            ..DensifyConfig::default()
        };
        let r =
            densify_and_prune(&mut m, &mut adam, &mut stats, &cfg, 1.0, false, &mut rng).unwrap();
        assert_eq!(r.split, n_parents);
        assert_eq!(m.len(), 2 * n_parents);
        let means = m.params.get(Param::Mean);
        let mut cov = [[0.0f64; 3]; 3];
        for i in 0..m.len() {
            for a in 0..3 {
                for b in 0..3 {
                    cov[a][b] += means[i * 3 + a] as f64 * means[i * 3 + b] as f64;
                }
            }
        }
        let rm = glam::Mat3::from_quat(q);
        let d = glam::Mat3::from_diagonal(Vec3::new(s[0] * s[0], s[1] * s[1], s[2] * s[2]));
        let expected = rm * d * rm.transpose();
        for (a, row) in cov.iter().enumerate() {
            for (b, entry) in row.iter().enumerate() {
                let got = entry / m.len() as f64;
                let want = expected.col(b)[a] as f64;
                // 8000 samples: standard error of a covariance entry ~ 4 / sqrt(8000) = 0.045.
                assert!((got - want).abs() < 0.15, "cov[{a}][{b}] {got} vs {want}");
            }
        }
    }

    #[test]
    fn world_and_screen_prunes_only_when_enabled() {
        let extent = 1.0;
        let mut m = model(&[0.5, 0.05], &[0.5, 0.5]);
        let mut adam = Adam::new(&m.params);
        let mut stats = DensifyStats::new(2);
        stats
            .accumulate(&[0.0, 0.0], &[true, true], &[1.0, 50.0])
            .unwrap();
        let cfg = DensifyConfig::default();
        let mut rng = SplitMix64::new(1);
        let mut m2 = m.clone();
        let mut adam2 = adam.clone();
        let mut stats2 = stats.clone();
        let r = densify_and_prune(&mut m, &mut adam, &mut stats, &cfg, extent, false, &mut rng)
            .unwrap();
        assert_eq!(r.pruned, 0);
        let r = densify_and_prune(
            &mut m2,
            &mut adam2,
            &mut stats2,
            &cfg,
            extent,
            true,
            &mut rng,
        )
        .unwrap();
        assert_eq!((r.pruned, r.after), (2, 0));
    }

    #[test]
    fn mismatched_inputs_are_errors_and_invisible_views_do_not_count() {
        let mut m = model(&[0.1, 0.1], &[0.5, 0.5]);
        let mut adam = Adam::new(&m.params);
        let mut stats = DensifyStats::new(2);
        assert!(matches!(
            stats.accumulate(&[1.0], &[true, true], &[1.0, 1.0]),
            Err(DensifyError::Length { .. })
        ));
        let skipped = stats
            .accumulate(&[f32::NAN, 5.0], &[true, false], &[1.0, 1.0])
            .unwrap();
        assert_eq!(skipped, 1);
        assert_eq!(stats.mean_grad(), vec![0.0, 0.0]);
        let mut short = DensifyStats::new(1);
        let mut rng = SplitMix64::new(1);
        let cfg = DensifyConfig::default();
        assert!(matches!(
            densify_and_prune(&mut m, &mut adam, &mut short, &cfg, 1.0, false, &mut rng),
            Err(DensifyError::RowCount { .. })
        ));
        assert!(matches!(
            densify_and_prune(
                &mut m,
                &mut adam,
                &mut stats,
                &cfg,
                f32::NAN,
                false,
                &mut rng
            ),
            Err(DensifyError::Extent(_))
        ));
    }

    #[test]
    fn opacity_reset_caps_and_clears_moments() {
        let mut m = model(&[0.1, 0.1], &[0.9, 0.001]);
        let mut adam = tagged_adam(&m);
        adam.m.get_mut(Param::OpacityLogit).fill(3.0);
        reset_opacity(&mut m, &mut adam, 0.01);
        let o = m.params.get(Param::OpacityLogit);
        assert!((sigmoid(o[0]) - 0.01).abs() < 1e-6);
        assert!((sigmoid(o[1]) - 0.001).abs() < 1e-7);
        assert!(adam.m.get(Param::OpacityLogit).iter().all(|&v| v == 0.0));
        assert!(adam.v.get(Param::OpacityLogit).iter().all(|&v| v == 0.0));
        assert_eq!(adam.m.row(Param::Mean, 1)[0], 101.0);
    }
}
