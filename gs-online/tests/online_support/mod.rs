//! The short synthetic sequence of the online-trainer tests (`online_sequence.rs`,
//! `online_wgpu.rs`): a plate with a ball casting a shadow, seen from a circling camera
//! under a moving Sun, and the held-out PSNR the tests score a trainer by.
#![allow(dead_code)]

use gs_core::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
use gs_online::online::{Frame, OnlineTrainer};

pub const W: u32 = 48;
pub const H: u32 = 36;
/// Camera steps per orbit: 15 degrees apart, more than the 10 degree keyframe threshold.
pub const PER_ORBIT: usize = 24;

/// Frame `id` of the sequence (all black when `eclipse`).
pub fn frame(scene: &SyntheticScene, id: u64, eclipse: bool) -> Frame {
    let camera = orbit_camera(id as usize % PER_ORBIT, PER_ORBIT, 2.4, 0.6, W, H);
    let sun = sun_direction(0.35 * id as f32, 0.9);
    let (mut image, mask) = scene.render(&camera, sun).unwrap();
    if eclipse {
        image.fill(0.0);
    }
    Frame {
        id,
        time_s: 5.0 * id as f64,
        camera,
        sun_dir_target: sun,
        image,
        mask: Some(mask),
        eclipse,
    }
}

/// Mean masked PSNR over three views the sequence never trains on.
pub fn held_out_psnr(t: &OnlineTrainer, scene: &SyntheticScene) -> f32 {
    let ids = [1000u64, 1007, 1013];
    ids.iter()
        .map(|&id| {
            let f = frame(scene, id, false);
            let obs = gs_core::sunaware::Observation {
                camera: f.camera,
                sun_dir: f.sun_dir_target,
                image: &f.image,
                mask: f.mask.as_deref(),
            };
            t.trainer().evaluate(&obs, true).unwrap().psnr_db
        })
        .sum::<f32>()
        / ids.len() as f32
}
