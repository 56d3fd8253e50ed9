//! The bus side of the component, without I/O: decode, synchronise, dispatch, count.
//!
//! [`BusCore`] takes raw UDP datagrams and CAN frames with a receive time (microseconds on
//! the receive clock: wall time live, the log's time stamps on replay), reassembles them
//! (CCSDS / Cyphal, bounded memory), decodes and validates the catalogue messages, feeds
//! telemetry to the synchronizer, pairs frames with telemetry and queues them for the
//! trainer thread, executes or queues commands, and collects acknowledgements and events
//! for the shell (`runtime.rs`) to send. It never blocks and never waits on the trainer.
//!
//! On CAN, messages arrive on the configured subject-IDs (`crate::cyphal_config`, the ICD
//! ports by default) and are dispatched by their ICD port; Sun vectors and poses are taken
//! only from the configured AOCS / navigation node-IDs when those are set.
//!
//! Telemetry passes the time-tag guard (`timeguard.rs`) before the synchronizer, and
//! commands pass the command gate (`cmdauth.rs`): a command from a source outside the
//! allow-list is counted and evented, never decoded and never acknowledged.
//!
//! Invariants: every input that is not used is counted exactly once in [`BusCounters`] or
//! in the reassembler/synchronizer counters; a frame waits for the telemetry sample after
//! its time tag at most `max_wait_us` and at most `pending_capacity` frames wait; error
//! events are rate-limited to one per error code per second (with the count in `detail`).
//! Every frame that goes on to the trainer carries the intrinsics it is used with
//! (`crate::camera`'s rule); a frame whose size disagrees with the configured camera and
//! that carries no camera model of its own is counted and evented, never trained on.

use crate::camera;
use crate::cmdauth::{CommandGate, CommandPolicy, CommandSource, Refusal, UdpIngress};
use crate::cyphal_config::{CyphalConfig, Direction, PORTS};
use crate::learner::{ObservedFrame, ViewRequest};
use crate::sync::{PoseSample, Stream, SunSample, SyncError, Synchronizer, WaitPolicy};
use crate::timeguard::{Admission, TelemetrySample, TimeGuardConfig, TimeTagGuard};
use crate::worker::{CommandJob, FrameJob, FrameUse, ModelCommand, WorkerShared};
use glam::{DQuat, DVec3};
use gs_core::Intrinsics;
use interfaces::ccsds::{CcsdsReassembler, CcsdsRxError};
use interfaces::cyphal::{CanReassembler, CanRxError, SubjectSet};
use interfaces::messages::{
    decode, decode_command, port, AckStatus, CameraFrame, Command, CommandAck, CommandKind,
    ErrorCode, Event, EventKind, HealthStatus, Mode, SunVector, TargetPose,
};
use std::collections::VecDeque;
use std::sync::Arc;

/// Bytes per CCSDS reassembly slot: the largest camera frame message accepted over UDP.
pub const UDP_SLOT_BYTES: usize = 1 << 20;
pub(crate) const UDP_SLOTS: usize = 4;
/// Bytes per Cyphal reassembly slot (telemetry, commands, small frames on CAN FD).
pub(crate) const CAN_SLOT_BYTES: usize = 16 * 1024;
pub(crate) const CAN_SLOTS: usize = 16;
const ERROR_EVENT_INTERVAL_US: u64 = 1_000_000;

fn is_inbound_port(port_id: u16) -> bool {
    matches!(
        port_id,
        port::SUN_VECTOR | port::TARGET_POSE | port::CAMERA_FRAME | port::COMMAND
    )
}

/// Settings of the bus core.
#[derive(Clone, Debug)]
pub struct CoreSettings {
    pub sync: crate::sync::SyncConfig,
    pub max_wait_us: u64,
    pub pending_capacity: usize,
    pub initial_mode: Mode,
    /// The configured camera (`[camera]`), for frames without their own camera model.
    pub camera: Intrinsics,
    pub time_guard: TimeGuardConfig,
    pub commands: CommandPolicy,
}

/// Counters kept by the bus core (the reassemblers and the synchronizer keep their own).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BusCounters {
    /// Camera frames decoded and valid.
    pub frames_received: u64,
    /// Frames not processed because the mode is Idle.
    pub frames_ignored_idle: u64,
    /// Frames without a camera model whose size is not the configured camera's.
    pub frames_camera_mismatch: u64,
    /// Messages whose bytes failed to decode or validate (per port).
    pub sun_decode_errors: u64,
    pub pose_decode_errors: u64,
    pub frame_decode_errors: u64,
    /// Telemetry decoded but dropped by the synchronizer (out of order, duplicate time).
    pub telemetry_out_of_order: u64,
    /// Telemetry dropped because its time tag was too far from the receive clock.
    pub telemetry_time_out_of_bounds: u64,
    /// Streams resynchronised to a new telemetry clock (buffer cleared).
    pub telemetry_resyncs: u64,
    pub commands_accepted: u64,
    pub commands_rejected: u64,
    pub commands_busy: u64,
    /// Commands from sources outside the allow-list (not acknowledged).
    pub commands_unauthorised: u64,
    /// Destructive commands without a valid arm (acknowledged EXECUTION_ERROR).
    pub commands_not_armed: u64,
    /// RENDER commands above the rate limit (acknowledged BUSY).
    pub commands_rate_limited: u64,
    /// Outbound messages that could not be encoded or sent (see the log).
    pub send_errors: u64,
    /// Datagrams above 1472 bytes, dropped by the UDP transport.
    pub oversized_datagrams: u64,
    /// Socket receive errors (UDP or CAN).
    pub receive_errors: u64,
    /// Rendered predictions too large for CAN FD, sent on UDP only.
    pub predictions_not_on_can: u64,
    /// CAN telemetry from a node other than the configured AOCS / navigation node.
    pub telemetry_wrong_source: u64,
    /// Service requests to this node that failed reassembly (CRC, toggle, ...) or decoding.
    pub service_requests_rejected: u64,
}

/// Everything the core counts, for tests and health.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CoreCounters {
    pub bus: BusCounters,
    pub udp: interfaces::ccsds::CcsdsRxCounters,
    pub can: interfaces::cyphal::CanRxCounters,
    pub sync: crate::sync::SyncCounters,
}

/// A message for the shell to send.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Outgoing {
    Ack(CommandAck),
    Event(Event),
}

struct PendingFrame {
    frame: OwnedFrame,
    received_us: u64,
}

struct OwnedFrame {
    frame_id: u32,
    time_us: u64,
    width: u16,
    height: u16,
    format: interfaces::messages::PixelFormat,
    pixels: Vec<u8>,
    mask: Option<Vec<u8>>,
    camera: Intrinsics,
}

/// A refused [`CoreSettings`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CoreConfigError {
    Sync(crate::sync::SyncConfigError),
    TimeGuard(crate::timeguard::TimeGuardConfigError),
}

impl std::fmt::Display for CoreConfigError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Sync(e) => write!(f, "{e}"),
            Self::TimeGuard(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for CoreConfigError {}

pub struct BusCore {
    settings: CoreSettings,
    udp_rx: CcsdsReassembler<Vec<u8>, UDP_SLOTS>,
    can_rx: CanReassembler<Vec<u8>, CAN_SLOTS>,
    /// Subject-IDs of the messages on CAN and the telemetry source node-IDs.
    can_ports: CyphalConfig,
    sync: Synchronizer,
    pose_guard: TimeTagGuard,
    sun_guard: TimeTagGuard,
    gate: CommandGate,
    pending: VecDeque<PendingFrame>,
    mode: Mode,
    /// The mode to return to once the trainer's learner is restarted after a panic (None
    /// when no restart is pending, or the operator set a mode since).
    mode_after_restart: Option<Mode>,
    counters: BusCounters,
    worker: Arc<WorkerShared>,
    outbox: Vec<Outgoing>,
    last_error_event_us: [Option<u64>; ErrorCode::COUNT],
    suppressed_errors: [u32; ErrorCode::COUNT],
    now_us: u64,
    /// Intrinsics (with the size) and format for RENDER: the last accepted camera frame's.
    render_camera: (Intrinsics, interfaces::messages::PixelFormat),
}

/// Health figures the core cannot know itself.
#[derive(Clone, Copy, Debug, Default)]
pub struct HealthContext {
    pub uptime_s: u32,
    pub memory_bytes: u64,
    pub publish_queue_depth: usize,
}

fn sat_u32(v: u64) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

impl BusCore {
    pub fn new(settings: CoreSettings, worker: Arc<WorkerShared>) -> Result<Self, CoreConfigError> {
        let sync = Synchronizer::new(settings.sync).map_err(CoreConfigError::Sync)?;
        let guard = TimeTagGuard::new(settings.time_guard).map_err(CoreConfigError::TimeGuard)?;
        let render_camera = (
            camera::render_default(&settings.camera),
            interfaces::messages::PixelFormat::Rgb8,
        );
        Ok(Self {
            pose_guard: guard.clone(),
            sun_guard: guard,
            gate: CommandGate::new(settings.commands),
            mode: settings.initial_mode,
            mode_after_restart: None,
            settings,
            udp_rx: CcsdsReassembler::new(vec![0; UDP_SLOTS * UDP_SLOT_BYTES])
                .with_apid_filter(is_inbound_port),
            can_rx: CanReassembler::new(vec![0; CAN_SLOTS * CAN_SLOT_BYTES])
                .with_subject_filter(is_inbound_port),
            can_ports: CyphalConfig::default(),
            sync,
            pending: VecDeque::new(),
            counters: BusCounters::default(),
            worker,
            outbox: Vec::new(),
            last_error_event_us: [None; ErrorCode::COUNT],
            suppressed_errors: [0; ErrorCode::COUNT],
            now_us: 0,
            render_camera,
        })
    }

    /// Takes CAN messages on the configured subject-IDs (and telemetry only from the
    /// configured source nodes) instead of the ICD defaults; `can_ports` is validated.
    pub(crate) fn with_can_ports(mut self, can_ports: &CyphalConfig) -> Self {
        let mut subjects = SubjectSet::default();
        for (spec, id) in PORTS.iter().zip(can_ports.subjects.as_array()) {
            if spec.direction == Direction::Subscribe && spec.always {
                subjects.insert(id);
            }
        }
        self.can_rx =
            CanReassembler::new(vec![0; CAN_SLOTS * CAN_SLOT_BYTES]).with_subject_set(subjects);
        self.can_ports = can_ports.clone();
        self
    }

    /// A service request to this node that failed reassembly or decoding: counted, and an
    /// error event (rate-limited like the others).
    pub(crate) fn count_service_request_rejected(&mut self, crc: bool) {
        self.counters.service_requests_rejected += 1;
        self.error_event(if crc {
            ErrorCode::CrcError
        } else {
            ErrorCode::DecodeError
        });
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    pub fn counters(&self) -> CoreCounters {
        CoreCounters {
            bus: self.counters,
            udp: *self.udp_rx.counters(),
            can: *self.can_rx.counters(),
            sync: self.sync.counters(),
        }
    }

    pub fn count_send_error(&mut self) {
        self.counters.send_errors += 1;
    }

    /// A prediction too large for CAN FD went on UDP only; `first` sends the run's one
    /// `PredictionNotOnCan` event (detail: its encoded size, bytes).
    pub(crate) fn prediction_not_on_can(&mut self, encoded_bytes: usize, first: bool) {
        self.counters.predictions_not_on_can += 1;
        if first {
            self.push_event(EventKind::Error {
                code: ErrorCode::PredictionNotOnCan,
                detail: u32::try_from(encoded_bytes).unwrap_or(u32::MAX),
            });
        }
    }

    /// A socket receive error; true for the first one (worth a log line).
    pub(crate) fn count_receive_error(&mut self) -> bool {
        self.counters.receive_errors += 1;
        self.error_event(ErrorCode::Internal);
        self.counters.receive_errors == 1
    }

    /// Datagrams the transport dropped as oversized (reported as decode errors).
    pub(crate) fn count_oversized_datagrams(&mut self, count: u64) {
        if count > 0 {
            self.counters.oversized_datagrams += count;
            self.error_event(ErrorCode::DecodeError);
        }
    }

    /// Messages to send, in order.
    pub fn take_outgoing(&mut self) -> Vec<Outgoing> {
        std::mem::take(&mut self.outbox)
    }

    fn error_event(&mut self, code: ErrorCode) {
        let i = code.index();
        let (Some(last), Some(suppressed)) = (
            self.last_error_event_us.get_mut(i),
            self.suppressed_errors.get_mut(i),
        ) else {
            // A code missing from `ErrorCode::ALL`: reported unthrottled rather than lost.
            self.push_event(EventKind::Error { code, detail: 1 });
            return;
        };
        *suppressed = suppressed.saturating_add(1);
        let due = last.is_none_or(|at| self.now_us.saturating_sub(at) >= ERROR_EVENT_INTERVAL_US);
        if due {
            *last = Some(self.now_us);
            let detail = std::mem::take(suppressed);
            self.push_event(EventKind::Error { code, detail });
        }
    }

    fn push_event(&mut self, kind: EventKind) {
        self.outbox.push(Outgoing::Event(Event {
            time_us: self.now_us,
            kind,
        }));
    }

    /// One received UDP datagram from the socket `ingress`.
    pub fn handle_datagram(&mut self, datagram: &[u8], ingress: UdpIngress, now_us: u64) {
        self.now_us = now_us;
        match self.udp_rx.push(datagram, now_us) {
            Ok(Some(message)) => {
                let apid = message.apid;
                let source = CommandSource::Udp {
                    ingress,
                    packet_type: message.packet_type,
                };
                let payload = message.payload.to_vec();
                self.handle_message(apid, &payload, source);
            }
            Ok(None) | Err(CcsdsRxError::NotSubscribed) => {}
            Err(CcsdsRxError::CrcMismatch) => self.error_event(ErrorCode::CrcError),
            Err(_) => self.error_event(ErrorCode::DecodeError),
        }
    }

    /// One received CAN frame (`id` without flag bits).
    pub fn handle_can_frame(&mut self, extended: bool, id: u32, data: &[u8], now_us: u64) {
        self.now_us = now_us;
        match self.can_rx.push_frame(extended, id, data, now_us) {
            Ok(Some(transfer)) => {
                // The subject filter admits configured subjects only, so the lookup succeeds.
                let Some(port_id) = self.can_ports.subjects.icd_port_of(transfer.subject_id) else {
                    return;
                };
                if !self
                    .can_ports
                    .accepts_source(port_id, transfer.source_node_id)
                {
                    self.counters.telemetry_wrong_source += 1;
                    self.error_event(ErrorCode::TelemetryInvalid);
                    return;
                }
                let source = CommandSource::Can {
                    node_id: transfer.source_node_id,
                };
                let payload = transfer.payload.to_vec();
                self.handle_message(port_id, &payload, source);
            }
            Ok(None) | Err(CanRxError::NotSubscribed) => {}
            Err(CanRxError::CrcMismatch) => self.error_event(ErrorCode::CrcError),
            Err(_) => self.error_event(ErrorCode::DecodeError),
        }
    }

    fn handle_message(&mut self, port_id: u16, payload: &[u8], source: CommandSource) {
        match port_id {
            port::SUN_VECTOR => self.handle_sun(payload),
            port::TARGET_POSE => self.handle_pose(payload),
            port::CAMERA_FRAME => self.handle_frame(payload),
            port::COMMAND if self.gate.authorises(source) => self.handle_command(payload, source),
            port::COMMAND => {
                // Strangers get no acknowledgement: counted, and one event per second.
                self.counters.commands_unauthorised += 1;
                self.error_event(ErrorCode::CommandUnauthorised);
            }
            _ => {}
        }
    }

    /// Time-tag guard, then synchronizer; frames waiting for this sample are retried.
    fn push_telemetry(&mut self, sample: TelemetrySample) {
        let guard = match sample.stream() {
            Stream::Pose => &mut self.pose_guard,
            Stream::Sun => &mut self.sun_guard,
        };
        match guard.push(&mut self.sync, sample, self.now_us) {
            Admission::Stored(_) => self.retry_pending(WaitPolicy::MayWait),
            Admission::Resynchronised(_) => {
                self.counters.telemetry_resyncs += 1;
                self.error_event(ErrorCode::TelemetryClockJump);
                self.retry_pending(WaitPolicy::MayWait);
            }
            Admission::OutOfBounds { .. } => {
                self.counters.telemetry_time_out_of_bounds += 1;
                self.error_event(ErrorCode::TelemetryTimeOutOfBounds);
            }
            Admission::Dropped(_) => {
                self.counters.telemetry_out_of_order += 1;
                self.error_event(ErrorCode::TelemetryStale);
            }
        }
    }

    fn handle_sun(&mut self, payload: &[u8]) {
        let Ok(sun) = decode::<SunVector>(payload) else {
            self.counters.sun_decode_errors += 1;
            self.error_event(ErrorCode::TelemetryInvalid);
            return;
        };
        let sample = SunSample {
            time_us: sun.time_us,
            sun_in_body: DVec3::from_array(sun.sun_body.map(f64::from)),
            valid: sun.valid,
            eclipse: sun.eclipse,
        };
        self.push_telemetry(TelemetrySample::Sun(sample));
    }

    fn handle_pose(&mut self, payload: &[u8]) {
        let Ok(pose) = decode::<TargetPose>(payload) else {
            self.counters.pose_decode_errors += 1;
            self.error_event(ErrorCode::TelemetryInvalid);
            return;
        };
        let [w, x, y, z] = pose.q_camera_from_target.map(f64::from);
        let sample = PoseSample {
            time_us: pose.time_us,
            camera_from_target: DQuat::from_xyzw(x, y, z, w),
            target_in_camera_m: DVec3::from_array(pose.t_camera_from_target_m.map(f64::from)),
            quality: pose_quality(&pose),
        };
        self.push_telemetry(TelemetrySample::Pose(sample));
    }

    fn handle_frame(&mut self, payload: &[u8]) {
        let frame = match decode::<CameraFrame>(payload) {
            Ok(frame) => frame,
            Err(_) => {
                self.counters.frame_decode_errors += 1;
                self.error_event(ErrorCode::DecodeError);
                return;
            }
        };
        self.counters.frames_received += 1;
        let intrinsics =
            match camera::for_frame(&self.settings.camera, &frame.header, frame.camera.as_ref()) {
                Ok(intrinsics) => intrinsics,
                Err(_) => {
                    self.counters.frames_camera_mismatch += 1;
                    self.error_event(ErrorCode::CameraMismatch);
                    return;
                }
            };
        self.render_camera = (intrinsics, frame.header.format);
        if self.mode == Mode::Idle {
            self.counters.frames_ignored_idle += 1;
            return;
        }
        let owned = OwnedFrame {
            frame_id: frame.header.frame_id,
            time_us: frame.header.time_us,
            width: frame.header.width,
            height: frame.header.height,
            format: frame.header.format,
            pixels: frame.pixels.to_vec(),
            mask: frame.mask.map(<[u8]>::to_vec),
            camera: intrinsics,
        };
        if self.pending.len() >= self.settings.pending_capacity.max(1) {
            if let Some(oldest) = self.pending.pop_front() {
                self.resolve(oldest.frame, WaitPolicy::NoWait);
            }
        }
        if let Some(frame) = self.resolve(owned, WaitPolicy::MayWait) {
            self.pending.push_back(PendingFrame {
                frame,
                received_us: self.now_us,
            });
        }
    }

    /// Synchronises and dispatches a frame; hands it back when it must wait.
    fn resolve(&mut self, frame: OwnedFrame, policy: WaitPolicy) -> Option<OwnedFrame> {
        match self.sync.synchronize(frame.time_us, policy) {
            Ok(telemetry) => {
                let usage = match self.mode {
                    Mode::Train => FrameUse::PredictAndTrain,
                    _ => FrameUse::PredictOnly,
                };
                let job = FrameJob {
                    frame: ObservedFrame {
                        frame_id: frame.frame_id,
                        time_us: frame.time_us,
                        width: frame.width,
                        height: frame.height,
                        format: frame.format,
                        pixels: frame.pixels,
                        mask: frame.mask,
                        camera: frame.camera,
                        telemetry,
                    },
                    usage,
                };
                if self.worker.push_frame(job) {
                    self.error_event(ErrorCode::QueueOverflow);
                }
                None
            }
            Err(SyncError::AwaitingTelemetry { .. }) => Some(frame),
            // Skipped on purpose (counted by the synchronizer), not an error.
            Err(SyncError::Eclipse) => None,
            Err(error) => {
                let code = match error {
                    SyncError::Missing { .. } => ErrorCode::TelemetryMissing,
                    SyncError::Stale { .. } => ErrorCode::TelemetryStale,
                    _ => ErrorCode::TelemetryInvalid,
                };
                self.error_event(code);
                None
            }
        }
    }

    fn retry_pending(&mut self, policy: WaitPolicy) {
        let waiting = std::mem::take(&mut self.pending);
        for p in waiting {
            if let Some(frame) = self.resolve(p.frame, policy) {
                self.pending.push_back(PendingFrame {
                    frame,
                    received_us: p.received_us,
                });
            }
        }
    }

    /// Time passes: expire reassembly and let frames stop waiting for telemetry.
    pub fn tick(&mut self, now_us: u64) {
        self.now_us = now_us;
        self.udp_rx.expire(now_us);
        self.can_rx.expire(now_us);
        while let Some(p) = self.pending.front() {
            if now_us.saturating_sub(p.received_us) < self.settings.max_wait_us {
                break;
            }
            if let Some(p) = self.pending.pop_front() {
                self.resolve(p.frame, WaitPolicy::NoWait);
            }
        }
    }

    /// Frames still waiting for telemetry.
    pub fn pending_frames(&self) -> usize {
        self.pending.len()
    }

    fn ack(&mut self, ack: CommandAck) {
        if ack.status == AckStatus::Ok {
            self.counters.commands_accepted += 1;
        } else {
            self.counters.commands_rejected += 1;
        }
        self.outbox.push(Outgoing::Ack(ack));
    }

    /// Acknowledgements produced later by the trainer thread.
    pub(crate) fn worker_ack(&mut self, ack: CommandAck) {
        if ack.status != AckStatus::Ok {
            // Counted as accepted when queued; the model then failed to execute it.
            self.counters.commands_rejected += 1;
            self.counters.commands_accepted = self.counters.commands_accepted.saturating_sub(1);
        }
        self.outbox.push(Outgoing::Ack(ack));
    }

    pub fn worker_event(&mut self, kind: EventKind) {
        self.push_event(kind);
    }

    fn set_mode(&mut self, to: Mode) {
        let from = self.mode;
        self.mode = to;
        if from != to {
            self.push_event(EventKind::ModeChanged { from, to });
        }
    }

    /// The trainer panicked: no training on a learner being restarted (Train becomes
    /// PredictOnly until `Self::trainer_restored`); when it gave up, Idle until commanded.
    pub fn trainer_faulted(&mut self, gave_up: bool) {
        if gave_up {
            self.mode_after_restart = None;
            self.set_mode(Mode::Idle);
        } else if self.mode == Mode::Train {
            self.mode_after_restart = Some(Mode::Train);
            self.set_mode(Mode::PredictOnly);
        }
    }

    /// The learner was restarted: back to the mode the fault interrupted.
    pub(crate) fn trainer_restored(&mut self) {
        if let Some(mode) = self.mode_after_restart.take() {
            self.set_mode(mode);
        }
    }

    fn handle_command(&mut self, payload: &[u8], source: CommandSource) {
        let command = match decode_command(payload) {
            Ok(command) => command,
            Err(error) => {
                self.ack(error.ack());
                return;
            }
        };
        if let Err(refusal) = self.gate.admit(&command.kind, source, self.now_us) {
            let (status, code) = match refusal {
                Refusal::NotArmed => {
                    self.counters.commands_not_armed += 1;
                    (AckStatus::ExecutionError, ErrorCode::CommandNotArmed)
                }
                Refusal::RateLimited => {
                    self.counters.commands_rate_limited += 1;
                    (AckStatus::Busy, ErrorCode::CommandRateLimited)
                }
            };
            self.error_event(code);
            self.ack(CommandAck {
                detail: code.index() as u16,
                ..command.ack(status)
            });
            return;
        }
        let Command { sequence, kind } = command;
        let model_command = match kind {
            CommandKind::Noop | CommandKind::Arm(_) => None,
            CommandKind::ResetCounters => {
                self.reset_counters();
                None
            }
            CommandKind::SetMode(to) => {
                // The operator's choice wins over a pending return after a restart.
                self.mode_after_restart = None;
                self.set_mode(to);
                None
            }
            CommandKind::ResetModel => Some(ModelCommand::ResetModel),
            CommandKind::SaveCheckpoint => Some(ModelCommand::SaveCheckpoint),
            CommandKind::LoadCheckpoint => Some(ModelCommand::LoadCheckpoint),
            CommandKind::Render(r) => {
                // The last frame's camera, shrunk by an integer factor when its image would
                // exceed the RENDER pixel bound (the field of view stays the same).
                let (camera, format) = self.render_camera;
                let factor = self
                    .gate
                    .render_downsample(camera.width as u16, camera.height as u16);
                let mut intrinsics = camera.downsampled(u32::from(factor));
                intrinsics.width = intrinsics.width.max(1);
                intrinsics.height = intrinsics.height.max(1);
                let [w, x, y, z] = r.q_camera_from_target.map(f64::from);
                Some(ModelCommand::Render(ViewRequest {
                    camera_from_target: DQuat::from_xyzw(x, y, z, w).normalize(),
                    target_in_camera_m: DVec3::from_array(r.t_camera_from_target_m.map(f64::from)),
                    sun_in_target: DVec3::from_array(r.sun_target.map(f64::from)).normalize(),
                    width: intrinsics.width as u16,
                    height: intrinsics.height as u16,
                    format,
                    intrinsics,
                }))
            }
        };
        let Some(model_command) = model_command else {
            self.ack(command.ack(AckStatus::Ok));
            return;
        };
        let job = CommandJob {
            sequence,
            opcode: kind.opcode(),
            command: model_command,
        };
        match self.worker.push_command(job) {
            // The trainer thread acknowledges once it has executed the command.
            Ok(()) => self.counters.commands_accepted += 1,
            Err(_) => {
                self.counters.commands_busy += 1;
                self.ack(command.ack(AckStatus::Busy));
            }
        }
    }

    fn reset_counters(&mut self) {
        self.counters = BusCounters::default();
        self.udp_rx.reset_counters();
        self.can_rx.reset_counters();
        self.sync.reset_counters();
        self.worker.reset_counters();
    }

    /// The health message for now.
    pub fn health(&self, context: HealthContext) -> HealthStatus {
        let c = self.counters();
        let worker = self.worker.snapshot();
        let depths = self.worker.depths();
        let sync_rejected = c.sync.frames.rejected_missing
            + c.sync.frames.rejected_stale
            + c.sync.frames.rejected_invalid
            + c.sync.frames.eclipse;
        let crc_errors = c.udp.rejected_crc_mismatch + c.can.rejected_crc_mismatch;
        let udp_rejected = c.udp.rejected_total()
            - c.udp.rejected_crc_mismatch
            - c.udp.rejected_not_subscribed
            - c.udp.rejected_idle;
        let can_rejected =
            c.can.rejected_total() - c.can.rejected_crc_mismatch - c.can.rejected_not_subscribed;
        let decode_errors = udp_rejected
            + can_rejected
            + c.udp.abandoned_messages
            + c.can.abandoned_transfers
            + c.bus.sun_decode_errors
            + c.bus.pose_decode_errors
            + c.bus.frame_decode_errors
            + c.bus.telemetry_out_of_order
            + c.bus.telemetry_time_out_of_bounds
            + c.bus.oversized_datagrams
            + c.bus.telemetry_wrong_source
            + c.bus.service_requests_rejected;
        let learner = worker.learner;
        HealthStatus {
            time_us: self.now_us,
            mode: self.mode,
            uptime_s: context.uptime_s,
            frames_received: sat_u32(c.bus.frames_received),
            frames_used: sat_u32(worker.frames_used),
            frames_dropped: sat_u32(
                sync_rejected
                    + c.bus.frames_ignored_idle
                    + c.bus.frames_camera_mismatch
                    + depths.frames_dropped,
            ),
            decode_errors: sat_u32(decode_errors),
            crc_errors: sat_u32(crc_errors),
            commands_accepted: sat_u32(c.bus.commands_accepted),
            commands_rejected: sat_u32(c.bus.commands_rejected + c.bus.commands_unauthorised),
            gaussians: learner.gaussians,
            rounds: learner.rounds,
            last_round_duration_ms: worker.last_round.map(|r| r.duration_ms),
            last_loss: worker
                .last_round
                .map(|r| r.loss)
                .filter(|l| l.is_finite() && *l >= 0.0),
            last_prediction_psnr_db: worker.last_prediction_psnr_db,
            window_fill: learner.window_fill.min(learner.window_capacity),
            window_capacity: learner.window_capacity,
            frame_queue_depth: u16::try_from(depths.frames + self.pending.len())
                .unwrap_or(u16::MAX),
            publish_queue_depth: u16::try_from(depths.predictions + context.publish_queue_depth)
                .unwrap_or(u16::MAX),
            memory_bytes: context.memory_bytes,
        }
    }
}

/// Navigation quality in (0, 1] from the pose uncertainties:
/// `1 / (1 + sigma_att / 0.01 rad + sigma_pos / 1 m)`; NaN for poses flagged invalid, which
/// the synchronizer stores as invalid markers (non-finite).
pub fn pose_quality(pose: &TargetPose) -> f64 {
    if !pose.valid {
        return f64::NAN;
    }
    1.0 / (1.0 + f64::from(pose.attitude_sigma_rad) / 0.01 + f64::from(pose.position_sigma_m))
}
