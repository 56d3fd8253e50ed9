//! The hull's surface: which occupied voxels have an empty 6-neighbour (outside the grid
//! counts as empty), and outward normals from the occupancy gradient.
//!
//! Invariant: every normal returned is unit length (where the gradient cancels, the
//! directions to the empty 6-neighbours stand in for it).

use super::carve::voxel_index;
use glam::Vec3;

const FACE_NEIGHBOURS: [[i64; 3]; 6] = [
    [-1, 0, 0],
    [1, 0, 0],
    [0, -1, 0],
    [0, 1, 0],
    [0, 0, -1],
    [0, 0, 1],
];

/// The occupancy (0 or 1) of voxel `(x, y, z)`; 0 outside the grid.
pub(super) fn occupancy_at(occupancy: &[u8], dims: [usize; 3], x: i64, y: i64, z: i64) -> f32 {
    if x < 0 || y < 0 || z < 0 || x >= dims[0] as i64 || y >= dims[1] as i64 || z >= dims[2] as i64
    {
        return 0.0;
    }
    occupancy[voxel_index(dims, x as usize, y as usize, z as usize)] as f32
}

/// Whether occupied voxel `i` has an empty (or out-of-grid) 6-neighbour.
pub(super) fn is_surface_voxel(occupancy: &[u8], dims: [usize; 3], i: usize) -> bool {
    let (x, y, z) = unflatten(dims, i);
    FACE_NEIGHBOURS
        .iter()
        .any(|o| occupancy_at(occupancy, dims, x + o[0], y + o[1], z + o[2]) == 0.0)
}

pub(super) fn unflatten(dims: [usize; 3], i: usize) -> (i64, i64, i64) {
    let x = i % dims[0];
    let y = (i / dims[0]) % dims[1];
    let z = i / (dims[0] * dims[1]);
    (x as i64, y as i64, z as i64)
}

/// Minus the occupancy gradient over the 3x3x3 neighbourhood (offsets weighted by
/// 1/|offset|^2, so the 26 neighbours smooth the 6-neighbour difference), unit length.
/// Where that cancels (a one-voxel-thin sheet), the sum of the directions to empty
/// 6-neighbours; where that cancels too, the first empty 6-neighbour's direction.
pub(super) fn outward_normal(occ: &impl Fn(i64, i64, i64) -> f32, x: i64, y: i64, z: i64) -> Vec3 {
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
