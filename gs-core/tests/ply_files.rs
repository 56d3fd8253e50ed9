//! PLY files on disk: a model initialised from points survives save/load bit-exactly and
//! renders identically (as configuration (a) of the Sun-aware model); a missing file is an
//! I/O error, not a panic.

use glam::Vec3;
use gs_core::init::random_in_sphere;
use gs_core::nn::SceneBox;
use gs_core::ply::{load_ply, save_ply, PlyError};
use gs_core::sunaware::{SunAwareConfig, SunAwareModel, Variant};
use gs_core::{Camera, GaussianModel, Intrinsics, ModelLayout, Param};

/// The RGB render of `gaussians` (SH degree 3) from `camera` as configuration (a).
fn render(gaussians: &GaussianModel, camera: &Camera) -> Vec<f32> {
    let config = SunAwareConfig::for_variant(Variant::A);
    let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).unwrap();
    let model = SunAwareModel::new(gaussians.clone(), scene_box, config).unwrap();
    model.render(camera, Vec3::Z).unwrap().image
}

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
    let image = render(&model, &cam);
    assert!(image.iter().any(|&v| v > 0.0), "the view shows nothing");
    assert_eq!(image, render(&loaded.model, &cam));
    assert!(matches!(
        load_ply(dir.join("does_not_exist.ply")),
        Err(PlyError::Io(_))
    ));
}
