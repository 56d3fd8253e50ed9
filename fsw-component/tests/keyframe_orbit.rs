//! The synchronizer feeding the keyframe window on a tumbling-target sequence, as the
//! component will run them: 1 Hz pose and Sun telemetry, a frame every 7 s between
//! telemetry samples, the target tumbling at 2 deg/s about its x-axis (paper, Experiments).
//!
//! Checks: interpolated view vectors match the analytic camera direction; every frame is
//! a keyframe (14 degrees per frame); the two newest are kept; and when the tumble brings
//! the view back near an old keyframe (every ~26 frames), the near-duplicate is dropped as
//! soon as both are out of the protected pair, so the non-protected keyframes stay at
//! least one frame step apart, and the window keeps frames a FIFO window would have lost.
//!
//! Observed behaviour worth knowing: with uniform motion all nearest-neighbour scores tie,
//! and the oldest-first tie-break makes the window a contiguous run of recent frames
//! (like FIFO); the rule spreads keyframes only through such revisits.

use fsw_component::sync::{PoseSample, SunSample, SyncConfig, Synchronizer, WaitPolicy};
use glam::{DQuat, DVec3};
use gs_online::keyframe::{Keyframe, KeyframeWindow, ViewDirection, WindowConfig};

const TUMBLE_RAD_PER_S: f64 = 2.0 * std::f64::consts::PI / 180.0;

/// Inertial attitude of the target at time t (target-to-inertial rotation).
fn inertial_from_target(t_s: f64) -> DQuat {
    DQuat::from_rotation_x(TUMBLE_RAD_PER_S * t_s)
}

/// Camera position in the inertial frame (target at the origin): 50 m away, drifting slowly.
fn camera_in_inertial(t_s: f64) -> DVec3 {
    let drift = 0.0001 * t_s;
    DVec3::new(drift.sin(), 0.0, drift.cos()) * 50.0
}

/// Camera axes are kept parallel to the inertial axes; only the view vector matters here.
fn pose_at(t_s: f64) -> (DQuat, DVec3) {
    let camera_from_target = inertial_from_target(t_s);
    let target_in_camera_m = -camera_in_inertial(t_s);
    (camera_from_target, target_in_camera_m)
}

fn view_truth(t_s: f64) -> DVec3 {
    (inertial_from_target(t_s).inverse() * camera_in_inertial(t_s)).normalize()
}

#[test]
fn synchronised_tumble_views_drop_revisit_duplicates() {
    let mut sync = Synchronizer::new(SyncConfig::default()).unwrap();
    let mut window: KeyframeWindow<u64> = KeyframeWindow::new(WindowConfig::default()).unwrap();
    let sun_in_body = DVec3::new(0.3, -0.4, 0.5).normalize();
    let mut telemetry_s = 0u64;
    let mut added = Vec::new();
    let mut revisits = 0usize;
    let mut kept_older_than_fifo = 0usize;
    for frame_index in 0..120u64 {
        let frame_us = frame_index * 7_000_000 + 300_000;
        // Telemetry up to one sample past the frame time.
        while telemetry_s * 1_000_000 <= frame_us + 1_000_000 {
            let (camera_from_target, target_in_camera_m) = pose_at(telemetry_s as f64);
            let time_us = telemetry_s * 1_000_000;
            sync.push_pose(PoseSample {
                time_us,
                camera_from_target,
                target_in_camera_m,
                quality: 1.0,
            })
            .unwrap();
            sync.push_sun(SunSample {
                time_us,
                sun_in_body,
                valid: true,
                eclipse: None,
            })
            .unwrap();
            telemetry_s += 1;
        }
        let synced = sync.synchronize(frame_us, WaitPolicy::MayWait).unwrap();
        let truth = view_truth(frame_us as f64 * 1e-6);
        let error_rad = synced.view_in_target.angle_between(truth);
        assert!(
            error_rad < 1e-6,
            "frame {frame_index}: view error {error_rad} rad"
        );
        // Translation is interpolated linearly, cutting the chord of the camera's 50 m arc
        // (1e-4 rad per 1 s sample): at most 50 * (1 - cos(5e-5)) = 6.25e-8 m short.
        assert!((synced.range_m - 50.0).abs() < 6.3e-8);

        let outcome = window.offer(Keyframe {
            id: frame_index,
            view: ViewDirection::new(synced.view_in_target).unwrap(),
            payload: frame_us,
        });
        if outcome.composition_changed() {
            added.push(frame_index);
        }
        assert!(window.len() <= 10);
        let keyframes = window.keyframes();
        // A first-in-first-out window would hold exactly the 10 newest frames.
        if keyframes.iter().any(|k| k.id + 10 <= frame_index) {
            kept_older_than_fifo += 1;
        }
        for (i, a) in keyframes.iter().enumerate() {
            for (j, b) in keyframes.iter().enumerate().skip(i + 1) {
                let angle_deg = a.view.get().angle_between(b.view.get()).to_degrees();
                if angle_deg < 10.0 {
                    revisits += 1;
                }
                // One frame step is 14 deg of tumble seen from at most 4.8 deg off the
                // tumble plane (camera drift): at least 14 * cos(4.8 deg) = 13.95 deg.
                if i >= 2 && j >= 2 {
                    assert!(
                        angle_deg > 13.95,
                        "frame {frame_index}: keyframes {} and {} only {angle_deg} deg apart",
                        a.id,
                        b.id
                    );
                }
            }
        }
    }
    assert_eq!(sync.counters().frames.synced, 120);
    // 14 degrees of tumble per frame: every frame moves the view past the 10 degree threshold.
    assert_eq!(added.len(), 120);
    assert_eq!(window.len(), 10);
    assert_eq!(&window.ids()[..2], &[119, 118]);

    // Dropping the older member of a duplicate pair, not the oldest keyframe, keeps
    // keyframes a FIFO window would have lost.
    assert!(kept_older_than_fifo > 0);
    assert!(
        revisits > 0,
        "the tumble never brought a view back near a kept one"
    );
}
