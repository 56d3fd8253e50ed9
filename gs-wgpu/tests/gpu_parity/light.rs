//! The shadow pass on the device against the CPU: the visibility from a random scene's
//! splats, and `GpuSunVisibility::sun_visibility` for a model in both light projections.

use super::*;

/// The GPU shadow pass against `sunaware::sun_visibility::visibility_from_splats`, on splats of a
/// random scene in a 128x128 light image with random receiver margins.
///
/// Tolerance: |V_gpu - V_cpu| <= 1e-4 for all but 0.5% of the Gaussians, and <= 2e-2 for
/// all. Why: V is a ratio of sums over a Gaussian's footprint pixels (f32 on the GPU,
/// f64 across tiles on the CPU; exp differs by an ulp), ~1e-6 apart; where rounding moves
/// an occluder's alpha across 1/255 at a pixel, that pixel's T changes by 0.4% and the
/// receiver's V by at most that.
#[test]
fn shadow_visibility_matches_cpu() {
    use gs_core::raster::blend::AlphaMode;
    use gs_core::raster::{camera_frame, project_splats};
    use gs_core::sunaware::sun_visibility::visibility_from_splats;
    use gs_wgpu::GpuSunVisibility;
    use std::sync::Arc;

    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let shadow = GpuSunVisibility::new(Arc::new(GpuRasterizer::new(ctx).unwrap())).unwrap();
    let mut scene = random_scene(31, 2000, 3, false);
    scene.camera.intrinsics = Intrinsics::from_fov_x(1.0, 128, 128);
    let frame = camera_frame(&scene.camera, 0.2).unwrap();
    let splats =
        project_splats(&frame, &scene.view(), AlphaMode { smooth: false }, 128, 128).splats;
    let mut rng = SplitMix64::new(32);
    let margins: Vec<f32> = (0..splats.len()).map(|_| rng.uniform(0.0, 0.3)).collect();
    for (radius, bias, margin) in [(2.0, 0.01, &margins[..]), (3.5, 0.05, &[][..])] {
        let cpu = visibility_from_splats(&splats, 128, radius, bias, margin);
        let gpu = shadow
            .visibility_from_splats(&splats, 128, radius, bias, margin)
            .unwrap();
        let worst = max_abs_diff(&gpu, &cpu);
        let n_off = count_above(&gpu, &cpu, 1e-4);
        let shadowed = cpu.iter().filter(|&&v| v < 0.5).count();
        let lit = cpu.iter().filter(|&&v| v > 0.9).count();
        eprintln!(
            "shadow r {radius} bias {bias}: max |dV| {worst:.2e}, {n_off} of {} above 1e-4 \
             ({shadowed} with V < 0.5, {lit} with V > 0.9)",
            cpu.len()
        );
        // The pass is not trivial: both shadowed and lit Gaussians.
        assert!(shadowed > 100 && lit > 100);
        assert!(worst <= 2e-2, "max |dV| {worst}");
        assert!(n_off * 200 <= cpu.len(), "{n_off} Gaussians off");
    }
}

/// `GpuSunVisibility::sun_visibility` against `sunaware::sun_visibility::sun_visibility` for a model, a
/// Sun direction and both light projections (same tolerance as the splat-level test).
#[test]
fn sun_visibility_matches_cpu() {
    use gs_core::init::random_in_sphere;
    use gs_core::nn::SceneBox;
    use gs_core::sunaware::config::{LightConfig, LightProjection};
    use gs_core::sunaware::sun_visibility::sun_visibility;
    use gs_core::ModelLayout;
    use gs_wgpu::{GpuSunVisibility, SunLight};
    use std::sync::Arc;

    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let shadow = GpuSunVisibility::new(Arc::new(GpuRasterizer::new(ctx).unwrap())).unwrap();
    let model = random_in_sphere(1500, Vec3::ZERO, 1.0, ModelLayout::sh(0), 9)
        .unwrap()
        .model;
    let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).unwrap();
    let sun = Vec3::new(0.3, -0.5, 0.8).normalize();
    let camera_centre = Vec3::new(0.0, -6.0, 1.0);
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        let config = LightConfig {
            projection,
            ..LightConfig::default()
        };
        let cpu = sun_visibility(&model, sun, camera_centre, &scene_box, &config, 0.01).unwrap();
        let gpu = shadow
            .sun_visibility(
                &model,
                &SunLight {
                    sun_dir: sun,
                    camera_centre,
                    scene_box: &scene_box,
                    config: &config,
                    near_m: 0.01,
                },
            )
            .unwrap();
        let worst = max_abs_diff(&gpu, &cpu);
        let n_off = count_above(&gpu, &cpu, 1e-4);
        let shadowed = cpu.iter().filter(|&&v| v < 0.5).count();
        eprintln!(
            "{projection:?}: max |dV| {worst:.2e}, {n_off} of {} above 1e-4, {shadowed} with V < 0.5",
            cpu.len()
        );
        assert!(shadowed > 50);
        assert!(worst <= 2e-2, "max |dV| {worst}");
        assert!(n_off * 200 <= cpu.len(), "{n_off} Gaussians off");
    }
}
