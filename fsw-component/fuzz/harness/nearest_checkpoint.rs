//! Nearest-keyframe learner checkpoint harness: `NearestKeyframeLearner::load` on arbitrary
//! bytes. Input: `selector(1) checkpoint...`; `selector >> 1` sets the window capacity
//! (2-9), and an odd selector appends the correct CRC-32 to the bytes so that mutations
//! reach the fields behind the checksum.
//!
//! Asserted: no panic; a refused checkpoint leaves the learner's state untouched; an
//! accepted one fits the window, saves and reloads to the same bytes, predicts an image of
//! the requested size, trains (a round's loss is finite, in [0, 1]) and takes new frames.
//! Allocation is bounded by the input (libFuzzer's `-malloc_limit_mb` flags the rest).

use fsw_component::learner::{Learner, ObservedFrame, ViewRequest};
use fsw_component::nearest_learner::NearestKeyframeLearner;
use fsw_component::sync::SyncedTelemetry;
use glam::{DQuat, DVec3};
use gs_online::keyframe::WindowConfig;
use interfaces::crc::crc32_ieee;
use interfaces::messages::PixelFormat;

pub fn run(input: &[u8]) {
    let Some((&selector, rest)) = input.split_first() else {
        return;
    };
    let capacity = 2 + usize::from(selector >> 1) % 8;
    let mut bytes = rest.to_vec();
    if selector & 1 == 1 {
        bytes.extend(crc32_ieee(rest).to_le_bytes());
    }
    let mut learner = learner(capacity);
    // A learner with a model: a refused load must keep it.
    learner.offer(&frame(7, DVec3::X));
    let before = learner.save();
    if learner.load(&bytes).is_err() {
        assert_eq!(learner.save(), before, "a refused load changed the model");
        return;
    }
    let stats = learner.stats();
    assert!(usize::from(stats.window_fill) <= capacity, "{stats:?}");
    let saved = learner.save();
    let mut reloaded = self::learner(capacity);
    reloaded
        .load(&saved)
        .expect("a saved checkpoint loads again");
    assert_eq!(reloaded.save(), saved);
    for format in [PixelFormat::Rgb8, PixelFormat::Gray8] {
        let request = ViewRequest {
            camera_from_target: DQuat::IDENTITY,
            target_in_camera_m: DVec3::new(0.3, -0.2, 10.0),
            sun_in_target: DVec3::Z,
            width: 5,
            height: 3,
            format,
            intrinsics: gs_core::Intrinsics::from_fov_x(0.5, 5, 3),
        };
        if let Ok(image) = learner.predict(&request) {
            assert_eq!((image.width, image.height, image.format), (5, 3, format));
            assert_eq!(image.pixels.len(), 15 * format.bytes_per_pixel());
        } else {
            assert_eq!(
                stats.window_fill, 0,
                "a loaded window with keyframes predicts"
            );
        }
    }
    if let Ok(Some(round)) = learner.run_round_if_due() {
        assert!((0.0..=1.0).contains(&round.loss), "{round:?}");
    }
    learner.offer(&frame(u32::MAX, DVec3::NEG_Y));
    if let Ok(Some(round)) = learner.run_round_if_due() {
        assert!((0.0..=1.0).contains(&round.loss), "{round:?}");
    }
}

pub fn learner(capacity: usize) -> NearestKeyframeLearner {
    NearestKeyframeLearner::new(WindowConfig {
        capacity,
        min_view_angle_deg: 10.0,
    })
    .expect("valid window")
}

/// A 4 x 2 RGB frame seen from `view` (unit, target frame) at 10 m.
pub fn frame(id: u32, view: DVec3) -> ObservedFrame {
    ObservedFrame {
        frame_id: id,
        time_us: u64::from(id) * 1_000_000,
        width: 4,
        height: 2,
        format: PixelFormat::Rgb8,
        pixels: (0..24).map(|i| (i * 10 + id as usize) as u8).collect(),
        mask: None,
        camera: gs_core::Intrinsics::from_fov_x(0.5, 4, 2),
        telemetry: SyncedTelemetry {
            time_us: u64::from(id) * 1_000_000,
            camera_from_target: DQuat::IDENTITY,
            target_in_camera_m: -view * 10.0,
            pose_quality: 1.0,
            sun_in_body: DVec3::Z,
            sun_in_camera: DVec3::Z,
            sun_in_target: DVec3::Z,
            view_in_target: view,
            range_m: 10.0,
            eclipse: false,
        },
    }
}
