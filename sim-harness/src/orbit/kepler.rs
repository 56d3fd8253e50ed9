//! Keplerian elements, Kepler's equation, ECI state vectors, the RTN frame and an RK4 two-body
//! propagator used as the numerical reference for the relative-motion model.
//!
//! Invariants: elliptical orbits only (0 <= e < 1, a > 0); angles in radians; the RTN frame is
//! right-handed and orthonormal (R radial out, N along the angular momentum, T = N x R).

use super::EARTH_MU_M3_S2;
use glam::{DMat3, DVec3};
use std::f64::consts::TAU;

/// Classical orbital elements of an elliptical Earth orbit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeplerElements {
    pub semi_major_axis_m: f64,
    pub eccentricity: f64,
    pub inclination_rad: f64,
    pub raan_rad: f64,
    pub arg_perigee_rad: f64,
    pub mean_anomaly_rad: f64,
}

/// Position and velocity in ECI.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitState {
    pub position_m: DVec3,
    pub velocity_m_s: DVec3,
}

/// Orthonormal radial / along-track / normal axes expressed in ECI.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RtnFrame {
    pub radial: DVec3,
    pub along_track: DVec3,
    pub normal: DVec3,
}

/// Eccentric anomaly E solving M = E - e sin E (Newton, converges for e < 1).
pub(crate) fn eccentric_anomaly_rad(mean_anomaly_rad: f64, eccentricity: f64) -> f64 {
    let m = mean_anomaly_rad.rem_euclid(TAU);
    let mut e_anom = if eccentricity < 0.8 {
        m
    } else {
        std::f64::consts::PI
    };
    for _ in 0..50 {
        let f = e_anom - eccentricity * e_anom.sin() - m;
        let step = f / (1.0 - eccentricity * e_anom.cos());
        e_anom -= step;
        if step.abs() < 1e-15 {
            break;
        }
    }
    e_anom
}

impl KeplerElements {
    /// Mean motion n = sqrt(mu / a^3), rad/s.
    pub fn mean_motion_rad_s(&self) -> f64 {
        (EARTH_MU_M3_S2 / self.semi_major_axis_m.powi(3)).sqrt()
    }

    /// Orbital period, seconds.
    pub fn period_s(&self) -> f64 {
        TAU / self.mean_motion_rad_s()
    }

    /// Mean argument of latitude u = omega + M, radians.
    pub fn mean_arg_of_latitude_rad(&self) -> f64 {
        self.arg_perigee_rad + self.mean_anomaly_rad
    }

    /// The same orbit `dt_s` later (unperturbed two-body motion: only M changes).
    pub fn propagated(&self, dt_s: f64) -> KeplerElements {
        KeplerElements {
            mean_anomaly_rad: self.mean_anomaly_rad + self.mean_motion_rad_s() * dt_s,
            ..*self
        }
    }

    /// Rotation from the perifocal frame (P towards perigee, Q, W normal) to ECI.
    fn eci_from_perifocal(&self) -> DMat3 {
        DMat3::from_rotation_z(self.raan_rad)
            * DMat3::from_rotation_x(self.inclination_rad)
            * DMat3::from_rotation_z(self.arg_perigee_rad)
    }

    /// ECI position and velocity.
    pub fn state(&self) -> OrbitState {
        let a = self.semi_major_axis_m;
        let e = self.eccentricity;
        let e_anom = eccentric_anomaly_rad(self.mean_anomaly_rad, e);
        let (sin_e, cos_e) = e_anom.sin_cos();
        let root = (1.0 - e * e).sqrt();
        let r = a * (1.0 - e * cos_e);
        let position_pf = DVec3::new(a * (cos_e - e), a * root * sin_e, 0.0);
        let speed_scale = (EARTH_MU_M3_S2 * a).sqrt() / r;
        let velocity_pf = DVec3::new(-speed_scale * sin_e, speed_scale * root * cos_e, 0.0);
        let rotation = self.eci_from_perifocal();
        OrbitState {
            position_m: rotation * position_pf,
            velocity_m_s: rotation * velocity_pf,
        }
    }
}

impl RtnFrame {
    /// RTN axes of a state (requires non-zero, non-parallel position and velocity).
    pub fn from_state(state: &OrbitState) -> RtnFrame {
        let radial = state.position_m.normalize();
        let normal = state.position_m.cross(state.velocity_m_s).normalize();
        RtnFrame {
            radial,
            along_track: normal.cross(radial),
            normal,
        }
    }

    /// Rotation taking RTN components to ECI components (columns are the axes).
    pub(crate) fn eci_from_rtn(&self) -> DMat3 {
        DMat3::from_cols(self.radial, self.along_track, self.normal)
    }

    /// Components of an ECI vector along R, T, N.
    pub fn to_rtn(&self, v_eci: DVec3) -> DVec3 {
        DVec3::new(
            v_eci.dot(self.radial),
            v_eci.dot(self.along_track),
            v_eci.dot(self.normal),
        )
    }
}

fn two_body_acceleration(position_m: DVec3) -> DVec3 {
    let r2 = position_m.length_squared();
    -EARTH_MU_M3_S2 / (r2 * r2.sqrt()) * position_m
}

/// One classical fourth-order Runge-Kutta step of point-mass two-body motion.
pub fn rk4_step(state: &OrbitState, dt_s: f64) -> OrbitState {
    let (r0, v0) = (state.position_m, state.velocity_m_s);
    let k1r = v0;
    let k1v = two_body_acceleration(r0);
    let k2r = v0 + 0.5 * dt_s * k1v;
    let k2v = two_body_acceleration(r0 + 0.5 * dt_s * k1r);
    let k3r = v0 + 0.5 * dt_s * k2v;
    let k3v = two_body_acceleration(r0 + 0.5 * dt_s * k2r);
    let k4r = v0 + dt_s * k3v;
    let k4v = two_body_acceleration(r0 + dt_s * k3r);
    OrbitState {
        position_m: r0 + dt_s / 6.0 * (k1r + 2.0 * k2r + 2.0 * k3r + k4r),
        velocity_m_s: v0 + dt_s / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v),
    }
}

/// Propagate `duration_s` with fixed RK4 steps no longer than `max_step_s` (last step shortened).
pub fn propagate_rk4(state: &OrbitState, duration_s: f64, max_step_s: f64) -> OrbitState {
    let steps = (duration_s / max_step_s).ceil().max(1.0) as u64;
    let dt = duration_s / steps as f64;
    let mut current = *state;
    for _ in 0..steps {
        current = rk4_step(&current, dt);
    }
    current
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leo(e: f64) -> KeplerElements {
        KeplerElements {
            semi_major_axis_m: 6_948_300.0,
            eccentricity: e,
            inclination_rad: 97.8f64.to_radians(),
            raan_rad: 0.4,
            arg_perigee_rad: 1.1,
            mean_anomaly_rad: 2.3,
        }
    }

    #[test]
    fn kepler_equation_is_solved() {
        for &e in &[0.0, 0.001, 0.3, 0.9] {
            for i in 0..50 {
                let m = i as f64 * 0.37 - 3.0;
                let big_e = eccentric_anomaly_rad(m, e);
                let residual = big_e - e * big_e.sin() - m.rem_euclid(TAU);
                assert!(residual.abs() < 1e-12, "e={e} M={m} residual {residual}");
            }
        }
    }

    #[test]
    fn state_has_vis_viva_energy_and_angular_momentum() {
        let el = leo(0.01);
        let s = el.state();
        let r = s.position_m.length();
        let v2 = s.velocity_m_s.length_squared();
        let energy = v2 / 2.0 - EARTH_MU_M3_S2 / r;
        assert!((energy + EARTH_MU_M3_S2 / (2.0 * el.semi_major_axis_m)).abs() < 1e-6);
        let h = s.position_m.cross(s.velocity_m_s);
        let h_expected = (EARTH_MU_M3_S2 * el.semi_major_axis_m * (1.0 - 0.01f64.powi(2))).sqrt();
        assert!((h.length() - h_expected).abs() / h_expected < 1e-12);
        // The angular momentum points along the orbit normal given by i and RAAN.
        let normal = DVec3::new(
            el.raan_rad.sin() * el.inclination_rad.sin(),
            -el.raan_rad.cos() * el.inclination_rad.sin(),
            el.inclination_rad.cos(),
        );
        assert!((h.normalize() - normal).length() < 1e-12);
    }

    #[test]
    fn rk4_matches_kepler_over_an_orbit() {
        let el = leo(0.02);
        let start = el.state();
        for &duration in &[1000.0, el.period_s()] {
            let numeric = propagate_rk4(&start, duration, 2.0);
            let analytic = el.propagated(duration).state();
            let err = (numeric.position_m - analytic.position_m).length();
            assert!(err < 1e-3, "RK4 vs Kepler after {duration} s: {err} m");
        }
    }

    #[test]
    fn rtn_frame_is_orthonormal_and_right_handed() {
        let s = leo(0.05).state();
        let f = RtnFrame::from_state(&s);
        let m = f.eci_from_rtn();
        assert!((m.transpose() * m - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-14));
        assert!((m.determinant() - 1.0).abs() < 1e-14);
        assert!(f.to_rtn(s.velocity_m_s).y > 0.0);
        assert!(
            (f.to_rtn(s.position_m) - DVec3::new(s.position_m.length(), 0.0, 0.0)).length() < 1e-6
        );
    }
}
