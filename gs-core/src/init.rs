//! Initial Gaussians from a point set or random points in a sphere, and the small seeded
//! RNG the training code uses.
//!
//! As in 3DGS: one isotropic Gaussian per point, scale `sqrt(mean of the squared
//! distances to the 3 nearest neighbours)` (the reference code's `distCUDA2`, clamped at
//! `1e-7` squared), identity rotation, opacity 0.1, SH DC from the point colour (higher
//! SH coefficients zero). Appearance features start at zero and shadow latents at one
//! (DESIGN.md: "l_i initialised to ones").
//!
//! Invariants:
//! - the nearest-neighbour search is a k-d tree (O(N log N)); results do not depend on
//!   the thread count;
//! - non-finite points (or colours) are dropped and counted, never stored;
//! - empty input, or fewer than 2 usable points (no neighbour to size a Gaussian), is an
//!   error.

use glam::Vec3;
use rayon::prelude::*;

use crate::model::{GaussianModel, ModelError, ModelLayout, Param};
use crate::sh::rgb_to_sh_dc;

/// Opacity of a fresh Gaussian.
pub const INITIAL_OPACITY: f32 = 0.1;
/// Floor on the mean squared neighbour distance (3DGS `clamp_min(.., 1e-7)`).
pub const MIN_NEIGHBOUR_DIST2: f32 = 1e-7;
const NEIGHBOURS: usize = 3;

pub use crate::rng::SplitMix64;

/// Error from initialisation.
#[derive(Debug, Clone, PartialEq)]
pub enum InitError {
    /// No points at all.
    Empty,
    /// After dropping non-finite points fewer than 2 remain.
    TooFewPoints {
        usable: usize,
        dropped: usize,
    },
    /// Colours given but not one per point.
    ColourCount {
        points: usize,
        colours: usize,
    },
    /// Sphere radius not finite and positive, or centre not finite.
    InvalidSphere,
    Model(ModelError),
}

impl std::fmt::Display for InitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            InitError::Empty => write!(f, "no points to initialise Gaussians from"),
            InitError::TooFewPoints { usable, dropped } => write!(
                f,
                "need at least 2 finite points to size Gaussians, got {usable} \
                 ({dropped} non-finite dropped)"
            ),
            InitError::ColourCount { points, colours } => {
                write!(f, "{points} points but {colours} colours")
            }
            InitError::InvalidSphere => {
                write!(
                    f,
                    "sphere needs a finite centre and a finite positive radius"
                )
            }
            InitError::Model(e) => write!(f, "model: {e}"),
        }
    }
}

impl std::error::Error for InitError {}

impl From<ModelError> for InitError {
    fn from(e: ModelError) -> Self {
        InitError::Model(e)
    }
}

/// A fresh model and what was dropped on the way.
#[derive(Clone, Debug)]
pub struct InitResult {
    pub model: GaussianModel,
    /// Points skipped because a coordinate or colour was NaN or infinite.
    pub dropped_non_finite: usize,
}

/// A k-d tree over points, stored implicitly: `order[lo..hi]` is a subtree whose root is
/// the median `order[(lo + hi) / 2]`, split on `axis[(lo + hi) / 2]`.
struct KdTree<'a> {
    points: &'a [Vec3],
    order: Vec<u32>,
    axis: Vec<u8>,
}

impl<'a> KdTree<'a> {
    fn build(points: &'a [Vec3]) -> Self {
        let mut tree = KdTree {
            points,
            order: (0..points.len() as u32).collect(),
            axis: vec![0; points.len()],
        };
        tree.build_range(0, points.len());
        tree
    }

    fn build_range(&mut self, lo: usize, hi: usize) {
        if hi - lo <= 1 {
            return;
        }
        let (mut min, mut max) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for &i in &self.order[lo..hi] {
            min = min.min(self.points[i as usize]);
            max = max.max(self.points[i as usize]);
        }
        let extent = max - min;
        let axis = if extent.x >= extent.y && extent.x >= extent.z {
            0
        } else if extent.y >= extent.z {
            1
        } else {
            2
        };
        let mid = (lo + hi) / 2;
        let pts = self.points;
        // Ties broken by index so the tree (and so the search) is fully deterministic.
        self.order[lo..hi].select_nth_unstable_by(mid - lo, |&a, &b| {
            pts[a as usize][axis]
                .total_cmp(&pts[b as usize][axis])
                .then(a.cmp(&b))
        });
        self.axis[mid] = axis as u8;
        self.build_range(lo, mid);
        self.build_range(mid + 1, hi);
    }

    /// The `K` smallest squared distances from `q` to points other than `skip`.
    fn nearest(&self, q: Vec3, skip: u32, best: &mut [f32; NEIGHBOURS]) {
        best.fill(f32::INFINITY);
        self.search(0, self.order.len(), q, skip, best);
    }

    fn search(&self, lo: usize, hi: usize, q: Vec3, skip: u32, best: &mut [f32; NEIGHBOURS]) {
        if lo >= hi {
            return;
        }
        let mid = (lo + hi) / 2;
        let idx = self.order[mid];
        let p = self.points[idx as usize];
        if idx != skip {
            let d2 = (p - q).length_squared();
            if d2 < best[NEIGHBOURS - 1] {
                // Insert into the sorted list of the K best.
                let mut k = NEIGHBOURS - 1;
                while k > 0 && best[k - 1] > d2 {
                    best[k] = best[k - 1];
                    k -= 1;
                }
                best[k] = d2;
            }
        }
        if hi - lo == 1 {
            return;
        }
        let axis = self.axis[mid] as usize;
        let diff = q[axis] - p[axis];
        let (near, far) = if diff < 0.0 {
            ((lo, mid), (mid + 1, hi))
        } else {
            ((mid + 1, hi), (lo, mid))
        };
        self.search(near.0, near.1, q, skip, best);
        if diff * diff < best[NEIGHBOURS - 1] {
            self.search(far.0, far.1, q, skip, best);
        }
    }
}

/// Mean squared distance from each point to its (up to) 3 nearest other points, floored
/// at [`MIN_NEIGHBOUR_DIST2`]. Needs at least 2 points.
pub fn mean_neighbour_dist2(points: &[Vec3]) -> Vec<f32> {
    let tree = KdTree::build(points);
    let k = NEIGHBOURS.min(points.len().saturating_sub(1)).max(1);
    (0..points.len())
        .into_par_iter()
        .map(|i| {
            let mut best = [f32::INFINITY; NEIGHBOURS];
            tree.nearest(points[i], i as u32, &mut best);
            let mean = best[..k].iter().sum::<f32>() / k as f32;
            mean.max(MIN_NEIGHBOUR_DIST2)
        })
        .collect()
}

/// Gaussians at `points`, coloured by `colours` (RGB in [0, 1]; grey 0.5 when `None`).
pub fn from_points(
    points: &[Vec3],
    colours: Option<&[[f32; 3]]>,
    layout: ModelLayout,
) -> Result<InitResult, InitError> {
    if points.is_empty() {
        return Err(InitError::Empty);
    }
    if let Some(c) = colours {
        if c.len() != points.len() {
            return Err(InitError::ColourCount {
                points: points.len(),
                colours: c.len(),
            });
        }
    }
    let grey = [0.5f32; 3];
    let mut kept_points = Vec::with_capacity(points.len());
    let mut kept_colours = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let c = colours.map_or(grey, |c| c[i]);
        if p.is_finite() && c.iter().all(|v| v.is_finite()) {
            kept_points.push(*p);
            kept_colours.push(c);
        }
    }
    let dropped = points.len() - kept_points.len();
    if kept_points.len() < 2 {
        return Err(InitError::TooFewPoints {
            usable: kept_points.len(),
            dropped,
        });
    }
    let dist2 = mean_neighbour_dist2(&kept_points);

    let mut model = GaussianModel::new(layout)?;
    let n = kept_points.len();
    model.params.push_zeros(n);
    let p = &mut model.params;
    for (i, pt) in kept_points.iter().enumerate() {
        p.row_mut(Param::Mean, i).copy_from_slice(&pt.to_array());
        let log_scale = 0.5 * dist2[i].ln();
        p.row_mut(Param::LogScale, i).fill(log_scale);
        p.row_mut(Param::Rotation, i)
            .copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(INITIAL_OPACITY);
        let dc = p.row_mut(Param::ShDc, i);
        for c in 0..3 {
            dc[c] = rgb_to_sh_dc(kept_colours[i][c]);
        }
    }
    p.get_mut(Param::ShadowLatent).fill(1.0);
    Ok(InitResult {
        model,
        dropped_non_finite: dropped,
    })
}

/// `n` Gaussians at points uniform in the ball (`centre`, `radius`), with uniformly
/// random colours (as 3DGS's random initialisation), sized by their neighbours.
pub fn random_in_sphere(
    n: usize,
    centre: Vec3,
    radius: f32,
    layout: ModelLayout,
    seed: u64,
) -> Result<InitResult, InitError> {
    if !centre.is_finite() || !radius.is_finite() || radius <= 0.0 {
        return Err(InitError::InvalidSphere);
    }
    if n == 0 {
        return Err(InitError::Empty);
    }
    let mut rng = SplitMix64::new(seed);
    let mut points = Vec::with_capacity(n);
    let mut colours = Vec::with_capacity(n);
    while points.len() < n {
        let v = Vec3::new(
            2.0 * rng.next_f32() - 1.0,
            2.0 * rng.next_f32() - 1.0,
            2.0 * rng.next_f32() - 1.0,
        );
        if v.length_squared() <= 1.0 {
            points.push(centre + v * radius);
            colours.push([rng.next_f32(), rng.next_f32(), rng.next_f32()]);
        }
    }
    from_points(&points, Some(&colours), layout)
}

/// `ln(p / (1 - p))`.
pub fn inverse_sigmoid(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute_force(points: &[Vec3]) -> Vec<f32> {
        let k = NEIGHBOURS.min(points.len() - 1);
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut d: Vec<f32> = points
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(_, q)| (*p - *q).length_squared())
                    .collect();
                d.sort_by(f32::total_cmp);
                (d[..k].iter().sum::<f32>() / k as f32).max(MIN_NEIGHBOUR_DIST2)
            })
            .collect()
    }

    #[test]
    fn kd_tree_matches_brute_force() {
        let mut rng = SplitMix64::new(5);
        // A clustered, partly degenerate (planar slab, duplicates) cloud.
        let mut pts: Vec<Vec3> = (0..1500)
            .map(|i| {
                let z = if i % 3 == 0 { 0.0 } else { rng.next_f32() };
                Vec3::new(rng.next_f32() * 4.0, rng.next_f32(), z)
            })
            .collect();
        pts.extend_from_within(..20);
        let fast = mean_neighbour_dist2(&pts);
        let slow = brute_force(&pts);
        for (a, b) in fast.iter().zip(&slow) {
            assert!((a - b).abs() <= 1e-6 * b.max(1e-6), "{a} vs {b}");
        }
        // Duplicates sit at distance zero from their twin: the mean is floored, finite.
        assert!(fast
            .iter()
            .all(|v| v.is_finite() && *v >= MIN_NEIGHBOUR_DIST2));
        // Two points: each one's only neighbour is the other.
        let two = mean_neighbour_dist2(&[Vec3::ZERO, Vec3::new(0.0, 3.0, 4.0)]);
        assert_eq!(two, vec![25.0, 25.0]);
    }

    #[test]
    fn grid_points_get_the_spacing_as_scale() {
        // On a cubic grid of spacing 0.2 every interior point has 6 neighbours at 0.2.
        let mut pts = Vec::new();
        for x in 0..10 {
            for y in 0..10 {
                for z in 0..10 {
                    pts.push(Vec3::new(x as f32, y as f32, z as f32) * 0.2);
                }
            }
        }
        let colours = vec![[0.8f32, 0.2, 0.5]; pts.len()];
        let r = from_points(&pts, Some(&colours), ModelLayout::sh(2)).unwrap();
        assert_eq!(r.dropped_non_finite, 0);
        let m = &r.model;
        assert_eq!(m.len(), 1000);
        let centre = 5 * 100 + 5 * 10 + 5;
        let s = m.params.row(Param::LogScale, centre);
        assert!((s[0].exp() - 0.2).abs() < 1e-5 && s[0] == s[1] && s[1] == s[2]);
        assert_eq!(m.params.row(Param::Rotation, 0), &[1.0, 0.0, 0.0, 0.0]);
        assert!((sigmoid(m.params.row(Param::OpacityLogit, 0)[0]) - 0.1).abs() < 1e-6);
        let rgb = crate::sh::sh_to_rgb(&m.params, 2, Vec3::new(9.0, 1.0, -3.0)).unwrap();
        assert!((rgb[0] - 0.8).abs() < 1e-6 && (rgb[2] - 0.5).abs() < 1e-6);
        assert!(m.params.get(Param::ShRest).iter().all(|&v| v == 0.0));
    }

    #[test]
    fn large_clouds_are_fast_enough_and_deterministic() {
        let r1 = random_in_sphere(
            100_000,
            Vec3::new(1.0, 2.0, 3.0),
            2.0,
            ModelLayout::sh(0),
            9,
        )
        .unwrap();
        let r2 = random_in_sphere(
            100_000,
            Vec3::new(1.0, 2.0, 3.0),
            2.0,
            ModelLayout::sh(0),
            9,
        )
        .unwrap();
        assert_eq!(r1.model, r2.model);
        assert_eq!(r1.model.len(), 100_000);
        let means = r1.model.params.get(Param::Mean);
        for i in 0..100_000 {
            let p = Vec3::from_slice(&means[i * 3..i * 3 + 3]);
            assert!((p - Vec3::new(1.0, 2.0, 3.0)).length() <= 2.0 + 1e-5);
        }
        // Uniform in a ball of radius 2: mean neighbour spacing ~ (4/3 pi 8 / 1e5)^(1/3).
        let s = r1.model.params.get(Param::LogScale)[0].exp();
        assert!(s > 0.005 && s < 0.1, "{s}");
    }

    #[test]
    fn bad_input_is_an_error_or_a_counted_drop() {
        let layout = ModelLayout::sh(0);
        assert!(matches!(
            from_points(&[], None, layout),
            Err(InitError::Empty)
        ));
        let pts = [Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0), Vec3::ONE];
        let r = from_points(&pts, None, layout).unwrap();
        assert_eq!((r.model.len(), r.dropped_non_finite), (2, 1));
        assert!(r
            .model
            .params
            .get(Param::Mean)
            .iter()
            .all(|v| v.is_finite()));
        let bad_colour = [[0.5; 3], [0.5; 3], [f32::INFINITY, 0.0, 0.0]];
        let r = from_points(&pts, Some(&bad_colour), layout);
        assert!(matches!(
            r,
            Err(InitError::TooFewPoints {
                usable: 1,
                dropped: 2
            })
        ));
        assert!(matches!(
            from_points(&pts, Some(&bad_colour[..2]), layout),
            Err(InitError::ColourCount { .. })
        ));
        assert!(matches!(
            random_in_sphere(10, Vec3::ZERO, -1.0, layout, 1),
            Err(InitError::InvalidSphere)
        ));
        assert!(matches!(
            from_points(&pts, None, ModelLayout::sh(7)),
            Err(InitError::Model(_))
        ));
    }

    #[test]
    fn rng_is_reproducible_and_roughly_normal() {
        let mut a = SplitMix64::new(42);
        let mut b = SplitMix64::new(42);
        let xs: Vec<f32> = (0..20000).map(|_| a.normal()).collect();
        let ys: Vec<f32> = (0..20000).map(|_| b.normal()).collect();
        assert_eq!(xs, ys);
        let mean = xs.iter().map(|&v| v as f64).sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        // Standard errors: 1/sqrt(2e4) = 0.007 for the mean, ~0.01 for the variance.
        assert!(
            mean.abs() < 0.03 && (var - 1.0).abs() < 0.05,
            "{mean} {var}"
        );
        let mut v: Vec<usize> = (0..10).collect();
        a.shuffle(&mut v);
        let mut sorted = v.clone();
        sorted.sort();
        assert_eq!(sorted, (0..10).collect::<Vec<_>>());
    }
}
