//! Colours for hull points ([`sample_colours`]): each point takes the colour of the view
//! that sees it most frontally.
//!
//! Invariant: a non-finite sample is never used; a point no view qualifies for gets the
//! fallback colour, and those points are counted.

use super::{FOREGROUND_THRESHOLD, NEAR_M};
use glam::{Vec3, Vec4};
use rayon::prelude::*;

use crate::camera::Camera;

/// One view for colouring: camera, sRGB-like image in [0, 1] (`width * height * 3`) and mask.
#[derive(Clone, Copy, Debug)]
pub struct ColourView<'a> {
    pub camera: Camera,
    pub rgb: &'a [f32],
    pub mask: &'a [u8],
}

/// Colour of each point from the view that sees it most frontally (largest cosine between
/// its normal and the direction to the camera) among the views where it projects onto a
/// foreground pixel; `fallback` where no view qualifies (or a view's buffers do not match
/// its camera: such views are skipped). Occlusion by other parts of the target is not
/// tested. Returns the colours and how many points got the fallback.
pub fn sample_colours(
    points: &[Vec3],
    normals: &[Vec3],
    views: &[ColourView],
    fallback: [f32; 3],
) -> (Vec<[f32; 3]>, usize) {
    let usable: Vec<&ColourView> = views
        .iter()
        .filter(|v| {
            let n = v.camera.intrinsics.pixel_count();
            n > 0 && v.rgb.len() == 3 * n && v.mask.len() == n
        })
        .collect();
    let colours: Vec<Option<[f32; 3]>> = points
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let normal = normals.get(i).copied().unwrap_or(Vec3::ZERO);
            let mut best: Option<(f32, [f32; 3])> = None;
            for view in &usable {
                let c = view.camera.world_to_camera(p);
                if c.z <= NEAR_M {
                    continue;
                }
                let (u, v) = view.camera.camera_to_pixel(c);
                let k = view.camera.intrinsics;
                if !(u >= 0.0 && v >= 0.0 && u < k.width as f32 && v < k.height as f32) {
                    continue;
                }
                let pixel = v as usize * k.width as usize + u as usize;
                if view.mask[pixel] < FOREGROUND_THRESHOLD {
                    continue;
                }
                let to_camera = (view.camera.position() - p).normalize_or_zero();
                let frontal = normal.dot(to_camera);
                let rgb = [
                    view.rgb[3 * pixel],
                    view.rgb[3 * pixel + 1],
                    view.rgb[3 * pixel + 2],
                ];
                if !Vec4::new(rgb[0], rgb[1], rgb[2], frontal).is_finite() {
                    continue;
                }
                if best.is_none_or(|(b, _)| frontal > b) {
                    best = Some((frontal, rgb));
                }
            }
            best.map(|(_, rgb)| rgb)
        })
        .collect();
    let missing = colours.iter().filter(|c| c.is_none()).count();
    (
        colours.into_iter().map(|c| c.unwrap_or(fallback)).collect(),
        missing,
    )
}
