//! A small Sun-lit scene with self-shadowing, for tests and sanity measurements.
//!
//! The target (body frame, centred on the origin): a square plate of flat Gaussians in the
//! plane z = 0 (side 1 m, normal +z, a colour pattern) and a ball of Gaussians of radius
//! `BALL_RADIUS_M` floating above its centre. Ground truth is Lambertian with an ambient
//! term, and the ball casts an exact shadow on the plate: a plate Gaussian is dark when the
//! ray from its centre towards the Sun hits the ball (analytic ray-sphere test, independent
//! of the model's shadow pass). Colours depend on the Sun only, the images are rendered by
//! the rasterizer with those colours, and the mask is the rendered opacity.

use glam::Vec3;

use crate::camera::{Camera, Intrinsics};
use crate::init::{inverse_sigmoid, SplitMix64};
use crate::model::{GaussianModel, ModelLayout, Param};
use crate::nn::SceneBox;
use crate::raster::{render, GaussianView, RasterSettings};

use super::error::SunAwareError;

pub const PLATE_HALF_SIDE_M: f32 = 0.5;
pub const BALL_CENTRE_M: [f32; 3] = [0.0, 0.0, 0.3];
pub const BALL_RADIUS_M: f32 = 0.15;
/// Light reaching surfaces that face away from the Sun or lie in shadow (Earth albedo).
pub const AMBIENT: f32 = 0.06;

/// The ground-truth scene.
#[derive(Clone, Debug)]
pub struct SyntheticScene {
    /// Geometry and opacity of the ground truth (SH groups unused).
    pub gaussians: GaussianModel,
    pub albedo: Vec<[f32; 3]>,
    pub normals: Vec<Vec3>,
    /// Plate Gaussians come first: `0..plate_count`.
    pub plate_count: usize,
    pub scene_box: SceneBox,
}

/// Whether the ray `origin + t dir` (t > 0) meets the ball.
fn ray_hits_ball(origin: Vec3, dir: Vec3) -> bool {
    let c = Vec3::from_array(BALL_CENTRE_M);
    let oc = origin - c;
    let b = oc.dot(dir);
    let disc = b * b - (oc.length_squared() - BALL_RADIUS_M * BALL_RADIUS_M);
    disc > 0.0 && -b - disc.sqrt() > 0.0
}

impl SyntheticScene {
    /// Plate of `plate_side x plate_side` Gaussians and a ball of `ball_count` Gaussians.
    pub fn plate_and_ball(plate_side: usize, ball_count: usize) -> Result<Self, SunAwareError> {
        if plate_side < 2 || ball_count < 4 {
            return Err(SunAwareError::Config(
                "synthetic scene needs plate_side >= 2 and ball_count >= 4".into(),
            ));
        }
        let mut means = Vec::new();
        let mut normals = Vec::new();
        let mut albedo = Vec::new();
        let mut log_scales = Vec::new();
        let step = 2.0 * PLATE_HALF_SIDE_M / (plate_side - 1) as f32;
        for iy in 0..plate_side {
            for ix in 0..plate_side {
                let x = -PLATE_HALF_SIDE_M + ix as f32 * step;
                let y = -PLATE_HALF_SIDE_M + iy as f32 * step;
                means.push(Vec3::new(x, y, 0.0));
                normals.push(Vec3::Z);
                // Four coloured quadrants so appearance is not one colour.
                let c = match (x >= 0.0, y >= 0.0) {
                    (true, true) => [0.9, 0.75, 0.3],
                    (false, true) => [0.3, 0.6, 0.9],
                    (true, false) => [0.8, 0.8, 0.8],
                    (false, false) => [0.7, 0.35, 0.3],
                };
                albedo.push(c);
                let s = (0.75 * step).ln();
                log_scales.push([s, s, (0.1 * step).ln()]);
            }
        }
        let plate_count = means.len();
        // Fibonacci sphere.
        let golden = std::f32::consts::PI * (3.0 - 5.0f32.sqrt());
        let ball_scale = (BALL_RADIUS_M * 2.2 / (ball_count as f32).sqrt()).ln();
        for k in 0..ball_count {
            let z = 1.0 - 2.0 * (k as f32 + 0.5) / ball_count as f32;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * k as f32;
            let n = Vec3::new(r * phi.cos(), r * phi.sin(), z);
            means.push(Vec3::from_array(BALL_CENTRE_M) + n * BALL_RADIUS_M);
            normals.push(n);
            albedo.push([0.85, 0.85, 0.9]);
            log_scales.push([ball_scale; 3]);
        }
        let mut gaussians = GaussianModel::new(ModelLayout::sh(0))?;
        gaussians.params.push_zeros(means.len());
        let p = &mut gaussians.params;
        for (i, m) in means.iter().enumerate() {
            p.row_mut(Param::Mean, i).copy_from_slice(&m.to_array());
            p.row_mut(Param::LogScale, i)
                .copy_from_slice(&log_scales[i]);
            p.row_mut(Param::Rotation, i)
                .copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
            p.row_mut(Param::OpacityLogit, i)[0] = inverse_sigmoid(0.95);
        }
        let scene_box = SceneBox::new([-0.6, -0.6, -0.15], [0.6, 0.6, 0.6])?;
        Ok(Self {
            gaussians,
            albedo,
            normals,
            plate_count,
            scene_box,
        })
    }

    /// Whether Gaussian `i` is in the ball's shadow for this Sun (plate Gaussians only).
    pub fn in_shadow(&self, i: usize, sun_dir: Vec3) -> bool {
        if i >= self.plate_count {
            return false;
        }
        let m = self.gaussians.params.row(Param::Mean, i);
        ray_hits_ball(Vec3::new(m[0], m[1], m[2]), sun_dir.normalize())
    }

    /// Ground-truth colour of every Gaussian under this Sun, `N * 3`.
    pub fn shade(&self, sun_dir: Vec3) -> Vec<f32> {
        let sun = sun_dir.normalize();
        let mut out = Vec::with_capacity(self.albedo.len() * 3);
        for (i, (a, n)) in self.albedo.iter().zip(&self.normals).enumerate() {
            let lit = if self.in_shadow(i, sun) {
                0.0
            } else {
                n.dot(sun).max(0.0)
            };
            let light = AMBIENT + (1.0 - AMBIENT) * lit;
            out.extend(a.iter().map(|c| c * light));
        }
        out
    }

    /// Ground-truth image (`H * W * 3`) and mask (`H * W`, the rendered opacity).
    pub fn render(
        &self,
        camera: &Camera,
        sun_dir: Vec3,
    ) -> Result<(Vec<f32>, Vec<f32>), SunAwareError> {
        let colours = self.shade(sun_dir);
        let view = GaussianView::from_model(&self.gaussians, &colours, 3);
        let out = render(camera, &view, &RasterSettings::default())?;
        let mask = out.alpha.iter().map(|a| a.clamp(0.0, 1.0)).collect();
        Ok((out.color, mask))
    }

    /// Surface samples for initialisation: the ground-truth centres jittered by
    /// `jitter_m` (seeded), their normals and a grey colour.
    pub fn surface_samples(
        &self,
        jitter_m: f32,
        seed: u64,
    ) -> (Vec<Vec3>, Vec<Vec3>, Vec<[f32; 3]>) {
        let mut rng = SplitMix64::new(seed);
        let points = (0..self.gaussians.len())
            .map(|i| {
                let m = self.gaussians.params.row(Param::Mean, i);
                Vec3::new(m[0], m[1], m[2])
                    + Vec3::new(rng.normal(), rng.normal(), rng.normal()) * jitter_m
            })
            .collect();
        (
            points,
            self.normals.clone(),
            vec![[0.5; 3]; self.normals.len()],
        )
    }
}

/// Camera `index` of `count` on a circle of `radius_m` around the z axis at `elevation_rad`
/// above the plate, looking at the origin.
pub fn orbit_camera(
    index: usize,
    count: usize,
    radius_m: f32,
    elevation_rad: f32,
    width: u32,
    height: u32,
) -> Camera {
    let az = std::f32::consts::TAU * index as f32 / count.max(1) as f32;
    let eye = Vec3::new(
        radius_m * elevation_rad.cos() * az.cos(),
        radius_m * elevation_rad.cos() * az.sin(),
        radius_m * elevation_rad.sin(),
    );
    let k = Intrinsics::from_fov_x(0.75, width, height);
    Camera::look_at(k, eye, Vec3::ZERO, Vec3::Z)
}

/// A Sun above the plate, at azimuth `azimuth_rad` and elevation `elevation_rad`.
pub fn sun_direction(azimuth_rad: f32, elevation_rad: f32) -> Vec3 {
    Vec3::new(
        elevation_rad.cos() * azimuth_rad.cos(),
        elevation_rad.cos() * azimuth_rad.sin(),
        elevation_rad.sin(),
    )
}
