//! Mesh builder for procedural targets: subdivided quads and boxes, cylinders/frustums with
//! caps, paraboloid dishes with thickness, all with outward (counter-clockwise) winding.
//!
//! Invariants: every triangle added references vertices already pushed; material indices come
//! from `material`, which de-duplicates by name. Dimensions are metres.

use super::{Material, TargetError, TargetMesh};
use glam::{Quat, Vec3};

/// Accumulates vertices, triangles and materials.
#[derive(Default)]
pub struct MeshBuilder {
    vertices_m: Vec<Vec3>,
    triangles: Vec<[u32; 3]>,
    material_of_triangle: Vec<u16>,
    materials: Vec<Material>,
}

/// Two unit vectors completing `axis` (unit) to a right-handed orthonormal basis.
fn perpendicular_basis(axis: Vec3) -> (Vec3, Vec3) {
    let helper = if axis.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let u = axis.cross(helper).normalize();
    let v = axis.cross(u);
    (u, v)
}

impl MeshBuilder {
    pub fn new() -> MeshBuilder {
        MeshBuilder::default()
    }

    /// Index of `material`, adding it unless one with the same name exists.
    pub fn material(&mut self, material: Material) -> u16 {
        if let Some(i) = self.materials.iter().position(|m| m.name == material.name) {
            return i as u16;
        }
        self.materials.push(material);
        (self.materials.len() - 1) as u16
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    fn push_vertex(&mut self, p: Vec3) -> u32 {
        self.vertices_m.push(p);
        (self.vertices_m.len() - 1) as u32
    }

    fn push_triangle(&mut self, tri: [u32; 3], material: u16) {
        self.triangles.push(tri);
        self.material_of_triangle.push(material);
    }

    /// A planar grid of `nu` x `nv` quads spanning `origin + s*edge_u + t*edge_v`, s, t in [0, 1],
    /// facing `edge_u x edge_v`.
    pub fn quad_grid(
        &mut self,
        origin: Vec3,
        edge_u: Vec3,
        edge_v: Vec3,
        nu: u32,
        nv: u32,
        material: u16,
    ) {
        let (nu, nv) = (nu.max(1), nv.max(1));
        let first = self.vertices_m.len() as u32;
        for j in 0..=nv {
            for i in 0..=nu {
                let p = origin + edge_u * (i as f32 / nu as f32) + edge_v * (j as f32 / nv as f32);
                self.push_vertex(p);
            }
        }
        let row = nu + 1;
        for j in 0..nv {
            for i in 0..nu {
                let a = first + j * row + i;
                self.push_triangle([a, a + 1, a + row + 1], material);
                self.push_triangle([a, a + row + 1, a + row], material);
            }
        }
    }

    /// An oriented box; `face_materials` are for the +x, -x, +y, -y, +z, -z faces (box frame).
    /// Faces are subdivided into cells no larger than `cell_m`.
    pub fn oriented_box(
        &mut self,
        center: Vec3,
        half_extents_m: Vec3,
        rotation: Quat,
        cell_m: f32,
        face_materials: [u16; 6],
    ) {
        let h = half_extents_m;
        let axes = [Vec3::X, Vec3::Y, Vec3::Z];
        for (face, &material) in face_materials.iter().enumerate() {
            let axis = face / 2;
            let sign = if face % 2 == 0 { 1.0 } else { -1.0 };
            let normal = axes[axis] * sign;
            // u, v span the face with u x v = normal.
            let u_axis = axes[(axis + 1) % 3];
            let v_axis = axes[(axis + 2) % 3] * sign;
            let u_len = 2.0 * h[(axis + 1) % 3];
            let v_len = 2.0 * h[(axis + 2) % 3];
            let origin = normal * h[axis] - u_axis * (u_len / 2.0) - v_axis * (v_len / 2.0);
            let nu = (u_len / cell_m).ceil().max(1.0) as u32;
            let nv = (v_len / cell_m).ceil().max(1.0) as u32;
            self.quad_grid(
                center + rotation * origin,
                rotation * (u_axis * u_len),
                rotation * (v_axis * v_len),
                nu,
                nv,
                material,
            );
        }
    }

    /// Axis-aligned box with one material everywhere.
    pub fn simple_box(&mut self, center: Vec3, half_extents_m: Vec3, cell_m: f32, material: u16) {
        self.oriented_box(
            center,
            half_extents_m,
            Quat::IDENTITY,
            cell_m,
            [material; 6],
        );
    }

    /// A frustum (cylinder when radii are equal) from `base` to `top`, `segments` around and
    /// `rings` along, with optional flat caps.
    pub(crate) fn frustum(
        &mut self,
        base: Vec3,
        top: Vec3,
        base_radius_m: f32,
        top_radius_m: f32,
        segments: u32,
        rings: u32,
        caps: bool,
        material: u16,
    ) {
        let segments = segments.max(3);
        let rings = rings.max(1);
        let axis = (top - base).normalize();
        let (u, v) = perpendicular_basis(axis);
        let ring_dir = |k: u32| {
            let angle = std::f32::consts::TAU * k as f32 / segments as f32;
            u * angle.cos() + v * angle.sin()
        };
        let first = self.vertices_m.len() as u32;
        for r in 0..=rings {
            let f = r as f32 / rings as f32;
            let radius = base_radius_m + (top_radius_m - base_radius_m) * f;
            let centre = base + (top - base) * f;
            for k in 0..segments {
                self.push_vertex(centre + ring_dir(k) * radius);
            }
        }
        for r in 0..rings {
            for k in 0..segments {
                let k1 = (k + 1) % segments;
                let a = first + r * segments + k;
                let b = first + r * segments + k1;
                let c = first + (r + 1) * segments + k1;
                let d = first + (r + 1) * segments + k;
                // (u, v, axis) is right-handed, so a -> b -> c runs counter-clockwise seen from outside.
                self.push_triangle([a, b, c], material);
                self.push_triangle([a, c, d], material);
            }
        }
        if caps {
            for (centre, radius, outward) in
                [(base, base_radius_m, -axis), (top, top_radius_m, axis)]
            {
                if radius <= 0.0 {
                    continue;
                }
                let c = self.push_vertex(centre);
                let ring_first = self.vertices_m.len() as u32;
                for k in 0..segments {
                    self.push_vertex(centre + ring_dir(k) * radius);
                }
                for k in 0..segments {
                    let a = ring_first + k;
                    let b = ring_first + (k + 1) % segments;
                    if outward.dot(axis) > 0.0 {
                        self.push_triangle([c, a, b], material);
                    } else {
                        self.push_triangle([c, b, a], material);
                    }
                }
            }
        }
    }

    /// A paraboloid dish opening towards `axis` (unit), its vertex at `vertex_point`, rim radius
    /// `radius_m` at height `depth_m`; the front (concave) side uses `front`, the back surface,
    /// offset by `thickness_m` along -axis, uses `back`; a rim band closes the shell.
    pub(crate) fn dish(
        &mut self,
        vertex_point: Vec3,
        axis: Vec3,
        radius_m: f32,
        depth_m: f32,
        thickness_m: f32,
        rings: u32,
        segments: u32,
        front: u16,
        back: u16,
    ) {
        let axis = axis.normalize();
        let (u, v) = perpendicular_basis(axis);
        let (rings, segments) = (rings.max(1), segments.max(3));
        let point = |ring: u32, k: u32, offset: f32| {
            let rho = radius_m * ring as f32 / rings as f32;
            let angle = std::f32::consts::TAU * k as f32 / segments as f32;
            let height = depth_m * (rho / radius_m).powi(2) - offset;
            vertex_point + (u * angle.cos() + v * angle.sin()) * rho + axis * height
        };
        for (offset, material, facing_axis) in [(0.0, front, true), (thickness_m, back, false)] {
            let centre = self.push_vertex(point(0, 0, offset));
            let first = self.vertices_m.len() as u32;
            for ring in 1..=rings {
                for k in 0..segments {
                    self.push_vertex(point(ring, k, offset));
                }
            }
            let tri = |t: [u32; 3], b: &mut MeshBuilder| {
                // Counter-clockwise around +axis faces +axis (the concave front).
                if facing_axis {
                    b.push_triangle(t, material);
                } else {
                    b.push_triangle([t[0], t[2], t[1]], material);
                }
            };
            for k in 0..segments {
                let k1 = (k + 1) % segments;
                tri([centre, first + k, first + k1], self);
            }
            for ring in 0..rings - 1 {
                for k in 0..segments {
                    let k1 = (k + 1) % segments;
                    let a = first + ring * segments + k;
                    let b = first + ring * segments + k1;
                    let c = first + (ring + 1) * segments + k1;
                    let d = first + (ring + 1) * segments + k;
                    tri([a, c, b], self);
                    tri([a, d, c], self);
                }
            }
        }
        if thickness_m > 0.0 {
            let rim_front = self.vertices_m.len() as u32;
            for k in 0..segments {
                self.push_vertex(point(rings, k, 0.0));
            }
            let rim_back = self.vertices_m.len() as u32;
            for k in 0..segments {
                self.push_vertex(point(rings, k, thickness_m));
            }
            for k in 0..segments {
                let k1 = (k + 1) % segments;
                self.push_triangle([rim_back + k, rim_back + k1, rim_front + k1], back);
                self.push_triangle([rim_back + k, rim_front + k1, rim_front + k], back);
            }
        }
    }

    /// Appends all of `other`, transformed by `rotation` then `translation`.
    pub(crate) fn append_transformed(
        &mut self,
        other: &MeshBuilder,
        rotation: Quat,
        translation: Vec3,
    ) {
        let first = self.vertices_m.len() as u32;
        let material_map: Vec<u16> = other
            .materials
            .iter()
            .map(|m| self.material(m.clone()))
            .collect();
        for &p in &other.vertices_m {
            self.push_vertex(rotation * p + translation);
        }
        for (tri, &m) in other.triangles.iter().zip(&other.material_of_triangle) {
            self.push_triangle(tri.map(|v| v + first), material_map[m as usize]);
        }
    }

    pub fn build(self) -> Result<TargetMesh, TargetError> {
        TargetMesh::new(
            self.vertices_m,
            self.triangles,
            self.material_of_triangle,
            self.materials,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume by the divergence theorem: positive iff the winding is outward everywhere.
    fn signed_volume(mesh: &TargetMesh) -> f32 {
        (0..mesh.triangle_count())
            .map(|t| {
                let [a, b, c] = mesh.triangle_corners_m(t);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn closed_shapes_have_outward_winding_and_right_volume() {
        let mut b = MeshBuilder::new();
        let m = b.material(Material::white_paint());
        b.oriented_box(
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(0.5, 1.0, 1.5),
            Quat::from_rotation_z(0.3),
            0.4,
            [m; 6],
        );
        let mesh = b.build().unwrap();
        assert!(
            (signed_volume(&mesh) - 6.0).abs() < 1e-3,
            "{}",
            signed_volume(&mesh)
        );

        let mut b = MeshBuilder::new();
        let m = b.material(Material::white_paint());
        let segments = 256;
        b.frustum(
            Vec3::ZERO,
            Vec3::new(0.0, 2.0, 0.0),
            1.0,
            1.0,
            segments,
            3,
            true,
            m,
        );
        let mesh = b.build().unwrap();
        // Inscribed polygon area: n/2 sin(2 pi / n) r^2, times height.
        let n = segments as f32;
        let expected = n / 2.0 * (std::f32::consts::TAU / n).sin() * 2.0;
        assert!((signed_volume(&mesh) - expected).abs() < 1e-3);

        let mut b = MeshBuilder::new();
        let m = b.material(Material::white_paint());
        b.dish(Vec3::ZERO, Vec3::Z, 2.0, 0.5, 0.05, 16, 64, m, m);
        let mesh = b.build().unwrap();
        // A closed shell of thickness 0.05 over ~ pi r^2 projected area: volume ~ 0.05 * 12.6.
        let v = signed_volume(&mesh);
        assert!(v > 0.5 && v < 0.7, "{v}");
    }
}
