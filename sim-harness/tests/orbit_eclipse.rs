//! Eclipse entry/exit from the conical shadow model against closed-form geometry for a circular
//! orbit whose plane makes an angle beta with the Sun direction.
//!
//! For a circular orbit of radius r the angle c between the Earth's centre and the Sun's centre
//! seen from the satellite obeys cos c = cos(beta) cos(phi), phi the orbit angle from the point
//! nearest the anti-Sun direction. Umbra: c < b - a, penumbra: b - a < c < b + a, where
//! b = asin(R_E / r) and a = the Sun's apparent radius. Mid-penumbra (c = b) is the classical
//! cylindrical-shadow boundary, duration (2/n) acos(sqrt(1 - (R_E/r)^2) / cos beta).

use glam::DVec3;
use sim_harness::orbit::kepler::KeplerElements;
use sim_harness::orbit::{sun_visible_fraction, AU_M, EARTH_RADIUS_M, SUN_RADIUS_M};

const A_M: f64 = 6_948_300.0;

/// Polar orbit in the x-z plane (normal -y) and a fixed Sun at 1 AU, beta above the plane.
fn setup(beta_rad: f64) -> (KeplerElements, DVec3) {
    let orbit = KeplerElements {
        semi_major_axis_m: A_M,
        eccentricity: 0.0,
        inclination_rad: std::f64::consts::FRAC_PI_2,
        raan_rad: 0.0,
        arg_perigee_rad: 0.0,
        mean_anomaly_rad: 0.0,
    };
    let sun = DVec3::new(beta_rad.cos(), -beta_rad.sin(), 0.0) * AU_M;
    (orbit, sun)
}

/// Total time in one orbit with `predicate(fraction)` true, with crossings found by bisection.
fn duration_where(beta_rad: f64, predicate: impl Fn(f64) -> bool) -> f64 {
    let (orbit, sun) = setup(beta_rad);
    let inside = |t: f64| {
        predicate(sun_visible_fraction(
            orbit.propagated(t).state().position_m,
            sun,
        ))
    };
    let period = orbit.period_s();
    let step = 1.0;
    let mut total = 0.0;
    let mut t = 0.0;
    let mut previous = inside(0.0);
    let mut entered_at = if previous { Some(0.0) } else { None };
    while t < period {
        let next_t = (t + step).min(period);
        let now = inside(next_t);
        if now != previous {
            let (mut lo, mut hi) = (t, next_t);
            for _ in 0..40 {
                let mid = 0.5 * (lo + hi);
                if inside(mid) == previous {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let crossing = 0.5 * (lo + hi);
            if now {
                entered_at = Some(crossing);
            } else if let Some(start) = entered_at.take() {
                total += crossing - start;
            }
        }
        previous = now;
        t = next_t;
    }
    if let Some(start) = entered_at {
        total += period - start;
    }
    total
}

/// Closed-form time with c below `c_limit_rad`, including the first-order effect of the Sun's
/// parallax: seen from the satellite the Sun is displaced by r/D sin c towards the satellite's
/// zenith side, so cos c grows by (r/D) sin^2 c and each boundary moves out by
/// dphi = (r/D) sin^2 c / (cos beta sin phi).
fn closed_form_duration_s(beta_rad: f64, c_limit_rad: f64) -> f64 {
    let n = (sim_harness::orbit::EARTH_MU_M3_S2 / A_M.powi(3)).sqrt();
    let cos_phi = c_limit_rad.cos() / beta_rad.cos();
    if cos_phi >= 1.0 {
        return 0.0;
    }
    let phi = cos_phi.acos();
    let parallax_phi = (A_M / AU_M) * c_limit_rad.sin().powi(2) / (beta_rad.cos() * phi.sin());
    2.0 * (phi + parallax_phi) / n
}

#[test]
fn shadow_durations_match_cone_geometry() {
    let b = (EARTH_RADIUS_M / A_M).asin();
    let a = (SUN_RADIUS_M / AU_M).asin();
    for beta_deg in [0.0f64, 30.0, 60.0] {
        let beta = beta_deg.to_radians();
        let umbra = duration_where(beta, |f| f == 0.0);
        let any_shadow = duration_where(beta, |f| f < 1.0);
        let mid = duration_where(beta, |f| f < 0.5);
        let umbra_expected = closed_form_duration_s(beta, b - a);
        let any_expected = closed_form_duration_s(beta, b + a);
        let cylinder = closed_form_duration_s(beta, b);
        eprintln!(
            "beta {beta_deg}: umbra {umbra:.2} s ({umbra_expected:.2}), shadow {any_shadow:.2} s \
             ({any_expected:.2}), mid-penumbra {mid:.2} s (cylinder {cylinder:.2})"
        );
        // Umbra and penumbra boundaries are exact in the model (second-order parallax terms are
        // microseconds). Mid-penumbra differs from c = b only by the planar disc-overlap formula
        // at the Earth's curved limb.
        assert!(
            (umbra - umbra_expected).abs() < 0.01,
            "umbra {umbra} vs {umbra_expected}"
        );
        assert!(
            (any_shadow - any_expected).abs() < 0.01,
            "shadow {any_shadow} vs {any_expected}"
        );
        assert!(
            (mid - cylinder).abs() < 0.1,
            "mid-penumbra {mid} vs cylinder {cylinder}"
        );
        assert!(
            umbra > 600.0,
            "a LEO orbit at beta {beta_deg} deg has a long eclipse"
        );
    }
}

#[test]
fn no_eclipse_above_the_critical_beta_angle() {
    let b = (EARTH_RADIUS_M / A_M).asin();
    let a = (SUN_RADIUS_M / AU_M).asin();
    let just_outside = b + a + 0.2f64.to_radians();
    assert_eq!(duration_where(just_outside, |f| f < 1.0), 0.0);
    // Just inside the penumbra cone: a short grazing partial eclipse, no umbra.
    let grazing = b + 0.1f64.to_radians();
    assert!(duration_where(grazing, |f| f < 1.0) > 0.0);
    assert_eq!(duration_where(grazing, |f| f == 0.0), 0.0);
}

#[test]
fn visible_fraction_decreases_monotonically_through_the_penumbra() {
    let (orbit, sun) = setup(0.0);
    // Entry: the satellite passes phi = -(b + a) .. -(b - a) before the anti-Sun point (u = pi).
    let period = orbit.period_s();
    let mut previous = 1.0;
    let mut saw_partial = false;
    for i in 0..4000 {
        let t = period * (0.5 - 0.2) + i as f64 * 0.25;
        let f = sun_visible_fraction(orbit.propagated(t).state().position_m, sun);
        assert!((0.0..=1.0).contains(&f));
        assert!(
            f <= previous + 1e-12,
            "fraction rose from {previous} to {f} at t = {t}"
        );
        saw_partial |= f > 0.0 && f < 1.0;
        previous = f;
    }
    assert!(saw_partial && previous == 0.0);
}
