//! A tiny synthetic orbit for the exact-resume tests: frame k looks at the target from 25
//! degrees further round a circle at 8 m, and sees a lit, textured disc (masked) on black;
//! the Sun is fixed in the target frame. Deterministic in k; 8-bit RGB.
#![allow(dead_code)]

use glam::Vec3;
use gs_core::{Camera, Intrinsics};

/// One frame of the orbit.
pub struct DiscFrame {
    pub camera: Camera,
    /// The camera's position, target frame, metres.
    pub eye_m: Vec3,
    /// Unit Sun direction, target frame.
    pub sun_target: Vec3,
    /// RGB8, row-major.
    pub pixels: Vec<u8>,
    /// 255 on the disc, 0 elsewhere.
    pub mask: Vec<u8>,
}

/// Frame `k` of the orbit, a square image of `side` pixels with the camera `intrinsics`.
pub fn disc_frame(k: u32, side: u16, intrinsics: Intrinsics) -> DiscFrame {
    let azimuth = k as f32 * 25f32.to_radians();
    let eye = Vec3::new(azimuth.cos(), azimuth.sin(), 0.3).normalize() * 8.0;
    let camera = Camera::look_at(intrinsics, eye, Vec3::ZERO, Vec3::Z);
    let centre_px = (f32::from(side) - 1.0) / 2.0;
    let (mut pixels, mut mask) = (Vec::new(), Vec::new());
    for y in 0..side {
        for x in 0..side {
            let (dx, dy) = (f32::from(x) - centre_px, f32::from(y) - centre_px);
            let inside = dx * dx + dy * dy < 25.0;
            let shade = ((x * 13 + y * 7 + k as u16 * 31) % 200) as u8;
            if inside {
                pixels.extend_from_slice(&[55 + shade, 40 + shade / 2, 90]);
            } else {
                pixels.extend_from_slice(&[0, 0, 0]);
            }
            mask.push(u8::from(inside) * 255);
        }
    }
    DiscFrame {
        camera,
        eye_m: eye,
        sun_target: Vec3::new(0.6, -0.3, 0.74).normalize(),
        pixels,
        mask,
    }
}
