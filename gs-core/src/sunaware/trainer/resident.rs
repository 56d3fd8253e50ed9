//! Device-resident training of a batch ([`SunAwareTrainer::step_many`] on a device backend):
//! one upload of the trainer's state, the steps on the device, one download.
//!
//! Invariants: every observation is checked before any work; an error mid-batch leaves the
//! host trainer as it was before the batch (nothing is downloaded); the counters add up as
//! the CPU step's do (a refused step counts as skipped, changes nothing).

use crate::sunaware::engine::SunAwareStepInput;
use crate::sunaware::error::SunAwareError;

use super::{Observation, StepStats, StepTimings, SunAwareTrainer};

impl SunAwareTrainer {
    pub(super) fn step_many_resident(
        &mut self,
        batch: &[(Observation, f32)],
    ) -> Result<Vec<StepStats>, SunAwareError> {
        let mut suns = Vec::with_capacity(batch.len());
        for (obs, progress) in batch {
            obs.validate()?;
            if !progress.is_finite() {
                return Err(SunAwareError::Config(
                    "lr_progress_in_round must be finite".into(),
                ));
            }
            if !(obs.sun_dir.is_finite() && obs.sun_dir.length_squared() > 1e-12) {
                return Err(SunAwareError::BadObservation(format!(
                    "Sun vector {:?} is not a finite non-zero vector",
                    obs.sun_dir
                )));
            }
            suns.push(obs.sun_dir.normalize());
        }
        let Some(device) = self.model.engine() else {
            return Err(SunAwareError::Gpu("no device backend set".into()));
        };
        let engine = match &self.resident.engine {
            Some(e) => e.clone(),
            None => {
                let e = std::sync::Arc::new(std::sync::Mutex::new(device.resident()?));
                self.resident.engine = Some(e.clone());
                e
            }
        };
        let mut engine = engine
            .lock()
            .map_err(|_| SunAwareError::Gpu("resident engine lock poisoned".into()))?;
        engine.upload(
            &self.model,
            &self.adam,
            &self.appearance_adam,
            &self.shadow_adam,
            &self.densify_stats,
        )?;
        let (mut steps, mut skipped, mut dropped) = (self.steps, 0u64, 0u64);
        let mut out = Vec::with_capacity(batch.len());
        let mut failure = None;
        for ((obs, progress), sun) in batch.iter().zip(&suns) {
            let position_lr = self.position_lr(*progress);
            let rates = self.group_rates(position_lr);
            let lr = &self.model.config.lr;
            let input = SunAwareStepInput {
                camera: &obs.camera,
                sun_dir: *sun,
                target: obs.image,
                mask: obs.mask,
                rates: &rates,
                sh_degree: self.sh_degree_after(steps),
                appearance_lr: lr.appearance_mlp,
                shadow_lr: lr.shadow_mlp,
            };
            let report = match engine.step(&self.model, &input) {
                Ok(r) => r,
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            };
            if report.refused {
                skipped += 1;
            } else {
                steps += 1;
                dropped += report.dropped_nonfinite as u64;
            }
            out.push(StepStats {
                step: steps,
                loss: report.loss,
                l1: report.l1,
                ssim: report.ssim,
                iso: report.iso,
                visible: report.visible,
                network_rows: report.network_rows,
                gaussians: self.model.len(),
                position_lr,
                skipped: report.refused,
                device_sort_retries: report.sort_retries,
                // Device stage times where the adapter has timestamp queries.
                timings: StepTimings {
                    total_ms: report.total_ms,
                    ..report.stages
                },
            });
        }
        if let Some(e) = failure {
            return Err(e);
        }
        engine.download(
            &mut self.model,
            &mut self.adam,
            &mut self.appearance_adam,
            &mut self.shadow_adam,
            &mut self.densify_stats,
        )?;
        self.steps = steps;
        self.skipped_nonfinite += skipped;
        self.raster_dropped += dropped;
        Ok(out)
    }
}
