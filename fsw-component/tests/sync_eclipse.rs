//! The synchronizer's eclipse rule (the ICD's): a Sun sample flagged eclipse marks the frames
//! it brackets; with a Sun direction on both sides they are synchronised with the flag set,
//! without one they are the counted, final `SyncError::Eclipse`, never NaN and never an
//! invalid-telemetry rejection; a sample flagged sunlit keeps the 1.0 validity rule.

use fsw_component::sync::{
    InvalidReason, PoseSample, SampleStatus, SunSample, SyncConfig, SyncError, Synchronizer,
    WaitPolicy,
};
use glam::{DQuat, DVec3};

fn lit(time_us: u64) -> SunSample {
    SunSample {
        time_us,
        sun_in_body: DVec3::X,
        valid: true,
        eclipse: None,
    }
}

#[test]
fn eclipse_flag_marks_frames_and_without_a_direction_skips_them() {
    let mut s = Synchronizer::new(SyncConfig::default()).unwrap();
    for t in [0, 1_000_000] {
        s.push_pose(PoseSample {
            time_us: t,
            camera_from_target: DQuat::IDENTITY,
            target_in_camera_m: DVec3::new(0.0, 0.0, 10.0),
            quality: 1.0,
        })
        .unwrap();
    }
    s.push_sun(lit(0)).unwrap();
    // Flagged eclipse with a valid vector (the AOCS's ephemeris): stored with it.
    assert_eq!(
        s.push_sun(SunSample {
            eclipse: Some(true),
            ..lit(500_000)
        }),
        Ok(SampleStatus::Valid)
    );
    // Flagged eclipse without a Sun solution: not an invalid marker either.
    assert_eq!(
        s.push_sun(SunSample {
            valid: false,
            sun_in_body: DVec3::splat(f64::NAN),
            eclipse: Some(true),
            ..lit(1_000_000)
        }),
        Ok(SampleStatus::Valid)
    );
    let sunlit = s.synchronize(0, WaitPolicy::NoWait).unwrap();
    assert!(!sunlit.eclipse);
    // Between a lit and an eclipse sample: eclipse, with the interpolated direction.
    let edge = s.synchronize(250_000, WaitPolicy::NoWait).unwrap();
    assert!(edge.eclipse && edge.sun_in_body.is_finite());
    assert!((edge.sun_in_body - DVec3::X).length() < 1e-12);
    // Next to the sample without a direction: skipped, counted, never NaN.
    assert_eq!(
        s.synchronize(750_000, WaitPolicy::NoWait),
        Err(SyncError::Eclipse)
    );
    assert_eq!(s.counters().frames.eclipse, 1);
    assert_eq!(s.counters().frames.rejected_invalid, 0);
    // `Some(false)` with an invalid vector stays an invalid marker, as without the flag.
    assert_eq!(
        s.push_sun(SunSample {
            valid: false,
            eclipse: Some(false),
            ..lit(2_000_000)
        }),
        Ok(SampleStatus::Invalid(InvalidReason::FlaggedInvalid))
    );
}
