//! The `table` job: every configuration of a preset on every scenario (the three built-in
//! targets unless scenario files are given), written to `table.csv`, `table.md`,
//! `figure.png` and `runs.json` (per-run details: masked metrics, counters, loss curves).
//!
//! Invariants: scenarios run one after another, configurations in the preset's order; the
//! CSV and Markdown are rewritten after every run, so an interrupted job leaves the finished
//! rows; rendered scenes are cached under `OUT/cache/` and reused when their key matches.

use super::data::{load_or_render_scene, SceneData};
use super::evaluate::score_view;
use super::figure::{grid_figure, Cell};
use super::preset::Preset;
use super::runner::{run_config, RunOutcome};
use super::table::{config_label, target_label, to_csv, to_markdown, ResultRow};
use super::write_text;
use super::ExperimentError;
use crate::dataset::{files, generate, GenerateOptions};
use crate::scenario::Scenario;
use gs_core::sunaware::Variant;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The three built-in targets' scenario files, embedded.
pub(crate) const BUILTIN_SCENARIOS: [(&str, &str); 3] = [
    (
        "cassini",
        include_str!("../../../config/scenarios/cassini.toml"),
    ),
    (
        "rosetta",
        include_str!("../../../config/scenarios/rosetta.toml"),
    ),
    (
        "starlink",
        include_str!("../../../config/scenarios/starlink.toml"),
    ),
];

/// The built-in targets' scenarios.
pub fn builtin_scenarios() -> Result<Vec<Scenario>, ExperimentError> {
    BUILTIN_SCENARIOS
        .iter()
        .map(|(name, text)| {
            let mut s = Scenario::from_toml_str(text, Path::new("."))?;
            s.name = name.to_string();
            Ok(s)
        })
        .collect()
}

/// What the job needs.
#[derive(Clone, Debug)]
pub struct TableJob {
    pub preset: Preset,
    /// Scenarios before the preset is applied.
    pub scenarios: Vec<Scenario>,
    pub out_dir: PathBuf,
    /// Also write each scenario's dataset (as `sim-harness generate` would) to `OUT/data/NAME`.
    pub keep_data: bool,
}

/// What the job produced.
#[derive(Clone, Debug)]
pub struct TableResult {
    pub rows: Vec<ResultRow>,
    pub runs: Vec<RunOutcome>,
    pub render_s: f64,
    pub total_s: f64,
}

fn row_of(run: &RunOutcome) -> ResultRow {
    ResultRow {
        target: run.target.clone(),
        config: run.config.clone(),
        ssim: run.eval.ssim,
        psnr: run.eval.psnr_db,
        gaussians: run.gaussians,
        train_s: run.train_s,
        step_ms: run.step_ms,
        ladder: super::ladder::Ladder::of(run),
    }
}

/// Details behind the table: target-pixel (masked) metrics, the same metrics on views the
/// model trained on, an all-black render's score, and the training counters.
pub(crate) fn diagnostics_markdown(runs: &[RunOutcome]) -> String {
    use std::fmt::Write as _;
    let mut out = String::from(
        "Details (PSNR dB / SSIM; masked = target pixels only; seen = up to 20 lit training \
         frames; black = an all-black render on the evaluation views, black seen = on the seen \
         frames):\n\n\
         | Target | Config. | eval masked | seen full | seen masked | black full | black masked | black seen full | rounds | steps | eclipse frames skipped |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in runs {
        let _ = writeln!(
            out,
            "| {} | {} | {:.2} / {:.4} | {:.2} / {:.4} | {:.2} / {:.4} | {:.2} / {:.4} | {:.2} / {:.4} | {:.2} / {:.4} | {} | {} | {} |",
            target_label(&r.target),
            r.config,
            r.eval.masked_psnr_db,
            r.eval.masked_ssim,
            r.seen.psnr_db,
            r.seen.ssim,
            r.seen.masked_psnr_db,
            r.seen.masked_ssim,
            r.black_eval.psnr_db,
            r.black_eval.ssim,
            r.black_eval.masked_psnr_db,
            r.black_eval.masked_ssim,
            r.black_seen.psnr_db,
            r.black_seen.ssim,
            r.rounds,
            r.steps,
            r.skipped_eclipse
        );
    }
    out
}

/// Ground truth beside each configuration for the first `views` evaluation views of each
/// scene; captions give each image's full-frame PSNR.
pub(crate) fn comparison_figure(
    scenes: &[SceneData],
    runs: &[RunOutcome],
    configs: &[String],
    views: usize,
) -> Result<crate::dataset::plots::Canvas, ExperimentError> {
    let mut labels = vec!["GROUND TRUTH".to_string()];
    labels.extend(configs.iter().map(|c| config_label(c).to_uppercase()));
    let (mut rows, mut row_labels) = (Vec::new(), Vec::new());
    let Some(first) = scenes.first() else {
        return Ok(grid_figure(1, 1, &labels, &[], &[], 1));
    };
    let k = first.intrinsics;
    for scene in scenes {
        if scene.intrinsics.width != k.width || scene.intrinsics.height != k.height {
            return Err(ExperimentError::Invalid(format!(
                "figure: scene {} is {}x{}, the first is {}x{}",
                scene.name, scene.intrinsics.width, scene.intrinsics.height, k.width, k.height
            )));
        }
        for (v, view) in scene.eval.iter().take(views).enumerate() {
            let mut row = vec![Cell {
                rgb8: Some(view.rgb8.clone()),
                caption: format!("VIEW {}", view.index),
            }];
            for c in configs {
                let run = runs
                    .iter()
                    .find(|r| r.target == scene.name && &r.config == c);
                let cell = match run.and_then(|r| r.renders.get(v)) {
                    Some(rgb8) => {
                        let image: Vec<f32> = rgb8.iter().map(|&b| b as f32 / 255.0).collect();
                        let m = score_view(&scene.intrinsics, view, &image)?;
                        Cell {
                            rgb8: Some(rgb8.clone()),
                            caption: format!("{:.2} DB", m.psnr_db),
                        }
                    }
                    None => Cell::default(),
                };
                row.push(cell);
            }
            rows.push(row);
            row_labels.push(target_label(&scene.name).to_uppercase());
        }
    }
    Ok(grid_figure(
        k.width,
        k.height,
        &labels,
        &row_labels,
        &rows,
        200,
    ))
}

/// Runs the job, reporting progress lines.
pub fn run_table(
    job: &TableJob,
    progress: &mut dyn FnMut(&str),
) -> Result<TableResult, ExperimentError> {
    let started = Instant::now();
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let variants: Vec<Variant> = job
        .preset
        .configs
        .iter()
        .map(|c| c.parse::<Variant>())
        .collect::<Result<_, _>>()?;
    let figure_views = job.preset.figure_views as usize;
    let (mut rows, mut runs, mut scenes) = (Vec::new(), Vec::new(), Vec::new());
    let mut render_s = 0.0;
    for scenario in &job.scenarios {
        let scenario = job.preset.apply(scenario)?;
        if job.keep_data {
            let dir = out
                .join("data")
                .join(super::cache::safe_name(&scenario.name));
            progress(&format!(
                "{}: writing the dataset to {}",
                scenario.name,
                dir.display()
            ));
            generate(
                &scenario,
                &dir,
                GenerateOptions { overwrite: true },
                &mut |_| {},
            )?;
        }
        let scene = load_or_render_scene(
            &scenario,
            job.preset.init_points as usize,
            &out.join("cache"),
            progress,
        )?;
        render_s += scene.render_s;
        for &variant in &variants {
            let (run, _) = run_config(&scene, &job.preset, variant, figure_views, progress)?;
            rows.push(row_of(&run));
            runs.push(run);
            write_text(&out.join("table.csv"), &to_csv(&rows))?;
            let markdown = format!("{}\n{}", to_markdown(&rows), diagnostics_markdown(&runs));
            write_text(&out.join("table.md"), &markdown)?;
            write_text(
                &out.join("runs.json"),
                &serde_json::to_string_pretty(&runs).map_err(|e| ExperimentError::io(out, e))?,
            )?;
            progress(&format!(
                "{} of {} runs done, {:.0} s elapsed",
                runs.len(),
                variants.len() * job.scenarios.len(),
                started.elapsed().as_secs_f64()
            ));
        }
        // Keep only what the figure needs of each scene.
        let mut kept = scene;
        kept.frames.clear();
        kept.eval.truncate(figure_views);
        scenes.push(kept);
    }
    let figure = comparison_figure(&scenes, &runs, &job.preset.configs, figure_views)?;
    files::write_png_rgb(
        &out.join("figure.png"),
        figure.width,
        figure.height,
        &figure.rgb8,
    )?;
    Ok(TableResult {
        rows,
        runs,
        render_s,
        total_s: started.elapsed().as_secs_f64(),
    })
}
