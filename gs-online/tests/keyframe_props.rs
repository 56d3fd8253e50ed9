//! Property tests of the keyframe window against an independent brute-force oracle:
//! bounded size, the two newest kept, the paper's add and evict rules, a correct
//! changed flag, and determinism. View sequences mix random directions with a small
//! palette of repeated directions so that exact score ties occur often.

use glam::DVec3;
use gs_online::keyframe::{
    Keyframe, KeyframeError, KeyframeWindow, NotAddedReason, OfferOutcome, ViewDirection,
    WindowConfig,
};
use proptest::prelude::*;

fn direction(azimuth_rad: f64, elevation_rad: f64) -> DVec3 {
    DVec3::new(
        elevation_rad.cos() * azimuth_rad.cos(),
        elevation_rad.cos() * azimuth_rad.sin(),
        elevation_rad.sin(),
    )
}

/// Either a random direction or one of eight fixed ones (repeats create ties).
fn view_strategy() -> impl Strategy<Value = DVec3> {
    prop_oneof![
        (0.0..std::f64::consts::TAU, -1.5..1.5f64).prop_map(|(a, e)| direction(a, e)),
        (0usize..8).prop_map(|k| direction(k as f64 * 0.7, (k % 3) as f64 * 0.4 - 0.4)),
        // Unnormalised input of varied length.
        (0.0..std::f64::consts::TAU, -1.5..1.5f64, 0.01..100.0f64)
            .prop_map(|(a, e, r)| direction(a, e) * r),
    ]
}

fn config_strategy() -> impl Strategy<Value = WindowConfig> {
    (2usize..8, prop_oneof![Just(10.0), 0.0..60.0f64]).prop_map(|(capacity, deg)| WindowConfig {
        capacity,
        min_view_angle_deg: deg,
    })
}

/// The paper's score d_i over non-protected keyframes, computed from scratch.
fn oracle_scores(views_newest_first: &[DVec3]) -> Vec<(usize, f64)> {
    let n = views_newest_first.len();
    (2..n)
        .map(|i| {
            let score = (2..n)
                .filter(|&j| j != i)
                .map(|j| views_newest_first[i].dot(views_newest_first[j]))
                .fold(f64::NEG_INFINITY, f64::max);
            (i, score)
        })
        .collect()
}

#[derive(Debug, PartialEq)]
struct Trace {
    ids_after_each_offer: Vec<Vec<u64>>,
    evicted: Vec<Option<u64>>,
}

fn run(config: WindowConfig, views: &[DVec3]) -> Trace {
    let mut window = KeyframeWindow::new(config).unwrap();
    let mut trace = Trace {
        ids_after_each_offer: Vec::new(),
        evicted: Vec::new(),
    };
    for (id, v) in views.iter().enumerate() {
        let frame = Keyframe {
            id: id as u64,
            view: ViewDirection::new(*v).unwrap(),
            payload: id,
        };
        let out = window.offer(frame);
        trace.evicted.push(out.evicted_id());
        trace.ids_after_each_offer.push(window.ids());
    }
    trace
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]

    #[test]
    fn window_follows_the_paper_rules(
        config in config_strategy(),
        raw_views in prop::collection::vec(view_strategy(), 1..60),
    ) {
        let cos_threshold = config.min_view_angle_deg.to_radians().cos();
        let mut window = KeyframeWindow::new(config).unwrap();
        let mut added_ids: Vec<u64> = Vec::new();
        for (index, raw) in raw_views.iter().enumerate() {
            let id = 1000 + index as u64;
            let view = ViewDirection::new(*raw).unwrap();
            prop_assert!((view.get().length() - 1.0).abs() < 1e-12);
            let before: Vec<(u64, DVec3)> =
                window.keyframes().iter().map(|k| (k.id, k.view.get())).collect();
            let generation_before = window.generation();

            let expect_add = before.first().is_none_or(|(_, w1)| view.get().dot(*w1) < cos_threshold);
            let out = window.offer(Keyframe { id, view, payload: id * 3 });
            let after = window.ids();

            prop_assert_eq!(out.composition_changed(), expect_add);
            let before_ids: Vec<u64> = before.iter().map(|(k, _)| *k).collect();
            prop_assert_eq!(out.composition_changed(), after != before_ids);
            prop_assert_eq!(
                window.generation(),
                generation_before + u64::from(out.composition_changed())
            );
            prop_assert!(window.len() <= config.capacity);

            match out {
                OfferOutcome::NotAdded { frame, reason } => {
                    prop_assert_eq!(frame.id, id);
                    prop_assert_eq!(frame.payload, id * 3);
                    let is_too_close = matches!(reason, NotAddedReason::ViewTooClose { .. });
                    prop_assert!(is_too_close);
                }
                OfferOutcome::Added { evicted } => {
                    added_ids.push(id);
                    // The two most recently added frames are the two newest keyframes.
                    let k = added_ids.len();
                    let expected_head: Vec<u64> =
                        added_ids[k.saturating_sub(2)..].iter().rev().copied().collect();
                    prop_assert_eq!(&after[..expected_head.len()], &expected_head[..]);

                    let mut candidate: Vec<(u64, DVec3)> = vec![(id, view.get())];
                    candidate.extend(before.iter().copied());
                    match evicted {
                        None => prop_assert!(candidate.len() <= config.capacity),
                        Some(gone) => {
                            prop_assert_eq!(candidate.len(), config.capacity + 1);
                            prop_assert_eq!(gone.payload, gone.id * 3);
                            let views: Vec<DVec3> = candidate.iter().map(|(_, v)| *v).collect();
                            let scores = oracle_scores(&views);
                            let gone_index = candidate.iter().position(|(k, _)| *k == gone.id).unwrap();
                            prop_assert!(gone_index >= 2, "a protected keyframe was evicted");
                            let gone_score = scores.iter().find(|(i, _)| *i == gone_index).unwrap().1;
                            for (i, s) in &scores {
                                // Nobody is more redundant; equally redundant ones are newer.
                                prop_assert!(*s <= gone_score);
                                if *s == gone_score {
                                    prop_assert!(*i <= gone_index);
                                }
                            }
                            let expected: Vec<u64> = candidate
                                .iter()
                                .map(|(k, _)| *k)
                                .filter(|k| *k != gone.id)
                                .collect();
                            prop_assert_eq!(&after, &expected);
                        }
                    }
                }
            }
            for k in window.keyframes() {
                prop_assert_eq!(k.payload, k.id * 3);
            }
        }
    }

    #[test]
    fn same_inputs_give_the_same_window(
        config in config_strategy(),
        views in prop::collection::vec(view_strategy(), 1..60),
    ) {
        prop_assert_eq!(run(config, &views), run(config, &views));
    }

    #[test]
    fn view_direction_accepts_exactly_finite_nonzero_vectors(
        x in prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(0.0), -1e3..1e3f64],
        y in prop_oneof![Just(f64::NEG_INFINITY), Just(0.0), -1e3..1e3f64],
        z in prop_oneof![Just(0.0), Just(1e-300), -1e3..1e3f64],
    ) {
        let v = DVec3::new(x, y, z);
        match ViewDirection::new(v) {
            Ok(d) => {
                prop_assert!(v.is_finite() && v.length() >= 1e-9);
                prop_assert!((d.get().length() - 1.0).abs() < 1e-12);
                prop_assert!(d.get().dot(v) > 0.0);
            }
            Err(KeyframeError::NonFiniteViewVector { .. }) => prop_assert!(!v.is_finite()),
            Err(KeyframeError::ZeroViewVector { .. }) => {
                prop_assert!(v.is_finite() && v.length() < 1e-9);
            }
            Err(other) => prop_assert!(false, "unexpected error {other:?}"),
        }
    }
}
