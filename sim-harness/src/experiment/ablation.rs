//! The keyframe-window ablation (the paper's Fig. 6): the same preset with W = 5, 10, 20, 40
//! on each target; metrics and training time per (target, W) in `window.csv` / `window.md`
//! and `window.png` (PSNR against W per target on the top panel, training CPU time on the
//! bottom one).
//!
//! Invariants: targets run one after another, window sizes in the given order; only W
//! changes between runs of a target; the CSV is the Pareto sweep's schema
//! ([`super::pareto::CSV_HEADER`]) with the setting named `wN`, rewritten after every run.

use super::ladder::{self, Ladder};
use super::pareto::{
    draw_xy_panel, masked_cell, run_settings, to_csv, write_canvas, Knob, PlotSeries, Setting,
    SweepRow,
};
use super::preset::Preset;
use super::table::target_label;
use super::write_text;
use super::ExperimentError;
use crate::dataset::plots::{Canvas, Rgb};
use crate::scenario::Scenario;
use std::fmt::Write as _;
use std::path::PathBuf;

/// What the window ablation needs.
#[derive(Clone, Debug)]
pub struct WindowJob {
    pub base: Preset,
    /// Scenarios before the preset is applied.
    pub scenarios: Vec<Scenario>,
    pub windows: Vec<usize>,
    pub out_dir: PathBuf,
}

const COLOURS: [Rgb; 6] = [
    [30, 80, 200],
    [200, 40, 40],
    [30, 150, 60],
    [150, 60, 170],
    [220, 140, 20],
    [60, 60, 60],
];

/// Markdown: one line per W, per target masked PSNR (black) / SSIM / training CPU s / wall
/// s / steps, then the ladder of every run.
pub fn to_markdown(rows: &[SweepRow]) -> String {
    let mut targets: Vec<&str> = Vec::new();
    let mut windows: Vec<usize> = Vec::new();
    for r in rows {
        if !targets.contains(&r.target.as_str()) {
            targets.push(&r.target);
        }
        if !windows.contains(&r.window) {
            windows.push(r.window);
        }
    }
    let mut out = String::from("| W |");
    for t in &targets {
        let n = target_label(t);
        let _ = write!(
            out,
            " {n} masked PSNR dB (black) | {n} SSIM | {n} steps | {n} train CPU s | {n} train wall s |"
        );
    }
    out.push_str("\n|---:|");
    for _ in &targets {
        out.push_str("---:|---:|---:|---:|---:|");
    }
    out.push('\n');
    for w in &windows {
        let _ = write!(out, "| {w} |");
        for t in &targets {
            match rows.iter().find(|r| r.target == *t && r.window == *w) {
                Some(r) => {
                    let _ = write!(
                        out,
                        " {} | {:.4} | {} | {:.1} | {:.1} |",
                        masked_cell(r),
                        r.ssim,
                        r.steps,
                        r.train_cpu_s,
                        r.train_s
                    );
                }
                None => out.push_str(" - | - | - | - | - |"),
            }
        }
        out.push('\n');
    }
    let ladders: Vec<(String, Ladder)> = rows
        .iter()
        .filter(|r| r.ladder.eval.is_some())
        .map(|r| {
            (
                format!("{} W = {}", target_label(&r.target), r.window),
                r.ladder,
            )
        })
        .collect();
    if !ladders.is_empty() {
        out.push('\n');
        out.push_str(&ladder::to_markdown(&ladders));
    }
    out
}

/// Two panels: evaluation masked PSNR (the target's pixels) against W (top, with each
/// target's all-black score as a pale line) and training CPU time against W (bottom), one
/// line per target; W on a log axis.
pub fn window_plot(rows: &[SweepRow]) -> Canvas {
    let mut targets: Vec<&str> = Vec::new();
    for r in rows {
        if !targets.contains(&r.target.as_str()) {
            targets.push(&r.target);
        }
    }
    let series = |value: fn(&SweepRow) -> f64| -> Vec<PlotSeries> {
        targets
            .iter()
            .enumerate()
            .map(|(k, t)| {
                let mut points: Vec<(f64, f64)> = rows
                    .iter()
                    .filter(|r| r.target == *t)
                    .map(|r| (r.window as f64, value(r)))
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                PlotSeries {
                    name: t.to_uppercase(),
                    color: COLOURS[k % COLOURS.len()],
                    points,
                    line: true,
                }
            })
            .collect()
    };
    // Each target's all-black score on the same views, in a pale shade of its colour: the
    // floor a model must clear (the same views at every W, so a flat line).
    let black_masked = |r: &SweepRow| r.ladder.eval.map_or(f64::NAN, |e| e.black_masked_psnr_db);
    let mut psnr = series(|r| r.masked_psnr_db);
    let floors: Vec<PlotSeries> = series(black_masked)
        .into_iter()
        .filter(|s| s.points.iter().all(|p| p.1.is_finite()))
        .map(|s| PlotSeries {
            name: format!("{} ALL-BLACK", s.name),
            color: s.color.map(|c| c / 2 + 128),
            ..s
        })
        .collect();
    psnr.extend(floors);
    let (w, h) = (900i64, 520i64);
    let mut canvas = Canvas::new(w as u32, 2 * h as u32, [255, 255, 255]);
    draw_xy_panel(
        &mut canvas,
        (0, 0, w, h),
        "EVAL MASKED PSNR VS KEYFRAME WINDOW W (PALE: ALL-BLACK RENDER)",
        "W (LOG)",
        "MASKED PSNR DB",
        true,
        &psnr,
        &[],
    );
    draw_xy_panel(
        &mut canvas,
        (0, h, w, h),
        "TRAINING CPU TIME VS W",
        "W (LOG)",
        "CPU S",
        true,
        &series(|r| r.train_cpu_s),
        &[],
    );
    canvas
}

/// Runs every (target, W) and writes `window.csv`, `window.md` (after every run) and
/// `window.png`.
pub fn run_window_ablation(
    job: &WindowJob,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<SweepRow>, ExperimentError> {
    if job.windows.is_empty() || job.scenarios.is_empty() {
        return Err(ExperimentError::Invalid(
            "ablation-window: needs at least one window size and one scenario".into(),
        ));
    }
    let settings: Vec<Setting> = job
        .windows
        .iter()
        .map(|&w| Setting::new(&format!("w{w}"), &[Knob::Window(w)]))
        .collect();
    // Bad sizes fail before anything runs.
    for s in &settings {
        s.preset(&job.base)?;
    }
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let mut rows: Vec<SweepRow> = Vec::new();
    for scenario in &job.scenarios {
        progress(&format!("target {}", scenario.name));
        let done = rows.clone();
        let target_rows = run_settings(
            scenario,
            &job.base,
            &settings,
            &out.join("cache"),
            progress,
            &mut |now| {
                let all: Vec<SweepRow> = done.iter().chain(now).cloned().collect();
                write_text(&out.join("window.csv"), &to_csv(&all, &[]))?;
                write_text(&out.join("window.md"), &to_markdown(&all))
            },
        )?;
        rows.extend(target_rows);
    }
    write_canvas(&out.join("window.png"), &window_plot(&rows))?;
    Ok(rows)
}
