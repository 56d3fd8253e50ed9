//! The component's async shell: sockets, the bus task, health at 1 Hz, replay.
//!
//! One tokio task owns the [`BusCore`] and multiplexes the UDP sockets, the CAN socket, the
//! 1 Hz health timer, a 50 ms housekeeping timer and the trainer thread's output signal.
//! The core does no I/O and never waits on the trainer, so health keeps its cadence during a
//! training round. Outputs: predictions to `udp.predictions_to` and, on CAN FD when they
//! fit `[can] prediction_max_bytes`, on `[cyphal.subjects] rendered_prediction`; acknowledgements,
//! health and events to `udp.health_to` and, when CAN is up, as Cyphal transfers on the bus.
//! Replay drives the same core from logs (no listening sockets); it waits for room in the
//! trainer queues instead of dropping, so a replay processes every frame.
//!
//! Files: this one (errors, the learner choice, start-up and the live bus task), `engine`
//! (the state live and replay share: core, worker, framers, node, and how outputs leave),
//! `replay_run` (driving the engine from logs).

use crate::cmdauth::UdpIngress;
use crate::config::ComponentConfig;
use crate::inbound::{BusCore, CoreCounters};
use crate::learner::Learner;
use crate::nearest_learner::NearestKeyframeLearner;
use crate::recorder::Recorder;
use crate::replay::{self};
use crate::sunaware_learner::{SunAwareLearner, SunAwareSettings};
use crate::transport::{CanTransport, CanTransportConfig, TransportError, UdpTransport};
use interfaces::messages::Mode;
use std::fmt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::watch;

mod engine;
mod replay_run;

use engine::{lock, Engine};
pub use replay_run::{run_replay, ReplaySpeed, ReplaySummary};

#[derive(Debug)]
pub enum RuntimeError {
    Config(String),
    Transport(TransportError),
    Can(TransportError),
    Io {
        what: String,
        source: std::io::Error,
    },
    Replay(replay::ReplayError),
}

impl fmt::Display for RuntimeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Config(why) => write!(f, "configuration: {why}"),
            Self::Transport(e) => write!(f, "{e}"),
            Self::Can(e) => write!(
                f,
                "CAN is enabled in the configuration but cannot be used: {e} \
                 (set [can] enabled = false to run on UDP only)"
            ),
            Self::Io { what, source } => write!(f, "{what}: {source}"),
            Self::Replay(e) => write!(f, "replay: {e}"),
        }
    }
}

impl std::error::Error for RuntimeError {}

/// Which model the trainer thread runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LearnerKind {
    /// The Sun-aware online trainer (gs-core): what flies.
    SunAware,
    /// The nearest-keyframe baseline: cheap and exact, for bus tests.
    NearestKeyframe,
}

impl std::str::FromStr for LearnerKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "sunaware" => Ok(Self::SunAware),
            "nearest" => Ok(Self::NearestKeyframe),
            other => Err(format!("learner {other:?}: want sunaware or nearest")),
        }
    }
}

/// Builds the model for `config`.
pub fn build_learner(
    config: &ComponentConfig,
    kind: LearnerKind,
) -> Result<Box<dyn Learner>, RuntimeError> {
    let window = config
        .window_config()
        .map_err(|e| RuntimeError::Config(e.to_string()))?;
    Ok(match kind {
        LearnerKind::NearestKeyframe => Box::new(
            NearestKeyframeLearner::new(window).map_err(|e| RuntimeError::Config(e.to_string()))?,
        ),
        LearnerKind::SunAware => {
            let mut settings = SunAwareSettings::with_window(window);
            // Window, passes, replay memory and the model (its keys, light camera, rates).
            settings.online = config
                .online_config()
                .map_err(|e| RuntimeError::Config(e.to_string()))?;
            // A missing feature or adapter stops the start here (never a CPU fallback).
            let kind = config
                .backend()
                .map_err(|e| RuntimeError::Config(e.to_string()))?;
            settings.backend = kind
                .open(
                    &crate::engines::device_engines(),
                    config.training.gpu_deterministic,
                )
                .map_err(|e| RuntimeError::Config(format!("training.backend: {e}")))?;
            settings.model = config.model.clone();
            settings.on_config_mismatch = config.checkpoint.on_config_mismatch;
            Box::new(SunAwareLearner::new(settings).map_err(RuntimeError::Config)?)
        }
    })
}

/// Asks for `bytes` of kernel receive buffer. Linux grants at most net.core.rmem_max
/// without CAP_NET_ADMIN: a smaller grant is reported, not an error, because the component
/// still works (bursts beyond the buffer are counted as kernel drops in health).
fn grow_receive_buffer(socket: &UdpTransport, bytes: usize) -> Result<(), RuntimeError> {
    if bytes == 0 {
        return Ok(());
    }
    socket
        .set_receive_buffer_bytes(bytes)
        .map_err(RuntimeError::Transport)?;
    // Linux reports twice the usable size it granted (the other half is bookkeeping).
    let granted = socket
        .receive_buffer_bytes()
        .map_err(RuntimeError::Transport)?
        / 2;
    if granted < bytes {
        eprintln!(
            "fsw-component: UDP {} receive buffer {granted} bytes, {bytes} asked \
             (raise net.core.rmem_max for larger camera bursts)",
            socket.local_addr()
        );
    }
    Ok(())
}

/// A running component (live mode).
pub struct ComponentHandle {
    pub frames_addr: SocketAddr,
    pub telemetry_addr: SocketAddr,
    core: Arc<Mutex<BusCore>>,
    worker: Arc<crate::worker::WorkerShared>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

impl ComponentHandle {
    pub fn counters(&self) -> CoreCounters {
        lock(&self.core).counters()
    }

    pub fn mode(&self) -> Mode {
        lock(&self.core).mode()
    }

    /// The trainer thread's figures (frames processed and used, predictions, rounds).
    pub fn worker_snapshot(&self) -> crate::worker::WorkerSnapshot {
        self.worker.snapshot()
    }

    /// Queue depths and drop counters.
    pub fn queue_depths(&self) -> crate::worker::QueueDepths {
        self.worker.depths()
    }

    /// Stops receiving, lets the trainer finish its queue, and returns when all is closed.
    pub async fn shutdown(self) {
        let _ = self.stop.send(true);
        let _ = self.task.await;
    }
}

/// Opens the CAN transport when the configuration enables it.
pub(crate) fn open_can(config: &ComponentConfig) -> Result<Option<CanTransport>, RuntimeError> {
    if !config.can.enabled {
        return Ok(None);
    }
    CanTransport::open(&CanTransportConfig {
        interface: config.can.interface.clone(),
        fd: config.can.fd,
    })
    .map(Some)
    .map_err(RuntimeError::Can)
}

/// Starts the component: binds the sockets, opens CAN if enabled, spawns the bus task.
pub async fn start(
    config: &ComponentConfig,
    learner: Box<dyn Learner>,
    record: Option<PathBuf>,
) -> Result<ComponentHandle, RuntimeError> {
    if !config.udp.enabled && !config.can.enabled {
        return Err(RuntimeError::Config(
            "both udp.enabled and can.enabled are false: nothing to listen on".into(),
        ));
    }
    let can = open_can(config)?;
    let bind = |port| SocketAddr::new(config.udp.bind_ip, port);
    let (frames, telemetry) = if config.udp.enabled {
        (
            Some(
                UdpTransport::bind(bind(config.udp.frames_port))
                    .await
                    .map_err(RuntimeError::Transport)?,
            ),
            Some(
                UdpTransport::bind(bind(config.udp.telemetry_port))
                    .await
                    .map_err(RuntimeError::Transport)?,
            ),
        )
    } else {
        (None, None)
    };
    for socket in frames.iter().chain(telemetry.iter()) {
        grow_receive_buffer(socket, config.udp.receive_buffer_bytes)?;
    }
    let mut recorder = match &record {
        Some(dir) => Some(
            Recorder::create(dir, &config.can.interface).map_err(|source| RuntimeError::Io {
                what: format!("create recording in {}", dir.display()),
                source,
            })?,
        ),
        None => None,
    };
    let (mut engine, resume_events) = Engine::new(config, learner, can).await?;
    for event in resume_events {
        engine.send_status(&event).await;
    }
    let unbound = SocketAddr::new(config.udp.bind_ip, 0);
    let frames_addr = frames.as_ref().map_or(unbound, UdpTransport::local_addr);
    let telemetry_addr = telemetry.as_ref().map_or(unbound, UdpTransport::local_addr);
    let core = Arc::clone(&engine.core);
    let worker = Arc::clone(&engine.worker.shared);
    let (stop, mut stopped) = watch::channel(false);
    let task = tokio::spawn(async move {
        let mut health = tokio::time::interval(Duration::from_secs(1));
        health.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut housekeeping = tokio::time::interval(Duration::from_millis(50));
        let mut frame_buf = Box::new([0u8; crate::transport::MAX_DATAGRAM_BYTES]);
        let mut telemetry_buf = Box::new([0u8; crate::transport::MAX_DATAGRAM_BYTES]);
        let shared = Arc::clone(&engine.worker.shared);
        let mut oversized_seen = 0;
        loop {
            tokio::select! {
                biased;
                _ = stopped.changed() => break,
                _ = health.tick() => engine.publish_health().await,
                _ = shared.output_ready.notified() => {}
                // Telemetry before frames when both are ready: a frame then finds the
                // samples sent before it.
                received = recv(telemetry.as_ref(), &mut telemetry_buf) => {
                    let now = engine.clock.now_us();
                    match received {
                        Ok((len, from)) => {
                            if let Some(r) = recorder.as_mut() {
                                r.udp(now, from.port(), telemetry_addr.port(), &telemetry_buf[..len]);
                            }
                            lock(&engine.core).handle_datagram(&telemetry_buf[..len], UdpIngress::Telemetry, now);
                        }
                        Err(error) => receive_failed(&engine, &error).await,
                    }
                }
                received = recv(frames.as_ref(), &mut frame_buf) => {
                    let now = engine.clock.now_us();
                    match received {
                        Ok((len, from)) => {
                            if let Some(r) = recorder.as_mut() {
                                r.udp(now, from.port(), frames_addr.port(), &frame_buf[..len]);
                            }
                            lock(&engine.core).handle_datagram(&frame_buf[..len], UdpIngress::Frames, now);
                        }
                        Err(error) => receive_failed(&engine, &error).await,
                    }
                }
                received = recv_can(engine.can.as_ref()) => {
                    let now = engine.clock.now_us();
                    match received {
                        Ok(frame) => {
                            if let Some(r) = recorder.as_mut() {
                                r.can(now, frame.id(), frame.data(), frame.is_fd());
                            }
                            if !engine.serve_request(frame.id(), frame.data(), now).await {
                                lock(&engine.core).handle_can_frame(true, frame.id(), frame.data(), now);
                            }
                        }
                        Err(error) => receive_failed(&engine, &error).await,
                    }
                }
                _ = housekeeping.tick() => {
                    let now = engine.clock.now_us();
                    lock(&engine.core).tick(now);
                    engine.service_rx.expire(now);
                    if let Some(r) = recorder.as_mut() {
                        r.flush();
                    }
                }
            }
            let oversized: u64 = [frames.as_ref(), telemetry.as_ref()]
                .into_iter()
                .flatten()
                .map(|s| s.stats().oversize_received_dropped)
                .sum();
            if oversized > oversized_seen {
                lock(&engine.core).count_oversized_datagrams(oversized - oversized_seen);
                oversized_seen = oversized;
            }
            engine.flush_outputs().await;
        }
        // Finish queued work on a blocking thread: the trainer may be mid-round.
        let Engine { worker, .. } = engine;
        let _ = tokio::task::spawn_blocking(move || worker.finish()).await;
    });
    Ok(ComponentHandle {
        frames_addr,
        telemetry_addr,
        core,
        worker,
        stop,
        task,
    })
}

/// A socket error (e.g. the CAN interface went down): counted, reported as an event, and
/// a short pause so that a persistent error does not spin the bus task.
async fn receive_failed(engine: &Engine, error: &TransportError) {
    let first = lock(&engine.core).count_receive_error();
    if first {
        eprintln!("fsw-component: receive failed: {error}");
    }
    tokio::time::sleep(Duration::from_millis(10)).await;
}

async fn recv(
    socket: Option<&UdpTransport>,
    buffer: &mut [u8; crate::transport::MAX_DATAGRAM_BYTES],
) -> Result<(usize, SocketAddr), TransportError> {
    match socket {
        Some(s) => s.recv_from(buffer).await,
        None => std::future::pending().await,
    }
}

async fn recv_can(
    can: Option<&CanTransport>,
) -> Result<crate::transport::RawCanFrame, TransportError> {
    match can {
        Some(c) => c.recv().await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn receive_buffer_grows_to_the_configured_size_or_the_system_cap() {
        let socket = UdpTransport::bind("127.0.0.1:0".parse().unwrap())
            .await
            .unwrap();
        let default_bytes = socket.receive_buffer_bytes().unwrap() / 2;
        let asked = 4 * default_bytes.max(64 << 10);
        grow_receive_buffer(&socket, asked).unwrap();
        let granted = socket.receive_buffer_bytes().unwrap() / 2;
        // Root (SO_RCVBUFFORCE) gets the size asked; others at most net.core.rmem_max.
        let cap = std::fs::read_to_string("/proc/sys/net/core/rmem_max")
            .ok()
            .and_then(|s| s.trim().parse::<usize>().ok());
        let expected = if granted >= asked {
            asked
        } else {
            cap.expect("granted less than asked, so a cap must exist")
                .max(default_bytes)
        };
        assert_eq!(granted, expected);
        grow_receive_buffer(&socket, 0).unwrap();
        assert_eq!(
            socket.receive_buffer_bytes().unwrap() / 2,
            granted,
            "0 leaves the buffer alone"
        );
    }
}
