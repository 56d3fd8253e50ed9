//! Supervision of the trainer thread, through the runtime over loopback UDP: a panicking
//! learner is reported, the mode leaves Train while the learner restarts from the newest
//! checkpoint, and training continues; repeated panics leave the component Idle; a hung
//! round is reported by the watchdog; learner failures and non-finite steps are events.

mod component_support;

use component_support::*;
use fsw_component::nearest_learner::NearestKeyframeLearner;
use fsw_component::runtime::{start, ComponentHandle};
use interfaces::messages::{event_detail, AckStatus, CommandKind, ErrorCode, EventKind, Mode};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

async fn start_scripted(
    name: &str,
    round_deadline_ms: u64,
) -> (
    Peer,
    ComponentHandle,
    Arc<Mutex<Script>>,
    std::path::PathBuf,
) {
    let dir = temp_dir(name);
    let peer = Peer::new().await;
    let mut config = peer.config(dir.join("model.bin"));
    config.training.round_deadline_ms = round_deadline_ms;
    let script = Arc::new(Mutex::new(Script::default()));
    let learner = Scripted {
        inner: Box::new(NearestKeyframeLearner::new(config.window_config().unwrap()).unwrap()),
        script: Arc::clone(&script),
    };
    let handle = start(&config, Box::new(learner), None).await.unwrap();
    (peer, handle, script, dir)
}

fn internal(detail: u32) -> EventKind {
    EventKind::Error {
        code: ErrorCode::Internal,
        detail,
    }
}

fn position(r: &Received, kind: EventKind) -> Option<usize> {
    r.events.iter().position(|e| e.kind == kind)
}

async fn wait_rounds(peer: &Peer, at_least: u32) {
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| r
            .last_health()
            .is_some_and(|h| h.rounds >= at_least))
            .await,
        "rounds stayed below {at_least}: {:?}",
        peer.snapshot(Received::last_health)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_round_restarts_the_learner_from_the_checkpoint_and_training_goes_on() {
    let (mut peer, handle, script, dir) = start_scripted("panic", 60_000).await;
    // Rounds after frames 3 and 4; then a checkpoint of rounds 2.
    for k in 0..5 {
        send_step(&mut peer, k, &handle).await;
    }
    wait_rounds(&peer, 2).await;
    peer.command(1, CommandKind::SaveCheckpoint, handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);

    script.lock().unwrap().panicking_rounds = 1;
    send_step(&mut peer, 5, &handle).await;
    let panicked = internal(event_detail::TRAINER_PANICKED);
    let to_predict = EventKind::ModeChanged {
        from: Mode::Train,
        to: Mode::PredictOnly,
    };
    let restored = EventKind::CheckpointLoaded { rounds: 2 };
    let back = EventKind::ModeChanged {
        from: Mode::PredictOnly,
        to: Mode::Train,
    };
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| position(r, back).is_some())
            .await,
        "no return to Train: {:?}",
        peer.snapshot(|r| r.events.clone())
    );
    let order: Vec<Option<usize>> = peer.snapshot(|r| {
        [panicked, to_predict, restored, back]
            .iter()
            .map(|&k| position(r, k))
            .collect()
    });
    assert!(
        order.iter().all(Option::is_some) && order.windows(2).all(|w| w[0] < w[1]),
        "events out of order: {order:?} in {:?}",
        peer.snapshot(|r| r.events.clone())
    );
    assert_eq!(handle.mode(), Mode::Train);
    assert_eq!(handle.worker_snapshot().trainer_restarts, 1);

    // The restarted learner holds the checkpoint's window and trains on new frames.
    for k in 6..9 {
        send_step(&mut peer, k, &handle).await;
    }
    wait_rounds(&peer, 3).await;
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn panics_in_a_row_leave_the_component_idle_until_commanded() {
    let (mut peer, handle, script, dir) = start_scripted("panic-loop", 60_000).await;
    script.lock().unwrap().panicking_rounds = u32::MAX;
    let gave_up = internal(event_detail::TRAINER_GAVE_UP);
    // A frame that arrives while a restart is in progress is only predicted (no round, no
    // panic), so send until the trainer gives up.
    let mut k = 0;
    while !peer
        .wait_for(Duration::from_millis(200), |r| {
            position(r, gave_up).is_some()
        })
        .await
    {
        assert!(k < 12, "{:?}", peer.snapshot(|r| r.events.clone()));
        send_step(&mut peer, k, &handle).await;
        k += 1;
    }
    assert_eq!(handle.mode(), Mode::Idle);
    let panics = peer.snapshot(|r| {
        r.events
            .iter()
            .filter(|e| e.kind == internal(event_detail::TRAINER_PANICKED))
            .count()
    });
    assert_eq!(panics, 3);
    // The operator clears the fault and commands Train: training runs again.
    script.lock().unwrap().panicking_rounds = 0;
    peer.command(1, CommandKind::SetMode(Mode::Train), handle.telemetry_addr)
        .await;
    assert_eq!(peer.wait_ack(1).await.status, AckStatus::Ok);
    for k in k..k + 5 {
        send_step(&mut peer, k, &handle).await;
    }
    wait_rounds(&peer, 1).await;
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hung_round_is_reported_within_two_seconds_of_its_deadline() {
    let deadline = Duration::from_millis(300);
    let (mut peer, handle, script, dir) = start_scripted("watchdog", 300).await;
    script.lock().unwrap().round_sleep = Duration::from_secs(5);
    for k in 0..3 {
        send_step(&mut peer, k, &handle).await;
    }
    // Frame 3 fills the window: its round hangs for 5 s.
    send_step(&mut peer, 3, &handle).await;
    let sent = Instant::now();
    let missed = internal(event_detail::ROUND_DEADLINE_MISSED);
    assert!(
        peer.wait_for(deadline + Duration::from_secs(2), |r| position(r, missed)
            .is_some())
            .await,
        "no watchdog event: {:?}",
        peer.snapshot(|r| r.events.clone())
    );
    assert!(
        sent.elapsed() < Duration::from_secs(5),
        "reported only after the round"
    );
    assert!(handle.worker_snapshot().busy, "the round still runs");
    // Once per job: nothing more until the round ends.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let count = peer.snapshot(|r| r.events.iter().filter(|e| e.kind == missed).count());
    assert_eq!(count, 1);
    assert_eq!(handle.worker_snapshot().deadline_misses, 1);
    script.lock().unwrap().round_sleep = Duration::ZERO;
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn learner_failures_and_non_finite_steps_are_events() {
    let (mut peer, handle, script, dir) = start_scripted("learner-errors", 60_000).await;
    {
        let mut s = script.lock().unwrap();
        s.refused_offers = 1;
        s.failing_rounds = 1;
        s.skipped_steps = 2;
    }
    for k in 0..6 {
        send_step(&mut peer, k, &handle).await;
    }
    let expected = [
        internal(event_detail::FRAME_REFUSED_BY_MODEL),
        internal(event_detail::ROUND_FAILED),
        EventKind::Error {
            code: ErrorCode::TrainingNonFinite,
            detail: 2,
        },
    ];
    assert!(
        peer.wait_for(Duration::from_secs(5), |r| expected
            .iter()
            .all(|&k| position(r, k).is_some()))
            .await,
        "{:?}",
        peer.snapshot(|r| r.events.clone())
    );
    assert_eq!(handle.mode(), Mode::Train, "errors are not faults");
    handle.shutdown().await;
    std::fs::remove_dir_all(&dir).unwrap();
}
