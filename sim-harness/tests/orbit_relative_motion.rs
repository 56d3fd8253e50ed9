//! The ROE linear map against a numerical (RK4) two-body propagation of chief and deputy, and
//! the passive-safety property of e/i-vector separation.

use glam::DVec3;
use sim_harness::orbit::kepler::{propagate_rk4, KeplerElements, OrbitState, RtnFrame};
use sim_harness::orbit::Roe;

const A_M: f64 = 6_948_300.0;

fn chief() -> KeplerElements {
    KeplerElements {
        semi_major_axis_m: A_M,
        eccentricity: 0.0,
        inclination_rad: 97.8f64.to_radians(),
        raan_rad: 0.4,
        arg_perigee_rad: 0.0,
        mean_anomaly_rad: 0.3,
    }
}

/// Deputy position relative to the chief in the chief's RTN frame from two numerically
/// propagated absolute orbits, sampled every `sample_s` for `duration_s`.
fn numerical_relative_rtn(roe: &Roe, duration_s: f64, sample_s: f64) -> Vec<(f64, DVec3)> {
    let chief = chief();
    let mut c: OrbitState = chief.state();
    let mut d: OrbitState = roe.deputy_elements(&chief).state();
    let mut out = Vec::new();
    let mut t = 0.0;
    while t <= duration_s {
        let rtn = RtnFrame::from_state(&c);
        out.push((t, rtn.to_rtn(d.position_m - c.position_m)));
        c = propagate_rk4(&c, sample_s, 2.5);
        d = propagate_rk4(&d, sample_s, 2.5);
        t += sample_s;
    }
    out
}

#[test]
fn roe_map_matches_two_body_propagation_over_an_orbit() {
    let chief = chief();
    let n = chief.mean_motion_rad_s();
    let period = chief.period_s();
    let cases_m = [
        [0.0, 0.0, 0.0, 300.0, 0.0, 300.0],
        [0.0, 100.0, 200.0, -150.0, 100.0, 250.0],
        [20.0, -300.0, 100.0, 100.0, -200.0, 50.0],
    ];
    for scaled in cases_m {
        let roe = Roe::from_scaled_m(scaled, A_M);
        let mut worst_m: f64 = 0.0;
        let mut largest_separation_m: f64 = 0.0;
        for (t, numeric) in numerical_relative_rtn(&roe, period, 20.0) {
            let u = chief.propagated(t).mean_arg_of_latitude_rad();
            let linear = roe.relative_position_rtn_m(A_M, n, u, t);
            worst_m = worst_m.max((linear - numeric).length());
            largest_separation_m = largest_separation_m.max(numeric.length());
        }
        eprintln!("ROE {scaled:?}: max |linear - numeric| = {worst_m:.4} m (separation up to {largest_separation_m:.0} m)");
        assert!(
            largest_separation_m > 250.0,
            "the case must actually separate the spacecraft"
        );
        // Second-order terms are of size |droe|^2 a and rho^2 / a: a few centimetres here.
        assert!(
            worst_m < 0.1,
            "linear map off by {worst_m} m for {scaled:?}"
        );
    }
}

/// Minimum radial-normal separation seen by the numerical propagation over three orbits.
fn numerical_min_rn_m(roe: &Roe) -> f64 {
    numerical_relative_rtn(roe, 3.0 * chief().period_s(), 5.0)
        .iter()
        .map(|(_, r)| r.x.hypot(r.z))
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn parallel_e_i_vectors_keep_the_predicted_radial_normal_separation() {
    for (de_m, di_m, phase_deg) in [
        (200.0, 200.0, 90.0),
        (150.0, 250.0, 30.0),
        (300.0, 120.0, -60.0),
    ] {
        let phase = f64::to_radians(phase_deg);
        let (s, c) = phase.sin_cos();
        let roe = Roe::from_scaled_m([0.0, 0.0, de_m * c, de_m * s, di_m * c, di_m * s], A_M);
        let theory = f64::min(de_m, di_m);
        assert!((roe.min_radial_normal_separation_m(A_M) - theory).abs() < 1e-9);
        let numeric = numerical_min_rn_m(&roe);
        eprintln!("de {de_m} m, di {di_m} m: numerical min RN separation {numeric:.3} m, theory {theory} m");
        // Sampling every 5 s (0.3 deg of u) can only overestimate the minimum, by < 0.02 m here.
        assert!((numeric - theory).abs() < 0.1, "{numeric} vs {theory}");
    }
}

#[test]
fn non_parallel_e_i_vectors_lose_separation_as_theory_predicts() {
    // 60 deg between de and di: the general formula; 90 deg: the orbits cross (zero minimum).
    for angle_deg in [60.0f64, 90.0] {
        let angle = angle_deg.to_radians();
        let roe = Roe::from_scaled_m(
            [
                0.0,
                0.0,
                0.0,
                200.0,
                200.0 * angle.sin(),
                200.0 * angle.cos(),
            ],
            A_M,
        );
        let theory = roe.min_radial_normal_separation_m(A_M);
        let numeric = numerical_min_rn_m(&roe);
        eprintln!("e/i angle {angle_deg} deg: numerical {numeric:.3} m, theory {theory:.3} m");
        assert!(theory < 200.0 - 1.0);
        assert!((numeric - theory).abs() < 0.5, "{numeric} vs {theory}");
    }
}

#[test]
fn e_i_separated_constructor_is_passively_safe() {
    let roe = Roe::e_i_separated(40.0, std::f64::consts::FRAC_PI_2, A_M);
    assert!((roe.min_radial_normal_separation_m(A_M) - 40.0).abs() < 1e-9);
    assert!((numerical_min_rn_m(&roe) - 40.0).abs() < 0.05);
}
