//! Property tests of the synchronizer: interpolation against analytic constant-rate motion,
//! hemisphere independence, frame-chain geometry built the other way round, robustness
//! (no panic, no NaN, bounded buffers, consistent counters) under arbitrary telemetry, and
//! recovery through the time-tag guard after arbitrary time tags.

use fsw_component::sync::{
    PoseSample, SampleStatus, SunSample, SyncConfig, SyncError, Synchronizer, WaitPolicy,
};
use fsw_component::timeguard::{TelemetrySample, TimeGuardConfig, TimeTagGuard};
use glam::{DQuat, DVec3};
use proptest::prelude::*;

fn unit_vector() -> impl Strategy<Value = DVec3> {
    (0.0..std::f64::consts::TAU, -1.0..1.0f64).prop_map(|(azimuth, z)| {
        let r = (1.0 - z * z).sqrt();
        DVec3::new(r * azimuth.cos(), r * azimuth.sin(), z)
    })
}

fn rotation() -> impl Strategy<Value = DQuat> {
    (unit_vector(), -3.1..3.1f64).prop_map(|(axis, angle)| DQuat::from_axis_angle(axis, angle))
}

fn config(camera_from_body: DQuat) -> SyncConfig {
    SyncConfig {
        buffer_capacity: 16,
        max_gap_us: 5_000_000,
        stale_after_us: 10_000_000,
        camera_from_body,
        ..SyncConfig::default()
    }
}

/// Angle of the rotation taking `b` to `a`, radians (sign of the quaternions ignored).
fn angle_between(a: DQuat, b: DQuat) -> f64 {
    let d = a * b.conjugate();
    2.0 * d.xyz().length().atan2(d.w.abs())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// A target spinning at a constant rate between two samples: slerp is exact.
    #[test]
    fn slerp_matches_constant_rate_rotation(
        q0 in rotation(),
        axis in unit_vector(),
        rate_rad_per_s in -2.5..2.5f64,
        dt_us in 1_000u64..1_200_000,
        fraction in 0.0..1.0f64,
        flip_first in any::<bool>(),
        flip_second in any::<bool>(),
        translation in (-50.0..50.0f64, -50.0..50.0f64, 1.0..100.0f64),
    ) {
        let t0 = 1_000_000u64;
        let t1 = t0 + dt_us;
        let at = |t: u64| DQuat::from_axis_angle(axis, rate_rad_per_s * (t - t0) as f64 * 1e-6) * q0;
        let sign = |flip: bool| if flip { -1.0 } else { 1.0 };
        let translation = DVec3::new(translation.0, translation.1, translation.2);
        let mut s = Synchronizer::new(config(DQuat::IDENTITY)).unwrap();
        for (t, flip) in [(t0, flip_first), (t1, flip_second)] {
            prop_assert_eq!(s.push_pose(PoseSample {
                time_us: t,
                camera_from_target: at(t) * sign(flip),
                target_in_camera_m: translation,
                quality: 1.0,
            }), Ok(SampleStatus::Valid));
            prop_assert_eq!(s.push_sun(SunSample { time_us: t, sun_in_body: DVec3::Z, valid: true, eclipse: None }),
                Ok(SampleStatus::Valid));
        }
        let t = t0 + (fraction * dt_us as f64) as u64;
        let out = s.synchronize(t, WaitPolicy::NoWait).unwrap();
        // |rate * dt| < 3 rad < pi: the short arc is the true motion.
        prop_assert!(angle_between(out.camera_from_target, at(t)) < 1e-9,
            "got {:?}, want {:?}", out.camera_from_target, at(t));
        prop_assert!((out.camera_from_target.length() - 1.0).abs() < 1e-12);
        prop_assert!((out.target_in_camera_m - translation).length() < 1e-9);
    }

    /// Sun vectors: unit, in the plane of the two samples, between them, exact at sample times.
    #[test]
    fn sun_interpolation_stays_on_the_short_arc(
        a in unit_vector(),
        b in unit_vector(),
        fraction in 0.0..=1.0f64,
    ) {
        prop_assume!(a.dot(b) > -0.99);
        let mut s = Synchronizer::new(config(DQuat::IDENTITY)).unwrap();
        for (t, v) in [(0u64, a), (1_000_000, b)] {
            s.push_sun(SunSample { time_us: t, sun_in_body: v, valid: true, eclipse: None }).unwrap();
            s.push_pose(PoseSample {
                time_us: t,
                camera_from_target: DQuat::IDENTITY,
                target_in_camera_m: DVec3::Z * 10.0,
                quality: 1.0,
            }).unwrap();
        }
        let t = (fraction * 1e6) as u64;
        let out = s.synchronize(t, WaitPolicy::NoWait).unwrap();
        let v = out.sun_in_body;
        prop_assert!((v.length() - 1.0).abs() < 1e-12);
        let normal = a.cross(b);
        if normal.length() > 1e-6 {
            prop_assert!(v.dot(normal.normalize()).abs() < 1e-9);
        }
        // Between a and b: no farther from either than they are from each other.
        prop_assert!(v.dot(a) >= a.dot(b) - 1e-12 && v.dot(b) >= a.dot(b) - 1e-12);
        if t == 0 { prop_assert!((v - a).length() < 1e-15); }
        if t == 1_000_000 { prop_assert!((v - b).length() < 1e-15); }
    }

    /// Build the scene from target-frame truths, express it as the sensors would, and
    /// check the synchronizer recovers the truths.
    #[test]
    fn frame_chain_recovers_target_frame_geometry(
        target_from_camera in rotation(),
        camera_from_body in rotation(),
        camera_dir in unit_vector(),
        range_m in 1.0..500.0f64,
        sun_in_target in unit_vector(),
    ) {
        let camera_in_target = camera_dir * range_m;
        let camera_from_target = target_from_camera.inverse();
        // x_cam = R x_target + t, and the camera centre maps to 0.
        let target_in_camera_m = -(camera_from_target * camera_in_target);
        let sun_in_body = camera_from_body.inverse() * (camera_from_target * sun_in_target);

        let mut s = Synchronizer::new(config(camera_from_body)).unwrap();
        s.push_pose(PoseSample { time_us: 5, camera_from_target, target_in_camera_m, quality: 0.9 }).unwrap();
        s.push_sun(SunSample { time_us: 5, sun_in_body, valid: true, eclipse: None }).unwrap();
        let out = s.synchronize(5, WaitPolicy::NoWait).unwrap();
        prop_assert!((out.view_in_target - camera_dir).length() < 1e-9);
        prop_assert!((out.range_m - range_m).abs() < 1e-9 * range_m);
        prop_assert!((out.sun_in_target - sun_in_target).length() < 1e-9);
        prop_assert!((out.sun_in_camera - camera_from_target * sun_in_target).length() < 1e-9);
        prop_assert_eq!(out.pose_quality, 0.9);
    }

    /// Arbitrary (hostile) telemetry: never a panic, never NaN out, buffers bounded,
    /// every push and every final answer counted exactly once.
    #[test]
    fn hostile_telemetry_is_counted_and_contained(
        events in prop::collection::vec(
            (0u8..3, 0u64..4, prop_oneof![4 => Just(0u64), 1 => 0u64..20],
             prop_oneof![1 => Just(f64::NAN), 1 => Just(f64::INFINITY), 8 => -2.0..2.0f64],
             -2.0..2.0f64, -2.0..2.0f64, any::<bool>(), any::<bool>()),
            1..200),
    ) {
        let mut s = Synchronizer::new(SyncConfig {
            buffer_capacity: 5,
            max_gap_us: 7,
            stale_after_us: 15,
            ..SyncConfig::default()
        }).unwrap();
        let (mut pose_pushes, mut sun_pushes, mut final_answers) = (0u64, 0u64, 0u64);
        let mut clock_us = 20u64;
        for (kind, advance_us, back_us, x, y, z, flag, make_unit) in events {
            // Mostly advancing time tags, sometimes reaching back (out of order, duplicates).
            clock_us += advance_us;
            let time_us = clock_us - back_us;
            // Half the samples are made well-formed so that frames do get synchronised.
            let raw = glam::DVec4::new(x, y, z, if flag { 1.0 } else { 0.1 });
            let raw = if make_unit { raw.try_normalize().unwrap_or(raw) } else { raw };
            let sun_raw = DVec3::new(x, y, z);
            let sun_raw = if make_unit { sun_raw.try_normalize().unwrap_or(sun_raw) } else { sun_raw };
            match kind {
                0 => {
                    pose_pushes += 1;
                    let _ = s.push_pose(PoseSample {
                        time_us,
                        camera_from_target: DQuat::from_vec4(raw),
                        target_in_camera_m: DVec3::new(y, z, x),
                        quality: 1.0,
                    });
                }
                1 => {
                    sun_pushes += 1;
                    let _ = s.push_sun(SunSample { time_us, sun_in_body: sun_raw, valid: flag || make_unit, eclipse: None });
                }
                _ => {
                    // Frames are usually a little older than the newest telemetry.
                    let time_us = clock_us - back_us - advance_us;
                    let policy = if flag { WaitPolicy::MayWait } else { WaitPolicy::NoWait };
                    match s.synchronize(time_us, policy) {
                        Ok(out) => {
                            final_answers += 1;
                            for v in [out.sun_in_body, out.sun_in_camera, out.sun_in_target, out.view_in_target] {
                                prop_assert!(v.is_finite() && (v.length() - 1.0).abs() < 1e-9);
                            }
                            prop_assert!(out.camera_from_target.is_finite());
                            prop_assert!((out.camera_from_target.length() - 1.0).abs() < 1e-9);
                            prop_assert!(out.target_in_camera_m.is_finite() && out.range_m > 0.0);
                        }
                        Err(e) => {
                            if e.is_final() { final_answers += 1; }
                            else {
                                let waiting = matches!(e, SyncError::AwaitingTelemetry { .. });
                                prop_assert!(waiting);
                            }
                        }
                    }
                }
            }
            prop_assert!(s.buffered(fsw_component::sync::Stream::Pose) <= 5);
            prop_assert!(s.buffered(fsw_component::sync::Stream::Sun) <= 5);
        }
        let c = s.counters();
        let pose_total = c.pose.stored_valid + c.pose.stored_invalid + c.pose.dropped_duplicate + c.pose.dropped_out_of_order;
        let sun_total = c.sun.stored_valid + c.sun.stored_invalid + c.sun.dropped_duplicate + c.sun.dropped_out_of_order;
        prop_assert_eq!(pose_total, pose_pushes);
        prop_assert_eq!(sun_total, sun_pushes);
        let f = c.frames;
        prop_assert_eq!(f.synced + f.rejected_missing + f.rejected_stale + f.rejected_invalid, final_answers);
        prop_assert_eq!(c.pose.stored_valid + c.pose.stored_invalid - c.pose.evicted_oldest,
            s.buffered(fsw_component::sync::Stream::Pose) as u64);
    }

    /// Arbitrary time tags (far future, far past, duplicates, on any receive time) then
    /// nominal 1 Hz traffic on one clock: through the time-tag guard, every frame from the
    /// (resync_after + 2)-th nominal step on is synchronised.
    #[test]
    fn arbitrary_time_tags_never_stop_synchronisation(
        prefix in prop::collection::vec(
            (any::<bool>(), prop_oneof![1 => any::<u64>(), 1 => 0u64..20_000_000],
             0u64..3_000_000, any::<bool>()),
            0..40),
        clock_offset_us in 0u64..1_000_000_000_000,
        resync_after in 2u32..5,
    ) {
        let mut s = Synchronizer::new(SyncConfig::default()).unwrap();
        let guard = TimeTagGuard::new(TimeGuardConfig { tolerance_us: 60_000_000, resync_after }).unwrap();
        let (mut pose_guard, mut sun_guard) = (guard.clone(), guard);
        let pose = |time_us| TelemetrySample::Pose(PoseSample {
            time_us,
            camera_from_target: DQuat::IDENTITY,
            target_in_camera_m: DVec3::new(0.0, 0.0, 10.0),
            quality: 1.0,
        });
        let sun = |time_us, valid| TelemetrySample::Sun(SunSample { time_us, sun_in_body: DVec3::X, valid, eclipse: None });
        let mut received_us = 1_700_000_000_000_000u64;
        for (is_pose, time_us, advance_us, valid) in prefix {
            received_us += advance_us;
            if is_pose {
                pose_guard.push(&mut s, pose(time_us), received_us);
            } else {
                sun_guard.push(&mut s, sun(time_us, valid), received_us);
            }
        }
        let first_synced_step = u64::from(resync_after) + 2;
        for k in 0..first_synced_step + 4 {
            received_us += 1_000_000;
            let t = clock_offset_us + k * 1_000_000;
            pose_guard.push(&mut s, pose(t), received_us);
            sun_guard.push(&mut s, sun(t, true), received_us + 10);
            if k >= 1 {
                let frame = s.synchronize(t - 500_000, WaitPolicy::NoWait);
                if k >= first_synced_step {
                    prop_assert!(frame.is_ok(), "step {}: {:?}", k, frame);
                }
            }
        }
    }
}
