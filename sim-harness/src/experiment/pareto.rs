//! Run time against error: one-at-a-time sweeps of the knobs that trade training time for
//! evaluation error around a base preset, the Pareto front of (training CPU time, PSNR), and
//! the `pareto` job that writes `pareto.csv`, `pareto.md` and `pareto.png`.
//!
//! Also the measuring instruments the skips table and the window ablation share:
//! `reset_peak_rss` / `peak_rss_mb`
//! (`VmHWM` of /proc/self/status, reset per run through /proc/self/clear_refs), [`Knob`] and
//! [`Setting`] (named preset overrides), `run_settings` (one row per setting) and
//! [`draw_xy_panel`] (line and scatter plots on the dataset plots' canvas).
//!
//! Invariants: a setting changes only the knobs it names, the rest come from the base preset;
//! settings run one after another, in the given order, configuration = the preset's first;
//! a point is on the front iff no other point has time <= and PSNR >= with one of them
//! strict (equal points are both on it; a non-finite point is never on it and dominates
//! nothing); the CSV header is [`CSV_HEADER`] and rows keep the run order. With the same
//! seed and thread count every metric is bit-identical between runs (times are not).

mod plot;
mod settings;
mod table;

pub(crate) use plot::write_canvas;
pub use plot::{draw_xy_panel, pareto_plot, PlotSeries};
pub use settings::{
    default_settings, describe, optional_settings, precision_name, select_settings, Knob, Setting,
};
pub(crate) use table::masked_cell;
pub use table::{from_csv, to_csv, to_markdown, CSV_HEADER};

use super::cache::scene_key;
use super::data::{load_or_render_scene, SceneData};
use super::ladder::{self, Ladder};
use super::preset::Preset;
use super::runner::run_config;
use super::write_text;
use super::ExperimentError;
use crate::scenario::Scenario;
use gs_core::sunaware::Variant;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The built-in target `name` (cassini, rosetta or starlink).
pub fn builtin_scenario(name: &str) -> Result<Scenario, ExperimentError> {
    super::table_job::builtin_scenarios()?
        .into_iter()
        .find(|s| s.name == name)
        .ok_or_else(|| {
            ExperimentError::Invalid(format!(
                "unknown target {name:?}: the built-in targets are cassini, rosetta and starlink"
            ))
        })
}

/// Resets the peak resident set size (Linux `clear_refs` 5). False where that is not
/// possible; [`peak_rss_mb`] then reports the peak since the process started.
pub(crate) fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Peak resident set size since the last reset (or the process start), MB (10^6 bytes);
/// NaN where /proc is not available.
pub(crate) fn peak_rss_mb() -> f64 {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return f64::NAN;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb * 1024.0 / 1e6)
}

/// One trained and evaluated setting.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepRow {
    pub setting: String,
    pub target: String,
    pub config: String,
    pub downsample: u32,
    pub width: u32,
    pub height: u32,
    pub max_gaussians: usize,
    pub init_points: u32,
    pub feature_dim: usize,
    pub encoding_frequencies: usize,
    pub window: usize,
    pub rounds_per_window_change: u32,
    pub passes_per_round: u32,
    pub skip_eclipse: bool,
    pub skip_unlit: bool,
    pub skip_unchanged_window: bool,
    pub frames: usize,
    pub rounds: u64,
    pub steps: u64,
    /// Wall time inside training rounds, seconds.
    pub train_s: f64,
    /// Process CPU time inside training rounds, seconds.
    pub train_cpu_s: f64,
    pub step_ms: f64,
    pub psnr_db: f64,
    pub ssim: f64,
    pub masked_psnr_db: f64,
    /// PSNR of an all-black render on the same evaluation views (the floor to beat), dB.
    pub black_psnr_db: f64,
    pub gaussians: usize,
    /// Peak resident memory of the process during training and evaluation, MB.
    pub peak_rss_mb: f64,
    /// Masked metrics on every rung beside black's (empty when read from a CSV written
    /// before the ladder existed).
    pub ladder: Ladder,
}

/// `front[i]`: point i = (time, psnr) is not dominated (less or equal time and greater or
/// equal PSNR, one strictly) by any other finite point. Non-finite points are never on it.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    points
        .iter()
        .map(|p| {
            finite(p)
                && !points
                    .iter()
                    .any(|q| finite(q) && q.0 <= p.0 && q.1 >= p.1 && (q.0 < p.0 || q.1 > p.1))
        })
        .collect()
}

/// The scene a preset needs, rendered (or read from `cache_dir`), reusing `last` when its
/// key matches.
fn scene_for(
    scenario: &Scenario,
    preset: &Preset,
    cache_dir: &Path,
    last: &mut Option<(u64, SceneData)>,
    progress: &mut dyn FnMut(&str),
) -> Result<(), ExperimentError> {
    let applied = preset.apply(scenario)?;
    let key = scene_key(&applied, preset.init_points as usize);
    if last.as_ref().map(|(k, _)| *k) != Some(key) {
        *last = None;
        let scene =
            load_or_render_scene(&applied, preset.init_points as usize, cache_dir, progress)?;
        *last = Some((key, scene));
    }
    Ok(())
}

/// Trains and evaluates one setting on `scene`.
pub(crate) fn run_one(
    scene: &SceneData,
    preset: &Preset,
    setting_name: &str,
    progress: &mut dyn FnMut(&str),
) -> Result<SweepRow, ExperimentError> {
    let variant: Variant = preset.configs[0].parse()?;
    reset_peak_rss();
    let (run, trainer) = run_config(scene, preset, variant, 0, progress)?;
    drop(trainer);
    Ok(SweepRow {
        setting: setting_name.to_string(),
        target: scene.name.clone(),
        config: variant.name().to_string(),
        downsample: preset.downsample,
        width: scene.intrinsics.width,
        height: scene.intrinsics.height,
        max_gaussians: preset.max_gaussians,
        init_points: preset.init_points,
        feature_dim: preset.feature_dim,
        encoding_frequencies: preset.encoding_frequencies,
        window: preset.window,
        rounds_per_window_change: preset.rounds_per_window_change,
        passes_per_round: preset.passes_per_round,
        skip_eclipse: preset.skip_eclipse,
        skip_unlit: preset.skip_unlit,
        skip_unchanged_window: preset.skip_unchanged_window,
        frames: scene.frames.len(),
        rounds: run.rounds,
        steps: run.steps,
        train_s: run.train_s,
        train_cpu_s: run.train_cpu_s,
        step_ms: run.step_ms,
        psnr_db: run.eval.psnr_db,
        ssim: run.eval.ssim,
        masked_psnr_db: run.eval.masked_psnr_db,
        black_psnr_db: run.black_eval.psnr_db,
        gaussians: run.gaussians,
        peak_rss_mb: peak_rss_mb(),
        ladder: Ladder::of(&run),
    })
}

/// Runs `settings` on `scenario` around `base`, one after another; `after_each` sees the
/// rows so far (to rewrite output files, so an interrupted job keeps its finished rows).
pub(crate) fn run_settings(
    scenario: &Scenario,
    base: &Preset,
    settings: &[Setting],
    cache_dir: &Path,
    progress: &mut dyn FnMut(&str),
    after_each: &mut dyn FnMut(&[SweepRow]) -> Result<(), ExperimentError>,
) -> Result<Vec<SweepRow>, ExperimentError> {
    let presets: Vec<Preset> = settings
        .iter()
        .map(|s| s.preset(base))
        .collect::<Result<_, _>>()?;
    let started = Instant::now();
    let mut last = None;
    let mut rows = Vec::new();
    for (i, (setting, preset)) in settings.iter().zip(&presets).enumerate() {
        progress(&format!(
            "[{}/{}] setting {} ({})",
            i + 1,
            settings.len(),
            setting.name,
            describe(&setting.knobs)
        ));
        scene_for(scenario, preset, cache_dir, &mut last, progress)?;
        let scene = &last.as_ref().expect("scene_for filled it").1;
        let row = run_one(scene, preset, &setting.name, &mut |l| progress(l))?;
        progress(&format!(
            "[{}/{}] {}: masked PSNR dB (black) {}, full {:.2} dB, SSIM {:.4}, train {:.1} s wall / {:.1} s CPU, {:.1} ms/step, {} Gaussians, peak {:.0} MB; {:.0} s elapsed",
            i + 1,
            settings.len(),
            setting.name,
            ladder::markdown_cell(row.ladder.eval.as_ref()).replace("**", ""),
            row.psnr_db,
            row.ssim,
            row.train_s,
            row.train_cpu_s,
            row.step_ms,
            row.gaussians,
            row.peak_rss_mb,
            started.elapsed().as_secs_f64()
        ));
        rows.push(row);
        after_each(&rows)?;
    }
    Ok(rows)
}

/// What the pareto job needs.
#[derive(Clone, Debug)]
pub struct ParetoJob {
    pub base: Preset,
    /// The scenario before the preset is applied.
    pub scenario: Scenario,
    pub settings: Vec<Setting>,
    pub out_dir: PathBuf,
}

/// Runs the sweep and writes `pareto.csv`, `pareto.md` (rewritten after every run) and
/// `pareto.png`.
pub fn run_pareto(
    job: &ParetoJob,
    progress: &mut dyn FnMut(&str),
) -> Result<(Vec<SweepRow>, Vec<bool>), ExperimentError> {
    if job.settings.is_empty() {
        return Err(ExperimentError::Invalid(
            "pareto: no settings to run".into(),
        ));
    }
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let write = |rows: &[SweepRow]| -> Result<Vec<bool>, ExperimentError> {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .map(|r| (r.train_cpu_s, r.masked_psnr_db))
            .collect();
        let front = pareto_front(&points);
        write_text(&out.join("pareto.csv"), &to_csv(rows, &front))?;
        write_text(&out.join("pareto.md"), &to_markdown(rows, &front))?;
        Ok(front)
    };
    let rows = run_settings(
        &job.scenario,
        &job.base,
        &job.settings,
        &out.join("cache"),
        progress,
        &mut |rows| write(rows).map(|_| ()),
    )?;
    let front = write_outputs(out, &rows)?;
    Ok((rows, front))
}

/// Writes `pareto.csv`, `pareto.md` and `pareto.png` for `rows` into `out` (the front
/// computed over these rows); returns the front.
pub fn write_outputs(out: &Path, rows: &[SweepRow]) -> Result<Vec<bool>, ExperimentError> {
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let points: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| (r.train_cpu_s, r.masked_psnr_db))
        .collect();
    let front = pareto_front(&points);
    write_text(&out.join("pareto.csv"), &to_csv(rows, &front))?;
    write_text(&out.join("pareto.md"), &to_markdown(rows, &front))?;
    let mut targets: Vec<String> = rows.iter().map(|r| r.target.to_uppercase()).collect();
    targets.dedup();
    let title = format!(
        "{}: TRAINING CPU TIME VS EVAL PSNR ({} SETTINGS)",
        targets.join("+"),
        rows.len()
    );
    write_canvas(&out.join("pareto.png"), &pareto_plot(rows, &front, &title))?;
    Ok(front)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gs_core::nn::MatmulPrecision;
    use plot::ticks;

    #[test]
    fn ticks_are_round_numbers_inside_the_range() {
        assert_eq!(ticks(0.0, 10.0, false), vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        assert_eq!(ticks(15.0, 250.0, true), vec![20.0, 50.0, 100.0, 200.0]);
        assert!(ticks(1.0, 1.0, false).is_empty());
    }

    #[test]
    fn knobs_change_only_what_they_name() {
        let base = Preset::default();
        let p = Setting::new("x", &[Knob::Window(4), Knob::SkipUnlit(true)])
            .preset(&base)
            .unwrap();
        assert_eq!((p.window, p.skip_unlit), (4, true));
        assert_eq!(p.downsample, base.downsample);
        assert_eq!(p.max_gaussians, base.max_gaussians);
        // A cap below the initial points lowers them to half the cap.
        let p = Setting::new("c", &[Knob::MaxGaussians(1000)])
            .preset(&base)
            .unwrap();
        assert_eq!((p.max_gaussians, p.init_points), (1000, 500));
        // An invalid value is an error naming the field.
        let e = Setting::new("w", &[Knob::Window(1)])
            .preset(&base)
            .unwrap_err()
            .to_string();
        assert!(e.contains("window"), "{e}");
    }

    /// The network settings the lead runs by name: not in the default sweep, and each sets
    /// only its knob (which reaches the trainer's configuration).
    #[test]
    fn network_settings_are_optional_and_set_their_knob() {
        let names: Vec<String> = ["mlp128", "mlp64", "bf16"].map(String::from).to_vec();
        assert!(default_settings().iter().all(|s| !names.contains(&s.name)));
        let base = Preset::default();
        let presets: Vec<Preset> = select_settings(&names)
            .unwrap()
            .iter()
            .map(|s| s.preset(&base).unwrap())
            .collect();
        assert_eq!(presets[0].appearance_hidden_width, 128);
        assert_eq!(presets[1].appearance_hidden_width, 64);
        assert_eq!(presets[2].mlp_precision, "bf16");
        assert_eq!(presets[2].appearance_hidden_width, 256);
        assert_eq!(presets[0].mlp_precision, "f32");
        let c = super::super::runner::online_config(&presets[2], Variant::D).unwrap();
        assert_eq!(c.model.mlp_precision, MatmulPrecision::Bf16);
        let c = super::super::runner::online_config(&presets[1], Variant::D).unwrap();
        assert_eq!(c.model.appearance_hidden_width, 64);
        assert_eq!(
            describe(&[Knob::MlpPrecision(MatmulPrecision::Bf16)]),
            "mlp_precision=bf16"
        );
    }

    #[test]
    fn peak_memory_and_cpu_time_are_measured() {
        let process_cpu_s = || gs_core::machine::process_cpu_s().expect("Linux reports CPU time");
        let before = process_cpu_s();
        let mut x = 0u64;
        for i in 0..3_000_000u64 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(i);
        }
        assert!(x != 1);
        assert!(process_cpu_s() >= before);
        let mb = peak_rss_mb();
        assert!(mb.is_finite() && mb > 0.5, "{mb}");
    }
}
