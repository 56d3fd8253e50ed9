//! The skips table: for each switchable skip (the online trainer's frame and round skips,
//! gs-core's network skip and its three rasterizer skips), the same scenario trained with
//! the skip active and without it; the training time it saves and what it costs in
//! evaluation error (`skips.csv`, `skips.md`; every run in the Pareto schema in
//! `skips-runs.csv`).
//!
//! Invariants: the base preset (every skip at its default) runs once and is reused as the
//! "with" or "without" side of every skip whose default matches and that needs no other
//! knob; a skip that only acts under other knobs (`SkipSpec::context`, e.g. the masked
//! loss for the background-tile skip) runs twice, with the context on both sides; every
//! run differs from its partner in exactly one skip; `saved` = without - with (positive:
//! the skip saves time) and `cost` = PSNR without - PSNR with (positive: the skip loses
//! quality).

use super::pareto::{run_settings, Knob, Setting, SweepRow};
use super::preset::Preset;
use super::write_text;
use super::ExperimentError;
use crate::scenario::Scenario;
use std::fmt::Write as _;
use std::path::PathBuf;

/// One switchable skip: the knob values that turn it on and off.
#[derive(Clone, Debug, PartialEq)]
pub struct SkipSpec {
    pub name: String,
    pub what: String,
    pub on: Knob,
    pub off: Knob,
    /// Knobs set on both sides (the conditions under which the skip acts at all); empty:
    /// the base preset as it is.
    pub context: Vec<Knob>,
}

/// The skips the experiments can switch: the online trainer's three, gs-core's
/// `skip_noncontributing_in_mlp` and its rasterizer skips (frustum cull, early
/// termination, background tiles under the masked loss).
pub fn switchable_skips() -> Vec<SkipSpec> {
    vec![
        SkipSpec {
            name: "eclipse".into(),
            what: "frames flagged as in eclipse never enter the window".into(),
            on: Knob::SkipEclipse(true),
            off: Knob::SkipEclipse(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "unlit".into(),
            what: "frames with mean full-frame brightness < 0.01 never enter the window".into(),
            on: Knob::SkipUnlit(true),
            off: Knob::SkipUnlit(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "unchanged-window".into(),
            what: "no round when the keyframe window did not change since the last one".into(),
            on: Knob::SkipUnchangedWindow(true),
            off: Knob::SkipUnchangedWindow(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "noncontributing-mlp".into(),
            what: "Phi and Psi run only for Gaussians the blend reads (alpha-only pass first)"
                .into(),
            on: Knob::SkipNoncontributingMlp(true),
            off: Knob::SkipNoncontributingMlp(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "frustum-cull".into(),
            what: "Gaussians whose footprint certainly misses the image are dropped before \
                   their covariance is projected (same image and gradients)"
                .into(),
            on: Knob::CullOutsideFrustum(true),
            off: Knob::CullOutsideFrustum(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "early-termination".into(),
            what: "a pixel stops blending before its transmittance falls below 1e-4".into(),
            on: Knob::EarlyTermination(true),
            off: Knob::EarlyTermination(false),
            context: Vec::new(),
        },
        SkipSpec {
            name: "masked-background-tiles".into(),
            what: "masked training (both runs): tiles farther than the SSIM window from the \
                   mask are neither blended nor back-propagated (same gradients)"
                .into(),
            on: Knob::SkipMaskedBackgroundTiles(true),
            off: Knob::SkipMaskedBackgroundTiles(false),
            context: vec![Knob::MaskedLoss(true)],
        },
    ]
}

/// Skips that have no switch (always on), with why; listed under the table.
pub(crate) const NOT_SWITCHABLE: [(&str, &str); 1] = [(
    "near-plane culling",
    "a Gaussian whose centre is nearer than the near plane has no perspective projection: \
     dropped whatever `cull_outside_frustum` says",
)];

/// One skip measured with and without.
#[derive(Clone, Debug, PartialEq)]
pub struct SkipRow {
    pub spec: SkipSpec,
    /// The skip is active in the base preset.
    pub default_on: bool,
    pub with: SweepRow,
    pub without: SweepRow,
}

impl SkipRow {
    /// Training CPU seconds the skip saves.
    pub fn saved_cpu_s(&self) -> f64 {
        self.without.train_cpu_s - self.with.train_cpu_s
    }

    /// PSNR the skip costs, dB (negative: the skip improves the score).
    pub fn psnr_cost_db(&self) -> f64 {
        self.without.psnr_db - self.with.psnr_db
    }

    /// Masked PSNR (the target's own pixels) the skip costs, dB: the headline cost.
    pub(crate) fn masked_psnr_cost_db(&self) -> f64 {
        self.without.masked_psnr_db - self.with.masked_psnr_db
    }

    pub(crate) fn ssim_cost(&self) -> f64 {
        self.without.ssim - self.with.ssim
    }
}

fn knob_is_set(preset: &Preset, knob: Knob) -> bool {
    let mut p = preset.clone();
    knob.apply(&mut p);
    &p == preset
}

/// What the skips job needs.
#[derive(Clone, Debug)]
pub struct SkipsJob {
    pub base: Preset,
    pub scenario: Scenario,
    pub skips: Vec<SkipSpec>,
    pub out_dir: PathBuf,
}

/// The CSV header, exactly.
pub const CSV_HEADER: &str = "skip,default_on,with_train_cpu_s,without_train_cpu_s,saved_cpu_s,\
with_train_s,without_train_s,with_steps,without_steps,with_psnr_db,without_psnr_db,psnr_cost_db,\
with_ssim,without_ssim,ssim_cost,with_masked_psnr_db,without_masked_psnr_db,masked_psnr_cost_db";

pub fn to_csv(rows: &[SkipRow]) -> String {
    let mut out = String::from(CSV_HEADER);
    out.push('\n');
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{:.2},{:.2},{:.2},{:.2},{:.2},{},{},{:.3},{:.3},{:.3},{:.4},{:.4},{:.4},{:.3},{:.3},{:.3}",
            r.spec.name,
            r.default_on,
            r.with.train_cpu_s,
            r.without.train_cpu_s,
            r.saved_cpu_s(),
            r.with.train_s,
            r.without.train_s,
            r.with.steps,
            r.without.steps,
            r.with.psnr_db,
            r.without.psnr_db,
            r.psnr_cost_db(),
            r.with.ssim,
            r.without.ssim,
            r.ssim_cost(),
            r.with.masked_psnr_db,
            r.without.masked_psnr_db,
            r.masked_psnr_cost_db()
        );
    }
    out
}

/// Markdown: the measured skips, then the ones without a switch.
pub fn to_markdown(rows: &[SkipRow]) -> String {
    let mut out = String::from(
        "| Skip | Default | What it skips | Steps with / without | Train CPU s with / without | Saved CPU s (%) | Train wall s with / without | masked PSNR dB with / without | masked cost dB | full PSNR dB with / without | SSIM with / without |\n\
         |---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in rows {
        let pct = 100.0 * r.saved_cpu_s() / r.without.train_cpu_s.max(1e-9);
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} / {} | {:.1} / {:.1} | {:+.1} ({:+.0} %) | {:.1} / {:.1} | {:.2} / {:.2} | {:+.2} | {:.2} / {:.2} | {:.4} / {:.4} |",
            r.spec.name,
            if r.default_on { "on" } else { "off" },
            r.spec.what,
            r.with.steps,
            r.without.steps,
            r.with.train_cpu_s,
            r.without.train_cpu_s,
            r.saved_cpu_s(),
            pct,
            r.with.train_s,
            r.without.train_s,
            r.with.masked_psnr_db,
            r.without.masked_psnr_db,
            r.masked_psnr_cost_db(),
            r.with.psnr_db,
            r.without.psnr_db,
            r.with.ssim,
            r.without.ssim
        );
    }
    out.push_str("\nNot switchable (always on, not measured):\n\n");
    for (name, why) in NOT_SWITCHABLE {
        let _ = writeln!(out, "- {name}: {why}");
    }
    out
}

/// Where a skip's two sides come from in the sweep.
enum Sides {
    /// The base run is one side, run `toggled` the other.
    Base { toggled: usize },
    /// Both sides run under the skip's context: runs `with` and `without`.
    Own { with: usize, without: usize },
}

/// Runs the base, one run per context-free skip toggled away from its default, and two per
/// skip with a context; writes `skips.csv`, `skips.md` and `skips-runs.csv`.
pub fn run_skips(
    job: &SkipsJob,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<SkipRow>, ExperimentError> {
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let mut settings = vec![Setting::new("base", &[])];
    let mut default_on = Vec::new();
    let mut sides = Vec::new();
    for s in &job.skips {
        let on = knob_is_set(&job.base, s.on);
        default_on.push(on);
        if s.context.is_empty() {
            let (name, knob) = if on {
                (format!("{}-off", s.name), s.off)
            } else {
                (format!("{}-on", s.name), s.on)
            };
            sides.push(Sides::Base {
                toggled: settings.len(),
            });
            settings.push(Setting::new(&name, &[knob]));
        } else {
            let with = settings.len();
            for (suffix, knob) in [("on", s.on), ("off", s.off)] {
                let mut knobs = s.context.clone();
                knobs.push(knob);
                settings.push(Setting::new(&format!("{}-{suffix}", s.name), &knobs));
            }
            sides.push(Sides::Own {
                with,
                without: with + 1,
            });
        }
    }
    let sweep = run_settings(
        &job.scenario,
        &job.base,
        &settings,
        &out.join("cache"),
        progress,
        &mut |_| Ok(()),
    )?;
    let base = &sweep[0];
    let rows: Vec<SkipRow> = job
        .skips
        .iter()
        .zip(&default_on)
        .zip(&sides)
        .map(|((spec, &on), side)| {
            let (with, without) = match *side {
                Sides::Base { toggled } if on => (base.clone(), sweep[toggled].clone()),
                Sides::Base { toggled } => (sweep[toggled].clone(), base.clone()),
                Sides::Own { with, without } => (sweep[with].clone(), sweep[without].clone()),
            };
            SkipRow {
                spec: spec.clone(),
                default_on: on,
                with,
                without,
            }
        })
        .collect();
    write_text(&out.join("skips.csv"), &to_csv(&rows))?;
    // Every run in the Pareto sweep's schema, to plot beside the sweep (`pareto-plot`).
    write_text(
        &out.join("skips-runs.csv"),
        &super::pareto::to_csv(&sweep, &[]),
    )?;
    write_text(&out.join("skips.md"), &to_markdown(&rows))?;
    Ok(rows)
}
