//! The geometry of one rendezvous instant: chief orbit, servicer position from the ROE map,
//! target tumble, camera look-at pose, Sun and Earth directions, Earth shadow.
//!
//! Frames: ECI (EME2000), chief RTN, target body, camera (OpenCV axes), servicer body
//! (= camera rotated by the mounting). The target sits at the chief's position; the servicer
//! (camera) is the deputy. Invariants: every direction returned is a unit vector; the camera
//! always looks at the target centre, so `t_camera_from_target_m` is (0, 0, range).

use super::attitude::{look_at_camera_from_inertial, TumbleAttitude};
use super::kepler::{KeplerElements, RtnFrame};
use super::roe::Roe;
use super::shadow::sun_visible_fraction;
use super::sun::sun_position_eci_m;
use super::time::UtcEpoch;
use glam::{DQuat, DVec3};

/// Everything that fixes the relative motion and illumination of a scenario.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RendezvousGeometry {
    pub epoch: UtcEpoch,
    pub chief: KeplerElements,
    pub roe: Roe,
    pub target_attitude: TumbleAttitude,
    /// Camera mounting on the servicer: maps camera-frame components to servicer body ones.
    pub q_body_from_camera: DQuat,
    /// Earth-albedo fill strength relative to the Sun with a fully lit Earth disc below.
    pub earth_albedo_strength: f64,
    /// A frame is flagged as eclipse when less than this fraction of the Sun's disc is visible.
    pub eclipse_below_sun_fraction: f64,
}

/// Geometry of one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameGeometry {
    pub time_s: f64,
    pub chief_position_eci_m: DVec3,
    /// Servicer (camera) position relative to the target in the chief RTN frame.
    pub servicer_rtn_m: DVec3,
    pub range_m: f64,
    /// x_camera = q_camera_from_target * x_target + t_camera_from_target_m.
    pub q_camera_from_target: DQuat,
    pub t_camera_from_target_m: DVec3,
    pub q_inertial_from_target: DQuat,
    pub sun_dir_target: DVec3,
    pub sun_dir_camera: DVec3,
    pub sun_dir_servicer_body: DVec3,
    /// Towards the Earth's centre, target body frame.
    pub earth_dir_target: DVec3,
    /// Earth-fill strength for this frame (0 in eclipse).
    pub earth_fill_strength: f64,
    pub sun_visible_fraction: f64,
    pub eclipse: bool,
    /// Angle between target->camera and target->Sun (0 = Sun behind the camera), radians.
    pub phase_angle_rad: f64,
}

impl RendezvousGeometry {
    /// Servicer position relative to the target in chief RTN at `t_s` (ROE linear map).
    pub(crate) fn servicer_rtn_m(&self, t_s: f64) -> DVec3 {
        let chief = self.chief.propagated(t_s);
        self.roe.relative_position_rtn_m(
            self.chief.semi_major_axis_m,
            self.chief.mean_motion_rad_s(),
            chief.mean_arg_of_latitude_rad(),
            t_s,
        )
    }

    /// Geometry at `t_s` seconds after the epoch.
    pub fn at(&self, t_s: f64) -> FrameGeometry {
        let chief_state = self.chief.propagated(t_s).state();
        let rtn = RtnFrame::from_state(&chief_state);
        let servicer_rtn_m = self.servicer_rtn_m(t_s);
        let camera_rel_target_eci = rtn.eci_from_rtn() * servicer_rtn_m;
        let range_m = camera_rel_target_eci.length();

        let q_camera_from_inertial =
            look_at_camera_from_inertial(camera_rel_target_eci, rtn.normal);
        let q_inertial_from_target = self.target_attitude.q_inertial_from_body(t_s);
        let q_camera_from_target = (q_camera_from_inertial * q_inertial_from_target).normalize();
        let t_camera_from_target_m = q_camera_from_inertial * (-camera_rel_target_eci);

        let sun_eci_m = sun_position_eci_m(self.epoch.centuries_tt_since_j2000(t_s));
        let sun_dir_inertial = (sun_eci_m - chief_state.position_m).normalize();
        let q_target_from_inertial = q_inertial_from_target.inverse();
        let sun_dir_target = q_target_from_inertial * sun_dir_inertial;
        let sun_dir_camera = q_camera_from_inertial * sun_dir_inertial;
        let sun_dir_servicer_body = self.q_body_from_camera * sun_dir_camera;
        let zenith = chief_state.position_m.normalize();
        let earth_dir_target = q_target_from_inertial * (-zenith);

        let fraction = sun_visible_fraction(chief_state.position_m, sun_eci_m);
        let eclipse = fraction < self.eclipse_below_sun_fraction;
        // Lit fraction of the Earth's disc seen from above: (1 + cos(Sun-zenith angle)) / 2.
        let earth_phase = 0.5 * (1.0 + sun_dir_inertial.dot(zenith));
        let earth_fill_strength = if eclipse {
            0.0
        } else {
            self.earth_albedo_strength * earth_phase
        };
        let phase_angle_rad = (camera_rel_target_eci / range_m)
            .dot(sun_dir_inertial)
            .clamp(-1.0, 1.0)
            .acos();
        FrameGeometry {
            time_s: t_s,
            chief_position_eci_m: chief_state.position_m,
            servicer_rtn_m,
            range_m,
            q_camera_from_target,
            t_camera_from_target_m,
            q_inertial_from_target,
            sun_dir_target,
            sun_dir_camera,
            sun_dir_servicer_body,
            earth_dir_target,
            earth_fill_strength,
            sun_visible_fraction: fraction,
            eclipse,
            phase_angle_rad,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::orbit::kepler::RtnFrame;

    fn geometry() -> RendezvousGeometry {
        RendezvousGeometry {
            epoch: UtcEpoch::new(2024, 6, 1, 6, 30, 0.0).unwrap(),
            chief: KeplerElements {
                semi_major_axis_m: 6_948_300.0,
                eccentricity: 0.0,
                inclination_rad: 97.8f64.to_radians(),
                raan_rad: 1.0,
                arg_perigee_rad: 0.0,
                mean_anomaly_rad: 0.2,
            },
            roe: Roe::from_scaled_m([0.0, 5.0, 3.0, 30.0, 3.0, 30.0], 6_948_300.0),
            target_attitude: TumbleAttitude {
                q_inertial_from_body_at_epoch: DQuat::from_euler(
                    glam::EulerRot::ZXY,
                    0.4,
                    1.0,
                    -0.3,
                ),
                axis_body: DVec3::X,
                rate_rad_s: 2f64.to_radians(),
            },
            q_body_from_camera: DQuat::from_rotation_y(0.5),
            earth_albedo_strength: 0.3,
            eclipse_below_sun_fraction: 0.5,
        }
    }

    #[test]
    fn frames_are_consistent_with_each_other() {
        let geo = geometry();
        for k in 0..200 {
            let t = k as f64 * 37.0;
            let g = geo.at(t);
            // Camera on target: the target centre projects onto the principal point.
            assert!((g.t_camera_from_target_m - DVec3::new(0.0, 0.0, g.range_m)).length() < 1e-9);
            assert!((g.range_m - g.servicer_rtn_m.length()).abs() < 1e-9);
            // The same Sun in every frame.
            assert!(
                (g.q_camera_from_target * g.sun_dir_target - g.sun_dir_camera).length() < 1e-12
            );
            assert!(
                (geo.q_body_from_camera * g.sun_dir_camera - g.sun_dir_servicer_body).length()
                    < 1e-12
            );
            let sun_eci = sun_position_eci_m(geo.epoch.centuries_tt_since_j2000(t));
            let sun_inertial = (sun_eci - g.chief_position_eci_m).normalize();
            assert!((g.q_inertial_from_target * g.sun_dir_target - sun_inertial).length() < 1e-12);
            // The camera position seen from the target matches the RTN position.
            let chief = geo.chief.propagated(t).state();
            let rtn = RtnFrame::from_state(&chief);
            let q_inertial_from_camera =
                g.q_inertial_from_target * g.q_camera_from_target.inverse();
            let camera_pos = q_inertial_from_camera * (-g.t_camera_from_target_m);
            assert!((rtn.to_rtn(camera_pos) - g.servicer_rtn_m).length() < 1e-8);
            // Image "up" (-y) leans towards the orbit normal.
            assert!((q_inertial_from_camera * DVec3::NEG_Y).dot(rtn.normal) > 0.0);
            // Earth below the chief, and the eclipse flag follows the visible fraction.
            assert!(
                (g.q_inertial_from_target * g.earth_dir_target + chief.position_m.normalize())
                    .length()
                    < 1e-12
            );
            assert_eq!(g.eclipse, g.sun_visible_fraction < 0.5);
            assert!(g.earth_fill_strength >= 0.0 && g.earth_fill_strength <= 0.3);
            if g.eclipse {
                assert_eq!(g.earth_fill_strength, 0.0);
            }
            let phase = (camera_pos / g.range_m).dot(sun_inertial).acos();
            assert!((phase - g.phase_angle_rad).abs() < 1e-9);
        }
    }

    #[test]
    fn an_orbit_has_both_sunlight_and_eclipse_at_low_beta() {
        // RAAN 1 rad in June at i = 97.8 deg: the Sun is near the orbit plane.
        let geo = geometry();
        let period = geo.chief.period_s();
        let flags: Vec<bool> = (0..600)
            .map(|k| geo.at(k as f64 * period / 600.0).eclipse)
            .collect();
        let eclipsed = flags.iter().filter(|&&e| e).count();
        assert!(
            eclipsed > 100 && eclipsed < 300,
            "{eclipsed} of 600 samples in eclipse"
        );
        // One contiguous shadow pass per orbit (two flag changes, counting wrap-around).
        let changes = (0..600)
            .filter(|&k| flags[k] != flags[(k + 1) % 600])
            .count();
        assert_eq!(changes, 2);
    }
}
