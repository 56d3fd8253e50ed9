//! Sanity measurement (ignored by default; run with `--ignored --nocapture`): configurations
//! a-d trained for the same number of steps on the synthetic Sun-lit scene with
//! self-shadowing, scored on held-out views with new cameras and Sun directions. Prints a
//! table; the paper's ordering is PSNR(b) > PSNR(a) and PSNR(c) >= PSNR(b).
//!
//! Phi generalises to a new Sun only when it has seen many: with 10 training views (10 Sun
//! directions) b fits its training views to 27 dB but scores no better than a on new ones
//! (it memorises); with 40 it generalises. Hence 40 training views.
//!
//! The default-run test below checks the cheap, large part of that claim after a short
//! run: with the Sun moving, the model that knows the Sun and splats shadows (c) clearly
//! beats SH colour (a) on held-out views.

use glam::Vec3;
use gs_core::init::from_points;
use gs_core::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
use gs_core::sunaware::{
    LightConfig, LightProjection, Observation, SunAwareConfig, SunAwareModel, SunAwareTrainer,
    Variant,
};
use gs_core::Camera;

struct Frame {
    camera: Camera,
    sun: Vec3,
    image: Vec<f32>,
    mask: Vec<f32>,
}

fn make_frames(scene: &SyntheticScene, n: usize, phase: f32, w: u32, h: u32) -> Vec<Frame> {
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
fn run(
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

#[test]
fn sun_and_shadow_aware_model_beats_sh_under_a_moving_sun() {
    let scene = SyntheticScene::plate_and_ball(12, 60).unwrap();
    let train = make_frames(&scene, 40, 0.0, 40, 30);
    let test = make_frames(&scene, 4, 0.37, 40, 30);
    let p = LightProjection::Perspective;
    let a = run(&scene, &train, &test, Variant::A, p, 300);
    let c = run(&scene, &train, &test, Variant::C, p, 300);
    eprintln!("a {:.2} dB, c {:.2} dB", a.0, c.0);
    assert!(c.0 > a.0 + 1.0, "PSNR(c) {:.2} vs PSNR(a) {:.2}", c.0, a.0);
}

#[test]
#[ignore = "sanity measurement: prints the a-d table (about a minute)"]
fn variants_table() {
    let steps: usize = std::env::var("SUNAWARE_STEPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(800);
    let scene = SyntheticScene::plate_and_ball(16, 100).unwrap();
    let train = make_frames(&scene, 40, 0.0, 64, 48);
    let test = make_frames(&scene, 6, 0.37, 64, 48);
    println!("synthetic plate + ball, 64x48, 40 training views, 6 held-out views, {steps} steps");
    println!("| config | light | PSNR (dB) | SSIM | Gaussians | ms/step |");
    println!("|---|---|---|---|---|---|");
    let rows = [
        (Variant::A, LightProjection::Perspective),
        (Variant::B, LightProjection::Perspective),
        (Variant::C, LightProjection::Perspective),
        (Variant::C, LightProjection::Orthographic),
        (Variant::D, LightProjection::Perspective),
        (Variant::D, LightProjection::Orthographic),
    ];
    for (v, p) in rows {
        let (psnr, ssim, n, ms) = run(&scene, &train, &test, v, p, steps);
        let light = if v.uses_shadow() {
            format!("{p:?}")
        } else {
            "-".into()
        };
        println!("| {v} | {light} | {psnr:.2} | {ssim:.4} | {n} | {ms:.1} |");
    }
}
