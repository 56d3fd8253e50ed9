//! The accuracy ladder of a run, as every report prints it: masked PSNR (the target's own
//! pixels) on each rung beside an all-black render's score on the same frames.
//!
//! Rungs: L0 window (the keyframes held at the end: fitting), L0 seen (frames trained on
//! earlier: forgetting), L1 held-out (frames of the same rendezvous never trained on), L2
//! eval (the paper's evaluation views: random Sun, attitude and viewpoint) and L2 covered
//! (the evaluation views near a trained viewpoint).
//!
//! Invariants: a rung with no views is `None` (NaN in CSV, `-` in Markdown), never a number; a
//! model that does not beat black by [`CLEAR_MARGIN_DB`] on a rung says so in words
//! (`verdict`); the CSV columns are exactly [`CSV_COLUMNS`], in that order; a paired
//! difference (`paired_masked_difference`) exists only over the same views in the same order.

use super::evaluate::{EvalSummary, ViewMetrics};
use super::runner::RunOutcome;
use super::ExperimentError;
use serde::Serialize;
use std::fmt::Write as _;

/// How far above an all-black render a model must score (masked PSNR) to count as drawing
/// the target, dB. Space is black: a model that draws nothing already scores the black
/// floor, so a model within a few dB of it is not usable for photometric navigation.
pub const CLEAR_MARGIN_DB: f64 = 3.0;

/// One rung: the model's and an all-black render's score on the same frames.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Rung {
    pub views: usize,
    pub masked_psnr_db: f64,
    pub masked_ssim: f64,
    pub psnr_db: f64,
    pub black_masked_psnr_db: f64,
    pub black_psnr_db: f64,
}

impl Rung {
    /// `None` when the rung has no frames (e.g. no held-out frames in the preset).
    fn of(model: &EvalSummary, black: &EvalSummary) -> Option<Rung> {
        (model.views > 0).then_some(Rung {
            views: model.views,
            masked_psnr_db: model.masked_psnr_db,
            masked_ssim: model.masked_ssim,
            psnr_db: model.psnr_db,
            black_masked_psnr_db: black.masked_psnr_db,
            black_psnr_db: black.psnr_db,
        })
    }

    /// Masked PSNR above black, dB.
    pub(crate) fn margin_db(&self) -> f64 {
        self.masked_psnr_db - self.black_masked_psnr_db
    }
}

/// The five rungs of one run; `None` for a rung without frames.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Ladder {
    pub window: Option<Rung>,
    pub seen: Option<Rung>,
    pub held_out: Option<Rung>,
    pub eval: Option<Rung>,
    pub covered: Option<Rung>,
}

/// The ladder's CSV column names as a string literal, so that the reports' own headers can
/// `concat!` them (one list for `table`, `pareto` and [`CSV_COLUMNS`]).
macro_rules! ladder_csv_columns {
    () => {
        "l0_window_masked_psnr,l0_window_black_masked_psnr,\
l0_seen_masked_psnr,l0_seen_black_masked_psnr,l1_held_out_masked_psnr,\
l1_held_out_black_masked_psnr,l2_eval_masked_psnr,l2_eval_black_masked_psnr,\
l2_covered_masked_psnr,l2_covered_black_masked_psnr,l2_eval_masked_ssim"
    };
}
pub(crate) use ladder_csv_columns;

/// The ladder's CSV columns: masked PSNR of the model and of black per rung, then the
/// masked SSIM of L2.
pub const CSV_COLUMNS: &str = ladder_csv_columns!();

impl Ladder {
    pub fn of(run: &RunOutcome) -> Ladder {
        Ladder {
            window: Rung::of(&run.window_fit, &run.black_window),
            seen: Rung::of(&run.seen, &run.black_seen),
            held_out: Rung::of(&run.held_out, &run.black_held_out),
            eval: Rung::of(&run.eval, &run.black_eval),
            covered: Rung::of(&run.eval_covered, &run.black_eval_covered),
        }
    }

    /// `(name, rung)` from fitting to generalisation.
    pub(crate) fn rungs(&self) -> [(&'static str, Option<&Rung>); 5] {
        [
            ("L0 window", self.window.as_ref()),
            ("L0 seen", self.seen.as_ref()),
            ("L1 held-out", self.held_out.as_ref()),
            ("L2 eval", self.eval.as_ref()),
            ("L2 covered", self.covered.as_ref()),
        ]
    }

    /// The values for [`CSV_COLUMNS`], comma-separated (NaN for a rung without frames).
    pub(crate) fn csv_fields(&self) -> String {
        let mut out = String::new();
        for (_, rung) in self.rungs() {
            let (model, black) = rung.map_or((f64::NAN, f64::NAN), |r| {
                (r.masked_psnr_db, r.black_masked_psnr_db)
            });
            let _ = write!(out, "{model:.3},{black:.3},");
        }
        let ssim = self.eval.map_or(f64::NAN, |r| r.masked_ssim);
        let _ = write!(out, "{ssim:.4}");
        out
    }

    /// Reads the [`CSV_COLUMNS`] fields back (the rungs' view counts and full-frame
    /// numbers are not in the CSV: views reads as 1 and full-frame PSNR as NaN; a NaN masked
    /// PSNR is a rung without frames).
    pub(crate) fn from_csv_fields(
        fields: &[&str],
        line_no: usize,
    ) -> Result<Ladder, ExperimentError> {
        let names: Vec<&str> = CSV_COLUMNS.split(',').collect();
        if fields.len() != names.len() {
            return Err(ExperimentError::Invalid(format!(
                "CSV line {line_no}: {} ladder fields, expected {}",
                fields.len(),
                names.len()
            )));
        }
        let value = |i: usize| -> Result<f64, ExperimentError> {
            fields[i].parse().map_err(|_| {
                ExperimentError::Invalid(format!(
                    "CSV line {line_no}: column {}: cannot read {:?}",
                    names[i], fields[i]
                ))
            })
        };
        let rung = |k: usize| -> Result<Option<Rung>, ExperimentError> {
            let masked = value(2 * k)?;
            let black = value(2 * k + 1)?;
            Ok((!masked.is_nan()).then_some(Rung {
                views: 1,
                masked_psnr_db: masked,
                masked_ssim: f64::NAN,
                psnr_db: f64::NAN,
                black_masked_psnr_db: black,
                black_psnr_db: f64::NAN,
            }))
        };
        let mut eval = rung(3)?;
        if let Some(eval) = eval.as_mut() {
            eval.masked_ssim = value(10)?;
        }
        Ok(Ladder {
            window: rung(0)?,
            seen: rung(1)?,
            held_out: rung(2)?,
            eval,
            covered: rung(4)?,
        })
    }
}

/// In words, how a rung compares with black: `below black`, `< 3 dB over black`, or
/// empty when the model clears the margin (or a number is missing).
pub(crate) fn verdict(rung: &Rung) -> &'static str {
    let margin = rung.margin_db();
    if margin.is_nan() {
        ""
    } else if margin <= 0.0 {
        "below black"
    } else if margin < CLEAR_MARGIN_DB {
        "< 3 dB over black"
    } else {
        ""
    }
}

/// One Markdown cell: `model (black)` masked PSNR, with the verdict when there is one; `-`
/// for a rung without frames.
pub(crate) fn markdown_cell(rung: Option<&Rung>) -> String {
    let Some(rung) = rung else {
        return "-".into();
    };
    let black = if rung.black_masked_psnr_db.is_nan() {
        "-".to_string()
    } else {
        format!("{:.2}", rung.black_masked_psnr_db)
    };
    match verdict(rung) {
        "" => format!("{:.2} ({black})", rung.masked_psnr_db),
        words => format!("{:.2} ({black}) **{words}**", rung.masked_psnr_db),
    }
}

/// The ladder table: one row per `(label, ladder)`.
pub fn to_markdown(rows: &[(String, Ladder)]) -> String {
    let mut out = String::from(
        "Accuracy ladder: masked PSNR dB on the target's own pixels, an all-black render's \
         score on the same frames in brackets (a model must beat it by a clear margin):\n\n\
         | Run | L0 window | L0 seen | L1 held-out | L2 eval | L2 covered views |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    for (label, ladder) in rows {
        let _ = write!(out, "| {label} |");
        for (_, rung) in ladder.rungs() {
            let _ = write!(out, " {} |", markdown_cell(rung));
        }
        out.push('\n');
    }
    out
}

/// One progress line: masked PSNR (black) and full-frame PSNR (black) per rung with frames,
/// flagged where the model is below black.
pub fn ladder_line(label: &str, o: &RunOutcome) -> String {
    let mut line = format!("{label}: masked PSNR (all-black)");
    for (name, rung) in Ladder::of(o).rungs() {
        let Some(rung) = rung else {
            continue;
        };
        let flag = match verdict(rung) {
            "" => String::new(),
            words => format!(" {}", words.to_uppercase()),
        };
        let _ = write!(
            line,
            "; {name} {:.2} ({:.2}) dB{flag}, full {:.2} ({:.2})",
            rung.masked_psnr_db, rung.black_masked_psnr_db, rung.psnr_db, rung.black_psnr_db
        );
    }
    line
}

/// A paired difference between two runs' scores on the same views: `b - a` per view.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub(crate) struct Paired {
    pub views: usize,
    pub mean_db: f64,
    /// Standard error of the mean (sample standard deviation over sqrt(views)); NaN for
    /// one view.
    pub standard_error_db: f64,
    /// Views where `b` scores higher than `a`.
    pub b_better: usize,
}

/// Masked PSNR of `b` minus `a`, paired view by view (each capped at 100 dB as in the
/// means); `None` when the two were not scored on the same views in the same order (or on
/// none), since an unpaired difference would carry the views' own scatter.
pub(crate) fn paired_masked_difference(a: &EvalSummary, b: &EvalSummary) -> Option<Paired> {
    let same_views = a.per_view.len() == b.per_view.len()
        && a.per_view
            .iter()
            .zip(&b.per_view)
            .all(|(x, y)| x.index == y.index);
    if !same_views || a.per_view.is_empty() {
        return None;
    }
    let score = |m: &ViewMetrics| m.masked_psnr_db.min(100.0);
    let d: Vec<f64> = a
        .per_view
        .iter()
        .zip(&b.per_view)
        .map(|(x, y)| score(y) - score(x))
        .collect();
    let n = d.len() as f64;
    let mean = d.iter().sum::<f64>() / n;
    let variance = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    Some(Paired {
        views: d.len(),
        mean_db: mean,
        standard_error_db: if d.len() > 1 {
            (variance / n).sqrt()
        } else {
            f64::NAN
        },
        b_better: d.iter().filter(|&&v| v > 0.0).count(),
    })
}

/// `+0.12 ± 0.05 (37/100)` for a paired difference, `-` for none.
pub(crate) fn paired_cell(p: Option<&Paired>) -> String {
    match p {
        Some(p) if p.standard_error_db.is_nan() => {
            format!("{:+.2} ({}/{})", p.mean_db, p.b_better, p.views)
        }
        Some(p) => format!(
            "{:+.2} ± {:.2} ({}/{})",
            p.mean_db, p.standard_error_db, p.b_better, p.views
        ),
        None => "-".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rung(model: f64, black: f64) -> Rung {
        Rung {
            views: 4,
            masked_psnr_db: model,
            masked_ssim: 0.5,
            psnr_db: model + 10.0,
            black_masked_psnr_db: black,
            black_psnr_db: black + 10.0,
        }
    }

    #[test]
    fn verdicts_name_the_failures() {
        assert_eq!(verdict(&rung(9.0, 9.5)), "below black");
        assert_eq!(verdict(&rung(9.5, 9.5)), "below black");
        assert_eq!(verdict(&rung(11.0, 9.5)), "< 3 dB over black");
        assert_eq!(verdict(&rung(13.0, 9.5)), "");
        assert_eq!(verdict(&rung(13.0, f64::NAN)), "");
        assert_eq!(markdown_cell(None), "-");
        assert_eq!(
            markdown_cell(Some(&rung(9.0, 9.5))),
            "9.00 (9.50) **below black**"
        );
        assert_eq!(markdown_cell(Some(&rung(20.0, 9.5))), "20.00 (9.50)");
    }

    #[test]
    fn csv_fields_round_trip_and_empty_rungs_stay_empty() {
        let ladder = Ladder {
            window: Some(rung(21.5, 7.25)),
            seen: Some(rung(19.125, 10.0)),
            held_out: None,
            eval: Some(rung(9.875, 9.5)),
            covered: Some(rung(11.0, 9.75)),
        };
        let text = ladder.csv_fields();
        assert_eq!(text.split(',').count(), CSV_COLUMNS.split(',').count());
        let fields: Vec<&str> = text.split(',').collect();
        let back = Ladder::from_csv_fields(&fields, 2).unwrap();
        assert_eq!(back.window.unwrap().masked_psnr_db, 21.5);
        assert_eq!(back.eval.unwrap().black_masked_psnr_db, 9.5);
        assert_eq!(back.eval.unwrap().masked_ssim, 0.5);
        assert_eq!(back.held_out, None);
        let err = Ladder::from_csv_fields(&fields[1..], 7).unwrap_err();
        assert!(err.to_string().contains("line 7"), "{err}");
        let mut bad = fields.clone();
        bad[4] = "x";
        let err = Ladder::from_csv_fields(&bad, 3).unwrap_err();
        assert!(err.to_string().contains("l1_held_out_masked_psnr"), "{err}");
    }

    fn summary(indices: &[u32], masked: &[f64]) -> EvalSummary {
        super::super::evaluate::summarise(
            indices
                .iter()
                .zip(masked)
                .map(|(&index, &m)| ViewMetrics {
                    index,
                    psnr_db: m + 10.0,
                    ssim: 0.5,
                    masked_psnr_db: m,
                    masked_ssim: 0.5,
                })
                .collect(),
        )
    }

    #[test]
    fn paired_differences_need_the_same_views() {
        let a = summary(&[3, 5, 9], &[10.0, 12.0, 14.0]);
        let b = summary(&[3, 5, 9], &[11.0, 12.0, 16.0]);
        let p = paired_masked_difference(&a, &b).unwrap();
        assert_eq!((p.views, p.b_better), (3, 2));
        assert!((p.mean_db - 1.0).abs() < 1e-12);
        // Differences 1, 0, 2: sample variance 1, so the standard error is 1/sqrt(3).
        assert!((p.standard_error_db - (1.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(paired_cell(Some(&p)), "+1.00 ± 0.58 (2/3)");
        let reordered = summary(&[5, 3, 9], &[11.0, 12.0, 16.0]);
        assert_eq!(paired_masked_difference(&a, &reordered), None);
        let shorter = summary(&[3, 5], &[11.0, 12.0]);
        assert_eq!(paired_masked_difference(&a, &shorter), None);
        let empty = summary(&[], &[]);
        assert_eq!(paired_masked_difference(&empty, &empty), None);
        assert_eq!(paired_cell(None), "-");
        let one = paired_masked_difference(&summary(&[1], &[5.0]), &summary(&[1], &[4.0]));
        assert_eq!(paired_cell(one.as_ref()), "-1.00 (0/1)");
    }
}
