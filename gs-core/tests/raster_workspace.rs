//! A reused [`RasterWorkspace`] gives results bit-identical to fresh calls.
//!
//! The workspace keeps scratch buffers (tile-major forward buffers, backward records and
//! sums) between calls without clearing them, so this checks that no stale value is ever
//! read: one workspace is driven through scenes of different sizes, channel counts and
//! images (large, then small, then large again, so leftovers from a bigger call sit in
//! the buffers), and every output and gradient must match a fresh `render` /
//! `render_backward` bit for bit.

use glam::Vec3;
use gs_core::raster::{
    render, render_backward, render_backward_with, render_with, GaussianGrads, GaussianView,
    PixelGrads, RasterSettings, RasterWorkspace, RenderOutput,
};
use gs_core::rng::SplitMix64;
use gs_core::{Camera, Intrinsics};

struct Scene {
    means: Vec<f32>,
    log_scales: Vec<f32>,
    rotations: Vec<f32>,
    opacity_logits: Vec<f32>,
    channels: Vec<f32>,
    n_channels: usize,
}

impl Scene {
    fn random(seed: u64, n: usize, n_channels: usize) -> Self {
        let mut rng = SplitMix64::new(seed);
        let mut u = |lo, hi, count: usize| (0..count).map(|_| rng.uniform(lo, hi)).collect();
        Self {
            means: u(-1.0, 1.0, 3 * n),
            log_scales: u(-3.5, -1.5, 3 * n),
            rotations: u(-1.0, 1.0, 4 * n),
            opacity_logits: u(-3.0, 4.0, n),
            channels: u(0.0, 1.0, n * n_channels),
            n_channels,
        }
    }

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
}

fn camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(0.9, width, height),
        Vec3::new(0.5, -4.0, 1.0),
        Vec3::ZERO,
        Vec3::Z,
    )
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn assert_same(label: &str, a: &(RenderOutput, GaussianGrads), b: &(RenderOutput, GaussianGrads)) {
    let (oa, ga) = a;
    let (ob, gb) = b;
    assert_eq!(bits(&oa.color), bits(&ob.color), "{label}: color");
    assert_eq!(bits(&oa.alpha), bits(&ob.alpha), "{label}: alpha");
    assert_eq!(bits(&oa.depth), bits(&ob.depth), "{label}: depth");
    assert_eq!(bits(&oa.radii_px), bits(&ob.radii_px), "{label}: radii");
    assert_eq!(bits(&ga.d_means), bits(&gb.d_means), "{label}: d_means");
    assert_eq!(
        bits(&ga.d_log_scales),
        bits(&gb.d_log_scales),
        "{label}: d_log_scales"
    );
    assert_eq!(
        bits(&ga.d_rotations),
        bits(&gb.d_rotations),
        "{label}: d_rotations"
    );
    assert_eq!(
        bits(&ga.d_opacity_logits),
        bits(&gb.d_opacity_logits),
        "{label}: d_opacity_logits"
    );
    assert_eq!(
        bits(&ga.d_channels),
        bits(&gb.d_channels),
        "{label}: d_channels"
    );
    assert_eq!(
        bits(&ga.mean2d_grad_ndc),
        bits(&gb.mean2d_grad_ndc),
        "{label}: mean2d_grad_ndc"
    );
}

fn pixel_grads(out: &RenderOutput, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = SplitMix64::new(seed);
    let px = out.width as usize * out.height as usize;
    let mut u = |count: usize| (0..count).map(|_| rng.uniform(-1.0, 1.0)).collect();
    (u(px * out.n_channels), u(px), u(px))
}

#[test]
fn reused_workspace_matches_fresh_calls_bit_for_bit() {
    let settings = RasterSettings::default();
    let mut workspace = RasterWorkspace::default();
    // (Gaussians, channels, width, height): big, small, different channel count, big.
    let cases = [
        (4000, 3, 160, 120),
        (300, 3, 40, 30),
        (2500, 4, 97, 61),
        (1500, 1, 160, 120),
        (4000, 3, 160, 120),
    ];
    for (i, &(n, nc, width, height)) in cases.iter().enumerate() {
        let scene = Scene::random(100 + i as u64, n, nc);
        let cam = camera(width, height);
        let fresh_out = render(&cam, &scene.view(), &settings).unwrap();
        let (c, a, d) = pixel_grads(&fresh_out, 7 + i as u64);
        let pixel = PixelGrads {
            d_color: &c,
            d_alpha: Some(&a),
            d_depth: Some(&d),
        };
        let fresh_grads =
            render_backward(&cam, &scene.view(), &settings, &fresh_out, &pixel).unwrap();
        let reused_out = render_with(&mut workspace, &cam, &scene.view(), &settings).unwrap();
        let reused_grads = render_backward_with(
            &mut workspace,
            &cam,
            &scene.view(),
            &settings,
            &reused_out,
            &pixel,
        )
        .unwrap();
        // The scene is not trivial: pixels covered and gradients non-zero.
        assert!(fresh_out.alpha.iter().any(|&v| v > 0.5), "case {i}");
        assert!(fresh_grads.d_means.iter().any(|&v| v != 0.0), "case {i}");
        assert_same(
            &format!("case {i}"),
            &(fresh_out, fresh_grads),
            &(reused_out, reused_grads),
        );
    }
}
