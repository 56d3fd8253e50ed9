//! Scenario files (TOML): orbit, attitude, camera, target, cadence, noise.
//!
//! Every field has a default; an empty file is the paper's setup (LEO with a = 6948.3 km, so one
//! orbit lasts 5764 s; a frame every 5 s for 5 orbits = 5,764 frames; Cassini-like target
//! tumbling at 2 deg/s about body x; SPEED camera downsampled by 2; passively safe
//! e/i-separated relative orbit sized to the target). Unknown fields are errors, and
//! `Scenario::validate` checks every range, so a loaded `Scenario` is always usable:
//! invariants after `load`/`from_toml_str`: all numbers finite and in range, quaternions unit.
//!
//! Files: this one (the scenario, its errors, loading and the derived quantities),
//! `sections` (the file's sections and their defaults), `validate` (the range checks),
//! `geometry` (the relative orbit and the rendezvous geometry for a target's size).

use crate::orbit::{KeplerElements, UtcEpoch};
use crate::target::BuiltinTarget;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

mod geometry;
mod sections;
#[cfg(test)]
mod tests;
mod validate;

pub use geometry::{TargetSize, AUTO_FILL_OF_HALF_FOV};
pub use sections::{
    AttitudeConfig, CameraConfig, ChiefOrbitConfig, NoiseConfig, RelativeOrbitConfig, RenderConfig,
    SequenceConfig, TargetConfig, TargetSource,
};

/// Why a scenario could not be loaded.
#[derive(Debug)]
pub enum ScenarioError {
    Io {
        path: PathBuf,
        message: String,
    },
    /// TOML syntax, unknown field or wrong type (the message names the line and field).
    Parse {
        source_name: String,
        message: String,
    },
    /// A value outside its allowed range.
    Invalid {
        field: String,
        message: String,
    },
}

impl fmt::Display for ScenarioError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ScenarioError::Io { path, message } => {
                write!(f, "cannot read scenario {}: {message}", path.display())
            }
            ScenarioError::Parse {
                source_name,
                message,
            } => write!(f, "malformed scenario {source_name}: {message}"),
            ScenarioError::Invalid { field, message } => {
                write!(f, "invalid scenario value `{field}`: {message}")
            }
        }
    }
}

impl std::error::Error for ScenarioError {}

fn invalid(field: &str, message: impl Into<String>) -> ScenarioError {
    ScenarioError::Invalid {
        field: field.to_string(),
        message: message.into(),
    }
}

/// A complete scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    pub seed: u64,
    /// UTC epoch of the first frame, a TOML offset date-time with a `Z` suffix.
    pub epoch: toml::value::Datetime,
    pub chief_orbit: ChiefOrbitConfig,
    /// Omitted: a passively safe e/i-separated orbit sized so the target fills the frame.
    pub relative_orbit: Option<RelativeOrbitConfig>,
    pub attitude: AttitudeConfig,
    pub camera: CameraConfig,
    pub target: TargetConfig,
    pub sequence: SequenceConfig,
    pub render: RenderConfig,
    pub noise: NoiseConfig,
    /// Folder relative OBJ paths are resolved against (the scenario file's folder).
    #[serde(skip)]
    pub base_dir: PathBuf,
}

impl Default for Scenario {
    fn default() -> Self {
        Scenario {
            name: "paper-default".to_string(),
            seed: 1,
            epoch: "2024-03-20T12:00:00Z"
                .parse()
                .expect("valid literal datetime"),
            chief_orbit: ChiefOrbitConfig::default(),
            relative_orbit: None,
            attitude: AttitudeConfig::default(),
            camera: CameraConfig::default(),
            target: TargetConfig::default(),
            sequence: SequenceConfig::default(),
            render: RenderConfig::default(),
            noise: NoiseConfig::default(),
            base_dir: PathBuf::from("."),
        }
    }
}

/// Downsampled pinhole intrinsics in pixels (pixel centres at +0.5).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub(crate) struct CameraIntrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl CameraIntrinsics {
    /// Half of the smaller field of view (the vertical one for a landscape sensor), radians.
    pub(crate) fn min_half_fov_rad(&self) -> f64 {
        let half_h = (self.width as f64 / 2.0 / self.fx).atan();
        let half_v = (self.height as f64 / 2.0 / self.fy).atan();
        half_h.min(half_v)
    }
}

impl Scenario {
    /// Reads, parses and validates a scenario file.
    pub fn load(path: &Path) -> Result<Scenario, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|e| ScenarioError::Io {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        let base_dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
        let mut scenario = Scenario::parse(&text, &path.display().to_string(), base_dir)?;
        if scenario.name.is_empty() || scenario.name == Scenario::default().name {
            if let Some(stem) = path.file_stem() {
                scenario.name = stem.to_string_lossy().into_owned();
            }
        }
        Ok(scenario)
    }

    /// Parses and validates scenario text; relative OBJ paths resolve against `base_dir`.
    pub fn from_toml_str(text: &str, base_dir: &Path) -> Result<Scenario, ScenarioError> {
        Scenario::parse(text, "<text>", base_dir.to_path_buf())
    }

    fn parse(text: &str, source_name: &str, base_dir: PathBuf) -> Result<Scenario, ScenarioError> {
        let mut scenario: Scenario = toml::from_str(text).map_err(|e| ScenarioError::Parse {
            source_name: source_name.to_string(),
            message: e.to_string(),
        })?;
        scenario.base_dir = base_dir;
        scenario.validate()?;
        Ok(scenario)
    }

    /// Applies command-line overrides and re-validates.
    pub fn with_overrides(
        mut self,
        frames: Option<u32>,
        downsample: Option<u32>,
        eval_views: Option<u32>,
    ) -> Result<Scenario, ScenarioError> {
        if frames.is_some() {
            self.sequence.frames = frames;
        }
        if let Some(k) = downsample {
            self.camera.downsample = k;
        }
        if let Some(n) = eval_views {
            self.sequence.eval_views = n;
        }
        self.validate()?;
        Ok(self)
    }

    /// The epoch as a calendar instant; must be a full UTC date-time.
    pub(crate) fn utc_epoch(&self) -> Result<UtcEpoch, ScenarioError> {
        let (Some(date), Some(time)) = (self.epoch.date, self.epoch.time) else {
            return Err(invalid(
                "epoch",
                format!(
                    "{} needs a date and a time, e.g. 2024-03-20T12:00:00Z",
                    self.epoch
                ),
            ));
        };
        match self.epoch.offset {
            Some(toml::value::Offset::Z | toml::value::Offset::Custom { minutes: 0 }) => {}
            _ => {
                return Err(invalid(
                    "epoch",
                    format!("{} must be UTC: end it with Z", self.epoch),
                ));
            }
        }
        let second = time.second.unwrap_or(0) as f64 + time.nanosecond.unwrap_or(0) as f64 * 1e-9;
        UtcEpoch::new(
            date.year as i32,
            date.month as u32,
            date.day as u32,
            time.hour as u32,
            time.minute as u32,
            second,
        )
        .map_err(|e| invalid("epoch", e.0))
    }

    /// The mesh source; the default is the Cassini-like target.
    pub(crate) fn target_source(&self) -> Result<TargetSource, ScenarioError> {
        match (&self.target.builtin, &self.target.obj) {
            (Some(_), Some(_)) => Err(invalid("target", "set either `builtin` or `obj`, not both")),
            (Some(kind), None) => Ok(TargetSource::Builtin(*kind)),
            (None, Some(path)) => Ok(TargetSource::Obj(self.base_dir.join(path))),
            (None, None) => Ok(TargetSource::Builtin(BuiltinTarget::Cassini)),
        }
    }

    pub(crate) fn chief_elements(&self) -> KeplerElements {
        let o = &self.chief_orbit;
        KeplerElements {
            semi_major_axis_m: o.semi_major_axis_km * 1000.0,
            eccentricity: o.eccentricity,
            inclination_rad: o.inclination_deg.to_radians(),
            raan_rad: o.raan_deg.to_radians(),
            arg_perigee_rad: o.arg_perigee_deg.to_radians(),
            mean_anomaly_rad: o.mean_anomaly_deg.to_radians(),
        }
    }

    /// Number of frames: `sequence.frames`, else whole cadences within `orbits` chief orbits.
    pub fn frame_count(&self) -> u32 {
        if let Some(frames) = self.sequence.frames {
            return frames;
        }
        let duration_s = self.sequence.orbits * self.chief_elements().period_s();
        // A tiny tolerance so 5 orbits of exactly 5 x 1152.8 cadences do not lose a frame.
        (duration_s / self.sequence.cadence_s + 1e-9)
            .floor()
            .min(10_000_000.0) as u32
    }

    /// Time of frame `index` after the epoch, seconds.
    pub(crate) fn frame_time_s(&self, index: u32) -> f64 {
        index as f64 * self.sequence.cadence_s
    }

    /// Intrinsics after downsampling (pixel-centre convention keeps cx = W/2 at the centre).
    pub(crate) fn camera_intrinsics(&self) -> CameraIntrinsics {
        let c = &self.camera;
        let k = c.downsample as f64;
        let [cx, cy] = c
            .principal_point_px
            .unwrap_or([c.width_px as f64 / 2.0, c.height_px as f64 / 2.0]);
        CameraIntrinsics {
            fx: c.focal_length_px / k,
            fy: c.focal_length_px / k,
            cx: cx / k,
            cy: cy / k,
            width: c.width_px / c.downsample,
            height: c.height_px / c.downsample,
        }
    }
}
