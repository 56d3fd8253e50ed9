//! The sections of a scenario file and their defaults (the paper's setup); every section
//! rejects unknown fields. Ranges are checked by `Scenario::validate`, not here.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

use crate::target::BuiltinTarget;

/// Chief (target) orbit, classical elements.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChiefOrbitConfig {
    pub semi_major_axis_km: f64,
    /// Must be small: the relative-motion map assumes a near-circular chief.
    pub eccentricity: f64,
    pub inclination_deg: f64,
    pub raan_deg: f64,
    pub arg_perigee_deg: f64,
    pub mean_anomaly_deg: f64,
}

impl Default for ChiefOrbitConfig {
    fn default() -> Self {
        ChiefOrbitConfig {
            semi_major_axis_km: 6948.3,
            eccentricity: 0.0,
            inclination_deg: 97.8,
            raan_deg: 60.0,
            arg_perigee_deg: 0.0,
            mean_anomaly_deg: 0.0,
        }
    }
}

/// Quasi-nonsingular ROE multiplied by the chief's semi-major axis, metres.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct RelativeOrbitConfig {
    pub da_m: f64,
    pub dl_m: f64,
    pub dex_m: f64,
    pub dey_m: f64,
    pub dix_m: f64,
    pub diy_m: f64,
}

/// Target attitude: initial orientation and a constant tumble.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AttitudeConfig {
    /// [w, x, y, z], rotation from the target body frame to ECI at the epoch.
    pub initial_quaternion: [f64; 4],
    /// Spin axis in the target body frame (normalised on load).
    pub tumble_axis: [f64; 3],
    pub tumble_rate_deg_s: f64,
}

impl Default for AttitudeConfig {
    fn default() -> Self {
        AttitudeConfig {
            // Body x (the spin axis) along ECI -z, perpendicular to the equinox Sun: the
            // tumble sweeps the Sun across the body (a spin axis along the Sun would not).
            initial_quaternion: [
                std::f64::consts::FRAC_1_SQRT_2,
                0.0,
                std::f64::consts::FRAC_1_SQRT_2,
                0.0,
            ],
            tumble_axis: [1.0, 0.0, 0.0],
            tumble_rate_deg_s: 2.0,
        }
    }
}

/// Full-resolution camera (SPEED by default) and the downsample factor applied to it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    pub focal_length_px: f64,
    pub width_px: u32,
    pub height_px: u32,
    /// Principal point in continuous pixel coordinates (pixel centres at +0.5); default: the
    /// image centre.
    pub principal_point_px: Option<[f64; 2]>,
    pub downsample: u32,
    /// [w, x, y, z], rotation from the camera frame to the servicer body frame.
    pub mounting_quaternion: [f64; 4],
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            // SPEED: f = 17.6 mm, pixel pitch 5.86 um.
            focal_length_px: 3003.41,
            width_px: 1920,
            height_px: 1200,
            principal_point_px: None,
            downsample: 2,
            mounting_quaternion: [1.0, 0.0, 0.0, 0.0],
        }
    }
}

/// The target model: one of the built-in procedural targets or an OBJ file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TargetConfig {
    pub builtin: Option<BuiltinTarget>,
    /// OBJ mesh; a relative path is taken relative to the scenario file's folder.
    pub obj: Option<PathBuf>,
    /// Points sampled on the surface for points.ply.
    pub surface_points: u32,
}

impl Default for TargetConfig {
    fn default() -> Self {
        TargetConfig {
            builtin: None,
            obj: None,
            surface_points: 10_000,
        }
    }
}

/// Which mesh a scenario uses, after resolving defaults and paths.
#[derive(Clone, Debug, PartialEq)]
pub enum TargetSource {
    Builtin(BuiltinTarget),
    Obj(PathBuf),
}

/// Image cadence and duration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SequenceConfig {
    pub cadence_s: f64,
    /// Duration in chief orbits (ignored when `frames` is set).
    pub orbits: f64,
    /// Number of frames; overrides `orbits`.
    pub frames: Option<u32>,
    /// Evaluation views written to eval/.
    pub eval_views: u32,
}

impl Default for SequenceConfig {
    fn default() -> Self {
        SequenceConfig {
            cadence_s: 5.0,
            orbits: 5.0,
            frames: None,
            eval_views: 100,
        }
    }
}

/// Ray-tracer settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    pub samples_per_pixel: u32,
    pub exposure: f64,
    /// Earth-albedo fill strength (fraction of the Sun's irradiance) under a fully lit Earth;
    /// 0 turns it off.
    pub earth_albedo: f64,
    /// Frames where less than this fraction of the Sun's disc is visible are eclipse frames.
    pub eclipse_below_sun_fraction: f64,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig {
            samples_per_pixel: 4,
            exposure: 1.0,
            earth_albedo: 0.3,
            eclipse_below_sun_fraction: 0.5,
        }
    }
}

/// Sensor noise applied to the telemetry only (images are always rendered from the truth).
/// Bias: a fixed rotation of the given angle about a seeded random axis (a fixed random offset
/// for positions); jitter: per-frame Gaussian, the value being the standard deviation per axis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseConfig {
    pub sun_bias_deg: f64,
    pub sun_jitter_deg: f64,
    pub attitude_bias_deg: f64,
    pub attitude_jitter_deg: f64,
    pub position_bias_m: f64,
    pub position_jitter_m: f64,
}
