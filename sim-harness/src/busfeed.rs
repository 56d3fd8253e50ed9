//! Bus feed: a generated dataset as the flight component's bus traffic, written as logs
//! (`can.log` candump + `udp.rec` UDP recording, the formats `fsw-component --replay` reads)
//! or played onto a live bus (UDP, and SocketCAN when an interface is given).
//!
//! Per telemetry line (one camera frame) the feed sends, in this order:
//! - `TargetPose` from the navigation node and `SunVector` from the AOCS node, both stamped
//!   with the frame's exposure time, so the synchronizer finds an exact sample for each
//!   stream (the frame cadence is longer than `sync.max_gap_ms`, so interpolation between
//!   frames would be rejected anyway);
//! - the `CameraFrame` (RGB8, with the mask when the dataset has one, and the dataset's
//!   camera model) as CCSDS datagrams to the component's frame port, after the telemetry.
//!
//! Time base: message times and log time tags are microseconds since the scenario epoch
//! (`time_s` of telemetry.jsonl). Log time tags are receive times: telemetry frames at the
//! exposure time plus `CAN_FRAME_SPACING_US` per frame, the camera datagrams from
//! `FRAME_LATENCY_US` after exposure, `DATAGRAM_SPACING_US` apart. They are strictly
//! increasing within a step and below the next step's, so any stable merge of the two logs
//! keeps the order above.
//!
//! Invariants: output depends only on the dataset and the options (byte-identical reruns);
//! bad input (missing files, non-finite or non-unit vectors, sizes that do not fit the
//! message, lines out of time order) is a [`BusFeedError`] naming the line or file, never a
//! panic. The Sun vector is sent `valid` also in eclipse: the AOCS knows the Sun direction
//! from its ephemeris, and the Sun-aware model needs it for the dark frames too; the
//! scenario's eclipse flag travels with it (`eclipse`), so the component skips the frames
//! the in-process trainer skips. The dataset
//! has no navigation covariance, so the pose uncertainties come from the options.

use fsw_component::config::ComponentConfig;
use fsw_component::outbound::{CanFramer, OutboundError, UdpFramer};
use fsw_component::recorder::{Recorder, CAN_FILE, UDP_FILE};
use fsw_component::transport::{CanTransport, CanTransportConfig, RawCanFrame};
use interfaces::messages::{
    CameraFrame, CameraModel, Distortion, FrameHeader, PixelFormat, SunVector, TargetPose,
};
use serde::Deserialize;
use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Node-ID of the AOCS (Sun vector source) on the simulated bus.
pub const AOCS_NODE_ID: u8 = 10;
/// Node-ID of relative navigation (target pose source).
pub const NAVIGATION_NODE_ID: u8 = 11;
/// Receive-time spacing of consecutive CAN frames in a log, microseconds.
pub(crate) const CAN_FRAME_SPACING_US: u64 = 100;
/// Receive time of a frame's first datagram after its exposure time, microseconds.
pub(crate) const FRAME_LATENCY_US: u64 = 10_000;
/// Receive-time spacing of consecutive camera datagrams, microseconds (1472 bytes per
/// 100 us: about 118 Mbit/s, a fast camera link).
pub(crate) const DATAGRAM_SPACING_US: u64 = 100;
/// UDP source port written for the camera's datagrams.
pub(crate) const CAMERA_SOURCE_PORT: u16 = 15100;
/// Datagrams sent back to back before `play` at full speed pauses for a millisecond, so a
/// frame does not overrun the receiver's socket buffer (about 94 Mbit/s).
const DATAGRAMS_PER_MS: usize = 8;

/// Why a dataset could not be turned into bus traffic.
#[derive(Debug)]
pub enum BusFeedError {
    Io { path: PathBuf, message: String },
    Telemetry { line: usize, message: String },
    Image { path: PathBuf, message: String },
    Encode(OutboundError),
    Options(String),
    Can { interface: String, message: String },
    Udp { to: SocketAddr, message: String },
}

impl fmt::Display for BusFeedError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::Telemetry { line, message } => {
                write!(f, "telemetry.jsonl line {line}: {message}")
            }
            Self::Image { path, message } => write!(f, "image {}: {message}", path.display()),
            Self::Encode(e) => write!(f, "{e}"),
            Self::Options(m) => write!(f, "{m}"),
            Self::Can { interface, message } => {
                write!(f, "CAN interface {interface:?}: {message}")
            }
            Self::Udp { to, message } => write!(f, "UDP to {to}: {message}"),
        }
    }
}

impl std::error::Error for BusFeedError {}

impl From<OutboundError> for BusFeedError {
    fn from(e: OutboundError) -> Self {
        Self::Encode(e)
    }
}

/// How the dataset is put on the bus.
#[derive(Clone, Debug, PartialEq)]
pub struct BusFeedOptions {
    pub aocs_node_id: u8,
    pub navigation_node_id: u8,
    /// CAN FD (64-byte frames) or classic CAN (8-byte frames).
    pub can_fd: bool,
    /// Interface name written in the candump log.
    pub can_interface: String,
    /// Destination port written for the camera datagrams (the component's frame port).
    pub frames_port: u16,
    pub position_sigma_m: f32,
    pub attitude_sigma_rad: f32,
    /// Send the target mask with each frame when the dataset has one.
    pub include_mask: bool,
}

impl BusFeedOptions {
    /// The bus as the component configuration describes it (CAN FD flag, interface, port).
    pub fn from_config(config: &ComponentConfig) -> Self {
        Self {
            aocs_node_id: AOCS_NODE_ID,
            navigation_node_id: NAVIGATION_NODE_ID,
            can_fd: config.can.fd,
            can_interface: config.can.interface.clone(),
            frames_port: config.udp.frames_port,
            position_sigma_m: 0.0,
            attitude_sigma_rad: 0.0,
            include_mask: true,
        }
    }

    /// The options against the component's own node-ID and the codec's ranges.
    pub fn validate(&self, component_node_id: u8) -> Result<(), BusFeedError> {
        let ids = [
            ("AOCS", self.aocs_node_id),
            ("navigation", self.navigation_node_id),
        ];
        for (name, id) in ids {
            if id > 127 {
                return Err(BusFeedError::Options(format!(
                    "{name} node-ID {id} is above 127"
                )));
            }
            if id == component_node_id {
                return Err(BusFeedError::Options(format!(
                    "{name} node-ID {id} is the component's own node-ID"
                )));
            }
        }
        if self.aocs_node_id == self.navigation_node_id {
            return Err(BusFeedError::Options(format!(
                "AOCS and navigation share node-ID {}",
                self.aocs_node_id
            )));
        }
        for (name, v) in [
            ("position sigma", self.position_sigma_m),
            ("attitude sigma", self.attitude_sigma_rad),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(BusFeedError::Options(format!(
                    "{name} {v} must be finite and >= 0"
                )));
            }
        }
        Ok(())
    }
}

#[derive(Deserialize)]
struct Intrinsics {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// The fields of a telemetry.jsonl line the feed uses (others are ignored).
#[derive(Deserialize)]
struct TelemetryJson {
    index: u32,
    time_s: Option<f64>,
    frame: String,
    #[serde(default)]
    mask: Option<String>,
    q_camera_from_target_wxyz: [f64; 4],
    t_camera_from_target_m: [f64; 3],
    sun_servicer_body: [f64; 3],
    #[serde(default)]
    eclipse: bool,
    intrinsics: Intrinsics,
}

/// One frame's telemetry, checked and in message units.
#[derive(Clone, Debug, PartialEq)]
pub struct FeedLine {
    pub index: u32,
    /// Exposure time, microseconds since the scenario epoch.
    pub time_us: u64,
    pub frame_path: PathBuf,
    pub mask_path: Option<PathBuf>,
    pub width: u16,
    pub height: u16,
    pub q_camera_from_target_wxyz: [f32; 4],
    pub t_camera_from_target_m: [f32; 3],
    pub sun_servicer_body: [f32; 3],
    /// The frame's camera, sent with it (`CameraFrame` 1.1).
    pub camera: CameraModel,
    /// The scenario's eclipse flag, sent as the AOCS's (`SunVector` 1.1).
    pub eclipse: bool,
}

/// Unit vector in f32 from an f64 one within 1e-3 of unit length (the sensor's output is
/// renormalised so that the f32 rounding stays inside the component's tolerance).
fn unit_f32<const N: usize>(
    v: [f64; N],
    what: &str,
    line: usize,
) -> Result<[f32; N], BusFeedError> {
    let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if !v.iter().all(|x| x.is_finite()) || (norm - 1.0).abs() > 1e-3 {
        return Err(BusFeedError::Telemetry {
            line,
            message: format!("{what} {v:?} is not a finite unit vector"),
        });
    }
    Ok(v.map(|x| (x / norm) as f32))
}

/// The dataset camera as a bus camera model (validated against its size).
fn camera_model(k: &Intrinsics) -> Result<CameraModel, interfaces::messages::ValidationError> {
    let model = CameraModel {
        fx_px: k.fx as f32,
        fy_px: k.fy as f32,
        cx_px: k.cx as f32,
        cy_px: k.cy as f32,
        distortion: Distortion::None,
    };
    let size = |v: u32| u16::try_from(v).unwrap_or(u16::MAX);
    model.check(size(k.width), size(k.height))?;
    Ok(model)
}

fn parse_line(text: &str, line: usize, dataset: &Path) -> Result<FeedLine, BusFeedError> {
    let bad = |message: String| BusFeedError::Telemetry { line, message };
    let json: TelemetryJson = serde_json::from_str(text).map_err(|e| bad(e.to_string()))?;
    let time_s = json
        .time_s
        .ok_or_else(|| bad("time_s is null (an evaluation view, not a sequence frame)".into()))?;
    if !(0.0..1e12).contains(&time_s) {
        return Err(bad(format!("time_s {time_s} is not a time >= 0")));
    }
    let t = json.t_camera_from_target_m;
    if !t.iter().all(|x| x.is_finite()) {
        return Err(bad(format!("t_camera_from_target_m {t:?} is not finite")));
    }
    let size = |v: u32, what: &str| {
        u16::try_from(v).ok().filter(|&s| s > 0).ok_or_else(|| {
            bad(format!(
                "image {what} {v} does not fit a camera frame (1-65535)"
            ))
        })
    };
    Ok(FeedLine {
        index: json.index,
        time_us: (time_s * 1e6).round() as u64,
        frame_path: dataset.join(&json.frame),
        mask_path: json.mask.filter(|m| !m.is_empty()).map(|m| dataset.join(m)),
        width: size(json.intrinsics.width, "width")?,
        height: size(json.intrinsics.height, "height")?,
        q_camera_from_target_wxyz: unit_f32(
            json.q_camera_from_target_wxyz,
            "q_camera_from_target_wxyz",
            line,
        )?,
        t_camera_from_target_m: t.map(|x| x as f32),
        sun_servicer_body: unit_f32(json.sun_servicer_body, "sun_servicer_body", line)?,
        camera: camera_model(&json.intrinsics).map_err(|e| bad(format!("intrinsics: {e}")))?,
        eclipse: json.eclipse,
    })
}

/// Reads `DIR/telemetry.jsonl`: the sequence frames in strictly increasing time.
pub fn load_telemetry(dataset: &Path) -> Result<Vec<FeedLine>, BusFeedError> {
    let path = dataset.join("telemetry.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| BusFeedError::Io {
        path: path.clone(),
        message: e.to_string(),
    })?;
    let mut lines = Vec::new();
    for (i, text) in text.lines().enumerate() {
        if text.trim().is_empty() {
            continue;
        }
        let line = parse_line(text, i + 1, dataset)?;
        if let Some(previous) = lines.last().map(|l: &FeedLine| l.time_us) {
            if line.time_us <= previous {
                return Err(BusFeedError::Telemetry {
                    line: i + 1,
                    message: format!(
                        "time {} us is not after the previous line's {previous} us",
                        line.time_us
                    ),
                });
            }
        }
        lines.push(line);
    }
    if lines.is_empty() {
        return Err(BusFeedError::Telemetry {
            line: 0,
            message: format!("{} has no frames", path.display()),
        });
    }
    Ok(lines)
}

fn load_png(path: &Path, width: u16, height: u16, grey: bool) -> Result<Vec<u8>, BusFeedError> {
    let bad = |message: String| BusFeedError::Image {
        path: path.to_path_buf(),
        message,
    };
    let image = image::open(path).map_err(|e| bad(e.to_string()))?;
    if (image.width(), image.height()) != (u32::from(width), u32::from(height)) {
        return Err(bad(format!(
            "{}x{} pixels, telemetry says {width}x{height}",
            image.width(),
            image.height()
        )));
    }
    Ok(if grey {
        image.to_luma8().into_raw()
    } else {
        image.to_rgb8().into_raw()
    })
}

/// One frame's traffic, framed and ready to send.
#[derive(Clone, Debug, PartialEq)]
pub struct BusStep {
    pub line: FeedLine,
    pub pose: TargetPose,
    pub sun: SunVector,
    /// Pose transfer, then Sun transfer.
    pub can_frames: Vec<RawCanFrame>,
    /// The same telemetry as CCSDS datagrams (pose, then Sun), for UDP telemetry.
    pub telemetry_datagrams: Vec<Vec<u8>>,
    pub frame_datagrams: Vec<Vec<u8>>,
}

/// Frames a dataset step by step; framer counters (transfer-IDs, sequence counts) carry over
/// from step to step as on a real bus.
pub struct BusFeed {
    options: BusFeedOptions,
    lines: Vec<FeedLine>,
    navigation: CanFramer,
    aocs: CanFramer,
    camera: UdpFramer,
    telemetry_udp: UdpFramer,
}

impl BusFeed {
    pub fn open(
        dataset: &Path,
        options: BusFeedOptions,
        component_node_id: u8,
    ) -> Result<Self, BusFeedError> {
        options.validate(component_node_id)?;
        let lines = load_telemetry(dataset)?;
        Ok(Self {
            navigation: CanFramer::new(options.navigation_node_id, options.can_fd),
            aocs: CanFramer::new(options.aocs_node_id, options.can_fd),
            options,
            lines,
            camera: UdpFramer::default(),
            telemetry_udp: UdpFramer::default(),
        })
    }

    pub fn lines(&self) -> &[FeedLine] {
        &self.lines
    }

    /// Loads frame `k`'s images and frames its messages.
    pub fn step(&mut self, k: usize) -> Result<BusStep, BusFeedError> {
        let line = self.lines[k].clone();
        let pose = TargetPose {
            time_us: line.time_us,
            q_camera_from_target: line.q_camera_from_target_wxyz,
            t_camera_from_target_m: line.t_camera_from_target_m,
            position_sigma_m: self.options.position_sigma_m,
            attitude_sigma_rad: self.options.attitude_sigma_rad,
            valid: true,
        };
        let sun = SunVector {
            time_us: line.time_us,
            sun_body: line.sun_servicer_body,
            valid: true,
            eclipse: Some(line.eclipse),
        };
        let pixels = load_png(&line.frame_path, line.width, line.height, false)?;
        let mask = match (&line.mask_path, self.options.include_mask) {
            (Some(path), true) if path.exists() => {
                Some(load_png(path, line.width, line.height, true)?)
            }
            _ => None,
        };
        let frame = CameraFrame {
            header: FrameHeader {
                frame_id: line.index,
                time_us: line.time_us,
                width: line.width,
                height: line.height,
                format: PixelFormat::Rgb8,
            },
            mask: mask.as_deref(),
            pixels: &pixels,
            camera: Some(line.camera),
        };
        let mut can_frames = self.navigation.frames(&pose)?;
        can_frames.extend(self.aocs.frames(&sun)?);
        let mut telemetry_datagrams = self.telemetry_udp.datagrams(&pose)?;
        telemetry_datagrams.extend(self.telemetry_udp.datagrams(&sun)?);
        let frame_datagrams = self.camera.datagrams(&frame)?;
        Ok(BusStep {
            line,
            pose,
            sun,
            can_frames,
            telemetry_datagrams,
            frame_datagrams,
        })
    }
}

/// What was written or played.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct BusFeedSummary {
    pub frames: u64,
    pub can_frames: u64,
    pub telemetry_datagrams: u64,
    pub frame_datagrams: u64,
    pub first_time_us: u64,
    pub last_time_us: u64,
}

/// Writes `OUT/can.log` and `OUT/udp.rec` for the dataset (see the module header for timing).
pub fn write_bus_logs(
    dataset: &Path,
    out: &Path,
    options: &BusFeedOptions,
    component_node_id: u8,
) -> Result<BusFeedSummary, BusFeedError> {
    let mut feed = BusFeed::open(dataset, options.clone(), component_node_id)?;
    let mut recorder =
        Recorder::create(out, &options.can_interface).map_err(|e| BusFeedError::Io {
            path: out.to_path_buf(),
            message: e.to_string(),
        })?;
    let mut summary = BusFeedSummary::default();
    for k in 0..feed.lines().len() {
        let step = feed.step(k)?;
        let t0 = step.line.time_us;
        let last_can_us = t0 + CAN_FRAME_SPACING_US * step.can_frames.len() as u64;
        let first_frame_us = t0 + FRAME_LATENCY_US;
        if last_can_us >= first_frame_us {
            return Err(BusFeedError::Options(format!(
                "{} telemetry CAN frames do not fit before the camera frame",
                step.can_frames.len()
            )));
        }
        let last_frame_us =
            first_frame_us + DATAGRAM_SPACING_US * step.frame_datagrams.len() as u64;
        if let Some(next) = feed.lines().get(k + 1) {
            if last_frame_us >= next.time_us {
                return Err(BusFeedError::Telemetry {
                    line: k + 2,
                    message: format!(
                        "frame {} takes until {last_frame_us} us on the link, after the next \
                         frame's exposure",
                        step.line.index
                    ),
                });
            }
        }
        for (i, f) in step.can_frames.iter().enumerate() {
            recorder.can(
                t0 + CAN_FRAME_SPACING_US * i as u64,
                f.id(),
                f.data(),
                f.is_fd(),
            );
        }
        for (i, d) in step.frame_datagrams.iter().enumerate() {
            recorder.udp(
                first_frame_us + DATAGRAM_SPACING_US * i as u64,
                CAMERA_SOURCE_PORT,
                options.frames_port,
                d,
            );
        }
        if k == 0 {
            summary.first_time_us = t0;
        }
        summary.last_time_us = last_frame_us;
        summary.frames += 1;
        summary.can_frames += step.can_frames.len() as u64;
        summary.frame_datagrams += step.frame_datagrams.len() as u64;
    }
    recorder.flush();
    if recorder.write_errors > 0 {
        return Err(BusFeedError::Io {
            path: out.to_path_buf(),
            message: format!("{} writes failed", recorder.write_errors),
        });
    }
    Ok(summary)
}

/// The log files `write_bus_logs` writes into `out`.
pub fn bus_log_paths(out: &Path) -> [PathBuf; 2] {
    [out.join(CAN_FILE), out.join(UDP_FILE)]
}

/// How fast `play` sends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PlaySpeed {
    /// Back to back, datagrams paced at about 94 Mbit/s.
    Max,
    /// Scenario time divided by this factor (1.0 = real time).
    Scaled(f64),
}

impl std::str::FromStr for PlaySpeed {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "max" {
            return Ok(Self::Max);
        }
        match s.parse::<f64>() {
            Ok(x) if x.is_finite() && x > 0.0 => Ok(Self::Scaled(x)),
            _ => Err(format!("speed {s:?}: want a factor > 0 or \"max\"")),
        }
    }
}

/// Where `play` sends.
#[derive(Clone, Debug, PartialEq)]
pub struct PlayTargets {
    /// The component's frame port.
    pub frames_udp: SocketAddr,
    /// Telemetry over UDP; when neither this nor `can_interface` is given, telemetry goes to
    /// `frames_udp` (the component decodes every port on both sockets).
    pub telemetry_udp: Option<SocketAddr>,
    /// Telemetry over SocketCAN on this interface.
    pub can_interface: Option<String>,
}

/// Plays the dataset onto the live bus.
pub async fn play(
    dataset: &Path,
    options: &BusFeedOptions,
    component_node_id: u8,
    targets: &PlayTargets,
    speed: PlaySpeed,
) -> Result<BusFeedSummary, BusFeedError> {
    let mut feed = BusFeed::open(dataset, options.clone(), component_node_id)?;
    let can = match &targets.can_interface {
        Some(interface) => Some(
            CanTransport::open(&CanTransportConfig {
                interface: interface.clone(),
                fd: options.can_fd,
            })
            .map_err(|e| BusFeedError::Can {
                interface: interface.clone(),
                message: format!("{e} (does it exist and is it up? see tests/ for vcan0)"),
            })?,
        ),
        None => None,
    };
    let telemetry_udp = match (targets.telemetry_udp, &can) {
        (Some(to), _) => Some(to),
        (None, None) => Some(targets.frames_udp),
        (None, Some(_)) => None,
    };
    let any: SocketAddr = if targets.frames_udp.is_ipv4() {
        "0.0.0.0:0"
    } else {
        "[::]:0"
    }
    .parse()
    .expect("literal address");
    let socket = tokio::net::UdpSocket::bind(any)
        .await
        .map_err(|e| BusFeedError::Udp {
            to: targets.frames_udp,
            message: format!("cannot bind a sending socket: {e}"),
        })?;
    let send = |to: SocketAddr, bytes: Vec<u8>| {
        let socket = &socket;
        async move {
            socket
                .send_to(&bytes, to)
                .await
                .map(|_| ())
                .map_err(|e| BusFeedError::Udp {
                    to,
                    message: e.to_string(),
                })
        }
    };
    let started = Instant::now();
    let first_us = feed.lines()[0].time_us;
    let mut summary = BusFeedSummary {
        first_time_us: first_us,
        ..Default::default()
    };
    for k in 0..feed.lines().len() {
        let step = feed.step(k)?;
        if let PlaySpeed::Scaled(factor) = speed {
            let due = Duration::from_secs_f64((step.line.time_us - first_us) as f64 / 1e6 / factor);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                tokio::time::sleep(wait).await;
            }
        }
        if let Some(can) = &can {
            for f in &step.can_frames {
                can.send(f).await.map_err(|e| BusFeedError::Can {
                    interface: can.interface().to_string(),
                    message: e.to_string(),
                })?;
            }
            summary.can_frames += step.can_frames.len() as u64;
        }
        if let Some(to) = telemetry_udp {
            for d in &step.telemetry_datagrams {
                send(to, d.clone()).await?;
            }
            summary.telemetry_datagrams += step.telemetry_datagrams.len() as u64;
        }
        // The camera's exposure-to-link latency: the telemetry is in before the frame.
        tokio::time::sleep(Duration::from_micros(FRAME_LATENCY_US)).await;
        for (i, d) in step.frame_datagrams.iter().enumerate() {
            if i > 0 && i % DATAGRAMS_PER_MS == 0 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
            send(targets.frames_udp, d.clone()).await?;
        }
        summary.frame_datagrams += step.frame_datagrams.len() as u64;
        summary.frames += 1;
        summary.last_time_us = step.line.time_us;
    }
    Ok(summary)
}
