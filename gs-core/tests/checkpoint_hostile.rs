//! Crafted Sun-aware checkpoints: a valid checksum over hostile sizes and optimiser values.
//!
//! Each case edits one field of a real checkpoint and recomputes the checksum, so only the
//! loader's own checks stand between the bytes and the model. Every case must be a
//! `Checkpoint` error naming the field, without a panic and without any single allocation
//! larger than a small multiple of the file (this binary's allocator records the largest
//! request made on the loading thread). The writer must refuse what the reader refuses.

use glam::Vec3;
use gs_core::init::from_points;
use gs_core::model::Param;
use gs_core::nn::SceneBox;
use gs_core::sunaware::checkpoint::{self, fnv1a64};
use gs_core::sunaware::{SunAwareConfig, SunAwareModel, SunAwareTrainer, Variant};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

/// The system allocator, recording the largest request while `MEASURING` is set.
struct Largest;

thread_local! {
    static MEASURING: Cell<bool> = const { Cell::new(false) };
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Largest {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

fn note(size: usize) {
    // `try_with`: the thread-locals may be gone while a thread exits.
    let _ = MEASURING.try_with(|m| {
        if m.get() {
            let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
        }
    });
}

#[global_allocator]
static ALLOCATOR: Largest = Largest;

/// Loads `bytes`; returns the result and the largest single allocation made meanwhile.
fn load_measured(bytes: &[u8]) -> (Result<SunAwareTrainer, String>, usize) {
    LARGEST.with(|l| l.set(0));
    MEASURING.with(|m| m.set(true));
    let result = checkpoint::from_bytes(bytes).map_err(|e| e.to_string());
    MEASURING.with(|m| m.set(false));
    (result, LARGEST.with(Cell::get))
}

/// A small configuration-d trainer (both networks present).
fn trainer() -> SunAwareTrainer {
    let points: Vec<Vec3> = (0..40)
        .map(|i| {
            let a = i as f32 * 0.7;
            Vec3::new(a.cos(), a.sin(), (i as f32 / 40.0) - 0.5)
        })
        .collect();
    let config = SunAwareConfig {
        appearance_hidden_width: 16,
        ..SunAwareConfig::for_variant(Variant::D)
    };
    let init = from_points(&points, None, config.layout()).unwrap();
    let scene_box = SceneBox::new([-2.0; 3], [2.0; 3]).unwrap();
    SunAwareTrainer::new(SunAwareModel::new(init.model, scene_box, config).unwrap())
}

/// File offsets (the layout in `checkpoint.rs`: 20 header bytes, then the config).
const PAYLOAD: usize = 20;
const FEATURE_DIM: usize = PAYLOAD + 13;
const SHADOW_LATENT_DIM: usize = PAYLOAD + 21;
/// From the end of the config section (200 bytes in version 8): max_gaussians is followed
/// by densify_from_step, background, near, seed, feature_init_std, refinement, hidden
/// width, shadow gain, shading, shading ambient, the normal's learning rate, Phi's
/// appearance inputs and the colour space.
const CONFIG_BYTES: usize = 200;
const MAX_GAUSSIANS: usize =
    PAYLOAD + CONFIG_BYTES - (8 + 8 + 12 + 4 + 8 + 4 + 1 + 8 + 4 + 1 + 4 + 4 + 1 + 1);
const HIDDEN_WIDTH: usize = PAYLOAD + CONFIG_BYTES - (8 + 4 + 1 + 4 + 4 + 1 + 1);
const GAUSSIAN_COUNT: usize = PAYLOAD + CONFIG_BYTES + 24;

/// A hostile case: its name, the (offset, bytes) edits, a word the error must contain.
type Case<'a> = (&'a str, &'a [(usize, &'a [u8])], &'a str);

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap())
}

/// `bytes` with `value` written at `at` and the checksum recomputed.
fn edited(bytes: &[u8], at: usize, value: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    out[at..at + value.len()].copy_from_slice(value);
    let end = out.len() - 8;
    let sum = fnv1a64(&out[PAYLOAD..end]);
    out[end..].copy_from_slice(&sum.to_le_bytes());
    out
}

/// Offset of the Gaussian Adam header: beta1 0.9, beta2 0.999, eps in a row.
fn adam_header(bytes: &[u8], eps: f32) -> usize {
    let pattern: Vec<u8> = [0.9f32, 0.999, eps]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let at = bytes
        .windows(pattern.len())
        .position(|w| w == pattern.as_slice())
        .expect("Adam header");
    assert!(
        bytes[at + 1..]
            .windows(pattern.len())
            .all(|w| w != pattern.as_slice()),
        "Adam header pattern is not unique"
    );
    at
}

fn assert_refused(bytes: &[u8], what: &str, expect_in_error: &str) {
    let (result, largest) = load_measured(bytes);
    let error = match result {
        Ok(_) => panic!("{what}: loaded"),
        Err(e) => e,
    };
    assert!(
        error.contains(expect_in_error),
        "{what}: {error:?} does not mention {expect_in_error:?}"
    );
    assert!(
        largest <= 4 * bytes.len() + (1 << 16),
        "{what}: an allocation of {largest} bytes for a {}-byte file",
        bytes.len()
    );
}

#[test]
fn hostile_sizes_are_refused_before_allocating() {
    let t = trainer();
    let good = checkpoint::to_bytes(&t);
    // The offsets point where the layout says.
    assert_eq!(
        u64_at(&good, FEATURE_DIM),
        t.model.config.feature_dim as u64
    );
    assert_eq!(
        u64_at(&good, SHADOW_LATENT_DIM),
        t.model.config.shadow_latent_dim as u64
    );
    assert_eq!(
        u64_at(&good, MAX_GAUSSIANS),
        t.model.config.max_gaussians as u64
    );
    assert_eq!(u64_at(&good, HIDDEN_WIDTH), 16);
    assert_eq!(u64_at(&good, GAUSSIAN_COUNT), t.model.len() as u64);
    let (loaded, largest) = load_measured(&good);
    assert_eq!(loaded.unwrap(), t);
    assert!(largest <= 4 * good.len(), "the valid file: {largest} bytes");

    let huge = (1u64 << 40).to_le_bytes();
    let none = 0u64.to_le_bytes();
    let max = u64::MAX.to_le_bytes();
    let wide = 4096u64.to_le_bytes();
    let third = (u64::MAX / 3).to_le_bytes();
    // Zero Gaussians keep the row-size check from catching a huge width first.
    let cases: [Case; 7] = [
        ("feature_dim", &[(FEATURE_DIM, &huge)], "feature_dim"),
        (
            "feature_dim, no Gaussians",
            &[(FEATURE_DIM, &huge), (GAUSSIAN_COUNT, &none)],
            "feature_dim",
        ),
        (
            "shadow latent, no Gaussians",
            &[(SHADOW_LATENT_DIM, &huge), (GAUSSIAN_COUNT, &none)],
            "shadow_latent_dim",
        ),
        ("max_gaussians", &[(MAX_GAUSSIANS, &max)], "max_gaussians"),
        // A width the configuration allows, whose networks the file cannot hold.
        ("hidden width", &[(HIDDEN_WIDTH, &wide)], "exceed the file"),
        (
            "Gaussian count",
            &[(GAUSSIAN_COUNT, &huge)],
            "Gaussian count",
        ),
        (
            "Gaussian count near usize::MAX",
            &[(GAUSSIAN_COUNT, &third)],
            "Gaussian count",
        ),
    ];
    for (what, edits, expect) in cases {
        let bytes = edits
            .iter()
            .fold(good.clone(), |b, (at, value)| edited(&b, *at, value));
        assert_refused(&bytes, what, expect);
    }
}

#[test]
fn adam_hyperparameters_step_and_moments_are_validated() {
    let t = trainer();
    let good = checkpoint::to_bytes(&t);
    let header = adam_header(&good, t.adam.eps);
    let step = header + 12;
    let floats: usize = t.model.gaussians.params.dims().iter().sum::<usize>() * t.model.len();
    let first_v = step + 8 + 4 * floats;
    let cases: [(&str, usize, Vec<u8>, &str); 7] = [
        ("beta1 = 1", header, 1.0f32.to_le_bytes().to_vec(), "beta1"),
        (
            "beta1 < 0",
            header,
            (-0.1f32).to_le_bytes().to_vec(),
            "beta1",
        ),
        (
            "beta2 > 1",
            header + 4,
            1.5f32.to_le_bytes().to_vec(),
            "beta2",
        ),
        ("eps = 0", header + 8, 0.0f32.to_le_bytes().to_vec(), "eps"),
        (
            "eps huge",
            header + 8,
            1e30f32.to_le_bytes().to_vec(),
            "eps",
        ),
        ("step", step, u64::MAX.to_le_bytes().to_vec(), "step"),
        (
            "negative second moment",
            first_v,
            (-1.0f32).to_le_bytes().to_vec(),
            "second moment",
        ),
    ];
    // The second moments start where the layout says: all zeros in a fresh trainer.
    assert_eq!(&good[first_v..first_v + 4], &0.0f32.to_le_bytes());
    for (what, at, value, expect) in cases {
        assert_refused(&edited(&good, at, &value), what, expect);
    }
}

#[test]
fn the_writer_refuses_what_the_reader_refuses() {
    let dir = std::env::temp_dir().join(format!("gs-ckpt-refuse-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (what, poison) in [("NaN moment", f32::NAN), ("negative moment", -1.0)] {
        let mut t = trainer();
        t.adam.v.get_mut(Param::OpacityLogit)[0] = poison;
        let path = dir.join("model.bin");
        let error = checkpoint::save_file(&t, &path).unwrap_err().to_string();
        assert!(error.contains("second moment"), "{what}: {error}");
        assert!(!path.exists(), "{what}: a file was written");
        let mut sink = Vec::new();
        assert!(checkpoint::save(&t, &mut sink).is_err(), "{what}");
        assert!(sink.is_empty(), "{what}: bytes were written");
        assert!(checkpoint::checked_to_bytes(&t).is_err(), "{what}");
    }
    let t = trainer();
    assert_eq!(
        checkpoint::checked_to_bytes(&t).unwrap(),
        checkpoint::to_bytes(&t)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
