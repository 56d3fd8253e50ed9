//! libFuzzer entry point: `cd fsw-component/fuzz && cargo +nightly fuzz run nearest_checkpoint corpus/nearest_checkpoint`.
//! The logic lives in `../harness/nearest_checkpoint.rs`, which `tests/fuzz_corpus.rs` also replays on
//! every test run.
#![no_main]

#[path = "../harness/mod.rs"]
#[allow(dead_code)]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::nearest_checkpoint::run(data));
