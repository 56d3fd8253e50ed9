//! The online trainer on a short synthetic sequence: a known Gaussian scene (a plate with a
//! ball casting a shadow) rendered from a circling camera under a moving Sun. Checks that it
//! trains without NaN and improves held-out PSNR, that rounds run only when the window
//! changed, that eclipse and unlit frames are skipped and counted (and are not when the
//! skips are switched off), and that bad frames are errors.

use glam::Vec3;
use gs_core::sunaware::synthetic::{orbit_camera, SyntheticScene};
use gs_core::sunaware::{LightConfig, SunAwareConfig, Variant};
use gs_online::keyframe::WindowConfig;
use gs_online::online::{Initialisation, OfferReport, OnlineConfig, OnlineTrainer, SkipReason};

mod online_support;
use online_support::{frame, held_out_psnr, H, PER_ORBIT, W};

fn config(capacity: usize) -> OnlineConfig {
    OnlineConfig {
        window: WindowConfig {
            capacity,
            ..WindowConfig::default()
        },
        model: SunAwareConfig {
            light: LightConfig {
                resolution_px: 96,
                ..LightConfig::default()
            },
            ..SunAwareConfig::for_variant(Variant::D)
        },
        densify_every_rounds: 5,
        ..OnlineConfig::default()
    }
}

fn surface_init(scene: &SyntheticScene) -> Initialisation {
    let (points, normals, colours) = scene.surface_samples(0.02, 11);
    Initialisation::SurfaceSamples {
        points,
        normals: Some(normals),
        colours: Some(colours),
    }
}

#[test]
fn short_sequence_trains_without_nan_and_improves_held_out_psnr() {
    let scene = SyntheticScene::plate_and_ball(12, 60).unwrap();
    let mut t = OnlineTrainer::new(config(6), &surface_init(&scene), scene.scene_box).unwrap();
    let before = held_out_psnr(&t, &scene);
    let mut reports = Vec::new();
    for id in 0..30 {
        t.offer(frame(&scene, id, false)).unwrap();
        if let Some(r) = t.run_round_if_due().unwrap() {
            assert!(
                r.mean_loss.is_finite(),
                "round {}: loss {}",
                r.rounds,
                r.mean_loss
            );
            assert_eq!(r.trained_ids.len(), 6, "one round = W steps");
            let mut ids = r.trained_ids.clone();
            ids.sort_unstable();
            ids.dedup();
            assert_eq!(ids.len(), 6, "each keyframe once per round");
            reports.push(r);
        }
    }
    // The window fills after 6 frames; every later frame changes it: 25 rounds.
    assert_eq!(reports.len(), 25);
    assert_eq!(t.rounds(), 25);
    assert!(reports.iter().filter(|r| r.densified.is_some()).count() == 5);
    assert_eq!(t.trainer().skipped_nonfinite, 0);
    let after = held_out_psnr(&t, &scene);
    eprintln!(
        "held-out PSNR {before:.2} -> {after:.2} dB, loss {:.4} -> {:.4}, {} Gaussians",
        reports[0].mean_loss,
        reports.last().unwrap().mean_loss,
        t.trainer().model.len()
    );
    assert!(
        after > before + 3.0,
        "held-out PSNR {before:.2} -> {after:.2} dB"
    );
    let p = t
        .predict(&orbit_camera(3, 24, 2.4, 0.6, W, H), Vec3::Z)
        .unwrap();
    assert!(p.image.iter().all(|v| v.is_finite()));
}

#[test]
fn passes_per_round_train_each_keyframe_that_often_and_keep_the_first_pass() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let run = |passes: u32| {
        let mut t = OnlineTrainer::new(
            OnlineConfig {
                passes_per_round: passes,
                ..config(3)
            },
            &surface_init(&scene),
            scene.scene_box,
        )
        .unwrap();
        let mut report = None;
        for id in 0..3 {
            t.offer(frame(&scene, id, false)).unwrap();
            report = report.or(t.run_round_if_due().unwrap());
        }
        report.expect("the window filled at the third frame")
    };
    let one = run(1);
    let three = run(3);
    assert_eq!(three.rounds, 1, "three passes are still one round");
    assert_eq!(three.trained_ids.len(), 9);
    for id in &one.trained_ids {
        let count = three.trained_ids.iter().filter(|&x| x == id).count();
        assert_eq!(
            count, 3,
            "keyframe {id} trained {count} times in three passes"
        );
    }
    assert_eq!(
        three.trained_ids[..3],
        one.trained_ids[..],
        "the first pass keeps the one-pass order"
    );
    assert_ne!(
        three.trained_ids[3..6],
        three.trained_ids[..3],
        "each pass reshuffles"
    );
}

#[test]
fn rounds_run_only_when_the_window_changed() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let mut t = OnlineTrainer::new(config(3), &surface_init(&scene), scene.scene_box).unwrap();
    for id in 0..2 {
        assert!(matches!(
            t.offer(frame(&scene, id, false)).unwrap(),
            OfferReport::Added { evicted: None }
        ));
        assert!(
            t.run_round_if_due().unwrap().is_none(),
            "window not full yet"
        );
    }
    t.offer(frame(&scene, 2, false)).unwrap();
    assert!(t.run_round_if_due().unwrap().is_some());
    assert!(t.run_round_if_due().unwrap().is_none(), "unchanged window");
    // Same view as the newest keyframe (id 2 and 2 + PER_ORBIT share a camera): not added.
    let close = frame(&scene, 2 + PER_ORBIT as u64, false);
    assert!(matches!(
        t.offer(close).unwrap(),
        OfferReport::Skipped(SkipReason::ViewTooClose { .. })
    ));
    assert!(t.run_round_if_due().unwrap().is_none());
    assert_eq!(t.counters().skipped_view, 1);
    // A new view evicts one keyframe and makes a round due again.
    let report = t.offer(frame(&scene, 3, false)).unwrap();
    assert!(
        matches!(report, OfferReport::Added { evicted: Some(_) }),
        "{report:?}"
    );
    assert!(t.run_round_if_due().unwrap().is_some());
    assert_eq!(t.rounds(), 2);

    // With the change requirement switched off, a full window trains every call.
    let mut always = OnlineTrainer::new(
        OnlineConfig {
            require_window_change: false,
            ..config(3)
        },
        &surface_init(&scene),
        scene.scene_box,
    )
    .unwrap();
    for id in 0..3 {
        always.offer(frame(&scene, id, false)).unwrap();
    }
    assert!(always.run_round_if_due().unwrap().is_some());
    assert!(always.run_round_if_due().unwrap().is_some());
}

#[test]
fn eclipse_and_unlit_frames_are_skipped_and_counted() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let mut t = OnlineTrainer::new(config(3), &surface_init(&scene), scene.scene_box).unwrap();
    assert_eq!(
        t.offer(frame(&scene, 0, true)).unwrap(),
        OfferReport::Skipped(SkipReason::Eclipse)
    );
    // Not flagged as eclipse but black: unlit.
    let mut dark = frame(&scene, 1, false);
    dark.image.fill(0.001);
    assert!(matches!(
        t.offer(dark).unwrap(),
        OfferReport::Skipped(SkipReason::Unlit { .. })
    ));
    t.offer(frame(&scene, 2, false)).unwrap();
    let c = t.counters();
    assert_eq!(
        (c.offered, c.added, c.skipped_eclipse, c.skipped_unlit),
        (3, 1, 1, 1)
    );
    assert_eq!(t.window().ids(), vec![2]);

    // Skips switched off: the same frames enter the window.
    let mut keep = OnlineTrainer::new(
        OnlineConfig {
            skip_eclipse: false,
            skip_unlit: false,
            ..config(3)
        },
        &surface_init(&scene),
        scene.scene_box,
    )
    .unwrap();
    assert!(matches!(
        keep.offer(frame(&scene, 0, true)).unwrap(),
        OfferReport::Added { .. }
    ));
    assert_eq!(keep.counters().skipped_eclipse, 0);
}

#[test]
fn frames_with_an_empty_mask_are_skipped_and_counted_not_errors() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    // The unlit skip off, so the empty-mask rule is the one that acts.
    let mut t = OnlineTrainer::new(
        OnlineConfig {
            skip_unlit: false,
            ..config(2)
        },
        &surface_init(&scene),
        scene.scene_box,
    )
    .unwrap();
    let empty = |id| {
        let mut f = frame(&scene, id, false);
        f.mask.as_mut().unwrap().fill(0.0);
        f
    };
    assert_eq!(
        t.offer(empty(0)).unwrap(),
        OfferReport::Skipped(SkipReason::EmptyMask)
    );
    // An empty mask of the wrong size, or a mask with a NaN, is still a bad frame.
    let mut short = empty(1);
    short.mask.as_mut().unwrap().pop();
    let msg = t.offer(short).unwrap_err().to_string();
    assert!(msg.contains("mask has"), "{msg}");
    let mut nan = empty(1);
    nan.mask.as_mut().unwrap()[5] = f32::NAN;
    assert!(t.offer(nan).is_err());
    // Training goes on with the frames that have a target in them.
    for id in 1..3 {
        t.offer(frame(&scene, id, false)).unwrap();
    }
    assert!(t.run_round_if_due().unwrap().is_some());
    let c = t.counters();
    assert_eq!(
        (c.offered, c.added, c.skipped_empty_mask, c.skipped_unlit),
        (3, 2, 1, 0)
    );
    let mut ids = t.window().ids();
    ids.sort_unstable();
    assert_eq!(ids, vec![1, 2]);
}

#[test]
fn bad_frames_are_errors_and_random_init_works() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let init = Initialisation::RandomSphere {
        count: 300,
        centre: Vec3::ZERO,
        radius_m: 0.8,
        seed: 4,
    };
    let mut t = OnlineTrainer::new(config(3), &init, scene.scene_box).unwrap();
    assert_eq!(t.trainer().model.len(), 300);
    let mut f = frame(&scene, 0, false);
    f.image.pop();
    let msg = t.offer(f).unwrap_err().to_string();
    assert!(msg.contains("image has"), "{msg}");
    let mut f = frame(&scene, 1, false);
    f.sun_dir_target = Vec3::new(f32::NAN, 0.0, 1.0);
    assert!(t.offer(f).is_err());
    assert_eq!(
        t.counters().offered,
        0,
        "rejected frames are not counted as offered"
    );
    for id in 0..3 {
        t.offer(frame(&scene, id, false)).unwrap();
    }
    let r = t.run_round_if_due().unwrap().unwrap();
    assert!(r.mean_loss.is_finite());
    // Mismatched normals are a configuration error.
    let (points, normals, _) = scene.surface_samples(0.0, 1);
    let bad = Initialisation::SurfaceSamples {
        points,
        normals: Some(normals[..3].to_vec()),
        colours: None,
    };
    assert!(OnlineTrainer::new(config(3), &bad, scene.scene_box).is_err());
}

#[test]
fn replay_memory_keeps_a_bounded_sample_of_evicted_keyframes_and_trains_on_it() {
    let scene = SyntheticScene::plate_and_ball(6, 20).unwrap();
    let replay = |capacity: usize, steps: usize| OnlineConfig {
        replay_capacity: capacity,
        replay_steps_per_round: steps,
        ..config(4)
    };
    let mut t = OnlineTrainer::new(replay(3, 2), &surface_init(&scene), scene.scene_box).unwrap();
    let mut evicted = Vec::new();
    let mut last = None;
    for id in 0..12 {
        if let OfferReport::Added {
            evicted: Some(gone),
        } = t.offer(frame(&scene, id, false)).unwrap()
        {
            evicted.push(gone);
        }
        if let Some(r) = t.run_round_if_due().unwrap() {
            last = Some(r);
        }
    }
    assert!(evicted.len() > 3, "the window evicted {evicted:?}");
    assert_eq!(t.replay_len(), 3, "bounded by the capacity");
    let r = last.expect("rounds ran");
    // W window steps, then the replay steps, on frames the window no longer holds.
    assert_eq!(r.trained_ids.len(), 4 + 2);
    let window: Vec<u64> = t.window().keyframes().iter().map(|k| k.id).collect();
    for id in &r.trained_ids[4..] {
        assert!(
            evicted.contains(id) && !window.contains(id),
            "replayed {id}"
        );
    }
    // Without a memory the round is the paper's: W steps.
    let mut plain =
        OnlineTrainer::new(replay(0, 2), &surface_init(&scene), scene.scene_box).unwrap();
    let mut steps = 0;
    for id in 0..12 {
        plain.offer(frame(&scene, id, false)).unwrap();
        if let Some(r) = plain.run_round_if_due().unwrap() {
            steps = r.trained_ids.len();
        }
    }
    assert_eq!((plain.replay_len(), steps), (0, 4));
}

/// With `shading = "lambert_learned"`, the surface normals of the initialisation become
/// the Gaussians' learned shading normals (unit length); other models carry none.
#[test]
fn surface_normals_start_the_learned_shading_normals() {
    use gs_core::sunaware::Shading;
    use gs_core::Param;
    let scene = SyntheticScene::plate_and_ball(8, 30).unwrap();
    let init = surface_init(&scene);
    let Initialisation::SurfaceSamples {
        normals: Some(normals),
        ..
    } = &init
    else {
        unreachable!("surface_init gives normals")
    };
    let mut learned = config(4);
    learned.model.shading = Shading::LambertLearned;
    let t = OnlineTrainer::new(learned, &init, scene.scene_box).unwrap();
    let params = &t.trainer().model.gaussians.params;
    assert_eq!(params.len(), normals.len());
    for (g, n) in normals.iter().enumerate() {
        let v = Vec3::from_slice(params.row(Param::Normal, g));
        assert!(
            (v - n.normalize()).length() < 1e-6,
            "Gaussian {g}: {v} vs {n}"
        );
    }
    let plain = OnlineTrainer::new(config(4), &init, scene.scene_box).unwrap();
    assert!(plain
        .trainer()
        .model
        .gaussians
        .params
        .get(Param::Normal)
        .is_empty());
}
