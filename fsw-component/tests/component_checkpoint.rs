//! Periodic checkpoints and resuming from the last one on start, over loopback UDP.

mod component_support;

use component_support::*;
use fsw_component::runtime::{build_learner, start, LearnerKind};
use interfaces::messages::{ErrorCode, EventKind};
use std::time::Duration;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn periodic_checkpoints_and_resume_on_start() {
    let dir = temp_dir("periodic");
    let checkpoint = dir.join("model.bin");
    let mut peer = Peer::new().await;
    let mut config = peer.config(checkpoint.clone());
    config.checkpoint.period_s = 1;
    let handle = start(
        &config,
        build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        None,
    )
    .await
    .unwrap();
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
    let handle = start(
        &config,
        build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        None,
    )
    .await
    .unwrap();
    assert!(
        peer.wait_for(Duration::from_secs(3), |r| r.last_health().is_some_and(
            |h| h.rounds == 3 && h.window_fill == 4 && h.frames_received == 0
        ))
        .await,
        "not resumed: {:?}",
        peer.snapshot(|r| r.last_health())
    );
    assert!(peer.snapshot(|r| r
        .events
        .iter()
        .any(|e| e.kind == EventKind::CheckpointLoaded { rounds: 3 })));
    handle.shutdown().await;
    assert!(std::fs::read(&checkpoint).unwrap() == saved);

    // A damaged checkpoint: start afresh, say so with an event, keep running.
    let mut damaged = saved.clone();
    damaged[12] ^= 0xff;
    std::fs::write(&checkpoint, &damaged).unwrap();
    let peer = Peer::new().await;
    let mut config = peer.config(checkpoint.clone());
    config.checkpoint.resume = true;
    let handle = start(
        &config,
        build_learner(&config, LearnerKind::NearestKeyframe).unwrap(),
        None,
    )
    .await
    .unwrap();
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
