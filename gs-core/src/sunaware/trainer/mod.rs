//! Training of a [`SunAwareModel`]: loss, Adam over every Gaussian group and both networks,
//! densification, rendering and evaluation.
//!
//! One [`SunAwareTrainer::step`] = forward, `(1 - l) L1 + l (1 - SSIM)` on the (masked)
//! image, `+ lambda_iso L_iso` for configuration (d), backward, Adam. The position rate
//! decays log-linearly from `position_init` to `position_final` (times the scene extent)
//! as `lr_progress_in_round` goes from 0 to 1: the online trainer restarts it every round
//! (the paper's sawtooth). Other groups keep constant rates, as in 3DGS.
//!
//! Invariants:
//! - a step whose render, loss or any gradient is non-finite changes nothing but the
//!   `skipped_nonfinite` counter (NaN/Inf never enter the parameters or moments);
//! - all randomness (densification) comes from SplitMix64 streams seeded by
//!   `(config.seed, densify_count)`, so the trainer's whole state is plain data that a
//!   checkpoint restores exactly;
//! - the scene extent is the scene box's diagonal (the target's size): it scales the
//!   position rate and the clone/split boundary.
//!
//! Files: this one holds the trainer's state, its rate schedule and the step on the CPU;
//! `step_io.rs` what goes into and comes out of a step, `objective.rs` the loss and
//! gradients of one observation, `flat_adam.rs` the networks' optimiser, `resident.rs`
//! the device-resident batch, `densify.rs` densification, `evaluate.rs` renders and
//! scores.

mod densify;
mod evaluate;
mod flat_adam;
mod objective;
mod resident;
mod step_io;

use std::time::Instant;

use super::engine::{Backend, ResidentTraining};
use crate::densify::DensifyStats;
use crate::model::Param;
use crate::optim::{Adam, GroupRates};

use super::error::SunAwareError;
use super::model::SunAwareModel;
use super::sun_visibility::box_sphere;

pub use evaluate::{masked_psnr, masked_ssim, RenderedImages, ViewScore};
pub use flat_adam::FlatAdam;
pub use objective::{loss_and_grads, LossParts};
pub use step_io::{Observation, StepStats, StepTimings};

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// A Sun-aware model with its optimiser state and counters.
#[derive(Clone, Debug, PartialEq)]
pub struct SunAwareTrainer {
    pub model: SunAwareModel,
    pub adam: Adam,
    pub appearance_adam: FlatAdam,
    pub shadow_adam: FlatAdam,
    pub densify_stats: DensifyStats,
    /// Steps applied (not counting skipped ones).
    pub steps: u64,
    /// Steps refused because of a non-finite render, loss or gradient.
    pub skipped_nonfinite: u64,
    /// Per-Gaussian rasterizer gradients replaced by zeros (non-finite), summed.
    pub raster_dropped: u64,
    /// Densification calls so far (seeds each call's random stream).
    pub densify_count: u64,
    /// Device-resident training on a device backend (not part of the trainer's value nor
    /// of its checkpoint).
    pub(crate) resident: ResidentSlot,
}

/// The device-resident training state ([`SunAwareTrainer::step_many`]): the engine (compiled kernels and device
/// buffers) is built on first use. Clones share the engine (each batch uploads its own
/// state, and a mutex serialises batches); equality ignores the slot.
#[derive(Clone, Default)]
pub(crate) struct ResidentSlot {
    engine: Option<std::sync::Arc<std::sync::Mutex<Box<dyn ResidentTraining>>>>,
}

impl PartialEq for ResidentSlot {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for ResidentSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ResidentSlot")
    }
}

impl SunAwareTrainer {
    pub fn new(model: SunAwareModel) -> Self {
        let adam = Adam::new(&model.gaussians.params);
        let appearance_adam =
            FlatAdam::new(model.appearance.as_ref().map_or(0, |n| n.mlp.num_params()));
        let shadow_adam = FlatAdam::new(model.shadow.as_ref().map_or(0, |n| n.mlp.num_params()));
        let densify_stats = DensifyStats::new(model.len());
        Self {
            model,
            adam,
            appearance_adam,
            shadow_adam,
            densify_stats,
            steps: 0,
            skipped_nonfinite: 0,
            raster_dropped: 0,
            densify_count: 0,
            resident: ResidentSlot::default(),
        }
    }

    /// Moves the trainer to `backend` (see [`SunAwareModel::set_backend`]): on a device,
    /// [`SunAwareTrainer::step_many`] trains device-resident. The backend is not part of
    /// the trainer's value or of its checkpoint.
    pub fn set_backend(&mut self, backend: &Backend) -> Result<(), SunAwareError> {
        self.resident.engine = None;
        self.model.set_backend(backend)
    }

    /// True when steps run device-resident: on a device backend,
    /// [`SunAwareTrainer::step_many`] keeps every parameter, moment and statistic on the
    /// device for a batch of steps.
    pub fn is_device_resident(&self) -> bool {
        self.model.engine().is_some()
    }

    /// Target size used for the position rate and the clone/split boundary, metres.
    pub fn scene_extent(&self) -> f32 {
        2.0 * box_sphere(&self.model.scene_box).1
    }

    /// SH degree in use at the current step (configuration a).
    pub fn active_sh_degree(&self) -> u32 {
        self.sh_degree_after(self.steps)
    }

    /// SH degree in use after `steps` applied steps.
    fn sh_degree_after(&self, steps: u64) -> u32 {
        let interval = self.model.config.sh_degree_interval.max(1);
        ((steps / interval).min(3) as u32).min(self.model.gaussians.layout().sh_degree)
    }

    /// Position rate at `progress` in [0, 1] through a round.
    pub fn position_lr(&self, progress: f32) -> f32 {
        let lr = &self.model.config.lr;
        let extent = self.scene_extent();
        let (a, b) = (lr.position_init * extent, lr.position_final * extent);
        if a <= 0.0 || b <= 0.0 {
            return 0.0;
        }
        let t = progress.clamp(0.0, 1.0) as f64;
        ((a as f64).ln() * (1.0 - t) + (b as f64).ln() * t).exp() as f32
    }

    fn group_rates(&self, position_lr: f32) -> GroupRates {
        let lr = &self.model.config.lr;
        let mut r = [0.0f32; Param::COUNT];
        r[Param::Mean.index()] = position_lr;
        r[Param::LogScale.index()] = lr.scale;
        r[Param::Rotation.index()] = lr.rotation;
        r[Param::OpacityLogit.index()] = lr.opacity;
        r[Param::ShDc.index()] = lr.sh_dc;
        r[Param::ShRest.index()] = lr.sh_rest;
        r[Param::Feature.index()] = lr.feature;
        r[Param::ShadowLatent.index()] = lr.shadow_latent;
        r[Param::Normal.index()] = lr.normal;
        r
    }

    /// Optimisation steps on `batch` (observation, position-rate progress) in order: the
    /// same as calling [`SunAwareTrainer::step`] on each, but when the trainer is
    /// device-resident ([`SunAwareTrainer::is_device_resident`]) the whole batch runs on
    /// the device with one upload of the trainer's state before and one download after,
    /// so the host copy (`model`, the optimisers, the statistics) is current whenever no
    /// batch is running. Every observation is checked before any work; an error mid-batch
    /// leaves the trainer as it was before the batch.
    pub fn step_many(
        &mut self,
        batch: &[(Observation, f32)],
    ) -> Result<Vec<StepStats>, SunAwareError> {
        if !self.is_device_resident() {
            return batch.iter().map(|(o, p)| self.step(o, *p)).collect();
        }
        self.step_many_resident(batch)
    }

    /// One optimisation step on one observation (on a device-resident trainer, a batch of
    /// one: see [`SunAwareTrainer::step_many`]).
    pub fn step(
        &mut self,
        obs: &Observation,
        lr_progress_in_round: f32,
    ) -> Result<StepStats, SunAwareError> {
        if self.is_device_resident() {
            let mut stats = self.step_many(&[(*obs, lr_progress_in_round)])?;
            return stats
                .pop()
                .ok_or_else(|| SunAwareError::Gpu("a batch of one gave no step".into()));
        }
        obs.validate()?;
        if !lr_progress_in_round.is_finite() {
            return Err(SunAwareError::Config(
                "lr_progress_in_round must be finite".into(),
            ));
        }
        let t_start = Instant::now();
        let settings = self.model.raster_settings(false);
        let degree = self.active_sh_degree();
        let (parts, pass, grads, mut timings) =
            loss_and_grads(&self.model, obs, degree, &settings, None)?;
        let position_lr = self.position_lr(lr_progress_in_round);
        let mut stats = StepStats {
            step: self.steps,
            loss: parts.total,
            l1: parts.l1,
            ssim: parts.ssim,
            iso: parts.iso,
            visible: pass.visible_list.len(),
            network_rows: pass.network_list.len(),
            gaussians: self.model.len(),
            position_lr,
            skipped: false,
            device_sort_retries: 0,
            timings: StepTimings::default(),
        };
        let grads = match grads {
            Some(g) if parts.total.is_finite() && g.first_non_finite().is_none() => g,
            _ => {
                self.skipped_nonfinite += 1;
                stats.skipped = true;
                self.model.recycle(pass);
                timings.total_ms = ms_since(t_start);
                stats.timings = timings;
                return Ok(stats);
            }
        };
        let t_opt = Instant::now();
        self.raster_dropped += grads.raster_dropped as u64;
        let rates = self.group_rates(position_lr);
        self.adam
            .step(&mut self.model.gaussians.params, &grads.params, &rates)?;
        if let Some(net) = &mut self.model.appearance {
            let lr = self.model.config.lr.appearance_mlp;
            self.appearance_adam
                .apply(net.mlp.params_mut(), &grads.appearance, lr)?;
        }
        if let Some(net) = &mut self.model.shadow {
            let lr = self.model.config.lr.shadow_mlp;
            self.shadow_adam
                .apply(net.mlp.params_mut(), &grads.shadow, lr)?;
        }
        self.densify_stats
            .accumulate(&grads.mean2d_grad_ndc, pass.visible(), pass.radii_px())?;
        self.steps += 1;
        stats.step = self.steps;
        self.model.recycle(pass);
        timings.optimizer_ms = ms_since(t_opt);
        timings.total_ms = ms_since(t_start);
        stats.timings = timings;
        Ok(stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::init::from_points;
    use crate::sunaware::config::{LightConfig, SunAwareConfig, Variant};
    use crate::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
    use glam::Vec3;

    /// A small configuration-d trainer on the synthetic scene and one observation of it.
    fn small_d_trainer() -> (SunAwareTrainer, Camera, Vec3, Vec<f32>, Vec<f32>) {
        let scene = SyntheticScene::plate_and_ball(14, 60).unwrap();
        let config = SunAwareConfig {
            light: LightConfig {
                resolution_px: 64,
                ..LightConfig::default()
            },
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let (points, _, colours) = scene.surface_samples(0.02, 5);
        let init = from_points(&points, Some(&colours), config.layout()).unwrap();
        let model = SunAwareModel::new(init.model, scene.scene_box, config).unwrap();
        let camera = orbit_camera(1, 8, 2.4, 0.6, 40, 32);
        let sun = sun_direction(0.4, 0.9);
        let (image, mask) = scene.render(&camera, sun).unwrap();
        (SunAwareTrainer::new(model), camera, sun, image, mask)
    }

    #[test]
    fn step_timings_are_disjoint_stages_inside_the_step() {
        let (mut t, camera, sun, image, mask) = small_d_trainer();
        let obs = Observation {
            camera,
            sun_dir: sun,
            image: &image,
            mask: Some(&mask),
        };
        for s in 0..3 {
            let stats = t.step(&obs, s as f32 / 3.0).unwrap();
            assert!(!stats.skipped);
            let tm = stats.timings;
            for (name, ms) in tm.stages() {
                assert!(ms.is_finite() && ms >= 0.0, "{name} = {ms}");
            }
            // Every stage of configuration d runs, so each takes some time.
            for (name, ms) in tm.stages() {
                assert!(ms > 0.0, "stage {name} was not timed");
            }
            // Disjoint intervals inside the step: their sum cannot exceed it (1 ns covers
            // the rounding of twelve nanosecond counts converted to milliseconds).
            assert!(
                tm.stage_sum_ms() <= tm.total_ms + 1e-6,
                "stages sum to {} ms > total {} ms",
                tm.stage_sum_ms(),
                tm.total_ms
            );
            assert!(tm.other_ms() >= -1e-6);
            assert!(tm.mlp_forward_ms() >= tm.phi_forward_ms);
        }
    }

    #[test]
    fn forward_and_loss_timings_fit_inside_loss_and_grads() {
        let (t, camera, sun, image, _) = small_d_trainer();
        let obs = Observation {
            camera,
            sun_dir: sun,
            image: &image,
            mask: None,
        };
        let settings = t.model.raster_settings(false);
        let (_, _, grads, tm) = loss_and_grads(&t.model, &obs, 0, &settings, None).unwrap();
        assert!(grads.is_some());
        assert_eq!(tm.optimizer_ms, 0.0);
        assert!(tm.stage_sum_ms() <= tm.total_ms + 1e-6);
        assert!(tm.project_ms > 0.0 && tm.blend_backward_ms > 0.0 && tm.loss_ms > 0.0);
    }
}
