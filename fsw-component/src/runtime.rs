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

use crate::cmdauth::UdpIngress;
use crate::config::ComponentConfig;
use crate::health::{memory_bytes, ReceiveClock};
use crate::inbound::{BusCore, CoreCounters, CoreSettings, HealthContext, Outgoing};
use crate::learner::Learner;
use crate::model_store::ModelStore;
use crate::nearest_learner::NearestKeyframeLearner;
use crate::node::{
    derived_unique_id, parse_unique_id, software_version, CyphalNode, NodeIdentity, NodeStatus,
};
use crate::outbound::{CanFramer, CanPredictions, PredictionOnCan, UdpFramer};
use crate::recorder::Recorder;
use crate::registers::Registers;
use crate::replay::{self, ReplayInput};
use crate::sunaware_learner::{SunAwareLearner, SunAwareSettings};
use crate::transport::{CanTransport, CanTransportConfig, TransportError, UdpTransport};
use crate::worker::{load_events, CheckpointSettings, Notice, QueueLimits, Worker};
use interfaces::cyphal::service_rx::{ServiceRequestRx, ServiceRxError};
use interfaces::cyphal::CanRxError;
use interfaces::messages::{
    ErrorCode, Event, EventKind, Message, Mode, PredictionSource, RenderedPrediction,
};
use serde::Serialize;
use std::fmt;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::watch;

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
            settings.online.passes_per_round = config.training.passes_per_round;
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
            settings.online.model = config
                .model_config()
                .map_err(|e| RuntimeError::Config(e.to_string()))?;
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

/// Concurrent service requests in reassembly, and bytes per request: the largest register
/// Access request (515 bytes) with CAN FD padding and the CRC.
const SERVICE_SESSIONS: usize = 4;
const SERVICE_SLOT_BYTES: usize = 1024;

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|p| p.into_inner())
}

/// Everything needed to run the core, shared by live and replay.
struct Engine {
    core: Arc<Mutex<BusCore>>,
    worker: Worker,
    clock: ReceiveClock,
    started: Instant,
    udp_framer: UdpFramer,
    can_framer: CanFramer,
    /// Predictions on CAN FD (None: UDP only).
    can_predictions: Option<CanPredictions>,
    node: CyphalNode,
    /// Requests to this node, reassembled apart from the message path.
    service_rx: ServiceRequestRx<Vec<u8>, SERVICE_SESSIONS>,
    tx: UdpTransport,
    can: Option<CanTransport>,
    health_to: SocketAddr,
    predictions_to: SocketAddr,
    predictions_sent: u64,
}

impl Engine {
    async fn new(
        config: &ComponentConfig,
        mut learner: Box<dyn Learner>,
        can: Option<CanTransport>,
    ) -> Result<(Self, Vec<Event>), RuntimeError> {
        let settings = CoreSettings {
            sync: config
                .sync_config()
                .map_err(|e| RuntimeError::Config(e.to_string()))?,
            max_wait_us: config.sync.max_wait_ms.saturating_mul(1000),
            pending_capacity: config.queues.pending_frames,
            initial_mode: Mode::Train,
            camera: config
                .camera_intrinsics()
                .map_err(|e| RuntimeError::Config(e.to_string()))?,
            time_guard: config
                .time_guard_config()
                .map_err(|e| RuntimeError::Config(e.to_string()))?,
            commands: config
                .command_policy()
                .map_err(|e| RuntimeError::Config(e.to_string()))?,
        };
        let mut resume_events = Vec::new();
        if config.checkpoint.resume {
            let store = ModelStore::open(&config.checkpoint.path, learner.as_ref());
            resume_events = load_events(store.load_newest(learner.as_mut()));
        }
        let worker = Worker::start(
            learner,
            QueueLimits {
                frames: config.queues.frames,
                commands: config.queues.commands,
                predictions: config.queues.predictions,
            },
            CheckpointSettings {
                path: config.checkpoint.path.clone(),
                period: (config.checkpoint.period_s > 0)
                    .then(|| Duration::from_secs(config.checkpoint.period_s)),
            },
            config.training.threads,
            config
                .denormals()
                .map_err(|e| RuntimeError::Config(e.to_string()))?,
            Duration::from_millis(config.training.round_deadline_ms),
        )
        .map_err(|source| RuntimeError::Io {
            what: "start the trainer thread".into(),
            source,
        })?;
        let core = BusCore::new(settings, Arc::clone(&worker.shared))
            .map_err(|e| RuntimeError::Config(e.to_string()))?
            .with_can_ports(&config.cyphal);
        let tx = UdpTransport::bind(SocketAddr::new(config.udp.bind_ip, 0))
            .await
            .map_err(RuntimeError::Transport)?;
        let clock = ReceiveClock::start();
        let mut node = CyphalNode::new(config.node.node_id, config.can.fd, node_identity(config))
            .with_subjects(&config.cyphal.subjects)
            .with_registers(Registers::new(config));
        let can_predictions = can_predictions(config, can.is_some());
        if let Some(p) = &can_predictions {
            node.publish_also(p.subject_id());
        }
        let events = resume_events
            .into_iter()
            .map(|kind| Event {
                time_us: clock.now_us(),
                kind,
            })
            .collect();
        Ok((
            Self {
                core: Arc::new(Mutex::new(core)),
                worker,
                clock,
                started: Instant::now(),
                udp_framer: UdpFramer::default(),
                can_framer: CanFramer::new(config.node.node_id, config.can.fd)
                    .with_subjects(config.cyphal.subjects),
                can_predictions,
                node,
                service_rx: ServiceRequestRx::new(vec![0; SERVICE_SESSIONS * SERVICE_SLOT_BYTES]),
                tx,
                can,
                health_to: config.udp.health_to,
                predictions_to: config.udp.predictions_to,
                predictions_sent: 0,
            },
            events,
        ))
    }

    async fn send_status<M: Message + Serialize>(&mut self, msg: &M) {
        let mut failed = false;
        match self.udp_framer.datagrams(msg) {
            Ok(datagrams) => {
                for d in datagrams {
                    failed |= self.tx.send_to(&d, self.health_to).await.is_err();
                }
            }
            Err(e) => {
                eprintln!("fsw-component: {e}");
                failed = true;
            }
        }
        if let Some(can) = &self.can {
            match self.can_framer.frames(msg) {
                Ok(frames) => {
                    for f in frames {
                        failed |= can.send(&f).await.is_err();
                    }
                }
                Err(e) => {
                    eprintln!("fsw-component: {e}");
                    failed = true;
                }
            }
        }
        if failed {
            lock(&self.core).count_send_error();
        }
    }

    /// Sends everything the core and the worker produced.
    async fn flush_outputs(&mut self) {
        let notices = self.worker.shared.take_notices();
        let overdue = self.worker.shared.overdue_job();
        let outgoing = {
            let mut core = lock(&self.core);
            for notice in notices {
                match notice {
                    Notice::Ack(ack) => core.worker_ack(ack),
                    Notice::Event(kind) => core.worker_event(kind),
                    Notice::TrainerFault { gave_up } => {
                        self.node.trainer_faulted(gave_up);
                        core.trainer_faulted(gave_up);
                    }
                    Notice::TrainerRestored => {
                        self.node.trainer_restored();
                        core.trainer_restored();
                    }
                }
            }
            if overdue {
                core.worker_event(EventKind::Error {
                    code: ErrorCode::Internal,
                    detail: interfaces::messages::event_detail::ROUND_DEADLINE_MISSED,
                });
            }
            core.take_outgoing()
        };
        for out in outgoing {
            match out {
                Outgoing::Ack(ack) => self.send_status(&ack).await,
                Outgoing::Event(event) => self.send_status(&event).await,
            }
        }
        for p in self.worker.shared.take_predictions() {
            let message = RenderedPrediction {
                header: p.header,
                source: p.source,
                q_camera_from_target: p.q_camera_from_target,
                t_camera_from_target_m: p.t_camera_from_target_m,
                sun_target: p.sun_target,
                psnr_db: p.psnr_db,
                ssim: p.ssim,
                pixels: &p.pixels,
            };
            let mut failed = false;
            match self.udp_framer.datagrams(&message) {
                Ok(datagrams) => {
                    for d in datagrams {
                        failed |= self.tx.send_to(&d, self.predictions_to).await.is_err();
                    }
                }
                Err(e) => {
                    eprintln!("fsw-component: prediction {:?}: {e}", p.source);
                    failed = true;
                }
            }
            if let (Some(can), Some(publisher)) = (&self.can, self.can_predictions.as_mut()) {
                match publisher.route(&message) {
                    Ok(PredictionOnCan::Frames(frames)) => {
                        for f in frames {
                            failed |= can.send(&f).await.is_err();
                        }
                    }
                    Ok(PredictionOnCan::TooLarge {
                        encoded_bytes,
                        first,
                    }) => lock(&self.core).prediction_not_on_can(encoded_bytes, first),
                    Err(e) => {
                        eprintln!("fsw-component: prediction {:?} on CAN: {e}", p.source);
                        failed = true;
                    }
                }
            }
            if failed {
                lock(&self.core).count_send_error();
            } else {
                self.predictions_sent += 1;
            }
            if matches!(p.source, PredictionSource::Command { .. }) {
                tokio::task::yield_now().await;
            }
        }
    }

    async fn publish_health(&mut self) {
        let context = HealthContext {
            uptime_s: u32::try_from(self.started.elapsed().as_secs()).unwrap_or(u32::MAX),
            memory_bytes: memory_bytes().unwrap_or(0),
            publish_queue_depth: 0,
        };
        let (health, send_errors) = {
            let core = lock(&self.core);
            (core.health(context), core.counters().bus.send_errors)
        };
        self.send_status(&health).await;
        if let Some(can) = &self.can {
            let heartbeat = self
                .node
                .heartbeat(&NodeStatus::from_health(&health, send_errors));
            let mut failed = false;
            for frame in self.node.heartbeat_frames(&heartbeat) {
                failed |= can.send(&frame).await.is_err();
            }
            if failed {
                lock(&self.core).count_send_error();
            }
        }
    }

    /// Takes a frame of a service request addressed to this node and answers the request
    /// once complete; `false` when the frame is not one, so that the message path takes
    /// (and counts) it as before. Rejected request frames and undecodable requests are
    /// counted and evented by the core.
    async fn serve_request(&mut self, id: u32, data: &[u8], now_us: u64) -> bool {
        let malformed_before = self.node.requests_malformed;
        let answer = match self.service_rx.push(id, data, self.node.node_id(), now_us) {
            Err(ServiceRxError::NotOurs(_)) => return false,
            Err(ServiceRxError::Rejected(error)) => {
                lock(&self.core).count_service_request_rejected(error == CanRxError::CrcMismatch);
                return true;
            }
            Ok(None) => return true,
            Ok(Some(request)) => self.node.answer(&request),
        };
        if self.node.requests_malformed > malformed_before {
            lock(&self.core).count_service_request_rejected(false);
        }
        let Some(frames) = answer else {
            return true;
        };
        let mut failed = false;
        if let Some(can) = &self.can {
            for frame in frames {
                failed |= can.send(&frame).await.is_err();
            }
        }
        if failed {
            lock(&self.core).count_send_error();
        }
        true
    }
}

/// The CAN FD prediction publisher when CAN is up, FD and `[can] predictions` is set.
fn can_predictions(config: &ComponentConfig, can_up: bool) -> Option<CanPredictions> {
    let c = &config.can;
    (can_up && c.fd && c.predictions).then(|| {
        CanPredictions::new(
            config.node.node_id,
            config.cyphal.subjects.rendered_prediction,
            c.prediction_max_bytes,
        )
    })
}

/// GetInfo's identity from the configuration (a derived unique-ID when none is set).
fn node_identity(config: &ComponentConfig) -> NodeIdentity {
    NodeIdentity {
        name: config.node.name.clone(),
        unique_id: parse_unique_id(&config.node.unique_id)
            .unwrap_or_else(|| derived_unique_id(&config.node.name, config.node.node_id)),
        software_version: software_version(),
        software_vcs_revision_id: 0,
    }
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
pub fn open_can(config: &ComponentConfig) -> Result<Option<CanTransport>, RuntimeError> {
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
                    core.handle_datagram(bytes, UdpIngress::Replayed, record.time_us)
                }
                ReplayInput::CanFrame { extended, id, data } => {
                    core.handle_can_frame(*extended, *id, data, record.time_us)
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
