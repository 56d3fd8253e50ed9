//! Ground-truth Sun visibility: which surface points the Sun reaches directly.
//!
//! `render_sunlight` classifies the surface point hit by each pixel-centre ray (the same
//! ray that makes the frame's mask and depth) as
//! - `SunClass::Lit`: its geometric normal (turned to the viewer, surfaces are two-sided)
//!   faces the Sun and the shadow ray towards the Sun escapes the mesh;
//! - `SunClass::CastShadow`: it faces the Sun but other geometry blocks the shadow ray
//!   (self-occlusion: what shadow splatting exists to model), or the frame is in eclipse;
//! - `SunClass::FacingAway`: the Sun is behind the surface (attached shadow, "n . l <= 0",
//!   which shading alone already explains);
//! - `SunClass::Background`: the ray misses the target.
//!
//! The test is exactly the one `shade` applies to the Sun (same normal, same shadow-ray
//! origin offset), so a pixel is `Lit` if and only if the renderer added direct sunlight to
//! its centre sample (before the material's micro-normal perturbation, which can only darken
//! a lit point further). `sun_reaches_point` answers the same question for an arbitrary
//! point, e.g. a Gaussian's centre (no normal: the ray starts a small step towards the Sun).
//!
//! Invariants: deterministic, independent of the thread count; validates the request like the
//! renderer.

use super::bvh::Ray;
use super::{CameraRays, FrameRequest, RenderError, Scene};
use glam::Vec3;
use rayon::prelude::*;

/// Direct-sunlight class of a pixel's centre hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub(crate) enum SunClass {
    Background = 0,
    Lit = 1,
    CastShadow = 2,
    FacingAway = 3,
}

/// Per-pixel [`SunClass`], row-major from the top-left pixel.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct SunlightMap {
    pub width: u32,
    pub height: u32,
    pub class: Vec<SunClass>,
}

impl SunlightMap {
    /// Fractions of the target's pixels that are lit, in cast shadow, facing away.
    pub(crate) fn fractions(&self) -> [f64; 3] {
        let mut counts = [0usize; 3];
        for c in &self.class {
            match c {
                SunClass::Lit => counts[0] += 1,
                SunClass::CastShadow => counts[1] += 1,
                SunClass::FacingAway => counts[2] += 1,
                SunClass::Background => {}
            }
        }
        let total = counts.iter().sum::<usize>().max(1) as f64;
        counts.map(|c| c as f64 / total)
    }
}

/// Classifies every pixel's centre hit (see the module header).
pub(crate) fn render_sunlight(
    scene: &Scene,
    req: &FrameRequest,
) -> Result<SunlightMap, RenderError> {
    req.validate()?;
    let (width, height) = (req.camera.width as usize, req.camera.height as usize);
    let rays = CameraRays::new(req);
    let sun = req.sun_dir_target.normalize();
    let mut class = vec![SunClass::Background; width * height];
    class
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let ray = rays.centre(x, y);
                let Some(hit) = scene.bvh.closest_hit(&ray, 0.0, f32::INFINITY) else {
                    continue;
                };
                let position = ray.origin + ray.direction * hit.t;
                let to_viewer = -ray.direction.normalize();
                let mut normal = scene.triangle_normals[hit.triangle_index as usize];
                if normal.dot(to_viewer) < 0.0 {
                    normal = -normal;
                }
                *out = if !req.sun_lit {
                    SunClass::CastShadow
                } else if normal.dot(sun) <= 0.0 {
                    SunClass::FacingAway
                } else {
                    let shadow_origin = position + normal * scene.shadow_offset_m;
                    if scene
                        .bvh
                        .any_hit(&Ray::new(shadow_origin, sun), 0.0, f32::INFINITY)
                    {
                        SunClass::CastShadow
                    } else {
                        SunClass::Lit
                    }
                };
            }
        });
    Ok(SunlightMap {
        width: req.camera.width,
        height: req.camera.height,
        class,
    })
}

/// Whether a ray from `point + step_m * sun` towards the Sun escapes the mesh. A point on a
/// closed body's face turned away from the Sun is therefore not reached (the ray crosses the
/// body), one on a thin single-layer plate is, from either side. `None` for a non-finite
/// point, a zero Sun vector or a negative step.
pub(crate) fn sun_reaches_point(
    scene: &Scene,
    point: Vec3,
    sun_dir: Vec3,
    step_m: f32,
) -> Option<bool> {
    let sun = sun_dir.try_normalize()?;
    if !point.is_finite() || !step_m.is_finite() || step_m < 0.0 {
        return None;
    }
    let start = point + sun * step_m;
    Some(!scene.bvh.any_hit(&Ray::new(start, sun), 0.0, f32::INFINITY))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raytrace::tests::request;
    use crate::target::{Material, MeshBuilder};

    /// A 2 m plate at z = 1 over a 0.5 m cube at the origin.
    fn plate_over_cube() -> Scene {
        let mut b = MeshBuilder::new();
        let m = b.material(Material::white_paint());
        b.quad_grid(
            Vec3::new(-1.0, -1.0, 1.0),
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 2.0, 0.0),
            4,
            4,
            m,
        );
        b.simple_box(Vec3::ZERO, Vec3::splat(0.25), 0.25, m);
        Scene::new(b.build().unwrap())
    }

    #[test]
    fn cube_under_plate_is_in_cast_shadow_until_the_sun_moves_aside() {
        let scene = plate_over_cube();
        // Seen from the side (below the plate), the cube's +x face is in the picture centre.
        let eye = Vec3::new(6.0, 0.0, 0.0);
        let centre = 32 * 64 + 32;
        // The Sun straight above: the cube's +x face is edge-on (n . l = 0: facing away).
        let from_above = render_sunlight(&scene, &request(eye, Vec3::Z)).unwrap();
        assert_eq!(from_above.class[centre], SunClass::FacingAway);
        // The Sun tilted towards +x but still above the plate's rim: the face turns to the
        // Sun and the plate blocks it.
        let tilted = Vec3::new(0.4, 0.0, 1.0).normalize();
        let map = render_sunlight(&scene, &request(eye, tilted)).unwrap();
        assert_eq!(map.class[centre], SunClass::CastShadow);
        // The Sun low from +x: the shadow ray passes under the plate.
        let low = Vec3::new(1.0, 0.0, 0.1).normalize();
        let map = render_sunlight(&scene, &request(eye, low)).unwrap();
        assert_eq!(map.class[centre], SunClass::Lit);
        assert_eq!(map.class[0], SunClass::Background);
        let [lit, cast, away] = map.fractions();
        assert!((lit + cast + away - 1.0).abs() < 1e-9);
        // Eclipse: nothing is lit.
        let mut dark = request(eye, tilted);
        dark.sun_lit = false;
        let map = render_sunlight(&scene, &dark).unwrap();
        assert!(map.class.iter().all(|&c| c != SunClass::Lit));
    }

    #[test]
    fn lit_pixels_are_exactly_those_the_renderer_gives_direct_sunlight() {
        let scene = plate_over_cube();
        let sun = Vec3::new(0.4, 0.3, 1.0).normalize();
        let req = request(Vec3::new(4.0, 3.0, 1.5), sun);
        let map = render_sunlight(&scene, &req).unwrap();
        let radiance = crate::raytrace::render_radiance(&scene, &req).unwrap();
        let mut lit = 0;
        for (c, rgb) in map.class.iter().zip(&radiance.radiance_rgb) {
            let bright = rgb.iter().any(|&v| v > 0.0);
            if *c == SunClass::Lit {
                lit += 1;
                // White paint has no micro-normal perturbation that could darken it.
                assert!(bright, "lit pixel without radiance");
            } else {
                assert!(!bright, "{c:?} pixel with radiance {rgb:?}");
            }
        }
        assert!(lit > 50, "only {lit} lit pixels");
        assert!(map.class.contains(&SunClass::CastShadow));
    }

    #[test]
    fn points_under_the_plate_are_not_reached() {
        let scene = plate_over_cube();
        let top_of_cube = Vec3::new(0.0, 0.0, 0.25);
        assert_eq!(
            sun_reaches_point(&scene, top_of_cube, Vec3::Z, 1e-3),
            Some(false)
        );
        assert_eq!(
            sun_reaches_point(&scene, top_of_cube, Vec3::X + 0.05 * Vec3::Z, 1e-3),
            Some(true)
        );
        // The cube's bottom face: reached from below; a Sun from above sends its ray
        // through the cube itself (and then the plate).
        let bottom = Vec3::new(0.0, 0.0, -0.25);
        assert_eq!(
            sun_reaches_point(&scene, bottom, -Vec3::Z, 1e-3),
            Some(true)
        );
        assert_eq!(
            sun_reaches_point(&scene, bottom, Vec3::new(0.3, 0.0, 1.0), 1e-3),
            Some(false)
        );
        assert_eq!(sun_reaches_point(&scene, bottom, Vec3::ZERO, 1e-3), None);
        assert_eq!(sun_reaches_point(&scene, bottom, Vec3::Z, -1e-3), None);
        assert_eq!(sun_reaches_point(&scene, bottom, Vec3::Z, f32::NAN), None);
        assert_eq!(
            sun_reaches_point(&scene, Vec3::splat(f32::NAN), Vec3::Z, 1e-3),
            None
        );
    }
}
