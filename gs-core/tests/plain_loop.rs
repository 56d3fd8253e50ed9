//! Training behaviour of configuration (a), plain 3DGS on the Sun-aware trainer:
//! determinism (across runs and thread counts, with densification, opacity resets and the
//! SH degree schedule), how the mask enters, non-finite steps being skipped, clear errors
//! for bad input, and a zero position rate freezing the means.

mod common;

use common::plain::{ground_truth, plain_model, ring_views, train, RunLog, Schedule, View};
use glam::Vec3;
use gs_core::init::{random_in_sphere, SplitMix64};
use gs_core::nn::SceneBox;
use gs_core::sunaware::{checkpoint, SunAwareConfig, SunAwareModel, SunAwareTrainer, Variant};
use gs_core::{GaussianModel, ModelLayout, Param};

/// Half size of the scene box: the ground truth lies within about 1.6 m of the origin.
const HALF_SIZE_M: f32 = 1.6;

/// A schedule that exercises every part of the loop in a few hundred steps.
fn busy_schedule(steps: usize) -> Schedule {
    Schedule {
        steps,
        densify_from: 40,
        densify_until: steps - 20,
        densify_interval: 40,
        opacity_reset_interval: 120,
        seed: 3,
    }
}

fn start_model() -> GaussianModel {
    random_in_sphere(150, Vec3::ZERO, 1.0, ModelLayout::sh(1), 5)
        .unwrap()
        .model
}

/// A trainer of [`start_model`] raising the SH degree every 60 steps.
fn trainer(edit: impl FnOnce(&mut SunAwareConfig)) -> SunAwareTrainer {
    SunAwareTrainer::new(plain_model(start_model(), HALF_SIZE_M, |c| {
        c.sh_degree_interval = 60;
        edit(c);
    }))
}

/// The trainer's whole state (model, optimiser moments, statistics, counters) and the loss
/// history, as bits.
fn bits(t: &SunAwareTrainer, log: &RunLog) -> (Vec<u8>, Vec<u32>) {
    let losses = log.losses.iter().map(|x| x.to_bits()).collect();
    (checkpoint::to_bytes(t), losses)
}

#[test]
fn training_is_bit_identical_across_runs_and_thread_counts() {
    let gt = ground_truth(60, 1);
    let views = ring_views(&gt, 8, 40);
    let schedule = busy_schedule(260);
    let run = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut t = trainer(|c| c.seed = seed);
            let log = train(&mut t, &views, &schedule);
            (t, log)
        })
    };
    let (ta, a) = run(2, 0);
    let reference = bits(&ta, &a);
    let (tb, b) = run(2, 0);
    assert!(bits(&tb, &b) == reference, "two runs with 2 threads differ");
    let (tc, c) = run(1, 0);
    assert!(bits(&tc, &c) == reference, "1 thread differs from 2");
    let (td, d) = run(3, 0);
    assert!(bits(&td, &d) == reference, "3 threads differ from 2");
    assert_eq!(a.densify_reports, d.densify_reports);
    // The run did densify, reset and raise the SH degree, and it learned something.
    assert!(a.densify_reports.len() >= 4);
    assert_ne!(ta.model.len(), 150);
    assert_eq!(ta.active_sh_degree(), 1);
    let first: f32 = a.losses[..20].iter().sum();
    let last: f32 = a.losses[a.losses.len() - 20..].iter().sum();
    assert!(last < 0.5 * first, "loss {first} -> {last}");
    assert_eq!(a.skipped, 0);
    assert_eq!(ta.skipped_nonfinite, 0);
    // The seed feeds densification's random draws.
    let (te, e) = run(2, 4);
    assert!(bits(&te, &e) != reference, "the seed changes nothing");
    // Every view is used once per pass of the shuffle.
    let mut pass: Vec<usize> = a.order[..8].to_vec();
    pass.sort();
    assert_eq!(pass, (0..8).collect::<Vec<_>>());
}

/// Pixels more than 5 px (half the SSIM window) outside the mask cannot influence
/// training: garbage there gives a bit-identical result, with the masked-background tile
/// skip on (the default) and off.
#[test]
fn pixels_far_outside_the_mask_do_not_influence_training() {
    let gt = ground_truth(60, 2);
    let size = 40usize;
    let mut views = ring_views(&gt, 6, size as u32);
    let mask: Vec<f32> = (0..size * size)
        .map(|p| if (p % size) < 20 { 1.0 } else { 0.0 })
        .collect();
    for v in &mut views {
        v.mask = Some(mask.clone());
    }
    let mut garbage = views.clone();
    let mut rng = SplitMix64::new(8);
    for v in &mut garbage {
        for p in 0..size * size {
            if p % size >= 26 {
                for c in 0..3 {
                    v.image[p * 3 + c] = rng.next_f32();
                }
            }
        }
    }
    let schedule = busy_schedule(120);
    for skip_tiles in [true, false] {
        let go = |views: &[View]| {
            let mut t = trainer(|c| c.skip_masked_background_tiles = skip_tiles);
            let log = train(&mut t, views, &schedule);
            bits(&t, &log)
        };
        let a = go(&views);
        assert!(
            go(&garbage) == a,
            "garbage outside the mask changed training (tile skip {skip_tiles})"
        );
        // ...while garbage inside the mask does change it.
        let mut inside = views.clone();
        inside[0].image[3 * 5] = 1.0 - inside[0].image[3 * 5];
        assert!(go(&inside) != a, "a pixel inside the mask changed nothing");
    }
}

/// A Gaussian whose colour is huge but finite (SH DC coefficients of 1e30) makes the SSIM
/// statistics overflow: every step is skipped and counted, and nothing reaches the model.
#[test]
fn non_finite_steps_are_counted_and_never_applied() {
    let gt = ground_truth(20, 3);
    let views = ring_views(&gt, 4, 24);
    let mut t = trainer(|_| {});
    let params = &mut t.model.gaussians.params;
    params.row_mut(Param::ShDc, 0).fill(1e30);
    // Make Gaussian 0 big, opaque and central so every view sees it.
    params.row_mut(Param::Mean, 0).fill(0.0);
    params.row_mut(Param::LogScale, 0).fill(0.3f32.ln());
    params.row_mut(Param::OpacityLogit, 0)[0] = 3.0;
    let before = t.clone();
    let schedule = Schedule {
        steps: 10,
        densify_from: 0,
        densify_until: 0,
        densify_interval: 100,
        opacity_reset_interval: 0,
        seed: 0,
    };
    let log = train(&mut t, &views, &schedule);
    assert_eq!(log.skipped, 10);
    assert_eq!(t.skipped_nonfinite, 10);
    assert_eq!(t.steps, 0);
    assert_eq!(t.model, before.model);
    assert_eq!(t.adam, before.adam);
    assert!(log.losses.iter().all(|l| l.is_nan()), "{:?}", log.losses);
}

#[test]
fn bad_input_is_a_clear_error() {
    let gt = ground_truth(10, 4);
    let views = ring_views(&gt, 3, 16);
    let mut t = trainer(|_| {});
    let before = t.clone();
    let reason = |edit: &dyn Fn(&mut View), index: usize| -> String {
        let mut bad = views[index].clone();
        edit(&mut bad);
        let mut t = before.clone();
        let msg = t.step(&bad.obs(), 0.0).unwrap_err().to_string();
        assert_eq!(t, before, "a refused step changed the trainer");
        msg
    };
    let msg = reason(&|v| v.image.pop().map(|_| ()).unwrap(), 1);
    assert!(msg.contains("H * W * 3"), "{msg}");
    let msg = reason(&|v| v.image[4] = f32::NAN, 2);
    assert!(msg.contains("not finite"), "{msg}");
    let msg = reason(&|v| v.mask = Some(vec![1.0; 10]), 0);
    assert!(msg.contains("mask"), "{msg}");
    let msg = reason(&|v| v.mask = Some(vec![0.0; 256]), 0);
    assert!(msg.contains("zero everywhere"), "{msg}");
    let msg = reason(&|v| v.mask = Some(vec![2.0; 256]), 1);
    assert!(msg.contains("[0, 1]"), "{msg}");
    // A zero Sun vector is refused even where the configuration does not read it.
    let mut zero_sun = views[0].obs();
    zero_sun.sun_dir = Vec3::ZERO;
    let msg = t.step(&zero_sun, 0.0).unwrap_err().to_string();
    assert!(msg.contains("Sun vector"), "{msg}");
    let msg = t.step(&views[0].obs(), f32::NAN).unwrap_err().to_string();
    assert!(msg.contains("lr_progress_in_round"), "{msg}");
    assert_eq!(t, before);

    let scene_box = SceneBox::new([-HALF_SIZE_M; 3], [HALF_SIZE_M; 3]).unwrap();
    let config = SunAwareConfig {
        sh_degree: 1,
        ..SunAwareConfig::for_variant(Variant::A)
    };
    let bad_config = SunAwareConfig {
        lambda_dssim: 1.5,
        ..config.clone()
    };
    let msg = SunAwareModel::new(start_model(), scene_box, bad_config)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("lambda_dssim"), "{msg}");
    let mut nan_model = start_model();
    nan_model.params.get_mut(Param::LogScale)[7] = f32::INFINITY;
    let msg = SunAwareModel::new(nan_model, scene_box, config)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains(Param::LogScale.name()) && msg.contains("value 7"),
        "{msg}"
    );
    // No scene extent from a degenerate box.
    assert!(SceneBox::new([0.0; 3], [0.0; 3]).is_err());
}

/// A position rate of zero freezes the means while everything else still learns.
#[test]
fn a_zero_position_rate_freezes_the_means() {
    let gt = ground_truth(40, 6);
    let views = ring_views(&gt, 5, 32);
    let mut t = trainer(|c| {
        c.lr.position_init = 0.0;
        c.lr.position_final = 0.0;
    });
    let start = t.model.gaussians.clone();
    for (k, v) in views.iter().enumerate() {
        let s = t.step(&v.obs(), k as f32 / views.len() as f32).unwrap();
        assert_eq!(s.position_lr, 0.0);
        assert!(!s.skipped);
    }
    let p = &t.model.gaussians.params;
    assert_eq!(p.get(Param::Mean), start.params.get(Param::Mean));
    assert_ne!(p.get(Param::ShDc), start.params.get(Param::ShDc));
    assert_ne!(p.get(Param::LogScale), start.params.get(Param::LogScale));
}
