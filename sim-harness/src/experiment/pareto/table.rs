//! The sweep's tables: `pareto.csv` ([`to_csv`], read back by [`from_csv`], also files
//! written before the ladder's columns existed) and the Markdown table `pareto.md`
//! ([`to_markdown`]).
//!
//! Invariant: the CSV header is [`CSV_HEADER`] and rows keep the run order.

use super::SweepRow;
use crate::experiment::ladder::{self, Ladder};
use crate::experiment::ExperimentError;
use std::fmt::Write as _;

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
