//! The camera model, the hull start and eclipse from telemetry, through the component over
//! loopback UDP with the real Sun-aware learner:
//! - a frame of another size without its own camera model is rejected, counted and
//!   evented; with a camera model (CameraFrame 1.1) the same frame is used;
//! - predictions are rendered with the configured camera: moving the principal point moves
//!   the rendered target by as many pixels;
//! - with masks, the first full window is carved into a visual hull: the event says so, the
//!   scene box and the Gaussians shrink from the 5 m prior to the 1 m target; without masks
//!   the random start stays, with an event;
//! - eclipse flags skip frames (with a Sun direction: the learner's eclipse skip; without
//!   one: the synchronizer's), and the unlit skip reads the mask, not the full frame.
//!
//! The scene: a sphere of radius 1 m at the target origin, seen from 10 m by a camera
//! circling the target's y axis at 45 degrees per second, 64x64 px with f = 80 px (the disc is
//! about 8 px in radius); telemetry at 1 Hz, frame k half way between samples k and k+1.

mod component_support;

use component_support::{set_camera, start_component, temp_dir, Peer};
use fsw_component::config::ComponentConfig;
use fsw_component::runtime::{ComponentHandle, LearnerKind};
use glam::DQuat;
use interfaces::messages::{
    AckStatus, CameraFrame, CameraModel, CommandKind, Distortion, ErrorCode, EventKind,
    FrameHeader, InitSource, PixelFormat, PredictionSource, SunVector, TargetPose,
};
use std::time::{Duration, Instant};

const SIZE: u16 = 64;
const FOCAL_PX: f32 = 80.0;
const RANGE_M: f64 = 10.0;
const RADIUS_M: f64 = 1.0;
const DEG_PER_S: f64 = 45.0;
const WAIT: Duration = Duration::from_secs(60);

fn camera_from_target(time_us: u64) -> DQuat {
    DQuat::from_rotation_y((time_us as f64 / 1e6 * DEG_PER_S).to_radians())
}

fn pose(time_us: u64) -> TargetPose {
    let q = camera_from_target(time_us);
    TargetPose {
        time_us,
        q_camera_from_target: [q.w as f32, q.x as f32, q.y as f32, q.z as f32],
        t_camera_from_target_m: [0.0, 0.0, RANGE_M as f32],
        position_sigma_m: 0.01,
        attitude_sigma_rad: 0.001,
        valid: true,
    }
}

fn sun(time_us: u64, eclipse: Option<bool>, valid: bool) -> SunVector {
    SunVector {
        time_us,
        sun_body: [0.0, 0.0, -1.0],
        valid,
        eclipse,
    }
}

/// The sphere seen from the boresight at `(cx, cy)`: (RGB pixels, mask) with `value` on it.
fn sphere_image(size: u16, focal_px: f32, cx: f32, cy: f32, value: u8) -> (Vec<u8>, Vec<u8>) {
    let n = usize::from(size);
    // Silhouette radius of a sphere of radius r at distance d: f r / sqrt(d^2 - r^2).
    let radius_px =
        f64::from(focal_px) * RADIUS_M / (RANGE_M * RANGE_M - RADIUS_M * RADIUS_M).sqrt();
    let mut rgb = vec![0u8; n * n * 3];
    let mut mask = vec![0u8; n * n];
    for y in 0..n {
        for x in 0..n {
            let (u, v) = (
                x as f64 + 0.5 - f64::from(cx),
                y as f64 + 0.5 - f64::from(cy),
            );
            if u * u + v * v <= radius_px * radius_px {
                mask[y * n + x] = 255;
                rgb[(y * n + x) * 3..(y * n + x) * 3 + 3].fill(value);
            }
        }
    }
    (rgb, mask)
}

fn config(peer: &Peer, name: &str, init: &str) -> ComponentConfig {
    let mut config = peer.config(temp_dir(name).join("checkpoint.bin"));
    set_camera(&mut config, SIZE, FOCAL_PX);
    config.model.init = init.to_string();
    config.model.initial_gaussians = 500;
    config.model.hull_resolution = 48;
    config
}

/// Telemetry at k+1 s (and 0 s for k = 0) with `sun_of` for the Sun samples, then, once
/// stored, `frame` at k + 0.5 s.
async fn step(
    peer: &mut Peer,
    handle: &ComponentHandle,
    k: u32,
    sun_of: impl Fn(u64) -> SunVector,
    frame: CameraFrame<'_>,
) {
    let stored = |h: &ComponentHandle| {
        let c = h.counters().sync;
        c.pose.stored_valid + c.pose.stored_invalid + c.sun.stored_valid + c.sun.stored_invalid
    };
    let before = stored(handle);
    let mut times = vec![u64::from(k + 1) * 1_000_000];
    if k == 0 {
        times.insert(0, 0);
    }
    for &t in &times {
        peer.send(&pose(t), handle.telemetry_addr).await;
        peer.send(&sun_of(t), handle.telemetry_addr).await;
    }
    let deadline = Instant::now() + Duration::from_secs(5);
    while stored(handle) < before + 2 * times.len() as u64 {
        assert!(
            Instant::now() < deadline,
            "telemetry of step {k} not stored"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    peer.send(&frame, handle.frames_addr).await;
}

fn header(k: u32, size: u16) -> FrameHeader {
    FrameHeader {
        frame_id: k,
        time_us: u64::from(k) * 1_000_000 + 500_000,
        width: size,
        height: size,
        format: PixelFormat::Rgb8,
    }
}

async fn wait_processed(handle: &ComponentHandle, frames: u64) {
    let deadline = Instant::now() + WAIT;
    while handle.worker_snapshot().frames_processed < frames {
        assert!(Instant::now() < deadline, "{frames} frames not processed");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

fn initialised(peer: &Peer) -> Vec<(InitSource, u32)> {
    peer.snapshot(|r| {
        r.events
            .iter()
            .filter_map(|e| match e.kind {
                EventKind::ModelInitialised { source, gaussians } => Some((source, gaussians)),
                _ => None,
            })
            .collect()
    })
}

fn lit(t: u64) -> SunVector {
    sun(t, None, true)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mismatched_frames_are_rejected_with_an_event_and_own_cameras_are_used() {
    let mut peer = Peer::new().await;
    let config = config(&peer, "camera-mismatch", "random");
    let handle = start_component(&config, LearnerKind::SunAware, None).await;
    let (rgb, _) = sphere_image(20, 50.0, 10.0, 10.0, 200);
    // 20x20 without a camera model: not the configured 64x64.
    let wrong = CameraFrame {
        header: header(0, 20),
        mask: None,
        pixels: &rgb,
        camera: None,
    };
    step(&mut peer, &handle, 0, lit, wrong).await;
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r.events.iter().any(
            |e| matches!(
                e.kind,
                EventKind::Error {
                    code: ErrorCode::CameraMismatch,
                    ..
                }
            )
        ))
        .await,
        "no CameraMismatch event"
    );
    assert_eq!(handle.counters().bus.frames_camera_mismatch, 1);
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r
            .last_health()
            .is_some_and(|h| h.frames_dropped == 1))
            .await,
        "health does not count the rejected frame"
    );
    // The same image with its own camera model is used, and predicted at its size.
    let own = CameraFrame {
        header: header(1, 20),
        mask: None,
        pixels: &rgb,
        camera: Some(CameraModel {
            fx_px: 50.0,
            fy_px: 50.0,
            cx_px: 10.0,
            cy_px: 10.0,
            distortion: Distortion::None,
        }),
    };
    step(&mut peer, &handle, 1, lit, own).await;
    wait_processed(&handle, 1).await;
    let source = PredictionSource::ObservedFrame { frame_id: 1 };
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .predictions
            .iter()
            .any(|p| p.source == source && p.pixels.len() == 20 * 20 * 3))
            .await
    );
    assert_eq!(handle.counters().bus.frames_camera_mismatch, 1);
    assert_eq!(handle.worker_snapshot().frames_used, 1);
    handle.shutdown().await;
}

/// Column of the brightness centroid of an RGB image.
fn centroid_x(pixels: &[u8], size: u16) -> f64 {
    let n = usize::from(size);
    let (mut sum, mut weight) = (0.0, 0.0);
    for (i, rgb) in pixels.chunks_exact(3).enumerate() {
        let w: f64 = rgb.iter().map(|&v| f64::from(v)).sum();
        sum += w * ((i % n) as f64 + 0.5);
        weight += w;
    }
    assert!(weight > 0.0, "the prediction is black");
    sum / weight
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn predictions_use_the_configured_principal_point() {
    let mut centroids = Vec::new();
    for cx in [32.0f32, 26.0] {
        let mut peer = Peer::new().await;
        let mut config = config(&peer, "camera-cx", "random");
        config.camera.cx_px = cx;
        // A start the size of the target, so its image is a compact blob.
        config.model.target_radius_m = RADIUS_M as f32;
        let handle = start_component(&config, LearnerKind::SunAware, None).await;
        let (rgb, _) = sphere_image(SIZE, FOCAL_PX, cx, 32.0, 200);
        let frame = CameraFrame {
            header: header(0, SIZE),
            mask: None,
            pixels: &rgb,
            camera: None,
        };
        step(&mut peer, &handle, 0, lit, frame).await;
        let source = PredictionSource::ObservedFrame { frame_id: 0 };
        assert!(
            peer.wait_for(WAIT, |r| r.predictions.iter().any(|p| p.source == source))
                .await
        );
        let pixels = peer.snapshot(|r| {
            r.predictions
                .iter()
                .find(|p| p.source == source)
                .unwrap()
                .pixels
                .clone()
        });
        centroids.push(centroid_x(&pixels, SIZE));
        handle.shutdown().await;
    }
    // Rendered before any training: the random start, the same bits but for the camera.
    assert!(
        (centroids[0] - 32.0).abs() < 1.5,
        "centred camera: {centroids:?}"
    );
    let shift = centroids[0] - centroids[1];
    assert!((shift - 6.0).abs() < 1.0, "cx 32 -> 26 moved it {shift} px");
}

/// Sends `frames` sphere frames with masks (or not), all lit; returns the handle.
async fn run_sphere(
    peer: &mut Peer,
    config: &ComponentConfig,
    frames: u32,
    with_masks: bool,
) -> ComponentHandle {
    let handle = start_component(config, LearnerKind::SunAware, None).await;
    let (rgb, mask) = sphere_image(SIZE, FOCAL_PX, 32.0, 32.0, 180);
    for k in 0..frames {
        let frame = CameraFrame {
            header: header(k, SIZE),
            mask: with_masks.then_some(&mask[..]),
            pixels: &rgb,
            camera: None,
        };
        step(peer, &handle, k, lit, frame).await;
        wait_processed(&handle, u64::from(k + 1)).await;
    }
    handle
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_first_full_window_is_carved_into_a_hull_start() {
    let mut peer = Peer::new().await;
    let config = config(&peer, "camera-hull", "hull");
    let window = config.training.window_size as u32;
    let handle = run_sphere(&mut peer, &config, window, true).await;
    assert_eq!(handle.worker_snapshot().learner.rounds, 1);
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| !r.events.is_empty())
            .await
    );
    let starts = initialised(&peer);
    assert_eq!(starts.len(), 1, "{starts:?}");
    assert_eq!(starts[0].0, InitSource::Hull);
    assert!(starts[0].1 > 0 && starts[0].1 <= 500, "{starts:?}");

    // The model's scene box and Gaussians, from the checkpoint file the component writes.
    peer.command(1, CommandKind::SaveCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);
    let bytes = std::fs::read(&config.checkpoint.path).unwrap();
    handle.shutdown().await;
    // Sun-aware component checkpoint v2 (`sunaware_learner.rs`): magic, hull start pending
    // u8, trainer length u64, then gs-core's trainer.
    assert_eq!(&bytes[..8], b"FSWSAL02");
    let trainer_len = u64::from_le_bytes(bytes[9..17].try_into().unwrap()) as usize;
    let trainer = gs_core::sunaware::checkpoint::from_bytes(&bytes[17..17 + trainer_len]).unwrap();
    let scene = &trainer.model.scene_box;
    for axis in 0..3 {
        let (lo, hi) = (scene.min_m()[axis], scene.max_m()[axis]);
        // Contains the 1 m sphere, far inside the 5 m prior.
        assert!(lo < -0.9 && hi > 0.9, "axis {axis}: {lo}..{hi}");
        assert!(lo > -2.0 && hi < 2.0, "axis {axis}: {lo}..{hi}");
    }
    let means = trainer
        .model
        .gaussians
        .params
        .get(gs_core::model::Param::Mean);
    let farthest = means
        .chunks_exact(3)
        .map(|m| (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt())
        .fold(0.0f32, f32::max);
    assert!(farthest < 1.6, "a Gaussian {farthest} m from the centre");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_masks_the_random_start_stays_with_an_event() {
    let mut peer = Peer::new().await;
    let config = config(&peer, "camera-nomask", "hull");
    let window = config.training.window_size as u32;
    let handle = run_sphere(&mut peer, &config, window, false).await;
    assert_eq!(handle.worker_snapshot().learner.rounds, 1);
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| !r.events.is_empty())
            .await
    );
    assert_eq!(initialised(&peer), vec![(InitSource::RandomNoMasks, 500)]);
    handle.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eclipse_flags_and_masked_unlit_frames_are_skipped() {
    let mut peer = Peer::new().await;
    let config = config(&peer, "camera-eclipse", "random");
    let handle = start_component(&config, LearnerKind::SunAware, None).await;
    let (rgb, mask) = sphere_image(SIZE, FOCAL_PX, 32.0, 32.0, 180);
    let (dark, _) = sphere_image(SIZE, FOCAL_PX, 32.0, 32.0, 1);
    let frame = |k: u32, pixels: &'static [u8], mask: Option<&'static [u8]>| CameraFrame {
        header: header(k, SIZE),
        mask,
        pixels,
        camera: None,
    };
    let leak = |v: Vec<u8>| -> &'static [u8] { Box::leak(v.into_boxed_slice()) };
    let (rgb, mask, dark) = (leak(rgb), leak(mask), leak(dark));
    // 0: lit, used.
    step(&mut peer, &handle, 0, lit, frame(0, rgb, Some(mask))).await;
    wait_processed(&handle, 1).await;
    // 1: the AOCS flags eclipse at 2 s with its Sun direction: the learner skips the frame.
    step(
        &mut peer,
        &handle,
        1,
        |t| sun(t, Some(t >= 2_000_000), true),
        frame(1, rgb, Some(mask)),
    )
    .await;
    wait_processed(&handle, 2).await;
    assert_eq!(
        handle.worker_snapshot().frames_used,
        1,
        "eclipse frame used"
    );
    // 2 and 3: eclipse without a Sun solution at 3 s brackets both: skipped by the
    // synchronizer, no error.
    let dark_sun = |t: u64| sun(t, Some(t < 4_000_000), t != 3_000_000);
    step(&mut peer, &handle, 2, dark_sun, frame(2, rgb, Some(mask))).await;
    step(&mut peer, &handle, 3, dark_sun, frame(3, rgb, Some(mask))).await;
    let deadline = Instant::now() + WAIT;
    while handle.counters().sync.frames.eclipse < 2 {
        assert!(Instant::now() < deadline, "{:#?}", handle.counters().sync);
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(handle.counters().sync.frames.rejected_invalid, 0);
    // 4: lit again, but the target is dark under its mask: unlit, skipped.
    let sunlit = |t: u64| sun(t, Some(false), true);
    step(&mut peer, &handle, 4, sunlit, frame(4, dark, Some(mask))).await;
    wait_processed(&handle, 3).await;
    assert_eq!(
        handle.worker_snapshot().frames_used,
        1,
        "unlit masked frame used"
    );
    // 5: the same dark image without a mask: no full-frame brightness test, used.
    step(&mut peer, &handle, 5, sunlit, frame(5, dark, None)).await;
    wait_processed(&handle, 4).await;
    assert_eq!(
        handle.worker_snapshot().frames_used,
        2,
        "unmasked frame skipped"
    );
    let telemetry_errors = peer.snapshot(|r| {
        r.events
            .iter()
            .filter(|e| {
                matches!(
                    e.kind,
                    EventKind::Error {
                        code: ErrorCode::TelemetryInvalid,
                        ..
                    }
                )
            })
            .count()
    });
    assert_eq!(telemetry_errors, 0);
    handle.shutdown().await;
}
