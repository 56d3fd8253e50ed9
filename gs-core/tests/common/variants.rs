//! The frames and the training loop shared by the test `sunaware_variants` and the example
//! of the same name: a synthetic Sun-lit scene seen from an orbit of cameras under a Sun that
//! moves from view to view, and one configuration trained for a fixed number of steps (the
//! paper's cadence: densify every 10 rounds of 10 steps) and scored on held-out views.
//!
//! Phi generalises to a new Sun only when it has seen many: with 10 training views (10 Sun
//! directions) b fits its training views to 27 dB but scores no better than a on new ones
//! (it memorises); with 40 it generalises. Hence 40 training views.
//!
//! Invariants: frames and training depend only on their arguments (deterministic).

use glam::Vec3;
use gs_core::init::from_points;
use gs_core::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
use gs_core::sunaware::{
    LightConfig, LightProjection, Observation, SunAwareConfig, SunAwareModel, SunAwareTrainer,
    Variant,
};
use gs_core::Camera;

pub struct Frame {
    camera: Camera,
    sun: Vec3,
    image: Vec<f32>,
    mask: Vec<f32>,
}

pub fn make_frames(scene: &SyntheticScene, n: usize, phase: f32, w: u32, h: u32) -> Vec<Frame> {
    (0..n)
        .map(|i| {
            let t = i as f32 + phase;
            let camera = orbit_camera((t * 97.0) as usize % (n * 97), n * 97, 2.4, 0.55, w, h);
            let sun = sun_direction(2.399 * t, 0.55 + 0.35 * (1.7 * t).sin().abs());
            let (image, mask) = scene.render(&camera, sun).unwrap();
            Frame {
                camera,
                sun,
                image,
                mask,
            }
        })
        .collect()
}

fn obs(f: &Frame) -> Observation<'_> {
    Observation {
        camera: f.camera,
        sun_dir: f.sun,
        image: &f.image,
        mask: Some(&f.mask),
    }
}

/// Trains one configuration and returns (held-out PSNR, SSIM, Gaussians, ms per step).
pub fn run(
    scene: &SyntheticScene,
    train: &[Frame],
    test: &[Frame],
    variant: Variant,
    projection: LightProjection,
    steps: usize,
) -> (f32, f32, usize, f64) {
    let config = SunAwareConfig {
        light: LightConfig {
            projection,
            resolution_px: 128,
            ..LightConfig::default()
        },
        ..SunAwareConfig::for_variant(variant)
    };
    let (points, _, colours) = scene.surface_samples(0.015, 21);
    let init = from_points(&points, Some(&colours), config.layout()).unwrap();
    let model = SunAwareModel::new(init.model, scene.scene_box, config).unwrap();
    let mut t = SunAwareTrainer::new(model);
    let round = 10;
    let start = std::time::Instant::now();
    for s in 0..steps {
        let f = &train[(s * 7) % train.len()];
        let stats = t.step(&obs(f), (s % round) as f32 / round as f32).unwrap();
        assert!(!stats.skipped);
        // The paper's cadence: densify every 10 rounds of 10 steps.
        if (s + 1) % 100 == 0 {
            t.densify_and_prune().unwrap();
        }
    }
    let ms = start.elapsed().as_secs_f64() * 1e3 / steps as f64;
    let (mut psnr, mut ssim) = (0.0, 0.0);
    for f in test {
        let s = t.evaluate(&obs(f), true).unwrap();
        psnr += s.psnr_db;
        ssim += s.ssim;
    }
    (
        psnr / test.len() as f32,
        ssim / test.len() as f32,
        t.model.len(),
        ms,
    )
}
