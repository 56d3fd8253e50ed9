//! Plain 3DGS scenes and a fixed-view-set training driver for configuration (a) of the
//! Sun-aware trainer (SH colour, no networks): the model of the paper's Table I row (a),
//! trained as vanilla 3DGS trains (a seeded shuffle of the views, densification every
//! `densify_interval` steps inside a window, periodic opacity resets, the position rate
//! decaying over the whole run).
//!
//! Invariants: scenes and the view order come from the caller's seeds only, so a run is a
//! pure function of (start model, views, schedule, thread count); configuration (a)
//! ignores the Sun vector, so every observation carries the same fixed one.

use glam::{Quat, Vec3};
use gs_core::camera::{Camera, Intrinsics};
use gs_core::densify::{reset_opacity, DensifyReport};
use gs_core::init::inverse_sigmoid;
use gs_core::nn::SceneBox;
use gs_core::rng::SplitMix64;
use gs_core::sh::rgb_to_sh_dc;
use gs_core::sunaware::{Observation, SunAwareConfig, SunAwareModel, SunAwareTrainer, Variant};
use gs_core::{GaussianModel, ModelLayout, Param};

/// The Sun vector of every observation (configuration (a) does not read it).
pub const SUN: Vec3 = Vec3::Z;

/// One posed training or held-out image.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    /// `H * W * 3` RGB in [0, 1].
    pub image: Vec<f32>,
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<Vec<f32>>,
}

impl View {
    pub fn obs(&self) -> Observation<'_> {
        Observation {
            camera: self.camera,
            sun_dir: SUN,
            image: &self.image,
            mask: self.mask.as_deref(),
        }
    }
}

/// A configuration-(a) model of `gaussians` (the configuration's SH degree follows the
/// model's) in the cube of half size `half_size_m` around the origin, with `edit` applied
/// to the configuration.
pub fn plain_model(
    gaussians: GaussianModel,
    half_size_m: f32,
    edit: impl FnOnce(&mut SunAwareConfig),
) -> SunAwareModel {
    let mut config = SunAwareConfig {
        sh_degree: gaussians.layout().sh_degree,
        // The driver below chooses when densification runs.
        densify_from_step: 0,
        ..SunAwareConfig::for_variant(Variant::A)
    };
    edit(&mut config);
    let h = half_size_m;
    let scene_box = SceneBox::new([-h; 3], [h; 3]).unwrap();
    SunAwareModel::new(gaussians, scene_box, config).unwrap()
}

/// Renders `gt` (at its full SH degree, black background) from each camera.
pub fn render_views(gt: &GaussianModel, cameras: &[Camera]) -> Vec<View> {
    let model = plain_model(gt.clone(), 2.0, |_| {});
    cameras
        .iter()
        .map(|&camera| View {
            camera,
            image: model.render(&camera, SUN).unwrap().image,
            mask: None,
        })
        .collect()
}

/// A ground-truth cloud of `n` SH-degree-0 Gaussians (flat, rotated, opacity 0.8, random
/// colours) around the origin, drawn from `seed`.
pub fn ground_truth(n: usize, seed: u64) -> GaussianModel {
    let mut rng = SplitMix64::new(seed);
    let mut m = GaussianModel::new(ModelLayout::sh(0)).unwrap();
    m.params.push_zeros(n);
    for i in 0..n {
        let p = Vec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.4;
        let q = Quat::from_rotation_z(rng.next_f32() * 6.0) * Quat::from_rotation_x(1.0);
        let params = &mut m.params;
        params
            .row_mut(Param::Mean, i)
            .copy_from_slice(&p.to_array());
        params.row_mut(Param::LogScale, i).copy_from_slice(&[
            0.12f32.ln(),
            0.06f32.ln(),
            0.03f32.ln(),
        ]);
        params
            .row_mut(Param::Rotation, i)
            .copy_from_slice(&[q.w, q.x, q.y, q.z]);
        params.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(0.8);
        for c in params.row_mut(Param::ShDc, i) {
            *c = rgb_to_sh_dc(rng.next_f32());
        }
    }
    m
}

/// `n` views on a ring of radius 3 around the origin, `size` x `size` pixels, rendered from
/// `gt`.
pub fn ring_views(gt: &GaussianModel, n: usize, size: u32) -> Vec<View> {
    let k = Intrinsics::from_fov_x(45f32.to_radians(), size, size);
    let cameras: Vec<Camera> = (0..n)
        .map(|i| {
            let a = i as f32 / n as f32 * std::f32::consts::TAU;
            let eye = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.8 * (3.0 * a).sin());
            Camera::look_at(k, eye, Vec3::ZERO, Vec3::Z)
        })
        .collect();
    render_views(gt, &cameras)
}

/// When densification and opacity resets run (1-based step numbers, as in 3DGS).
#[derive(Clone, Copy, Debug)]
pub struct Schedule {
    pub steps: usize,
    /// Densify-and-prune at steps `from < s < until` that are multiples of `interval`.
    pub densify_from: usize,
    pub densify_until: usize,
    pub densify_interval: usize,
    /// Opacities capped at 0.01 every this many steps before `densify_until` (0: never).
    pub opacity_reset_interval: usize,
    /// Seeds the shuffle of the views.
    pub seed: u64,
}

/// What a driven run did.
#[derive(Clone, Debug, PartialEq)]
pub struct RunLog {
    /// Loss of every step (NaN or infinite where the step was refused).
    pub losses: Vec<f32>,
    /// Steps refused for something non-finite.
    pub skipped: usize,
    /// Densifications, with their step.
    pub densify_reports: Vec<(usize, DensifyReport)>,
    /// The view of every step.
    pub order: Vec<usize>,
}

/// Trains `t` on `views` under `schedule`: every view once per pass of a seeded shuffle,
/// the position rate decaying over the whole run.
pub fn train(t: &mut SunAwareTrainer, views: &[View], schedule: &Schedule) -> RunLog {
    let mut shuffle = SplitMix64::new(schedule.seed);
    let mut pending: Vec<usize> = Vec::new();
    let mut log = RunLog {
        losses: Vec::with_capacity(schedule.steps),
        skipped: 0,
        densify_reports: Vec::new(),
        order: Vec::with_capacity(schedule.steps),
    };
    for step in 1..=schedule.steps {
        if pending.is_empty() {
            pending = (0..views.len()).collect();
            shuffle.shuffle(&mut pending);
        }
        let index = pending.pop().expect("refilled above");
        let progress = (step - 1) as f32 / schedule.steps as f32;
        let stats = t.step(&views[index].obs(), progress).unwrap();
        log.losses.push(stats.loss);
        log.skipped += stats.skipped as usize;
        log.order.push(index);
        if step >= schedule.densify_until {
            continue;
        }
        if step > schedule.densify_from && step.is_multiple_of(schedule.densify_interval) {
            log.densify_reports
                .push((step, t.densify_and_prune().unwrap()));
        }
        let reset = schedule.opacity_reset_interval;
        if reset > 0 && step.is_multiple_of(reset) {
            reset_opacity(&mut t.model.gaussians, &mut t.adam, 0.01);
        }
    }
    log
}
