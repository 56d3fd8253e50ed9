//! Periodic checkpoints and resuming from the last one on start, over loopback UDP.

mod component_support;

use component_support::*;
use fsw_component::runtime::LearnerKind;
use interfaces::messages::{event_detail, AckStatus, CommandKind, ErrorCode, EventKind};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn periodic_checkpoints_and_resume_on_start() {
    let dir = temp_dir("periodic");
    let checkpoint = dir.join("model.bin");
    let mut peer = Peer::new().await;
    let mut config = peer.config(checkpoint.clone());
    config.checkpoint.period_s = 1;
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    for k in 0..6 {
        send_step(&mut peer, k, &handle).await;
    }
    // Rounds after frames 3, 4 and 5; then wait for a periodic save that has all three.
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .events
            .iter()
            .any(|e| e.kind == EventKind::CheckpointSaved { rounds: 3 }))
            .await,
        "no periodic checkpoint"
    );
    assert!(
        !dir.join("model.bin.tmp").exists(),
        "temporary file left behind"
    );
    let saved = std::fs::read(&checkpoint).unwrap();
    handle.shutdown().await;

    // Restart with resume: the model comes back (window, rounds) before any frame arrives.
    let peer = Peer::new().await;
    let mut config = peer.config(checkpoint.clone());
    config.checkpoint.resume = true;
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r.last_health().is_some_and(
            |h| h.rounds == 3 && h.window_fill == 4 && h.frames_received == 0
        ))
        .await,
        "not resumed: {:?}",
        peer.snapshot(Received::last_health)
    );
    assert!(peer.snapshot(|r| r
        .events
        .iter()
        .any(|e| e.kind == EventKind::CheckpointLoaded { rounds: 3 })));
    handle.shutdown().await;
    assert!(std::fs::read(&checkpoint).unwrap() == saved);

    // A damaged checkpoint and no previous slot: start afresh, say so, keep running.
    let _ = std::fs::remove_file(dir.join("model.bin.prev"));
    let mut damaged = saved.clone();
    damaged[12] ^= 0xff;
    std::fs::write(&checkpoint, &damaged).unwrap();
    let peer = Peer::new().await;
    let mut config = peer.config(checkpoint.clone());
    config.checkpoint.resume = true;
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r.events.iter().any(|e| e.kind
            == EventKind::Error {
                code: ErrorCode::CheckpointLoadFailed,
                detail: 0
            }))
        .await
    );
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 0 && h.window_fill == 0))
            .await
    );
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Starts the nearest-keyframe component on `checkpoint` with `resume` and `period_s`.
async fn start_on(
    checkpoint: &std::path::Path,
    resume: bool,
    period_s: u64,
) -> (Peer, fsw_component::runtime::ComponentHandle) {
    let peer = Peer::new().await;
    let mut config = peer.config(checkpoint.to_path_buf());
    config.checkpoint.resume = resume;
    config.checkpoint.period_s = period_s;
    let handle = start_component(&config, LearnerKind::NearestKeyframe, None).await;
    (peer, handle)
}

async fn command_status(
    peer: &mut Peer,
    sequence: u32,
    kind: CommandKind,
    handle: &fsw_component::runtime::ComponentHandle,
) -> AckStatus {
    peer.command(sequence, kind, handle.telemetry_addr).await;
    peer.wait_ack(sequence).await.status
}

fn has_event(r: &Received, kind: EventKind) -> bool {
    r.events.iter().any(|e| e.kind == kind)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_without_resume_never_saves_an_untrained_model_over_a_trained_one() {
    let dir = temp_dir("untrained-over-trained");
    let checkpoint = dir.join("model.bin");
    let previous = dir.join("model.bin.prev");
    let (mut peer, handle) = start_on(&checkpoint, false, 0).await;
    for k in 0..6 {
        send_step(&mut peer, k, &handle).await;
    }
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 3))
            .await
    );
    let save = CommandKind::SaveCheckpoint;
    assert_eq!(
        command_status(&mut peer, 1, save, &handle).await,
        AckStatus::Ok
    );
    let trained = std::fs::read(&checkpoint).unwrap();
    handle.shutdown().await;

    // A restart that does not resume: the periodic save must not replace rounds 3 by 0.
    let (mut peer, handle) = start_on(&checkpoint, false, 1).await;
    send_step(&mut peer, 0, &handle).await;
    let refused = EventKind::Error {
        code: ErrorCode::CheckpointSaveFailed,
        detail: event_detail::SAVE_REFUSED_FEWER_ROUNDS,
    };
    assert!(
        peer.wait_for(Duration::from_secs(4), |r| has_event(r, refused))
            .await,
        "no refusal: {:?}",
        peer.snapshot(|r| r.events.clone())
    );
    assert!(
        !peer.snapshot(|r| r
            .events
            .iter()
            .any(|e| matches!(e.kind, EventKind::CheckpointSaved { .. }))),
        "an untrained model was saved"
    );
    assert_eq!(
        command_status(&mut peer, 2, save, &handle).await,
        AckStatus::ExecutionError,
        "SAVE_CHECKPOINT is refused too"
    );
    assert_eq!(std::fs::read(&checkpoint).unwrap(), trained);
    assert!(handle.worker_snapshot().checkpoints_refused >= 2);

    // RESET_MODEL is the explicit command that discards the trained model: then a save
    // goes through, and the trained model is still the previous slot.
    let arm = CommandKind::Arm(CommandKind::RESET_MODEL);
    assert_eq!(
        command_status(&mut peer, 30, arm, &handle).await,
        AckStatus::Ok
    );
    let reset = CommandKind::ResetModel;
    assert_eq!(
        command_status(&mut peer, 3, reset, &handle).await,
        AckStatus::Ok
    );
    assert_eq!(
        command_status(&mut peer, 4, save, &handle).await,
        AckStatus::Ok
    );
    assert_eq!(std::fs::read(&previous).unwrap(), trained);
    assert_ne!(std::fs::read(&checkpoint).unwrap(), trained);
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_newest_checkpoint_falls_back_to_the_previous_one() {
    let dir = temp_dir("fallback");
    let checkpoint = dir.join("model.bin");
    let previous = dir.join("model.bin.prev");
    let temporary = dir.join("model.bin.tmp");
    let (mut peer, handle) = start_on(&checkpoint, false, 0).await;
    // Rounds after frames 3, 4 and 5: save at rounds 2, then at rounds 3.
    for k in 0..5 {
        send_step(&mut peer, k, &handle).await;
    }
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 2))
            .await
    );
    let save = CommandKind::SaveCheckpoint;
    assert_eq!(
        command_status(&mut peer, 1, save, &handle).await,
        AckStatus::Ok
    );
    send_step(&mut peer, 5, &handle).await;
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 3))
            .await
    );
    assert_eq!(
        command_status(&mut peer, 2, save, &handle).await,
        AckStatus::Ok
    );
    handle.shutdown().await;
    assert!(previous.exists(), "no previous slot");

    // The newest slot damaged on disk and a half-written temporary left by a crash.
    let mut newest = std::fs::read(&checkpoint).unwrap();
    newest[12] ^= 0xff;
    std::fs::write(&checkpoint, &newest).unwrap();
    std::fs::write(&temporary, b"half a checkpoint").unwrap();
    let (peer, handle) = start_on(&checkpoint, true, 0).await;
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| has_event(
            r,
            EventKind::CheckpointLoaded { rounds: 2 }
        ) && has_event(
            r,
            EventKind::Error {
                code: ErrorCode::CheckpointLoadFailed,
                detail: event_detail::LOAD_NEWEST_FAILED_PREVIOUS_USED,
            }
        ))
        .await,
        "{:?}",
        peer.snapshot(|r| r.events.clone())
    );
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 2 && h.window_fill == 4))
            .await
    );
    handle.shutdown().await;
    assert!(!temporary.exists(), "the stale temporary is removed");

    // The previous slot truncated too: start afresh and say so.
    let bytes = std::fs::read(&previous).unwrap();
    std::fs::write(&previous, &bytes[..bytes.len() / 2]).unwrap();
    let (peer, handle) = start_on(&checkpoint, true, 0).await;
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| has_event(
            r,
            EventKind::Error {
                code: ErrorCode::CheckpointLoadFailed,
                detail: event_detail::LOAD_NOTHING_USABLE,
            }
        ))
        .await
    );
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r
            .last_health()
            .is_some_and(|h| h.rounds == 0))
            .await
    );
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}
