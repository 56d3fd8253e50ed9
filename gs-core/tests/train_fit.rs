//! Fit tests: a synthetic scene of 300 Gaussians, rendered from 24 views, is recovered by
//! the vanilla training loop to a held-out PSNR of at least 30 dB, from a perturbed
//! ground truth and from random points with densification.

use glam::{Quat, Vec3};
use gs_core::init::{inverse_sigmoid, random_in_sphere, SplitMix64};
use gs_core::sh::rgb_to_sh_dc;
use gs_core::train::{evaluate, render_rgb, train, TrainConfig, TrainView, ViewScore};
use gs_core::{Camera, GaussianModel, Intrinsics, ModelLayout, Param};

fn ground_truth(n: usize, rng: &mut SplitMix64) -> GaussianModel {
    let mut m = GaussianModel::new(ModelLayout::sh(0)).unwrap();
    m.params.push_zeros(n);
    for i in 0..n {
        let p = loop {
            let v = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE;
            if v.length_squared() <= 1.0 {
                break v;
            }
        };
        let q = Quat::from_euler(
            glam::EulerRot::XYZ,
            rng.next_f32() * 6.3,
            rng.next_f32() * 6.3,
            rng.next_f32() * 6.3,
        );
        let params = &mut m.params;
        params
            .row_mut(Param::Mean, i)
            .copy_from_slice(&p.to_array());
        for s in params.row_mut(Param::LogScale, i) {
            *s = (0.04 + 0.08 * rng.next_f32()).ln();
        }
        params
            .row_mut(Param::Rotation, i)
            .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        params.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(0.6 + 0.35 * rng.next_f32());
        for c in params.row_mut(Param::ShDc, i) {
            *c = rgb_to_sh_dc(0.1 + 0.8 * rng.next_f32());
        }
    }
    m
}

fn fibonacci_cameras(n: usize, offset: f32, radius: f32, k: Intrinsics) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = (i as f32 + offset) * std::f32::consts::PI * (3.0 - 5f32.sqrt());
            let eye = Vec3::new(r * phi.cos(), r * phi.sin(), z) * radius;
            Camera::look_at(k, eye, Vec3::ZERO, Vec3::Z)
        })
        .collect()
}

struct Scene {
    gt: GaussianModel,
    train_views: Vec<TrainView>,
    test_views: Vec<TrainView>,
}

/// 300 Gaussians in the unit ball, 24 training views on a sphere of radius 4 and 6
/// held-out views at other positions (radius 4.2), 64x64 pixels, black background.
fn scene(rng: &mut SplitMix64) -> Scene {
    let gt = ground_truth(300, rng);
    let k = Intrinsics::from_fov_x(40f32.to_radians(), 64, 64);
    let view = |c: Camera| TrainView {
        camera: c,
        image: render_rgb(&gt, &c, 0, [0.0; 3]).unwrap(),
        mask: None,
    };
    let train_views = fibonacci_cameras(24, 0.0, 4.0, k)
        .into_iter()
        .map(view)
        .collect();
    let test_views = fibonacci_cameras(6, 0.37, 4.2, k)
        .into_iter()
        .map(view)
        .collect();
    Scene {
        gt,
        train_views,
        test_views,
    }
}

fn mean_psnr(s: &[ViewScore]) -> f32 {
    s.iter().map(|v| v.psnr_db).sum::<f32>() / s.len() as f32
}

fn fit(scene: &Scene, start: GaussianModel, config: &TrainConfig, label: &str) -> f32 {
    let before = mean_psnr(&evaluate(&start, &scene.test_views, [0.0; 3]).unwrap());
    let t = std::time::Instant::now();
    let result = train(start, &scene.train_views, config, |_| {}).unwrap();
    let after = mean_psnr(&evaluate(&result.model, &scene.test_views, [0.0; 3]).unwrap());
    eprintln!(
        "{label}: held-out PSNR {before:.2} -> {after:.2} dB in {:.1} s, {} -> {} Gaussians \
         (ground truth {}), loss {:.4} -> {:.4}",
        t.elapsed().as_secs_f64(),
        scene.gt.len(),
        result.model.len(),
        scene.gt.len(),
        result.losses[0],
        result.losses.last().unwrap()
    );
    assert_eq!(result.skipped_non_finite_steps, 0);
    after
}

/// Ground truth with positions (sigma 0.05, about the Gaussians' size), log-scales
/// (sigma 0.3) perturbed, opacities reset to 0.5 and colours to grey; no densification.
#[test]
fn perturbed_start_recovers_held_out_views() {
    let mut rng = SplitMix64::new(1);
    let scene = scene(&mut rng);
    let mut start = scene.gt.clone();
    for v in start.params.get_mut(Param::Mean) {
        *v += 0.05 * rng.normal();
    }
    for v in start.params.get_mut(Param::LogScale) {
        *v += 0.3 * rng.normal();
    }
    start.params.get_mut(Param::OpacityLogit).fill(0.0);
    start.params.get_mut(Param::ShDc).fill(0.0);
    let config = TrainConfig {
        iterations: 2000,
        densify_until_iter: 0,
        ..TrainConfig::default()
    };
    assert!(fit(&scene, start, &config, "perturbed start") >= 30.0);
}

/// Random points in a ball with random colours, grown and pruned by densification.
#[test]
fn random_start_with_densification_recovers_held_out_views() {
    let mut rng = SplitMix64::new(2);
    let scene = scene(&mut rng);
    let start = random_in_sphere(300, Vec3::ZERO, 1.2, ModelLayout::sh(0), 3)
        .unwrap()
        .model;
    let config = TrainConfig {
        iterations: 1500,
        densify_from_iter: 100,
        densify_interval: 100,
        densify_until_iter: 700,
        opacity_reset_interval: 400,
        ..TrainConfig::default()
    };
    assert!(fit(&scene, start, &config, "random start") >= 30.0);
}
