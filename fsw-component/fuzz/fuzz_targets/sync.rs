//! libFuzzer entry point: `cd fsw-component/fuzz && cargo +nightly fuzz run sync corpus/sync`.
//! The logic lives in `../harness/sync.rs`, which `tests/fuzz_corpus.rs` also replays on
//! every test run.
#![no_main]

#[path = "../harness/mod.rs"]
#[allow(dead_code)]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::sync::run(data));
