//! Seeded sensor noise for the telemetry: a fixed bias plus per-frame Gaussian jitter on the
//! Sun vector, the attitude and the position of the camera-from-target pose.
//!
//! Invariants: the same seed gives the same noise sequence; with every setting at zero the
//! telemetry equals the truth bit for bit (no rotation is applied at all).

use crate::scenario::NoiseConfig;
use glam::{DQuat, DVec3};
use gs_core::rng::SplitMix64;

/// Noise state for one sequence: biases fixed at construction, jitter drawn per frame.
pub(crate) struct TelemetryNoise {
    config: NoiseConfig,
    sun_bias: DQuat,
    attitude_bias: DQuat,
    position_bias_m: DVec3,
    rng: SplitMix64,
}

/// Pose and Sun vectors as reported by the (noisy) sensors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct NoisyTelemetry {
    pub q_camera_from_target: DQuat,
    pub t_camera_from_target_m: DVec3,
    pub sun_dir_servicer_body: DVec3,
    pub sun_dir_target: DVec3,
}

/// Standard normal deviate (Box-Muller, one of the pair).
fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u1 = 1.0 - rng.next_f64(); // (0, 1]: ln is finite
    let u2 = rng.next_f64();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Uniformly distributed unit vector.
pub(crate) fn random_unit_vector(rng: &mut SplitMix64) -> DVec3 {
    let z = 2.0 * rng.next_f64() - 1.0;
    let phi = std::f64::consts::TAU * rng.next_f64();
    let r = (1.0 - z * z).max(0.0).sqrt();
    DVec3::new(r * phi.cos(), r * phi.sin(), z)
}

fn gaussian_vector(rng: &mut SplitMix64, sigma: f64) -> DVec3 {
    DVec3::new(gaussian(rng), gaussian(rng), gaussian(rng)) * sigma
}

impl TelemetryNoise {
    pub fn new(config: &NoiseConfig, seed: u64) -> TelemetryNoise {
        let mut rng = SplitMix64::new(gs_core::rng::mix64(seed ^ 0x6E6F_6973_655F_7631));
        let sun_bias = DQuat::from_axis_angle(
            random_unit_vector(&mut rng),
            config.sun_bias_deg.to_radians(),
        );
        let attitude_bias = DQuat::from_axis_angle(
            random_unit_vector(&mut rng),
            config.attitude_bias_deg.to_radians(),
        );
        let position_bias_m = random_unit_vector(&mut rng) * config.position_bias_m;
        TelemetryNoise {
            config: config.clone(),
            sun_bias,
            attitude_bias,
            position_bias_m,
            rng,
        }
    }

    /// Applies bias and a fresh jitter draw to the true values. The Sun in the target frame is
    /// derived from the noisy Sun sensor and the noisy pose, as on board.
    pub fn apply(
        &mut self,
        q_camera_from_target: DQuat,
        t_camera_from_target_m: DVec3,
        sun_dir_servicer_body: DVec3,
        sun_dir_target: DVec3,
        q_body_from_camera: DQuat,
    ) -> NoisyTelemetry {
        let c = &self.config;
        // Always draw the same number of deviates so streams do not shift with settings.
        let sun_jitter = gaussian_vector(&mut self.rng, c.sun_jitter_deg.to_radians());
        let attitude_jitter = gaussian_vector(&mut self.rng, c.attitude_jitter_deg.to_radians());
        let position_jitter = gaussian_vector(&mut self.rng, c.position_jitter_m);
        let sun_noisy = c.sun_bias_deg > 0.0 || c.sun_jitter_deg > 0.0;
        let attitude_noisy = c.attitude_bias_deg > 0.0 || c.attitude_jitter_deg > 0.0;
        let q = if attitude_noisy {
            (DQuat::from_scaled_axis(attitude_jitter) * self.attitude_bias * q_camera_from_target)
                .normalize()
        } else {
            q_camera_from_target
        };
        let t = if c.position_bias_m > 0.0 || c.position_jitter_m > 0.0 {
            t_camera_from_target_m + self.position_bias_m + position_jitter
        } else {
            t_camera_from_target_m
        };
        let sun_body = if sun_noisy {
            (DQuat::from_scaled_axis(sun_jitter) * self.sun_bias * sun_dir_servicer_body)
                .normalize()
        } else {
            sun_dir_servicer_body
        };
        let sun_target = if sun_noisy || attitude_noisy {
            (q.inverse() * (q_body_from_camera.inverse() * sun_body)).normalize()
        } else {
            sun_dir_target
        };
        NoisyTelemetry {
            q_camera_from_target: q,
            t_camera_from_target_m: t,
            sun_dir_servicer_body: sun_body,
            sun_dir_target: sun_target,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn truth() -> (DQuat, DVec3, DVec3, DVec3, DQuat) {
        let q = DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.0, 2.0);
        let mount = DQuat::from_rotation_y(0.4);
        let sun_target = DVec3::new(0.3, -0.5, 0.8).normalize();
        let sun_body = mount * (q * sun_target);
        (q, DVec3::new(0.0, 0.0, 40.0), sun_body, sun_target, mount)
    }

    #[test]
    fn zero_noise_is_the_truth_exactly() {
        let (q, t, sb, st, mount) = truth();
        let mut noise = TelemetryNoise::new(&NoiseConfig::default(), 7);
        let n = noise.apply(q, t, sb, st, mount);
        assert_eq!(
            n,
            NoisyTelemetry {
                q_camera_from_target: q,
                t_camera_from_target_m: t,
                sun_dir_servicer_body: sb,
                sun_dir_target: st
            }
        );
    }

    #[test]
    fn bias_and_jitter_have_the_configured_size() {
        let (q, t, sb, st, mount) = truth();
        let config = NoiseConfig {
            sun_bias_deg: 2.0,
            attitude_jitter_deg: 0.5,
            position_jitter_m: 0.1,
            ..NoiseConfig::default()
        };
        let mut noise = TelemetryNoise::new(&config, 7);
        let frames = 4000;
        let mut pos_sq = 0.0;
        let mut att_sq = 0.0;
        for _ in 0..frames {
            let n = noise.apply(q, t, sb, st, mount);
            // Pure bias on the Sun sensor: always exactly 2 deg off.
            let sun_err_deg = n.sun_dir_servicer_body.angle_between(sb).to_degrees();
            assert!(sun_err_deg <= 2.0 + 1e-9);
            pos_sq += (n.t_camera_from_target_m - t).length_squared();
            att_sq += (n.q_camera_from_target * q.inverse())
                .to_scaled_axis()
                .length_squared();
            // The target-frame Sun is consistent with the noisy sensor and pose.
            let back = mount * (n.q_camera_from_target * n.sun_dir_target);
            assert!((back - n.sun_dir_servicer_body).length() < 1e-12);
        }
        // Three axes of sigma each: E|e|^2 = 3 sigma^2 (4000 samples: a few % statistical error).
        let pos_sigma = (pos_sq / frames as f64 / 3.0).sqrt();
        let att_sigma_deg = (att_sq / frames as f64 / 3.0).sqrt().to_degrees();
        assert!((pos_sigma - 0.1).abs() < 0.005, "{pos_sigma}");
        assert!((att_sigma_deg - 0.5).abs() < 0.025, "{att_sigma_deg}");
    }
}
