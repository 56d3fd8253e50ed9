//! The initialisation ablation (the paper's Fig. 7, plus a visual hull): configuration d
//! trained online on each target from (1) points sampled on the true surface (the paper),
//! (2) random points in the bounding sphere, (3) a visual hull carved from the first
//! keyframes' masks and known poses (no ground-truth model needed); written to `init.csv`,
//! `init.md`, `init_curves.csv`, `runs.json` and `init.png` (PSNR bars per target, Gaussian
//! count over rounds); `hull.png` shows each target's surface samples beside its hull.
//!
//! The hull's views are the first K keyframes the online trainer's window would take (the
//! first K lit frames each at least `min_view_angle_deg` from the previous keyframe): what the
//! component holds when its window first fills and training starts, so the hull uses no
//! frame the trainer has not seen by then. K defaults to the window size W. The carving box
//! is the cube around the target's bounding sphere (a size prior, not the model); colours are
//! sampled from the keyframe images (the view that sees each point most frontally), or grey.
//! Variants (`hull` with suffixes `-grey`, `-volume`, `-recarve`, `-silhouette`, `-photo`):
//! points filling the hull's voxels rather than its surface; points inside the hull that
//! project onto the foreground in every keyframe (`-silhouette`, preset key
//! `hull_silhouette`), optionally drawn favouring those whose colour the keyframes agree on
//! (`-photo`, `gs_core::hull::carve_photo_consistent`, preset key `hull_photo`); and [`HullPruner`],
//! which carves a persistent volume with every keyframe as the window takes it and prunes
//! the Gaussians whose centres fall outside it (more than one voxel from any occupied
//! voxel). All use only the images, masks and poses of frames the trainer has been offered
//! by then, never an evaluation view.
//!
//! Invariants: every number written comes from a run in this process; runs go one after
//! another, targets in order, initialisations in the order asked; the CSV and Markdown are
//! rewritten after every run; `cpu_s` is this process's CPU time (all threads) over the run,
//! the steadier cost measure on a shared machine. [`merge_runs`] reads several jobs'
//! `runs.json` back and writes the tables and `init.png` of all their runs together (one job
//! per target keeps each paired comparison within one process).

mod figure;
mod hull;
mod report;

pub use figure::{cloud_figure, plot, write_hull_figure, Cloud};
pub use hull::{
    distance_summary, far_distance_m, first_keyframes, hull_initialisation, mean_nearest_distance,
    nearest_distances, uncovered_fraction, HullPruner, HullReport, GREY,
};
pub use report::{curves_csv, to_csv, to_markdown, CSV_HEADER};

use super::data::load_or_render_scene;
use super::preset::{InitKind, Preset};
use super::runner::{run_config, RunOutcome};
use super::write_text;
use super::ExperimentError;
use crate::dataset::files;
use crate::scenario::Scenario;
use glam::Vec3;
use gs_core::model::Param;
use gs_core::sunaware::Variant;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::time::Instant;

/// The initialisation's name in files.
pub fn init_name(kind: InitKind, grey: bool) -> &'static str {
    match (kind, grey) {
        (InitKind::Surface, _) => "surface",
        (InitKind::Random, _) => "random",
        (InitKind::Hull, false) => "hull",
        (InitKind::Hull, true) => "hull-grey",
    }
}

/// A hull start's options beyond the kind (each a `hull` name suffix).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct HullVariant {
    /// `-grey`: grey initial colours.
    pub grey: bool,
    /// `-volume`: points fill the hull's voxels.
    pub volume: bool,
    /// `-recarve`: carve with every keyframe and prune Gaussians outside ([`HullPruner`]).
    pub recarve: bool,
    /// `-photo`: points inside the hull where the keyframes agree on the colour.
    pub photo: bool,
    /// `-silhouette`: points inside the hull on the foreground in every keyframe.
    pub silhouette: bool,
}

/// Parses `surface`, `random`, or `hull` followed by any of `-grey`, `-volume`, `-recarve`,
/// `-photo`, `-silhouette` (each at most once, any order; `-photo` overrides `-silhouette`,
/// both override `-volume`).
pub(crate) fn parse_init_variant(name: &str) -> Result<(InitKind, HullVariant), ExperimentError> {
    let unknown = || {
        ExperimentError::Invalid(format!(
            "unknown initialisation {name:?} (surface, random, or hull with any of the \
             suffixes -grey, -volume, -recarve, -photo, -silhouette)"
        ))
    };
    match name {
        "surface" => return Ok((InitKind::Surface, HullVariant::default())),
        "random" => return Ok((InitKind::Random, HullVariant::default())),
        _ => {}
    }
    let rest = name.strip_prefix("hull").ok_or_else(unknown)?;
    let mut variant = HullVariant::default();
    if rest.is_empty() {
        return Ok((InitKind::Hull, variant));
    }
    let suffixes = rest.strip_prefix('-').ok_or_else(unknown)?;
    for suffix in suffixes.split('-') {
        let flag = match suffix {
            "grey" => &mut variant.grey,
            "volume" => &mut variant.volume,
            "recarve" => &mut variant.recarve,
            "photo" => &mut variant.photo,
            "silhouette" => &mut variant.silhouette,
            _ => return Err(unknown()),
        };
        if *flag {
            return Err(unknown());
        }
        *flag = true;
    }
    Ok((InitKind::Hull, variant))
}

/// Parses an initialisation name (see `parse_init_variant`) into its kind and whether
/// its colours are grey.
pub fn parse_init(name: &str) -> Result<(InitKind, bool), ExperimentError> {
    parse_init_variant(name).map(|(kind, v)| (kind, v.grey))
}

/// One run of the ablation (as written to, and read back from, `runs.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct InitRun {
    pub init: String,
    pub initial_gaussians: usize,
    /// Process CPU time over the whole run (initialisation, training, evaluation), seconds.
    pub cpu_s: f64,
    /// Wall time over the whole run, seconds.
    pub wall_s: f64,
    pub hull: Option<HullReport>,
    /// The final Gaussians' centres: mean distance to the nearest true surface sample, m.
    pub final_mean_distance_m: f64,
    /// ... and the fraction farther than [`far_distance_m`] (phantom Gaussians).
    pub final_far_fraction: f64,
    pub run: RunOutcome,
}

/// What the job needs.
#[derive(Clone, Debug)]
pub struct InitAblationJob {
    /// Its `configs` are ignored: the ablation trains configuration d.
    pub preset: Preset,
    pub scenarios: Vec<Scenario>,
    /// Initialisations in order, as `parse_init` names them.
    pub inits: Vec<String>,
    pub out_dir: PathBuf,
}

/// What the job produced.
#[derive(Clone, Debug)]
pub struct InitAblationResult {
    pub runs: Vec<InitRun>,
    pub render_s: f64,
    pub total_s: f64,
    pub total_cpu_s: f64,
}

/// Runs the job, reporting progress lines.
pub fn run_init_ablation(
    job: &InitAblationJob,
    progress: &mut dyn FnMut(&str),
) -> Result<InitAblationResult, ExperimentError> {
    let started = Instant::now();
    let cpu_started = gs_core::machine::process_cpu_s();
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let inits: Vec<(InitKind, HullVariant)> = job
        .inits
        .iter()
        .map(|n| parse_init_variant(n))
        .collect::<Result<_, _>>()?;
    if inits.is_empty() {
        return Err(ExperimentError::Invalid(
            "no initialisation to compare".into(),
        ));
    }
    let names: Vec<String> = job.inits.clone();
    let mut runs = Vec::new();
    let mut render_s = 0.0;
    for scenario in &job.scenarios {
        let scenario = job.preset.apply(scenario)?;
        let scene = load_or_render_scene(
            &scenario,
            job.preset.init_points as usize,
            &out.join("cache"),
            progress,
        )?;
        render_s += scene.render_s;
        for (&(kind, variant), name) in inits.iter().zip(&names) {
            let run_started = Instant::now();
            let cpu_before = gs_core::machine::process_cpu_s();
            let preset = Preset {
                init: kind,
                hull_grey_colours: variant.grey,
                hull_volume: variant.volume,
                hull_recarve: variant.recarve,
                hull_photo: variant.photo,
                hull_silhouette: variant.silhouette,
                configs: vec!["d".into()],
                ..job.preset.clone()
            };
            let hull = if kind == InitKind::Hull {
                let (_, report) = hull_initialisation(&scene, &preset)?;
                progress(&format!(
                    "{}/{name}: hull from frames {:?}: {} occupied voxels of {:.3} m, {} points, mean {:.3} m from the true surface, {:.2} s",
                    scene.name,
                    report.frames,
                    report.occupied_voxels,
                    report.voxel_m,
                    report.points,
                    report.mean_distance_to_surface_m,
                    report.carve_s
                ));
                Some(report)
            } else {
                None
            };
            let (run, trainer) = run_config(&scene, &preset, Variant::D, 0, progress)?;
            let params = &trainer.trainer().model.gaussians.params;
            let centres: Vec<Vec3> = (0..params.len())
                .map(|i| Vec3::from_slice(params.row(Param::Mean, i)))
                .collect();
            let far_m = far_distance_m(&scene, &preset);
            let (final_mean_distance_m, final_far_fraction) =
                distance_summary(&centres, &scene, far_m);
            progress(&format!(
                "{}/{name}: final Gaussians {:.3} m from the true surface on average, {:.1} % farther than {:.2} m",
                scene.name,
                final_mean_distance_m,
                100.0 * final_far_fraction,
                far_m
            ));
            let initial_gaussians = match (&hull, kind) {
                (Some(h), _) => h.points,
                (None, InitKind::Surface) => scene.surface.len().min(preset.init_points as usize),
                (None, _) => preset.init_points as usize,
            };
            let cpu_s = match (cpu_before, gs_core::machine::process_cpu_s()) {
                (Some(a), Some(b)) => b - a,
                _ => f64::NAN,
            };
            runs.push(InitRun {
                init: name.clone(),
                initial_gaussians,
                cpu_s,
                wall_s: run_started.elapsed().as_secs_f64(),
                hull,
                final_mean_distance_m,
                final_far_fraction,
                run,
            });
            write_text(&out.join("init.csv"), &to_csv(&runs))?;
            write_text(&out.join("init.md"), &to_markdown(&runs))?;
            write_text(&out.join("init_curves.csv"), &curves_csv(&runs))?;
            write_text(
                &out.join("runs.json"),
                &serde_json::to_string_pretty(&runs).map_err(|e| ExperimentError::io(out, e))?,
            )?;
            progress(&format!(
                "{} of {} runs done, {:.0} s elapsed",
                runs.len(),
                inits.len() * job.scenarios.len(),
                started.elapsed().as_secs_f64()
            ));
        }
    }
    write_plot(out, &runs, &names)?;
    let total_cpu_s = match (cpu_started, gs_core::machine::process_cpu_s()) {
        (Some(a), Some(b)) => b - a,
        _ => f64::NAN,
    };
    Ok(InitAblationResult {
        runs,
        render_s,
        total_s: started.elapsed().as_secs_f64(),
        total_cpu_s,
    })
}

/// Writes `init.png` of `runs`, one colour per name of `names`.
fn write_plot(
    out: &std::path::Path,
    runs: &[InitRun],
    names: &[String],
) -> Result<(), ExperimentError> {
    let canvas = plot(runs, names);
    files::write_png_rgb(
        &out.join("init.png"),
        canvas.width,
        canvas.height,
        &canvas.rgb8,
    )?;
    Ok(())
}

/// Reads the `runs.json` of several jobs (in the order given) and writes `init.csv`,
/// `init.md` and `init.png` of all their runs to `out`; the starts keep the order in which
/// they first appear. Paired differences are taken only within one target, so runs of one
/// target should come from one job (one binary). Returns the runs.
pub fn merge_runs(
    paths: &[PathBuf],
    out: &std::path::Path,
) -> Result<Vec<InitRun>, ExperimentError> {
    let mut runs: Vec<InitRun> = Vec::new();
    for path in paths {
        let text = std::fs::read_to_string(path).map_err(|e| ExperimentError::io(path, e))?;
        let job: Vec<InitRun> = serde_json::from_str(&text).map_err(|e| {
            ExperimentError::Invalid(format!(
                "{}: not an ablation-init runs.json: {e}",
                path.display()
            ))
        })?;
        runs.extend(job);
    }
    if runs.is_empty() {
        return Err(ExperimentError::Invalid("no runs to merge".into()));
    }
    let mut names: Vec<String> = Vec::new();
    for r in &runs {
        if !names.contains(&r.init) {
            names.push(r.init.clone());
        }
    }
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    write_text(&out.join("init.csv"), &to_csv(&runs))?;
    write_text(&out.join("init.md"), &to_markdown(&runs))?;
    write_plot(out, &runs, &names)?;
    Ok(runs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::data::render_scene;
    use crate::experiment::runner::{online_config, scene_box};
    use gs_core::rng::SplitMix64;
    use gs_online::online::{Initialisation, OnlineTrainer};
    use std::path::Path;

    #[test]
    fn hull_names_parse_with_their_suffixes_once_each() {
        assert_eq!(
            parse_init_variant("surface").unwrap(),
            (InitKind::Surface, HullVariant::default())
        );
        let (kind, v) = parse_init_variant("hull-recarve-volume").unwrap();
        assert_eq!(kind, InitKind::Hull);
        assert!(v.recarve && v.volume && !v.grey);
        assert_eq!(parse_init("hull-grey").unwrap(), (InitKind::Hull, true));
        let (kind, v) = parse_init_variant("hull-photo").unwrap();
        assert_eq!(kind, InitKind::Hull);
        assert!(v.photo && !v.volume && !v.recarve && !v.grey && !v.silhouette);
        let (_, v) = parse_init_variant("hull-silhouette").unwrap();
        assert!(v.silhouette && !v.photo && !v.volume);
        for bad in [
            "hull-",
            "hull-grey-grey",
            "hull-photo-photo",
            "hull-silhouette-silhouette",
            "hullgrey",
            "hull-shell",
            "random-grey",
            "",
        ] {
            let e = parse_init_variant(bad).unwrap_err().to_string();
            assert!(e.contains(&format!("{bad:?}")), "{bad}: {e}");
        }
    }

    #[test]
    fn the_photo_preset_keys_parse_and_bad_values_are_errors() {
        let p = Preset::from_toml_str(
            "init = \"hull\"\nhull_photo = true\nhull_silhouette = true\nhull_photo_spread_width = 0.25\nhull_photo_samples = 8\n",
            "t.toml",
        )
        .unwrap();
        assert!(p.hull_photo && p.hull_silhouette);
        assert_eq!(p.hull_photo_spread_width, 0.25);
        assert_eq!(p.hull_photo_samples, 8);
        assert!(!Preset::default().hull_photo);
        for bad in [
            "hull_photo_spread_width = 0.0",
            "hull_photo_spread_width = -1.0",
            "hull_photo_spread_width = nan",
            "hull_photo_samples = 0",
            "hull_photo_samples = 65",
        ] {
            let e = Preset::from_toml_str(bad, "t.toml")
                .unwrap_err()
                .to_string();
            let key = bad.split(' ').next().unwrap();
            assert!(e.contains(key), "{bad}: {e}");
        }
    }

    /// On a small rendered target from its first keyframes, the photo-consistent and the
    /// silhouette starts lie closer to the true surface than the volume start (the
    /// carving's margin shell is dropped), report their candidates, and are reproducible.
    #[test]
    fn the_photo_and_silhouette_starts_lie_closer_to_the_surface_than_the_volume_start() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
        let preset = Preset {
            name: "tiny".into(),
            downsample: 10,
            cadence_s: 30.0,
            frames: Some(8),
            eval_views: 1,
            figure_views: 1,
            samples_per_pixel: 1,
            window: 4,
            init_points: 400,
            hull_resolution: 48,
            init: InitKind::Hull,
            hull_volume: true,
            ..Preset::default()
        };
        let scenario = preset.apply(&Scenario::load(&path).unwrap()).unwrap();
        let scene = render_scene(&scenario, 2000, &mut |_| {}).unwrap();
        let (_, volume) = hull_initialisation(&scene, &preset).unwrap();
        let photo_preset = Preset {
            hull_photo: true,
            ..preset.clone()
        };
        let (init, photo) = hull_initialisation(&scene, &photo_preset).unwrap();
        assert_eq!(photo.frames, volume.frames);
        assert_eq!(photo.occupied_voxels, volume.occupied_voxels);
        assert_eq!(photo.points, 400);
        assert_eq!(
            photo.photo_candidates,
            preset.hull_photo_samples as usize * volume.occupied_voxels
        );
        assert!(photo.photo_off_silhouette > 0);
        assert_eq!(volume.photo_candidates, 0);
        assert!(
            photo.mean_distance_to_surface_m < 0.8 * volume.mean_distance_to_surface_m,
            "photo {} m, volume {} m",
            photo.mean_distance_to_surface_m,
            volume.mean_distance_to_surface_m
        );
        assert!(photo.far_fraction < volume.far_fraction);
        let (again, _) = hull_initialisation(&scene, &photo_preset).unwrap();
        assert_eq!(init, again);
        let silhouette_preset = Preset {
            hull_silhouette: true,
            ..preset.clone()
        };
        let (_, silhouette) = hull_initialisation(&scene, &silhouette_preset).unwrap();
        assert_eq!(silhouette.points, 400);
        assert_eq!(
            silhouette.photo_off_silhouette, photo.photo_off_silhouette,
            "the same candidates, the same test"
        );
        assert_eq!(silhouette.photo_median_spread, 0.0);
        assert!(
            silhouette.mean_distance_to_surface_m < 0.8 * volume.mean_distance_to_surface_m,
            "silhouette {} m, volume {} m",
            silhouette.mean_distance_to_surface_m,
            volume.mean_distance_to_surface_m
        );
    }

    /// Gaussians on the true surface and Gaussians spread through the bounding ball: carving
    /// with the frames as they arrive removes exactly the ones outside the (dilated) hull,
    /// never one on the surface, and keeps every kept row's moments and statistics.
    #[test]
    fn the_pruner_removes_exactly_the_gaussians_outside_the_hull() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
        let preset = Preset {
            name: "tiny".into(),
            downsample: 20,
            cadence_s: 10.0,
            frames: Some(6),
            eval_views: 1,
            figure_views: 1,
            samples_per_pixel: 1,
            window: 3,
            init_points: 300,
            max_gaussians: 1000,
            light_resolution_px: 32,
            hull_resolution: 40,
            init: InitKind::Hull,
            hull_recarve: true,
            ..Preset::default()
        };
        let scenario = preset.apply(&Scenario::load(&path).unwrap()).unwrap();
        let scene = render_scene(&scenario, 300, &mut |_| {}).unwrap();
        let surface: Vec<Vec3> = scene.surface.iter().map(|s| s.position_m).collect();
        let radius = scene.bounding_radius_m;
        let mut rng = SplitMix64::new(3);
        let mut ball = Vec::new();
        while ball.len() < 300 {
            let p = Vec3::new(
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            );
            if p.length() <= 1.0 {
                ball.push(p * radius);
            }
        }
        let points: Vec<Vec3> = surface.iter().chain(&ball).copied().collect();
        let init = Initialisation::SurfaceSamples {
            points: points.clone(),
            normals: None,
            colours: None,
        };
        let mut trainer = OnlineTrainer::new(
            online_config(&preset, Variant::D).unwrap(),
            &init,
            scene_box(&scene).unwrap(),
        )
        .unwrap();
        // Tag each row's moments and statistics with its index, to follow them.
        {
            let t = trainer.trainer_mut();
            for i in 0..points.len() {
                t.adam.m.row_mut(Param::Mean, i)[0] = i as f32;
                t.adam.v.row_mut(Param::Mean, i)[0] = i as f32;
            }
            t.densify_stats.visible_count = (0..points.len() as u32).collect();
        }
        let mut pruner = HullPruner::for_preset(&scene, &preset).unwrap().unwrap();
        let mut total = 0;
        for frame in 0..scene.frames.len() {
            total += pruner.keyframe_added(&mut trainer, &scene, frame).unwrap();
        }
        assert_eq!(pruner.keyframes, scene.frames.len());
        assert_eq!(pruner.pruned, total);
        let volume = pruner.volume();
        let expected: Vec<usize> = (0..points.len())
            .filter(|&i| volume.contains(points[i], HullPruner::DILATE_VOXELS))
            .collect();
        // Every surface sample survives (carving is conservative); many ball points go.
        assert!(expected[..surface.len()]
            .iter()
            .enumerate()
            .all(|(k, &i)| k == i));
        assert!(total > 100, "only {total} of 300 ball points pruned");
        assert_eq!(points.len() - expected.len(), total);
        let t = trainer.trainer();
        let params = &t.model.gaussians.params;
        assert_eq!(params.len(), expected.len());
        assert_eq!(t.adam.m.len(), expected.len());
        assert_eq!(t.densify_stats.len(), expected.len());
        for (row, &i) in expected.iter().enumerate() {
            assert_eq!(Vec3::from_slice(params.row(Param::Mean, row)), points[i]);
            assert_eq!(t.adam.m.row(Param::Mean, row)[0], i as f32);
            assert_eq!(t.adam.v.row(Param::Mean, row)[0], i as f32);
            assert_eq!(t.densify_stats.visible_count[row], i as u32);
        }
        // A preset without re-carving gives no pruner.
        let plain = Preset {
            hull_recarve: false,
            ..preset
        };
        assert!(HullPruner::for_preset(&scene, &plain).unwrap().is_none());
    }
}
