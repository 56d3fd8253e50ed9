//! Exact resume of the online trainer itself: the model through gs-core's checkpoint, the
//! rest through `gs_online::resume`, on frames with arbitrary f32 images (the f32 encoding)
//! and a replay memory; the resumed trainer ends with the same model and state bytes as one
//! that never stopped. A state saved under other settings, or holding more keyframes than
//! W, is refused and changes nothing.

use gs_core::sunaware::checkpoint;
use gs_core::sunaware::synthetic::SyntheticScene;
use gs_core::sunaware::{LightConfig, SunAwareConfig, Variant};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{Initialisation, OnlineConfig, OnlineTrainer};
use gs_online::resume::peek_settings;

mod online_support;
use online_support::{frame, H, W};

const MAX_PIXELS: usize = 1 << 20;

fn config() -> OnlineConfig {
    OnlineConfig {
        window: WindowConfig {
            capacity: 3,
            ..WindowConfig::default()
        },
        model: SunAwareConfig {
            light: LightConfig {
                resolution_px: 32,
                ..LightConfig::default()
            },
            ..SunAwareConfig::for_variant(Variant::D)
        },
        densify_every_rounds: 4,
        shuffle_seed: 3,
        replay_capacity: 2,
        replay_steps_per_round: 2,
        ..OnlineConfig::default()
    }
}

fn trainer(scene: &SyntheticScene, config: OnlineConfig) -> OnlineTrainer {
    let init = Initialisation::RandomSphere {
        count: 40,
        centre: glam::Vec3::ZERO,
        radius_m: 1.0,
        seed: 5,
    };
    OnlineTrainer::new(config, &init, scene.scene_box).unwrap()
}

fn feed(t: &mut OnlineTrainer, scene: &SyntheticScene, ids: std::ops::Range<u64>) {
    for id in ids {
        t.offer(frame(scene, id, false)).unwrap();
        t.run_round_if_due().unwrap();
    }
}

#[test]
fn restored_trainer_continues_bit_for_bit() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let mut whole = trainer(&scene, config());
    feed(&mut whole, &scene, 0..10);
    assert!(whole.rounds() >= 4, "densification must run");
    assert!(whole.replay_len() > 0);
    let split = 5;
    let mut first = trainer(&scene, config());
    feed(&mut first, &scene, 0..split);
    let (model, state) = (checkpoint::to_bytes(first.trainer()), first.state_bytes());
    assert_eq!(peek_settings(&state).unwrap().rounds, first.rounds());
    let f32_images = 3 * (W * H * 3 * 4) as usize;
    assert!(
        state.len() > f32_images,
        "the rendered images are stored as f32"
    );
    drop(first);
    let mut resumed = trainer(&scene, config());
    *resumed.trainer_mut() = checkpoint::from_bytes(&model).unwrap();
    resumed.restore_state(&state, MAX_PIXELS).unwrap();
    assert!(resumed.state_bytes() == state);
    feed(&mut resumed, &scene, split..10);
    assert!(checkpoint::to_bytes(resumed.trainer()) == checkpoint::to_bytes(whole.trainer()));
    assert!(resumed.state_bytes() == whole.state_bytes());
    assert_eq!(resumed.counters(), whole.counters());
}

#[test]
fn other_settings_or_too_many_keyframes_are_refused() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let mut saved = trainer(&scene, config());
    feed(&mut saved, &scene, 0..4);
    let state = saved.state_bytes();
    let mut other = trainer(
        &scene,
        OnlineConfig {
            shuffle_seed: 4,
            ..config()
        },
    );
    let before = other.state_bytes();
    assert!(other.restore_state(&state, MAX_PIXELS).is_err());
    assert!(
        other.state_bytes() == before,
        "a refused restore changes nothing"
    );
    // Frames larger than the caller's pixel limit are refused.
    let mut same = trainer(&scene, config());
    let error = same.restore_state(&state, 100).unwrap_err().to_string();
    assert!(error.contains("pixels"), "{error}");
    // A window count above W, whatever its size, is refused before reading frames.
    let count_at = 8 + 32 + 8 + 9 + 8 + 8 + 64;
    for count in [4u64, u64::MAX] {
        let mut hostile = state.clone();
        hostile[count_at..count_at + 8].copy_from_slice(&count.to_le_bytes());
        let error = same
            .restore_state(&hostile, MAX_PIXELS)
            .unwrap_err()
            .to_string();
        assert!(error.contains("at most 3"), "{error}");
    }
    same.restore_state(&state, MAX_PIXELS).unwrap();
    assert!(same.state_bytes() == state);
}
