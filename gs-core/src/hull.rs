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

use glam::{Vec3, Vec4};
use rayon::prelude::*;

use crate::camera::Camera;
use crate::rng::SplitMix64;

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

/// A view prepared for O(1) footprint tests: the summed-area table of its foreground.
struct PreparedView {
    camera: Camera,
    width: usize,
    height: usize,
    /// `(width + 1) * (height + 1)` prefix counts of foreground pixels.
    summed: Vec<u32>,
}

impl PreparedView {
    fn new(index: usize, view: &HullView) -> Result<Self, HullError> {
        let k = view.camera.intrinsics;
        let (width, height) = (k.width as usize, k.height as usize);
        let pose_ok = view.camera.rotation.is_finite() && view.camera.translation.is_finite();
        let intrinsics_ok =
            [k.fx, k.fy, k.cx, k.cy].iter().all(|v| v.is_finite()) && k.fx > 0.0 && k.fy > 0.0;
        if width == 0 || height == 0 || !pose_ok || !intrinsics_ok {
            return Err(HullError::BadCamera { view: index });
        }
        if view.mask.len() != width * height {
            return Err(HullError::MaskSize {
                view: index,
                expected: width * height,
                got: view.mask.len(),
            });
        }
        let stride = width + 1;
        let mut summed = vec![0u32; stride * (height + 1)];
        for y in 0..height {
            let mut row = 0u32;
            for x in 0..width {
                row += (view.mask[y * width + x] >= FOREGROUND_THRESHOLD) as u32;
                summed[(y + 1) * stride + x + 1] = summed[y * stride + x + 1] + row;
            }
        }
        Ok(PreparedView {
            camera: view.camera,
            width,
            height,
            summed,
        })
    }

    /// Foreground pixels in columns `x0..x1`, rows `y0..y1` (in bounds, non-empty).
    fn foreground_in(&self, x0: usize, x1: usize, y0: usize, y1: usize) -> u32 {
        let s = self.width + 1;
        self.summed[y1 * s + x1] + self.summed[y0 * s + x0]
            - self.summed[y0 * s + x1]
            - self.summed[y1 * s + x0]
    }

    /// `None` when this view abstains on the box `lo..hi`, else whether its footprint
    /// touches the foreground.
    fn vote(&self, lo: Vec3, hi: Vec3, margin_px: f32) -> Option<bool> {
        let (mut u_min, mut u_max) = (f32::INFINITY, f32::NEG_INFINITY);
        let (mut v_min, mut v_max) = (f32::INFINITY, f32::NEG_INFINITY);
        for corner in 0..8 {
            let p = Vec3::new(
                if corner & 1 == 0 { lo.x } else { hi.x },
                if corner & 2 == 0 { lo.y } else { hi.y },
                if corner & 4 == 0 { lo.z } else { hi.z },
            );
            let c = self.camera.world_to_camera(p);
            if c.z <= NEAR_M {
                return None;
            }
            let (u, v) = self.camera.camera_to_pixel(c);
            u_min = u_min.min(u);
            u_max = u_max.max(u);
            v_min = v_min.min(v);
            v_max = v_max.max(v);
        }
        // Pixel (x, y) covers [x, x+1) x [y, y+1).
        let x0 = (u_min - margin_px).floor();
        let x1 = (u_max + margin_px).floor() + 1.0;
        let y0 = (v_min - margin_px).floor();
        let y1 = (v_max + margin_px).floor() + 1.0;
        let inside = x0 >= 0.0
            && y0 >= 0.0
            && x1 <= self.width as f32
            && y1 <= self.height as f32
            && x0 < x1
            && y0 < y1;
        if !inside {
            return None;
        }
        Some(self.foreground_in(x0 as usize, x1 as usize, y0 as usize, y1 as usize) > 0)
    }
}

fn voxel_index(dims: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    x + dims[0] * (y + dims[1] * z)
}

/// The carved occupancy (one byte per voxel, 1 occupied, x fastest) after validating the
/// views, the grid and the point count; [`HullError::NothingLeft`] when every voxel is
/// carved.
fn carve_occupancy(
    views: &[HullView],
    grid: HullGrid,
    options: HullOptions,
) -> Result<(f32, [usize; 3], Vec<u8>), HullError> {
    if views.is_empty() {
        return Err(HullError::NoViews);
    }
    if options.point_count == 0 {
        return Err(HullError::ZeroPointCount);
    }
    let (voxel_m, dims) = grid.layout()?;
    let prepared: Vec<PreparedView> = views
        .iter()
        .enumerate()
        .map(|(i, v)| PreparedView::new(i, v))
        .collect::<Result<_, _>>()?;
    let total = dims[0] * dims[1] * dims[2];
    let margin_px = options.margin_px as f32;
    let min_views = options.min_views;
    let corner_of = |x: usize, y: usize, z: usize| {
        grid.min_m + Vec3::new(x as f32, y as f32, z as f32) * voxel_m
    };

    // Occupancy, one byte per voxel; each z-slab is decided independently.
    let slab = dims[0] * dims[1];
    let mut occupancy = vec![0u8; total];
    occupancy
        .par_chunks_mut(slab)
        .enumerate()
        .for_each(|(z, slab_out)| {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let lo = corner_of(x, y, z);
                    let hi = lo + Vec3::splat(voxel_m);
                    let mut voters = 0u32;
                    let mut carved = false;
                    for view in &prepared {
                        match view.vote(lo, hi, margin_px) {
                            Some(true) => voters += 1,
                            Some(false) => {
                                carved = true;
                                break;
                            }
                            None => {}
                        }
                    }
                    slab_out[x + dims[0] * y] = (!carved && voters >= min_views) as u8;
                }
            }
        });
    if occupancy.iter().all(|&o| o == 0) {
        return Err(HullError::NothingLeft { voxels: total });
    }
    Ok((voxel_m, dims, occupancy))
}

/// Carves the grid with the views and returns points on the hull's surface.
pub fn carve(
    views: &[HullView],
    grid: HullGrid,
    options: HullOptions,
) -> Result<HullPoints, HullError> {
    if options.sampling == HullSampling::Silhouette {
        return carve_silhouette_consistent(views, grid, options, SILHOUETTE_SAMPLES_PER_VOXEL)
            .map(|(hull, _)| hull);
    }
    let (voxel_m, dims, occupancy) = carve_occupancy(views, grid, options)?;
    let total = dims[0] * dims[1] * dims[2];
    let corner_of = |x: usize, y: usize, z: usize| {
        grid.min_m + Vec3::new(x as f32, y as f32, z as f32) * voxel_m
    };
    let occupied = occupancy.iter().filter(|&&o| o != 0).count();

    let occ = |x: i64, y: i64, z: i64| occupancy_at(&occupancy, dims, x, y, z);
    let surface: Vec<usize> = (0..total)
        .into_par_iter()
        .filter(|&i| {
            if occupancy[i] == 0 {
                return false;
            }
            is_surface_voxel(&occupancy, dims, i)
        })
        .collect();
    let surface_count = surface.len();
    let candidates = match options.sampling {
        HullSampling::Shell => surface,
        HullSampling::Volume | HullSampling::Silhouette => {
            (0..total).filter(|&i| occupancy[i] != 0).collect()
        }
    };

    // Deterministic subsample: a seeded partial Fisher-Yates, then back to index order.
    let mut chosen = candidates;
    if chosen.len() > options.point_count {
        let mut rng = SplitMix64::new(options.seed);
        for i in 0..options.point_count {
            let j = i + rng.below(chosen.len() - i);
            chosen.swap(i, j);
        }
        chosen.truncate(options.point_count);
        chosen.sort_unstable();
    }

    let (points, normals): (Vec<Vec3>, Vec<Vec3>) = chosen
        .par_iter()
        .map(|&i| {
            let (x, y, z) = unflatten(dims, i);
            let offset = match options.sampling {
                HullSampling::Shell => Vec3::splat(0.5),
                HullSampling::Volume | HullSampling::Silhouette => {
                    // Per-voxel stream: independent of thread count and of the other voxels.
                    let mut rng = SplitMix64::new(
                        options.seed ^ (i as u64).wrapping_mul(0xA076_1D64_78BD_642F),
                    );
                    Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32())
                }
            };
            let point = corner_of(x as usize, y as usize, z as usize) + offset * voxel_m;
            (point, outward_normal(&occ, x, y, z))
        })
        .unzip();
    Ok(HullPoints {
        points,
        normals,
        voxel_m,
        dims,
        occupied,
        surface: surface_count,
        occupancy,
    })
}

/// Settings of [`carve_photo_consistent`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhotoOptions {
    /// Candidate points drawn (seeded, uniform) inside each occupied voxel.
    pub samples_per_voxel: u32,
    /// Width of the consistency weight in units of the median colour spread over the
    /// candidates: a candidate of spread `s` is drawn with weight
    /// `exp(-(s / (spread_width * median))^2 / 2)`. Small values approach keeping only the
    /// most consistent candidates; large ones approach [`HullSampling::Volume`].
    pub spread_width: f32,
}

impl Default for PhotoOptions {
    fn default() -> Self {
        PhotoOptions {
            samples_per_voxel: 4,
            spread_width: 0.5,
        }
    }
}

/// The smallest colour spread the photo-consistency weight resolves: one 8-bit level.
const MIN_SPREAD: f32 = 1.0 / 255.0;

/// Candidates per occupied voxel of [`HullSampling::Silhouette`].
pub const SILHOUETTE_SAMPLES_PER_VOXEL: u32 = 4;

/// What [`carve_photo_consistent`] saw, for reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhotoStats {
    /// Candidate points drawn in the occupied voxels.
    pub candidates: usize,
    /// Candidates whose projection falls on background (mask below one half, bilinear) in
    /// a view that sees them: outside the silhouette itself, inside only the carving's
    /// conservative margin.
    pub off_silhouette: usize,
    /// Candidates seen (in front, inside the image) by fewer than two views: no spread.
    pub unscored: usize,
    /// Median colour spread of the scored candidates (RGB in [0, 1]).
    pub median_spread: f32,
}

/// A colour view checked against its camera.
struct PhotoView<'a> {
    camera: Camera,
    width: usize,
    height: usize,
    /// `None`: masks only (every colour reads as black, so every spread is 0).
    rgb: Option<&'a [f32]>,
    mask: &'a [u8],
}

impl PhotoView<'_> {
    /// Bilinear mask (foreground 1, background 0) and colour at `point`, or `None` where
    /// the view does not see it (behind the camera or outside the image's pixel centres).
    fn sample(&self, point: Vec3) -> Option<(f32, Vec3)> {
        let c = self.camera.world_to_camera(point);
        if c.z <= NEAR_M {
            return None;
        }
        let (u, v) = self.camera.camera_to_pixel(c);
        // Pixel (x, y) covers [x, x+1) x [y, y+1): its centre is at x + 0.5.
        let (x, y) = (u - 0.5, v - 0.5);
        let (w, h) = (self.width as f32, self.height as f32);
        if !(x >= 0.0 && y >= 0.0 && x <= w - 1.0 && y <= h - 1.0) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let taps = [
            (x0, y0, (1.0 - fx) * (1.0 - fy)),
            (x1, y0, fx * (1.0 - fy)),
            (x0, y1, (1.0 - fx) * fy),
            (x1, y1, fx * fy),
        ];
        let mut mask = 0.0;
        let mut rgb = Vec3::ZERO;
        for (px, py, weight) in taps {
            let i = py * self.width + px;
            mask += weight * (self.mask[i] >= FOREGROUND_THRESHOLD) as u8 as f32;
            if let Some(image) = self.rgb {
                rgb += weight * Vec3::new(image[3 * i], image[3 * i + 1], image[3 * i + 2]);
            }
        }
        Some((mask, rgb))
    }
}

/// Colour spread of `point` over the views that see it: the root mean square distance of
/// their colours from the mean, per channel. `Err(true)`: on background in some view;
/// `Err(false)`: fewer than two views see it (or a colour is not finite).
fn colour_spread(point: Vec3, views: &[PhotoView]) -> Result<f32, bool> {
    let mut colours = [Vec3::ZERO; 64];
    let mut n = 0usize;
    for view in views {
        let Some((mask, rgb)) = view.sample(point) else {
            continue;
        };
        if mask < 0.5 {
            return Err(true);
        }
        if n < colours.len() && rgb.is_finite() {
            colours[n] = rgb;
            n += 1;
        }
    }
    if n < 2 {
        return Err(false);
    }
    let mean = colours[..n].iter().copied().sum::<Vec3>() / n as f32;
    let square: f32 = colours[..n]
        .iter()
        .map(|c| (*c - mean).length_squared())
        .sum();
    Ok((square / (3 * n) as f32).sqrt())
}

/// Carves like [`carve`] (the masks of `views`), then places the points inside the hull where
/// the views agree on the colour (voxel colouring, soft): `samples_per_voxel` seeded
/// uniform candidates per occupied voxel; a candidate that projects onto background in
/// any view that sees it is dropped (the carving keeps a conservative margin around the
/// silhouette; the point itself is outside it); the others are scored by their colour
/// spread over the views that see them, and `point_count` of them are drawn without
/// replacement with weight `exp(-(spread / width)^2 / 2)` (Gumbel-top-k, seeded). A point
/// on the true surface sees the same surface point in every view, so its colours differ
/// only by shading; a point in front of or behind it sees different surface points where
/// the target is textured. Occlusion is ignored (every view that has the point in its
/// image counts), and so is shading between views. Where the target is uniform the
/// weights are flat and the points fill the hull like [`HullSampling::Volume`].
/// `options.sampling` is ignored. Candidates seen by one view only are kept with the
/// median weight (no evidence either way). Normals are the occupancy-gradient ones of
/// their voxels; `surface` counts the hull's surface voxels as in [`carve`].
pub fn carve_photo_consistent(
    views: &[ColourView],
    grid: HullGrid,
    options: HullOptions,
    photo: PhotoOptions,
) -> Result<(HullPoints, PhotoStats), HullError> {
    let hull_views: Vec<HullView> = views
        .iter()
        .map(|v| HullView {
            camera: v.camera,
            mask: v.mask,
        })
        .collect();
    let photo_views: Vec<PhotoView> = views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let n = v.camera.intrinsics.pixel_count();
            if v.rgb.len() != 3 * n {
                return Err(HullError::MaskSize {
                    view: i,
                    expected: 3 * n,
                    got: v.rgb.len(),
                });
            }
            Ok(PhotoView {
                camera: v.camera,
                width: v.camera.intrinsics.width as usize,
                height: v.camera.intrinsics.height as usize,
                rgb: Some(v.rgb),
                mask: v.mask,
            })
        })
        .collect::<Result<_, _>>()?;
    consistent_points(&hull_views, &photo_views, grid, options, photo)
}

/// Carves like [`carve`], then draws `samples_per_voxel` seeded uniform candidates in each
/// occupied voxel, drops those that project onto background (bilinear mask below one half)
/// in any view that sees them, and returns `point_count` of the rest, drawn uniformly
/// (seeded): points inside the hull and on the silhouette in every view. The carving keeps
/// a conservative margin around the silhouette (a voxel survives when any pixel under its
/// grown footprint is foreground), which at voxels of a pixel or less is most of a thin
/// target's hull; this test at the point itself removes it. Not conservative: a point of
/// the true surface within half a pixel of a silhouette's edge may be dropped. `stats`
/// as for [`carve_photo_consistent`] (every spread 0).
pub fn carve_silhouette_consistent(
    views: &[HullView],
    grid: HullGrid,
    options: HullOptions,
    samples_per_voxel: u32,
) -> Result<(HullPoints, PhotoStats), HullError> {
    let photo_views: Vec<PhotoView> = views
        .iter()
        .map(|v| PhotoView {
            camera: v.camera,
            width: v.camera.intrinsics.width as usize,
            height: v.camera.intrinsics.height as usize,
            rgb: None,
            mask: v.mask,
        })
        .collect();
    let photo = PhotoOptions {
        samples_per_voxel,
        spread_width: 1.0,
    };
    consistent_points(views, &photo_views, grid, options, photo)
}

/// The shared body of [`carve_photo_consistent`] and [`carve_silhouette_consistent`]:
/// `photo_views` are `views` with their images (or none).
fn consistent_points(
    views: &[HullView],
    photo_views: &[PhotoView],
    grid: HullGrid,
    options: HullOptions,
    photo: PhotoOptions,
) -> Result<(HullPoints, PhotoStats), HullError> {
    let (voxel_m, dims, occupancy) = carve_occupancy(views, grid, options)?;
    let samples = photo.samples_per_voxel.max(1) as usize;
    let total = dims[0] * dims[1] * dims[2];
    let occupied_voxels: Vec<usize> = (0..total).filter(|&i| occupancy[i] != 0).collect();

    // Candidates: (voxel, position, spread or why not, Gumbel noise), in voxel order; each
    // voxel has its own seeded stream, so the draw does not depend on the thread count.
    struct Candidate {
        voxel: usize,
        point: Vec3,
        spread: Result<f32, bool>,
        gumbel: f32,
    }
    let candidates: Vec<Candidate> = occupied_voxels
        .par_iter()
        .flat_map_iter(|&i| {
            let (x, y, z) = unflatten(dims, i);
            let corner = grid.min_m + Vec3::new(x as f32, y as f32, z as f32) * voxel_m;
            let mut rng =
                SplitMix64::new(options.seed ^ (i as u64).wrapping_mul(0xA076_1D64_78BD_642F));
            (0..samples).map(move |_| {
                let offset = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                // u in (0, 1]: -ln(-ln u) is a standard Gumbel draw.
                let u = (rng.next_f32() + 0.5 / (1u64 << 24) as f32).min(1.0 - 1e-7);
                let point = corner + offset * voxel_m;
                Candidate {
                    voxel: i,
                    point,
                    spread: colour_spread(point, photo_views),
                    gumbel: -(-u.ln()).ln(),
                }
            })
        })
        .collect();
    let mut spreads: Vec<f32> = candidates.iter().filter_map(|c| c.spread.ok()).collect();
    spreads.sort_unstable_by(f32::total_cmp);
    let median_spread = spreads.get(spreads.len() / 2).copied().unwrap_or(0.0);
    // Spreads below one 8-bit level are quantisation, not evidence: a median below that
    // (more than half the candidates on exactly the same colour in every view, e.g. an
    // unlit dark body) must not make the weight a knife edge.
    let width = (photo.spread_width.max(0.0) * median_spread.max(MIN_SPREAD)).max(1e-6);
    let median_log_weight = -0.5 * (median_spread / width).powi(2);
    let stats = PhotoStats {
        candidates: candidates.len(),
        off_silhouette: candidates.iter().filter(|c| c.spread == Err(true)).count(),
        unscored: candidates.iter().filter(|c| c.spread == Err(false)).count(),
        median_spread,
    };

    // Gumbel-top-k: the `point_count` largest `log weight + Gumbel` keys are a weighted
    // draw without replacement.
    let mut keyed: Vec<(f32, usize)> = candidates
        .iter()
        .enumerate()
        .filter_map(|(k, c)| {
            let log_weight = match c.spread {
                Ok(s) => -0.5 * (s / width).powi(2),
                Err(false) => median_log_weight,
                Err(true) => return None,
            };
            Some((log_weight + c.gumbel, k))
        })
        .collect();
    if keyed.is_empty() {
        return Err(HullError::NothingLeft {
            voxels: occupied_voxels.len(),
        });
    }
    keyed.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    keyed.truncate(options.point_count);
    let mut chosen: Vec<usize> = keyed.into_iter().map(|(_, k)| k).collect();
    chosen.sort_unstable();

    let occ = |x: i64, y: i64, z: i64| occupancy_at(&occupancy, dims, x, y, z);
    let surface = occupied_voxels
        .iter()
        .filter(|&&i| is_surface_voxel(&occupancy, dims, i))
        .count();
    let (points, normals): (Vec<Vec3>, Vec<Vec3>) = chosen
        .iter()
        .map(|&k| {
            let c = &candidates[k];
            let (x, y, z) = unflatten(dims, c.voxel);
            (c.point, outward_normal(&occ, x, y, z))
        })
        .unzip();
    Ok((
        HullPoints {
            points,
            normals,
            voxel_m,
            dims,
            occupied: occupied_voxels.len(),
            surface,
            occupancy,
        },
        stats,
    ))
}

/// A carving volume that keeps its occupancy between views: every voxel starts occupied
/// and each [`CarvedVolume::carve`] removes the voxels that view shows to be background
/// (same vote as [`carve`]; a view that does not see a voxel wholly abstains, so voxels no
/// view has seen stay occupied).
#[derive(Clone, Debug, PartialEq)]
pub struct CarvedVolume {
    grid: HullGrid,
    voxel_m: f32,
    dims: [usize; 3],
    /// One byte per voxel (1 occupied), x fastest then y then z.
    occupancy: Vec<u8>,
    occupied: usize,
    views: usize,
}

impl CarvedVolume {
    /// Every voxel of `grid` occupied.
    pub fn new(grid: HullGrid) -> Result<Self, HullError> {
        let (voxel_m, dims) = grid.layout()?;
        let total = dims[0] * dims[1] * dims[2];
        Ok(CarvedVolume {
            grid,
            voxel_m,
            dims,
            occupancy: vec![1; total],
            occupied: total,
            views: 0,
        })
    }

    /// Carves with one view (footprints grown by `margin_px`); returns how many voxels it
    /// removed. A bad camera or mask is an error and changes nothing. Carving away every
    /// voxel is allowed here (the caller decides what an empty hull means).
    pub fn carve(&mut self, view: &HullView, margin_px: u32) -> Result<usize, HullError> {
        let prepared = PreparedView::new(self.views, view)?;
        let margin = margin_px as f32;
        let (grid, voxel_m, dims) = (self.grid, self.voxel_m, self.dims);
        let slab = dims[0] * dims[1];
        let removed: usize = self
            .occupancy
            .par_chunks_mut(slab)
            .enumerate()
            .map(|(z, slab_occ)| {
                let mut removed = 0;
                for y in 0..dims[1] {
                    for x in 0..dims[0] {
                        let cell = &mut slab_occ[x + dims[0] * y];
                        if *cell == 0 {
                            continue;
                        }
                        let lo = grid.min_m + Vec3::new(x as f32, y as f32, z as f32) * voxel_m;
                        if prepared.vote(lo, lo + Vec3::splat(voxel_m), margin) == Some(false) {
                            *cell = 0;
                            removed += 1;
                        }
                    }
                }
                removed
            })
            .sum();
        self.occupied -= removed;
        self.views += 1;
        Ok(removed)
    }

    /// Whether `point` lies in an occupied voxel or within `dilate_voxels` voxels (in each
    /// axis) of one. Points outside the grid, or not finite, are outside.
    pub fn contains(&self, point: Vec3, dilate_voxels: u32) -> bool {
        let rel = (point - self.grid.min_m) / self.voxel_m;
        if !rel.is_finite() {
            return false;
        }
        let d = dilate_voxels as i64;
        let centre = [
            rel.x.floor() as i64,
            rel.y.floor() as i64,
            rel.z.floor() as i64,
        ];
        for dz in -d..=d {
            for dy in -d..=d {
                for dx in -d..=d {
                    let (x, y, z) = (centre[0] + dx, centre[1] + dy, centre[2] + dz);
                    if x < 0
                        || y < 0
                        || z < 0
                        || x >= self.dims[0] as i64
                        || y >= self.dims[1] as i64
                        || z >= self.dims[2] as i64
                    {
                        continue;
                    }
                    if self.occupancy[voxel_index(self.dims, x as usize, y as usize, z as usize)]
                        != 0
                    {
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Occupied voxels.
    pub fn occupied(&self) -> usize {
        self.occupied
    }

    /// Views carved with so far.
    pub fn views(&self) -> usize {
        self.views
    }

    pub fn voxel_m(&self) -> f32 {
        self.voxel_m
    }

    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// The occupancy, one byte per voxel (1 occupied), x fastest then y then z.
    pub fn occupancy(&self) -> &[u8] {
        &self.occupancy
    }
}

const FACE_NEIGHBOURS: [[i64; 3]; 6] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
];

/// The occupancy (0 or 1) of voxel `(x, y, z)`; 0 outside the grid.
fn occupancy_at(occupancy: &[u8], dims: [usize; 3], x: i64, y: i64, z: i64) -> f32 {
    if x < 0 || y < 0 || z < 0 || x >= dims[0] as i64 || y >= dims[1] as i64 || z >= dims[2] as i64
    {
        return 0.0;
    }
    occupancy[voxel_index(dims, x as usize, y as usize, z as usize)] as f32
}

/// Whether occupied voxel `i` has an empty (or out-of-grid) 6-neighbour.
fn is_surface_voxel(occupancy: &[u8], dims: [usize; 3], i: usize) -> bool {
    let (x, y, z) = unflatten(dims, i);
    FACE_NEIGHBOURS
        .iter()
        .any(|o| occupancy_at(occupancy, dims, x + o[0], y + o[1], z + o[2]) == 0.0)
}

fn unflatten(dims: [usize; 3], i: usize) -> (i64, i64, i64) {
    let x = i % dims[0];
    let y = (i / dims[0]) % dims[1];
    let z = i / (dims[0] * dims[1]);
    (x as i64, y as i64, z as i64)
}

/// Minus the occupancy gradient over the 3x3x3 neighbourhood (offsets weighted by
/// 1/|offset|^2, so the 26 neighbours smooth the 6-neighbour difference), unit length.
/// Where that cancels (a one-voxel-thin sheet), the sum of the directions to empty
/// 6-neighbours; where that cancels too, the first empty 6-neighbour's direction.
fn outward_normal(occ: &impl Fn(i64, i64, i64) -> f32, x: i64, y: i64, z: i64) -> Vec3 {
    let mut gradient = Vec3::ZERO;
    for dz in -1..=1i64 {
        for dy in -1..=1i64 {
            for dx in -1..=1i64 {
                let d2 = (dx * dx + dy * dy + dz * dz) as f32;
                if d2 == 0.0 {
                    continue;
                }
                let o = Vec3::new(dx as f32, dy as f32, dz as f32);
                gradient += o * (occ(x + dx, y + dy, z + dz) / d2);
            }
        }
    }
    let outward = -gradient;
    if outward.length_squared() > 1e-6 {
        return outward.normalize();
    }
    let mut open = Vec3::ZERO;
    let mut first_open = None;
    for o in FACE_NEIGHBOURS {
        if occ(x + o[0], y + o[1], z + o[2]) == 0.0 {
            let d = Vec3::new(o[0] as f32, o[1] as f32, o[2] as f32);
            open += d;
            first_open.get_or_insert(d);
        }
    }
    if open.length_squared() > 1e-6 {
        open.normalize()
    } else {
        // Surface voxels always have an empty 6-neighbour; +z only guards the impossible.
        first_open.unwrap_or(Vec3::Z)
    }
}

/// One view for colouring: camera, sRGB-like image in [0, 1] (`width * height * 3`) and mask.
#[derive(Clone, Copy, Debug)]
pub struct ColourView<'a> {
    pub camera: Camera,
    pub rgb: &'a [f32],
    pub mask: &'a [u8],
}

/// Colour of each point from the view that sees it most frontally (largest cosine between
/// its normal and the direction to the camera) among the views where it projects onto a
/// foreground pixel; `fallback` where no view qualifies (or a view's buffers do not match
/// its camera: such views are skipped). Occlusion by other parts of the target is not
/// tested. Returns the colours and how many points got the fallback.
pub fn sample_colours(
    points: &[Vec3],
    normals: &[Vec3],
    views: &[ColourView],
    fallback: [f32; 3],
) -> (Vec<[f32; 3]>, usize) {
    let usable: Vec<&ColourView> = views
        .iter()
        .filter(|v| {
            let n = v.camera.intrinsics.pixel_count();
            n > 0 && v.rgb.len() == 3 * n && v.mask.len() == n
        })
        .collect();
    let colours: Vec<Option<[f32; 3]>> = points
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let normal = normals.get(i).copied().unwrap_or(Vec3::ZERO);
            let mut best: Option<(f32, [f32; 3])> = None;
            for view in &usable {
                let c = view.camera.world_to_camera(p);
                if c.z <= NEAR_M {
                    continue;
                }
                let (u, v) = view.camera.camera_to_pixel(c);
                let k = view.camera.intrinsics;
                if !(u >= 0.0 && v >= 0.0 && u < k.width as f32 && v < k.height as f32) {
                    continue;
                }
                let pixel = v as usize * k.width as usize + u as usize;
                if view.mask[pixel] < FOREGROUND_THRESHOLD {
                    continue;
                }
                let to_camera = (view.camera.position() - p).normalize_or_zero();
                let frontal = normal.dot(to_camera);
                let rgb = [
                    view.rgb[3 * pixel],
                    view.rgb[3 * pixel + 1],
                    view.rgb[3 * pixel + 2],
                ];
                if !Vec4::new(rgb[0], rgb[1], rgb[2], frontal).is_finite() {
                    continue;
                }
                if best.is_none_or(|(b, _)| frontal > b) {
                    best = Some((frontal, rgb));
                }
            }
            best.map(|(_, rgb)| rgb)
        })
        .collect();
    let missing = colours.iter().filter(|c| c.is_none()).count();
    (
        colours.into_iter().map(|c| c.unwrap_or(fallback)).collect(),
        missing,
    )
}
