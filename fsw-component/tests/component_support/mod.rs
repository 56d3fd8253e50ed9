//! Test peer for the component integration tests: the rest of the spacecraft on loopback UDP.
//!
//! Sends telemetry, frames and commands as CCSDS Space Packets, listens for health, events,
//! acknowledgements and predictions on its own ephemeral ports, and scripts a small orbit
//! scenario: the camera circles the target at 10 m, 20 degrees per second, telemetry at 1 Hz,
//! a 16x16 RGB frame at every half second mark after the telemetry that brackets it.
//! [`Scripted`] wraps a learner to inject faults and slow rounds.
#![allow(dead_code)]

use fsw_component::config::ComponentConfig;
use fsw_component::learner::{
    Learner, LearnerError, LearnerStats, ObservedFrame, OfferResult, PredictedImage, RoundSummary,
    ViewRequest,
};
use fsw_component::outbound::UdpFramer;
use fsw_component::runtime::{build_learner, start, ComponentHandle, LearnerKind};
use glam::{DQuat, DVec3};
use interfaces::ccsds::{message_packets, CcsdsReassembler, PacketType};
use interfaces::messages::{
    decode, port, CameraFrame, CameraModel, Command, CommandAck, CommandKind, Distortion, Event,
    FrameHeader, HealthStatus, Message, PixelFormat, PredictionSource, RenderedPrediction,
    SunVector, TargetPose,
};
use serde::Serialize;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::net::UdpSocket;

pub const FRAME_SIZE: u16 = 16;
/// SPEED's focal length (3003.41 px at 1920 px wide) scaled to `FRAME_SIZE`.
pub const FRAME_FOCAL_PX: f32 = 3003.41 * 16.0 / 1920.0;
pub const SUN_BODY: [f32; 3] = [0.0, 0.6, 0.8];
pub const DEG_PER_S: f64 = 20.0;

#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    pub header: FrameHeader,
    pub source: PredictionSource,
    pub q: [f32; 4],
    pub t: [f32; 3],
    pub sun: [f32; 3],
    pub psnr_db: Option<f32>,
    pub ssim: Option<f32>,
    pub pixels: Vec<u8>,
}

#[derive(Default, Debug)]
pub struct Received {
    pub health: Vec<(Instant, HealthStatus)>,
    pub acks: Vec<CommandAck>,
    pub events: Vec<Event>,
    pub predictions: Vec<Prediction>,
    pub undecodable: u64,
}

impl Received {
    pub fn ack(&self, sequence: u32) -> Option<CommandAck> {
        self.acks
            .iter()
            .find(|a| a.sequence == Some(sequence))
            .copied()
    }
    pub fn last_health(&self) -> Option<HealthStatus> {
        self.health.last().map(|h| h.1)
    }
}

pub struct Peer {
    socket: UdpSocket,
    framer: UdpFramer,
    pub health_addr: SocketAddr,
    pub predictions_addr: SocketAddr,
    pub received: Arc<Mutex<Received>>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
    telecommand_count: u16,
    raw_counts: std::collections::BTreeMap<u16, u16>,
}

async fn listen(socket: UdpSocket, received: Arc<Mutex<Received>>) {
    let mut rx: CcsdsReassembler<Vec<u8>, 4> = CcsdsReassembler::new(vec![0; 4 << 20]);
    let mut buffer = vec![0u8; 2048];
    let started = Instant::now();
    loop {
        let Ok((len, _)) = socket.recv_from(&mut buffer).await else {
            return;
        };
        let now = started.elapsed().as_micros() as u64;
        let Ok(Some(message)) = rx.push(&buffer[..len], now) else {
            continue;
        };
        let mut r = received.lock().unwrap();
        let payload = message.payload;
        let ok = match message.apid {
            port::HEALTH_STATUS => decode::<HealthStatus>(payload)
                .map(|h| r.health.push((Instant::now(), h)))
                .is_ok(),
            port::COMMAND_ACK => decode::<CommandAck>(payload)
                .map(|a| r.acks.push(a))
                .is_ok(),
            port::EVENT => decode::<Event>(payload).map(|e| r.events.push(e)).is_ok(),
            port::RENDERED_PREDICTION => decode::<RenderedPrediction>(payload)
                .map(|p| {
                    r.predictions.push(Prediction {
                        header: p.header,
                        source: p.source,
                        q: p.q_camera_from_target,
                        t: p.t_camera_from_target_m,
                        sun: p.sun_target,
                        psnr_db: p.psnr_db,
                        ssim: p.ssim,
                        pixels: p.pixels.to_vec(),
                    });
                })
                .is_ok(),
            _ => false,
        };
        if !ok {
            r.undecodable += 1;
        }
    }
}

impl Peer {
    pub async fn new() -> Self {
        let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let health = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let predictions = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let received = Arc::new(Mutex::new(Received::default()));
        let health_addr = health.local_addr().unwrap();
        let predictions_addr = predictions.local_addr().unwrap();
        let tasks = vec![
            tokio::spawn(listen(health, Arc::clone(&received))),
            tokio::spawn(listen(predictions, Arc::clone(&received))),
        ];
        Self {
            socket,
            framer: UdpFramer::default(),
            health_addr,
            predictions_addr,
            received,
            tasks,
            telecommand_count: 0,
            raw_counts: std::collections::BTreeMap::new(),
        }
    }

    /// A UDP-only configuration on ephemeral ports that reports to this peer.
    pub fn config(&self, checkpoint: PathBuf) -> ComponentConfig {
        let mut config = ComponentConfig::default();
        config.can.enabled = false;
        config.udp.frames_port = 0;
        config.udp.telemetry_port = 0;
        config.udp.health_to = self.health_addr;
        config.udp.predictions_to = self.predictions_addr;
        config.training.window_size = 4;
        // The scenario's camera: SPEED's field of view at 16x16 px.
        set_camera(&mut config, FRAME_SIZE, FRAME_FOCAL_PX);
        config.checkpoint.path = checkpoint;
        config.checkpoint.period_s = 0;
        config
    }

    pub async fn send<M: Message + Serialize>(&mut self, msg: &M, to: SocketAddr) {
        for d in self.framer.datagrams(msg).unwrap() {
            self.send_raw(&d, to).await;
        }
    }

    pub async fn send_raw(&self, datagram: &[u8], to: SocketAddr) {
        self.socket.send_to(datagram, to).await.unwrap();
    }

    /// Raw command bytes as one telecommand packet (for malformed commands).
    pub async fn send_command_bytes(&mut self, bytes: &[u8], to: SocketAddr) {
        let packets: Vec<_> = message_packets(
            PacketType::Telecommand,
            port::COMMAND,
            bytes,
            self.telecommand_count.wrapping_add(1000),
            1472,
        )
        .unwrap()
        .collect();
        self.telecommand_count = self.telecommand_count.wrapping_add(packets.len() as u16);
        for p in packets {
            self.send_raw(&p, to).await;
        }
    }

    pub async fn command(&mut self, sequence: u32, kind: CommandKind, to: SocketAddr) {
        self.send(&Command { sequence, kind }, to).await;
    }

    /// Telemetry packets for `payload` on `apid` with this peer's raw sequence counter
    /// (starting far from the framer's, so no count repeats back to back).
    pub fn raw_packets(&mut self, apid: u16, payload: &[u8]) -> Vec<Vec<u8>> {
        let first = *self.raw_counts.get(&apid).unwrap_or(&5000);
        let out = packets(apid, payload, first);
        self.raw_counts
            .insert(apid, (first + out.len() as u16) % 16384);
        out
    }

    pub fn snapshot<T>(&self, f: impl FnOnce(&Received) -> T) -> T {
        f(&self.received.lock().unwrap())
    }

    /// Polls `condition` every 10 ms until it holds or `timeout` passes.
    pub async fn wait_for(&self, timeout: Duration, condition: impl Fn(&Received) -> bool) -> bool {
        let deadline = Instant::now() + timeout;
        loop {
            if condition(&self.received.lock().unwrap()) {
                return true;
            }
            if Instant::now() > deadline {
                return false;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    pub async fn wait_ack(&self, sequence: u32) -> CommandAck {
        assert!(
            self.wait_for(Duration::from_secs(5), |r| r.ack(sequence).is_some())
                .await,
            "no acknowledgement for command {sequence}"
        );
        self.snapshot(|r| r.ack(sequence).unwrap())
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

pub fn camera_from_target_at(time_us: u64) -> DQuat {
    let angle = (time_us as f64 / 1e6 * DEG_PER_S).to_radians();
    DQuat::from_rotation_y(angle)
}

pub fn pose_at(time_us: u64) -> TargetPose {
    let q = camera_from_target_at(time_us);
    TargetPose {
        time_us,
        q_camera_from_target: [q.w as f32, q.x as f32, q.y as f32, q.z as f32],
        t_camera_from_target_m: [0.0, 0.0, 10.0],
        position_sigma_m: 0.01,
        attitude_sigma_rad: 0.001,
        valid: true,
    }
}

pub fn sun_at(time_us: u64) -> SunVector {
    SunVector {
        time_us,
        sun_body: SUN_BODY,
        valid: true,
        eclipse: None,
    }
}

pub fn frame_pixels(frame_id: u32) -> Vec<u8> {
    let n = usize::from(FRAME_SIZE);
    (0..n * n * 3)
        .map(|i| {
            ((frame_id as usize * 37 + (i / 3 % n) * 5 + (i / 3 / n) * 3 + i % 3 * 50) % 256) as u8
        })
        .collect()
}

/// Configures a square camera of `size` px, focal length `focal_px`, centred.
pub fn set_camera(config: &mut ComponentConfig, size: u16, focal_px: f32) {
    config.camera.width_px = size;
    config.camera.height_px = size;
    config.camera.fx_px = focal_px;
    config.camera.fy_px = focal_px;
    config.camera.cx_px = f32::from(size) / 2.0;
    config.camera.cy_px = f32::from(size) / 2.0;
}

/// The scenario's camera (SPEED's field of view) as a bus camera model for a `size` square
/// image.
pub fn scaled_camera(size: u16) -> CameraModel {
    let scale = f32::from(size) / f32::from(FRAME_SIZE);
    CameraModel {
        fx_px: FRAME_FOCAL_PX * scale,
        fy_px: FRAME_FOCAL_PX * scale,
        cx_px: f32::from(size) / 2.0,
        cy_px: f32::from(size) / 2.0,
        distortion: Distortion::None,
    }
}

pub fn frame_header(frame_id: u32, time_us: u64) -> FrameHeader {
    FrameHeader {
        frame_id,
        time_us,
        width: FRAME_SIZE,
        height: FRAME_SIZE,
        format: PixelFormat::Rgb8,
    }
}

/// Frame `k` of the scenario (no mask, no camera model) over `pixels` (`frame_pixels(k)`).
pub fn step_frame(k: u32, pixels: &[u8]) -> CameraFrame<'_> {
    CameraFrame {
        header: frame_header(k, frame_time_us(k)),
        mask: None,
        pixels,
        camera: None,
    }
}

/// Scenario time of frame `k`: half way between telemetry samples k and k+1 (seconds).
pub fn frame_time_us(k: u32) -> u64 {
    u64::from(k) * 1_000_000 + 500_000
}

/// Sends step `k` of the scenario: telemetry at k+1 s (and at 0 s for k = 0), then, once
/// `handle` has stored that telemetry (frames and telemetry use different sockets, whose
/// order of arrival is not defined), frame k.
pub async fn send_step(peer: &mut Peer, k: u32, handle: &ComponentHandle) {
    let (frames, telemetry) = (handle.frames_addr, handle.telemetry_addr);
    let stored = |h: &ComponentHandle| {
        let c = h.counters().sync;
        c.pose.stored_valid + c.pose.stored_invalid + c.sun.stored_valid + c.sun.stored_invalid
    };
    let before = stored(handle);
    let mut sent = 0;
    if k == 0 {
        peer.send(&pose_at(0), telemetry).await;
        peer.send(&sun_at(0), telemetry).await;
        sent += 2;
    }
    let next = u64::from(k + 1) * 1_000_000;
    peer.send(&pose_at(next), telemetry).await;
    peer.send(&sun_at(next), telemetry).await;
    sent += 2;
    let deadline = Instant::now() + Duration::from_secs(5);
    while stored(handle) < before + sent {
        assert!(
            Instant::now() < deadline,
            "telemetry of step {k} not stored"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let pixels = frame_pixels(k);
    peer.send(&step_frame(k, &pixels), frames).await;
}

/// Unit direction from the target to the camera, target frame, at `time_us`.
pub fn view_at(time_us: u64) -> DVec3 {
    let q = camera_from_target_at(time_us);
    -(q.inverse() * DVec3::new(0.0, 0.0, 10.0)).normalize()
}

/// Starts the component live on `config` with a learner of `kind`, recording the bus traffic
/// to `record` when given: the start-up every loopback test shares.
pub async fn start_component(
    config: &ComponentConfig,
    kind: LearnerKind,
    record: Option<PathBuf>,
) -> ComponentHandle {
    let learner = build_learner(config, kind).expect("learner from the test configuration");
    start(config, learner, record)
        .await
        .expect("component starts")
}

pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fsw-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// postcard varint (LEB128).
pub fn varint(mut value: u64) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let byte = (value & 0x7f) as u8;
        value >>= 7;
        if value == 0 {
            out.push(byte);
            return out;
        }
        out.push(byte | 0x80);
    }
}

/// TargetPose bytes written by hand, so that invalid values can be sent at all.
pub fn raw_pose(time_us: u64, q: [f32; 4], t: [f32; 3], valid: bool) -> Vec<u8> {
    let mut out = varint(time_us);
    for v in q.iter().chain(&t).chain(&[0.01, 0.001]) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.push(u8::from(valid));
    out
}

/// SunVector bytes written by hand.
pub fn raw_sun(time_us: u64, sun: [f32; 3], valid: bool) -> Vec<u8> {
    let mut out = varint(time_us);
    for v in &sun {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.push(u8::from(valid));
    out
}

/// The datagrams of `payload` on `apid` (telemetry packets), first sequence count `first`.
pub fn packets(apid: u16, payload: &[u8], first: u16) -> Vec<Vec<u8>> {
    message_packets(PacketType::Telemetry, apid, payload, first, 1472)
        .unwrap()
        .map(|p| p.to_vec())
        .collect()
}

/// What the scripted learner does on its next calls (shared with the test).
#[derive(Default)]
pub struct Script {
    /// Round calls that panic (counted down).
    pub panicking_rounds: u32,
    /// Every round sleeps this long first.
    pub round_sleep: Duration,
    /// Reported as skipped (non-finite) steps of every round.
    pub skipped_steps: u32,
    /// Round calls that fail with an error (counted down).
    pub failing_rounds: u32,
    /// Offers that the model refuses (counted down).
    pub refused_offers: u32,
}

/// A learner driven by a [`Script`] (faults, slow rounds) around a real one.
pub struct Scripted {
    pub inner: Box<dyn Learner>,
    pub script: Arc<Mutex<Script>>,
}

impl Learner for Scripted {
    fn offer(&mut self, frame: &ObservedFrame) -> OfferResult {
        let mut script = self.script.lock().unwrap();
        if script.refused_offers > 0 {
            script.refused_offers -= 1;
            return OfferResult::Refused;
        }
        drop(script);
        self.inner.offer(frame)
    }
    fn run_round_if_due(&mut self) -> Result<Option<RoundSummary>, LearnerError> {
        let (sleep, skipped) = {
            let mut script = self.script.lock().unwrap();
            if script.panicking_rounds > 0 {
                script.panicking_rounds -= 1;
                drop(script);
                panic!("scripted panic in a training round");
            }
            if script.failing_rounds > 0 {
                script.failing_rounds -= 1;
                return Err(LearnerError::Training("scripted failure".into()));
            }
            (script.round_sleep, script.skipped_steps)
        };
        let round = self.inner.run_round_if_due()?;
        if round.is_some() {
            std::thread::sleep(sleep);
        }
        Ok(round.map(|r| RoundSummary {
            skipped_steps: skipped,
            ..r
        }))
    }
    fn predict(&self, view: &ViewRequest) -> Result<PredictedImage, LearnerError> {
        self.inner.predict(view)
    }
    fn reset(&mut self) -> Result<(), LearnerError> {
        self.inner.reset()
    }
    fn save(&self) -> Vec<u8> {
        self.inner.save()
    }
    fn load(&mut self, bytes: &[u8]) -> Result<(), LearnerError> {
        self.inner.load(bytes)
    }
    fn inspect(&self, bytes: &[u8]) -> Result<u64, LearnerError> {
        self.inner.inspect(bytes)
    }
    fn stats(&self) -> LearnerStats {
        self.inner.stats()
    }
}
