//! The simulator's seeded generator is gs-core's SplitMix64 (Steele, Lea, Flood 2014), used
//! for pixel jitter and surface sampling, with its finaliser `mix64` to derive a seed per
//! pixel. Invariant: the stream depends only on the seed, so results are bit-identical
//! across runs and thread counts when every pixel derives its own seed.

pub use gs_core::rng::{mix64, SplitMix64};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_values_and_ranges() {
        // First output for seed 0 from the reference implementation.
        assert_eq!(SplitMix64::new(0).next_u64(), 0xE220_A839_7B1D_CDAF);
        // next_f32 is the top 24 bits over 2^24, as the scenes cached before this module
        // re-exported gs-core's generator were drawn (same bits).
        let mut a = SplitMix64::new(42);
        let mut b = SplitMix64::new(42);
        for _ in 0..1000 {
            let expected = (b.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32);
            assert_eq!(a.next_f32().to_bits(), expected.to_bits());
        }
        let mut rng = SplitMix64::new(42);
        let mean = (0..10_000).map(|_| rng.next_f32() as f64).sum::<f64>() / 10_000.0;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        assert!((0..1000).all(|_| (0.0..1.0).contains(&rng.next_f32())));
        assert_eq!(
            mix64(1),
            SplitMix64::new(1u64.wrapping_sub(0x9E37_79B9_7F4A_7C15)).next_u64()
        );
    }
}
