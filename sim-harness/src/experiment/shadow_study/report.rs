//! What the study reports: the per-view and per-stage scores, the oracle's rows, the Sun
//! coverage and the shadow headroom ([`ShadowStudyReport`], written as JSON), and the
//! summary tables of `shadow_study.md` ([`to_markdown`]).
//!
//! Invariant: every number comes from the run that filled the report.

use super::scores::{GaussianScores, PixelScores};
use serde::Serialize;

/// Scores of one view at one stage.
#[derive(Clone, Debug, Serialize)]
pub struct ViewShadowReport {
    /// `eval K` or `frame K`.
    pub view: String,
    pub psnr_db: f64,
    /// Fractions of the target's pixels lit / in cast shadow / facing away.
    pub truth_fractions: [f64; 3],
    pub shadow_image: PixelScores,
    pub visibility_image: PixelScores,
    pub visibility: GaussianScores,
    pub refined_visibility: GaussianScores,
}

/// One stage (before or after training), per view and pooled.
#[derive(Clone, Debug, Serialize)]
pub struct StageReport {
    pub stage: String,
    pub gaussians: usize,
    pub views: Vec<ViewShadowReport>,
    pub shadow_image: PixelScores,
    pub visibility_image: PixelScores,
    pub visibility: GaussianScores,
    pub refined_visibility: GaussianScores,
}

/// The light pass on opaque surface samples for one light setting, pooled over the views.
#[derive(Clone, Debug, Serialize)]
pub struct OracleRow {
    pub projection: String,
    pub resolution_px: u32,
    pub depth_bias_fraction: f32,
    /// Receivers ignore occluders within this many of their own sigmas along the light
    /// axis (0: the fixed bias alone, the shadow pass before the acne fix).
    pub receiver_extent_sigmas: f32,
    /// Gaussians whose surface faces the Sun (cos(outward normal, Sun) >= 0.1): reached =
    /// lit, blocked = in cast shadow. This is what shadow splatting has to tell apart.
    pub facing: GaussianScores,
    /// Mean V of Gaussians on surfaces facing away (cos <= -0.1): dark by shading whatever V
    /// says; back faces of thin bodies sit within the front face's extent and stay V ~ 1.
    pub mean_on_facing_away: f64,
    /// Facing Gaussians by cos(normal, Sun) in [`COS_BUCKETS`] (face-on first): neighbours on
    /// a tilted surface are nearer the light than each other, so false self-shadowing
    /// ("acne") grows as the Sun grazes the surface.
    pub by_cos: Vec<GaussianScores>,
}

/// (depth bias fraction, receiver extent in sigmas) settings of the oracle sweep.
pub const ORACLE_BIAS_AND_EXTENT: [(f32, f32); 8] = [
    (0.005, 0.0),
    (0.02, 0.0),
    (0.05, 0.0),
    (0.02, 1.0),
    (0.02, 2.0),
    (0.02, 3.0),
    (0.005, 2.0),
    (0.05, 2.0),
];

/// Lower bounds of the |cos(normal, Sun)| buckets of [`OracleRow::by_cos`].
pub const COS_BUCKETS: [f32; 4] = [0.9, 0.7, 0.4, 0.1];

/// Quantiles (min, 25 %, median, 75 %, max) of a list of angles, degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct AngleQuantiles {
    pub min: f64,
    pub p25: f64,
    pub median: f64,
    pub p75: f64,
    pub max: f64,
}

pub(super) fn quantiles(mut v: Vec<f64>) -> AngleQuantiles {
    if v.is_empty() {
        return AngleQuantiles::default();
    }
    v.sort_by(f64::total_cmp);
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    AngleQuantiles {
        min: q(0.0),
        p25: q(0.25),
        median: q(0.5),
        p75: q(0.75),
        max: q(1.0),
    }
}

/// How the evaluation views' Sun directions relate to the training frames' (target frame).
#[derive(Clone, Debug, Serialize)]
pub struct SunCoverage {
    /// Angle between the training frames' Sun directions and their mean direction.
    pub train_sun_spread_deg: AngleQuantiles,
    /// Per evaluation view: angle to the nearest training Sun direction.
    pub eval_to_nearest_train_sun_deg: AngleQuantiles,
    /// Per evaluation view: over training frames, the smallest max(Sun angle, view angle):
    /// how far the nearest training frame with both a similar Sun and a similar viewpoint is.
    pub eval_to_nearest_train_sun_and_view_deg: AngleQuantiles,
}

/// PSNR of the evaluation views rendered without cast shadows against the true views.
#[derive(Clone, Debug, Serialize)]
pub struct ShadowHeadroom {
    /// Mean over views of the full-frame PSNR (capped at 100 dB per view), dB.
    pub mean_psnr_db: f64,
    /// Full-frame PSNR of the pooled squared error over all views, dB.
    pub pooled_psnr_db: f64,
    /// Mean squared error per pixel and channel on [0, 1] images, pooled.
    pub pooled_mse: f64,
    pub per_view_psnr_db: Vec<f64>,
}

/// Everything the study measured.
#[derive(Clone, Debug, Serialize)]
pub struct ShadowStudyReport {
    pub target: String,
    pub width: u32,
    pub height: u32,
    /// Pooled fractions of target pixels lit / cast shadow / facing away.
    pub truth_fractions_train: [f64; 3],
    pub truth_fractions_eval: [f64; 3],
    /// Per evaluation view (all of them): cast-shadow fraction of the target's pixels.
    pub eval_cast_fraction: Vec<f64>,
    pub sun_coverage: SunCoverage,
    /// The evaluation views re-rendered without cast shadows (same request otherwise), PSNR
    /// against the true views: the error of a model perfect in every other respect that
    /// ignores self-shadowing; the ceiling of what shadow splatting can add.
    pub no_cast_shadow_psnr: ShadowHeadroom,
    pub oracle: Vec<OracleRow>,
    pub before: StageReport,
    pub after: Option<StageReport>,
    /// Configuration c after training on all evaluation views (mean PSNR, dB).
    pub eval_psnr_db: Option<f64>,
    pub eval_psnr_per_view_db: Vec<f64>,
    pub total_s: f64,
}

fn pct(v: f64) -> String {
    format!("{:.1} %", 100.0 * v)
}

fn f3(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.3}")
    } else {
        "-".into()
    }
}

fn stage_rows(s: &StageReport) -> String {
    let mut t = String::new();
    let p = |name: &str, x: &PixelScores| {
        format!(
            "| {} {name} | {} | {} | {} | {} | {} |\n",
            s.stage,
            f3(x.iou_dark),
            f3(x.accuracy),
            f3(x.mean_on_lit),
            f3(x.mean_on_cast),
            f3(x.mean_on_away)
        )
    };
    t += &p("S (pixels)", &s.shadow_image);
    t += &p("V image (pixels)", &s.visibility_image);
    let g = |name: &str, x: &GaussianScores| {
        format!(
            "| {} {name} | | {} | {} | {} | |\n",
            s.stage,
            f3(x.accuracy),
            f3(x.mean_on_reached),
            f3(x.mean_on_blocked)
        )
    };
    t += &g("V_i (Gaussians)", &s.visibility);
    t += &g("V'_i (Gaussians)", &s.refined_visibility);
    t
}

/// The summary tables of a report.
pub fn to_markdown(r: &ShadowStudyReport) -> String {
    let mut t = format!(
        "# Shadow study: {} ({}x{})\n\n## Ground truth\n\nTarget pixels lit / in cast shadow / facing away from the Sun: training frames {} / {} / {}, evaluation views {} / {} / {}.\n\n",
        r.target,
        r.width,
        r.height,
        pct(r.truth_fractions_train[0]),
        pct(r.truth_fractions_train[1]),
        pct(r.truth_fractions_train[2]),
        pct(r.truth_fractions_eval[0]),
        pct(r.truth_fractions_eval[1]),
        pct(r.truth_fractions_eval[2]),
    );
    let h = &r.no_cast_shadow_psnr;
    t += &format!(
        "Evaluation views rendered without cast shadows, against the true views: PSNR {:.2} dB (mean over views; pooled MSE {:.2e} = {:.2} dB). A model that ignores self-shadowing cannot score above this even if perfect otherwise.\n\n",
        h.mean_psnr_db, h.pooled_mse, h.pooled_psnr_db
    );
    let q = |a: &AngleQuantiles| {
        format!(
            "{:.1} / {:.1} / {:.1} / {:.1} / {:.1}",
            a.min, a.p25, a.median, a.p75, a.max
        )
    };
    let c = &r.sun_coverage;
    t += "## Sun directions (target frame), degrees: min / 25 % / median / 75 % / max\n\n";
    t += &format!(
        "- training Sun around its mean: {}\n- evaluation Sun to the nearest training Sun: {}\n- evaluation (Sun, view) to the nearest training frame with both close (max of the two angles): {}\n\n",
        q(&c.train_sun_spread_deg),
        q(&c.eval_to_nearest_train_sun_deg),
        q(&c.eval_to_nearest_train_sun_and_view_deg)
    );
    t += "## Light pass on opaque surface samples (oracle geometry)\n\n";
    t += "Gaussians on surfaces facing the Sun (cos(outward normal, Sun) >= 0.1): accuracy of V >= 0.5 as \"the Sun reaches the centre\" (lit) against blocked (cast shadow), mean V on lit / cast-shadow Gaussians, mean V on lit Gaussians by cos(normal, Sun) (their count in brackets); mean V of Gaussians on surfaces facing away (cos <= -0.1).\n\n";
    t += "| projection | light px | bias | extent sigmas | accuracy | V lit | V cast | V facing away |";
    for lo in COS_BUCKETS {
        t += &format!(" V lit, cos >= {lo} |");
    }
    t += "\n|---|---:|---:|---:|---:|---:|---:|---:|";
    t += &"---:|".repeat(COS_BUCKETS.len());
    t += "\n";
    for o in &r.oracle {
        t += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            o.projection,
            o.resolution_px,
            o.depth_bias_fraction,
            o.receiver_extent_sigmas,
            f3(o.facing.accuracy),
            f3(o.facing.mean_on_reached),
            f3(o.facing.mean_on_blocked),
            f3(o.mean_on_facing_away),
        );
        for bucket in &o.by_cos {
            t += &format!(" {} ({}) |", f3(bucket.mean_on_reached), bucket.reached);
        }
        t += "\n";
    }
    t +=
        "\n## Configuration c: shadow image S, V image and V_i / V'_i against the ground truth\n\n";
    t += "Pixels: IoU and accuracy of value < 0.5 against cast shadow (pixels facing the Sun), mean value on lit / cast / facing-away pixels. Gaussians (opacity-weighted, those in view): accuracy, mean on reached / blocked.\n\n";
    t += "| stage, quantity | IoU | accuracy | mean lit / reached | mean cast / blocked | mean facing away |\n|---|---:|---:|---:|---:|---:|\n";
    t += &stage_rows(&r.before);
    if let Some(a) = &r.after {
        t += &stage_rows(a);
    }
    if let Some(p) = r.eval_psnr_db {
        t += &format!(
            "\nConfiguration c after training: evaluation PSNR {p:.2} dB over {} views.\n",
            r.eval_psnr_per_view_db.len()
        );
    }
    t += &format!("\nTotal {:.0} s.\n", r.total_s);
    t
}
