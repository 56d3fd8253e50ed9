//! One experiment run: a configuration (a-d) trained on one scene through the paper's online
//! procedure (`gs_online::online::OnlineTrainer`: frames offered in time order, keyframe
//! window W, a round of W steps whenever the window changed, densify every few rounds), then
//! evaluated on the scene's evaluation views.
//!
//! Invariants: frames are offered strictly in time order and evaluation views never train;
//! training uses the full frame on the black background (no mask: the background is part of
//! what the paper's full-frame metrics score; `Preset::masked_loss` gives the frames their
//! masks instead, and a frame whose mask is empty is then refused with an error) and
//! ground-truth poses and Sun vectors;
//! eclipse frames are skipped (the online trainer counts them); `train_s` is the wall time
//! spent inside training rounds (densification included) and `step_ms` that time divided by
//! the steps applied.

use super::data::{SceneData, ViewData};
use super::evaluate::{
    black_baseline, camera_of, evaluate_model, nearest_angle_deg, score_with_black, seen_views,
    summarise, sun_of, EvalSummary,
};
use super::preset::{InitKind, Preset, PresetError};
use crate::raytrace::linear_to_srgb8;
use glam::{DVec3, Vec3};
use gs_core::nn::SceneBox;
use gs_core::sunaware::{BackendKind, Variant};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{Frame, Initialisation, OnlineConfig, OnlineError, OnlineTrainer};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// One training round, for loss curves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RoundPoint {
    pub round: u64,
    /// Index of the last frame offered before the round.
    pub frame_index: u32,
    pub mean_loss: f64,
    pub gaussians: usize,
    /// Training wall time so far (rounds only), seconds.
    pub train_s: f64,
}

/// Evaluation during training.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalPoint {
    pub round: u64,
    pub psnr_db: f64,
    pub ssim: f64,
    pub masked_psnr_db: f64,
    pub gaussians: usize,
}

/// Everything a run produced.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunOutcome {
    pub target: String,
    pub config: String,
    pub eval: EvalSummary,
    /// The same metrics on up to 20 lit training frames (views the model trained on): the
    /// gap to `eval` measures generalisation to new poses and Sun directions.
    pub seen: EvalSummary,
    /// An all-black render on the evaluation views (the floor to beat).
    pub black_eval: EvalSummary,
    /// An all-black render on the same training frames as `seen`.
    pub black_seen: EvalSummary,
    /// Accuracy ladder L0: the keyframes in the window at the end (fitting, without
    /// forgetting), and an all-black render on them.
    pub window_fit: EvalSummary,
    pub black_window: EvalSummary,
    /// Accuracy ladder L1: lit frames of the same rendezvous that training never received
    /// (every `Preset::holdout_every`-th frame; empty when 0), and an all-black render on
    /// them.
    pub held_out: EvalSummary,
    pub black_held_out: EvalSummary,
    /// Accuracy ladder L2 split by coverage: the evaluation views whose viewpoint lies within
    /// `COVERED_VIEW_DEG` of a frame training received (the rest show sides of the target
    /// training never saw), and an all-black render on them.
    pub eval_covered: EvalSummary,
    pub black_eval_covered: EvalSummary,
    pub gaussians: usize,
    pub rounds: u64,
    pub steps: u64,
    pub skipped_nonfinite_steps: u64,
    pub frames_offered: u64,
    pub keyframes_added: u64,
    pub skipped_eclipse: u64,
    /// Frames whose mask was zero everywhere (the target out of the image).
    pub skipped_empty_mask: u64,
    pub skipped_view: u64,
    pub train_s: f64,
    /// Process CPU time (all threads, user + system, getrusage) spent inside training
    /// rounds, seconds: on a shared machine a steadier cost measure than `train_s`.
    pub train_cpu_s: f64,
    pub step_ms: f64,
    pub eval_s: f64,
    pub curve: Vec<RoundPoint>,
    /// Evaluation every `eval_every_rounds` rounds (empty when 0).
    pub eval_curve: Vec<EvalPoint>,
    /// sRGB renders of the first evaluation views (for figures).
    #[serde(skip)]
    pub renders: Vec<Vec<u8>>,
}

/// An evaluation view counts as covered when its viewpoint is within this angle of a
/// viewpoint training received (`RunOutcome::eval_covered`), degrees.
pub(crate) const COVERED_VIEW_DEG: f64 = 30.0;

/// Whether sequence frame `i` is withheld from training for the held-out rung (L1).
pub(crate) fn is_held_out(preset: &Preset, i: usize) -> bool {
    let every = preset.holdout_every as usize;
    every > 0 && i % every == every - 1
}

/// The lit sequence frames training received (none withheld for L1), in time order.
pub fn trained_frames<'a>(scene: &'a SceneData, preset: &Preset) -> Vec<&'a ViewData> {
    lit_frames(scene, preset, false)
}

/// The lit sequence frames withheld from training and scored as the held-out rung (L1), in
/// time order.
pub fn held_out_frames<'a>(scene: &'a SceneData, preset: &Preset) -> Vec<&'a ViewData> {
    lit_frames(scene, preset, true)
}

/// The sequence frames in `trainer`'s keyframe window (the ladder's L0 window), in time
/// order.
pub fn window_frames<'a>(scene: &'a SceneData, trainer: &OnlineTrainer) -> Vec<&'a ViewData> {
    let window_ids: Vec<u64> = trainer.window().keyframes().iter().map(|k| k.id).collect();
    scene
        .frames
        .iter()
        .filter(|v| window_ids.contains(&(v.index as u64)))
        .collect()
}

/// The lit sequence frames that are (`held_out`) or are not withheld for L1, in time order.
fn lit_frames<'a>(scene: &'a SceneData, preset: &Preset, held_out: bool) -> Vec<&'a ViewData> {
    scene
        .frames
        .iter()
        .enumerate()
        .filter(|(i, v)| is_held_out(preset, *i) == held_out && !v.eclipse)
        .map(|(_, v)| v)
        .collect()
}

/// The scene box of the target: its vertex bounds grown by 5 % on each side.
pub fn scene_box(scene: &SceneData) -> Result<SceneBox, OnlineError> {
    let (lo, hi) = (scene.bounds_min_m, scene.bounds_max_m);
    let mut min_m = [0.0f32; 3];
    let mut max_m = [0.0f32; 3];
    for axis in 0..3 {
        // A flat target (zero extent on one axis) still gets a box.
        let pad = (0.05 * (hi[axis] - lo[axis])).max(0.02 * scene.bounding_radius_m.max(0.1));
        min_m[axis] = lo[axis] - pad;
        max_m[axis] = hi[axis] + pad;
    }
    SceneBox::new(min_m, max_m)
        .map_err(|e| OnlineError::Config(format!("scene box of {}: {e}", scene.name)))
}

/// The online trainer's settings for `variant` under `preset` (a model key the model refuses
/// is named).
pub fn online_config(preset: &Preset, variant: Variant) -> Result<OnlineConfig, PresetError> {
    let model = preset.model_config(variant)?;
    Ok(OnlineConfig {
        window: WindowConfig {
            capacity: preset.window,
            min_view_angle_deg: preset.min_view_angle_deg,
        },
        model,
        densify_every_rounds: preset.densify_every_rounds as u64,
        passes_per_round: preset.passes_per_round,
        skip_eclipse: preset.skip_eclipse,
        // Off by default: without a mask the unlit test averages over the black background;
        // eclipse frames are flagged by the simulator and skipped above.
        skip_unlit: preset.skip_unlit,
        shuffle_seed: preset.seed,
        replay_capacity: preset.replay_capacity,
        replay_steps_per_round: preset.replay_steps_per_round,
        sun_jitter_rad: preset.sun_jitter_deg.to_radians(),
        // Extra rounds on an unchanged window only when the preset asks for them (the
        // runner counts them per change; the trainer alone would refuse a repeat).
        require_window_change: preset.rounds_per_window_change <= 1 && preset.skip_unchanged_window,
        ..OnlineConfig::default()
    })
}

/// How the Gaussians start: the preset's choice, from the scene's surface samples (with
/// their material colours, sRGB) or random in the bounding sphere.
pub fn initialisation(scene: &SceneData, preset: &Preset) -> Initialisation {
    match preset.init {
        InitKind::Surface => {
            let n = (preset.init_points as usize).min(scene.surface.len());
            let samples = &scene.surface[..n];
            Initialisation::SurfaceSamples {
                points: samples.iter().map(|s| s.position_m).collect(),
                normals: None,
                colours: Some(
                    samples
                        .iter()
                        .map(|s| s.albedo_rgb.map(|c| linear_to_srgb8(c) as f32 / 255.0))
                        .collect(),
                ),
            }
        }
        InitKind::Random => Initialisation::RandomSphere {
            count: preset.init_points as usize,
            centre: Vec3::ZERO,
            radius_m: scene.bounding_radius_m.max(0.1),
            seed: preset.seed ^ 0x5EED,
        },
        // A hull that cannot be carved gives no points, which `OnlineTrainer::new` refuses;
        // `try_initialisation` says why.
        InitKind::Hull => super::ablation_init::hull_initialisation(scene, preset).map_or(
            Initialisation::SurfaceSamples {
                points: Vec::new(),
                normals: None,
                colours: None,
            },
            |(init, _)| init,
        ),
    }
}

/// [`initialisation`], with the reason when a visual hull cannot be carved.
pub fn try_initialisation(
    scene: &SceneData,
    preset: &Preset,
) -> Result<Initialisation, OnlineError> {
    match preset.init {
        InitKind::Hull => Ok(super::ablation_init::hull_initialisation(scene, preset)?.0),
        _ => Ok(initialisation(scene, preset)),
    }
}

/// The online trainer's frame for sequence frame `i` of `scene` (full-frame loss).
pub fn training_frame(scene: &SceneData, i: usize) -> Frame {
    training_frame_with_mask(scene, i, false)
}

/// [`training_frame`], carrying the frame's foreground mask when `masked` (the trainer
/// then weighs the loss by it: `Preset::masked_loss`).
pub(crate) fn training_frame_with_mask(scene: &SceneData, i: usize, masked: bool) -> Frame {
    let view = &scene.frames[i];
    Frame {
        id: view.index as u64,
        time_s: view.time_s.unwrap_or(0.0),
        camera: camera_of(&scene.intrinsics, view),
        sun_dir_target: sun_of(view),
        image: view.rgb_f32(),
        mask: masked.then(|| view.mask_f32()),
        eclipse: view.eclipse,
    }
}

/// Trains `variant` on `scene` online and evaluates it. `keep_renders` evaluation renders are
/// kept for figures. Returns the trainer too (for checkpoints and PLY export).
pub fn run_config(
    scene: &SceneData,
    preset: &Preset,
    variant: Variant,
    keep_renders: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<(RunOutcome, OnlineTrainer), OnlineError> {
    let label = format!("{}/{}", scene.name, variant.name());
    let mut trainer = OnlineTrainer::new(
        online_config(preset, variant).map_err(|e| OnlineError::Config(e.to_string()))?,
        &try_initialisation(scene, preset)?,
        scene_box(scene)?,
    )?;
    // The preset's backend (a missing feature or adapter is an error here, before training).
    let backend = preset
        .backend
        .parse::<BackendKind>()
        .and_then(|kind| kind.open(&fsw_component::engines::device_engines(), true))?;
    trainer.trainer_mut().set_backend(&backend)?;
    progress(&format!(
        "{label}: {} initial Gaussians, {} frames, W = {}",
        trainer.trainer().model.len(),
        scene.frames.len(),
        preset.window
    ));
    let started = Instant::now();
    let mut curve = Vec::new();
    let mut eval_curve = Vec::new();
    let mut train_s = 0.0;
    let mut train_cpu_s = 0.0;
    let report_every = (scene.frames.len() / 10).max(1);
    let rounds_per_change = preset.rounds_per_window_change.max(1);
    // `init = "hull"` with `hull_recarve`: carve with each new keyframe, prune outside.
    let mut hull_pruner = super::ablation_init::HullPruner::for_preset(scene, preset)?;
    for i in 0..scene.frames.len() {
        if is_held_out(preset, i) {
            continue;
        }
        let generation_before = trainer.window().generation();
        trainer.offer(training_frame_with_mask(scene, i, preset.masked_loss))?;
        if let Some(pruner) = hull_pruner.as_mut() {
            if trainer.window().generation() != generation_before {
                let pruned = pruner.keyframe_added(&mut trainer, scene, i)?;
                if pruned > 0 {
                    progress(&format!(
                        "{label}: keyframe {i}: hull re-carved ({} voxels left), {pruned} Gaussians pruned outside it",
                        pruner.occupied_voxels()
                    ));
                }
            }
        }
        // The paper: one round per window change (a round is only ever due right after a
        // change). `rounds_per_window_change` > 1 trains the changed window that many times
        // (more iterations per frame on a sparse frame subset).
        let rounds_due = if trainer.window().generation() != generation_before
            || !preset.skip_unchanged_window
        {
            rounds_per_change
        } else {
            0
        };
        for _ in 0..rounds_due {
            let cpu_before_s = gs_core::machine::process_cpu_s().unwrap_or(0.0);
            let Some(report) = trainer.run_round_if_due()? else {
                break;
            };
            train_cpu_s += gs_core::machine::process_cpu_s().unwrap_or(0.0) - cpu_before_s;
            train_s += report.duration_s;
            curve.push(RoundPoint {
                round: report.rounds,
                frame_index: scene.frames[i].index,
                mean_loss: report.mean_loss as f64,
                gaussians: report.gaussians,
                train_s,
            });
            let every = preset.eval_every_rounds;
            if every > 0 && report.rounds % every == 0 {
                let (e, _) = evaluate_model(&trainer.trainer().model, scene, 0)?;
                progress(&format!(
                    "{label}: round {}: evaluation PSNR {:.2} dB, SSIM {:.4}",
                    report.rounds, e.psnr_db, e.ssim
                ));
                eval_curve.push(EvalPoint {
                    round: report.rounds,
                    psnr_db: e.psnr_db,
                    ssim: e.ssim,
                    masked_psnr_db: e.masked_psnr_db,
                    gaussians: report.gaussians,
                });
            }
        }
        if (i + 1) % report_every == 0 || i + 1 == scene.frames.len() {
            let last = curve.last();
            progress(&format!(
                "{label}: frame {}/{}, {} rounds, loss {:.4}, {} Gaussians, {:.0} s",
                i + 1,
                scene.frames.len(),
                trainer.rounds(),
                last.map_or(f64::NAN, |p| p.mean_loss),
                trainer.trainer().model.len(),
                started.elapsed().as_secs_f64()
            ));
        }
    }
    let eval_started = Instant::now();
    let (eval, renders) = evaluate_model(&trainer.trainer().model, scene, keep_renders)?;
    let model = &trainer.trainer().model;
    let k = &scene.intrinsics;
    let trained = trained_frames(scene, preset);
    let seen_frames = seen_views(&trained, 20);
    let window_frames = window_frames(scene, &trainer);
    let held_frames = held_out_frames(scene, preset);
    let (window_fit, black_window) = score_with_black(model, k, &window_frames)?;
    let (held_out, black_held_out) = score_with_black(model, k, &held_frames)?;
    let (seen, black_seen) = score_with_black(model, k, &seen_frames)?;
    let trained_dirs: Vec<DVec3> = trained.iter().map(|v| v.view_dir_target()).collect();
    let covered: Vec<usize> = (0..scene.eval.len())
        .filter(|&i| {
            nearest_angle_deg(scene.eval[i].view_dir_target(), &trained_dirs) <= COVERED_VIEW_DEG
        })
        .collect();
    let black_eval = black_baseline(k, &scene.eval)?;
    let subset = |s: &EvalSummary| summarise(covered.iter().map(|&i| s.per_view[i]).collect());
    let eval_covered = subset(&eval);
    let black_eval_covered = subset(&black_eval);
    let eval_s = eval_started.elapsed().as_secs_f64();
    let t = trainer.trainer();
    let counters = trainer.counters();
    let steps = t.steps;
    let outcome = RunOutcome {
        target: scene.name.clone(),
        config: variant.name().to_string(),
        gaussians: t.model.len(),
        rounds: trainer.rounds(),
        steps,
        skipped_nonfinite_steps: t.skipped_nonfinite,
        frames_offered: counters.offered,
        keyframes_added: counters.added,
        skipped_eclipse: counters.skipped_eclipse,
        skipped_empty_mask: counters.skipped_empty_mask,
        skipped_view: counters.skipped_view,
        train_s,
        train_cpu_s,
        step_ms: if steps > 0 {
            1e3 * train_s / steps as f64
        } else {
            0.0
        },
        eval_s,
        curve,
        eval_curve,
        renders,
        eval,
        seen,
        black_eval,
        black_seen,
        window_fit,
        black_window,
        held_out,
        black_held_out,
        eval_covered,
        black_eval_covered,
    };
    progress(&super::ladder::ladder_line(&label, &outcome));
    progress(&format!(
        "{label}: PSNR {:.2} dB, SSIM {:.4} (masked {:.2} dB / {:.4}; seen views {:.2} dB, all-black there {:.2} dB; all-black {:.2} dB), {} Gaussians, {} rounds, {} steps, train {:.0} s ({:.1} ms/step), eval {:.0} s",
        outcome.eval.psnr_db,
        outcome.eval.ssim,
        outcome.eval.masked_psnr_db,
        outcome.eval.masked_ssim,
        outcome.seen.psnr_db,
        outcome.black_seen.psnr_db,
        outcome.black_eval.psnr_db,
        outcome.gaussians,
        outcome.rounds,
        outcome.steps,
        outcome.train_s,
        outcome.step_ms,
        outcome.eval_s
    ));
    Ok((outcome, trainer))
}
