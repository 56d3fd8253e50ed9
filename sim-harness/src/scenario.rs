//! Scenario files (TOML): orbit, attitude, camera, target, cadence, noise.
//!
//! Every field has a default; an empty file is the paper's setup (LEO with a = 6948.3 km, so one
//! orbit lasts 5764 s; a frame every 5 s for 5 orbits = 5,764 frames; Cassini-like target
//! tumbling at 2 deg/s about body x; SPEED camera downsampled by 2; passively safe
//! e/i-separated relative orbit sized to the target). Unknown fields are errors, and
//! `Scenario::validate` checks every range, so a loaded `Scenario` is always usable:
//! invariants after `load`/`from_toml_str`: all numbers finite and in range, quaternions unit.

use crate::orbit::{KeplerElements, RendezvousGeometry, Roe, TumbleAttitude, UtcEpoch};
use crate::target::BuiltinTarget;
use glam::{DQuat, DVec3};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};

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
pub struct CameraIntrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl CameraIntrinsics {
    /// Half of the smaller field of view (the vertical one for a landscape sensor), radians.
    pub fn min_half_fov_rad(&self) -> f64 {
        let half_h = (self.width as f64 / 2.0 / self.fx).atan();
        let half_v = (self.height as f64 / 2.0 / self.fy).atan();
        half_h.min(half_v)
    }
}

/// Closest-approach range of the automatic e/i-separated orbit is chosen so a sphere of the
/// target's framing radius (see `TargetSize`) spans this fraction of the smaller half field of
/// view: 1.0 = it just fits the frame height. The range then grows to 2.24 times that.
pub const AUTO_FILL_OF_HALF_FOV: f64 = 1.0;
/// The automatic orbit's relative e and i vectors point along +y or -y (phase +-90 deg: radial
/// and normal motion in quadrature, the largest along-track offset at the ascending node);
/// of the two, the one that starts with the servicer on the sunlit side is used.
const AUTO_EI_PHASES_RAD: [f64; 2] = [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2];

fn check_finite(field: &str, value: f64) -> Result<(), ScenarioError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(invalid(field, format!("{value} is not a finite number")))
    }
}

fn check_range(field: &str, value: f64, lo: f64, hi: f64) -> Result<(), ScenarioError> {
    check_finite(field, value)?;
    if value < lo || value > hi {
        return Err(invalid(field, format!("{value} is outside [{lo}, {hi}]")));
    }
    Ok(())
}

fn unit_quaternion(field: &str, wxyz: [f64; 4]) -> Result<DQuat, ScenarioError> {
    let q = DQuat::from_xyzw(wxyz[1], wxyz[2], wxyz[3], wxyz[0]);
    if !q.is_finite() || (q.length() - 1.0).abs() > 1e-3 {
        return Err(invalid(
            field,
            format!(
                "{wxyz:?} is not a unit quaternion [w, x, y, z] (norm {})",
                q.length()
            ),
        ));
    }
    Ok(q.normalize())
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

    /// Checks every value's range; see the module header.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        self.utc_epoch()?;
        let o = &self.chief_orbit;
        let earth_radius_km = crate::orbit::EARTH_RADIUS_M / 1000.0;
        check_range(
            "chief_orbit.semi_major_axis_km",
            o.semi_major_axis_km,
            earth_radius_km + 150.0,
            50_000.0,
        )?;
        check_range("chief_orbit.eccentricity", o.eccentricity, 0.0, 0.01)?;
        if o.semi_major_axis_km * (1.0 - o.eccentricity) < earth_radius_km + 150.0 {
            return Err(invalid(
                "chief_orbit.eccentricity",
                "perigee below 150 km altitude",
            ));
        }
        // The y component of the relative inclination vector divides by sin(i).
        check_range("chief_orbit.inclination_deg", o.inclination_deg, 1.0, 179.0)?;
        check_finite("chief_orbit.raan_deg", o.raan_deg)?;
        check_finite("chief_orbit.arg_perigee_deg", o.arg_perigee_deg)?;
        check_finite("chief_orbit.mean_anomaly_deg", o.mean_anomaly_deg)?;
        if let Some(r) = &self.relative_orbit {
            let names = ["da_m", "dl_m", "dex_m", "dey_m", "dix_m", "diy_m"];
            let values = [r.da_m, r.dl_m, r.dex_m, r.dey_m, r.dix_m, r.diy_m];
            for (name, value) in names.iter().zip(values) {
                // The linear map's error grows as separation^2 / a: 10 km gives ~10 m.
                check_range(
                    &format!("relative_orbit.{name}"),
                    value,
                    -10_000.0,
                    10_000.0,
                )?;
            }
        }
        let a = &self.attitude;
        unit_quaternion("attitude.initial_quaternion", a.initial_quaternion)?;
        let axis = DVec3::from_array(a.tumble_axis);
        if !axis.is_finite() || axis.length() < 1e-9 {
            return Err(invalid(
                "attitude.tumble_axis",
                format!("{:?} is not a usable axis", a.tumble_axis),
            ));
        }
        check_range(
            "attitude.tumble_rate_deg_s",
            a.tumble_rate_deg_s,
            -180.0,
            180.0,
        )?;
        let c = &self.camera;
        check_range("camera.focal_length_px", c.focal_length_px, 1.0, 1e6)?;
        for (field, value) in [
            ("camera.width_px", c.width_px),
            ("camera.height_px", c.height_px),
        ] {
            if !(8..=crate::raytrace::MAX_IMAGE_SIDE).contains(&value) {
                return Err(invalid(
                    field,
                    format!(
                        "{value} is outside [8, {}]",
                        crate::raytrace::MAX_IMAGE_SIDE
                    ),
                ));
            }
        }
        if c.downsample == 0 || c.width_px / c.downsample < 8 || c.height_px / c.downsample < 8 {
            return Err(invalid(
                "camera.downsample",
                format!(
                    "{} must be >= 1 and leave an image of at least 8x8 pixels",
                    c.downsample
                ),
            ));
        }
        if let Some([cx, cy]) = c.principal_point_px {
            check_range("camera.principal_point_px[0]", cx, 0.0, c.width_px as f64)?;
            check_range("camera.principal_point_px[1]", cy, 0.0, c.height_px as f64)?;
        }
        unit_quaternion("camera.mounting_quaternion", c.mounting_quaternion)?;
        self.target_source()?;
        if !(1..=10_000_000).contains(&self.target.surface_points) {
            return Err(invalid(
                "target.surface_points",
                format!("{} is outside [1, 10000000]", self.target.surface_points),
            ));
        }
        let s = &self.sequence;
        check_range("sequence.cadence_s", s.cadence_s, 0.001, 86_400.0)?;
        check_range("sequence.orbits", s.orbits, 0.0, 1000.0)?;
        if let Some(frames) = s.frames {
            if !(1..=10_000_000).contains(&frames) {
                return Err(invalid(
                    "sequence.frames",
                    format!("{frames} is outside [1, 10000000]"),
                ));
            }
        } else if self.frame_count() == 0 {
            return Err(invalid(
                "sequence.orbits",
                "the duration is shorter than one cadence: no frames",
            ));
        }
        if s.eval_views > 100_000 {
            return Err(invalid(
                "sequence.eval_views",
                format!("{} is above 100000", s.eval_views),
            ));
        }
        let r = &self.render;
        if !(1..=crate::raytrace::MAX_SAMPLES_PER_PIXEL).contains(&r.samples_per_pixel) {
            return Err(invalid(
                "render.samples_per_pixel",
                format!(
                    "{} is outside [1, {}]",
                    r.samples_per_pixel,
                    crate::raytrace::MAX_SAMPLES_PER_PIXEL
                ),
            ));
        }
        check_range("render.exposure", r.exposure, 0.0, 1e6)?;
        check_range("render.earth_albedo", r.earth_albedo, 0.0, 1.0)?;
        check_range(
            "render.eclipse_below_sun_fraction",
            r.eclipse_below_sun_fraction,
            0.0,
            1.0,
        )?;
        let n = &self.noise;
        check_range("noise.sun_bias_deg", n.sun_bias_deg, 0.0, 45.0)?;
        check_range("noise.sun_jitter_deg", n.sun_jitter_deg, 0.0, 45.0)?;
        check_range("noise.attitude_bias_deg", n.attitude_bias_deg, 0.0, 45.0)?;
        check_range(
            "noise.attitude_jitter_deg",
            n.attitude_jitter_deg,
            0.0,
            45.0,
        )?;
        check_range("noise.position_bias_m", n.position_bias_m, 0.0, 1000.0)?;
        check_range("noise.position_jitter_m", n.position_jitter_m, 0.0, 1000.0)?;
        Ok(())
    }

    /// The epoch as a calendar instant; must be a full UTC date-time.
    pub fn utc_epoch(&self) -> Result<UtcEpoch, ScenarioError> {
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
            Some(toml::value::Offset::Z) | Some(toml::value::Offset::Custom { minutes: 0 }) => {}
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
    pub fn target_source(&self) -> Result<TargetSource, ScenarioError> {
        match (&self.target.builtin, &self.target.obj) {
            (Some(_), Some(_)) => Err(invalid("target", "set either `builtin` or `obj`, not both")),
            (Some(kind), None) => Ok(TargetSource::Builtin(*kind)),
            (None, Some(path)) => Ok(TargetSource::Obj(self.base_dir.join(path))),
            (None, None) => Ok(TargetSource::Builtin(BuiltinTarget::Cassini)),
        }
    }

    pub fn chief_elements(&self) -> KeplerElements {
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
    pub fn frame_time_s(&self, index: u32) -> f64 {
        index as f64 * self.sequence.cadence_s
    }

    /// Intrinsics after downsampling (pixel-centre convention keeps cx = W/2 at the centre).
    pub fn camera_intrinsics(&self) -> CameraIntrinsics {
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

    /// The relative orbit: the configured one, or the automatic e/i-separated one (at e/i phase
    /// `auto_phase_rad`) whose closest approach lets a sphere of the target's framing radius
    /// fill `AUTO_FILL_OF_HALF_FOV` of the smaller half field of view.
    pub fn roe(&self, target: TargetSize, auto_phase_rad: f64) -> Roe {
        let a = self.chief_orbit.semi_major_axis_km * 1000.0;
        match &self.relative_orbit {
            Some(r) => Roe::from_scaled_m([r.da_m, r.dl_m, r.dex_m, r.dey_m, r.dix_m, r.diy_m], a),
            None => {
                let half_fov = self.camera_intrinsics().min_half_fov_rad();
                let separation_m =
                    target.framing_radius_m / (AUTO_FILL_OF_HALF_FOV * half_fov).tan();
                Roe::e_i_separated(separation_m, auto_phase_rad, a)
            }
        }
    }

    /// All geometry of the scenario for a target of the given size. Fails when the servicer
    /// would come closer than 1.5 bounding radii to the target's centre.
    pub fn geometry(&self, target: TargetSize) -> Result<RendezvousGeometry, ScenarioError> {
        let a = &self.attitude;
        let axis = DVec3::from_array(a.tumble_axis).normalize();
        let geometry = RendezvousGeometry {
            epoch: self.utc_epoch()?,
            chief: self.chief_elements(),
            roe: self.roe(target, AUTO_EI_PHASES_RAD[0]),
            target_attitude: TumbleAttitude {
                q_inertial_from_body_at_epoch: unit_quaternion(
                    "attitude.initial_quaternion",
                    a.initial_quaternion,
                )?,
                axis_body: axis,
                rate_rad_s: a.tumble_rate_deg_s.to_radians(),
            },
            q_body_from_camera: unit_quaternion(
                "camera.mounting_quaternion",
                self.camera.mounting_quaternion,
            )?,
            earth_albedo_strength: self.render.earth_albedo,
            eclipse_below_sun_fraction: self.render.eclipse_below_sun_fraction,
        };
        // Automatic orbit: start on the sunlit side (smaller Sun phase angle at the first frame),
        // so short runs do not begin with a backlit target.
        let geometry = if self.relative_orbit.is_none() {
            let flipped = RendezvousGeometry {
                roe: self.roe(target, AUTO_EI_PHASES_RAD[1]),
                ..geometry
            };
            if flipped.at(0.0).phase_angle_rad < geometry.at(0.0).phase_angle_rad {
                flipped
            } else {
                geometry
            }
        } else {
            geometry
        };
        // The relative orbit is periodic up to the along-track drift: check one orbit and the
        // whole run, sampled finely enough (at most 0.5 deg of orbit between samples).
        let duration_s =
            (self.frame_count() as f64 * self.sequence.cadence_s).max(geometry.chief.period_s());
        let samples = ((duration_s / geometry.chief.period_s()) * 720.0)
            .ceil()
            .min(1e6) as u32;
        let closest_m = (0..=samples)
            .map(|i| {
                geometry
                    .servicer_rtn_m(duration_s * i as f64 / samples as f64)
                    .length()
            })
            .fold(f64::INFINITY, f64::min);
        let keep_out_m = 1.5 * target.bounding_radius_m;
        if closest_m < keep_out_m {
            return Err(invalid(
                "relative_orbit",
                format!(
                    "the servicer comes within {closest_m:.2} m of the target centre, inside 1.5 x \
                     its bounding radius ({:.2} m)",
                    target.bounding_radius_m
                ),
            ));
        }
        Ok(geometry)
    }
}

/// Size of the target mesh, for sizing and checking the relative orbit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TargetSize {
    /// Largest vertex distance from the body origin, metres.
    pub bounding_radius_m: f64,
    /// Radius holding most of the surface (the dataset uses the 90th percentile of the surface
    /// samples' distances): thin booms do not shrink the target in the frame.
    pub framing_radius_m: f64,
}

impl TargetSize {
    /// A target whose surface fills its bounding sphere.
    pub fn sphere(radius_m: f64) -> TargetSize {
        TargetSize {
            bounding_radius_m: radius_m,
            framing_radius_m: radius_m,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_is_the_paper_setup() {
        let s = Scenario::from_toml_str("", Path::new(".")).unwrap();
        assert_eq!(s.frame_count(), 5764);
        let period = s.chief_elements().period_s();
        assert!((period - 5764.0).abs() < 1.0, "period {period}");
        let cam = s.camera_intrinsics();
        assert_eq!((cam.width, cam.height), (960, 600));
        assert!((cam.fx - 1501.705).abs() < 1e-9 && cam.cx == 480.0 && cam.cy == 300.0);
        assert_eq!(
            s.target_source().unwrap(),
            TargetSource::Builtin(BuiltinTarget::Cassini)
        );
        assert_eq!(s.attitude.tumble_rate_deg_s, 2.0);
    }

    #[test]
    fn unknown_fields_and_bad_values_are_named() {
        let err = Scenario::from_toml_str("[camera]\nfocal_lenght_px = 3.0\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.contains("focal_lenght_px"), "{err}");
        let err = Scenario::from_toml_str("[target]\nbuiltin = \"hubble\"\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.contains("hubble"), "{err}");
        let err = Scenario::from_toml_str("[sequence]\ncadence_s = -1.0\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("sequence.cadence_s") && err.contains("-1"),
            "{err}"
        );
        let err = Scenario::from_toml_str("[chief_orbit]\ninclination_deg = 0.0\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.contains("inclination_deg"), "{err}");
        let err = Scenario::from_toml_str("epoch = 2024-03-20T12:00:00\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.contains("epoch") && err.contains("UTC"), "{err}");
        let err = Scenario::from_toml_str(
            "[attitude]\ninitial_quaternion = [1.0, 1.0, 0.0, 0.0]\n",
            Path::new("."),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("unit quaternion"), "{err}");
        let err = Scenario::from_toml_str(
            "[target]\nbuiltin = \"rosetta\"\nobj = \"x.obj\"\n",
            Path::new("."),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("not both"), "{err}");
        let err = Scenario::from_toml_str("[camera]\ndownsample = 0\n", Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.contains("camera.downsample"), "{err}");
    }

    #[test]
    fn overrides_shorten_and_downsample() {
        let s = Scenario::from_toml_str("", Path::new("."))
            .unwrap()
            .with_overrides(Some(12), Some(8), Some(3))
            .unwrap();
        assert_eq!(s.frame_count(), 12);
        assert_eq!(s.sequence.eval_views, 3);
        let cam = s.camera_intrinsics();
        assert_eq!((cam.width, cam.height), (240, 150));
        assert!((cam.fx - 3003.41 / 8.0).abs() < 1e-9);
        assert!(Scenario::default()
            .with_overrides(None, Some(1000), None)
            .is_err());
    }

    #[test]
    fn automatic_relative_orbit_frames_the_target_and_is_safe() {
        let s = Scenario::default();
        let radius_m = 6.0;
        let geometry = s.geometry(TargetSize::sphere(radius_m)).unwrap();
        let a = s.chief_orbit.semi_major_axis_km * 1000.0;
        let min_rn = geometry.roe.min_radial_normal_separation_m(a);
        let half_fov = s.camera_intrinsics().min_half_fov_rad();
        // At the closest approach (radial-normal minimum, zero along-track) the bounding sphere
        // just fits the smaller field of view.
        assert!(((radius_m / min_rn).atan() - half_fov).abs() < 1e-9);
        let ranges: Vec<f64> = (0..1200)
            .map(|i| geometry.servicer_rtn_m(i as f64 * 5.0).length())
            .collect();
        let closest = ranges.iter().cloned().fold(f64::INFINITY, f64::min);
        let farthest = ranges.iter().cloned().fold(0.0, f64::max);
        assert!(
            (closest - min_rn).abs() < 0.05 && farthest < 2.25 * min_rn,
            "{closest} {farthest}"
        );
    }

    #[test]
    fn automatic_relative_orbit_starts_on_the_sunlit_side() {
        for raan_deg in [0.0, 60.0, 150.0, 240.0, 330.0] {
            let mut s = Scenario::default();
            s.chief_orbit.raan_deg = raan_deg;
            let geometry = s.geometry(TargetSize::sphere(3.0)).unwrap();
            let phase_deg = geometry.at(0.0).phase_angle_rad.to_degrees();
            assert!(
                phase_deg < 90.0,
                "RAAN {raan_deg}: starts {phase_deg} deg from the Sun"
            );
            // A configured orbit is used as given, even when backlit.
            let roe_m = geometry
                .roe
                .scaled_m(s.chief_orbit.semi_major_axis_km * 1000.0);
            s.relative_orbit = Some(RelativeOrbitConfig {
                dey_m: -roe_m[3],
                diy_m: -roe_m[5],
                ..RelativeOrbitConfig::default()
            });
            let mirrored = s.geometry(TargetSize::sphere(3.0)).unwrap();
            let mirrored_deg = mirrored.at(0.0).phase_angle_rad.to_degrees();
            assert!(
                (mirrored_deg - (180.0 - phase_deg)).abs() < 0.5,
                "{mirrored_deg}"
            );
        }
    }

    #[test]
    fn a_relative_orbit_through_the_target_is_rejected() {
        // e/i-separated by 3 m: the servicer flies 3..6.7 m from the centre of a 5 m target.
        let s = Scenario::from_toml_str(
            "[relative_orbit]\ndey_m = 3.0\ndiy_m = 3.0\n",
            Path::new("."),
        )
        .unwrap();
        let err = s.geometry(TargetSize::sphere(5.0)).unwrap_err().to_string();
        assert!(
            err.contains("relative_orbit") && err.contains("3.00 m"),
            "{err}"
        );
        // The same orbit is fine around a 1 m target; only the bounding radius matters here.
        let long_boom = TargetSize {
            bounding_radius_m: 5.0,
            framing_radius_m: 1.0,
        };
        assert!(s.geometry(long_boom).is_err());
        assert!(s.geometry(TargetSize::sphere(1.0)).is_ok());
    }
}
