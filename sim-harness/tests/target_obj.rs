//! OBJ loading: a committed cube with an .mtl (quads, negative indices, two materials), a file
//! without materials, and clear errors for missing, malformed and out-of-range files.

use glam::Vec3;
use sim_harness::target::{load_obj, Material, TargetError, TargetMesh};
use std::path::{Path, PathBuf};

fn asset(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("assets")
        .join(name)
}

/// Signed volume by the divergence theorem (positive for outward winding).
fn signed_volume(mesh: &TargetMesh) -> f32 {
    (0..mesh.triangle_count())
        .map(|t| {
            let [a, b, c] = mesh.triangle_corners_m(t);
            a.dot(b.cross(c)) / 6.0
        })
        .sum()
}

#[test]
fn cube_with_mtl_loads_geometry_and_maps_materials() {
    let mesh = load_obj(&asset("two_material_box.obj")).unwrap();
    assert_eq!(mesh.triangle_count(), 12);
    assert!((mesh.bounding_radius_m() - 0.75f32.sqrt()).abs() < 1e-6);
    assert!((mesh.surface_area_m2() - 6.0).abs() < 1e-6);
    assert!((signed_volume(&mesh) - 1.0).abs() < 1e-6, "winding kept");

    let mut gold_triangles = 0;
    for t in 0..mesh.triangle_count() {
        let material = &mesh.materials()[mesh.material_of_triangle()[t] as usize];
        let [a, b, c] = mesh.triangle_corners_m(t);
        let normal = (b - a).cross(c - a).normalize();
        if normal.z.abs() > 0.99 {
            // The +z / -z faces use "gold_mli": our gold MLI preset, not the MTL's Kd.
            assert_eq!(material.name, "gold_mli");
            assert_eq!(
                material.base_color_linear,
                Material::gold_mli().base_color_linear
            );
            assert_eq!(material.metallic, 1.0);
            assert!(material.crinkle_amplitude > 0.0);
            gold_triangles += 1;
        } else {
            assert_eq!(material.name, "red_plastic");
            assert_eq!(material.base_color_linear, [0.8, 0.1, 0.1]);
            assert_eq!(material.metallic, 0.0);
            // Ns 98 -> alpha = sqrt(2 / 100), roughness = sqrt(alpha).
            let expected = (2.0f32 / 100.0).sqrt().sqrt();
            assert!((material.roughness - expected).abs() < 1e-6);
        }
    }
    assert_eq!(gold_triangles, 4);
}

#[test]
fn obj_without_materials_gets_the_default() {
    let mesh = load_obj(&asset("no_material_triangle.obj")).unwrap();
    assert_eq!(mesh.triangle_count(), 1);
    assert_eq!(
        mesh.materials()[mesh.material_of_triangle()[0] as usize],
        Material::default_grey()
    );
    assert_eq!(mesh.triangle_corners_m(0)[1], Vec3::new(2.0, 0.0, 0.0));
}

#[test]
fn missing_file_is_an_io_error_naming_the_path() {
    let path = asset("does_not_exist.obj");
    let err = load_obj(&path).unwrap_err();
    assert!(matches!(err, TargetError::Io { .. }), "{err:?}");
    assert!(err.to_string().contains("does_not_exist.obj"), "{err}");
}

#[test]
fn malformed_and_out_of_range_files_are_parse_errors() {
    for name in ["malformed.obj", "bad_index.obj"] {
        let err = load_obj(&asset(name)).unwrap_err();
        assert!(matches!(err, TargetError::Parse { .. }), "{name}: {err:?}");
        assert!(err.to_string().contains(name), "{err}");
    }
}

#[test]
fn missing_material_library_is_an_error() {
    let dir = std::env::temp_dir().join(format!("render_mtl_test_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("lost_mtl.obj");
    std::fs::write(
        &path,
        "mtllib nowhere.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl x\nf 1 2 3\n",
    )
    .unwrap();
    let err = load_obj(&path).unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(matches!(err, TargetError::Parse { .. }), "{err:?}");
    assert!(err.to_string().contains("material library"), "{err}");
}

#[test]
fn file_without_faces_is_an_error() {
    let dir = std::env::temp_dir().join(format!("render_obj_test_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("points_only.obj");
    std::fs::write(&path, "v 0 0 0\nv 1 0 0\n").unwrap();
    let err = load_obj(&path).unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(err.to_string().contains("no faces"), "{err}");
}

#[test]
fn relay_satellite_loads_with_every_part_on_a_preset_material() {
    // The accuracy ladder's fourth target (config/scenarios/relay.toml).
    let mesh = load_obj(&asset("relay_sat.obj")).unwrap();
    // Every triangle names one of the five presets (none fell back to the default).
    let mut used: Vec<&str> = mesh
        .material_of_triangle()
        .iter()
        .map(|&m| mesh.materials()[m as usize].name.as_str())
        .collect();
    used.sort_unstable();
    used.dedup();
    assert_eq!(
        used,
        [
            "aluminium",
            "gold_mli",
            "silver_mli",
            "solar_cell",
            "white_paint"
        ]
    );
    // The wing reaches 6.8 m along +y: the bounding sphere is that of the whole craft.
    let max_y = mesh
        .vertices_m()
        .iter()
        .map(|v| v.y)
        .fold(f32::MIN, f32::max);
    assert!((max_y - 6.8).abs() < 1e-3, "{max_y}");
    assert!(mesh.bounding_radius_m() > 3.0);
}
