//! Gradient check of the isotropic scale loss (Eq. 6) against central differences of an
//! f64 reference.

use super::*;

use gs_core::regularizer::{IsoReduction, IsotropicLoss};

/// f64 reference of Eq. 6 with the given per-Gaussian factor.
fn iso_reference(log_scales: &[f64], factor: f64) -> f64 {
    log_scales
        .chunks_exact(3)
        .map(|u| {
            let s: Vec<f64> = u.iter().map(|v| v.exp()).collect();
            let mean = s.iter().sum::<f64>() / 3.0;
            s.iter().map(|v| (v - mean).abs()).sum::<f64>()
        })
        .sum::<f64>()
        * factor
}

#[test]
fn isotropic_loss_gradient_matches_finite_differences() {
    let n = 40;
    // Kinks (a scale equal to its Gaussian's mean scale) are avoided by construction: the
    // three log-scales sit 0.3 apart plus a jitter of at most 0.1; the assert confirms it.
    let mut log_scales = Vec::with_capacity(3 * n);
    let base = values(n, 55);
    let spread = values(3 * n, 56);
    for i in 0..n {
        for a in 0..3 {
            log_scales.push(-3.0 + base[i] + 0.3 * a as f32 + 0.1 * spread[3 * i + a]);
        }
    }
    let log64 = to_f64(&log_scales);
    for u in log64.chunks_exact(3) {
        let s: Vec<f64> = u.iter().map(|v| v.exp()).collect();
        let mean = s.iter().sum::<f64>() / 3.0;
        assert!(
            s.iter().all(|v| (v - mean).abs() > 1e-4),
            "kink too close: {s:?}"
        );
    }
    for (reduction, lambda, factor) in [
        (IsoReduction::Sum, 0.7f32, 0.7f64),
        (IsoReduction::MeanOverEntries, 10.0, 10.0 / (3 * n) as f64),
    ] {
        let loss = IsotropicLoss::new(lambda, reduction).unwrap();
        let mut grad = vec![0.0f32; 3 * n];
        let value = loss.value_and_grad(&log_scales, &mut grad).unwrap();
        let reference = iso_reference(&log64, factor);
        assert!(
            (value as f64 - reference).abs() <= 1e-5 * reference,
            "{value} vs {reference}"
        );
        let h = 1e-6;
        let scale = grad.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
        for k in 0..log64.len() {
            let (mut plus, mut minus) = (log64.clone(), log64.clone());
            plus[k] += h;
            minus[k] -= h;
            let numeric =
                (iso_reference(&plus, factor) - iso_reference(&minus, factor)) / (2.0 * h);
            assert_grad_close("d_log_scales", k, grad[k], numeric, scale);
        }
    }
}
