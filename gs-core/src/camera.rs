//! Pinhole camera: intrinsics in pixels and a rigid world-to-camera transform.
//!
//! Convention (OpenCV): camera x right, y down, z forward; a point is in front of the
//! camera when its camera-frame z is positive. Pixel centres are at integer + 0.5
//! coordinates, so the pixel (u, v) covers [u, u+1) x [v, v+1).

use glam::{Mat3, Quat, Vec3};

/// Pinhole intrinsics, pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    /// Square pixels, principal point at the image centre, from a horizontal field of view.
    pub fn from_fov_x(fov_x_rad: f32, width: u32, height: u32) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x_rad).tan();
        Self {
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            width,
            height,
        }
    }

    /// Horizontal field of view, radians.
    pub fn fov_x_rad(&self) -> f32 {
        2.0 * (0.5 * self.width as f32 / self.fx).atan()
    }

    /// Vertical field of view, radians.
    pub fn fov_y_rad(&self) -> f32 {
        2.0 * (0.5 * self.height as f32 / self.fy).atan()
    }

    /// The same camera with the image scaled by `1/factor` (pixel centres stay consistent).
    pub fn downsampled(&self, factor: u32) -> Self {
        let s = 1.0 / factor as f32;
        Self {
            fx: self.fx * s,
            fy: self.fy * s,
            cx: self.cx * s,
            cy: self.cy * s,
            width: self.width / factor,
            height: self.height / factor,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// A camera: `x_camera = rotation * x_world + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// Rotation from world to camera frame (unit quaternion).
    pub rotation: Quat,
    /// World origin expressed in the camera frame, metres.
    pub translation: Vec3,
}

impl Camera {
    /// A camera at `eye` looking at `target`, with `up` giving the image's -y direction.
    pub fn look_at(intrinsics: Intrinsics, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let z = (target - eye).normalize();
        let mut x = z.cross(up);
        if x.length_squared() < 1e-12 {
            // `up` parallel to the view direction: any perpendicular will do.
            x = z.any_orthonormal_vector();
        }
        let x = x.normalize();
        let y = z.cross(x);
        // Rows of the world-to-camera rotation are the camera axes in world coordinates.
        let rotation = Quat::from_mat3(&Mat3::from_cols(x, y, z).transpose()).normalize();
        Self {
            intrinsics,
            rotation,
            translation: -(rotation * eye),
        }
    }

    /// Camera centre in world coordinates.
    pub fn position(&self) -> Vec3 {
        -(self.rotation.conjugate() * self.translation)
    }

    /// World point to camera frame.
    pub fn world_to_camera(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }

    /// Camera-frame point to pixel coordinates (no check that z > 0).
    pub fn camera_to_pixel(&self, p: Vec3) -> (f32, f32) {
        let k = &self.intrinsics;
        (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_puts_the_target_on_the_principal_point() {
        let k = Intrinsics::from_fov_x(1.0, 64, 48);
        let eye = Vec3::new(3.0, -2.0, 5.0);
        let target = Vec3::new(0.5, 0.25, -1.0);
        let cam = Camera::look_at(k, eye, target, Vec3::Z);
        let p = cam.world_to_camera(target);
        assert!(p.z > 0.0);
        let (u, v) = cam.camera_to_pixel(p);
        assert!((u - k.cx).abs() < 1e-4 && (v - k.cy).abs() < 1e-4);
        assert!((cam.position() - eye).length() < 1e-5);
        // World up appears towards the top of the image (negative v).
        let (_, v_up) = cam.camera_to_pixel(cam.world_to_camera(target + Vec3::Z * 0.1));
        assert!(v_up < k.cy);
    }

    #[test]
    fn fov_round_trips() {
        let k = Intrinsics::from_fov_x(0.7, 960, 600);
        assert!((k.fov_x_rad() - 0.7).abs() < 1e-6);
        assert_eq!(k.downsampled(2).width, 480);
    }
}
