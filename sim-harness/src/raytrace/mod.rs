//! CPU ray tracer: BVH, physically based shading, hard Sun shadows.
//!
//! Radiometry (normalised units): the Sun delivers irradiance `SUN_IRRADIANCE` = pi on a
//! surface facing it, so a white Lambertian surface facing the Sun has radiance exactly 1 and a
//! surface of albedo a has radiance a. Pixel value (linear) = exposure * radiance, then clamped
//! to [0, 1] and sRGB-encoded to 8 bits. The optional Earth-albedo fill is a second directional
//! light of irradiance `strength * SUN_IRRADIANCE`, shadowed like the Sun. No other light: the
//! background is black, eclipse frames without fill are exactly zero.
//!
//! Geometry: `x_cam = R x_target + t`, OpenCV axes (x right, y down, z forward), pixel centres
//! at +0.5. Mask and depth come from the ray through each pixel centre; colour averages
//! `samples_per_pixel` stratified, seeded jittered rays (1 sample = the centre ray).
//! [`material_ids`] gives the material the same centre ray hits (scores split by material).
//!
//! Invariants: rendering is deterministic (each pixel seeds its own RNG from the request seed
//! and its index; rows are independent, so the thread count does not matter); radiance is
//! finite and non-negative; depth is the camera z of the hit or +inf.

pub mod bvh;
pub mod shading;
pub mod sunlight;

use crate::target::TargetMesh;
use bvh::{Bvh, Ray};
use glam::{Quat, Vec3};
use gs_core::rng::{mix64, SplitMix64};
use rayon::prelude::*;
use std::fmt;

/// Sun irradiance in normalised units (see the module header).
pub const SUN_IRRADIANCE: f32 = std::f32::consts::PI;
/// Default exposure: sunlit white paint (albedo 0.8) facing the Sun maps to 0.8 linear (sRGB 231).
pub const DEFAULT_EXPOSURE: f32 = 1.0;
/// Largest image side accepted (guards against absurd allocations).
pub(crate) const MAX_IMAGE_SIDE: u32 = 16_384;
/// Most samples per pixel accepted.
pub(crate) const MAX_SAMPLES_PER_PIXEL: u32 = 1024;

/// A mesh with its acceleration structure, ready to render.
pub struct Scene {
    mesh: TargetMesh,
    bvh: Bvh,
    triangle_normals: Vec<Vec3>,
    /// Offset of shadow-ray origins along the normal, metres.
    shadow_offset_m: f32,
}

impl Scene {
    pub fn new(mesh: TargetMesh) -> Scene {
        let corners: Vec<[Vec3; 3]> = (0..mesh.triangle_count())
            .map(|t| mesh.triangle_corners_m(t))
            .collect();
        let bvh = Bvh::build(&corners);
        let triangle_normals = corners
            .iter()
            .map(|[a, b, c]| (*b - *a).cross(*c - *a).normalize_or_zero())
            .collect();
        // Large enough to escape float error at the mesh's scale, far below any feature size.
        let shadow_offset_m = 2e-5 * mesh.bounding_radius_m().max(1.0);
        Scene {
            mesh,
            bvh,
            triangle_normals,
            shadow_offset_m,
        }
    }

    pub fn mesh(&self) -> &TargetMesh {
        &self.mesh
    }
}

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeCamera {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

/// Earth-albedo fill light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EarthFill {
    /// Unit vector towards the Earth, target body frame.
    pub dir_target: Vec3,
    /// Irradiance as a fraction of the Sun's (0.3 typical).
    pub strength: f32,
}

/// Everything needed to render one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameRequest {
    pub camera: PinholeCamera,
    pub camera_from_target_rotation: Quat,
    pub camera_from_target_translation_m: Vec3,
    /// Unit vector towards the Sun, target body frame.
    pub sun_dir_target: Vec3,
    /// False in eclipse: no direct sunlight at all.
    pub sun_lit: bool,
    pub earth_albedo: Option<EarthFill>,
    pub samples_per_pixel: u32,
    pub exposure: f32,
    pub seed: u64,
}

/// An 8-bit sRGB frame with its mask and depth, row-major from the top-left pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// sRGB, 3 bytes per pixel.
    pub rgb8: Vec<u8>,
    /// 255 where the pixel-centre ray hits the target, else 0.
    pub mask: Vec<u8>,
    /// Camera z of the pixel-centre hit in metres; +inf for background.
    pub depth_m: Vec<f32>,
}

/// Linear radiance (normalised units, before exposure) with mask and depth.
#[derive(Clone, Debug, PartialEq)]
pub struct RadianceFrame {
    pub width: u32,
    pub height: u32,
    pub radiance_rgb: Vec<[f32; 3]>,
    pub mask: Vec<u8>,
    pub depth_m: Vec<f32>,
}

/// Why a request cannot be rendered.
#[derive(Clone, Debug, PartialEq)]
pub enum RenderError {
    InvalidCamera(String),
    InvalidPose(String),
    InvalidLighting(String),
    InvalidSampling(String),
}

impl fmt::Display for RenderError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RenderError::InvalidCamera(m) => write!(f, "invalid camera: {m}"),
            RenderError::InvalidPose(m) => write!(f, "invalid pose: {m}"),
            RenderError::InvalidLighting(m) => write!(f, "invalid lighting: {m}"),
            RenderError::InvalidSampling(m) => write!(f, "invalid sampling: {m}"),
        }
    }
}

impl std::error::Error for RenderError {}

fn is_unit(v: Vec3) -> bool {
    v.is_finite() && (v.length() - 1.0).abs() < 1e-3
}

impl FrameRequest {
    /// Checks every field; the renderer relies on these.
    pub fn validate(&self) -> Result<(), RenderError> {
        let c = &self.camera;
        if c.width == 0 || c.height == 0 || c.width > MAX_IMAGE_SIDE || c.height > MAX_IMAGE_SIDE {
            return Err(RenderError::InvalidCamera(format!(
                "image size {}x{} outside 1..={MAX_IMAGE_SIDE}",
                c.width, c.height
            )));
        }
        if ![c.fx, c.fy, c.cx, c.cy].iter().all(|v| v.is_finite()) || c.fx <= 0.0 || c.fy <= 0.0 {
            return Err(RenderError::InvalidCamera(format!(
                "focal lengths must be finite and positive, principal point finite: {c:?}"
            )));
        }
        let q = self.camera_from_target_rotation;
        if !q.is_finite() || (q.length() - 1.0).abs() > 1e-3 {
            return Err(RenderError::InvalidPose(format!(
                "rotation {q:?} is not a unit quaternion"
            )));
        }
        if !self.camera_from_target_translation_m.is_finite() {
            return Err(RenderError::InvalidPose(format!(
                "translation {:?} is not finite",
                self.camera_from_target_translation_m
            )));
        }
        if self.sun_lit && !is_unit(self.sun_dir_target) {
            return Err(RenderError::InvalidLighting(format!(
                "Sun direction {:?} is not a unit vector",
                self.sun_dir_target
            )));
        }
        if let Some(fill) = self.earth_albedo {
            if !is_unit(fill.dir_target) || !fill.strength.is_finite() || fill.strength < 0.0 {
                return Err(RenderError::InvalidLighting(format!(
                    "Earth fill needs a unit direction and a finite strength >= 0: {fill:?}"
                )));
            }
        }
        if self.samples_per_pixel == 0 || self.samples_per_pixel > MAX_SAMPLES_PER_PIXEL {
            return Err(RenderError::InvalidSampling(format!(
                "samples per pixel {} outside 1..={MAX_SAMPLES_PER_PIXEL}",
                self.samples_per_pixel
            )));
        }
        if !self.exposure.is_finite() || self.exposure < 0.0 {
            return Err(RenderError::InvalidSampling(format!(
                "exposure {} must be finite and >= 0",
                self.exposure
            )));
        }
        Ok(())
    }
}

/// Renders an 8-bit frame. An invalid request (see `FrameRequest::validate`) yields an all-black
/// frame with an empty mask and infinite depth, of the requested size clamped to
/// `MAX_IMAGE_SIDE`; call `try_render_frame` to get the error instead.
pub fn render_frame(scene: &Scene, req: &FrameRequest) -> Frame {
    try_render_frame(scene, req).unwrap_or_else(|_| {
        let width = req.camera.width.min(MAX_IMAGE_SIDE);
        let height = req.camera.height.min(MAX_IMAGE_SIDE);
        let n = width as usize * height as usize;
        Frame {
            width,
            height,
            rgb8: vec![0; 3 * n],
            mask: vec![0; n],
            depth_m: vec![f32::INFINITY; n],
        }
    })
}

/// Renders an 8-bit frame, or says why the request is invalid.
pub fn try_render_frame(scene: &Scene, req: &FrameRequest) -> Result<Frame, RenderError> {
    try_render_frame_with(scene, req, true)
}

/// [`try_render_frame`], optionally without cast shadows (see [`render_radiance_with`]).
pub(crate) fn try_render_frame_with(
    scene: &Scene,
    req: &FrameRequest,
    cast_shadows: bool,
) -> Result<Frame, RenderError> {
    let radiance = render_radiance_with(scene, req, cast_shadows)?;
    let rgb8 = radiance
        .radiance_rgb
        .par_iter()
        .flat_map_iter(|rgb| rgb.map(|c| linear_to_srgb8(c * req.exposure)))
        .collect();
    Ok(Frame {
        width: radiance.width,
        height: radiance.height,
        rgb8,
        mask: radiance.mask,
        depth_m: radiance.depth_m,
    })
}

/// Renders linear radiance (before exposure), mask and depth.
pub fn render_radiance(scene: &Scene, req: &FrameRequest) -> Result<RadianceFrame, RenderError> {
    render_radiance_with(scene, req, true)
}

/// [`render_radiance`], optionally without cast shadows (`cast_shadows = false`: no shadow
/// rays, every surface facing a light receives it). Only for studies of how much the
/// target's self-shadowing weighs in an image (`sunlight`); datasets always cast shadows.
pub(crate) fn render_radiance_with(
    scene: &Scene,
    req: &FrameRequest,
    cast_shadows: bool,
) -> Result<RadianceFrame, RenderError> {
    req.validate()?;
    let (width, height) = (req.camera.width as usize, req.camera.height as usize);
    let rays = CameraRays::new(req);
    let lights = Lights::from_request(req);

    let mut radiance_rgb = vec![[0.0f32; 3]; width * height];
    let mut mask = vec![0u8; width * height];
    let mut depth_m = vec![f32::INFINITY; width * height];
    radiance_rgb
        .par_chunks_mut(width)
        .zip(mask.par_chunks_mut(width))
        .zip(depth_m.par_chunks_mut(width))
        .enumerate()
        .for_each(|(y, ((rgb_row, mask_row), depth_row))| {
            for x in 0..width {
                let pixel_index = (y * width + x) as u64;
                let centre_ray = rays.centre(x, y);
                let centre_hit = scene.bvh.closest_hit(&centre_ray, 0.0, f32::INFINITY);
                if let Some(hit) = centre_hit {
                    mask_row[x] = 255;
                    depth_row[x] = hit.t;
                }
                let spp = req.samples_per_pixel;
                let sum = if spp == 1 {
                    centre_hit.map_or(Vec3::ZERO, |hit| {
                        shade(scene, &lights, &centre_ray, hit, cast_shadows)
                    })
                } else {
                    let mut rng = SplitMix64::new(mix64(req.seed ^ mix64(pixel_index)));
                    // A square count gets a jittered grid; any other count jittered rows
                    // (uniform x), so that every sub-pixel area is sampled equally.
                    let side = (spp as f32).sqrt().round() as u32;
                    let columns = if side * side == spp { side } else { 1 };
                    let rows = spp / columns;
                    let mut sum = Vec3::ZERO;
                    for k in 0..spp {
                        let (i, j) = (k % columns, k / columns);
                        let sx = (i as f32 + rng.next_f32()) / columns as f32;
                        let sy = (j as f32 + rng.next_f32()) / rows as f32;
                        let ray = rays.through(x as f32 + sx, y as f32 + sy);
                        if let Some(hit) = scene.bvh.closest_hit(&ray, 0.0, f32::INFINITY) {
                            sum += shade(scene, &lights, &ray, hit, cast_shadows);
                        }
                    }
                    sum
                };
                rgb_row[x] = (sum / spp as f32).to_array();
            }
        });
    Ok(RadianceFrame {
        width: req.camera.width,
        height: req.camera.height,
        radiance_rgb,
        mask,
        depth_m,
    })
}

/// The rays of a request's camera in the target frame (shared by every per-pixel pass, so
/// the image, its mask and the maps of what each pixel sees use the same rays).
pub(crate) struct CameraRays {
    origin: Vec3,
    target_from_camera: Quat,
    camera: PinholeCamera,
}

impl CameraRays {
    pub(crate) fn new(req: &FrameRequest) -> CameraRays {
        let target_from_camera = req.camera_from_target_rotation.normalize().inverse();
        CameraRays {
            origin: target_from_camera * -req.camera_from_target_translation_m,
            target_from_camera,
            camera: req.camera,
        }
    }

    /// The ray through image point (`px`, `py`) (pixel units, top-left corner at 0).
    pub(crate) fn through(&self, px: f32, py: f32) -> Ray {
        let c = &self.camera;
        let d_cam = Vec3::new((px - c.cx) / c.fx, (py - c.cy) / c.fy, 1.0);
        // Camera z of a point at ray parameter s equals s, since d_cam.z = 1.
        Ray::new(self.origin, self.target_from_camera * d_cam)
    }

    /// The ray through the centre of pixel (`x`, `y`): the one that makes mask and depth.
    pub(crate) fn centre(&self, x: usize, y: usize) -> Ray {
        self.through(x as f32 + 0.5, y as f32 + 0.5)
    }
}

/// The material index (into `scene.mesh().materials()`) of the first surface each pixel's
/// centre ray hits, row-major from the top-left pixel; `None` where the ray misses the target
/// (background). The ray is the one that makes the frame's mask, so a pixel has `Some` exactly
/// where `render_frame` gives it mask 255. Only the request's camera and pose matter.
pub fn material_ids(scene: &Scene, req: &FrameRequest) -> Result<Vec<Option<u16>>, RenderError> {
    req.validate()?;
    let width = req.camera.width as usize;
    let rays = CameraRays::new(req);
    let mut ids = vec![None; width * req.camera.height as usize];
    ids.par_chunks_mut(width).enumerate().for_each(|(y, row)| {
        for (x, id) in row.iter_mut().enumerate() {
            *id = scene
                .bvh
                .closest_hit(&rays.centre(x, y), 0.0, f32::INFINITY)
                .map(|hit| scene.mesh.material_of_triangle()[hit.triangle_index as usize]);
        }
    });
    Ok(ids)
}

/// Directional lights: (unit direction towards the light, irradiance).
struct Lights {
    lights: Vec<(Vec3, f32)>,
}

impl Lights {
    fn from_request(req: &FrameRequest) -> Lights {
        let mut lights = Vec::with_capacity(2);
        if req.sun_lit {
            lights.push((req.sun_dir_target.normalize(), SUN_IRRADIANCE));
        }
        if let Some(fill) = req.earth_albedo {
            if fill.strength > 0.0 {
                lights.push((fill.dir_target.normalize(), fill.strength * SUN_IRRADIANCE));
            }
        }
        Lights { lights }
    }
}

/// Radiance leaving the hit point towards the ray origin.
fn shade(scene: &Scene, lights: &Lights, ray: &Ray, hit: bvh::Hit, cast_shadows: bool) -> Vec3 {
    if lights.lights.is_empty() {
        return Vec3::ZERO;
    }
    let t = hit.triangle_index as usize;
    let position = ray.origin + ray.direction * hit.t;
    let to_viewer = -ray.direction.normalize();
    let mut normal = scene.triangle_normals[t];
    // Surfaces are two-sided: shade the side the viewer sees.
    if normal.dot(to_viewer) < 0.0 {
        normal = -normal;
    }
    let material = &scene.mesh.materials()[scene.mesh.material_of_triangle()[t] as usize];
    let mut point = shading::surface_point(material, position, normal);
    // A perturbed normal must not face away from the viewer (it would black out the pixel).
    if point.normal.dot(to_viewer) <= 1e-4 {
        point.normal = normal;
    }
    let shadow_origin = position + normal * scene.shadow_offset_m;
    let mut radiance = Vec3::ZERO;
    for &(to_light, irradiance) in &lights.lights {
        // Light behind the geometric surface cannot reach this side, whatever the crinkles say.
        if normal.dot(to_light) <= 0.0 {
            continue;
        }
        let n_dot_l = point.normal.dot(to_light);
        if n_dot_l <= 0.0 {
            continue;
        }
        if cast_shadows
            && scene
                .bvh
                .any_hit(&Ray::new(shadow_origin, to_light), 0.0, f32::INFINITY)
        {
            continue;
        }
        radiance += shading::brdf(&point, to_light, to_viewer) * (irradiance * n_dot_l);
    }
    radiance
}

/// Camera-from-target pose (rotation, translation) of a camera at `eye_target` looking at
/// `look_at_target`, with image "up" (-y) as close to `up_target` as possible. Returns None
/// when the inputs are not finite, the eye sits on the look-at point, or up is parallel to the
/// viewing direction.
pub fn camera_pose_looking_at(
    eye_target: Vec3,
    look_at_target: Vec3,
    up_target: Vec3,
) -> Option<(Quat, Vec3)> {
    let forward = (look_at_target - eye_target).try_normalize()?;
    let right = forward.cross(up_target).try_normalize()?;
    let down = forward.cross(right);
    // Rows of the camera-from-target matrix are the camera axes in target coordinates.
    let rotation = Quat::from_mat3(&glam::Mat3::from_cols(right, down, forward).transpose());
    Some((rotation, -(rotation * eye_target)))
}

/// Linear [0, 1] (clamped) to 8-bit sRGB.
pub fn linear_to_srgb8(linear: f32) -> u8 {
    let c = if linear.is_finite() {
        linear.clamp(0.0, 1.0)
    } else {
        0.0
    };
    // The same curve the model encodes its linear renders with (`colour_space = "linear"`).
    (gs_core::srgb::encode(c) * 255.0 + 0.5) as u8
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::target::{Material, MeshBuilder};

    /// A 64x64 request (focal length 80 pixels) from `eye` towards the origin, image up +z.
    pub(crate) fn request(eye: Vec3, sun: Vec3) -> FrameRequest {
        let (rotation, translation) = camera_pose_looking_at(eye, Vec3::ZERO, Vec3::Z).unwrap();
        FrameRequest {
            camera: PinholeCamera {
                fx: 80.0,
                fy: 80.0,
                cx: 32.0,
                cy: 32.0,
                width: 64,
                height: 64,
            },
            camera_from_target_rotation: rotation,
            camera_from_target_translation_m: translation,
            sun_dir_target: sun,
            sun_lit: true,
            earth_albedo: None,
            samples_per_pixel: 1,
            exposure: 1.0,
            seed: 0,
        }
    }

    #[test]
    fn material_ids_name_the_centre_hit_and_none_for_background() {
        // Gold over x in [-1, 0], z in [-1, 1]; white paint over x in [0, 1], z in [0, 1]
        // only, in the plane y = 0, seen from -y: image x is +x, image y (down) is -z.
        let mut b = MeshBuilder::new();
        let gold = b.material(Material::gold_mli());
        let white = b.material(Material::white_paint());
        b.quad_grid(
            Vec3::new(-1.0, 0.0, -1.0),
            Vec3::X,
            2.0 * Vec3::Z,
            2,
            4,
            gold,
        );
        b.quad_grid(Vec3::ZERO, Vec3::X, Vec3::Z, 2, 2, white);
        let scene = Scene::new(b.build().unwrap());
        let mut req = request(Vec3::new(0.0, -5.0, 0.0), Vec3::NEG_Y);
        // Only the centre ray counts, however many samples the colour takes.
        req.samples_per_pixel = 4;
        let ids = material_ids(&scene, &req).unwrap();
        // 1 m is 16 pixels at 5 m: the plate spans pixels 16..48 each way.
        let at = |x: usize, y: usize| ids[y * 64 + x];
        assert_eq!(at(24, 24), Some(gold));
        assert_eq!(at(24, 40), Some(gold));
        assert_eq!(at(40, 24), Some(white));
        assert_eq!(at(40, 40), None, "below the white quad is background");
        assert_eq!(at(2, 2), None);
        assert_eq!(at(60, 32), None);
        assert_eq!(scene.mesh().materials()[gold as usize].name, "gold_mli");
        // Some exactly where the frame's mask is set.
        let frame = render_frame(&scene, &req);
        for (id, m) in ids.iter().zip(&frame.mask) {
            assert_eq!(id.is_some(), *m == 255);
        }
        assert_eq!(ids.iter().filter(|i| **i == Some(white)).count(), 16 * 16);
        let mut bad = req;
        bad.camera.fx = 0.0;
        assert!(material_ids(&scene, &bad).is_err());
    }

    #[test]
    fn srgb_encoding_reference_points() {
        assert_eq!(linear_to_srgb8(0.0), 0);
        assert_eq!(linear_to_srgb8(1.0), 255);
        assert_eq!(linear_to_srgb8(2.0), 255);
        assert_eq!(linear_to_srgb8(f32::NAN), 0);
        // 0.2 linear = 0.4845 sRGB = 123.6 -> 124; 0.8 -> 0.9063 -> 231.
        assert_eq!(linear_to_srgb8(0.2), 124);
        assert_eq!(linear_to_srgb8(0.8), 231);
        assert_eq!(linear_to_srgb8(0.002), 7);
    }
}
