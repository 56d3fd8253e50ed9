//! Dataset writer: frames, masks, depth, telemetry, evaluation views, points, plots.
//!
//! Layout written by `generate` under the output folder:
//! - `frames/NNNNNN.png` 8-bit sRGB, `masks/NNNNNN.png` 8-bit grey (255 = target),
//!   `depth/NNNNNN.npy` float32 camera-z depth in metres, shape (height, width), +inf where
//!   no surface (NumPy `.npy` v1.0, little-endian: `numpy.load` reads it);
//! - `telemetry.jsonl`: one JSON object per frame (see `TelemetryLine`);
//! - `eval/` with the same four items for random evaluation views;
//! - `points.ply` (binary little-endian, x y z nx ny nz red green blue);
//! - `contact_sheet.png`, `trajectory.png`.
//!
//! Invariants: output bytes depend only on the scenario (seeded RNGs, renderer deterministic
//! for any thread count, fixed-format writers), so the same scenario gives byte-identical
//! folders. Images always come from the truth; sensor noise touches the telemetry only.

pub mod eval;
pub mod files;
pub mod noise;
pub mod plots;

use crate::orbit::{FrameGeometry, RtnFrame};
use crate::raytrace::{try_render_frame, EarthFill, Frame, FrameRequest, PinholeCamera, Scene};
use crate::scenario::{CameraIntrinsics, Scenario, ScenarioError, TargetSize, TargetSource};
use crate::target::{builtin_target, load_obj, TargetError, TargetMesh};
use glam::{DQuat, DVec3, Vec3};
use gs_core::rng::mix64;
use serde::Serialize;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Why a dataset could not be written.
#[derive(Debug)]
pub enum DatasetError {
    Scenario(ScenarioError),
    Target(TargetError),
    Render { what: String, message: String },
    Io { path: PathBuf, message: String },
    OutputNotEmpty(PathBuf),
}

impl fmt::Display for DatasetError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DatasetError::Scenario(e) => write!(f, "{e}"),
            DatasetError::Target(e) => write!(f, "target: {e}"),
            DatasetError::Render { what, message } => write!(f, "cannot render {what}: {message}"),
            DatasetError::Io { path, message } => {
                write!(f, "cannot write {}: {message}", path.display())
            }
            DatasetError::OutputNotEmpty(path) => write!(
                f,
                "output folder {} is not empty (choose a new folder or pass --overwrite)",
                path.display()
            ),
        }
    }
}

impl std::error::Error for DatasetError {}

impl From<ScenarioError> for DatasetError {
    fn from(e: ScenarioError) -> Self {
        DatasetError::Scenario(e)
    }
}

impl From<TargetError> for DatasetError {
    fn from(e: TargetError) -> Self {
        DatasetError::Target(e)
    }
}

/// Options that do not change what is written.
#[derive(Clone, Copy, Debug, Default)]
pub struct GenerateOptions {
    /// Write into a non-empty folder (files of the same name are replaced, others kept).
    pub overwrite: bool,
}

/// What `generate` did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GenerateSummary {
    pub frames: u32,
    pub eclipse_frames: u32,
    pub eval_views: u32,
    pub min_range_m: f64,
    pub max_range_m: f64,
    pub target_bounding_radius_m: f64,
    pub target_framing_radius_m: f64,
    pub target_triangles: usize,
    /// a * (da, dl, dex, dey, dix, diy) actually used, metres.
    pub roe_scaled_m: [f64; 6],
    pub surface_points: usize,
}

/// Ground truth for a telemetry line.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub(crate) struct TruthRecord {
    pub q_camera_from_target_wxyz: [f64; 4],
    pub t_camera_from_target_m: [f64; 3],
    pub sun_servicer_body: [f64; 3],
    pub sun_target_body: [f64; 3],
    pub sun_visible_fraction: f64,
    pub earth_dir_target_body: [f64; 3],
    pub earth_fill_strength: f64,
    pub range_m: f64,
    pub phase_angle_deg: f64,
    /// Servicer position in the chief RTN frame (sequence frames only).
    pub servicer_rtn_m: Option<[f64; 3]>,
}

/// One line of telemetry.jsonl. Top-level pose and Sun vectors are what the sensors report
/// (with the scenario's noise); `truth` holds the exact values the image was rendered with.
/// Quaternions are [w, x, y, z] with w >= 0; x_camera = R(q) x_target + t (OpenCV axes).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub(crate) struct TelemetryLine {
    pub index: u32,
    /// Seconds since the scenario epoch (null for evaluation views).
    pub time_s: Option<f64>,
    pub utc: Option<String>,
    pub frame: String,
    pub mask: String,
    pub depth: String,
    pub q_camera_from_target_wxyz: [f64; 4],
    pub t_camera_from_target_m: [f64; 3],
    pub sun_servicer_body: [f64; 3],
    pub sun_target_body: [f64; 3],
    pub eclipse: bool,
    pub intrinsics: CameraIntrinsics,
    pub truth: TruthRecord,
}

/// [w, x, y, z] with a non-negative scalar part (q and -q are the same rotation).
pub(crate) fn wxyz(q: DQuat) -> [f64; 4] {
    let q = if q.w < 0.0 { -q } else { q };
    [q.w, q.x, q.y, q.z]
}

/// Loads the scenario's target mesh (built-in or OBJ), the one the dataset renders.
pub fn load_target(scenario: &Scenario) -> Result<TargetMesh, DatasetError> {
    Ok(match scenario.target_source()? {
        TargetSource::Builtin(kind) => builtin_target(kind),
        TargetSource::Obj(path) => load_obj(&path)?,
    })
}

fn pinhole(c: &CameraIntrinsics) -> PinholeCamera {
    PinholeCamera {
        fx: c.fx as f32,
        fy: c.fy as f32,
        cx: c.cx as f32,
        cy: c.cy as f32,
        width: c.width,
        height: c.height,
    }
}

fn unit_f32(v: DVec3) -> Vec3 {
    v.as_vec3().normalize()
}

/// The render request for a frame geometry. In the penumbra (part of the Sun's disc hidden,
/// not flagged as eclipse) the Sun is dimmed by the visible fraction f: the renderer has one
/// exposure for all lights, so exposure is scaled by f and the Earth fill by 1/f, which leaves
/// the fill's contribution unchanged.
pub(crate) fn frame_request(scenario: &Scenario, g: &FrameGeometry, seed: u64) -> FrameRequest {
    let sun_scale = if g.eclipse {
        1.0
    } else {
        g.sun_visible_fraction.clamp(1e-3, 1.0)
    };
    let earth_albedo = (g.earth_fill_strength > 0.0).then(|| EarthFill {
        dir_target: unit_f32(g.earth_dir_target),
        strength: (g.earth_fill_strength / sun_scale) as f32,
    });
    FrameRequest {
        camera: pinhole(&scenario.camera_intrinsics()),
        camera_from_target_rotation: g.q_camera_from_target.as_quat().normalize(),
        camera_from_target_translation_m: g.t_camera_from_target_m.as_vec3(),
        sun_dir_target: unit_f32(g.sun_dir_target),
        sun_lit: !g.eclipse,
        earth_albedo,
        samples_per_pixel: scenario.render.samples_per_pixel,
        exposure: (scenario.render.exposure * sun_scale) as f32,
        seed,
    }
}

/// Output sub-folders of one image set (the sequence, or eval/).
struct ImageSet {
    root: PathBuf,
}

impl ImageSet {
    fn create(root: PathBuf) -> Result<ImageSet, DatasetError> {
        for sub in ["frames", "masks", "depth"] {
            let dir = root.join(sub);
            std::fs::create_dir_all(&dir).map_err(|e| DatasetError::Io {
                path: dir.clone(),
                message: e.to_string(),
            })?;
        }
        Ok(ImageSet { root })
    }

    /// Writes the three images of `frame`; returns their paths relative to the set's root.
    fn write(&self, index: u32, frame: &Frame) -> Result<[String; 3], DatasetError> {
        let names = [
            format!("frames/{index:06}.png"),
            format!("masks/{index:06}.png"),
            format!("depth/{index:06}.npy"),
        ];
        files::write_png_rgb(
            &self.root.join(&names[0]),
            frame.width,
            frame.height,
            &frame.rgb8,
        )?;
        files::write_png_grey(
            &self.root.join(&names[1]),
            frame.width,
            frame.height,
            &frame.mask,
        )?;
        files::write_bytes(
            &self.root.join(&names[2]),
            &files::npy_f32_bytes(frame.width, frame.height, &frame.depth_m),
        )?;
        Ok(names)
    }
}

fn jsonl_line(line: &TelemetryLine) -> String {
    let mut text =
        serde_json::to_string(line).expect("telemetry is plain data with finite numbers");
    text.push('\n');
    text
}

fn render(
    scene: &Scene,
    request: &FrameRequest,
    what: impl Fn() -> String,
) -> Result<Frame, DatasetError> {
    try_render_frame(scene, request).map_err(|e| DatasetError::Render {
        what: what(),
        message: e.to_string(),
    })
}

/// Renders and writes the whole dataset for `scenario` into `out_dir`, reporting progress
/// lines through `progress`.
pub fn generate(
    scenario: &Scenario,
    out_dir: &Path,
    options: GenerateOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<GenerateSummary, DatasetError> {
    scenario.validate()?;
    if !options.overwrite {
        if let Ok(mut entries) = std::fs::read_dir(out_dir) {
            if entries.next().is_some() {
                return Err(DatasetError::OutputNotEmpty(out_dir.to_path_buf()));
            }
        }
    }
    let started = Instant::now();
    let mesh = load_target(scenario)?;
    let radius_m = mesh.bounding_radius_m() as f64;
    let triangles = mesh.triangle_count();
    let target_size = target_size(scenario, &mesh);
    let geometry = scenario.geometry(target_size)?;
    let a_m = geometry.chief.semi_major_axis_m;
    let frames = scenario.frame_count();
    let intrinsics = scenario.camera_intrinsics();
    progress(&format!(
        "scenario {}: {frames} frames of {}x{} every {} s, target {triangles} triangles (radius {radius_m:.2} m, framing radius {:.2} m), \
         ROE x a [da dl dex dey dix diy] = {:.1?} m",
        scenario.name,
        intrinsics.width,
        intrinsics.height,
        scenario.sequence.cadence_s,
        target_size.framing_radius_m,
        geometry.roe.scaled_m(a_m)
    ));

    let samples = mesh.sample_surface(
        scenario.target.surface_points as usize,
        point_seed(scenario),
    );
    let points: Vec<files::PlyPoint> = samples
        .iter()
        .map(|s| files::PlyPoint {
            position: s.position_m.to_array(),
            normal: s.normal.to_array(),
            rgb8: s.albedo_rgb.map(crate::raytrace::linear_to_srgb8),
        })
        .collect();
    std::fs::create_dir_all(out_dir).map_err(|e| DatasetError::Io {
        path: out_dir.to_path_buf(),
        message: e.to_string(),
    })?;
    files::write_bytes(
        &out_dir.join("points.ply"),
        &files::ply_bytes(
            &points,
            &format!("sim-harness surface samples of {}", scenario.name),
        ),
    )?;
    let scene = Scene::new(mesh);

    let sequence = ImageSet::create(out_dir.to_path_buf())?;
    let epoch = geometry.epoch;
    let mut noise = noise::TelemetryNoise::new(&scenario.noise, scenario.seed);
    let sheet_indices = plots::contact_sheet_indices(frames, 48);
    let mut thumbnails = Vec::new();
    let mut trajectory = Vec::with_capacity(frames as usize);
    let mut telemetry = String::new();
    let mut eclipse_frames = 0;
    let (mut min_range_m, mut max_range_m) = (f64::INFINITY, 0.0f64);
    let report_every = (frames / 100).max(1);
    for index in 0..frames {
        let t_s = scenario.frame_time_s(index);
        let g = geometry.at(t_s);
        let request = frame_request(scenario, &g, sequence_seed(scenario, index));
        let frame = render(&scene, &request, || format!("frame {index}"))?;
        let [frame_name, mask_name, depth_name] = sequence.write(index, &frame)?;
        let noisy = noise.apply(
            g.q_camera_from_target,
            g.t_camera_from_target_m,
            g.sun_dir_servicer_body,
            g.sun_dir_target,
            geometry.q_body_from_camera,
        );
        telemetry.push_str(&jsonl_line(&TelemetryLine {
            index,
            time_s: Some(t_s),
            utc: Some(epoch.iso8601_after(t_s)),
            frame: frame_name,
            mask: mask_name,
            depth: depth_name,
            q_camera_from_target_wxyz: wxyz(noisy.q_camera_from_target),
            t_camera_from_target_m: noisy.t_camera_from_target_m.to_array(),
            sun_servicer_body: noisy.sun_dir_servicer_body.to_array(),
            sun_target_body: noisy.sun_dir_target.to_array(),
            eclipse: g.eclipse,
            intrinsics,
            truth: truth_record(&g, Some(g.servicer_rtn_m)),
        }));
        eclipse_frames += g.eclipse as u32;
        min_range_m = min_range_m.min(g.range_m);
        max_range_m = max_range_m.max(g.range_m);
        let chief_state = geometry.chief.propagated(t_s).state();
        let sun_inertial = g.q_inertial_from_target * g.sun_dir_target;
        trajectory.push(plots::TrajectorySample {
            time_s: t_s,
            servicer_rtn_m: g.servicer_rtn_m,
            sun_rtn: RtnFrame::from_state(&chief_state).to_rtn(sun_inertial),
            sun_visible_fraction: g.sun_visible_fraction,
            eclipse: g.eclipse,
        });
        if sheet_indices.binary_search(&index).is_ok() {
            let factor = frame.width.div_ceil(240);
            let (width, height, rgb8) =
                plots::downscale_rgb(frame.width, frame.height, &frame.rgb8, factor);
            thumbnails.push(plots::Thumbnail {
                index,
                eclipse: g.eclipse,
                width,
                height,
                rgb8,
            });
        }
        if (index + 1) % report_every == 0 || index + 1 == frames {
            let elapsed = started.elapsed().as_secs_f64();
            let eta = elapsed / (index + 1) as f64 * (frames - index - 1) as f64;
            progress(&format!(
                "frame {}/{frames} ({:.0}%), {eclipse_frames} in eclipse, {elapsed:.1} s elapsed, ~{eta:.0} s left",
                index + 1,
                100.0 * (index + 1) as f64 / frames as f64
            ));
        }
    }
    files::write_bytes(&out_dir.join("telemetry.jsonl"), telemetry.as_bytes())?;
    let sheet = plots::contact_sheet(&thumbnails, 8);
    files::write_png_rgb(
        &out_dir.join("contact_sheet.png"),
        sheet.width,
        sheet.height,
        &sheet.rgb8,
    )?;
    let period_s = geometry.chief.period_s();
    let outline: Vec<DVec3> = (0..=360)
        .map(|k| geometry.servicer_rtn_m(period_s * k as f64 / 360.0))
        .collect();
    let plot = plots::trajectory_plot(&trajectory, &outline);
    files::write_png_rgb(
        &out_dir.join("trajectory.png"),
        plot.width,
        plot.height,
        &plot.rgb8,
    )?;

    let eval_views = scenario.sequence.eval_views;
    if eval_views > 0 {
        let eval_set = ImageSet::create(out_dir.join("eval"))?;
        let (range_lo, range_hi) = eval::scenario_range_m(scenario, &geometry);
        let mut eval_telemetry = String::new();
        for k in 0..eval_views {
            let view = eval::eval_view(scenario, &geometry, k, (range_lo, range_hi));
            let request = frame_request(scenario, &view, eval_seed(scenario, k));
            let frame = render(&scene, &request, || format!("evaluation view {k}"))?;
            let [frame_name, mask_name, depth_name] = eval_set.write(k, &frame)?;
            eval_telemetry.push_str(&jsonl_line(&TelemetryLine {
                index: k,
                time_s: None,
                utc: None,
                frame: frame_name,
                mask: mask_name,
                depth: depth_name,
                q_camera_from_target_wxyz: wxyz(view.q_camera_from_target),
                t_camera_from_target_m: view.t_camera_from_target_m.to_array(),
                sun_servicer_body: view.sun_dir_servicer_body.to_array(),
                sun_target_body: view.sun_dir_target.to_array(),
                eclipse: false,
                intrinsics,
                truth: truth_record(&view, None),
            }));
            if (k + 1) % 10 == 0 || k + 1 == eval_views {
                progress(&format!("evaluation view {}/{eval_views}", k + 1));
            }
        }
        files::write_bytes(
            &out_dir.join("eval").join("telemetry.jsonl"),
            eval_telemetry.as_bytes(),
        )?;
    }
    progress(&format!("done in {:.1} s", started.elapsed().as_secs_f64()));
    Ok(GenerateSummary {
        frames,
        eclipse_frames,
        eval_views,
        min_range_m,
        max_range_m,
        target_bounding_radius_m: radius_m,
        target_framing_radius_m: target_size.framing_radius_m,
        target_triangles: triangles,
        roe_scaled_m: geometry.roe.scaled_m(a_m),
        surface_points: points.len(),
    })
}

/// Seed of the target's surface samples (framing, points.ply, initialisation).
pub(crate) fn point_seed(scenario: &Scenario) -> u64 {
    mix64(scenario.seed ^ 0x706F_696E_7473)
}

/// Ray-tracing seed of sequence frame `index`.
pub(crate) fn sequence_seed(scenario: &Scenario, index: u32) -> u64 {
    mix64(scenario.seed.wrapping_add(mix64(index as u64)))
}

/// Ray-tracing seed of evaluation view `k`.
pub(crate) fn eval_seed(scenario: &Scenario, k: u32) -> u64 {
    mix64(scenario.seed ^ 0x6576_616C ^ mix64(k as u64))
}

/// The size the scenario's geometry frames `mesh` by: its bounding radius and the 90th
/// percentile of its surface samples' distances (the scenario's sample count and seed).
pub(crate) fn target_size(scenario: &Scenario, mesh: &TargetMesh) -> TargetSize {
    let radius_m = mesh.bounding_radius_m() as f64;
    let samples = mesh.sample_surface(
        scenario.target.surface_points as usize,
        point_seed(scenario),
    );
    TargetSize {
        bounding_radius_m: radius_m,
        framing_radius_m: framing_radius_m(&samples).unwrap_or(radius_m),
    }
}

/// 90th percentile of the samples' distances from the body origin (None without samples).
pub(crate) fn framing_radius_m(samples: &[crate::target::SurfaceSample]) -> Option<f64> {
    let mut radii: Vec<f32> = samples.iter().map(|s| s.position_m.length()).collect();
    radii.sort_by(f32::total_cmp);
    let index = (radii.len() * 9 / 10).min(radii.len().checked_sub(1)?);
    Some(radii[index] as f64)
}

fn truth_record(g: &FrameGeometry, servicer_rtn_m: Option<DVec3>) -> TruthRecord {
    TruthRecord {
        q_camera_from_target_wxyz: wxyz(g.q_camera_from_target),
        t_camera_from_target_m: g.t_camera_from_target_m.to_array(),
        sun_servicer_body: g.sun_dir_servicer_body.to_array(),
        sun_target_body: g.sun_dir_target.to_array(),
        sun_visible_fraction: g.sun_visible_fraction,
        earth_dir_target_body: g.earth_dir_target.to_array(),
        earth_fill_strength: g.earth_fill_strength,
        range_m: g.range_m,
        phase_angle_deg: g.phase_angle_rad.to_degrees(),
        servicer_rtn_m: servicer_rtn_m.map(|v| v.to_array()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::TargetSize;

    #[test]
    fn penumbra_dims_the_sun_but_not_the_earth_fill() {
        let scenario = Scenario::default();
        let geometry = scenario.geometry(TargetSize::sphere(3.0)).unwrap();
        let mut g = geometry.at(0.0);
        assert!(!g.eclipse && g.sun_visible_fraction == 1.0 && g.earth_fill_strength > 0.0);
        let full = frame_request(&scenario, &g, 1);
        assert_eq!(full.exposure, 1.0);
        g.sun_visible_fraction = 0.8;
        let partial = frame_request(&scenario, &g, 1);
        assert!((partial.exposure - 0.8).abs() < 1e-6);
        let fill = |r: &FrameRequest| r.earth_albedo.unwrap().strength * r.exposure;
        assert!((fill(&partial) - fill(&full)).abs() < 1e-6);
        g.eclipse = true;
        g.sun_visible_fraction = 0.2;
        g.earth_fill_strength = 0.0;
        let dark = frame_request(&scenario, &g, 1);
        assert!(!dark.sun_lit && dark.earth_albedo.is_none());
    }
}
