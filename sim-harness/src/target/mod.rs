//! Target spacecraft: triangle meshes, materials, procedural targets, OBJ loading, surface sampling.
//!
//! Invariants of a `TargetMesh` (checked by `TargetMesh::new`, the only constructor): at least
//! one triangle; every vertex finite; every triangle index and material index in range; every
//! material sanitized. Coordinates are metres in the target body frame. Degenerate
//! (zero-area) triangles are allowed: they are never hit and never sampled.

mod builder;
mod builtin;
mod material;
mod obj;

pub use builder::MeshBuilder;
pub use material::{Material, MIN_ROUGHNESS};
pub use obj::load_obj;

use glam::Vec3;
use gs_core::rng::SplitMix64;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

/// A triangle mesh with one material per triangle, in the target body frame (metres).
#[derive(Clone, Debug)]
pub struct TargetMesh {
    vertices_m: Vec<Vec3>,
    triangles: Vec<[u32; 3]>,
    material_of_triangle: Vec<u16>,
    materials: Vec<Material>,
}

/// Why a mesh could not be built or loaded.
#[derive(Debug)]
pub enum TargetError {
    /// The file could not be opened or read.
    Io { path: PathBuf, message: String },
    /// The file was read but its contents are not a valid OBJ mesh.
    Parse { path: PathBuf, message: String },
    /// The mesh data violates an invariant (empty, out-of-range index, non-finite vertex, ...).
    InvalidMesh(String),
    /// A target name that is not one of the built-in targets.
    UnknownTarget(String),
}

impl fmt::Display for TargetError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TargetError::Io { path, message } => {
                write!(f, "cannot read mesh file {}: {message}", path.display())
            }
            TargetError::Parse { path, message } => {
                write!(f, "malformed mesh file {}: {message}", path.display())
            }
            TargetError::InvalidMesh(m) => write!(f, "invalid mesh: {m}"),
            TargetError::UnknownTarget(name) => write!(
                f,
                "unknown built-in target {name:?} (expected cassini, rosetta or starlink)"
            ),
        }
    }
}

impl std::error::Error for TargetError {}

/// One point sampled on the target surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceSample {
    /// Position in the target body frame, metres.
    pub position_m: Vec3,
    /// Unit geometric normal of the triangle (by its winding; outward for built-in targets).
    pub normal: Vec3,
    /// Base colour of the material at that point, linear RGB in [0, 1].
    pub albedo_rgb: [f32; 3],
    /// Index of the triangle the sample lies on.
    pub triangle_index: u32,
}

/// The three procedural targets modelled after the paper's.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BuiltinTarget {
    Cassini,
    Rosetta,
    Starlink,
}

impl BuiltinTarget {
    pub const ALL: [BuiltinTarget; 3] = [
        BuiltinTarget::Cassini,
        BuiltinTarget::Rosetta,
        BuiltinTarget::Starlink,
    ];

    pub fn name(self) -> &'static str {
        match self {
            BuiltinTarget::Cassini => "cassini",
            BuiltinTarget::Rosetta => "rosetta",
            BuiltinTarget::Starlink => "starlink",
        }
    }
}

impl fmt::Display for BuiltinTarget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BuiltinTarget {
    type Err = TargetError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        BuiltinTarget::ALL
            .into_iter()
            .find(|t| t.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| TargetError::UnknownTarget(s.to_string()))
    }
}

/// Builds one of the procedural targets (deterministic: same kind, same mesh).
pub fn builtin_target(kind: BuiltinTarget) -> TargetMesh {
    match kind {
        BuiltinTarget::Cassini => builtin::cassini(),
        BuiltinTarget::Rosetta => builtin::rosetta(),
        BuiltinTarget::Starlink => builtin::starlink(),
    }
}

impl TargetMesh {
    /// Validates and builds a mesh. Materials are sanitized (clamped into their ranges).
    pub fn new(
        vertices_m: Vec<Vec3>,
        triangles: Vec<[u32; 3]>,
        material_of_triangle: Vec<u16>,
        materials: Vec<Material>,
    ) -> Result<TargetMesh, TargetError> {
        if triangles.is_empty() {
            return Err(TargetError::InvalidMesh("mesh has no triangles".into()));
        }
        if triangles.len() > u32::MAX as usize / 2 {
            return Err(TargetError::InvalidMesh(format!(
                "too many triangles ({})",
                triangles.len()
            )));
        }
        if material_of_triangle.len() != triangles.len() {
            return Err(TargetError::InvalidMesh(format!(
                "{} material indices for {} triangles",
                material_of_triangle.len(),
                triangles.len()
            )));
        }
        if let Some(i) = vertices_m.iter().position(|v| !v.is_finite()) {
            return Err(TargetError::InvalidMesh(format!(
                "vertex {i} is not finite: {:?}",
                vertices_m[i]
            )));
        }
        let vertex_count = vertices_m.len();
        if let Some((t, tri)) = triangles
            .iter()
            .enumerate()
            .find(|(_, tri)| tri.iter().any(|&v| v as usize >= vertex_count))
        {
            return Err(TargetError::InvalidMesh(format!(
                "triangle {t} {tri:?} indexes past the {vertex_count} vertices"
            )));
        }
        if let Some((t, &m)) = material_of_triangle
            .iter()
            .enumerate()
            .find(|(_, &m)| m as usize >= materials.len())
        {
            return Err(TargetError::InvalidMesh(format!(
                "triangle {t} uses material {m} of {}",
                materials.len()
            )));
        }
        let materials = materials.into_iter().map(Material::sanitized).collect();
        Ok(TargetMesh {
            vertices_m,
            triangles,
            material_of_triangle,
            materials,
        })
    }

    pub fn vertices_m(&self) -> &[Vec3] {
        &self.vertices_m
    }

    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    pub fn material_of_triangle(&self) -> &[u16] {
        &self.material_of_triangle
    }

    pub fn materials(&self) -> &[Material] {
        &self.materials
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The three corners of triangle `index` in metres.
    pub fn triangle_corners_m(&self, index: usize) -> [Vec3; 3] {
        self.triangles[index].map(|v| self.vertices_m[v as usize])
    }

    /// Largest distance of any used vertex from the body-frame origin, metres.
    pub fn bounding_radius_m(&self) -> f32 {
        self.triangles
            .iter()
            .flatten()
            .map(|&v| self.vertices_m[v as usize].length())
            .fold(0.0, f32::max)
    }

    /// Total surface area in square metres (one side per triangle).
    pub fn surface_area_m2(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| triangle_area_m2(self.triangle_corners_m(t)) as f64)
            .sum()
    }

    /// `n` points uniformly distributed by area over the surface (seeded, deterministic).
    /// Returns an empty vector when the mesh has zero total area.
    pub fn sample_surface(&self, n: usize, seed: u64) -> Vec<SurfaceSample> {
        // Cumulative area in f64 so that tens of thousands of small triangles add up exactly
        // enough for the binary search to be uniform.
        let mut cumulative_area = Vec::with_capacity(self.triangles.len());
        let mut total = 0.0f64;
        for t in 0..self.triangles.len() {
            total += triangle_area_m2(self.triangle_corners_m(t)) as f64;
            cumulative_area.push(total);
        }
        if total <= 0.0 || !total.is_finite() {
            return Vec::new();
        }
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                let target = rng.next_f64() * total;
                // First triangle whose cumulative area exceeds the target: zero-area triangles
                // have equal cumulative values and are never selected.
                let t = cumulative_area
                    .partition_point(|&c| c <= target)
                    .min(self.triangles.len() - 1);
                let [a, b, c] = self.triangle_corners_m(t);
                let (r1, r2) = (rng.next_f32(), rng.next_f32());
                let s = r1.sqrt();
                let position_m = a * (1.0 - s) + b * (s * (1.0 - r2)) + c * (s * r2);
                let material = &self.materials[self.material_of_triangle[t] as usize];
                SurfaceSample {
                    position_m,
                    normal: (b - a).cross(c - a).normalize_or_zero(),
                    albedo_rgb: material.base_color_linear,
                    triangle_index: t as u32,
                }
            })
            .collect()
    }
}

/// Area of a triangle in square metres.
pub fn triangle_area_m2([a, b, c]: [Vec3; 3]) -> f32 {
    0.5 * (b - a).cross(c - a).length()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_triangles() -> TargetMesh {
        // Triangle 0 has area 0.5, triangle 1 has area 1.5 (three times larger).
        let v = vec![
            Vec3::ZERO,
            Vec3::X,
            Vec3::Y,
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(3.0, 0.0, 1.0),
            Vec3::new(0.0, 1.0, 1.0),
        ];
        TargetMesh::new(
            v,
            vec![[0, 1, 2], [3, 4, 5]],
            vec![0, 1],
            vec![Material::white_paint(), Material::gold_mli()],
        )
        .unwrap()
    }

    #[test]
    fn new_rejects_bad_meshes() {
        let m = || vec![Material::default_grey()];
        assert!(TargetMesh::new(vec![Vec3::ZERO; 3], vec![], vec![], m()).is_err());
        assert!(TargetMesh::new(vec![Vec3::ZERO; 3], vec![[0, 1, 3]], vec![0], m()).is_err());
        assert!(TargetMesh::new(vec![Vec3::ZERO; 3], vec![[0, 1, 2]], vec![1], m()).is_err());
        assert!(TargetMesh::new(vec![Vec3::ZERO; 3], vec![[0, 1, 2]], vec![], m()).is_err());
        let nan = vec![Vec3::ZERO, Vec3::X, Vec3::new(f32::NAN, 0.0, 0.0)];
        let err = TargetMesh::new(nan, vec![[0, 1, 2]], vec![0], m()).unwrap_err();
        assert!(err.to_string().contains("not finite"), "{err}");
    }

    #[test]
    fn sampling_is_uniform_by_area_and_on_the_triangles() {
        let mesh = two_triangles();
        let n = 40_000;
        let samples = mesh.sample_surface(n, 7);
        assert_eq!(samples.len(), n);
        let on_big = samples.iter().filter(|s| s.triangle_index == 1).count();
        // Expected fraction 0.75; binomial sigma = sqrt(0.75 * 0.25 / n) ~ 0.0022; allow 4 sigma.
        let fraction = on_big as f64 / n as f64;
        assert!((fraction - 0.75).abs() < 4.0 * 0.00217, "{fraction}");
        for s in &samples {
            let [a, b, c] = mesh.triangle_corners_m(s.triangle_index as usize);
            // Inside the triangle: barycentric coordinates all in [0, 1] and the point in-plane.
            let n = (b - a).cross(c - a);
            let area2 = n.length();
            let w_a = (b - s.position_m).cross(c - s.position_m).dot(n) / (area2 * area2);
            let w_b = (c - s.position_m).cross(a - s.position_m).dot(n) / (area2 * area2);
            let w_c = 1.0 - w_a - w_b;
            for w in [w_a, w_b, w_c] {
                assert!((-1e-5..=1.0 + 1e-5).contains(&w), "{w}");
            }
            assert!((s.position_m - a).dot(n / area2).abs() < 1e-5);
            assert!((s.normal.length() - 1.0).abs() < 1e-5);
            let material = mesh.material_of_triangle()[s.triangle_index as usize];
            let expected = mesh.materials()[material as usize].base_color_linear;
            assert_eq!(s.albedo_rgb, expected);
        }
        // Within the big triangle (x + 3y <= 3 at z = 1), uniformity: the half with x < 1.5
        // (x in [0, 1.5]) holds 3/4 of its area.
        let big: Vec<_> = samples.iter().filter(|s| s.triangle_index == 1).collect();
        let left = big.iter().filter(|s| s.position_m.x < 1.5).count() as f64 / big.len() as f64;
        assert!((left - 0.75).abs() < 0.015, "{left}");
    }

    #[test]
    fn sampling_is_deterministic_by_seed() {
        let mesh = two_triangles();
        assert_eq!(mesh.sample_surface(100, 3), mesh.sample_surface(100, 3));
        assert_ne!(mesh.sample_surface(100, 3), mesh.sample_surface(100, 4));
    }

    #[test]
    fn names_parse_and_serialize_lowercase() {
        for t in BuiltinTarget::ALL {
            assert_eq!(t.name().parse::<BuiltinTarget>().unwrap(), t);
            let json = serde_json::to_string(&t).unwrap();
            assert_eq!(json, format!("\"{}\"", t.name()));
            assert_eq!(serde_json::from_str::<BuiltinTarget>(&json).unwrap(), t);
        }
        assert_eq!(
            "Starlink".parse::<BuiltinTarget>().unwrap(),
            BuiltinTarget::Starlink
        );
        let err = "hubble".parse::<BuiltinTarget>().unwrap_err();
        assert!(err.to_string().contains("hubble"));
    }
}
