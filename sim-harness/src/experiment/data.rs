//! In-memory datasets for experiments: the training sequence (time order) and the evaluation
//! views of one scenario, rendered exactly as `dataset::generate` renders them (same frame
//! requests and seeds), plus the target's surface samples for initialisation.
//!
//! Invariants: frame k of the sequence and view k of the evaluation set are byte-identical to
//! `frames/k.png` / `eval/frames/k.png` of `sim-harness generate` on the same scenario; poses
//! and Sun vectors are the ground truth the images were rendered with (the paper assumes
//! perfect knowledge of both), expressed in the target body frame, which is the model's world
//! frame. A cache file is only ever used when its key (a hash of the scenario's TOML text and
//! the format version) matches, so a changed scenario never reads stale images.

use crate::dataset::{
    eval, eval_seed, frame_request, load_target, point_seed, sequence_seed, target_size,
    DatasetError,
};
use crate::orbit::FrameGeometry;
use crate::raytrace::{try_render_frame, FrameRequest, Scene};
use crate::scenario::Scenario;
use crate::target::{SurfaceSample, TargetMesh};
use glam::{DQuat, DVec3};
use rayon::prelude::*;
use std::path::Path;
use std::time::Instant;

/// One rendered image with the geometry it was rendered with.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewData {
    pub index: u32,
    /// Seconds after the epoch (None for evaluation views).
    pub time_s: Option<f64>,
    pub eclipse: bool,
    /// x_camera = q * x_target + t (OpenCV axes).
    pub q_camera_from_target: DQuat,
    pub t_camera_from_target_m: DVec3,
    /// Unit vector towards the Sun, target body frame.
    pub sun_dir_target: DVec3,
    /// sRGB bytes, width * height * 3.
    pub rgb8: Vec<u8>,
    /// 255 where the pixel-centre ray hits the target, else 0.
    pub mask8: Vec<u8>,
}

impl ViewData {
    /// RGB in [0, 1] (the PNG values the paper trains on), pixel-major.
    pub fn rgb_f32(&self) -> Vec<f32> {
        self.rgb8.iter().map(|&v| v as f32 / 255.0).collect()
    }

    /// Mask in {0, 1}.
    pub fn mask_f32(&self) -> Vec<f32> {
        self.mask8
            .iter()
            .map(|&v| if v >= 128 { 1.0 } else { 0.0 })
            .collect()
    }

    /// Unit direction from the target to the camera, target body frame.
    pub fn view_dir_target(&self) -> DVec3 {
        (-(self.q_camera_from_target.inverse() * self.t_camera_from_target_m)).normalize()
    }
}

/// Pinhole intrinsics of every image in a scene, pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneIntrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

/// Everything an experiment needs from one scenario.
#[derive(Clone, Debug)]
pub struct SceneData {
    pub name: String,
    pub intrinsics: SceneIntrinsics,
    pub frames: Vec<ViewData>,
    pub eval: Vec<ViewData>,
    /// Surface samples (uniform by area) for the paper's initialisation.
    pub surface: Vec<SurfaceSample>,
    /// Axis-aligned bounds of the mesh vertices, target body frame, metres.
    pub bounds_min_m: [f32; 3],
    pub bounds_max_m: [f32; 3],
    pub bounding_radius_m: f32,
    /// Wall time spent rendering (0 when read from the cache), seconds.
    pub render_s: f64,
}

fn view_from(
    g: &FrameGeometry,
    index: u32,
    time_s: Option<f64>,
    frame: crate::raytrace::Frame,
) -> ViewData {
    ViewData {
        index,
        time_s,
        eclipse: g.eclipse,
        q_camera_from_target: g.q_camera_from_target,
        t_camera_from_target_m: g.t_camera_from_target_m,
        sun_dir_target: g.sun_dir_target,
        rgb8: frame.rgb8,
        mask8: frame.mask,
    }
}

/// The request that rendered sequence frame `index` of `mesh` (the scenario's target) in
/// `render_scene` (same geometry, lights, exposure and seed): for ray-tracing that frame again
/// with something changed.
pub fn sequence_frame_request(
    scenario: &Scenario,
    mesh: &TargetMesh,
    index: u32,
) -> Result<FrameRequest, DatasetError> {
    let geometry = scenario.geometry(target_size(scenario, mesh))?;
    let g = geometry.at(scenario.frame_time_s(index));
    Ok(frame_request(scenario, &g, sequence_seed(scenario, index)))
}

/// Renders the scenario's sequence and evaluation views into memory. `surface_points`
/// samples are drawn for initialisation (with the same seed `generate` uses for points.ply).
pub fn render_scene(
    scenario: &Scenario,
    surface_points: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<SceneData, DatasetError> {
    scenario.validate()?;
    let started = Instant::now();
    let mesh = load_target(scenario)?;
    let radius_m = mesh.bounding_radius_m();
    let (surface, lo, hi) = mesh_facts(&mesh, surface_points, point_seed(scenario));
    let geometry = scenario.geometry(target_size(scenario, &mesh))?;
    let k = scenario.camera_intrinsics();
    let scene = Scene::new(mesh);
    let frame_count = scenario.frame_count();
    progress(&format!(
        "{}: rendering {frame_count} frames and {} evaluation views at {}x{}",
        scenario.name, scenario.sequence.eval_views, k.width, k.height
    ));
    let frames: Vec<ViewData> = (0..frame_count)
        .into_par_iter()
        .map(|index| {
            let t_s = scenario.frame_time_s(index);
            let g = geometry.at(t_s);
            let request = frame_request(scenario, &g, sequence_seed(scenario, index));
            try_render_frame(&scene, &request)
                .map(|frame| view_from(&g, index, Some(t_s), frame))
                .map_err(|e| DatasetError::Render {
                    what: format!("frame {index}"),
                    message: e.to_string(),
                })
        })
        .collect::<Result<_, _>>()?;
    let ranges = eval::scenario_range_m(scenario, &geometry);
    let eval_views: Vec<ViewData> = (0..scenario.sequence.eval_views)
        .into_par_iter()
        .map(|view| {
            let g = eval::eval_view(scenario, &geometry, view, ranges);
            let request = frame_request(scenario, &g, eval_seed(scenario, view));
            try_render_frame(&scene, &request)
                .map(|frame| view_from(&g, view, None, frame))
                .map_err(|e| DatasetError::Render {
                    what: format!("evaluation view {view}"),
                    message: e.to_string(),
                })
        })
        .collect::<Result<_, _>>()?;
    let render_s = started.elapsed().as_secs_f64();
    progress(&format!("{}: rendered in {render_s:.1} s", scenario.name));
    Ok(SceneData {
        name: scenario.name.clone(),
        intrinsics: SceneIntrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: k.width,
            height: k.height,
        },
        frames,
        eval: eval_views,
        surface,
        bounds_min_m: lo,
        bounds_max_m: hi,
        bounding_radius_m: radius_m,
        render_s,
    })
}

/// Surface samples and the vertex bounds of a mesh.
fn mesh_facts(
    mesh: &TargetMesh,
    surface_points: usize,
    point_seed: u64,
) -> (Vec<SurfaceSample>, [f32; 3], [f32; 3]) {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in mesh.vertices_m() {
        for axis in 0..3 {
            lo[axis] = lo[axis].min(v[axis]);
            hi[axis] = hi[axis].max(v[axis]);
        }
    }
    (mesh.sample_surface(surface_points, point_seed), lo, hi)
}

/// Renders the scene, or reads it from `cache_dir` when a cache file for exactly this
/// scenario and sample count exists; writes the cache after rendering.
pub(crate) fn load_or_render_scene(
    scenario: &Scenario,
    surface_points: usize,
    cache_dir: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<SceneData, DatasetError> {
    let key = super::cache::scene_key(scenario, surface_points);
    let path = cache_dir.join(format!(
        "{}-{key:016x}.bin",
        super::cache::safe_name(&scenario.name)
    ));
    if let Some(scene) = super::cache::read(&path, key)? {
        progress(&format!(
            "{}: read from cache {}",
            scenario.name,
            path.display()
        ));
        // The surface samples and bounds are cheap and not cached: recompute them.
        let mesh = load_target(scenario)?;
        let mut scene = scene;
        let (surface, lo, hi) = mesh_facts(&mesh, surface_points, point_seed(scenario));
        scene.surface = surface;
        scene.bounds_min_m = lo;
        scene.bounds_max_m = hi;
        scene.bounding_radius_m = mesh.bounding_radius_m();
        return Ok(scene);
    }
    let scene = render_scene(scenario, surface_points, progress)?;
    std::fs::create_dir_all(cache_dir).map_err(|e| DatasetError::Io {
        path: cache_dir.to_path_buf(),
        message: e.to_string(),
    })?;
    super::cache::write(&path, key, &scene)?;
    Ok(scene)
}
