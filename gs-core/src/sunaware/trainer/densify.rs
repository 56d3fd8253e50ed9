//! Densification of the Sun-aware trainer: 3DGS densify-and-prune on the gradient
//! statistics gathered since the last call, under the `max_gaussians` cap.
//!
//! Invariants: the count after densification never exceeds `max_gaussians`; the random
//! stream is seeded by `(config.seed, densify_count)`, so a checkpointed trainer densifies
//! the same way after a restore.

use crate::densify::{densify_and_prune, DensifyConfig, DensifyReport};
use crate::init::SplitMix64;
use crate::sunaware::error::SunAwareError;

use super::SunAwareTrainer;

impl SunAwareTrainer {
    /// One 3DGS densify-and-prune on the statistics gathered since the last call. Before
    /// `densify_from_step` steps nothing is added (pruning still runs). `max_gaussians` is a
    /// hard cap: when more Gaussians pass the gradient threshold than there is room for,
    /// only the ones with the largest gradients are densified.
    pub fn densify_and_prune(&mut self) -> Result<DensifyReport, SunAwareError> {
        let config = &self.model.config;
        let room = config.max_gaussians.saturating_sub(self.model.len());
        let grad_threshold = if room == 0 || self.steps < config.densify_from_step {
            f32::INFINITY
        } else {
            capped_grad_threshold(
                &self.densify_stats.mean_grad(),
                config.densify.grad_threshold,
                room,
            )
        };
        let densify = DensifyConfig {
            grad_threshold,
            ..config.densify
        };
        let size_prune = config.size_prune;
        let seed = config.seed ^ 0xD3_5E_00_00;
        let mut rng =
            SplitMix64::new(seed ^ self.densify_count.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let extent = self.scene_extent();
        let report = densify_and_prune(
            &mut self.model.gaussians,
            &mut self.adam,
            &mut self.densify_stats,
            &densify,
            extent,
            size_prune,
            &mut rng,
        )?;
        self.densify_count += 1;
        Ok(report)
    }
}

/// The densify gradient threshold that lets at most `room` Gaussians through: `base`, or,
/// when more than `room` mean gradients reach it, just above the `room + 1`-th largest one.
/// Every densified Gaussian (a clone, or a split's two children replacing the parent) adds
/// exactly one, so the count after densification never exceeds the cap.
fn capped_grad_threshold(mean_grads: &[f32], base: f32, room: usize) -> f32 {
    let mut passing: Vec<f32> = mean_grads.iter().copied().filter(|&g| g >= base).collect();
    if passing.len() <= room {
        return base;
    }
    passing.sort_unstable_by(|a, b| b.total_cmp(a));
    // Strictly above the (room + 1)-th largest: ties at that value are all left out, so
    // at most `room` pass `g >= threshold`.
    let cut = passing[room];
    if cut.is_finite() {
        cut.next_up()
    } else {
        f32::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn passing(grads: &[f32], threshold: f32) -> usize {
        grads.iter().filter(|&&g| g >= threshold).count()
    }

    #[test]
    fn densify_threshold_keeps_the_base_when_there_is_room() {
        let grads = [1e-4, 3e-4, 5e-4, 0.0];
        assert_eq!(capped_grad_threshold(&grads, 2e-4, 2), 2e-4);
        assert_eq!(capped_grad_threshold(&grads, 2e-4, 10), 2e-4);
    }

    #[test]
    fn densify_threshold_lets_through_only_the_largest_gradients_up_to_the_room() {
        let grads = [9e-4, 3e-4, 7e-4, 1e-4, 5e-4, 8e-4];
        let t = capped_grad_threshold(&grads, 2e-4, 2);
        assert_eq!(passing(&grads, t), 2);
        assert!(t > 7e-4 && t <= 8e-4, "threshold {t}");
        assert_eq!(passing(&grads, capped_grad_threshold(&grads, 2e-4, 0)), 0);
    }

    #[test]
    fn densify_threshold_never_exceeds_the_room_on_ties() {
        // Four equal gradients and room for two: none of the tied ones can be chosen
        // without exceeding the cap, so only the larger one passes.
        let grads = [6e-4, 6e-4, 6e-4, 6e-4, 9e-4];
        let t = capped_grad_threshold(&grads, 2e-4, 2);
        assert_eq!(passing(&grads, t), 1);
    }
}
