//! Candidates inside the carved hull: [`carve_silhouette_consistent`] keeps those whose
//! own projection is foreground in every view that sees them; [`carve_photo_consistent`]
//! also weights them towards colours the views agree on (soft voxel colouring).
//!
//! Invariants: candidates are drawn with a seeded generator in voxel order, so the result
//! does not depend on the thread count; occlusion is ignored.

use super::carve::carve_occupancy;
use super::colour::ColourView;
use super::surface::{is_surface_voxel, occupancy_at, outward_normal, unflatten};
#[cfg(doc)]
use super::{carve, HullSampling};
use super::{HullError, HullGrid, HullOptions, HullPoints, HullView, FOREGROUND_THRESHOLD, NEAR_M};
use glam::Vec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::rng::SplitMix64;

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
