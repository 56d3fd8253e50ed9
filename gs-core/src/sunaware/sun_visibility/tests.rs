//! Tests of the Sun visibility pass: the tile walk against a plain per-pixel scan, bit for
//! bit, and the whole pass against a serial scan on any thread count.

use super::tile_walk::{footprint_power, occluder_alpha, tile_visibility};
use super::*;
use crate::raster::blend::{ALPHA_MIN, TRANSMITTANCE_STOP};
use crate::raster::splat_rect;
use crate::rng::SplitMix64;

/// The per-pixel scan over the whole tile list that `tile_visibility` replaces.
fn plain_scan_tile(
    list: &[u32],
    ranked: &[Splat],
    limit_of_rank: &[f32],
    rect: PixelRect,
    footprint_radius_px: f32,
) -> Vec<[f32; 2]> {
    let mut acc = vec![[0.0f32; 2]; list.len()];
    let mut receivers: Vec<usize> = (0..list.len()).collect();
    receivers.sort_by(|&a, &b| {
        limit_of_rank[list[a] as usize]
            .total_cmp(&limit_of_rank[list[b] as usize])
            .then(a.cmp(&b))
    });
    let r2 = footprint_radius_px * footprint_radius_px;
    for py in rect.y0..rect.y1 {
        for px in rect.x0..rect.x1 {
            let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
            let mut trans = 1.0f32;
            let mut next_occluder = 0;
            for &k in &receivers {
                let s = &ranked[list[k] as usize];
                let (dx, dy) = (s.mean_px[0] - fx, s.mean_px[1] - fy);
                if dx * dx + dy * dy > r2 {
                    continue;
                }
                let [a, b, c] = s.conic;
                let weight = (-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).exp();
                if weight.is_nan() || weight <= 1e-6 {
                    continue;
                }
                let limit = limit_of_rank[list[k] as usize];
                while next_occluder < list.len()
                    && ranked[list[next_occluder] as usize].depth < limit
                {
                    if trans >= TRANSMITTANCE_STOP {
                        let o = &ranked[list[next_occluder] as usize];
                        let alpha = occluder_alpha(o.opacity, footprint_power(o, fx, fy));
                        if alpha >= ALPHA_MIN {
                            trans *= 1.0 - alpha;
                        }
                    }
                    next_occluder += 1;
                }
                let seen = if trans < TRANSMITTANCE_STOP {
                    0.0
                } else {
                    trans
                };
                acc[k][0] += weight;
                acc[k][1] += weight * seen;
            }
        }
    }
    acc
}

/// The whole pass against the reference it replaced: every tile by the plain per-pixel
/// scan, then each Gaussian's sums over its tiles in tile order, serially. Same bits,
/// on 1, 2 and 3 threads. The light image (72 px) ends inside a tile row and column.
#[test]
fn visibility_matches_the_serial_plain_scan_on_any_thread_count() {
    let side = 72u32;
    let radius = 2.0f32;
    let bias = 0.01f32;
    let mut rng = SplitMix64::new(21);
    let n = 700;
    let splats: Vec<Option<Splat>> = (0..n)
        .map(|i| {
            let wide = rng.uniform(0.05, 0.8);
            let conic = [wide, rng.uniform_symmetric(0.5 * wide), wide * 1.2];
            let det = conic[0] * conic[2] - conic[1] * conic[1];
            let cov = [conic[2] / det, -conic[1] / det, conic[0] / det];
            let mean_px = [rng.uniform(-4.0, 76.0), rng.uniform(-4.0, 76.0)];
            let opacity = rng.uniform(0.05, 0.99);
            let depth = rng.uniform(1.0, 2.0);
            let rect = splat_rect(mean_px, cov, 2.0 * (opacity / ALPHA_MIN).ln(), side, side);
            (i % 17 != 0 && !rect.is_empty()).then_some(Splat {
                mean_px,
                conic,
                opacity,
                depth,
                rect,
            })
        })
        .collect();
    let margin: Vec<f32> = (0..n).map(|_| rng.uniform(0.0, 0.05)).collect();

    let order = depth_order(&splats);
    let ranked: Vec<Splat> = order.iter().filter_map(|&g| splats[g as usize]).collect();
    let limit_of_rank: Vec<f32> = order
        .iter()
        .zip(&ranked)
        .map(|(&g, s)| s.depth - bias - margin[g as usize])
        .collect();
    let grid = TileGrid::new(side, side);
    let rects: Vec<PixelRect> = ranked.iter().map(|s| s.rect).collect();
    let bins = bin_tiles(&grid, &rects);
    let mut sum_w = vec![0.0f64; n];
    let mut sum_wt = vec![0.0f64; n];
    for t in 0..grid.n_tiles() {
        let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
        let acc = plain_scan_tile(list, &ranked, &limit_of_rank, grid.tile_rect(t), radius);
        for (&rank, a) in list.iter().zip(&acc) {
            let g = order[rank as usize] as usize;
            sum_w[g] += a[0] as f64;
            sum_wt[g] += a[1] as f64;
        }
    }
    let want: Vec<u32> = sum_w
        .iter()
        .zip(&sum_wt)
        .map(|(&w, &wt)| {
            let v = if w > 0.0 {
                ((wt / w) as f32).clamp(0.0, 1.0)
            } else {
                1.0
            };
            v.to_bits()
        })
        .collect();
    let shadowed = want
        .iter()
        .filter(|&&b| f32::from_bits(b) > 0.0 && f32::from_bits(b) < 0.9)
        .count();
    assert!(shadowed > n / 10, "only {shadowed} partly shadowed");
    for threads in [1, 2, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let got = pool.install(|| visibility_from_splats(&splats, side, radius, bias, &margin));
        let got: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
        assert!(got == want, "{threads} threads");
    }
}

#[test]
fn tile_walk_matches_the_plain_scan_bit_for_bit() {
    let rect = PixelRect {
        x0: 16,
        y0: 32,
        x1: 32,
        y1: 48,
    };
    let mut rng = SplitMix64::new(7);
    for (trial, &count) in [0usize, 1, 5, 40, 300].iter().enumerate() {
        for &radius in &[0.5f32, 1.3, 2.0, 3.7] {
            // Centres in and around the tile, some far off and one non-finite; dense,
            // opaque occluders so that pixels saturate; depths with ties.
            // Each splat's rectangle is the rasterizer's bound in a 64 x 64 image.
            let mut ranked: Vec<Splat> = (0..count)
                .map(|i| {
                    let wide = rng.uniform(0.02, 0.6);
                    let conic = [wide, rng.uniform_symmetric(0.5 * wide), wide * 1.3];
                    let det = conic[0] * conic[2] - conic[1] * conic[1];
                    let cov = [conic[2] / det, -conic[1] / det, conic[0] / det];
                    let mean_px = [rng.uniform(12.0, 36.0), rng.uniform(28.0, 52.0)];
                    let opacity = if i % 7 == 0 {
                        rng.uniform(0.0, 0.01)
                    } else {
                        rng.uniform(0.05, 0.99)
                    };
                    let q_max = 2.0 * (opacity / ALPHA_MIN).ln();
                    let rect = if q_max > 0.0 {
                        splat_rect(mean_px, cov, q_max, 64, 64)
                    } else {
                        PixelRect {
                            x0: 0,
                            y0: 0,
                            x1: 0,
                            y1: 0,
                        }
                    };
                    Splat {
                        mean_px,
                        conic,
                        opacity,
                        depth: (i / 3) as f32 * 0.01,
                        rect,
                    }
                })
                .collect();
            if count == 300 {
                // Four near-opaque walls in front of everything: the whole tile
                // saturates and the walk can stop.
                for wall in ranked.iter_mut().take(4) {
                    wall.conic = [1e-4, 0.0, 1e-4];
                    wall.opacity = 0.99;
                    wall.depth = -1.0;
                    wall.rect = PixelRect {
                        x0: 0,
                        y0: 0,
                        x1: 64,
                        y1: 64,
                    };
                }
            }
            if count > 3 {
                ranked[2].mean_px[0] = f32::NAN;
                ranked[3].mean_px = [1e9, -1e9];
            }
            let limit_of_rank: Vec<f32> = ranked
                .iter()
                .map(|s| s.depth - rng.uniform(0.0, 0.05))
                .collect();
            let list: Vec<u32> = (0..count as u32).collect();
            let floors: Vec<f32> = ranked.iter().map(occluder_power_floor).collect();
            let want = plain_scan_tile(&list, &ranked, &limit_of_rank, rect, radius);
            let bits = |v: &[[f32; 2]]| {
                v.iter()
                    .flat_map(|p| [p[0].to_bits(), p[1].to_bits()])
                    .collect::<Vec<_>>()
            };
            let walk = TileWalk {
                list: &list,
                ranked: &ranked,
                limit_of_rank: &limit_of_rank,
                power_floor_of_rank: &floors,
                rect,
                footprint_radius_px: radius,
            };
            // Both builds of the walk (AVX-512 where the CPU has it, and plain).
            for isa in [WalkIsa::Detect, WalkIsa::Plain] {
                let got = tile_visibility(&walk, isa);
                assert_eq!(
                    bits(&got),
                    bits(&want),
                    "trial {trial}, radius {radius} {isa:?}"
                );
            }
            let got = tile_visibility(&walk, WalkIsa::Detect);
            if count >= 40 {
                assert!(
                    got.iter().any(|a| a[0] > 0.0 && a[1] < a[0]),
                    "no shadowing"
                );
            }
        }
    }
}
