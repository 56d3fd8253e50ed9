//! [`CarvedVolume`]: the occupancy kept between views, so an online trainer can carve with
//! each view as it arrives and ask whether a point is still inside.
//!
//! Invariant: carving is monotone (a carved voxel stays carved) and order-free (views A
//! then B give the same occupancy as B then A).

#[cfg(doc)]
use super::carve;
use super::carve::{voxel_index, PreparedView};
use super::{HullError, HullGrid, HullView};
use glam::Vec3;
use rayon::prelude::*;

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
