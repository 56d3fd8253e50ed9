//! Carving: each view, prepared as a summed-area table of its foreground, votes on each
//! voxel of the grid ([`carve`], rayon over voxels); the surviving surface voxels become
//! the points.
//!
//! Invariants: a view votes only where the voxel lies wholly in front of it and its grown
//! footprint wholly inside the image; each voxel is decided alone, so the thread count
//! changes nothing; every point and normal returned is finite.

use super::photo::{carve_silhouette_consistent, SILHOUETTE_SAMPLES_PER_VOXEL};
use super::surface::{is_surface_voxel, occupancy_at, outward_normal, unflatten};
use super::{
    HullError, HullGrid, HullOptions, HullPoints, HullSampling, HullView, FOREGROUND_THRESHOLD,
    NEAR_M,
};
use glam::Vec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::rng::SplitMix64;

/// A view prepared for O(1) footprint tests: the summed-area table of its foreground.
pub(super) struct PreparedView {
    camera: Camera,
    width: usize,
    height: usize,
    /// `(width + 1) * (height + 1)` prefix counts of foreground pixels.
    summed: Vec<u32>,
}

impl PreparedView {
    pub(super) fn new(index: usize, view: &HullView) -> Result<Self, HullError> {
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
    pub(super) fn vote(&self, lo: Vec3, hi: Vec3, margin_px: f32) -> Option<bool> {
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

pub(super) fn voxel_index(dims: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    x + dims[0] * (y + dims[1] * z)
}

/// The carved occupancy (one byte per voxel, 1 occupied, x fastest) after validating the
/// views, the grid and the point count; [`HullError::NothingLeft`] when every voxel is
/// carved.
pub(super) fn carve_occupancy(
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
