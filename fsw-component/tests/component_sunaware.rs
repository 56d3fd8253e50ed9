//! The component with the real Sun-aware online trainer (gs-core) over loopback UDP: a
//! prediction for every accepted frame (the initial Gaussians render from the start), rounds
//! once the window is full, health during rounds, checkpoints that reload to the same bytes,
//! and a replay of the recording that reproduces the live model byte for byte.

mod component_support;

use component_support::*;
use fsw_component::runtime::{build_learner, run_replay, LearnerKind, ReplaySpeed};
use interfaces::messages::{AckStatus, CommandKind, PredictionSource};
use std::time::{Duration, Instant};

const STEPS: u32 = 5;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sun_aware_trainer_live_checkpoint_and_replay() {
    let dir = temp_dir("sunaware");
    let mut peer = Peer::new().await;
    let checkpoint = dir.join("live.bin");
    let config = peer.config(checkpoint.clone());
    let record = dir.join("record");
    let handle = start_component(&config, LearnerKind::SunAware, Some(record.clone())).await;
    for k in 0..STEPS {
        send_step(&mut peer, k, &handle).await;
        let deadline = Instant::now() + Duration::from_secs(60);
        while handle.worker_snapshot().frames_processed < u64::from(k + 1) {
            assert!(Instant::now() < deadline, "frame {k} not processed");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    for k in 0..STEPS {
        let source = PredictionSource::ObservedFrame { frame_id: k };
        let p = peer
            .snapshot(|r| r.predictions.iter().find(|p| p.source == source).cloned())
            .unwrap_or_else(|| panic!("no prediction for frame {k}"));
        assert_eq!(p.pixels.len(), 16 * 16 * 3);
        assert!(p.psnr_db.is_some_and(f32::is_finite));
        assert!(p.ssim.is_some_and(|s| (-1.0..=1.0).contains(&s)));
    }
    let snapshot = handle.worker_snapshot();
    assert_eq!(snapshot.frames_used, u64::from(STEPS));
    assert_eq!(
        snapshot.learner.rounds, 2,
        "rounds after frames 3 and 4 (W = 4)"
    );
    assert!(snapshot.learner.gaussians > 0);
    let round = snapshot.last_round.unwrap();
    assert!(round.loss.is_finite() && round.loss >= 0.0);

    peer.command(1, CommandKind::SaveCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);
    let live = std::fs::read(&checkpoint).unwrap();
    peer.command(
        20,
        CommandKind::Arm(CommandKind::RESET_MODEL),
        handle.telemetry_addr,
    )
    .await;
    assert_eq!(peer.wait_ack(20).await.status, AckStatus::Ok);
    peer.command(2, CommandKind::ResetModel, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(2).await.status, AckStatus::Ok);
    assert_eq!(handle.worker_snapshot().learner.rounds, 0);
    peer.command(
        30,
        CommandKind::Arm(CommandKind::LOAD_CHECKPOINT),
        handle.telemetry_addr,
    )
    .await;
    assert_eq!(peer.wait_ack(30).await.status, AckStatus::Ok);
    peer.command(3, CommandKind::LoadCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(3).await.status, AckStatus::Ok);
    assert_eq!(handle.worker_snapshot().learner.rounds, 2);
    std::fs::remove_file(&checkpoint).unwrap();
    peer.command(4, CommandKind::SaveCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(4).await.status, AckStatus::Ok);
    assert!(
        std::fs::read(&checkpoint).unwrap() == live,
        "load + save changed the bytes"
    );
    handle.shutdown().await;

    // The recording (with SAVE, RESET, LOAD, SAVE) replays to the same checkpoint bytes.
    let mut replay_config = config.clone();
    replay_config.checkpoint.path = dir.join("replayed.bin");
    let summary = run_replay(
        &replay_config,
        build_learner(&replay_config, LearnerKind::SunAware).unwrap(),
        &[record.join("udp.rec"), record.join("can.log")],
        ReplaySpeed::AsFastAsPossible,
    )
    .await
    .unwrap();
    assert_eq!(summary.frames_used, u64::from(STEPS));
    assert!(
        std::fs::read(dir.join("replayed.bin")).unwrap() == live,
        "replay differs"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
