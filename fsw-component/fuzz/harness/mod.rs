//! Fuzz harnesses of `fsw-component`, shared by the `cargo fuzz` targets (`../fuzz_targets/`)
//! and the committed-corpus replay test (`../../tests/fuzz_corpus.rs`). Each `run` takes
//! one input; any panic, or a broken invariant (asserted in the harness), is a finding.
//! Inputs are read with [`Bytes`], which yields zeros once the input is used up, so every
//! byte string is a valid (if short) program for every harness.

pub mod bus_core;
pub mod logs;
pub mod nearest_checkpoint;
pub mod sync;

/// A cursor over the fuzz input; reads past the end give zeros and `done()` turns true.
pub struct Bytes<'a> {
    data: &'a [u8],
}

impl<'a> Bytes<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Self { data }
    }

    pub fn done(&self) -> bool {
        self.data.is_empty()
    }

    pub fn take(&mut self, n: usize) -> &'a [u8] {
        let (head, tail) = self.data.split_at(n.min(self.data.len()));
        self.data = tail;
        head
    }

    fn array<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        let head = self.take(N);
        out[..head.len()].copy_from_slice(head);
        out
    }

    pub fn u8(&mut self) -> u8 {
        self.array::<1>()[0]
    }

    pub fn i8(&mut self) -> i8 {
        i8::from_le_bytes(self.array())
    }

    pub fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.array())
    }

    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.array())
    }

    pub fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.array())
    }

    pub fn f32(&mut self) -> f32 {
        f32::from_le_bytes(self.array())
    }
}
