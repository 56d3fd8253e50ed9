//! The ablation's tables: `init.csv` ([`to_csv`]), the Markdown report `init.md`
//! ([`to_markdown`]) and the per-round curves `init_curves.csv` ([`curves_csv`]). Both
//! tables carry the accuracy ladder ([`crate::experiment::ladder`]), and the Markdown the
//! paired difference of every start against surface samples on each rung.
//!
//! Invariant: every number written comes from the runs handed in, in their order.

use super::InitRun;
use crate::experiment::evaluate::EvalSummary;
use crate::experiment::ladder::{self, Ladder};
use crate::experiment::runner::RunOutcome;
use crate::experiment::table::target_label;
use std::fmt::Write as _;

/// CSV header of `init.csv`: the run's settings and results, then the ladder's columns
/// ([`ladder::CSV_COLUMNS`]).
pub const CSV_HEADER: &str = concat!(
    "target,init,psnr,ssim,masked_psnr,masked_ssim,seen_psnr,black_psnr,initial_gaussians,final_gaussians,rounds,steps,train_s,step_ms,run_wall_s,run_cpu_s,hull_frames,hull_points,hull_voxel_m,hull_mean_dist_m,hull_carve_s,hull_far_fraction,final_mean_dist_m,final_far_fraction,",
    ladder::ladder_csv_columns!()
);

/// One line per run.
pub fn to_csv(runs: &[InitRun]) -> String {
    let mut out = format!("{CSV_HEADER}\n");
    for r in runs {
        let o = &r.run;
        let hull = match &r.hull {
            Some(h) => format!(
                "{},{},{:.4},{:.4},{:.2}",
                h.frames.len(),
                h.points,
                h.voxel_m,
                h.mean_distance_to_surface_m,
                h.carve_s
            ),
            None => ",,,,".into(),
        };
        let hull_far = r
            .hull
            .as_ref()
            .map_or(String::new(), |h| format!("{:.4}", h.far_fraction));
        let _ = writeln!(
            out,
            "{},{},{:.2},{:.4},{:.2},{:.4},{:.2},{:.2},{},{},{},{},{:.1},{:.1},{:.1},{:.1},{},{},{:.4},{:.4},{}",
            o.target,
            r.init,
            o.eval.psnr_db,
            o.eval.ssim,
            o.eval.masked_psnr_db,
            o.eval.masked_ssim,
            o.seen.psnr_db,
            o.black_eval.psnr_db,
            r.initial_gaussians,
            o.gaussians,
            o.rounds,
            o.steps,
            o.train_s,
            o.step_ms,
            r.wall_s,
            r.cpu_s,
            hull,
            hull_far,
            r.final_mean_distance_m,
            r.final_far_fraction,
            Ladder::of(o).csv_fields()
        );
    }
    out
}

/// The Markdown report: metrics per target and initialisation, the gap to surface samples,
/// the accuracy ladder, the paired differences against surface samples, the evaluation curve
/// and the hull's facts.
pub fn to_markdown(runs: &[InitRun]) -> String {
    let mut out = String::from(
        "Configuration (d), evaluation views (L2); masked = the target's own pixels, an \
         all-black render's score in brackets; full frame beside.\n\n\
         | Target | Init. | masked PSNR↑ (black) | full PSNR↑ (black) | SSIM↑ | seen PSNR | Δ PSNR vs surface | \\|G\\| start → end | train s | run CPU s |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in runs {
        let o = &r.run;
        let surface = runs
            .iter()
            .find(|s| s.init == "surface" && s.run.target == o.target);
        let delta = match surface {
            Some(s) if s.init != r.init => {
                format!("{:+.2} dB", o.eval.psnr_db - s.run.eval.psnr_db)
            }
            _ => "-".into(),
        };
        let _ = writeln!(
            out,
            "| {} | {} | {} | {:.2} ({:.2}) | {:.4} | {:.2} | {} | {} → {} | {:.1} | {:.1} |",
            target_label(&o.target),
            r.init,
            ladder::markdown_cell(Ladder::of(o).eval.as_ref()),
            o.eval.psnr_db,
            o.black_eval.psnr_db,
            o.eval.ssim,
            o.seen.psnr_db,
            delta,
            r.initial_gaussians,
            o.gaussians,
            o.train_s,
            r.cpu_s
        );
    }
    let ladders: Vec<(String, Ladder)> = runs
        .iter()
        .map(|r| {
            (
                format!("{} {}", target_label(&r.run.target), r.init),
                Ladder::of(&r.run),
            )
        })
        .collect();
    out.push('\n');
    out.push_str(&ladder::to_markdown(&ladders));
    out.push_str(&paired_markdown(runs));
    let with_curve: Vec<&InitRun> = runs
        .iter()
        .filter(|r| !r.run.eval_curve.is_empty())
        .collect();
    if let Some(first) = with_curve.first() {
        out.push_str("\nEvaluation PSNR (dB) during training, by round:\n\n| Target | Init. |");
        for p in &first.run.eval_curve {
            let _ = write!(out, " {} |", p.round);
        }
        out.push_str("\n|---|---|");
        out.push_str(&"---:|".repeat(first.run.eval_curve.len()));
        out.push('\n');
        for r in &with_curve {
            let _ = write!(out, "| {} | {} |", target_label(&r.run.target), r.init);
            for p in &r.run.eval_curve {
                let _ = write!(out, " {:.2} |", p.psnr_db);
            }
            out.push('\n');
        }
    }
    out.push_str(
        "\nThe final Gaussians' centres against the true surface (nearest surface sample; far: \
         more than two hull voxels away):\n\n\
         | Target | Init. | mean dist. m | far |\n|---|---|---:|---:|\n",
    );
    for r in runs {
        let _ = writeln!(
            out,
            "| {} | {} | {:.3} | {:.1} % |",
            target_label(&r.run.target),
            r.init,
            r.final_mean_distance_m,
            100.0 * r.final_far_fraction
        );
    }
    let hulls: Vec<&InitRun> = runs.iter().filter(|r| r.hull.is_some()).collect();
    if !hulls.is_empty() {
        out.push_str(
            "\nVisual hulls (carved from the first keyframes' masks and poses):\n\n\
             | Target | Init. | frames | voxel m | occupied voxels | surface voxels | points | uncoloured | mean dist. to true surface m | far | carve s |\n\
             |---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        for r in hulls {
            let Some(h) = &r.hull else { continue };
            let frames: Vec<String> = h.frames.iter().map(ToString::to_string).collect();
            let _ = writeln!(
                out,
                "| {} | {} | {} | {:.3} | {} | {} | {} | {} | {:.3} | {:.1} % | {:.2} |",
                target_label(&r.run.target),
                r.init,
                frames.join(" "),
                h.voxel_m,
                h.occupied_voxels,
                h.surface_voxels,
                h.points,
                h.uncoloured_points,
                h.mean_distance_to_surface_m,
                100.0 * h.far_fraction,
                h.carve_s
            );
        }
    }
    out
}

/// A run's scores on one rung.
type RungOf = fn(&RunOutcome) -> &EvalSummary;

/// The rungs a paired difference is reported on, with the run's scores on each.
const PAIRED_RUNGS: [(&str, RungOf); 5] = [
    ("L0 window", |o| &o.window_fit),
    ("L0 seen", |o| &o.seen),
    ("L1 held-out", |o| &o.held_out),
    ("L2 eval", |o| &o.eval),
    ("L2 covered", |o| &o.eval_covered),
];

/// Every start minus surface samples of the same target, masked PSNR paired view by view
/// on each rung; empty when no target has both.
fn paired_markdown(runs: &[InitRun]) -> String {
    let mut rows = String::new();
    for r in runs.iter().filter(|r| r.init != "surface") {
        let Some(surface) = runs
            .iter()
            .find(|s| s.init == "surface" && s.run.target == r.run.target)
        else {
            continue;
        };
        let _ = write!(
            rows,
            "| {} | {} − surface |",
            target_label(&r.run.target),
            r.init
        );
        for (_, rung) in PAIRED_RUNGS {
            let p = ladder::paired_masked_difference(rung(&surface.run), rung(&r.run));
            let _ = write!(rows, " {} |", ladder::paired_cell(p.as_ref()));
        }
        rows.push('\n');
    }
    if rows.is_empty() {
        return rows;
    }
    let mut out = String::from(
        "\nPaired differences against surface samples: masked PSNR dB, mean ± standard error \
         over the same views, in brackets the views where the other start scores higher:\n\n\
         | Target | Difference |",
    );
    for (name, _) in PAIRED_RUNGS {
        let _ = write!(out, " {name} |");
    }
    out.push_str("\n|---|---|");
    out.push_str(&"---:|".repeat(PAIRED_RUNGS.len()));
    out.push('\n');
    out.push_str(&rows);
    out
}

/// Per-round curves: Gaussian count, mean loss and training seconds.
pub fn curves_csv(runs: &[InitRun]) -> String {
    let mut out = String::from("target,init,round,frame_index,gaussians,mean_loss,train_s\n");
    for r in runs {
        for p in &r.run.curve {
            let _ = writeln!(
                out,
                "{},{},{},{},{},{:.6},{:.3}",
                r.run.target, r.init, p.round, p.frame_index, p.gaussians, p.mean_loss, p.train_s
            );
        }
    }
    out
}
