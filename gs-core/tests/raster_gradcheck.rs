//! Finite-difference checks of the rasterizer's analytic backward pass, end to end
//! (projection, binning, blending), for every parameter of every Gaussian and every
//! channel, with colour, alpha and depth all in the loss.
//!
//! Scenes mix overlapping, elongated, near-plane, partly off-screen and
//! Jacobian-clamped Gaussians. They run in smooth-cutoff mode, where the image is C1 in
//! the parameters (see `blend.rs`), and the loss is a fixed random linear functional of
//! the rendered colour, alpha and depth images.

use glam::Vec3;
use gs_core::raster::{render, render_backward, GaussianView, PixelGrads, RasterSettings};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};

#[derive(Clone)]
struct Scene {
    camera: Camera,
    settings: RasterSettings,
    means: Vec<f32>,
    log_scales: Vec<f32>,
    rotations: Vec<f32>,
    opacity_logits: Vec<f32>,
    channels: Vec<f32>,
    n_channels: usize,
}

impl Scene {
    fn view(&self) -> GaussianView<'_> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels: &self.channels,
            n_channels: self.n_channels,
        }
    }

    /// Adds a Gaussian given its centre in the camera frame.
    fn push(&mut self, rng: &mut SplitMix64, centre_cam: Vec3, log_scale: [f32; 3]) {
        let world = self.camera.rotation.conjugate() * (centre_cam - self.camera.translation);
        self.means.extend(world.to_array());
        self.log_scales.extend(log_scale);
        for _ in 0..4 {
            self.rotations.push(rng.uniform(-1.0, 1.0));
        }
        // Opacities 0.12..0.88: raw alpha stays below the 0.99 clamp (a kink).
        self.opacity_logits.push(rng.uniform(-2.0, 2.0));
        for _ in 0..self.n_channels {
            self.channels.push(rng.uniform(0.0, 1.0));
        }
    }
}

/// 64x48 image, fov_x 1 rad (tan(fov/2) = 0.546, Jacobian clamp at 0.71).
fn random_scene(seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let k = Intrinsics::from_fov_x(1.0, 64, 48);
    let camera = Camera::look_at(
        k,
        Vec3::new(0.4, -0.3, -4.0),
        Vec3::new(0.0, 0.1, 0.0),
        Vec3::new(0.1, 1.0, 0.0),
    );
    let n_channels = 4;
    let mut scene = Scene {
        camera,
        settings: RasterSettings {
            near_m: 0.2,
            background: (0..n_channels).map(|_| rng.uniform(0.0, 1.0)).collect(),
            smooth_cutoff: true,
            ..RasterSettings::default()
        },
        means: vec![],
        log_scales: vec![],
        rotations: vec![],
        opacity_logits: vec![],
        channels: vec![],
        n_channels,
    };
    let ln = |v: f32| v.ln();
    // Overlapping cluster in front of the camera.
    for _ in 0..6 {
        let c = Vec3::new(
            rng.uniform(-0.4, 0.4),
            rng.uniform(-0.3, 0.3),
            rng.uniform(3.0, 5.0),
        );
        let s = [(); 3].map(|_| ln(rng.uniform(0.1, 0.35)));
        scene.push(&mut rng, c, s);
    }
    // Elongated (needles and discs).
    for _ in 0..3 {
        let c = Vec3::new(
            rng.uniform(-0.8, 0.8),
            rng.uniform(-0.5, 0.5),
            rng.uniform(3.0, 5.0),
        );
        scene.push(&mut rng, c, [ln(0.7), ln(0.04), ln(0.12)]);
    }
    // Near-plane: a few near-plane-distances in front of a 0.2 m near plane, huge on screen.
    // Their depths differ: swapping the depth order of two overlapping Gaussians is a
    // genuine discontinuity of splatting, which a finite difference must not straddle.
    for z in [0.26, 0.31] {
        let c = Vec3::new(rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), z);
        scene.push(&mut rng, c, [ln(0.02), ln(0.012), ln(0.03)]);
    }
    // Partly off-screen: centres just past the left and bottom edges.
    scene.push(&mut rng, Vec3::new(-2.45, 0.1, 4.0), [ln(0.3); 3]);
    scene.push(
        &mut rng,
        Vec3::new(0.2, 1.75, 4.0),
        [ln(0.25), ln(0.4), ln(0.2)],
    );
    // Jacobian clamp active: x/z = 0.8 > 0.71, wide enough to reach the image.
    scene.push(
        &mut rng,
        Vec3::new(3.2, -0.2, 4.0),
        [ln(0.9), ln(0.5), ln(0.6)],
    );
    scene
}

struct LossWeights {
    color: Vec<f32>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
}

fn loss_weights(scene: &Scene, seed: u64) -> LossWeights {
    let mut rng = SplitMix64::new(seed);
    let px = scene.camera.intrinsics.pixel_count();
    let mut draw = |n: usize, scale: f32| (0..n).map(|_| rng.uniform(-scale, scale)).collect();
    LossWeights {
        color: draw(px * scene.n_channels, 1.0),
        alpha: draw(px, 1.0),
        depth: draw(px, 0.3),
    }
}

fn loss(scene: &Scene, w: &LossWeights) -> f64 {
    let out = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    let dot = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| *x as f64 * *y as f64)
            .sum::<f64>()
    };
    dot(&out.color, &w.color) + dot(&out.alpha, &w.alpha) + dot(&out.depth, &w.depth)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Group {
    Mean,
    LogScale,
    Rotation,
    Opacity,
    Channel,
}

fn param_mut(scene: &mut Scene, group: Group, idx: usize) -> &mut f32 {
    match group {
        Group::Mean => &mut scene.means[idx],
        Group::LogScale => &mut scene.log_scales[idx],
        Group::Rotation => &mut scene.rotations[idx],
        Group::Opacity => &mut scene.opacity_logits[idx],
        Group::Channel => &mut scene.channels[idx],
    }
}

/// Central-difference check of every parameter.
///
/// Tolerance: |fd - analytic| <= 2e-2 * max(|fd|, |analytic|) + 2e-3 * G, where G is
/// the largest analytic gradient magnitude in that parameter group. Why: the forward is
/// f32, so the loss (a sum over ~15k weighted pixel values of order 1) carries rounding
/// noise near 1e-5; divided by 2h = 2e-3 that is ~5e-3 absolute, well under 2e-3 G for
/// these scenes (G is 1..100), and the h^2 truncation term is below 1% for h = 1e-3 at
/// the curvatures here. A wrong term in any chain-rule step gives errors of order 100%.
fn check_scene(seed: u64) {
    let scene = random_scene(seed);
    let w = loss_weights(&scene, seed ^ 0xABCD);
    let fwd = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    let n = scene.opacity_logits.len();
    assert!(
        fwd.visible.iter().all(|&v| v),
        "every Gaussian of the test scene should be visible: {:?}",
        fwd.visible
    );
    let grads = render_backward(
        &scene.camera,
        &scene.view(),
        &scene.settings,
        &fwd,
        &PixelGrads {
            d_color: &w.color,
            d_alpha: Some(&w.alpha),
            d_depth: Some(&w.depth),
        },
    )
    .unwrap();
    assert_eq!(grads.dropped_nonfinite, 0);
    let groups = [
        (Group::Mean, &grads.d_means, 3 * n),
        (Group::LogScale, &grads.d_log_scales, 3 * n),
        (Group::Rotation, &grads.d_rotations, 4 * n),
        (Group::Opacity, &grads.d_opacity_logits, n),
        (Group::Channel, &grads.d_channels, scene.n_channels * n),
    ];
    let h = 1e-3f32;
    let mut failures = Vec::new();
    let mut worst_ratio = 0.0f64;
    for (group, analytic, len) in groups {
        assert_eq!(analytic.len(), len);
        let g_max = analytic.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
        assert!(g_max > 0.0, "{group:?}: all gradients zero");
        for (idx, &an) in analytic.iter().enumerate() {
            let mut plus = scene.clone();
            *param_mut(&mut plus, group, idx) += h;
            let mut minus = scene.clone();
            *param_mut(&mut minus, group, idx) -= h;
            // Use the perturbed values actually represented in f32.
            let step =
                (*param_mut(&mut plus, group, idx) - *param_mut(&mut minus, group, idx)) as f64;
            let fd = (loss(&plus, &w) - loss(&minus, &w)) / step;
            let an = an as f64;
            let tol = 2e-2 * fd.abs().max(an.abs()) + 2e-3 * g_max;
            worst_ratio = worst_ratio.max((fd - an).abs() / tol);
            if (fd - an).abs() > tol {
                failures.push(format!(
                    "{group:?}[{idx}] (Gaussian {}): fd {fd:.6} analytic {an:.6} tol {tol:.2e}",
                    match group {
                        Group::Mean | Group::LogScale => idx / 3,
                        Group::Rotation => idx / 4,
                        Group::Opacity => idx,
                        Group::Channel => idx / scene.n_channels,
                    }
                ));
            }
        }
    }
    println!("seed {seed}: worst |fd - analytic| / tolerance = {worst_ratio:.3}");
    assert!(failures.is_empty(), "seed {seed}:\n{}", failures.join("\n"));
}

#[test]
fn gradients_match_finite_differences_scene_a() {
    check_scene(1);
}

#[test]
fn gradients_match_finite_differences_scene_b() {
    check_scene(7);
}

#[test]
fn gradients_match_finite_differences_scene_c() {
    check_scene(2026);
}
