//! Replay: the engine driven from recorded datagrams and CAN frames with their time stamps,
//! as fast as the trainer takes them or at a scaled real-time pace. It waits for room in the
//! trainer queue instead of dropping, so a replay processes every frame and reproduces a live
//! run's rounds.

use crate::cmdauth::UdpIngress;
use crate::config::ComponentConfig;
use crate::inbound::CoreCounters;
use crate::learner::Learner;
use crate::replay::{self, ReplayInput};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use super::engine::{lock, Engine};
use super::RuntimeError;

/// How fast a replay runs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ReplaySpeed {
    /// As fast as the trainer takes the frames.
    AsFastAsPossible,
    /// Original timing scaled by this factor (1.0 = real time, 2.0 = twice as fast).
    Scaled(f64),
}

/// What a replay did.
#[derive(Clone, Copy, Debug)]
pub struct ReplaySummary {
    pub load: replay::ReplayLoadStats,
    pub counters: CoreCounters,
    pub rounds: u32,
    pub frames_used: u64,
    pub predictions_sent: u64,
}

/// Replays logs through the same decoders, publishes outputs like a live run, and returns
/// once every record is processed and the trainer is idle.
pub async fn run_replay(
    config: &ComponentConfig,
    learner: Box<dyn Learner>,
    logs: &[PathBuf],
    speed: ReplaySpeed,
) -> Result<ReplaySummary, RuntimeError> {
    let (records, load) = replay::load(logs).map_err(RuntimeError::Replay)?;
    let (mut engine, resume_events) = Engine::new(config, learner, None).await?;
    for event in resume_events {
        engine.send_status(&event).await;
    }
    let replay_started = Instant::now();
    let first_us = records.first().map_or(0, |r| r.time_us);
    let mut last_health = Instant::now();
    let mut last_us = first_us;
    for record in &records {
        if let ReplaySpeed::Scaled(factor) = speed {
            let offset_s = (record.time_us - first_us) as f64 / 1e6 / factor;
            let due = Duration::from_secs_f64(offset_s.max(0.0));
            if let Some(wait) = due.checked_sub(replay_started.elapsed()) {
                tokio::time::sleep(wait).await;
            }
        }
        while !engine.worker.shared.has_room() {
            engine.flush_outputs().await;
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
        {
            let mut core = lock(&engine.core);
            core.tick(record.time_us);
            match &record.input {
                ReplayInput::Datagram(bytes) => {
                    core.handle_datagram(bytes, UdpIngress::Replayed, record.time_us);
                }
                ReplayInput::CanFrame { extended, id, data } => {
                    core.handle_can_frame(*extended, *id, data, record.time_us);
                }
            }
        }
        last_us = record.time_us;
        engine.flush_outputs().await;
        if last_health.elapsed() >= Duration::from_secs(1) {
            last_health = Instant::now();
            engine.publish_health().await;
        }
    }
    // Frames still waiting for telemetry time out as they would have live.
    lock(&engine.core).tick(last_us.saturating_add(config.sync.max_wait_ms.saturating_mul(1000)));
    while !engine.worker.shared.is_idle() {
        engine.flush_outputs().await;
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    engine.flush_outputs().await;
    engine.publish_health().await;
    let snapshot = engine.worker.shared.snapshot();
    let counters = lock(&engine.core).counters();
    let predictions_sent = engine.predictions_sent;
    let Engine { worker, .. } = engine;
    let _ = tokio::task::spawn_blocking(move || worker.finish()).await;
    Ok(ReplaySummary {
        load,
        counters,
        rounds: snapshot.learner.rounds,
        frames_used: snapshot.frames_used,
        predictions_sent,
    })
}
