//! PLY files on disk: a model initialised from points survives save/load bit-exactly and
//! renders identically; a missing file is an I/O error, not a panic.

use glam::Vec3;
use gs_core::init::random_in_sphere;
use gs_core::ply::{load_ply, save_ply, PlyError};
use gs_core::train::render_rgb;
use gs_core::{Camera, Intrinsics, ModelLayout, Param};

#[test]
fn saved_model_loads_and_renders_identically() {
    let mut model = random_in_sphere(500, Vec3::ZERO, 1.0, ModelLayout::sh(3), 4)
        .unwrap()
        .model;
    // Non-trivial view-dependent colour so the f_rest ordering matters for the render.
    for (i, v) in model.params.get_mut(Param::ShRest).iter_mut().enumerate() {
        *v = ((i * 37) % 101) as f32 / 101.0 - 0.5;
    }
    let dir = std::env::temp_dir().join(format!("gs_core_ply_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("model.ply");
    save_ply(&model, &path).unwrap();
    let loaded = load_ply(&path).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(loaded.dropped_non_finite, 0);
    assert_eq!(loaded.model, model);
    let k = Intrinsics::from_fov_x(0.8, 48, 32);
    let cam = Camera::look_at(k, Vec3::new(0.5, -3.0, 1.0), Vec3::ZERO, Vec3::Z);
    assert_eq!(
        render_rgb(&model, &cam, 3, [0.0; 3]).unwrap(),
        render_rgb(&loaded.model, &cam, 3, [0.0; 3]).unwrap()
    );
    assert!(matches!(
        load_ply(dir.join("does_not_exist.ply")),
        Err(PlyError::Io(_))
    ));
}
