//! The component over real UDP sockets on 127.0.0.1: scenario, predictions, health, commands.

mod component_support;

use component_support::*;
use fsw_component::runtime::{build_learner, start, LearnerKind};
use gs_online::imagemetrics;
use interfaces::messages::{
    AckStatus, CommandKind, ErrorCode, EventKind, Mode, PredictionSource, RenderRequest,
};
use std::sync::{Arc, Mutex};
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(5);

fn prediction_for(r: &Received, frame_id: u32) -> Option<Prediction> {
    r.predictions
        .iter()
        .find(|p| p.source == PredictionSource::ObservedFrame { frame_id })
        .cloned()
}

/// Command bytes written by hand (postcard: varint sequence, varint opcode, raw f32 LE), so
/// that invalid arguments can be sent at all.
fn render_bytes(sequence: u8, q: [f32; 4], t: [f32; 3], sun: [f32; 3]) -> Vec<u8> {
    let mut out = vec![sequence, 6];
    for v in q.iter().chain(&t).chain(&sun) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_scenario_predictions_health_and_commands() {
    let dir = temp_dir("live");
    let mut peer = Peer::new().await;
    let config = peer.config(dir.join("checkpoint.bin"));
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    let telemetry = handle.telemetry_addr;

    for k in 0..8 {
        send_step(&mut peer, k, &handle).await;
        if k == 0 {
            // Nothing learned yet: the first frame has no prediction.
            tokio::time::sleep(Duration::from_millis(200)).await;
        } else {
            assert!(
                peer.wait_for(WAIT, |r| prediction_for(r, k).is_some())
                    .await,
                "no prediction for frame {k}: {:?} {:?} {:?}",
                peer.snapshot(Received::last_health),
                peer.snapshot(|r| r.events.clone()),
                handle.counters()
            );
        }
    }
    for k in 1..8 {
        let p = peer.snapshot(|r| prediction_for(r, k)).unwrap();
        assert_eq!(p.header.time_us, frame_time_us(k));
        // Rendered before training on frame k, at its pose: the nearest keyframe view is
        // frame k-1 (20 degrees away), so the baseline predicts exactly that image.
        assert_eq!(p.pixels, frame_pixels(k - 1), "frame {k}");
        let expected_psnr =
            imagemetrics::psnr_db(&frame_pixels(k - 1), &frame_pixels(k), 16, 16, 3).unwrap();
        let expected_ssim =
            imagemetrics::ssim(&frame_pixels(k - 1), &frame_pixels(k), 16, 16, 3).unwrap();
        assert_eq!(p.psnr_db, Some(expected_psnr));
        assert_eq!(p.ssim, Some(expected_ssim));
        let q = camera_from_target_at(frame_time_us(k));
        let got = glam::DQuat::from_xyzw(
            f64::from(p.q[1]),
            f64::from(p.q[2]),
            f64::from(p.q[3]),
            f64::from(p.q[0]),
        );
        assert!(
            got.dot(q).abs() > 1.0 - 1e-6,
            "pose of frame {k}: {got:?} vs {q:?}"
        );
        assert_eq!(p.t, [0.0, 0.0, 10.0]);
    }

    // Health at 1 Hz with the scenario's figures.
    assert!(
        peer.wait_for(Duration::from_secs(4), |r| r.health.len() >= 3)
            .await
    );
    let health = peer.snapshot(|r| r.last_health().unwrap());
    assert_eq!(health.mode, Mode::Train);
    assert_eq!(health.frames_received, 8);
    assert_eq!(
        health.frames_used, 8,
        "every frame moved the view by 20 degrees"
    );
    assert_eq!(health.frames_dropped, 0);
    assert_eq!((health.window_fill, health.window_capacity), (4, 4));
    assert_eq!(
        health.rounds, 5,
        "a round per composition change once full (frames 3..7)"
    );
    assert!(health.last_loss.is_some() && health.last_prediction_psnr_db.is_some());
    assert!(health.memory_bytes > 1 << 20);
    assert_eq!((health.decode_errors, health.crc_errors), (0, 0));

    // Commands and acknowledgements.
    let addr = telemetry;
    peer.command(1, CommandKind::Noop, addr).await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);
    peer.send_command_bytes(&[2, 9], addr).await;
    let ack = peer.wait_ack(2).await;
    assert_eq!(
        (ack.status, ack.opcode),
        (AckStatus::InvalidOpcode, Some(9))
    );
    peer.send_command_bytes(&[0x83], addr).await; // unterminated varint
    assert!(
        peer.wait_for(WAIT, |r| r
            .acks
            .iter()
            .any(|a| a.status == AckStatus::FormatError && a.sequence.is_none()))
            .await
    );
    let bad = render_bytes(4, [1.0, 0.5, 0.0, 0.0], [0.0, 0.0, 10.0], [0.0, 0.0, 1.0]);
    peer.send_command_bytes(&bad, addr).await;
    assert_eq!(peer.wait_ack(4).await.status, AckStatus::ValidationError);
    let nan = render_bytes(
        5,
        [1.0, 0.0, 0.0, 0.0],
        [f32::NAN, 0.0, 10.0],
        [0.0, 0.0, 1.0],
    );
    peer.send_command_bytes(&nan, addr).await;
    assert_eq!(peer.wait_ack(5).await.status, AckStatus::ValidationError);

    let q = camera_from_target_at(frame_time_us(3));
    let render = RenderRequest {
        q_camera_from_target: [q.w as f32, q.x as f32, q.y as f32, q.z as f32],
        t_camera_from_target_m: [0.0, 0.0, 10.0],
        sun_target: [0.0, 0.0, 1.0],
    };
    peer.command(6, CommandKind::Render(render), addr).await;
    assert_eq!(peer.wait_ack(6).await.status, AckStatus::Ok);
    assert!(
        peer.wait_for(WAIT, |r| r
            .predictions
            .iter()
            .any(|p| p.source == PredictionSource::Command { sequence: 6 }))
            .await
    );
    let rendered = peer.snapshot(|r| {
        r.predictions
            .iter()
            .find(|p| p.source == PredictionSource::Command { sequence: 6 })
            .cloned()
            .unwrap()
    });
    assert_eq!(rendered.psnr_db, None, "no observed frame to compare with");
    assert_eq!(
        rendered.pixels.len(),
        16 * 16 * 3,
        "the camera's size and format"
    );
    // The baseline renders the stored keyframe nearest to the requested view.
    assert!((0..8).any(|j| rendered.pixels == frame_pixels(j)));

    peer.command(7, CommandKind::SetMode(Mode::PredictOnly), addr)
        .await;
    assert_eq!(peer.wait_ack(7).await.status, AckStatus::Ok);
    assert!(
        peer.wait_for(WAIT, |r| r.events.iter().any(|e| e.kind
            == EventKind::ModeChanged {
                from: Mode::Train,
                to: Mode::PredictOnly
            }))
        .await
    );
    send_step(&mut peer, 8, &handle).await;
    assert!(
        peer.wait_for(WAIT, |r| prediction_for(r, 8).is_some())
            .await
    );
    peer.command(8, CommandKind::SetMode(Mode::Idle), addr)
        .await;
    assert_eq!(peer.wait_ack(8).await.status, AckStatus::Ok);
    send_step(&mut peer, 9, &handle).await;
    assert!(
        peer.wait_for(WAIT, |r| r
            .last_health()
            .is_some_and(|h| h.frames_received == 10 && h.mode == Mode::Idle))
            .await
    );
    let health = peer.snapshot(|r| r.last_health().unwrap());
    assert_eq!(
        health.frames_used, 8,
        "predict-only and idle frames do not train"
    );
    assert_eq!(health.frames_dropped, 1, "the frame received while idle");
    assert!(peer.snapshot(|r| prediction_for(r, 9).is_none()));
    peer.command(9, CommandKind::SetMode(Mode::Train), addr)
        .await;
    assert_eq!(peer.wait_ack(9).await.status, AckStatus::Ok);

    peer.command(10, CommandKind::SaveCheckpoint, addr).await;
    assert_eq!(peer.wait_ack(10).await.status, AckStatus::Ok);
    let saved = std::fs::read(dir.join("checkpoint.bin")).unwrap();
    assert!(peer.snapshot(|r| r
        .events
        .iter()
        .any(|e| e.kind == EventKind::CheckpointSaved { rounds: 5 })));

    // Destructive commands need an ARM naming them first.
    peer.command(11, CommandKind::ResetModel, addr).await;
    let refused = peer.wait_ack(11).await;
    assert_eq!(refused.status, AckStatus::ExecutionError);
    assert_eq!(refused.detail, ErrorCode::CommandNotArmed.index() as u16);
    peer.command(111, CommandKind::Arm(CommandKind::RESET_MODEL), addr)
        .await;
    assert_eq!(peer.wait_ack(111).await.status, AckStatus::Ok);
    peer.command(112, CommandKind::ResetModel, addr).await;
    assert_eq!(peer.wait_ack(112).await.status, AckStatus::Ok);
    peer.command(12, CommandKind::ResetCounters, addr).await;
    assert_eq!(peer.wait_ack(12).await.status, AckStatus::Ok);
    assert!(
        peer.wait_for(WAIT, |r| r
            .last_health()
            .is_some_and(|h| h.frames_received == 0
                && h.rounds == 0
                && h.window_fill == 0))
            .await,
        "counters and model reset"
    );
    peer.command(113, CommandKind::Arm(CommandKind::LOAD_CHECKPOINT), addr)
        .await;
    assert_eq!(peer.wait_ack(113).await.status, AckStatus::Ok);
    peer.command(13, CommandKind::LoadCheckpoint, addr).await;
    assert_eq!(peer.wait_ack(13).await.status, AckStatus::Ok);
    assert!(
        peer.wait_for(WAIT, |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 5 && h.window_fill == 4))
            .await,
        "model restored from the checkpoint"
    );
    let health = peer.snapshot(|r| r.last_health().unwrap());
    assert_eq!(health.commands_rejected, 0, "counted since the reset");
    assert_eq!(
        health.commands_accepted, 3,
        "RESET_COUNTERS itself, ARM and LOAD_CHECKPOINT"
    );
    peer.command(14, CommandKind::SaveCheckpoint, addr).await;
    assert_eq!(peer.wait_ack(14).await.status, AckStatus::Ok);
    assert_eq!(std::fs::read(dir.join("checkpoint.bin")).unwrap(), saved);
    assert_eq!(peer.snapshot(|r| r.undecodable), 0);
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_keeps_1_hz_and_commands_are_acknowledged_during_a_long_round() {
    let dir = temp_dir("slow");
    let mut peer = Peer::new().await;
    let config = peer.config(dir.join("checkpoint.bin"));
    let learner = Scripted {
        inner: build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        script: Arc::new(Mutex::new(Script {
            round_sleep: Duration::from_millis(3500),
            ..Script::default()
        })),
    };
    let handle = start(&config, Box::new(learner), None).await.unwrap();
    for k in 0..4 {
        send_step(&mut peer, k, &handle).await;
    }
    // Frame 3 fills the window: the round starts; let it get going.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = peer.snapshot(|r| r.health.len());
    peer.command(1, CommandKind::Noop, handle.telemetry_addr)
        .await;
    let ack = peer.wait_ack(1).await;
    assert_eq!(ack.status, AckStatus::Ok);
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r.health.len() >= before + 3)
            .await,
        "health stalled during the round"
    );
    let (during, times) = peer.snapshot(|r| {
        let h: Vec<_> = r.health[before..].iter().map(|h| h.1).collect();
        let t: Vec<_> = r.health[before..].iter().map(|h| h.0).collect();
        (h, t)
    });
    assert!(
        during.iter().take(2).all(|h| h.rounds == 0),
        "round still running: {during:?}"
    );
    for pair in times.windows(2) {
        let gap = pair[1] - pair[0];
        assert!(
            gap > Duration::from_millis(700) && gap < Duration::from_millis(1300),
            "health gap {gap:?}"
        );
    }
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 1))
            .await
    );
    let h = peer.snapshot(|r| r.last_health().unwrap());
    assert!(h.last_round_duration_ms.unwrap() >= 3500);
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}
