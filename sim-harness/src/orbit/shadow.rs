//! Conical Earth-shadow model (Montenbruck & Gill, sec. 3.4.2): the visible fraction of the
//! solar disc seen from a satellite, 1 in sunlight, 0 in the umbra, in between in the penumbra.
//!
//! Invariant: the result is always in [0, 1]; positions are geocentric ECI metres and the
//! satellite is outside the Earth.

use super::{EARTH_RADIUS_M, SUN_RADIUS_M};
use glam::DVec3;
use std::f64::consts::PI;

/// Fraction of the Sun's disc visible from `satellite_m` (0 = umbra, 1 = full sunlight).
pub fn sun_visible_fraction(satellite_m: DVec3, sun_m: DVec3) -> f64 {
    let to_sun = sun_m - satellite_m;
    let sun_distance = to_sun.length();
    let sat_distance = satellite_m.length();
    // Apparent radii of the Sun and the Earth, and their centres' angular separation.
    let a = (SUN_RADIUS_M / sun_distance).asin();
    let b = (EARTH_RADIUS_M / sat_distance).min(1.0).asin();
    let c = ((-satellite_m).dot(to_sun) / (sat_distance * sun_distance))
        .clamp(-1.0, 1.0)
        .acos();
    if c >= a + b {
        return 1.0;
    }
    if c <= b - a {
        return 0.0;
    }
    // Partial overlap of two discs of radii a and b at distance c (small-angle, planar).
    let x = (c * c + a * a - b * b) / (2.0 * c);
    let y = (a * a - x * x).max(0.0).sqrt();
    let overlap = a * a * (x / a).clamp(-1.0, 1.0).acos()
        + b * b * ((c - x) / b).clamp(-1.0, 1.0).acos()
        - c * y;
    (1.0 - overlap / (PI * a * a)).clamp(0.0, 1.0)
}
