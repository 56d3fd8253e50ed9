//! Target attitude (initial orientation plus a constant tumble about a body axis) and the
//! camera's look-at attitude.
//!
//! Conventions: `q_inertial_from_body` maps body-frame components to inertial ones. Camera axes
//! follow OpenCV: x right, y down, z forward (boresight).

use glam::{DMat3, DQuat, DVec3};

/// Torque-free spin about a fixed body axis at a constant rate (a flat spin, as in the paper).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TumbleAttitude {
    pub q_inertial_from_body_at_epoch: DQuat,
    /// Unit spin axis, body frame.
    pub axis_body: DVec3,
    pub rate_rad_s: f64,
}

impl TumbleAttitude {
    /// Orientation at `t_s` after the epoch. A rotation about a body axis composes on the right.
    pub(crate) fn q_inertial_from_body(&self, t_s: f64) -> DQuat {
        let spin = DQuat::from_axis_angle(self.axis_body, self.rate_rad_s * t_s);
        (self.q_inertial_from_body_at_epoch * spin).normalize()
    }
}

/// Attitude of a camera at `camera_from_target_inertial` (the camera's position relative to the
/// target) looking at the target centre. Roll: image "up" (-y) is as close as possible to
/// `up_hint`; a fallback hint is used when the two are nearly parallel.
pub fn look_at_camera_from_inertial(camera_position_rel_target: DVec3, up_hint: DVec3) -> DQuat {
    let forward = (-camera_position_rel_target).normalize();
    let mut hint = up_hint.normalize();
    if forward.cross(hint).length() < 1e-3 {
        hint = forward.any_orthonormal_vector();
    }
    // y points down, so it is minus the hint's part perpendicular to the boresight.
    let down = -(hint - forward * forward.dot(hint)).normalize();
    let right = down.cross(forward);
    let inertial_from_camera = DMat3::from_cols(right, down, forward);
    DQuat::from_mat3(&inertial_from_camera)
        .inverse()
        .normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tumble_rate_and_axis_are_respected() {
        let q0 = DQuat::from_euler(glam::EulerRot::ZYX, 0.3, -0.2, 1.0);
        let tumble = TumbleAttitude {
            q_inertial_from_body_at_epoch: q0,
            axis_body: DVec3::X,
            rate_rad_s: 2f64.to_radians(),
        };
        // The body x axis stays fixed in inertial space; body y turns by rate * t about it.
        let x0 = q0 * DVec3::X;
        let y0 = q0 * DVec3::Y;
        let t = 10.0;
        let q = tumble.q_inertial_from_body(t);
        assert!((q * DVec3::X - x0).length() < 1e-12);
        let y = q * DVec3::Y;
        assert!((y0.dot(y) - 20f64.to_radians().cos()).abs() < 1e-12);
        // Positive rotation: y0 moves towards z0 (right-hand rule about x).
        assert!(y.dot(q0 * DVec3::Z) > 0.0);
    }

    #[test]
    fn look_at_points_the_boresight_at_the_target() {
        let cam_pos = DVec3::new(12.0, -30.0, 7.0);
        let q = look_at_camera_from_inertial(cam_pos, DVec3::Z);
        // The target (origin) lies on the +z axis of the camera at the range.
        let target_in_camera = q * (DVec3::ZERO - cam_pos);
        assert!((target_in_camera - DVec3::new(0.0, 0.0, cam_pos.length())).length() < 1e-9);
        // Inertial +z appears "up" in the image: negative camera y.
        assert!((q * DVec3::Z).y < 0.0);
        assert!((q * DVec3::Z).x.abs() < 1e-12);
        // Degenerate hint along the boresight still gives a proper rotation.
        let q2 = look_at_camera_from_inertial(DVec3::new(0.0, 0.0, 5.0), DVec3::Z);
        assert!(((q2 * DVec3::new(0.0, 0.0, -5.0)) - DVec3::new(0.0, 0.0, 5.0)).length() < 1e-9);
    }
}
