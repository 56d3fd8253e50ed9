//! Evaluation views: random target attitudes, viewpoints at the scenario's ranges, random roll,
//! random Sun and Earth directions; never part of the training sequence.
//!
//! Invariants: view k depends only on the scenario seed and k (its own RNG stream), so the set
//! is identical whatever the number of frames; the Sun is always up (no eclipse) and the phase
//! angle (camera-target-Sun) is at most `EVAL_MAX_PHASE_DEG`, so no view is a black backlit
//! silhouette.

use crate::orbit::{look_at_camera_from_inertial, FrameGeometry, RendezvousGeometry};
use crate::scenario::Scenario;
use glam::{DQuat, DVec3};
use gs_core::rng::{mix64, SplitMix64};

use super::noise::random_unit_vector;

/// Largest camera-target-Sun angle of an evaluation view, degrees.
pub(crate) const EVAL_MAX_PHASE_DEG: f64 = 120.0;
const EVAL_STREAM: u64 = 0x6576_616C_7669_6577;

/// Smallest and largest camera-target range over the scenario's duration (at least one orbit).
pub(crate) fn scenario_range_m(scenario: &Scenario, geometry: &RendezvousGeometry) -> (f64, f64) {
    let duration_s = (scenario.frame_count() as f64 * scenario.sequence.cadence_s)
        .max(geometry.chief.period_s());
    let samples = 2000;
    (0..=samples)
        .map(|i| {
            geometry
                .servicer_rtn_m(duration_s * i as f64 / samples as f64)
                .length()
        })
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
            (lo.min(r), hi.max(r))
        })
}

/// Uniformly distributed rotation (Shoemake's method).
pub(crate) fn random_rotation(rng: &mut SplitMix64) -> DQuat {
    let (u1, u2, u3) = (rng.next_f64(), rng.next_f64(), rng.next_f64());
    let tau = std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    DQuat::from_xyzw(
        a * (tau * u2).sin(),
        a * (tau * u2).cos(),
        b * (tau * u3).sin(),
        b * (tau * u3).cos(),
    )
    .normalize()
}

/// Geometry of evaluation view `k`. Orbit-only fields (time, chief position, RTN position) are
/// zero: an evaluation view is not on the trajectory.
pub(crate) fn eval_view(
    scenario: &Scenario,
    geometry: &RendezvousGeometry,
    k: u32,
    (range_lo_m, range_hi_m): (f64, f64),
) -> FrameGeometry {
    let mut rng = SplitMix64::new(mix64(scenario.seed ^ EVAL_STREAM) ^ mix64(k as u64 + 1));
    let q_inertial_from_target = random_rotation(&mut rng);
    let view_dir = random_unit_vector(&mut rng);
    let range_m = range_lo_m + (range_hi_m - range_lo_m) * rng.next_f64();
    let camera_rel_target = view_dir * range_m;
    let up_hint = random_unit_vector(&mut rng);
    let q_camera_from_inertial = look_at_camera_from_inertial(camera_rel_target, up_hint);
    let cos_max_phase = EVAL_MAX_PHASE_DEG.to_radians().cos();
    let mut sun = view_dir;
    for _ in 0..64 {
        let candidate = random_unit_vector(&mut rng);
        if candidate.dot(view_dir) >= cos_max_phase {
            sun = candidate;
            break;
        }
    }
    let earth = random_unit_vector(&mut rng);
    let q_target_from_inertial = q_inertial_from_target.inverse();
    let sun_dir_camera = q_camera_from_inertial * sun;
    FrameGeometry {
        time_s: 0.0,
        chief_position_eci_m: DVec3::ZERO,
        servicer_rtn_m: DVec3::ZERO,
        range_m,
        q_camera_from_target: (q_camera_from_inertial * q_inertial_from_target).normalize(),
        t_camera_from_target_m: q_camera_from_inertial * (-camera_rel_target),
        q_inertial_from_target,
        sun_dir_target: q_target_from_inertial * sun,
        sun_dir_camera,
        sun_dir_servicer_body: geometry.q_body_from_camera * sun_dir_camera,
        earth_dir_target: q_target_from_inertial * earth,
        // Lit fraction of the Earth's disc seen from the target, as in the sequence.
        earth_fill_strength: geometry.earth_albedo_strength * 0.5 * (1.0 - sun.dot(earth)),
        sun_visible_fraction: 1.0,
        eclipse: false,
        phase_angle_rad: view_dir.dot(sun).clamp(-1.0, 1.0).acos(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_are_seeded_in_range_and_lit() {
        let scenario = Scenario::default();
        let geometry = scenario
            .geometry(crate::scenario::TargetSize::sphere(6.0))
            .unwrap();
        let (lo, hi) = scenario_range_m(&scenario, &geometry);
        assert!(lo > 30.0 && hi > 2.0 * lo && hi < 2.3 * lo, "{lo} {hi}");
        let mut mean_sun = DVec3::ZERO;
        for k in 0..200 {
            let v = eval_view(&scenario, &geometry, k, (lo, hi));
            assert_eq!(v, eval_view(&scenario, &geometry, k, (lo, hi)));
            assert!(v.range_m >= lo && v.range_m <= hi);
            assert!(v.phase_angle_rad.to_degrees() <= EVAL_MAX_PHASE_DEG + 1e-9);
            assert!((v.t_camera_from_target_m - DVec3::new(0.0, 0.0, v.range_m)).length() < 1e-9);
            // Sun seen from the camera agrees with the Sun in the target frame through the pose.
            assert!(
                (v.q_camera_from_target * v.sun_dir_target - v.sun_dir_camera).length() < 1e-12
            );
            mean_sun += v.q_inertial_from_target * v.sun_dir_target;
        }
        // Directions are spread over the sphere, not stuck near one value.
        assert!(mean_sun.length() / 200.0 < 0.2);
        let other = Scenario {
            seed: 2,
            ..Scenario::default()
        };
        assert_ne!(
            eval_view(&other, &geometry, 0, (lo, hi)),
            eval_view(&scenario, &geometry, 0, (lo, hi))
        );
    }
}
