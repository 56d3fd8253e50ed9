//! Quasi-nonsingular relative orbital elements (D'Amico) and their linear map to the deputy's
//! position in the chief's RTN frame, valid for a near-circular chief.
//!
//! Definitions (chief c, deputy d, u = omega + M the mean argument of latitude):
//! da = (a_d - a_c)/a_c, dl = (u_d - u_c) + (RAAN_d - RAAN_c) cos i_c,
//! de = e_d - e_c as (e cos omega, e sin omega) vectors, dix = i_d - i_c,
//! diy = (RAAN_d - RAAN_c) sin i_c. All dimensionless; "metres" variants are a_c times them.
//! Invariant: the chief is not equatorial (sin i_c != 0), else diy has no meaning.

use super::kepler::KeplerElements;
use glam::DVec3;

/// Dimensionless quasi-nonsingular relative orbital elements.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Roe {
    pub da: f64,
    pub dl: f64,
    pub dex: f64,
    pub dey: f64,
    pub dix: f64,
    pub diy: f64,
}

impl Roe {
    /// ROE from values scaled by the chief's semi-major axis (a * droe, metres).
    pub fn from_scaled_m(scaled_m: [f64; 6], semi_major_axis_m: f64) -> Roe {
        let [da, dl, dex, dey, dix, diy] = scaled_m.map(|v| v / semi_major_axis_m);
        Roe {
            da,
            dl,
            dex,
            dey,
            dix,
            diy,
        }
    }

    /// The values scaled by `semi_major_axis_m` (metres), in the order da, dl, dex, dey, dix, diy.
    pub(crate) fn scaled_m(&self, semi_major_axis_m: f64) -> [f64; 6] {
        [self.da, self.dl, self.dex, self.dey, self.dix, self.diy].map(|v| v * semi_major_axis_m)
    }

    /// Passively safe e/i-separated geometry: parallel relative e and i vectors, both of size
    /// `separation_m / a`, at phase `phase_rad` (pi/2 puts both along y: radial and normal motion
    /// in quadrature, largest along-track excursion at the ascending node).
    pub fn e_i_separated(separation_m: f64, phase_rad: f64, semi_major_axis_m: f64) -> Roe {
        let d = separation_m / semi_major_axis_m;
        let (sin_p, cos_p) = phase_rad.sin_cos();
        Roe {
            da: 0.0,
            dl: 0.0,
            dex: d * cos_p,
            dey: d * sin_p,
            dix: d * cos_p,
            diy: d * sin_p,
        }
    }

    /// Deputy position in the chief RTN frame (metres) from the linear map, at mean argument of
    /// latitude `u_rad` of the chief and time `t_s` since the epoch of these ROE.
    pub fn relative_position_rtn_m(
        &self,
        semi_major_axis_m: f64,
        mean_motion_rad_s: f64,
        u_rad: f64,
        t_s: f64,
    ) -> DVec3 {
        let a = semi_major_axis_m;
        let (sin_u, cos_u) = u_rad.sin_cos();
        let dl = self.dl - 1.5 * mean_motion_rad_s * self.da * t_s;
        DVec3::new(
            a * (self.da - self.dex * cos_u - self.dey * sin_u),
            a * (dl + 2.0 * self.dex * sin_u - 2.0 * self.dey * cos_u),
            a * (self.dix * sin_u - self.diy * cos_u),
        )
    }

    /// Minimum separation in the radial-normal plane over an orbit (metres), for da = 0
    /// (Montenbruck et al. 2006): sqrt(2) a |de.di| / sqrt(de^2 + di^2 + |de + di| |de - di|).
    /// For parallel vectors this is a * min(|de|, |di|); for perpendicular ones it is zero.
    pub fn min_radial_normal_separation_m(&self, semi_major_axis_m: f64) -> f64 {
        let de = glam::DVec2::new(self.dex, self.dey);
        let di = glam::DVec2::new(self.dix, self.diy);
        let denominator =
            (de.length_squared() + di.length_squared() + (de + di).length() * (de - di).length())
                .sqrt();
        if denominator == 0.0 {
            return 0.0;
        }
        std::f64::consts::SQRT_2 * semi_major_axis_m * de.dot(di).abs() / denominator
    }

    /// Deputy Keplerian elements realising these ROE about `chief` (exact inverse of the
    /// definitions above). The chief must not be equatorial.
    pub fn deputy_elements(&self, chief: &KeplerElements) -> KeplerElements {
        let (sin_i, cos_i) = chief.inclination_rad.sin_cos();
        let raan_d = chief.raan_rad + self.diy / sin_i;
        let u_d = chief.mean_arg_of_latitude_rad() + self.dl - (raan_d - chief.raan_rad) * cos_i;
        let ex_d = chief.eccentricity * chief.arg_perigee_rad.cos() + self.dex;
        let ey_d = chief.eccentricity * chief.arg_perigee_rad.sin() + self.dey;
        let arg_perigee_d = ey_d.atan2(ex_d);
        KeplerElements {
            semi_major_axis_m: chief.semi_major_axis_m * (1.0 + self.da),
            eccentricity: ex_d.hypot(ey_d),
            inclination_rad: chief.inclination_rad + self.dix,
            raan_rad: raan_d,
            arg_perigee_rad: arg_perigee_d,
            mean_anomaly_rad: u_d - arg_perigee_d,
        }
    }
}
