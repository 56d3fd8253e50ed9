//! Wavefront OBJ loading (via `tobj`): polygons are triangulated, `.mtl` materials are mapped to
//! ours (a preset when the material name names one, e.g. "gold_mli", else from Kd / Ns / illum),
//! and faces without a material get a neutral default.
//!
//! Invariants: the result passes `TargetMesh::new` (all indices checked, vertices finite); a
//! missing or malformed `.obj`, or a named `.mtl` that cannot be loaded, is an error naming the
//! file (never a silent loss of the materials). Faces using a material the library lacks get
//! the default.

use super::{Material, TargetError, TargetMesh};
use glam::Vec3;
use std::path::Path;

/// Loads an OBJ mesh (metres, target body frame) with its materials.
pub fn load_obj(path: &Path) -> Result<TargetMesh, TargetError> {
    // Open it ourselves first so a missing file gets the OS error text, which tobj drops.
    if let Err(e) = std::fs::metadata(path) {
        return Err(TargetError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        });
    }
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, materials) = tobj::load_obj(path, &options).map_err(|e| match e {
        tobj::LoadError::OpenFileFailed | tobj::LoadError::ReadError => TargetError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
        other => TargetError::Parse {
            path: path.to_path_buf(),
            message: other.to_string(),
        },
    })?;
    // tobj reports an error here only when a `mtllib` was named and none could be loaded; a
    // file without `mtllib` gives an empty list (every face then gets the default material).
    let obj_materials = materials.map_err(|e| TargetError::Parse {
        path: path.to_path_buf(),
        message: format!("its material library (mtllib) cannot be loaded: {e}"),
    })?;

    let mut ours: Vec<Material> = obj_materials.iter().map(map_material).collect();
    let default_index = ours.len();
    ours.push(Material::default_grey());
    if ours.len() > u16::MAX as usize {
        return Err(TargetError::Parse {
            path: path.to_path_buf(),
            message: format!("too many materials ({})", ours.len()),
        });
    }

    let mut vertices_m = Vec::new();
    let mut triangles = Vec::new();
    let mut material_of_triangle = Vec::new();
    for model in &models {
        let mesh = &model.mesh;
        let first = vertices_m.len() as u32;
        if mesh.positions.len() % 3 != 0 || mesh.indices.len() % 3 != 0 {
            return Err(TargetError::Parse {
                path: path.to_path_buf(),
                message: format!("object {:?} has incomplete vertex or face data", model.name),
            });
        }
        vertices_m.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2])),
        );
        let material = match mesh.material_id {
            Some(id) if id < obj_materials.len() => id,
            _ => default_index,
        } as u16;
        for tri in mesh.indices.chunks_exact(3) {
            triangles.push([tri[0] + first, tri[1] + first, tri[2] + first]);
            material_of_triangle.push(material);
        }
    }
    if triangles.is_empty() {
        return Err(TargetError::Parse {
            path: path.to_path_buf(),
            message: "no faces found".into(),
        });
    }
    TargetMesh::new(vertices_m, triangles, material_of_triangle, ours).map_err(|e| {
        TargetError::Parse {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    })
}

/// Our material for an MTL entry: a preset by name, else a dielectric (or a metal for
/// `illum 3`, reflection on) coloured by Kd, with roughness from the Phong exponent Ns.
fn map_material(m: &tobj::Material) -> Material {
    if let Some(preset) = Material::preset_for_name(&m.name) {
        return preset.sanitized();
    }
    let metallic = m.illumination_model == Some(3);
    let base = if metallic {
        m.specular.or(m.diffuse)
    } else {
        m.diffuse
    }
    .unwrap_or([0.5, 0.5, 0.5]);
    // Blinn-Phong exponent to GGX alpha (alpha^2 = 2 / (Ns + 2)), roughness = sqrt(alpha).
    let roughness = m
        .shininess
        .filter(|ns| ns.is_finite() && *ns >= 0.0)
        .map_or(0.5, |ns| (2.0 / (ns + 2.0)).sqrt().sqrt());
    Material {
        name: m.name.clone(),
        base_color_linear: base,
        metallic: if metallic { 1.0 } else { 0.0 },
        roughness,
        ..Material::default_grey()
    }
    .sanitized()
}
