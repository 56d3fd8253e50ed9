//! The `demo` job (the README's main job): an embedded small Cassini-like scenario, rendered
//! in memory, configuration (d) trained online, and everything a person wants to look at
//! written to one folder:
//! - `renders.png`: ground truth beside the model's render for a few evaluation views;
//! - `loss_curve.csv` (round, frame, mean loss, Gaussians, training seconds) and
//!   `loss_curve.png`;
//! - `metrics.json`: evaluation means (full frame and masked), per-view scores, counters;
//! - `model.ply` (baked for the first evaluation view's Sun and viewpoint, opens in ordinary
//!   3DGS viewers) and `checkpoint.bin` (the whole trainer, resumable bit-exactly).
//!
//! Invariants: the scenario and preset are compiled in (`include_str!`), so the demo needs no
//! files; the same binary and thread count give the same numbers.

use super::data::render_scene;
use super::figure::{grid_figure, Cell};
use super::preset::Preset;
use super::runner::{run_config, RoundPoint, RunOutcome};
use super::ExperimentError;
use crate::dataset::files;
use crate::dataset::plots::Canvas;
use crate::scenario::Scenario;
use gs_core::sunaware::{checkpoint, export, Variant};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The demo's scenario.
pub const DEMO_SCENARIO: &str = include_str!("demo_scenario.toml");
/// The demo's training settings.
pub const DEMO_PRESET: &str = include_str!("../../../config/presets/demo.toml");

/// What the demo wrote and measured.
#[derive(Clone, Debug, Serialize)]
pub struct DemoSummary {
    pub out_dir: PathBuf,
    pub frames: usize,
    pub eval_views: usize,
    pub width: u32,
    pub height: u32,
    pub render_s: f64,
    pub total_s: f64,
    pub run: RunOutcome,
}

/// Loss curve CSV: `round,frame_index,mean_loss,gaussians,train_s`.
pub(crate) fn curve_csv(curve: &[RoundPoint]) -> String {
    let mut out = String::from("round,frame_index,mean_loss,gaussians,train_s\n");
    for p in curve {
        let _ = writeln!(
            out,
            "{},{},{:.6},{},{:.3}",
            p.round, p.frame_index, p.mean_loss, p.gaussians, p.train_s
        );
    }
    out
}

/// Mean loss per round as a line plot (x: round, y: loss from 0 to the largest value).
pub(crate) fn curve_plot(curve: &[RoundPoint]) -> Canvas {
    let (w, h) = (640u32, 360u32);
    let (left, right, top, bottom) = (60.0, 20.0, 30.0, 40.0);
    let mut canvas = Canvas::new(w, h, [255, 255, 255]);
    let finite: Vec<&RoundPoint> = curve.iter().filter(|p| p.mean_loss.is_finite()).collect();
    let max_loss = finite
        .iter()
        .map(|p| p.mean_loss)
        .fold(0.0f64, f64::max)
        .max(1e-6);
    let max_round = finite.iter().map(|p| p.round).max().unwrap_or(1).max(1) as f64;
    let x_of = |round: f64| left + (w as f64 - left - right) * round / max_round;
    let y_of = |loss: f64| top + (h as f64 - top - bottom) * (1.0 - loss / max_loss);
    let axis = [60, 60, 60];
    canvas.line((left, top), (left, h as f64 - bottom), 1, axis);
    canvas.line(
        (left, h as f64 - bottom),
        (w as f64 - right, h as f64 - bottom),
        1,
        axis,
    );
    super::figure::draw_text(&mut canvas, 8, 8, "LOSS PER ROUND", 2, axis);
    super::figure::draw_text(
        &mut canvas,
        4,
        top as i64,
        &format!("{max_loss:.3}"),
        2,
        axis,
    );
    super::figure::draw_text(
        &mut canvas,
        4,
        (h as f64 - bottom) as i64 - 10,
        "0",
        2,
        axis,
    );
    super::figure::draw_text(
        &mut canvas,
        (w as f64 - right) as i64 - 60,
        (h as f64 - bottom) as i64 + 10,
        &format!("{}", max_round as u64),
        2,
        axis,
    );
    super::figure::draw_text(
        &mut canvas,
        left as i64,
        (h as f64 - bottom) as i64 + 10,
        "ROUND",
        2,
        axis,
    );
    for pair in finite.windows(2) {
        canvas.line(
            (x_of(pair[0].round as f64), y_of(pair[0].mean_loss)),
            (x_of(pair[1].round as f64), y_of(pair[1].mean_loss)),
            2,
            [30, 80, 200],
        );
    }
    canvas
}

/// The demo's scenario and preset (parsed from the embedded text).
pub fn demo_inputs() -> Result<(Scenario, Preset), ExperimentError> {
    let preset = Preset::from_toml_str(DEMO_PRESET, "config/presets/demo.toml")?;
    let scenario = Scenario::from_toml_str(DEMO_SCENARIO, Path::new("."))?;
    Ok((preset.apply(&scenario)?, preset))
}

/// Runs the demo into `out_dir` with `scenario` and `preset` (already applied).
pub fn run_demo_with(
    scenario: &Scenario,
    preset: &Preset,
    out_dir: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<DemoSummary, ExperimentError> {
    let started = Instant::now();
    std::fs::create_dir_all(out_dir).map_err(|e| ExperimentError::io(out_dir, e))?;
    let scene = render_scene(scenario, preset.init_points as usize, progress)?;
    let figure_views = preset.figure_views as usize;
    let (run, trainer) = run_config(&scene, preset, Variant::D, figure_views, progress)?;
    let k = scene.intrinsics;
    let rows: Vec<Vec<Cell>> = scene
        .eval
        .iter()
        .zip(&run.renders)
        .zip(&run.eval.per_view)
        .map(|((view, render), m)| {
            vec![
                Cell {
                    rgb8: Some(view.rgb8.clone()),
                    caption: format!("VIEW {}", view.index),
                },
                Cell {
                    rgb8: Some(render.clone()),
                    caption: format!("{:.2} DB  SSIM {:.3}", m.psnr_db, m.ssim),
                },
            ]
        })
        .collect();
    let labels = ["GROUND TRUTH".to_string(), "(D) MODEL".to_string()];
    let figure = grid_figure(k.width, k.height, &labels, &[], &rows, 320);
    files::write_png_rgb(
        &out_dir.join("renders.png"),
        figure.width,
        figure.height,
        &figure.rgb8,
    )?;
    let csv_path = out_dir.join("loss_curve.csv");
    std::fs::write(&csv_path, curve_csv(&run.curve))
        .map_err(|e| ExperimentError::io(&csv_path, e))?;
    let plot = curve_plot(&run.curve);
    files::write_png_rgb(
        &out_dir.join("loss_curve.png"),
        plot.width,
        plot.height,
        &plot.rgb8,
    )?;
    let model = &trainer.trainer().model;
    if let Some(view) = scene.eval.first() {
        let camera = super::evaluate::camera_of(&k, view);
        export::save_baked_ply(
            model,
            camera.position(),
            super::evaluate::sun_of(view),
            out_dir.join("model.ply"),
        )?;
    }
    checkpoint::save_file(trainer.trainer(), out_dir.join("checkpoint.bin"))?;
    let summary = DemoSummary {
        out_dir: out_dir.to_path_buf(),
        frames: scene.frames.len(),
        eval_views: scene.eval.len(),
        width: k.width,
        height: k.height,
        render_s: scene.render_s,
        total_s: started.elapsed().as_secs_f64(),
        run,
    };
    let json_path = out_dir.join("metrics.json");
    let json =
        serde_json::to_string_pretty(&summary).map_err(|e| ExperimentError::io(&json_path, e))?;
    std::fs::write(&json_path, json).map_err(|e| ExperimentError::io(&json_path, e))?;
    Ok(summary)
}

/// The demo with its embedded scenario and preset.
pub fn run_demo(
    out_dir: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<DemoSummary, ExperimentError> {
    let (scenario, preset) = demo_inputs()?;
    run_demo_with(&scenario, &preset, out_dir, progress)
}
