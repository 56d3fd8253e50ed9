//! Scene builders and bit-exact comparisons shared by the rasterizer tests
//! (`raster_compact`, `raster_skips`, `raster_invariants`); [`plain`] holds the plain
//! 3DGS scenes and training driver of configuration (a) (`plain_fit`, `plain_loop`).
//!
//! Invariants: every builder draws from the caller's RNG in a fixed order, so a seed
//! always gives the same scene; the comparisons check `f32` bits, not values (NaN equals
//! NaN, -0 differs from +0).

// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

pub mod plain;

use glam::Vec3;
use gs_core::camera::Camera;
use gs_core::raster::project::GaussianParams;
use gs_core::raster::{
    render_backward, GaussianGrads, GaussianView, PixelGrads, RasterSettings, RenderOutput,
};
use gs_core::rng::SplitMix64;

/// A Gaussian model as flat arrays, in the layout `GaussianView` reads.
#[derive(Clone, Default)]
pub struct Gaussians {
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub rotations: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub channels: Vec<f32>,
    pub n_channels: usize,
}

impl Gaussians {
    pub fn new(n_channels: usize) -> Self {
        Self {
            n_channels,
            ..Default::default()
        }
    }

    pub fn view(&self) -> GaussianView<'_> {
        GaussianView {
            means: &self.means,
            log_scales: &self.log_scales,
            rotations: &self.rotations,
            opacity_logits: &self.opacity_logits,
            channels: &self.channels,
            n_channels: self.n_channels,
        }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn params(&self, i: usize) -> GaussianParams {
        let m = &self.means[3 * i..3 * i + 3];
        let s = &self.log_scales[3 * i..3 * i + 3];
        let q = &self.rotations[4 * i..4 * i + 4];
        GaussianParams {
            mean: [m[0], m[1], m[2]],
            log_scale: [s[0], s[1], s[2]],
            rotation: [q[0], q[1], q[2], q[3]],
            opacity_logit: self.opacity_logits[i],
        }
    }

    pub fn push(
        &mut self,
        mean: [f32; 3],
        log_scale: [f32; 3],
        rot: [f32; 4],
        logit: f32,
        ch: &[f32],
    ) {
        assert_eq!(ch.len(), self.n_channels);
        self.means.extend(mean);
        self.log_scales.extend(log_scale);
        self.rotations.extend(rot);
        self.opacity_logits.push(logit);
        self.channels.extend_from_slice(ch);
    }

    /// Adds a Gaussian with its centre given in the camera frame: scales of
    /// `sigma_m` times U(0.5, 1.5) per axis, a random rotation, then the opacity logit
    /// from `opacity_logit` (which may draw from `rng`), then U(0, 1) channels.
    pub fn push_in_camera(
        &mut self,
        rng: &mut SplitMix64,
        camera: &Camera,
        centre_cam: Vec3,
        sigma_m: f32,
        opacity_logit: impl FnOnce(&mut SplitMix64) -> f32,
    ) {
        let world = camera.rotation.conjugate() * (centre_cam - camera.translation);
        self.means.extend(world.to_array());
        for _ in 0..3 {
            self.log_scales.push((sigma_m * rng.uniform(0.5, 1.5)).ln());
        }
        for _ in 0..4 {
            self.rotations.push(rng.uniform(-1.0, 1.0));
        }
        self.opacity_logits.push(opacity_logit(rng));
        for _ in 0..self.n_channels {
            self.channels.push(rng.uniform(0.0, 1.0));
        }
    }

    /// Inserts Gaussian `src` of `other` at position `at`.
    pub fn insert_from(&mut self, at: usize, other: &Gaussians, src: usize) {
        let nc = self.n_channels;
        let splice = |dst: &mut Vec<f32>, from: &[f32], w: usize| {
            let row = from[src * w..src * w + w].to_vec();
            dst.splice(at * w..at * w, row);
        };
        splice(&mut self.means, &other.means, 3);
        splice(&mut self.log_scales, &other.log_scales, 3);
        splice(&mut self.rotations, &other.rotations, 4);
        splice(&mut self.opacity_logits, &other.opacity_logits, 1);
        splice(&mut self.channels, &other.channels, nc);
    }

    pub fn random_cloud(
        rng: &mut SplitMix64,
        n: usize,
        n_channels: usize,
        centre: Vec3,
        radius: f32,
    ) -> Self {
        let mut g = Gaussians::new(n_channels);
        for _ in 0..n {
            let m = centre
                + Vec3::new(
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                ) * radius;
            let s = [(); 3].map(|_| rng.uniform(-3.5, -1.5));
            let q = [(); 4].map(|_| rng.uniform(-1.0, 1.0));
            let ch: Vec<f32> = (0..n_channels).map(|_| rng.uniform(0.0, 1.0)).collect();
            g.push(m.to_array(), s, q, rng.uniform(-3.0, 4.0), &ch);
        }
        g
    }
}

/// Pixel gradients drawn from U(-1, 1): colour (`pixels * n_channels`), then alpha, then
/// depth (`pixels` each).
pub fn pixel_weights(
    rng: &mut SplitMix64,
    pixels: usize,
    n_channels: usize,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect() };
    (draw(pixels * n_channels), draw(pixels), draw(pixels))
}

/// `render_backward` of `out` with colour, alpha and depth pixel gradients.
pub fn backward(
    camera: &Camera,
    g: &Gaussians,
    settings: &RasterSettings,
    out: &RenderOutput,
    weights: &(Vec<f32>, Vec<f32>, Vec<f32>),
) -> GaussianGrads {
    render_backward(
        camera,
        &g.view(),
        settings,
        out,
        &PixelGrads {
            d_color: &weights.0,
            d_alpha: Some(&weights.1),
            d_depth: Some(&weights.2),
        },
    )
    .unwrap()
}

pub fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Same bits everywhere; the message names the first difference only.
pub fn assert_bits_eq(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!("{what}: first difference at {i}: {} vs {}", a[i], b[i]);
    }
}

/// Every gradient group the same bits, and the same dropped count.
pub fn assert_same_grads(a: &GaussianGrads, b: &GaussianGrads, what: &str) {
    assert_bits_eq(&a.d_means, &b.d_means, &format!("{what}: d_means"));
    assert_bits_eq(
        &a.d_log_scales,
        &b.d_log_scales,
        &format!("{what}: d_log_scales"),
    );
    assert_bits_eq(
        &a.d_rotations,
        &b.d_rotations,
        &format!("{what}: d_rotations"),
    );
    assert_bits_eq(
        &a.d_opacity_logits,
        &b.d_opacity_logits,
        &format!("{what}: d_opacity_logits"),
    );
    assert_bits_eq(&a.d_channels, &b.d_channels, &format!("{what}: d_channels"));
    assert_bits_eq(
        &a.mean2d_grad_ndc,
        &b.mean2d_grad_ndc,
        &format!("{what}: mean2d_grad_ndc"),
    );
    assert_eq!(a.dropped_nonfinite, b.dropped_nonfinite, "{what}: dropped");
}
