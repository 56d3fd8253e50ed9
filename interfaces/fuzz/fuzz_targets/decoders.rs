//! libFuzzer entry point: `cd interfaces/fuzz && cargo +nightly fuzz run decoders corpus/decoders`.
//! The logic lives in `../harness.rs`, which `tests/corpus.rs` also replays on every test run.
#![no_main]

#[path = "../harness.rs"]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::run(data));
