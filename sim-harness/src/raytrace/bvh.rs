//! Bounding volume hierarchy over triangles: binned surface-area-heuristic build, stack-based
//! traversal with nearest-child-first ordering, Moller-Trumbore intersection; closest-hit for
//! camera rays and any-hit for shadow rays.
//!
//! Invariants: nodes are stored depth-first (an interior node's left child follows it); a leaf
//! covers `count` > 0 consecutive entries of `triangles`, an interior node has `count == 0` and
//! its right child at `right_or_first`. Each node's box encloses all triangles under it. The
//! build is deterministic (no parallelism, stable ordering). Ray directions need not be unit:
//! hit distances are in units of the direction's length.

use glam::Vec3;

const BIN_COUNT: usize = 12;
const MAX_LEAF_SIZE: usize = 4;
/// Cost of a node visit relative to a triangle test, for the SAH.
const TRAVERSAL_COST: f32 = 1.0;

#[derive(Clone, Copy, Debug)]
struct Aabb {
    min: Vec3,
    max: Vec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };

    fn grow_point(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    fn grow(&mut self, other: &Aabb) {
        self.min = self.min.min(other.min);
        self.max = self.max.max(other.max);
    }

    fn half_area(&self) -> f32 {
        let d = (self.max - self.min).max(Vec3::ZERO);
        d.x * d.y + d.y * d.z + d.z * d.x
    }
}

#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: Aabb,
    right_or_first: u32,
    count: u32,
}

/// Precomputed triangle for intersection: one corner and two edges.
#[derive(Clone, Copy, Debug)]
struct PackedTriangle {
    v0: Vec3,
    edge1: Vec3,
    edge2: Vec3,
}

/// A ray with precomputed reciprocal direction.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: Vec3,
    pub direction: Vec3,
    inverse_direction: Vec3,
}

impl Ray {
    pub fn new(origin: Vec3, direction: Vec3) -> Ray {
        Ray {
            origin,
            direction,
            inverse_direction: direction.recip(),
        }
    }
}

/// The closest intersection along a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Hit {
    /// Ray parameter of the hit (distance in units of the direction's length).
    pub t: f32,
    /// Index of the triangle in the mesh's original order.
    pub triangle_index: u32,
}

/// A BVH over a triangle soup.
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    triangles: Vec<PackedTriangle>,
    original_index: Vec<u32>,
}

struct BuildItem {
    bounds: Aabb,
    centroid: Vec3,
    index: u32,
}

impl Bvh {
    /// Builds over `corners[i]` = the three corners of triangle i. Zero-area triangles are kept
    /// (they are never hit) so that indices stay aligned with the mesh.
    pub fn build(corners: &[[Vec3; 3]]) -> Bvh {
        let mut items: Vec<BuildItem> = corners
            .iter()
            .enumerate()
            .map(|(i, tri)| {
                let mut bounds = Aabb::EMPTY;
                tri.iter().for_each(|&p| bounds.grow_point(p));
                BuildItem {
                    bounds,
                    centroid: (tri[0] + tri[1] + tri[2]) / 3.0,
                    index: i as u32,
                }
            })
            .collect();
        let mut nodes = Vec::with_capacity(2 * items.len().max(1));
        if !items.is_empty() {
            build_recursive(&mut nodes, &mut items, 0, 0);
        }
        let triangles = items
            .iter()
            .map(|item| {
                let [a, b, c] = corners[item.index as usize];
                PackedTriangle {
                    v0: a,
                    edge1: b - a,
                    edge2: c - a,
                }
            })
            .collect();
        Bvh {
            nodes,
            triangles,
            original_index: items.iter().map(|item| item.index).collect(),
        }
    }

    /// The closest hit with `t_min < t < t_max`, if any.
    pub(crate) fn closest_hit(&self, ray: &Ray, t_min: f32, t_max: f32) -> Option<Hit> {
        let mut best_t = t_max;
        let mut best_slot = u32::MAX;
        self.traverse(ray, t_min, &mut best_t, |slot, _| {
            best_slot = slot;
            false
        });
        (best_slot != u32::MAX).then(|| Hit {
            t: best_t,
            triangle_index: self.original_index[best_slot as usize],
        })
    }

    /// Whether anything is hit with `t_min < t < t_max` (shadow rays).
    pub(crate) fn any_hit(&self, ray: &Ray, t_min: f32, t_max: f32) -> bool {
        let mut best_t = t_max;
        let mut found = false;
        self.traverse(ray, t_min, &mut best_t, |_, _| {
            found = true;
            true
        });
        found
    }

    /// Visits candidate triangles front to back; `on_hit(slot, t)` is called for each hit
    /// closer than `best_t` (which is then lowered to t) and returns true to stop.
    fn traverse(
        &self,
        ray: &Ray,
        t_min: f32,
        best_t: &mut f32,
        mut on_hit: impl FnMut(u32, f32) -> bool,
    ) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = [0u32; 64];
        let mut stack_len = 0usize;
        let mut node_index = 0u32;
        if slab_entry(&self.nodes[0].bounds, ray, t_min, *best_t).is_none() {
            return;
        }
        loop {
            let node = &self.nodes[node_index as usize];
            if node.count > 0 {
                let first = node.right_or_first as usize;
                for slot in first..first + node.count as usize {
                    if let Some(t) = intersect(&self.triangles[slot], ray, t_min, *best_t) {
                        *best_t = t;
                        if on_hit(slot as u32, t) {
                            return;
                        }
                    }
                }
            } else {
                let left = node_index + 1;
                let right = node.right_or_first;
                let t_left = slab_entry(&self.nodes[left as usize].bounds, ray, t_min, *best_t);
                let t_right = slab_entry(&self.nodes[right as usize].bounds, ray, t_min, *best_t);
                match (t_left, t_right) {
                    (Some(a), Some(b)) => {
                        let (near, far) = if a <= b { (left, right) } else { (right, left) };
                        // The tree depth is bounded (see build), so the stack cannot overflow.
                        stack[stack_len] = far;
                        stack_len += 1;
                        node_index = near;
                        continue;
                    }
                    (Some(_), None) => {
                        node_index = left;
                        continue;
                    }
                    (None, Some(_)) => {
                        node_index = right;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            if stack_len == 0 {
                return;
            }
            stack_len -= 1;
            node_index = stack[stack_len];
        }
    }
}

/// Entry distance of the ray into the box within [t_min, t_max], if it enters.
#[inline]
fn slab_entry(b: &Aabb, ray: &Ray, t_min: f32, t_max: f32) -> Option<f32> {
    let t1 = (b.min - ray.origin) * ray.inverse_direction;
    let t2 = (b.max - ray.origin) * ray.inverse_direction;
    // min/max ignore NaN (0 * inf on a slab plane), which keeps such rays conservative.
    let near = t1.min(t2).max_element().max(t_min);
    let far = t1.max(t2).min_element().min(t_max);
    (near <= far).then_some(near)
}

/// Moller-Trumbore; returns t in (t_min, t_max).
#[inline]
fn intersect(tri: &PackedTriangle, ray: &Ray, t_min: f32, t_max: f32) -> Option<f32> {
    let p = ray.direction.cross(tri.edge2);
    let det = tri.edge1.dot(p);
    if det.abs() < 1e-20 {
        return None;
    }
    let inv_det = 1.0 / det;
    let s = ray.origin - tri.v0;
    let u = s.dot(p) * inv_det;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(tri.edge1);
    let v = ray.direction.dot(q) * inv_det;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = tri.edge2.dot(q) * inv_det;
    (t > t_min && t < t_max).then_some(t)
}

/// Builds the subtree for `items` (which start at slot `offset`) at `nodes.len()`. Depth stays below the
/// traversal stack size because a split is forced to be a median split once depth reaches 40.
fn build_recursive(nodes: &mut Vec<Node>, items: &mut [BuildItem], offset: usize, depth: u32) {
    let mut bounds = Aabb::EMPTY;
    let mut centroid_bounds = Aabb::EMPTY;
    for item in items.iter() {
        bounds.grow(&item.bounds);
        centroid_bounds.grow_point(item.centroid);
    }
    let node_index = nodes.len();
    nodes.push(Node {
        bounds,
        right_or_first: 0,
        count: 0,
    });
    let make_leaf = |nodes: &mut Vec<Node>, items: &[BuildItem]| {
        nodes[node_index].count = items.len() as u32;
        nodes[node_index].right_or_first = offset as u32;
    };
    if items.len() <= MAX_LEAF_SIZE {
        make_leaf(nodes, items);
        return;
    }
    let extent = centroid_bounds.max - centroid_bounds.min;
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    if extent[axis] <= 0.0 {
        // All centroids coincide: no split separates them.
        if items.len() <= 64 {
            make_leaf(nodes, items);
            return;
        }
        let mid = items.len() / 2;
        split_and_recurse(nodes, items, offset, mid, node_index, depth);
        return;
    }

    let mid = if depth >= 40 {
        items.sort_by(|a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
        items.len() / 2
    } else {
        match best_sah_split(items, &centroid_bounds, axis, &bounds) {
            Some(bin_split) => {
                let lo = centroid_bounds.min[axis];
                let scale = BIN_COUNT as f32 / extent[axis];
                let bin_of = |c: f32| (((c - lo) * scale) as usize).min(BIN_COUNT - 1);
                partition_in_place(items, |item| bin_of(item.centroid[axis]) < bin_split)
            }
            None => {
                make_leaf(nodes, items);
                return;
            }
        }
    };
    let mid = if mid == 0 || mid == items.len() {
        items.sort_by(|a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
        items.len() / 2
    } else {
        mid
    };
    split_and_recurse(nodes, items, offset, mid, node_index, depth);
}

fn split_and_recurse(
    nodes: &mut Vec<Node>,
    items: &mut [BuildItem],
    offset: usize,
    mid: usize,
    node_index: usize,
    depth: u32,
) {
    let (left, right) = items.split_at_mut(mid);
    build_recursive(nodes, left, offset, depth + 1);
    nodes[node_index].right_or_first = nodes.len() as u32;
    build_recursive(nodes, right, offset + mid, depth + 1);
}

/// The bin boundary (split before bin k) with the lowest SAH cost, or None when a leaf is
/// cheaper (only allowed for small item counts).
fn best_sah_split(
    items: &[BuildItem],
    centroid_bounds: &Aabb,
    axis: usize,
    bounds: &Aabb,
) -> Option<usize> {
    let lo = centroid_bounds.min[axis];
    let scale = BIN_COUNT as f32 / (centroid_bounds.max[axis] - lo);
    let mut bin_bounds = [Aabb::EMPTY; BIN_COUNT];
    let mut bin_counts = [0usize; BIN_COUNT];
    for item in items {
        let b = (((item.centroid[axis] - lo) * scale) as usize).min(BIN_COUNT - 1);
        bin_counts[b] += 1;
        bin_bounds[b].grow(&item.bounds);
    }
    // Sweep from the right to get suffix areas and counts.
    let mut right_area = [0.0f32; BIN_COUNT];
    let mut right_count = [0usize; BIN_COUNT];
    let mut acc = Aabb::EMPTY;
    let mut count = 0;
    for k in (1..BIN_COUNT).rev() {
        acc.grow(&bin_bounds[k]);
        count += bin_counts[k];
        right_area[k] = acc.half_area();
        right_count[k] = count;
    }
    let mut best: Option<(f32, usize)> = None;
    let mut acc = Aabb::EMPTY;
    let mut count = 0;
    for k in 1..BIN_COUNT {
        acc.grow(&bin_bounds[k - 1]);
        count += bin_counts[k - 1];
        if count == 0 || right_count[k] == 0 {
            continue;
        }
        let cost = acc.half_area() * count as f32 + right_area[k] * right_count[k] as f32;
        if best.is_none_or(|(c, _)| cost < c) {
            best = Some((cost, k));
        }
    }
    let (cost, k) = best?;
    let parent_area = bounds.half_area().max(f32::MIN_POSITIVE);
    let split_cost = TRAVERSAL_COST + cost / parent_area;
    let leaf_cost = items.len() as f32;
    if leaf_cost <= split_cost && items.len() <= 16 {
        None
    } else {
        Some(k)
    }
}

/// Stable-enough in-place partition: items satisfying `goes_left` first; returns their count.
fn partition_in_place(items: &mut [BuildItem], goes_left: impl Fn(&BuildItem) -> bool) -> usize {
    let mut boundary = 0;
    for i in 0..items.len() {
        if goes_left(&items[i]) {
            items.swap(boundary, i);
            boundary += 1;
        }
    }
    boundary
}

#[cfg(test)]
mod tests {
    use super::*;
    use gs_core::rng::SplitMix64;

    fn random_vec(rng: &mut SplitMix64, scale: f32) -> Vec3 {
        Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * (2.0 * scale)
            - Vec3::splat(scale)
    }

    #[test]
    fn bvh_agrees_with_brute_force() {
        let mut rng = SplitMix64::new(5);
        // Small random triangles in a 10 m cube, plus a few duplicates and degenerate ones.
        let mut corners: Vec<[Vec3; 3]> = (0..3000)
            .map(|_| {
                let c = random_vec(&mut rng, 5.0);
                [
                    c + random_vec(&mut rng, 0.4),
                    c + random_vec(&mut rng, 0.4),
                    c + random_vec(&mut rng, 0.4),
                ]
            })
            .collect();
        corners.extend_from_within(0..50);
        corners.push([Vec3::ONE; 3]);
        let bvh = Bvh::build(&corners);
        let packed: Vec<PackedTriangle> = corners
            .iter()
            .map(|[a, b, c]| PackedTriangle {
                v0: *a,
                edge1: *b - *a,
                edge2: *c - *a,
            })
            .collect();
        let mut hits = 0;
        for _ in 0..3000 {
            let origin = random_vec(&mut rng, 8.0);
            let target = random_vec(&mut rng, 3.0);
            let ray = Ray::new(origin, target - origin);
            let brute = packed
                .iter()
                .filter_map(|t| intersect(t, &ray, 0.0, f32::INFINITY))
                .fold(f32::INFINITY, f32::min);
            let hit = bvh.closest_hit(&ray, 0.0, f32::INFINITY);
            match hit {
                Some(h) => {
                    hits += 1;
                    assert_eq!(h.t, brute);
                    let tri = &packed[h.triangle_index as usize];
                    assert_eq!(intersect(tri, &ray, 0.0, f32::INFINITY), Some(h.t));
                }
                None => assert_eq!(brute, f32::INFINITY),
            }
            assert_eq!(bvh.any_hit(&ray, 0.0, f32::INFINITY), brute.is_finite());
            // Limited range: only hits closer than t_max count.
            assert_eq!(bvh.any_hit(&ray, 0.0, 0.5), brute < 0.5);
        }
        assert!(hits > 500, "{hits}");
    }
}
