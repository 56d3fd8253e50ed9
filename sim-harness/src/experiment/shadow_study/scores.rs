//! Scores of a visibility against the ray-traced ground truth: per pixel ([`PixelScores`]:
//! IoU and accuracy of "dark" against cast shadow, mean values per Sun class) and per
//! Gaussian ([`GaussianScores`]: opacity-weighted, against whether the Sun reaches its
//! centre), with the accumulators that sum them over views.
//!
//! Invariant: an empty denominator gives NaN (null in the JSON), never a division by zero
//! reported as a number.

use crate::raytrace::sunlight::SunClass;
use serde::Serialize;

/// Pixel scores of a map in [0, 1] (S or the V image) against the ground truth: "predicted
/// dark" is `value < 0.5`, "truly dark" is cast shadow; IoU and accuracy count only pixels
/// that face the Sun (lit or cast shadow), since facing-away pixels are dark whatever S says.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PixelScores {
    pub lit_px: usize,
    pub cast_px: usize,
    pub away_px: usize,
    pub mean_on_lit: f64,
    pub mean_on_cast: f64,
    pub mean_on_away: f64,
    pub iou_dark: f64,
    pub accuracy: f64,
}

#[derive(Clone, Copy, Debug, Default)]
pub(super) struct PixelAcc {
    n: [usize; 3],
    sum: [f64; 3],
    tp: usize,
    fp: usize,
    fn_: usize,
    tn: usize,
}

impl PixelAcc {
    pub(super) fn add(&mut self, class: SunClass, value: f32) {
        let slot = match class {
            SunClass::Lit => 0,
            SunClass::CastShadow => 1,
            SunClass::FacingAway => 2,
            SunClass::Background => return,
        };
        self.n[slot] += 1;
        self.sum[slot] += value as f64;
        let dark = value < 0.5;
        match (slot, dark) {
            (1, true) => self.tp += 1,
            (1, false) => self.fn_ += 1,
            (0, true) => self.fp += 1,
            (0, false) => self.tn += 1,
            _ => {}
        }
    }

    pub(super) fn merge(&mut self, o: &PixelAcc) {
        for k in 0..3 {
            self.n[k] += o.n[k];
            self.sum[k] += o.sum[k];
        }
        self.tp += o.tp;
        self.fp += o.fp;
        self.fn_ += o.fn_;
        self.tn += o.tn;
    }

    pub(super) fn scores(&self) -> PixelScores {
        let mean = |k: usize| ratio(self.sum[k], self.n[k] as f64);
        PixelScores {
            lit_px: self.n[0],
            cast_px: self.n[1],
            away_px: self.n[2],
            mean_on_lit: mean(0),
            mean_on_cast: mean(1),
            mean_on_away: mean(2),
            iou_dark: ratio(self.tp as f64, (self.tp + self.fp + self.fn_) as f64),
            accuracy: ratio(
                (self.tp + self.tn) as f64,
                (self.tp + self.tn + self.fp + self.fn_) as f64,
            ),
        }
    }
}

/// NaN for an empty denominator (written as null in the JSON).
pub(super) fn ratio(a: f64, b: f64) -> f64 {
    if b > 0.0 {
        a / b
    } else {
        f64::NAN
    }
}

/// Per-Gaussian scores of a visibility (`V_i` or `V'_i`) against whether the Sun reaches the
/// Gaussian's centre, weighted by opacity: mean value on reached / blocked Gaussians and the
/// accuracy of `value >= 0.5` meaning "reached".
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct GaussianScores {
    pub reached: usize,
    pub blocked: usize,
    pub mean_on_reached: f64,
    pub mean_on_blocked: f64,
    pub accuracy: f64,
}

#[derive(Clone, Copy, Debug, Default)]
pub(super) struct GaussianAcc {
    n: [usize; 2],
    w: [f64; 2],
    sum: [f64; 2],
    correct_w: f64,
}

impl GaussianAcc {
    pub(super) fn add(&mut self, reached: bool, value: f32, weight: f32) {
        let k = usize::from(!reached);
        self.n[k] += 1;
        self.w[k] += weight as f64;
        self.sum[k] += (weight * value) as f64;
        if (value >= 0.5) == reached {
            self.correct_w += weight as f64;
        }
    }

    pub(super) fn merge(&mut self, o: &GaussianAcc) {
        for k in 0..2 {
            self.n[k] += o.n[k];
            self.w[k] += o.w[k];
            self.sum[k] += o.sum[k];
        }
        self.correct_w += o.correct_w;
    }

    pub(super) fn scores(&self) -> GaussianScores {
        GaussianScores {
            reached: self.n[0],
            blocked: self.n[1],
            mean_on_reached: ratio(self.sum[0], self.w[0]),
            mean_on_blocked: ratio(self.sum[1], self.w[1]),
            accuracy: ratio(self.correct_w, self.w[0] + self.w[1]),
        }
    }
}
