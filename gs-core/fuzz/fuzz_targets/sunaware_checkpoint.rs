//! libFuzzer entry point:
//! `cd gs-core/fuzz && cargo +nightly fuzz run sunaware_checkpoint corpus/sunaware_checkpoint`.
//! The logic lives in `../harness.rs`, which `tests/fuzz_corpus.rs` also replays on every
//! test run.
#![no_main]

#[path = "../harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::run(data));
