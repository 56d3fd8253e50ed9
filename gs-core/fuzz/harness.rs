//! Fuzz harness of the Sun-aware checkpoint loader (`sunaware::checkpoint::from_bytes`),
//! shared by the `cargo fuzz` target (`fuzz_targets/sunaware_checkpoint.rs`) and the
//! committed-corpus replay test (`../tests/fuzz_corpus.rs`).
//!
//! Input: `selector(1) file...`. An odd selector rewrites the header's payload length and
//! the trailing FNV-1a checksum to match the bytes, so that mutations get past the
//! checksum into the fields (sizes, dimensions, Adam state, networks) behind it.
//!
//! Asserted: no panic; a refused file gives a printable error; a loaded trainer holds only
//! finite numbers (Gaussians, Adam moments, network weights and their Adam state,
//! densification statistics) and saves to bytes that load back to an equal trainer.
//! Allocation must stay proportional to the file: libFuzzer's `-malloc_limit_mb` flags a
//! size field that is trusted before it is checked.

use gs_core::model::Param;
use gs_core::sunaware::checkpoint::{fnv1a64, from_bytes, to_bytes};
use gs_core::sunaware::SunAwareTrainer;

/// Magic, version and payload length before the payload; the checksum after it.
const HEADER_BYTES: usize = 20;
const TRAILER_BYTES: usize = 8;

pub fn run(input: &[u8]) {
    let Some((&selector, rest)) = input.split_first() else {
        return;
    };
    let mut bytes = rest.to_vec();
    if selector & 1 == 1 {
        fix_length_and_checksum(&mut bytes);
    }
    match from_bytes(&bytes) {
        Err(e) => assert!(!e.to_string().is_empty()),
        Ok(trainer) => {
            check_finite(&trainer);
            let saved = to_bytes(&trainer);
            let again = from_bytes(&saved).expect("a saved checkpoint loads again");
            assert!(again == trainer, "the reloaded trainer differs");
            assert_eq!(to_bytes(&again), saved);
        }
    }
}

/// Makes the length field and checksum agree with the bytes (when there is room for them).
pub fn fix_length_and_checksum(bytes: &mut [u8]) {
    if bytes.len() < HEADER_BYTES + TRAILER_BYTES {
        return;
    }
    let payload_end = bytes.len() - TRAILER_BYTES;
    let len = (payload_end - HEADER_BYTES) as u64;
    bytes[12..HEADER_BYTES].copy_from_slice(&len.to_le_bytes());
    let sum = fnv1a64(&bytes[HEADER_BYTES..payload_end]);
    bytes[payload_end..].copy_from_slice(&sum.to_le_bytes());
}

fn check_finite(t: &SunAwareTrainer) {
    let finite = |what: &str, values: &[f32]| {
        assert!(values.iter().all(|v| v.is_finite()), "non-finite {what}");
    };
    for p in Param::ALL {
        finite("Gaussian parameter", t.model.gaussians.params.get(p));
        finite("Adam first moment", t.adam.m.get(p));
        finite("Adam second moment", t.adam.v.get(p));
    }
    finite(
        "Adam hyper-parameters",
        &[t.adam.beta1, t.adam.beta2, t.adam.eps],
    );
    if let Some(net) = &t.model.appearance {
        finite("appearance weights", net.mlp.params());
    }
    if let Some(net) = &t.model.shadow {
        finite("shadow weights", net.mlp.params());
    }
    for adam in [&t.appearance_adam, &t.shadow_adam] {
        finite("network Adam first moment", &adam.m);
        finite("network Adam second moment", &adam.v);
    }
    finite("densify gradient sums", &t.densify_stats.grad_accum);
    finite("densify radii", &t.densify_stats.max_radius_px);
}
