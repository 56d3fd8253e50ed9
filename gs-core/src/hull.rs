//! Visual hull by voxel carving: initial points for the Gaussians from foreground masks and
//! known camera poses, with no ground-truth model of the target.
//!
//! A box (the scene box) is cut into cubic voxels. Each view votes on each voxel: the voxel's
//! projected footprint (the pixel rectangle covering its 8 projected corners, grown by
//! `margin_px`) must contain at least one foreground pixel, else the view carves it. A view
//! votes only when the voxel lies wholly in front of the camera and its whole grown footprint
//! lies inside the image; otherwise it abstains (a view that does not see a voxel cannot
//! carve it). A voxel survives when no voting view carves it and at least `min_views` views
//! voted. The surface voxels (occupied, with at least one empty 6-neighbour; outside the grid
//! counts as empty) become the points, at the voxel centres, with outward normals from the
//! occupancy gradient, subsampled to the requested count by a seeded shuffle
//! ([`HullSampling::Shell`]); or every occupied voxel is a candidate and each point lies at a
//! seeded uniform position inside its voxel ([`HullSampling::Volume`]), so the points fill
//! the hull and some lie on the true surface wherever it is inside the hull.
//! [`HullSampling::Silhouette`] ([`carve_silhouette_consistent`]) draws candidates inside
//! the occupied voxels and keeps those whose own projection is foreground in every view
//! that sees them, removing the carving's conservative margin.
//! [`carve_photo_consistent`] also takes the views' images: it draws candidates inside the
//! occupied voxels, drops those that project onto background in a view (the carving's
//! conservative margin), and draws the points with weights favouring candidates whose colour
//! agrees across the views (soft voxel colouring; occlusion ignored).
//!
//! [`CarvedVolume`] keeps the occupancy between calls: an online trainer carves it with each
//! new view as it arrives and asks whether a point is still inside (to prune Gaussians the
//! later views show to be outside the object). Carving is monotone: a voxel once carved stays
//! carved, and the result after views A then B equals the result after B then A.
//!
//! Invariants:
//! - conservative: with `margin_px >= 1` (masks sampled at pixel centres), every voxel that
//!   meets the true object survives, so the carved hull contains the object (within the grid);
//! - deterministic: the result depends only on the inputs, never on the thread count (each
//!   voxel is decided independently; collections keep index order; the shuffle is seeded);
//! - never panics on bad input: empty views, mask sizes that do not match the camera, a zero
//!   resolution, a degenerate or non-finite box, too many voxels, or everything carved away
//!   are [`HullError`]s; every returned point and normal is finite, every normal unit length.

mod carve;
mod colour;
mod photo;
mod surface;
mod volume;

pub use carve::carve;
pub use colour::{sample_colours, ColourView};
pub use photo::{
    carve_photo_consistent, carve_silhouette_consistent, PhotoOptions, PhotoStats,
    SILHOUETTE_SAMPLES_PER_VOXEL,
};
pub use volume::CarvedVolume;

use glam::Vec3;

use crate::camera::Camera;

/// A mask pixel is foreground when its value is at least this.
pub const FOREGROUND_THRESHOLD: u8 = 128;
/// Upper bound on the voxel count (a 320^3 grid), so a bad resolution is an error rather
/// than an allocation failure.
pub const MAX_VOXELS: usize = 1 << 25;
/// Camera-frame depth below which a voxel corner counts as behind the camera, metres.
const NEAR_M: f32 = 1e-4;

/// One view for carving: a pinhole camera and its foreground mask.
#[derive(Clone, Copy, Debug)]
pub struct HullView<'a> {
    pub camera: Camera,
    /// `width * height` values, row-major; foreground where `>= FOREGROUND_THRESHOLD`.
    pub mask: &'a [u8],
}

/// The carving volume: an axis-aligned box cut into cubic voxels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HullGrid {
    pub min_m: Vec3,
    pub max_m: Vec3,
    /// Voxels along the box's longest side; the other sides get as many voxels of the same
    /// size as cover them.
    pub voxels_along_longest: u32,
}

impl HullGrid {
    /// The cube around a bounding sphere.
    pub fn around_sphere(centre: Vec3, radius_m: f32, voxels_along_longest: u32) -> Self {
        HullGrid {
            min_m: centre - Vec3::splat(radius_m),
            max_m: centre + Vec3::splat(radius_m),
            voxels_along_longest,
        }
    }

    /// Voxel edge length and voxel counts per axis, after validation.
    pub fn layout(&self) -> Result<(f32, [usize; 3]), HullError> {
        if self.voxels_along_longest == 0 {
            return Err(HullError::ZeroResolution);
        }
        let extent = self.max_m - self.min_m;
        if !(self.min_m.is_finite() && self.max_m.is_finite()) || extent.min_element() <= 0.0 {
            return Err(HullError::InvalidBox {
                min_m: self.min_m.to_array(),
                max_m: self.max_m.to_array(),
            });
        }
        let voxel_m = extent.max_element() / self.voxels_along_longest as f32;
        let mut dims = [0usize; 3];
        for (axis, d) in dims.iter_mut().enumerate() {
            // Floating point can put the ratio a hair above an integer: round that away.
            let ratio = extent[axis] / voxel_m;
            *d = ((ratio - 1e-4).ceil() as usize).max(1);
        }
        let total = dims[0]
            .checked_mul(dims[1])
            .and_then(|v| v.checked_mul(dims[2]))
            .unwrap_or(usize::MAX);
        if total > MAX_VOXELS {
            return Err(HullError::TooManyVoxels {
                voxels: total,
                max: MAX_VOXELS,
            });
        }
        Ok((voxel_m, dims))
    }
}

/// Carving settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HullOptions {
    /// Points to return (fewer when the hull has fewer surface voxels).
    pub point_count: usize,
    /// Pixels added around each footprint before the mask test (1 makes the carving
    /// conservative for masks sampled at pixel centres).
    pub margin_px: u32,
    /// A voxel needs at least this many voting views to survive (1: at least one view
    /// must have seen it).
    pub min_views: u32,
    /// Seed of the subsampling shuffle (and of the in-voxel positions for `Volume`).
    pub seed: u64,
    /// Where the points go: the hull's surface voxels or all its voxels.
    pub sampling: HullSampling,
}

/// Which voxels give points.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum HullSampling {
    /// Surface voxels (an empty 6-neighbour), at their centres.
    #[default]
    Shell,
    /// Every occupied voxel, at a seeded uniform position inside it. Interior voxels have
    /// no outward direction: their normal is the occupancy-gradient fallback (+z where the
    /// neighbourhood is full), which matters only for colour sampling.
    Volume,
    /// Points inside occupied voxels that project onto the foreground in every view that
    /// sees them ([`carve_silhouette_consistent`] with [`SILHOUETTE_SAMPLES_PER_VOXEL`]).
    Silhouette,
}

impl Default for HullOptions {
    fn default() -> Self {
        HullOptions {
            point_count: 10_000,
            margin_px: 1,
            min_views: 1,
            seed: 0,
            sampling: HullSampling::Shell,
        }
    }
}

/// Points on the carved hull's surface.
#[derive(Clone, Debug, PartialEq)]
pub struct HullPoints {
    /// Surface voxel centres, world frame, metres (in voxel index order).
    pub points: Vec<Vec3>,
    /// Outward unit normals, one per point.
    pub normals: Vec<Vec3>,
    pub voxel_m: f32,
    pub dims: [usize; 3],
    /// Voxels that survived carving.
    pub occupied: usize,
    /// Surface voxels before subsampling.
    pub surface: usize,
    /// The carved occupancy, one byte per voxel (1 occupied), x fastest then y then z.
    pub occupancy: Vec<u8>,
}

/// Why carving could not produce points.
#[derive(Clone, Debug, PartialEq)]
pub enum HullError {
    /// No views given.
    NoViews,
    /// A view's mask does not have `width * height` values.
    MaskSize {
        view: usize,
        expected: usize,
        got: usize,
    },
    /// A view's camera has a zero-sized image, non-finite pose or non-positive focal length.
    BadCamera {
        view: usize,
    },
    /// `voxels_along_longest` is zero.
    ZeroResolution,
    /// The box is not finite or has a side of zero or negative length.
    InvalidBox {
        min_m: [f32; 3],
        max_m: [f32; 3],
    },
    TooManyVoxels {
        voxels: usize,
        max: usize,
    },
    /// `point_count` is zero.
    ZeroPointCount,
    /// Every voxel was carved (or seen by fewer than `min_views` views).
    NothingLeft {
        voxels: usize,
    },
}

impl std::fmt::Display for HullError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HullError::NoViews => write!(f, "visual hull: no views to carve with"),
            HullError::MaskSize {
                view,
                expected,
                got,
            } => write!(
                f,
                "visual hull: view {view}'s mask has {got} values, its camera {expected} pixels"
            ),
            HullError::BadCamera { view } => write!(
                f,
                "visual hull: view {view}'s camera has an empty image, a non-finite pose or a \
                 non-positive focal length"
            ),
            HullError::ZeroResolution => write!(f, "visual hull: resolution must be positive"),
            HullError::InvalidBox { min_m, max_m } => write!(
                f,
                "visual hull: box {min_m:?}..{max_m:?} must be finite with positive sides"
            ),
            HullError::TooManyVoxels { voxels, max } => {
                write!(f, "visual hull: {voxels} voxels exceed the limit of {max}")
            }
            HullError::ZeroPointCount => write!(f, "visual hull: point_count must be positive"),
            HullError::NothingLeft { voxels } => write!(
                f,
                "visual hull: all {voxels} voxels were carved (no view's mask covers the box?)"
            ),
        }
    }
}

impl std::error::Error for HullError {}
