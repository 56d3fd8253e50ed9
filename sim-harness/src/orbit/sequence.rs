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
    pub fn servicer_rtn_m(&self, t_s: f64) -> DVec3 {
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
