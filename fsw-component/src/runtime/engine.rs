//! The engine the live bus task and replay share: the inbound core, the trainer worker, the
//! UDP and CAN framers, the Cyphal node and its service requests, and the sockets outputs
//! leave on. Outputs are sent in the order the core queued them; a send error is counted,
//! never fatal.

use crate::config::ComponentConfig;
use crate::health::{memory_bytes, ReceiveClock};
use crate::inbound::{BusCore, CoreSettings, HealthContext, Outgoing};
use crate::learner::Learner;
use crate::model_store::ModelStore;
use crate::node::{
    derived_unique_id, parse_unique_id, software_version, CyphalNode, NodeIdentity, NodeStatus,
};
use crate::outbound::{CanFramer, CanPredictions, PredictionOnCan, UdpFramer};
use crate::registers::Registers;
use crate::transport::{CanTransport, UdpTransport};
use crate::worker::{load_events, CheckpointSettings, Notice, QueueLimits, Worker};
use interfaces::cyphal::service_rx::{ServiceRequestRx, ServiceRxError};
use interfaces::cyphal::CanRxError;
use interfaces::messages::{
    ErrorCode, Event, EventKind, Message, Mode, PredictionSource, RenderedPrediction,
};
use serde::Serialize;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::RuntimeError;

/// Concurrent service requests in reassembly, and bytes per request: the largest register
/// Access request (515 bytes) with CAN FD padding and the CRC.
pub(super) const SERVICE_SESSIONS: usize = 4;
pub(super) const SERVICE_SLOT_BYTES: usize = 1024;

pub(super) fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Everything needed to run the core, shared by live and replay.
pub(super) struct Engine {
    pub(super) core: Arc<Mutex<BusCore>>,
    pub(super) worker: Worker,
    pub(super) clock: ReceiveClock,
    pub(super) started: Instant,
    pub(super) udp_framer: UdpFramer,
    pub(super) can_framer: CanFramer,
    /// Predictions on CAN FD (None: UDP only).
    pub(super) can_predictions: Option<CanPredictions>,
    pub(super) node: CyphalNode,
    /// Requests to this node, reassembled apart from the message path.
    pub(super) service_rx: ServiceRequestRx<Vec<u8>, SERVICE_SESSIONS>,
    pub(super) tx: UdpTransport,
    pub(super) can: Option<CanTransport>,
    pub(super) health_to: SocketAddr,
    pub(super) predictions_to: SocketAddr,
    pub(super) predictions_sent: u64,
}

impl Engine {
    pub(super) async fn new(
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

    pub(super) async fn send_status<M: Message + Serialize>(&mut self, msg: &M) {
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
    pub(super) async fn flush_outputs(&mut self) {
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

    pub(super) async fn publish_health(&mut self) {
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
    pub(super) async fn serve_request(&mut self, id: u32, data: &[u8], now_us: u64) -> bool {
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
pub(super) fn can_predictions(config: &ComponentConfig, can_up: bool) -> Option<CanPredictions> {
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
pub(super) fn node_identity(config: &ComponentConfig) -> NodeIdentity {
    NodeIdentity {
        name: config.node.name.clone(),
        unique_id: parse_unique_id(&config.node.unique_id)
            .unwrap_or_else(|| derived_unique_id(&config.node.name, config.node.node_id)),
        software_version: software_version(),
        software_vcs_revision_id: 0,
    }
}
