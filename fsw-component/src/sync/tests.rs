//! Tests of `sync` (a child module, so they reach its private items).

use super::*;

fn pose(time_us: u64) -> PoseSample {
    PoseSample {
        time_us,
        camera_from_target: DQuat::IDENTITY,
        target_in_camera_m: DVec3::new(0.0, 0.0, 10.0),
        quality: 1.0,
    }
}

fn sun(time_us: u64) -> SunSample {
    SunSample {
        time_us,
        sun_in_body: DVec3::X,
        valid: true,
        eclipse: None,
    }
}

fn sync() -> Synchronizer {
    Synchronizer::new(SyncConfig {
        buffer_capacity: 4,
        max_gap_us: 1_000,
        stale_after_us: 5_000,
        ..SyncConfig::default()
    })
    .unwrap()
}

#[test]
fn config_validation_names_the_problem() {
    let bad = |f: fn(&mut SyncConfig)| {
        let mut c = SyncConfig::default();
        f(&mut c);
        c.validate().unwrap_err()
    };
    assert_eq!(
        bad(|c| c.buffer_capacity = 1),
        SyncConfigError::BufferTooSmall { capacity: 1 }
    );
    assert_eq!(bad(|c| c.max_gap_us = 0), SyncConfigError::ZeroMaxGap);
    assert!(matches!(
        bad(|c| c.unit_norm_tolerance = f64::NAN),
        SyncConfigError::BadTolerance { .. }
    ));
    assert!(matches!(
        bad(|c| c.camera_from_body = DQuat::from_xyzw(0.0, 0.0, 0.0, 2.0)),
        SyncConfigError::BadMounting { .. }
    ));
}

#[test]
fn exact_and_interpolated_samples() {
    let mut s = sync();
    s.push_pose(pose(1_000)).unwrap();
    s.push_sun(sun(1_000)).unwrap();
    let mut p = pose(2_000);
    p.camera_from_target = DQuat::from_rotation_z(1.0);
    p.target_in_camera_m = DVec3::new(0.0, 0.0, 20.0);
    p.quality = 0.5;
    s.push_pose(p).unwrap();
    s.push_sun(SunSample {
        sun_in_body: DVec3::Y,
        ..sun(2_000)
    })
    .unwrap();
    let exact = s.synchronize(1_000, WaitPolicy::NoWait).unwrap();
    assert_eq!(exact.camera_from_target, DQuat::IDENTITY);
    assert_eq!(exact.view_in_target, DVec3::new(0.0, 0.0, -1.0));
    let mid = s.synchronize(1_500, WaitPolicy::NoWait).unwrap();
    let expected = DQuat::from_rotation_z(0.5);
    assert!(mid.camera_from_target.dot(expected).abs() > 1.0 - 1e-12);
    assert!((mid.target_in_camera_m.z - 15.0).abs() < 1e-12);
    assert_eq!(mid.pose_quality, 0.5);
    let half = std::f64::consts::FRAC_1_SQRT_2;
    assert!((mid.sun_in_body - DVec3::new(half, half, 0.0)).length() < 1e-12);
    assert_eq!(s.counters().frames.synced, 2);
}

#[test]
fn each_rejection_kind_is_reported_and_counted() {
    let mut s = sync();
    assert_eq!(
        s.synchronize(10, WaitPolicy::MayWait),
        Err(SyncError::Missing {
            stream: Stream::Pose,
            detail: MissingDetail::NoSamples
        })
    );
    for t in [1_000, 1_500, 4_000] {
        s.push_pose(pose(t)).unwrap();
        s.push_sun(sun(t)).unwrap();
    }
    // Before the oldest sample.
    assert!(matches!(
        s.synchronize(900, WaitPolicy::MayWait),
        Err(SyncError::Missing {
            detail: MissingDetail::BeforeOldest {
                oldest_time_us: 1_000
            },
            ..
        })
    ));
    // 2_600 us gap between 1_500 and 4_000: both sides more than 1_000 away at 2_700.
    assert!(matches!(
        s.synchronize(2_700, WaitPolicy::MayWait),
        Err(SyncError::Missing {
            detail: MissingDetail::GapBefore { gap_us: 1_200 },
            ..
        })
    ));
    assert!(matches!(
        s.synchronize(2_400, WaitPolicy::MayWait),
        Err(SyncError::Missing {
            detail: MissingDetail::GapAfter { gap_us: 1_600 },
            ..
        })
    ));
    // After the newest: wait, or give up, or stale.
    assert_eq!(
        s.synchronize(4_500, WaitPolicy::MayWait),
        Err(SyncError::AwaitingTelemetry {
            stream: Stream::Pose
        })
    );
    assert!(matches!(
        s.synchronize(4_500, WaitPolicy::NoWait),
        Err(SyncError::Missing {
            detail: MissingDetail::NoSampleAfter {
                newest_time_us: 4_000
            },
            ..
        })
    ));
    assert_eq!(
        s.synchronize(9_001, WaitPolicy::MayWait),
        Err(SyncError::Stale {
            stream: Stream::Pose,
            age_us: 5_001
        })
    );
    // Invalid Sun flag at 4_800 brackets a frame at 4_500.
    s.push_pose(pose(5_000)).unwrap();
    assert_eq!(
        s.push_sun(SunSample {
            valid: false,
            ..sun(4_800)
        }),
        Ok(SampleStatus::Invalid(InvalidReason::FlaggedInvalid))
    );
    assert_eq!(
        s.synchronize(4_500, WaitPolicy::MayWait),
        Err(SyncError::Invalid {
            stream: Stream::Sun,
            reason: InvalidReason::FlaggedInvalid
        })
    );
    let c = s.counters().frames;
    assert_eq!(
        (
            c.synced,
            c.rejected_missing,
            c.rejected_stale,
            c.rejected_invalid
        ),
        (0, 5, 1, 1)
    );
}

#[test]
fn malformed_samples_become_invalid_markers_and_never_leak_nan() {
    let mut s = sync();
    let mut nan_pose = pose(1_000);
    nan_pose.camera_from_target = DQuat::from_xyzw(f64::NAN, 0.0, 0.0, 1.0);
    assert_eq!(
        s.push_pose(nan_pose),
        Ok(SampleStatus::Invalid(InvalidReason::NonFinite))
    );
    let mut long = pose(2_000);
    long.camera_from_target = DQuat::from_xyzw(0.0, 0.0, 0.0, 1.01);
    assert!(matches!(
        s.push_pose(long),
        Ok(SampleStatus::Invalid(InvalidReason::NonUnit { .. }))
    ));
    assert!(matches!(
        s.push_sun(SunSample {
            sun_in_body: DVec3::new(0.0, 0.5, 0.0),
            ..sun(1_000)
        }),
        Ok(SampleStatus::Invalid(InvalidReason::NonUnit { .. }))
    ));
    s.push_sun(sun(2_000)).unwrap();
    assert!(matches!(
        s.synchronize(1_500, WaitPolicy::NoWait),
        Err(SyncError::Invalid {
            stream: Stream::Pose,
            reason: InvalidReason::NonFinite
        })
    ));
    // Slightly off-unit inside the tolerance is renormalised.
    let mut near = pose(3_000);
    near.camera_from_target = DQuat::from_xyzw(0.0, 0.0, 0.0, 1.0005);
    assert_eq!(s.push_pose(near), Ok(SampleStatus::Valid));
    s.push_sun(sun(3_000)).unwrap();
    let out = s.synchronize(3_000, WaitPolicy::NoWait).unwrap();
    assert!((out.camera_from_target.length() - 1.0).abs() < 1e-15);
    assert_eq!(s.counters().pose.stored_invalid, 2);
    assert_eq!(s.counters().sun.stored_invalid, 1);
}

#[test]
fn out_of_order_duplicates_and_overflow_are_counted() {
    let mut s = sync();
    for t in [10, 20, 30] {
        s.push_sun(sun(t)).unwrap();
    }
    assert_eq!(
        s.push_sun(sun(30)),
        Err(SampleDropped::Duplicate { time_us: 30 })
    );
    assert_eq!(
        s.push_sun(sun(25)),
        Err(SampleDropped::OutOfOrder {
            time_us: 25,
            newest_time_us: 30
        })
    );
    for t in [40, 50, 60] {
        s.push_sun(sun(t)).unwrap();
    }
    assert_eq!(s.buffered(Stream::Sun), 4);
    let c = s.counters().sun;
    assert_eq!(
        (
            c.stored_valid,
            c.dropped_duplicate,
            c.dropped_out_of_order,
            c.evicted_oldest
        ),
        (6, 1, 1, 2)
    );
    s.reset_counters();
    assert_eq!(s.counters(), SyncCounters::default());
}

#[test]
fn degenerate_geometry_is_invalid() {
    let mut s = sync();
    let mut at_origin = pose(0);
    at_origin.target_in_camera_m = DVec3::ZERO;
    s.push_pose(at_origin).unwrap();
    s.push_sun(sun(0)).unwrap();
    assert!(matches!(
        s.synchronize(0, WaitPolicy::NoWait),
        Err(SyncError::Invalid {
            reason: InvalidReason::ZeroRange,
            ..
        })
    ));
    s.push_pose(pose(1_000)).unwrap();
    s.push_pose(pose(2_000)).unwrap();
    s.push_sun(SunSample {
        sun_in_body: -DVec3::X,
        ..sun(2_000)
    })
    .unwrap();
    assert!(matches!(
        s.synchronize(1_000, WaitPolicy::NoWait),
        Err(SyncError::Invalid {
            stream: Stream::Sun,
            reason: InvalidReason::SunInterpolationDegenerate
        })
    ));
}

#[test]
fn slerp_takes_the_short_way() {
    let a = DQuat::from_rotation_z(0.2);
    let b = DQuat::from_rotation_z(0.6);
    let mid = slerp_shortest(a, -b, 0.5);
    assert!(mid.dot(DQuat::from_rotation_z(0.4)).abs() > 1.0 - 1e-12);
    assert_eq!(slerp_shortest(a, b, 0.0), a);
    assert!(slerp_shortest(a, b, 1.0).dot(b) > 1.0 - 1e-15);
}
