//! Replays the committed fuzz corpus of the Sun-aware checkpoint loader
//! (`fuzz/corpus/sunaware_checkpoint/`) through the fuzz harness (`fuzz/harness.rs`) on
//! every test run, and runs the harness on random inputs and on random single-byte damage
//! of a real checkpoint. The seeds are checkpoints written by `checkpoint::to_bytes` for
//! small models of every variant (untrained and after a few steps), so mutations start
//! from valid files. `cargo test -p gs-core --test fuzz_corpus -- --ignored` rewrites them.

#[path = "../fuzz/harness.rs"]
mod harness;

use gs_core::init::from_points;
use gs_core::sunaware::checkpoint;
use gs_core::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};
use gs_core::sunaware::{
    LightConfig, Observation, SunAwareConfig, SunAwareModel, SunAwareTrainer, Variant,
};
use proptest::prelude::*;
use std::path::PathBuf;

fn corpus_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/sunaware_checkpoint")
}

#[test]
fn committed_corpus_replays_without_findings() {
    let mut files = 0;
    for entry in std::fs::read_dir(corpus_dir()).expect("corpus directory exists") {
        harness::run(&std::fs::read(entry.unwrap().path()).unwrap());
        files += 1;
    }
    assert!(files >= 8, "corpus has only {files} files");
}

/// Inputs that fuzzing found before issue 16, finding 4 (bound every size field before
/// allocating) was fixed; each must now be refused cleanly: `oversized-appearance-mlp` passes the checksum with a
/// `feature_dim` that makes `SunAwareModel::new` ask `Mlp::new` for ~256 GiB before any
/// weight is read (found by the `sunaware_checkpoint` target under `-malloc_limit_mb=512`),
/// `oversized-shadow-mlp` the same through `shadow_latent_dim` and `ShadowNet::new`;
/// `gaussian-row-width-wraps` panics with "capacity overflow" in `ParamSet::push_zeros`
/// (`from_bytes`, "push_zeros(n)"), presumably because the row width `dims().sum() * 4` is
/// unchecked: with a huge dimension the "count fits the file" check sees a wrapped product.
/// They live outside the corpus so that the fuzzer and the replay above can start.
#[test]
fn known_findings_are_refused_cleanly() {
    let dir =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz/regressions/sunaware_checkpoint");
    let mut files = 0;
    for entry in std::fs::read_dir(dir).expect("regressions directory exists") {
        harness::run(&std::fs::read(entry.unwrap().path()).unwrap());
        files += 1;
    }
    assert!(files >= 1);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn harness_survives_random_inputs(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        harness::run(&bytes);
    }

    #[test]
    fn harness_survives_damaged_checkpoints(at in any::<usize>(), value in any::<u8>()) {
        let mut seed = vec![1u8];
        seed.extend(checkpoint::to_bytes(&small_trainer(Variant::D, 0)));
        let at = 1 + at % (seed.len() - 1);
        seed[at] = value;
        harness::run(&seed);
    }
}

/// A model of a few Gaussians with small networks, trained `steps` steps on 16 x 12 views.
fn small_trainer(variant: Variant, steps: usize) -> SunAwareTrainer {
    let scene = SyntheticScene::plate_and_ball(2, 4).unwrap();
    let config = SunAwareConfig {
        sh_degree: 1,
        feature_dim: 4,
        shadow_latent_dim: 2,
        encoding_frequencies: 1,
        appearance_hidden_width: 4,
        light: LightConfig {
            resolution_px: 16,
            ..Default::default()
        },
        ..SunAwareConfig::for_variant(variant)
    };
    let (points, _normals, colours) = scene.surface_samples(0.02, 3);
    let init = from_points(&points, Some(&colours), config.layout()).unwrap();
    let model = SunAwareModel::new(init.model, scene.scene_box, config).unwrap();
    let mut t = SunAwareTrainer::new(model);
    for s in 0..steps {
        let camera = orbit_camera(s * 10, 40, 2.4, 0.6, 16, 12);
        let sun = sun_direction(0.5 * s as f32, 0.8);
        let (image, mask) = scene.render(&camera, sun).unwrap();
        let obs = Observation {
            camera,
            sun_dir: sun,
            image: &image,
            mask: Some(&mask),
        };
        t.step(&obs, 0.5).unwrap();
    }
    t
}

#[test]
#[ignore = "rewrites the committed seed corpus"]
fn regenerate_seed_corpus() {
    let dir = corpus_dir();
    std::fs::create_dir_all(&dir).unwrap();
    let mut i = 0;
    for variant in Variant::ALL {
        for steps in [0, 3] {
            let bytes = checkpoint::to_bytes(&small_trainer(variant, steps));
            // Even: the file as written; odd: length and checksum recomputed by the harness.
            for selector in [0u8, 1] {
                let mut seed = vec![selector];
                seed.extend(&bytes);
                harness::run(&seed);
                std::fs::write(dir.join(format!("seed-{i:03}")), &seed).unwrap();
                i += 1;
            }
        }
    }
}
