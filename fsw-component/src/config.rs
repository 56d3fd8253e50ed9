//! Component configuration (config/component.toml).
//!
//! Every section and field has a default, so a file only states what differs; unknown
//! keys are errors (a misspelt key must not silently fall back to a default).
//! [`ComponentConfig::validate`] checks ranges and cross-field consistency and names the
//! offending key; [`ComponentConfig::load`] reads, parses and validates in one step.
//! Quaternions are written `[w, x, y, z]` like the bus messages.
//! `[training]` is in [`training`]: its keys (the demo preset's model and trainer by
//! default) and the online trainer's configuration they give.

use crate::cmdauth::{CommandConfig, CommandPolicy};
use crate::cyphal_config::{CyphalConfig, CyphalConfigError};
use crate::hull_start::ModelSettings;
use crate::node::{parse_unique_id, DEFAULT_NODE_NAME};
use crate::sync::SyncConfig;
use crate::timeguard::TimeGuardConfig;
use glam::DQuat;
use gs_core::fpmode::DenormalMode;
use gs_core::sunaware::{BackendKind, ModelKey, SunAwareConfig, SunAwareError, Variant};
use gs_online::keyframe::{KeyframeError, KeyframeWindow, WindowConfig};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};

/// Largest Cyphal/CAN node-ID.
pub(crate) const MAX_NODE_ID: u8 = 127;
/// Linux interface names are at most IFNAMSIZ - 1 = 15 bytes.
pub(crate) const MAX_INTERFACE_NAME_BYTES: usize = 15;
/// Largest `[can] prediction_max_bytes`: 64 KiB, about 1,040 CAN FD frames.
pub(crate) const MAX_PREDICTION_CAN_BYTES: usize = 1 << 16;
/// Default `[can] prediction_max_bytes`: 4 KiB, 66 CAN FD frames (a 32x32 RGB image).
pub(crate) const DEFAULT_PREDICTION_CAN_BYTES: usize = 4096;
/// Upper bound of `training.passes_per_round`: a round must still end within minutes.
pub(crate) const MAX_PASSES_PER_ROUND: u32 = 100;
/// Range of `training.round_deadline_ms`: 100 ms to one hour.
pub(crate) const ROUND_DEADLINE_MS_RANGE: std::ops::RangeInclusive<u64> = 100..=3_600_000;

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ComponentConfig {
    pub node: NodeConfig,
    pub can: CanConfig,
    pub udp: UdpConfig,
    pub camera: CameraConfig,
    pub sync: SyncSettings,
    pub training: TrainingConfig,
    pub model: ModelSettings,
    pub checkpoint: CheckpointConfig,
    pub queues: QueueConfig,
    pub commands: CommandConfig,
    pub cyphal: CyphalConfig,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeConfig {
    /// Cyphal node-ID of this component, 0-127.
    pub node_id: u8,
    /// Node name reported by uavcan.node.GetInfo, 1-50 bytes.
    pub name: String,
    /// 128-bit unique-ID reported by GetInfo, 32 hex digits; "" derives it from
    /// /etc/machine-id (a per-machine 128-bit ID) XOR the node-ID, or from the name and
    /// node-ID where that file is missing.
    pub unique_id: String,
    /// Free text for operators: the `uavcan.node.description` register, at most 256 bytes.
    pub description: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CanConfig {
    pub enabled: bool,
    /// SocketCAN interface, e.g. "can0" or "vcan0".
    pub interface: String,
    /// Use CAN FD (64-byte frames; the interface needs MTU 72).
    pub fd: bool,
    /// With `fd`: publish each rendered prediction whose encoding is at most
    /// `prediction_max_bytes` also as a multi-frame Cyphal/CAN FD transfer; larger ones go
    /// on UDP only (counted, and one `PredictionNotOnCan` event per run). Classic CAN
    /// never carries predictions.
    pub predictions: bool,
    /// Largest encoded `RenderedPrediction` sent on CAN FD, bytes (1 to
    /// `MAX_PREDICTION_CAN_BYTES`); the subject is `[cyphal.subjects] rendered_prediction`.
    pub prediction_max_bytes: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct UdpConfig {
    pub enabled: bool,
    /// Local address the receiving sockets bind to.
    pub bind_ip: IpAddr,
    /// Camera frames arrive here (0: any free port, for tests).
    pub frames_port: u16,
    /// Pose, Sun telemetry and commands arrive here when sent over UDP (0: any free port).
    pub telemetry_port: u16,
    /// Rendered predictions are sent to this address.
    pub predictions_to: SocketAddr,
    /// Health status, events and command acknowledgements are sent to this address.
    pub health_to: SocketAddr,
    /// Kernel receive buffer asked for on both receiving sockets, bytes; 0 keeps the
    /// system default (about 200 KiB, less than one 640x480 RGB frame in flight).
    pub receive_buffer_bytes: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Camera mounting: rotation taking servicer-body vectors to camera-frame vectors, [w, x, y, z].
    pub camera_from_body_wxyz: [f64; 4],
    /// Image size the camera delivers, pixels. A frame without its own camera model
    /// (`CameraFrame` 1.0) must have exactly this size (`crate::camera`).
    pub width_px: u16,
    pub height_px: u16,
    /// Focal lengths, pixels.
    pub fx_px: f32,
    pub fy_px: f32,
    /// Principal point, pixels from the image's top-left corner (pixel centres at +0.5).
    pub cx_px: f32,
    pub cy_px: f32,
    /// Lens distortion: only "none" (the camera sends undistorted images).
    pub distortion: String,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyncSettings {
    /// Telemetry samples kept per stream.
    pub buffer_capacity: usize,
    /// Largest distance from a frame time to the telemetry sample on either side.
    pub max_gap_ms: u64,
    /// A frame later than the newest telemetry by more than this is stale.
    pub stale_after_ms: u64,
    /// How long a frame may wait for the telemetry sample after its time tag.
    pub max_wait_ms: u64,
    /// Allowed |norm - 1| of quaternions and Sun vectors.
    pub unit_norm_tolerance: f64,
    /// Poses with a lower quality are rejected.
    pub min_pose_quality: f64,
    /// Largest change of (telemetry time tag - receive time) from the stream's last
    /// accepted sample; samples beyond it are dropped.
    pub time_tag_tolerance_ms: u64,
    /// Consecutive consistent rejected samples of a stream taken as a clock jump.
    pub resync_after_samples: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckpointConfig {
    /// Newest checkpoint; the one before it is kept as `<path>.prev` (both written
    /// atomically and verified; a save never replaces a model trained for more rounds).
    pub path: PathBuf,
    /// Seconds between periodic checkpoints; 0 disables them.
    pub period_s: u64,
    /// Resume at start from the newest slot the model accepts (`path`, else `path.prev`).
    pub resume: bool,
    /// A checkpoint whose model (or window, shuffle seed, replay capacity) differs from the
    /// configured one: refused, or used with a log line.
    pub on_config_mismatch: crate::sunaware_learner::OnConfigMismatch,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QueueConfig {
    /// Synchronised frames waiting for the trainer (oldest dropped when full).
    pub frames: usize,
    /// Frames waiting for telemetry after their time tag.
    pub pending_frames: usize,
    /// Commands waiting for execution (rejected BUSY when full).
    pub commands: usize,
    /// Outgoing predictions (oldest dropped when full).
    pub predictions: usize,
}

impl Default for NodeConfig {
    fn default() -> Self {
        Self {
            node_id: 42,
            name: DEFAULT_NODE_NAME.into(),
            unique_id: String::new(),
            description: String::new(),
        }
    }
}

impl Default for CanConfig {
    fn default() -> Self {
        Self {
            // UDP alone works everywhere; CAN needs an interface that exists.
            enabled: false,
            interface: "vcan0".to_string(),
            fd: true,
            predictions: true,
            prediction_max_bytes: DEFAULT_PREDICTION_CAN_BYTES,
        }
    }
}

impl Default for UdpConfig {
    fn default() -> Self {
        let localhost = IpAddr::V4(Ipv4Addr::LOCALHOST);
        Self {
            enabled: true,
            bind_ip: localhost,
            frames_port: 15_001,
            telemetry_port: 15_002,
            predictions_to: SocketAddr::new(localhost, 15_003),
            health_to: SocketAddr::new(localhost, 15_004),
            receive_buffer_bytes: 4 << 20,
        }
    }
}

impl Default for CameraConfig {
    fn default() -> Self {
        // SPEED's camera (Tango mission): 1920x1200 px, f = 3003.41 px, centred.
        Self {
            camera_from_body_wxyz: [1.0, 0.0, 0.0, 0.0],
            width_px: 1920,
            height_px: 1200,
            fx_px: 3003.41,
            fy_px: 3003.41,
            cx_px: 960.0,
            cy_px: 600.0,
            distortion: "none".to_string(),
        }
    }
}

impl Default for SyncSettings {
    fn default() -> Self {
        let sync = SyncConfig::default();
        Self {
            buffer_capacity: sync.buffer_capacity,
            max_gap_ms: sync.max_gap_us / 1_000,
            stale_after_ms: sync.stale_after_us / 1_000,
            max_wait_ms: 1_000,
            unit_norm_tolerance: sync.unit_norm_tolerance,
            min_pose_quality: sync.min_pose_quality,
            time_tag_tolerance_ms: TimeGuardConfig::default().tolerance_us / 1_000,
            resync_after_samples: TimeGuardConfig::default().resync_after,
        }
    }
}

impl Default for CheckpointConfig {
    fn default() -> Self {
        Self {
            path: PathBuf::from("out/component/checkpoint.bin"),
            period_s: 300,
            resume: false,
            on_config_mismatch: crate::sunaware_learner::OnConfigMismatch::Refuse,
        }
    }
}

impl Default for QueueConfig {
    fn default() -> Self {
        Self {
            frames: 4,
            pending_frames: 8,
            commands: 16,
            predictions: 8,
        }
    }
}

/// A configuration problem: the key (as written in the TOML file) and what is wrong.
#[derive(Debug)]
pub enum ConfigError {
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    Parse {
        path: PathBuf,
        message: String,
    },
    Invalid {
        key: &'static str,
        problem: String,
    },
    /// A `[cyphal]` key (its name is built from the port).
    Cyphal(CyphalConfigError),
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Read { path, error } => {
                write!(f, "cannot read config {}: {error}", path.display())
            }
            Self::Parse { path, message } => {
                write!(f, "config {} is not valid: {message}", path.display())
            }
            Self::Invalid { key, problem } => write!(f, "config key `{key}`: {problem}"),
            Self::Cyphal(CyphalConfigError { key, problem }) => {
                write!(f, "config key `{key}`: {problem}")
            }
        }
    }
}

impl std::error::Error for ConfigError {}

fn invalid(key: &'static str, problem: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key,
        problem: problem.into(),
    }
}

impl ComponentConfig {
    /// Parses TOML text (`origin` names it in errors) and validates it.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        let mut config: Self = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: e.to_string(),
        })?;
        // Registers written over the bus win over the file (Cyphal: values persist).
        crate::registers::apply_register_file(&mut config)?;
        config.validate()?;
        Ok(config)
    }

    /// Reads, parses and validates a config file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        Self::from_toml_str(&text, path)
    }

    /// The TOML text of this configuration.
    pub fn to_toml_string(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# cannot serialise: {e}\n"))
    }

    /// `[can] prediction_max_bytes`.
    fn validate_can_predictions(&self) -> Result<(), ConfigError> {
        let c = &self.can;
        if !(1..=MAX_PREDICTION_CAN_BYTES).contains(&c.prediction_max_bytes) {
            return Err(invalid(
                "can.prediction_max_bytes",
                format!(
                    "{} is not 1 to {MAX_PREDICTION_CAN_BYTES} bytes",
                    c.prediction_max_bytes
                ),
            ));
        }
        Ok(())
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.node.name.is_empty() || self.node.name.len() > 50 {
            return Err(invalid(
                "node.name",
                format!("{:?} must be 1 to 50 bytes", self.node.name),
            ));
        }
        if !self.node.unique_id.is_empty() && parse_unique_id(&self.node.unique_id).is_none() {
            return Err(invalid(
                "node.unique_id",
                format!("{:?} is not 32 hex digits", self.node.unique_id),
            ));
        }
        if self.node.node_id > MAX_NODE_ID {
            return Err(invalid(
                "node.node_id",
                format!(
                    "{} is above the Cyphal maximum {MAX_NODE_ID}",
                    self.node.node_id
                ),
            ));
        }
        let description_capacity = interfaces::cyphal::register::ValueKind::String.capacity();
        if self.node.description.len() > description_capacity {
            return Err(invalid(
                "node.description",
                format!("longer than {description_capacity} bytes"),
            ));
        }
        self.cyphal
            .validate(self.node.node_id)
            .map_err(ConfigError::Cyphal)?;
        let name = &self.can.interface;
        if name.is_empty()
            || name.len() > MAX_INTERFACE_NAME_BYTES
            || !name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b))
        {
            return Err(invalid(
                "can.interface",
                format!("{name:?} is not a network interface name (1-15 of [A-Za-z0-9_.-])"),
            ));
        }
        self.validate_can_predictions()?;
        if !self.can.enabled && !self.udp.enabled {
            return Err(invalid(
                "can.enabled",
                "both CAN and UDP are disabled: the component could not receive anything",
            ));
        }
        let u = &self.udp;
        if u.frames_port != 0 && u.frames_port == u.telemetry_port {
            return Err(invalid(
                "udp.telemetry_port",
                format!("same as udp.frames_port ({})", u.frames_port),
            ));
        }
        for (key, address) in [
            ("udp.predictions_to", u.predictions_to),
            ("udp.health_to", u.health_to),
        ] {
            if address.port() == 0 || address.ip().is_unspecified() {
                return Err(invalid(
                    key,
                    format!("{address} is not a destination (needs an address and a port)"),
                ));
            }
        }
        self.sync_config()?;
        self.time_guard_config()?;
        self.command_policy()?;
        self.camera_intrinsics()?;
        self.model.validate()?;
        self.window_config()?;
        self.variant()?;
        if !(1..=MAX_PASSES_PER_ROUND).contains(&self.training.passes_per_round) {
            return Err(invalid(
                "training.passes_per_round",
                format!("must be within 1..={MAX_PASSES_PER_ROUND}"),
            ));
        }
        if !ROUND_DEADLINE_MS_RANGE.contains(&self.training.round_deadline_ms) {
            return Err(invalid(
                "training.round_deadline_ms",
                format!("must be within {ROUND_DEADLINE_MS_RANGE:?}"),
            ));
        }
        if self.training.threads == 0 {
            return Err(invalid("training.threads", "must be at least 1"));
        }
        // The model first: whether the backend runs it is a property of the file, the
        // same in every build; whether this build has the backend comes after.
        // The model, and the replay memory beside it.
        self.online_config()?;
        self.backend()?;
        self.denormals()?;
        if self.checkpoint.path.as_os_str().is_empty() {
            return Err(invalid("checkpoint.path", "must not be empty"));
        }
        if self.checkpoint.path.file_name().is_none() {
            return Err(invalid(
                "checkpoint.path",
                format!("{} does not name a file", self.checkpoint.path.display()),
            ));
        }
        for (key, capacity) in [
            ("queues.frames", self.queues.frames),
            ("queues.pending_frames", self.queues.pending_frames),
            ("queues.commands", self.queues.commands),
            ("queues.predictions", self.queues.predictions),
        ] {
            if capacity == 0 {
                return Err(invalid(key, "queue capacity must be at least 1"));
            }
        }
        if self.sync.max_wait_ms > self.sync.stale_after_ms {
            return Err(invalid(
                "sync.max_wait_ms",
                format!(
                    "{} ms exceeds sync.stale_after_ms ({} ms): frames would wait for telemetry already stale",
                    self.sync.max_wait_ms, self.sync.stale_after_ms
                ),
            ));
        }
        Ok(())
    }

    /// Camera mounting as a unit quaternion (validated).
    pub fn camera_from_body(&self) -> Result<DQuat, ConfigError> {
        let [w, x, y, z] = self.camera.camera_from_body_wxyz;
        let q = DQuat::from_xyzw(x, y, z, w);
        let norm = q.length();
        if !q.is_finite() || (norm - 1.0).abs() > 1e-6 {
            return Err(invalid(
                "camera.camera_from_body_wxyz",
                format!("norm {norm} is not 1 (within 1e-6): not a rotation"),
            ));
        }
        Ok(q / norm)
    }

    /// The synchronizer settings this configuration describes.
    pub fn sync_config(&self) -> Result<SyncConfig, ConfigError> {
        let s = &self.sync;
        let sync = SyncConfig {
            buffer_capacity: s.buffer_capacity,
            max_gap_us: s.max_gap_ms.saturating_mul(1_000),
            stale_after_us: s.stale_after_ms.saturating_mul(1_000),
            unit_norm_tolerance: s.unit_norm_tolerance,
            min_pose_quality: s.min_pose_quality,
            camera_from_body: self.camera_from_body()?,
        };
        sync.validate().map_err(|e| {
            let key = match e {
                crate::sync::SyncConfigError::BufferTooSmall { .. } => "sync.buffer_capacity",
                crate::sync::SyncConfigError::ZeroMaxGap => "sync.max_gap_ms",
                crate::sync::SyncConfigError::BadTolerance { .. } => "sync.unit_norm_tolerance",
                crate::sync::SyncConfigError::BadMinPoseQuality { .. } => "sync.min_pose_quality",
                crate::sync::SyncConfigError::BadMounting { .. } => "camera.camera_from_body_wxyz",
            };
            invalid(key, e.to_string())
        })?;
        Ok(sync)
    }

    /// The telemetry time-tag guard this configuration describes.
    pub fn time_guard_config(&self) -> Result<TimeGuardConfig, ConfigError> {
        let guard = TimeGuardConfig {
            tolerance_us: self.sync.time_tag_tolerance_ms.saturating_mul(1_000),
            resync_after: self.sync.resync_after_samples,
        };
        guard.validate().map_err(|e| {
            let key = match e {
                crate::timeguard::TimeGuardConfigError::ZeroTolerance => {
                    "sync.time_tag_tolerance_ms"
                }
                crate::timeguard::TimeGuardConfigError::ResyncTooEager { .. } => {
                    "sync.resync_after_samples"
                }
            };
            invalid(key, e.to_string())
        })?;
        Ok(guard)
    }

    /// Who may command, arming and RENDER limits (`[commands]`).
    pub fn command_policy(&self) -> Result<CommandPolicy, ConfigError> {
        self.commands
            .policy()
            .map_err(|(key, problem)| invalid(key, problem))
    }

    /// The model configuration named by `training.variant`.
    pub fn variant(&self) -> Result<Variant, ConfigError> {
        self.training
            .variant
            .parse()
            .map_err(|e: SunAwareError| invalid("training.variant", e.to_string()))
    }

    /// The backend named by `training.backend`, checked against this build (`wgpu` needs
    /// the cargo feature). Whether an adapter exists is found when it is opened.
    pub fn backend(&self) -> Result<BackendKind, ConfigError> {
        let kind = self.backend_kind()?;
        kind.check_compiled_in(&crate::engines::device_engines())
            .map_err(|e| invalid("training.backend", e.to_string()))?;
        Ok(kind)
    }

    /// The backend named by `training.backend`, whether or not this build has it.
    fn backend_kind(&self) -> Result<BackendKind, ConfigError> {
        self.training
            .backend
            .parse()
            .map_err(|e: SunAwareError| invalid("training.backend", e.to_string()))
    }

    /// The trainer threads' denormal mode named by `training.denormals`.
    pub fn denormals(&self) -> Result<DenormalMode, ConfigError> {
        self.training
            .denormals
            .parse()
            .map_err(|e: String| invalid("training.denormals", e))
    }

    /// The Sun-aware model's settings: the variant and the `[training]` model keys over
    /// the trainer's defaults, each set by gs-core's [`SunAwareConfig::set_key`] (the
    /// model's own parsers; the simulator's presets go through it too) and checked by the
    /// model's validation one at a time, so the error names the key; then the light
    /// camera's resolution and the rates (gs-core's `RateOverrides`, as the presets'
    /// `[rates]`). Then the backend must
    /// run the model ([`BackendKind::check_model`]): checked here, when the file loads, not
    /// when the device opens.
    pub fn model_config(&self) -> Result<SunAwareConfig, ConfigError> {
        let t = &self.training;
        let mut model = SunAwareConfig {
            variant: self.variant()?,
            ..SunAwareConfig::default()
        };
        // In dependency order: `appearance_inputs = "local"` needs the learned normal.
        let keys = [
            (
                "training.appearance_hidden_width",
                ModelKey::AppearanceHiddenWidth(t.appearance_hidden_width),
            ),
            (
                "training.encoding_frequencies",
                ModelKey::EncodingFrequencies(t.encoding_frequencies),
            ),
            (
                "training.mlp_precision",
                ModelKey::MlpPrecision(&t.mlp_precision),
            ),
            ("training.shadow_gain", ModelKey::ShadowGain(t.shadow_gain)),
            ("training.shading", ModelKey::Shading(&t.shading)),
            (
                "training.appearance_inputs",
                ModelKey::AppearanceInputs(&t.appearance_inputs),
            ),
            (
                "training.colour_space",
                ModelKey::ColourSpace(&t.colour_space),
            ),
        ];
        for (name, key) in keys {
            model
                .set_key(key)
                .map_err(|e| invalid(name, e.to_string()))?;
        }
        // The light camera and the rates are part of the model too (checkpoints store them,
        // so a resume with other values is a model mismatch).
        model.light.resolution_px = t.light_resolution_px;
        model
            .validate()
            .map_err(|e| invalid("training.light_resolution_px", e.to_string()))?;
        t.rates
            .set_on(&mut model)
            .map_err(|e| invalid("training.rates", e.to_string()))?;
        self.backend_kind()?.check_model(&model).map_err(|why| {
            invalid(
                "training.backend",
                format!(
                    "backend = {:?} cannot train the model the [training] keys describe: \
                         {why}",
                    t.backend
                ),
            )
        })?;
        Ok(model)
    }

    /// The keyframe window settings this configuration describes.
    pub fn window_config(&self) -> Result<WindowConfig, ConfigError> {
        let window = WindowConfig {
            capacity: self.training.window_size,
            min_view_angle_deg: self.training.min_view_angle_deg,
        };
        KeyframeWindow::<()>::new(window).map_err(|e| {
            let key = match e {
                KeyframeError::CapacityTooSmall { .. } => "training.window_size",
                _ => "training.min_view_angle_deg",
            };
            invalid(key, e.to_string())
        })?;
        Ok(window)
    }
}

#[cfg(test)]
mod tests;
pub mod training;

pub use training::TrainingConfig;
