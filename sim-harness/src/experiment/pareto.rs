//! Run time against error: one-at-a-time sweeps of the knobs that trade training time for
//! evaluation error around a base preset, the Pareto front of (training CPU time, PSNR), and
//! the `pareto` job that writes `pareto.csv`, `pareto.md` and `pareto.png`.
//!
//! Also the measuring instruments the skips table and the window ablation share:
//! [`reset_peak_rss`] / [`peak_rss_mb`]
//! (`VmHWM` of /proc/self/status, reset per run through /proc/self/clear_refs), [`Knob`] and
//! [`Setting`] (named preset overrides), [`run_settings`] (one row per setting) and
//! [`draw_xy_panel`] (line and scatter plots on the dataset plots' canvas).
//!
//! Invariants: a setting changes only the knobs it names, the rest come from the base preset;
//! settings run one after another, in the given order, configuration = the preset's first;
//! a point is on the front iff no other point has time <= and PSNR >= with one of them
//! strict (equal points are both on it; a non-finite point is never on it and dominates
//! nothing); the CSV header is [`CSV_HEADER`] and rows keep the run order. With the same
//! seed and thread count every metric is bit-identical between runs (times are not).

use super::cache::scene_key;
use super::data::{load_or_render_scene, SceneData};
use super::figure::{draw_text, text_width};
use super::ladder::{self, Ladder};
use super::preset::Preset;
use super::runner::run_config;
use super::write_text;
use super::ExperimentError;
use crate::dataset::files;
use crate::dataset::plots::{Canvas, Rgb};
use crate::scenario::Scenario;
use gs_core::nn::MatmulPrecision;
use gs_core::sunaware::Variant;
use std::fmt::Write as _;
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
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Peak resident set size since the last reset (or the process start), MB (10^6 bytes);
/// NaN where /proc is not available.
pub fn peak_rss_mb() -> f64 {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return f64::NAN;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb * 1024.0 / 1e6)
}

/// One knob of a preset set to a value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Knob {
    /// SPEED camera divided by this (image resolution).
    Downsample(u32),
    /// Gaussian cap (initial points are capped at half of it).
    MaxGaussians(usize),
    /// Width of the appearance feature f_i (Phi's per-Gaussian input).
    FeatureDim(usize),
    EncodingFrequencies(usize),
    RoundsPerWindowChange(u32),
    PassesPerRound(u32),
    Window(usize),
    SkipEclipse(bool),
    SkipUnlit(bool),
    SkipUnchangedWindow(bool),
    /// Phi and Psi only for the Gaussians the blend reads.
    SkipNoncontributingMlp(bool),
    /// Training frames carry their masks and the loss is weighed by them.
    MaskedLoss(bool),
    /// gs-core's early frustum cull.
    CullOutsideFrustum(bool),
    /// Blending stops at transmittance 1e-4.
    EarlyTermination(bool),
    /// With masked training: only the tiles the masked loss reads are blended.
    SkipMaskedBackgroundTiles(bool),
    /// Hidden width of Phi's layers.
    AppearanceHiddenWidth(usize),
    /// Arithmetic of the networks' matrix products.
    MlpPrecision(MatmulPrecision),
    Config(Variant),
}

impl Knob {
    /// Sets this knob on `preset`.
    pub fn apply(&self, preset: &mut Preset) {
        match *self {
            Knob::Downsample(v) => preset.downsample = v,
            Knob::MaxGaussians(v) => {
                preset.max_gaussians = v;
                preset.init_points = preset.init_points.min((v / 2).max(2) as u32);
            }
            Knob::FeatureDim(v) => preset.feature_dim = v,
            Knob::EncodingFrequencies(v) => preset.encoding_frequencies = v,
            Knob::RoundsPerWindowChange(v) => preset.rounds_per_window_change = v,
            Knob::PassesPerRound(v) => preset.passes_per_round = v,
            Knob::Window(v) => preset.window = v,
            Knob::SkipEclipse(v) => preset.skip_eclipse = v,
            Knob::SkipUnlit(v) => preset.skip_unlit = v,
            Knob::SkipUnchangedWindow(v) => preset.skip_unchanged_window = v,
            Knob::SkipNoncontributingMlp(v) => preset.skip_noncontributing_in_mlp = v,
            Knob::MaskedLoss(v) => preset.masked_loss = v,
            Knob::CullOutsideFrustum(v) => preset.cull_outside_frustum = v,
            Knob::EarlyTermination(v) => preset.early_termination = v,
            Knob::SkipMaskedBackgroundTiles(v) => preset.skip_masked_background_tiles = v,
            Knob::AppearanceHiddenWidth(v) => preset.appearance_hidden_width = v,
            Knob::MlpPrecision(v) => preset.mlp_precision = precision_name(v).into(),
            Knob::Config(v) => preset.configs = vec![v.name().to_string()],
        }
    }
}

/// The preset's name of a matrix-product precision (`Preset::mlp_precision`).
pub fn precision_name(p: MatmulPrecision) -> &'static str {
    match p {
        MatmulPrecision::F32 => "f32",
        MatmulPrecision::Bf16 => "bf16",
    }
}

/// A named set of knob values applied on top of a base preset.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    pub name: String,
    pub knobs: Vec<Knob>,
}

impl Setting {
    pub fn new(name: &str, knobs: &[Knob]) -> Setting {
        Setting {
            name: name.to_string(),
            knobs: knobs.to_vec(),
        }
    }

    /// The base preset with this setting's knobs, validated.
    pub fn preset(&self, base: &Preset) -> Result<Preset, ExperimentError> {
        let mut p = base.clone();
        for k in &self.knobs {
            k.apply(&mut p);
        }
        p.name = format!("{}+{}", base.name, self.name);
        p.validate()?;
        Ok(p)
    }
}

/// The default sweep around the base: one knob at a time, configurations (a) and (b), and a
/// few combined cheap points. The skips are toggled by the `skips` job on the same base
/// ([`super::skips`]); [`optional_settings`] has more (dearer) points for `--settings`.
pub fn default_settings() -> Vec<Setting> {
    use Knob::*;
    vec![
        Setting::new("base", &[]),
        Setting::new("ds24", &[Downsample(24)]),
        Setting::new("ds12", &[Downsample(12)]),
        Setting::new("cap1500", &[MaxGaussians(1500)]),
        Setting::new("cap6000", &[MaxGaussians(6000)]),
        Setting::new("feat32", &[FeatureDim(32)]),
        Setting::new("enc2", &[EncodingFrequencies(2)]),
        Setting::new("enc6", &[EncodingFrequencies(6)]),
        Setting::new("rounds1", &[RoundsPerWindowChange(1)]),
        Setting::new("rounds4", &[RoundsPerWindowChange(4)]),
        Setting::new("w4", &[Window(4)]),
        Setting::new("w10", &[Window(10)]),
        Setting::new("config-a", &[Config(Variant::A)]),
        Setting::new("config-b", &[Config(Variant::B)]),
        Setting::new(
            "fast",
            &[
                Downsample(24),
                MaxGaussians(1500),
                FeatureDim(32),
                RoundsPerWindowChange(1),
            ],
        ),
        Setting::new(
            "fast-b",
            &[Config(Variant::B), Downsample(24), MaxGaussians(1500)],
        ),
    ]
}

/// Settings `--settings` can name besides the default sweep: the skips toggled (also in
/// the `skips` table), a second pass per round, a dear combined point, Phi's hidden width
/// 128 and 64 (`mlp128`, `mlp64`) and bfloat16 matrix products (`bf16`, a CPU with
/// AVX-512 BF16).
pub fn optional_settings() -> Vec<Setting> {
    use Knob::*;
    vec![
        Setting::new("mlp128", &[AppearanceHiddenWidth(128)]),
        Setting::new("mlp64", &[AppearanceHiddenWidth(64)]),
        Setting::new("bf16", &[MlpPrecision(MatmulPrecision::Bf16)]),
        Setting::new("frustum-off", &[CullOutsideFrustum(false)]),
        Setting::new("earlystop-off", &[EarlyTermination(false)]),
        Setting::new("masked", &[MaskedLoss(true)]),
        Setting::new(
            "masked-tiles-off",
            &[MaskedLoss(true), SkipMaskedBackgroundTiles(false)],
        ),
        Setting::new("passes2", &[PassesPerRound(2)]),
        Setting::new("eclipse-off", &[SkipEclipse(false)]),
        Setting::new("unlit-on", &[SkipUnlit(true)]),
        Setting::new("unchanged-off", &[SkipUnchangedWindow(false)]),
        Setting::new("mlpskip-off", &[SkipNoncontributingMlp(false)]),
        Setting::new("dear", &[Downsample(12), RoundsPerWindowChange(4)]),
    ]
}

/// The default or optional settings named in `names`, in the given order (the default
/// sweep when empty);
/// an unknown name is an error listing the known ones.
pub fn select_settings(names: &[String]) -> Result<Vec<Setting>, ExperimentError> {
    if names.is_empty() {
        return Ok(default_settings());
    }
    let mut all = default_settings();
    all.extend(optional_settings());
    names
        .iter()
        .map(|n| {
            all.iter().find(|s| &s.name == n).cloned().ok_or_else(|| {
                ExperimentError::Invalid(format!(
                    "unknown setting {n:?}; the settings are {}",
                    all.iter()
                        .map(|s| s.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })
        })
        .collect()
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

/// The CSV header before the ladder's columns (files written then still read back).
const CSV_HEADER_BEFORE_LADDER: &str = "setting,target,config,downsample,width,height,\
max_gaussians,init_points,feature_dim,encoding_frequencies,window,rounds_per_window_change,\
passes_per_round,skip_eclipse,skip_unlit,skip_unchanged_window,frames,rounds,steps,train_s,\
train_cpu_s,step_ms,psnr_db,ssim,masked_psnr_db,black_psnr_db,gaussians,peak_rss_mb,pareto";

/// The CSV header, exactly: the settings and results, `pareto`, then the ladder's columns
/// ([`ladder::CSV_COLUMNS`]).
pub const CSV_HEADER: &str = concat!(
    "setting,target,config,downsample,width,height,",
    "max_gaussians,init_points,feature_dim,encoding_frequencies,window,rounds_per_window_change,",
    "passes_per_round,skip_eclipse,skip_unlit,skip_unchanged_window,frames,rounds,steps,train_s,",
    "train_cpu_s,step_ms,psnr_db,ssim,masked_psnr_db,black_psnr_db,gaussians,peak_rss_mb,pareto,",
    ladder::ladder_csv_columns!()
);

/// CSV text; `front[i]` marks row i on the Pareto front (missing entries: false).
pub fn to_csv(rows: &[SweepRow], front: &[bool]) -> String {
    let mut out = String::from(CSV_HEADER);
    out.push('\n');
    for (i, r) in rows.iter().enumerate() {
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{:.2},{:.2},{:.2},{:.3},{:.4},{:.3},{:.3},{},{:.1},{},{}",
            r.setting.replace(',', ";"),
            r.target.replace(',', ";"),
            r.config,
            r.downsample,
            r.width,
            r.height,
            r.max_gaussians,
            r.init_points,
            r.feature_dim,
            r.encoding_frequencies,
            r.window,
            r.rounds_per_window_change,
            r.passes_per_round,
            r.skip_eclipse,
            r.skip_unlit,
            r.skip_unchanged_window,
            r.frames,
            r.rounds,
            r.steps,
            r.train_s,
            r.train_cpu_s,
            r.step_ms,
            r.psnr_db,
            r.ssim,
            r.masked_psnr_db,
            r.black_psnr_db,
            r.gaussians,
            r.peak_rss_mb,
            front.get(i).copied().unwrap_or(false),
            r.ladder.csv_fields()
        );
    }
    out
}

/// Rows read back from CSV text written by [`to_csv`] (the `pareto` column is ignored: the
/// front depends on which rows are plotted together). Errors name the line and column.
pub fn from_csv(text: &str) -> Result<Vec<SweepRow>, ExperimentError> {
    let mut lines = text.lines();
    let header = lines.next();
    let with_ladder = header == Some(CSV_HEADER);
    if !with_ladder && header != Some(CSV_HEADER_BEFORE_LADDER) {
        return Err(ExperimentError::Invalid(
            "CSV: the first line is not the pareto header".into(),
        ));
    }
    let columns = if with_ladder {
        CSV_HEADER.split(',').count()
    } else {
        CSV_HEADER_BEFORE_LADDER.split(',').count()
    };
    let base_columns = CSV_HEADER_BEFORE_LADDER.split(',').count();
    let mut rows = Vec::new();
    for (k, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let f: Vec<&str> = line.split(',').collect();
        let line_no = k + 2;
        if f.len() != columns {
            return Err(ExperimentError::Invalid(format!(
                "CSV line {line_no}: {} fields, expected {columns}",
                f.len()
            )));
        }
        fn parse<T: std::str::FromStr>(
            f: &[&str],
            i: usize,
            line_no: usize,
        ) -> Result<T, ExperimentError> {
            f[i].parse().map_err(|_| {
                let name = CSV_HEADER.split(',').nth(i).unwrap_or("?");
                ExperimentError::Invalid(format!(
                    "CSV line {line_no}: column {name}: cannot read {:?}",
                    f[i]
                ))
            })
        }
        rows.push(SweepRow {
            setting: f[0].to_string(),
            target: f[1].to_string(),
            config: f[2].to_string(),
            downsample: parse(&f, 3, line_no)?,
            width: parse(&f, 4, line_no)?,
            height: parse(&f, 5, line_no)?,
            max_gaussians: parse(&f, 6, line_no)?,
            init_points: parse(&f, 7, line_no)?,
            feature_dim: parse(&f, 8, line_no)?,
            encoding_frequencies: parse(&f, 9, line_no)?,
            window: parse(&f, 10, line_no)?,
            rounds_per_window_change: parse(&f, 11, line_no)?,
            passes_per_round: parse(&f, 12, line_no)?,
            skip_eclipse: parse(&f, 13, line_no)?,
            skip_unlit: parse(&f, 14, line_no)?,
            skip_unchanged_window: parse(&f, 15, line_no)?,
            frames: parse(&f, 16, line_no)?,
            rounds: parse(&f, 17, line_no)?,
            steps: parse(&f, 18, line_no)?,
            train_s: parse(&f, 19, line_no)?,
            train_cpu_s: parse(&f, 20, line_no)?,
            step_ms: parse(&f, 21, line_no)?,
            psnr_db: parse(&f, 22, line_no)?,
            ssim: parse(&f, 23, line_no)?,
            masked_psnr_db: parse(&f, 24, line_no)?,
            black_psnr_db: parse(&f, 25, line_no)?,
            gaussians: parse(&f, 26, line_no)?,
            peak_rss_mb: parse(&f, 27, line_no)?,
            ladder: if with_ladder {
                Ladder::from_csv_fields(&f[base_columns..], line_no)?
            } else {
                Ladder::default()
            },
        });
    }
    Ok(rows)
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
pub fn run_one(
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
pub fn run_settings(
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
            "[{}/{}] {}: masked PSNR {} dB, full {:.2} dB, SSIM {:.4}, train {:.1} s wall / {:.1} s CPU, {:.1} ms/step, {} Gaussians, peak {:.0} MB; {:.0} s elapsed",
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

/// Knob values as text (`downsample=24 max_gaussians=1500`; `base` for none).
pub fn describe(knobs: &[Knob]) -> String {
    if knobs.is_empty() {
        return "base".into();
    }
    knobs
        .iter()
        .map(|k| match k {
            Knob::Downsample(v) => format!("downsample={v}"),
            Knob::MaxGaussians(v) => format!("max_gaussians={v}"),
            Knob::FeatureDim(v) => format!("feature_dim={v}"),
            Knob::EncodingFrequencies(v) => format!("encoding_frequencies={v}"),
            Knob::RoundsPerWindowChange(v) => format!("rounds_per_window_change={v}"),
            Knob::PassesPerRound(v) => format!("passes_per_round={v}"),
            Knob::Window(v) => format!("window={v}"),
            Knob::SkipEclipse(v) => format!("skip_eclipse={v}"),
            Knob::SkipUnlit(v) => format!("skip_unlit={v}"),
            Knob::SkipUnchangedWindow(v) => format!("skip_unchanged_window={v}"),
            Knob::SkipNoncontributingMlp(v) => format!("skip_noncontributing_in_mlp={v}"),
            Knob::MaskedLoss(v) => format!("masked_loss={v}"),
            Knob::CullOutsideFrustum(v) => format!("cull_outside_frustum={v}"),
            Knob::EarlyTermination(v) => format!("early_termination={v}"),
            Knob::SkipMaskedBackgroundTiles(v) => format!("skip_masked_background_tiles={v}"),
            Knob::AppearanceHiddenWidth(v) => format!("appearance_hidden_width={v}"),
            Knob::MlpPrecision(v) => format!("mlp_precision={}", precision_name(*v)),
            Knob::Config(v) => format!("config={}", v.name()),
        })
        .collect::<Vec<_>>()
        .join(" ")
}

pub(crate) fn write_canvas(path: &Path, canvas: &Canvas) -> Result<(), ExperimentError> {
    files::write_png_rgb(path, canvas.width, canvas.height, &canvas.rgb8)?;
    Ok(())
}

/// One series of a plot.
#[derive(Clone, Debug)]
pub struct PlotSeries {
    pub name: String,
    pub color: Rgb,
    pub points: Vec<(f64, f64)>,
    /// Join consecutive points with a line.
    pub line: bool,
}

/// Axis ticks: 1-2-5 steps (log: 1, 2, 5 times powers of ten) within [lo, hi].
fn ticks(lo: f64, hi: f64, log: bool) -> Vec<f64> {
    let mut out = Vec::new();
    if !(lo.is_finite() && hi.is_finite() && hi > lo) {
        return out;
    }
    if log {
        let mut decade = 10f64.powf(lo.log10().floor());
        while decade <= hi {
            for m in [1.0, 2.0, 5.0] {
                let v = m * decade;
                if v >= lo && v <= hi {
                    out.push(v);
                }
            }
            decade *= 10.0;
        }
        return out;
    }
    let raw = (hi - lo) / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let mut v = (lo / step).ceil() * step;
    while v <= hi + 1e-9 * step {
        out.push(v);
        v += step;
    }
    out
}

fn tick_label(v: f64) -> String {
    if v.abs() >= 100.0 || v.fract() == 0.0 {
        format!("{v:.0}")
    } else if (10.0 * v).fract().abs() < 1e-9 {
        format!("{v:.1}")
    } else {
        format!("{v:.2}")
    }
}

/// Draws a framed x-y panel into `canvas` at (x0, y0) of `w` x `h` pixels: axes with tick
/// labels, each series' points (squares) and lines, a legend, and text labels at data points.
#[allow(clippy::too_many_arguments)]
pub fn draw_xy_panel(
    canvas: &mut Canvas,
    (x0, y0, w, h): (i64, i64, i64, i64),
    title: &str,
    x_label: &str,
    y_label: &str,
    log_x: bool,
    series: &[PlotSeries],
    labels: &[(f64, f64, String, Rgb)],
) {
    let axis: Rgb = [60, 60, 60];
    let grid: Rgb = [225, 225, 225];
    let (left, right, top, bottom) = (70i64, 20i64, 40i64, 44i64);
    let (px0, px1, py0, py1) = (x0 + left, x0 + w - right, y0 + top, y0 + h - bottom);
    let all: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .filter(|p| p.0.is_finite() && p.1.is_finite() && (!log_x || p.0 > 0.0))
        .collect();
    draw_text(canvas, x0 + 8, y0 + 8, title, 2, axis);
    if all.is_empty() {
        return;
    }
    let fx = |v: f64| if log_x { v.log10() } else { v };
    let (mut xlo, mut xhi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(fx(p.0)), a.1.max(fx(p.0)))
    });
    let (mut ylo, mut yhi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| {
        (a.0.min(p.1), a.1.max(p.1))
    });
    let pad = |lo: &mut f64, hi: &mut f64| {
        let span = (*hi - *lo).max(1e-6);
        *lo -= 0.08 * span;
        *hi += 0.08 * span;
    };
    pad(&mut xlo, &mut xhi);
    pad(&mut ylo, &mut yhi);
    let sx = |v: f64| px0 as f64 + (px1 - px0) as f64 * (fx(v) - xlo) / (xhi - xlo);
    let sy = |v: f64| py1 as f64 - (py1 - py0) as f64 * (v - ylo) / (yhi - ylo);
    let (data_xlo, data_xhi) = if log_x {
        (10f64.powf(xlo), 10f64.powf(xhi))
    } else {
        (xlo, xhi)
    };
    for t in ticks(data_xlo, data_xhi, log_x) {
        let x = sx(t);
        canvas.line((x, py0 as f64), (x, py1 as f64), 1, grid);
        let label = tick_label(t);
        draw_text(
            canvas,
            x as i64 - text_width(&label, 2) / 2,
            py1 + 6,
            &label,
            2,
            axis,
        );
    }
    for t in ticks(ylo, yhi, false) {
        let y = sy(t);
        canvas.line((px0 as f64, y), (px1 as f64, y), 1, grid);
        let label = tick_label(t);
        draw_text(
            canvas,
            px0 - 6 - text_width(&label, 2),
            y as i64 - 5,
            &label,
            2,
            axis,
        );
    }
    canvas.rect_outline(px0, py0, px1 - px0 + 1, py1 - py0 + 1, 1, axis);
    draw_text(
        canvas,
        (px0 + px1) / 2 - text_width(x_label, 2) / 2,
        py1 + 24,
        x_label,
        2,
        axis,
    );
    draw_text(canvas, x0 + 8, y0 + 24, y_label, 2, axis);
    for s in series {
        let pts: Vec<(f64, f64)> = s
            .points
            .iter()
            .copied()
            .filter(|p| p.0.is_finite() && p.1.is_finite() && (!log_x || p.0 > 0.0))
            .collect();
        if s.line {
            for pair in pts.windows(2) {
                canvas.line(
                    (sx(pair[0].0), sy(pair[0].1)),
                    (sx(pair[1].0), sy(pair[1].1)),
                    2,
                    s.color,
                );
            }
        }
        for p in &pts {
            canvas.fill_rect(sx(p.0) as i64 - 3, sy(p.1) as i64 - 3, 7, 7, s.color);
        }
    }
    // Legend in the lower right corner (slow and poor: usually empty in these plots).
    let named = series.iter().filter(|s| !s.name.is_empty()).count() as i64;
    let mut ly = py1 - 6 - 16 * named;
    for s in series.iter().filter(|s| !s.name.is_empty()) {
        let lx = px1 - 10 - text_width(&s.name, 2) - 14;
        canvas.fill_rect(lx, ly, 10, 10, s.color);
        draw_text(canvas, lx + 14, ly, &s.name, 2, axis);
        ly += 16;
    }
    for (k, (x, y, text, color)) in labels.iter().enumerate() {
        if !(x.is_finite() && y.is_finite()) || (log_x && *x <= 0.0) {
            continue;
        }
        // Alternate above and below the point so neighbouring labels overlap less.
        let dy = if k % 2 == 0 { -16 } else { 8 };
        draw_text(
            canvas,
            sx(*x) as i64 + 6,
            sy(*y) as i64 + dy,
            text,
            2,
            *color,
        );
    }
}

/// Training CPU time against evaluation masked PSNR (the target's own pixels), every setting
/// a grey point, the front in red joined as a line and labelled with the settings' names, and
/// the all-black render's score as a black line (the floor every setting must clear).
pub fn pareto_plot(rows: &[SweepRow], front: &[bool], title: &str) -> Canvas {
    let mut canvas = Canvas::new(960, 600, [255, 255, 255]);
    let point = |r: &SweepRow| (r.train_cpu_s, r.masked_psnr_db);
    let mut on: Vec<(f64, f64, &str)> = rows
        .iter()
        .zip(front)
        .filter(|(_, f)| **f)
        .map(|(r, _)| (r.train_cpu_s, r.masked_psnr_db, r.setting.as_str()))
        .collect();
    on.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let red: Rgb = [200, 30, 30];
    let grey: Rgb = [130, 130, 130];
    let (x_lo, x_hi) = rows
        .iter()
        .map(|r| r.train_cpu_s)
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        });
    let black_db = rows
        .iter()
        .filter_map(|r| r.ladder.eval.map(|e| e.black_masked_psnr_db))
        .find(|v| v.is_finite());
    let series = [
        PlotSeries {
            name: "ALL-BLACK RENDER".into(),
            color: [0, 0, 0],
            points: match black_db {
                Some(b) if x_lo <= x_hi => vec![(x_lo, b), (x_hi, b)],
                _ => Vec::new(),
            },
            line: true,
        },
        PlotSeries {
            name: "DOMINATED".into(),
            color: grey,
            points: rows
                .iter()
                .zip(front)
                .filter(|(_, f)| !**f)
                .map(|(r, _)| point(r))
                .collect(),
            line: false,
        },
        PlotSeries {
            name: "PARETO FRONT".into(),
            color: red,
            points: on.iter().map(|p| (p.0, p.1)).collect(),
            line: true,
        },
    ];
    let mut labels: Vec<(f64, f64, String, Rgb)> = on
        .iter()
        .map(|p| (p.0, p.1, p.2.to_uppercase(), red))
        .collect();
    labels.extend(rows.iter().zip(front).filter(|(_, f)| !**f).map(|(r, _)| {
        (
            r.train_cpu_s,
            r.masked_psnr_db,
            r.setting.to_uppercase(),
            grey,
        )
    }));
    draw_xy_panel(
        &mut canvas,
        (0, 0, 960, 600),
        title,
        "TRAINING CPU TIME S (LOG)",
        "EVAL MASKED PSNR DB",
        true,
        &series,
        &labels,
    );
    canvas
}

/// Masked PSNR beside black's with the ladder's verdict; rows read from a CSV without the
/// ladder show the masked PSNR alone.
pub(crate) fn masked_cell(r: &SweepRow) -> String {
    match r.ladder.eval.as_ref() {
        None => format!("{:.2}", r.masked_psnr_db),
        eval => ladder::markdown_cell(eval),
    }
}

/// Markdown table of the rows, fastest first, front rows in bold; the front is on masked
/// PSNR (the target's own pixels), and the ladder of every row follows.
pub fn to_markdown(rows: &[SweepRow], front: &[bool]) -> String {
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| rows[a].train_cpu_s.total_cmp(&rows[b].train_cpu_s));
    let mut out = String::from(
        "| Setting | Front | Image | Cap | Feat. | Enc. L | W | Rounds/change | Passes | Steps | Train CPU s | Train wall s | ms/step | masked PSNR dB (black) | PSNR dB | SSIM | Gaussians | Peak MB |\n\
         |---|:-:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for i in order {
        let r = &rows[i];
        let on = front.get(i).copied().unwrap_or(false);
        let name = if on {
            format!("**{}**", r.setting)
        } else {
            r.setting.clone()
        };
        let _ = writeln!(
            out,
            "| {name} ({}) | {} | {}x{} | {} | {} | {} | {} | {} | {} | {} | {:.1} | {:.1} | {:.1} | {} | {:.2} | {:.4} | {} | {:.0} |",
            r.config,
            if on { "yes" } else { "" },
            r.width,
            r.height,
            r.max_gaussians,
            r.feature_dim,
            r.encoding_frequencies,
            r.window,
            r.rounds_per_window_change,
            r.passes_per_round,
            r.steps,
            r.train_cpu_s,
            r.train_s,
            r.step_ms,
            masked_cell(r),
            r.psnr_db,
            r.ssim,
            r.gaussians,
            r.peak_rss_mb
        );
    }
    if let Some(r) = rows.first() {
        let _ = writeln!(
            out,
            "\nAn all-black render scores {:.2} dB full frame on the same evaluation views ({}x{}).",
            r.black_psnr_db, r.width, r.height
        );
    }
    let ladders: Vec<(String, Ladder)> = rows
        .iter()
        .filter(|r| r.ladder.eval.is_some())
        .map(|r| (format!("{} ({})", r.setting, r.config), r.ladder))
        .collect();
    if !ladders.is_empty() {
        out.push('\n');
        out.push_str(&ladder::to_markdown(&ladders));
    }
    out
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
        let c = super::super::runner::online_config(&presets[2], Variant::D);
        assert_eq!(c.model.mlp_precision, MatmulPrecision::Bf16);
        let c = super::super::runner::online_config(&presets[1], Variant::D);
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
