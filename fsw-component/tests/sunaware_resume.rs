//! Exact resume of the Sun-aware learner: N frames, save, drop the learner, build a new one
//! from the checkpoint, M more frames, gives the same checkpoint bytes (model, optimiser,
//! window, counters), bit for bit, as N + M frames in one run; the split points cover a
//! pending hull start, a full window, replay memory and a densification after the resume.
//! Also: a configuration that differs from the checkpoint's is refused by default and used
//! (with a log line) when configured so, and a checkpoint of the paper's model is refused
//! by the default (learned-normal) model naming the settings that differ; the learned
//! normals start finite and outward on the random and the hull start; a checkpoint
//! claiming a huge window is refused before allocating; a version-1 checkpoint still loads.

use fsw_component::config::ComponentConfig;
use fsw_component::learner::{Learner, ObservedFrame};
use fsw_component::runtime::{build_learner, LearnerKind};
use fsw_component::sunaware_learner::{
    OnConfigMismatch, SunAwareLearner, SunAwareSettings, CHECKPOINT_MAGIC,
};
use fsw_component::sync::SyncedTelemetry;
use glam::{DQuat, DVec3, Vec3};
use gs_core::Intrinsics;
use gs_core::Param;
use gs_online::keyframe::WindowConfig;
use interfaces::crc::crc32_ieee;
use interfaces::messages::{EventKind, InitSource, PixelFormat};
use orbit_disc::{disc_frame, DiscFrame};
use std::path::Path;

mod orbit_disc;

const SIDE: u16 = 16;
const FRAMES: u32 = 14;

fn settings() -> SunAwareSettings {
    let mut s = SunAwareSettings::with_window(WindowConfig {
        capacity: 3,
        min_view_angle_deg: 10.0,
    });
    s.model.initial_gaussians = 60;
    s.model.hull_resolution = 16;
    s.model.target_radius_m = 2.0;
    s.online.replay_capacity = 2;
    s.online.replay_steps_per_round = 1;
    s.online.shuffle_seed = 7;
    s
}

/// Frame k of the disc orbit (`orbit_disc`), with exact telemetry.
fn frame(k: u32) -> ObservedFrame {
    let intrinsics = Intrinsics::from_fov_x(0.5, u32::from(SIDE), u32::from(SIDE));
    let DiscFrame {
        camera,
        eye_m: eye,
        pixels,
        mask,
        ..
    } = disc_frame(k, SIDE, intrinsics);
    let r = camera.rotation.as_dquat();
    let view = eye.as_dvec3().normalize();
    let sun = DVec3::new(0.6, -0.3, 0.74).normalize();
    ObservedFrame {
        frame_id: k,
        time_us: u64::from(k) * 1_000_000,
        width: SIDE,
        height: SIDE,
        format: PixelFormat::Rgb8,
        pixels,
        mask: Some(mask),
        camera: intrinsics,
        telemetry: SyncedTelemetry {
            time_us: u64::from(k) * 1_000_000,
            camera_from_target: DQuat::from_xyzw(r.x, r.y, r.z, r.w),
            target_in_camera_m: camera.translation.as_dvec3(),
            pose_quality: 1.0,
            sun_in_body: sun,
            sun_in_camera: camera.rotation.as_dquat() * sun,
            sun_in_target: sun,
            view_in_target: view,
            range_m: 8.0,
            eclipse: false,
        },
    }
}

fn hull_starts(learner: &mut SunAwareLearner) -> usize {
    learner
        .take_events()
        .iter()
        .filter(|e| {
            matches!(
                e,
                EventKind::ModelInitialised {
                    source: InitSource::Hull,
                    ..
                }
            )
        })
        .count()
}

fn run(learner: &mut SunAwareLearner, frames: std::ops::Range<u32>) -> u32 {
    let mut rounds = 0;
    for k in frames {
        learner.offer(&frame(k));
        if learner.run_round_if_due().unwrap().is_some() {
            rounds += 1;
        }
    }
    rounds
}

#[test]
fn resumed_learner_trains_the_same_model_bit_for_bit() {
    let mut whole = SunAwareLearner::new(settings()).unwrap();
    let rounds = run(&mut whole, 0..FRAMES);
    assert!(rounds >= 10, "{rounds} rounds: densification must run");
    assert_eq!(hull_starts(&mut whole), 1, "the model starts from the hull");
    let reference = whole.save();
    // Split 2: the window is not full and the hull start is still to come; later splits
    // resume a carved, trained model that must not be carved again.
    for split in [2, 5, 9] {
        let mut first = SunAwareLearner::new(settings()).unwrap();
        run(&mut first, 0..split);
        let saved = first.save();
        let carved_before = hull_starts(&mut first);
        drop(first);
        let mut resumed = SunAwareLearner::new(settings()).unwrap();
        resumed.take_events();
        resumed.load(&saved).unwrap();
        assert!(resumed.save() == saved, "load then save is the identity");
        run(&mut resumed, split..FRAMES);
        assert_eq!(
            carved_before + hull_starts(&mut resumed),
            1,
            "split at {split}"
        );
        let after = resumed.save();
        assert_eq!(after.len(), reference.len(), "split at {split}");
        assert!(
            after == reference,
            "split at {split}: resumed checkpoint differs from the uninterrupted run's"
        );
    }
}

fn rewrap(body: &[u8]) -> Vec<u8> {
    let mut out = body.to_vec();
    let crc = crc32_ieee(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

#[test]
fn a_different_configuration_is_refused_or_used_on_request() {
    let mut learner = SunAwareLearner::new(settings()).unwrap();
    run(&mut learner, 0..5);
    let saved = learner.save();
    let mut other = settings();
    other.online.model.lambda_dssim += 0.1;
    let mut refusing = SunAwareLearner::new(other.clone()).unwrap();
    let error = refusing.load(&saved).unwrap_err();
    assert!(
        format!("{error:?}").contains("on_config_mismatch"),
        "{error:?}"
    );
    assert!(refusing.inspect(&saved).is_err());
    assert_eq!(refusing.stats().rounds, 0, "a refused load changes nothing");
    other.on_config_mismatch = OnConfigMismatch::UseCheckpoint;
    let mut using = SunAwareLearner::new(other).unwrap();
    using.load(&saved).unwrap();
    assert!(
        using.save() == saved,
        "the checkpoint's configuration is used"
    );
    // A different window (W) is a difference too.
    let mut wider = settings();
    wider.online.window.capacity = 4;
    assert!(SunAwareLearner::new(wider).unwrap().load(&saved).is_err());
}

/// A component configuration from TOML text, built the way the binary builds its learner.
fn component_learner(text: &str) -> Box<dyn Learner> {
    let config = ComponentConfig::from_toml_str(text, Path::new("t.toml")).unwrap();
    build_learner(&config, LearnerKind::SunAware).unwrap()
}

/// A checkpoint of the paper's model (the component's default model before the
/// learned-normal shading) under today's default model: refused, naming the settings
/// that differ and no other; with `use_checkpoint` it resumes as the paper's model.
#[test]
fn a_paper_model_checkpoint_is_refused_by_the_default_model_naming_the_settings() {
    const SMALL: &str = "[model]\ninit = \"random\"\ninitial_gaussians = 40\n";
    let paper = component_learner(&format!(
        "[training]\nshading = \"none\"\nappearance_inputs = \"paper\"\nshadow_gain = 1.0\n{SMALL}"
    ));
    let saved = paper.save();
    let mut default = component_learner(SMALL);
    let error = default.load(&saved).unwrap_err().to_string();
    for named in [
        "on_config_mismatch",
        "shading: None, LambertLearned",
        "appearance_inputs: Paper, Local",
        "shadow_gain: 1.0, 2.0",
    ] {
        assert!(error.contains(named), "{named:?} missing: {error}");
    }
    // Only what differs is named (the Phi width and encoding are the same).
    assert!(!error.contains("appearance_hidden_width"), "{error}");
    assert!(default.inspect(&saved).is_err());
    let mut using = component_learner(&format!(
        "[checkpoint]\non_config_mismatch = \"use_checkpoint\"\n{SMALL}"
    ));
    using.load(&saved).unwrap();
    assert!(
        using.save() == saved,
        "the checkpoint's paper model is used as it was"
    );
}

/// Every learned shading normal of the default model starts finite and unit length,
/// facing out of the start (the radial rule of `gs_core::sunaware::shading::initial_normals`
/// for round Gaussians): the random start, and the hull start that replaces it.
#[test]
fn the_hull_start_gives_the_learned_normals_a_finite_outward_start() {
    let mut s = settings();
    s.online.model = ComponentConfig::default().model_config().unwrap();
    let mut learner = SunAwareLearner::new(s).unwrap();
    check_normals(&learner.save(), "random start", 1e-5);
    let mut k = 0;
    while hull_starts(&mut learner) == 0 {
        learner.offer(&frame(k));
        learner.run_round_if_due().unwrap();
        k += 1;
        assert!(k < FRAMES, "no hull start");
    }
    // The hull start is followed at once by its first round, which turns the normals a
    // little (Adam on the unnormalised vector): still finite, near unit, outward.
    check_normals(&learner.save(), "hull start after one round", 0.5);
}

/// Checks the learned normals in a component checkpoint: finite, length within `slack`
/// of 1, and pointing away from the scene box's centre.
fn check_normals(saved: &[u8], what: &str, slack: f32) {
    let trainer_len = u64::from_le_bytes(saved[9..17].try_into().unwrap()) as usize;
    let trainer = gs_core::sunaware::checkpoint::from_bytes(&saved[17..17 + trainer_len]).unwrap();
    let model = &trainer.model;
    let params = &model.gaussians.params;
    assert!(!params.is_empty(), "{what}");
    let centre = (Vec3::from(model.scene_box.min_m()) + Vec3::from(model.scene_box.max_m())) * 0.5;
    let mut outward = 0;
    for g in 0..params.len() {
        let n = Vec3::from_slice(params.row(Param::Normal, g));
        assert!(n.is_finite(), "{what}: Gaussian {g}: {n}");
        assert!(
            (n.length() - 1.0).abs() <= slack,
            "{what}: Gaussian {g}: |{n}|"
        );
        let mean = Vec3::from_slice(params.row(Param::Mean, g));
        if n.dot(mean - centre) > 0.0 {
            outward += 1;
        }
    }
    assert!(
        outward * 10 >= params.len() * 9,
        "{what}: {outward} of {} normals face out",
        params.len()
    );
}

#[test]
fn a_hostile_window_count_is_refused_before_allocating() {
    let mut learner = SunAwareLearner::new(settings()).unwrap();
    run(&mut learner, 0..5);
    let saved = learner.save();
    let body = &saved[..saved.len() - 4];
    assert_eq!(&body[..8], CHECKPOINT_MAGIC);
    let trainer_len = u64::from_le_bytes(body[9..17].try_into().unwrap()) as usize;
    let state_at = 17 + trainer_len + 8;
    // Online state: magic 8, settings 32, rounds 8, last generation 9, generation 8,
    // evictions 8, counters 64, then the window count.
    let count_at = state_at + 8 + 32 + 8 + 9 + 8 + 8 + 64;
    assert_eq!(
        u64::from_le_bytes(body[count_at..count_at + 8].try_into().unwrap()),
        3,
        "the window count sits where the format says"
    );
    for hostile_count in [4, 1 << 40, u64::MAX] {
        let mut hostile = body.to_vec();
        hostile[count_at..count_at + 8].copy_from_slice(&hostile_count.to_le_bytes());
        let error = learner.load(&rewrap(&hostile)).unwrap_err();
        assert!(format!("{error:?}").contains("at most 3"), "{error:?}");
    }
    // A frame claiming 2^32 x 2^32 pixels is refused by its size bound.
    let first_frame = count_at + 8;
    let mut huge = body.to_vec();
    let width_at = first_frame + 8 + 8 + 16;
    huge[width_at..width_at + 8].copy_from_slice(&[0xff; 8]);
    let error = learner.load(&rewrap(&huge)).unwrap_err();
    assert!(format!("{error:?}").contains("pixels"), "{error:?}");
    // Truncated state: refused, and the learner still holds what it had.
    let rounds = learner.stats().rounds;
    let mut truncated = body[..body.len() - 10].to_vec();
    let state_len = (truncated.len() - state_at) as u64;
    truncated[state_at - 8..state_at].copy_from_slice(&state_len.to_le_bytes());
    assert!(learner.load(&rewrap(&truncated)).is_err());
    assert_eq!(learner.stats().rounds, rounds);
    assert!(learner.save() == saved, "a refused load changes nothing");
}

#[test]
fn a_version_1_checkpoint_resumes_the_model_with_an_empty_window() {
    let mut learner = SunAwareLearner::new(settings()).unwrap();
    run(&mut learner, 0..6);
    let saved = learner.save();
    let body = &saved[..saved.len() - 4];
    let trainer_len = u64::from_le_bytes(body[9..17].try_into().unwrap()) as usize;
    let rounds = u64::from(learner.stats().rounds);
    assert!(rounds > 0);
    let mut v1 = b"FSWSAL01".to_vec();
    v1.extend_from_slice(&rounds.to_le_bytes());
    v1.extend_from_slice(&(trainer_len as u64).to_le_bytes());
    v1.extend_from_slice(&body[17..17 + trainer_len]);
    let v1 = rewrap(&v1);
    let mut resumed = SunAwareLearner::new(settings()).unwrap();
    assert_eq!(resumed.inspect(&v1), Ok(rounds));
    resumed.load(&v1).unwrap();
    let stats = resumed.stats();
    assert_eq!(u64::from(stats.rounds), rounds);
    assert_eq!(stats.window_fill, 0, "version 1 holds no window");
    assert_eq!(stats.gaussians, learner.stats().gaussians);
}
