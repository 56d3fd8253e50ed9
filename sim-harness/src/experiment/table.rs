//! The results table: one row per (target, configuration), written as CSV and as Markdown laid
//! out like the paper's Table I (configurations down, targets across, best value per target
//! in bold), with the target's own pixels as the headline: masked SSIM, masked PSNR beside an
//! all-black render's, then full-frame PSNR and the number of Gaussians; then the accuracy
//! ladder of every run ([`super::ladder`]) and a training-time table.
//!
//! Invariants: the CSV header is exactly [`CSV_HEADER`] and rows keep the order they were
//! given in; targets and configurations appear in the Markdown in order of first appearance;
//! a missing (target, configuration) cell prints `-`; a configuration within
//! [`super::ladder::CLEAR_MARGIN_DB`] of black says so in the cell.

use super::ladder::{self, Ladder};
use std::fmt::Write as _;

/// The CSV header, exactly: full-frame SSIM and PSNR on the evaluation views, then the
/// ladder's columns ([`ladder::CSV_COLUMNS`]).
pub const CSV_HEADER: &str = concat!(
    "target,config,ssim,psnr,gaussians,train_s,step_ms,",
    ladder::ladder_csv_columns!()
);

/// One trained and evaluated configuration on one target.
#[derive(Clone, Debug, PartialEq)]
pub struct ResultRow {
    pub target: String,
    /// `a`..`d`.
    pub config: String,
    /// Mean SSIM over the evaluation views (full frame).
    pub ssim: f64,
    /// Mean PSNR over the evaluation views (full frame), dB.
    pub psnr: f64,
    pub gaussians: usize,
    /// Wall time spent in training rounds (densification included), seconds.
    pub train_s: f64,
    /// Mean wall time of one training step (forward, backward, Adam), milliseconds.
    pub step_ms: f64,
    /// Masked metrics on every rung, beside black's.
    pub ladder: Ladder,
}

/// The paper's row label of a configuration letter.
pub(crate) fn config_label(config: &str) -> String {
    match config {
        "a" => "(a) 3DGS".into(),
        "b" => "(b) + Illum.".into(),
        "c" => "(c) + Shadow Splatting".into(),
        "d" => "(d) + Isotropic Loss".into(),
        other => format!("({other})"),
    }
}

/// Title-case display name of a target (`cassini` -> `Cassini`).
pub(crate) fn target_label(target: &str) -> String {
    let mut chars = target.chars();
    match chars.next() {
        Some(first) => first.to_uppercase().chain(chars).collect(),
        None => String::new(),
    }
}

fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_string()
    }
}

/// CSV text: the header and one line per row.
pub fn to_csv(rows: &[ResultRow]) -> String {
    let mut out = String::from(CSV_HEADER);
    out.push('\n');
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{:.4},{:.2},{},{:.1},{:.1},{}",
            csv_field(&r.target),
            csv_field(&r.config),
            r.ssim,
            r.psnr,
            r.gaussians,
            r.train_s,
            r.step_ms,
            r.ladder.csv_fields()
        );
    }
    out
}

fn first_appearance<'a>(items: impl Iterator<Item = &'a str>) -> Vec<&'a str> {
    let mut seen: Vec<&str> = Vec::new();
    for item in items {
        if !seen.contains(&item) {
            seen.push(item);
        }
    }
    seen
}

/// Gaussians as the paper prints them (42.7K).
pub(crate) fn gaussians_label(n: usize) -> String {
    if n >= 1000 {
        format!("{:.1}K", n as f64 / 1000.0)
    } else {
        n.to_string()
    }
}

/// Markdown: Table I layout (masked headline), the ladder, then training wall time and step
/// time per target.
pub fn to_markdown(rows: &[ResultRow]) -> String {
    let targets = first_appearance(rows.iter().map(|r| r.target.as_str()));
    let configs = first_appearance(rows.iter().map(|r| r.config.as_str()));
    let cell = |t: &str, c: &str| rows.iter().find(|r| r.target == t && r.config == c);
    let best = |t: &str, value: fn(&ResultRow) -> f64| {
        rows.iter()
            .filter(|r| r.target == t)
            .map(value)
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let mut out = String::from(
        "Evaluation views (L2). Masked = the target's own pixels; an all-black render's masked \
         PSNR in brackets.\n\n| Config. |",
    );
    for t in &targets {
        let name = target_label(t);
        let _ = write!(
            out,
            " {name} masked SSIM↑ | {name} masked PSNR↑ (black) | {name} full PSNR | {name} \\|G\\| |"
        );
    }
    out.push_str("\n|---|");
    for _ in &targets {
        out.push_str("---:|---:|---:|---:|");
    }
    out.push('\n');
    let masked_ssim = |r: &ResultRow| r.ladder.eval.map_or(f64::NAN, |e| e.masked_ssim);
    let masked_psnr = |r: &ResultRow| r.ladder.eval.map_or(f64::NAN, |e| e.masked_psnr_db);
    for c in &configs {
        let _ = write!(out, "| {} |", config_label(c));
        for t in &targets {
            match cell(t, c) {
                Some(r) => {
                    // The best value in bold: only the number, the cell may carry a
                    // bold verdict after it.
                    let bold = |v: f64, b: f64, text: String| {
                        if v != b {
                            return text;
                        }
                        match text.split_once(' ') {
                            Some((number, rest)) => format!("**{number}** {rest}"),
                            None => format!("**{text}**"),
                        }
                    };
                    let _ = write!(
                        out,
                        " {} | {} | {:.2} | {} |",
                        bold(
                            masked_ssim(r),
                            best(t, masked_ssim),
                            format!("{:.4}", masked_ssim(r))
                        ),
                        bold(
                            masked_psnr(r),
                            best(t, masked_psnr),
                            ladder::markdown_cell(r.ladder.eval.as_ref())
                        ),
                        r.psnr,
                        gaussians_label(r.gaussians)
                    );
                }
                None => out.push_str(" - | - | - | - |"),
            }
        }
        out.push('\n');
    }
    out.push('\n');
    let ladders: Vec<(String, Ladder)> = rows
        .iter()
        .map(|r| {
            (
                format!("{} {}", target_label(&r.target), config_label(&r.config)),
                r.ladder,
            )
        })
        .collect();
    out.push_str(&ladder::to_markdown(&ladders));
    out.push_str("\nTraining wall time (s) / mean step time (ms):\n\n| Config. |");
    for t in &targets {
        let name = target_label(t);
        let _ = write!(out, " {name} train s | {name} step ms |");
    }
    out.push_str("\n|---|");
    for _ in &targets {
        out.push_str("---:|---:|");
    }
    out.push('\n');
    for c in &configs {
        let _ = write!(out, "| {} |", config_label(c));
        for t in &targets {
            match cell(t, c) {
                Some(r) => {
                    let _ = write!(out, " {:.1} | {:.1} |", r.train_s, r.step_ms);
                }
                None => out.push_str(" - | - |"),
            }
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::ladder::Rung;

    fn row(config: &str, masked_psnr_db: f64) -> ResultRow {
        let eval = Rung {
            views: 4,
            masked_psnr_db,
            masked_ssim: 0.3,
            psnr_db: 20.0,
            black_masked_psnr_db: 10.0,
            black_psnr_db: 19.0,
        };
        ResultRow {
            target: "cassini".into(),
            config: config.into(),
            ssim: 0.9,
            psnr: 20.0,
            gaussians: 4000,
            train_s: 1.0,
            step_ms: 1.0,
            ladder: Ladder {
                eval: Some(eval),
                ..Ladder::default()
            },
        }
    }

    #[test]
    fn the_best_cell_bolds_its_number_not_its_verdict() {
        let md = to_markdown(&[row("a", 11.5), row("b", 11.0)]);
        assert!(
            md.contains("| **11.50** (10.00) **< 3 dB over black** |"),
            "{md}"
        );
        assert!(
            md.contains("| 11.00 (10.00) **< 3 dB over black** |"),
            "{md}"
        );
        assert!(!md.contains("****"), "{md}");
    }
}
