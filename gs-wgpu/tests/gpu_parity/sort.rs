//! The device's radix sort against a stable CPU sort of the same keys (live keys sorted
//! by (tile, order bits), stably; the rest untouched).

use super::*;

/// Random sort keys: tiles below `n_tiles` and order bits from a handful of values (so
/// many keys tie on both), word 2 random (not ascending, so only a stable sort keeps the
/// given order among ties), word 3 the key's position.
fn sort_keys_input(seed: u64, len: usize, n_tiles: u32) -> Vec<[u32; 4]> {
    let mut rng = SplitMix64::new(seed);
    let orders: Vec<u32> = (0..7).map(|_| rng.next_u64() as u32).collect();
    (0..len)
        .map(|i| {
            let r = rng.next_u64();
            let tile = ((r >> 8) % n_tiles as u64) as u32;
            // Mostly shared values (top bit set and clear among them), some all-random.
            let order = if r & 7 == 0 {
                (r >> 32) as u32
            } else {
                orders[((r >> 3) % 7) as usize]
            };
            [tile, order, rng.next_u64() as u32, i as u32]
        })
        .collect()
}

#[test]
fn radix_sort_matches_a_stable_cpu_sort() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let raster = GpuRasterizer::new(ctx).unwrap();
    // (buffer length, live keys on the device, tiles): empty, single, block edges (4096
    // keys per workgroup), capacity above the count, 0 tile bits (an even pass count:
    // 8), 9 and 12 tile bits (11 passes: the copy back), 13 (12 passes).
    let cases = [
        (0, 0, 5),
        (1, 1, 5),
        (1, 0, 5),
        (700, 700, 1),
        (4096, 4095, 300),
        (4097, 4097, 4096),
        (10007, 6001, 4096),
        (50001, 50001, 5000),
        (70000, 65537, 300),
    ];
    for (k, &(len, live, n_tiles)) in cases.iter().enumerate() {
        let keys = sort_keys_input(100 + k as u64, len, n_tiles);
        let mut expected = keys[..live].to_vec();
        expected.sort_by_key(|key| (key[0], key[1]));
        expected.extend_from_slice(&keys[live..]);
        let got = raster.sort_keys(&keys, live, n_tiles).unwrap();
        assert_eq!(got.len(), len);
        let first_bad = got.iter().zip(&expected).position(|(a, b)| a != b);
        assert!(
            first_bad.is_none(),
            "len {len}, live {live}, {n_tiles} tiles: first difference at {first_bad:?}"
        );
    }
    let mut keys = sort_keys_input(7, 10, 3);
    assert!(raster.sort_keys(&keys, 11, 3).is_err(), "live > length");
    keys[9][0] = 3;
    assert!(raster.sort_keys(&keys, 10, 3).is_err(), "tile >= n_tiles");
    // Past the live keys a tile word is not read.
    assert!(raster.sort_keys(&keys, 9, 3).is_ok());
}
