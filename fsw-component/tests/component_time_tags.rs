//! Telemetry time tags over real UDP on 127.0.0.1: one far-future sample, or a backwards
//! step of the spacecraft clock, must not stop training; frames are accepted again within a
//! bounded number of telemetry samples, and the drop or the resynchronisation is evented.

mod component_support;

use component_support::*;
use fsw_component::runtime::ComponentHandle;
use fsw_component::runtime::LearnerKind;
use interfaces::messages::{CameraFrame, ErrorCode, EventKind, PredictionSource};
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(5);

/// Telemetry samples handled by the core: stored (valid or as invalid markers) or dropped.
fn telemetry_handled(h: &ComponentHandle) -> u64 {
    let c = h.counters();
    c.sync.pose.stored_valid
        + c.sync.pose.stored_invalid
        + c.sync.sun.stored_valid
        + c.sync.sun.stored_invalid
        + c.bus.telemetry_out_of_order
        + c.bus.telemetry_time_out_of_bounds
}

/// Telemetry at `t_us` (pose and Sun), handled, then a frame `id` 0.5 s before it.
async fn step_at(peer: &mut Peer, handle: &ComponentHandle, id: u32, t_us: u64) {
    let before = telemetry_handled(handle);
    peer.send(&pose_at(t_us), handle.telemetry_addr).await;
    peer.send(&sun_at(t_us), handle.telemetry_addr).await;
    // Frames and telemetry use different sockets: wait until both samples were handled,
    // so that the frame after them finds them.
    let deadline = std::time::Instant::now() + WAIT;
    while telemetry_handled(handle) < before + 2 {
        assert!(
            std::time::Instant::now() < deadline,
            "telemetry at {t_us} not handled"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let pixels = frame_pixels(id);
    let frame = CameraFrame {
        header: frame_header(id, t_us - 500_000),
        mask: None,
        pixels: &pixels,
        camera: None,
    };
    peer.send(&frame, handle.frames_addr).await;
}

/// Waits for the prediction of frame `id`: it was synchronised and reached the model.
async fn wait_predicted(peer: &Peer, id: u32) -> bool {
    let source = PredictionSource::ObservedFrame { frame_id: id };
    peer.wait_for(WAIT, |r| r.predictions.iter().any(|p| p.source == source))
        .await
}

/// Frames resolved by the synchronizer: (synchronised, all final answers).
fn frames_resolved(h: &ComponentHandle) -> (u64, u64) {
    let f = h.counters().sync.frames;
    let all = f.synced + f.rejected_missing + f.rejected_stale + f.rejected_invalid;
    (f.synced, all)
}

/// Waits for the synchronizer's final answer on one more frame; true when it was synchronised.
async fn next_frame_synced(handle: &ComponentHandle, before: (u64, u64)) -> bool {
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let now = frames_resolved(handle);
        if now.1 > before.1 {
            return now.0 > before.0;
        }
        assert!(std::time::Instant::now() < deadline, "frame not resolved");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

fn has_error_event(peer: &Peer, code: ErrorCode) -> bool {
    peer.snapshot(|r| {
        r.events
            .iter()
            .any(|e| matches!(e.kind, EventKind::Error { code: c, .. } if c == code))
    })
}

async fn started(peer: &Peer, name: &str) -> (ComponentHandle, std::path::PathBuf) {
    let dir = temp_dir(name);
    let config = peer.config(dir.join("checkpoint.bin"));
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    (handle, dir)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_single_far_future_sample_does_not_stop_training() {
    let mut peer = Peer::new().await;
    let (handle, dir) = started(&peer, "time-future").await;
    for k in 0..4 {
        send_step(&mut peer, k, &handle).await;
    }
    assert!(wait_predicted(&peer, 3).await, "nominal frame 3");
    // One Sun sample a year ahead, flagged invalid (its numbers are not checked), and one
    // pose a day ahead: neither may become the newest sample.
    let year_us = 365 * 86_400 * 1_000_000u64;
    let far = raw_sun(4_000_000 + year_us, SUN_BODY, false);
    let packets = peer.raw_packets(interfaces::messages::port::SUN_VECTOR, &far);
    for p in &packets {
        peer.send_raw(p, handle.telemetry_addr).await;
    }
    peer.send(&pose_at(4_000_000 + 86_400_000_000), handle.telemetry_addr)
        .await;
    // Nominal traffic continues: every following frame is synchronised and predicted.
    for k in 4..8u32 {
        step_at(&mut peer, &handle, 10 + k, u64::from(k + 1) * 1_000_000).await;
        assert!(
            wait_predicted(&peer, 10 + k).await,
            "frame {} after the far-future samples: {:#?}",
            10 + k,
            handle.counters()
        );
    }
    let c = handle.counters();
    assert_eq!(c.bus.telemetry_time_out_of_bounds, 2, "{c:#?}");
    assert!(has_error_event(&peer, ErrorCode::TelemetryTimeOutOfBounds));
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backwards_clock_step_resynchronises_with_an_event() {
    let mut peer = Peer::new().await;
    let (handle, dir) = started(&peer, "time-backwards").await;
    // The spacecraft clock starts an hour ahead, then ground corrects it by one hour.
    let hour_us = 3_600_000_000u64;
    let mut id = 0;
    for k in 1..5u64 {
        step_at(&mut peer, &handle, id, hour_us + k * 1_000_000).await;
        id += 1;
    }
    assert!(
        wait_predicted(&peer, id - 1).await,
        "nominal frame before the step"
    );
    // After the step: frames recover within the resynchronisation count (3 samples per
    // stream) plus one step to bracket a frame.
    let mut first_recovered = None;
    for k in 10..18u64 {
        let before = frames_resolved(&handle);
        step_at(&mut peer, &handle, id, k * 1_000_000).await;
        if next_frame_synced(&handle, before).await && first_recovered.is_none() {
            first_recovered = Some(k);
        }
        id += 1;
    }
    let recovered = first_recovered.unwrap_or_else(|| {
        panic!(
            "no frame accepted after the clock step: {:#?}",
            handle.counters()
        )
    });
    assert!(recovered <= 13, "recovered only at step {recovered}");
    assert!(has_error_event(&peer, ErrorCode::TelemetryClockJump));
    let c = handle.counters();
    assert_eq!(c.bus.telemetry_resyncs, 2, "one per stream: {c:#?}");
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}
