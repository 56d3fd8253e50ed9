//! libFuzzer entry point: `cd fsw-component/fuzz && cargo +nightly fuzz run bus_core corpus/bus_core`.
//! The logic lives in `../harness/bus_core.rs`, which `tests/fuzz_corpus.rs` also replays on
//! every test run.
#![no_main]

#[path = "../harness/mod.rs"]
#[allow(dead_code)]
mod harness;

libfuzzer_sys::fuzz_target!(|data: &[u8]| harness::bus_core::run(data));
