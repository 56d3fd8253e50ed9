//! Tests of the tile blend: the backward against finite differences (with and without
//! early termination), the contribution flags, the skip of unreached rows, and every
//! build of the row loops against the reference loops bit for bit.

use super::backward::{backward_entry, backward_with, BackwardPass};
use super::contributions::contributions_with;
use super::forward::forward_with;
use super::*;
use crate::raster::bin::TILE_PIXELS;

const NC: usize = 2;

/// Perturbs one splat quantity (splats, channels, step).
type Bump<'a> = &'a dyn Fn(&mut [Splat], &mut [f32], f32);

fn tile() -> PixelRect {
    PixelRect {
        x0: 16,
        y0: 32,
        x1: 32,
        y1: 48,
    }
}

/// Five wide splats, each clipped by its rectangle to a few pixels where its alpha is
/// far above 1/255, stacked so that the central pixels stop early (hard mode):
/// T = 0.05, 2.5e-3, 1.25e-4 after three, and the fourth (raw alpha 0.9) would take
/// it to 1.25e-5 < 1e-4.
fn splats() -> (Vec<Splat>, Vec<f32>) {
    let rect = |x0, y0, x1, y1| PixelRect { x0, y0, x1, y1 };
    let s = |mx: f32, my: f32, o: f32, z: f32, r: PixelRect| Splat {
        mean_px: [mx, my],
        conic: [0.004, 0.001, 0.006],
        opacity: o,
        depth: z,
        rect: r,
    };
    let splats = vec![
        s(20.0, 36.0, 0.96, 1.0, rect(18, 34, 24, 40)),
        s(22.0, 37.0, 0.96, 1.5, rect(20, 35, 26, 41)),
        s(21.0, 38.0, 0.96, 2.0, rect(19, 36, 25, 42)),
        s(23.0, 36.5, 0.9, 2.5, rect(17, 33, 27, 43)),
        s(20.5, 39.0, 0.6, 3.0, rect(16, 32, 30, 46)),
    ];
    let channels = vec![0.9, 0.1, 0.2, 0.7, 0.5, 0.5, 0.3, 0.8, 0.6, 0.4];
    (splats, channels)
}

type TileImages = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<u32>);

/// Blends `list` over tile `t` (background `[0.25, 0.75]`).
fn forward_on(
    t: &PixelRect,
    list: &[u32],
    splats: &[Splat],
    channels: &[f32],
    mode: AlphaMode,
    early_termination: bool,
) -> TileImages {
    let mut color = vec![0.0; TILE_PIXELS * NC];
    let mut depth = vec![0.0; TILE_PIXELS];
    let mut trans = vec![0.0; TILE_PIXELS];
    let mut last = vec![0; TILE_PIXELS];
    let inputs = TileInputs {
        tile: t,
        list,
        splats,
        splat_channels: channels,
        n_channels: NC,
        background: &[0.25, 0.75],
        mode,
    };
    blend_tile_forward(
        &inputs,
        early_termination,
        TileForwardOut {
            color: &mut color,
            depth: &mut depth,
            transmittance: &mut trans,
            last: &mut last,
        },
    );
    (color, depth, trans, last)
}

fn render_tile(splats: &[Splat], channels: &[f32], early_termination: bool) -> TileImages {
    let list: Vec<u32> = (0..splats.len() as u32).collect();
    let hard = AlphaMode { smooth: false };
    forward_on(&tile(), &list, splats, channels, hard, early_termination)
}

/// Loss weights in image layout for an image 48 wide, 48 high (the tile is inside).
fn weights() -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut state = 99u32;
    let mut next = || {
        state = state.wrapping_mul(1664525).wrapping_add(1013904223);
        (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
    };
    let n = 48 * 48;
    let c: Vec<f32> = (0..n * NC).map(|_| next()).collect();
    let a: Vec<f32> = (0..n).map(|_| next()).collect();
    let d: Vec<f32> = (0..n).map(|_| next()).collect();
    (c, a, d)
}

fn loss(splats: &[Splat], channels: &[f32], early_termination: bool) -> f64 {
    let (wc, wa, wd) = weights();
    let (color, depth, trans, _) = render_tile(splats, channels, early_termination);
    let t = tile();
    let mut sum = 0.0f64;
    for y in t.y0..t.y1 {
        for x in t.x0..t.x1 {
            let p = ((y - t.y0) * TILE_PX + (x - t.x0)) as usize;
            let pix = (y * 48 + x) as usize;
            for k in 0..NC {
                sum += (wc[pix * NC + k] * color[p * NC + k]) as f64;
            }
            sum += (wa[pix] * (1.0 - trans[p])) as f64 + (wd[pix] * depth[p]) as f64;
        }
    }
    sum
}

#[test]
fn fast_exp_is_accurate_and_safe() {
    let mut worst = 0.0f64;
    let mut x = -87.0f32;
    while x < 10.0 {
        let exact = (x as f64).exp();
        worst = worst.max(((fast_exp(x) as f64) - exact).abs() / exact);
        x += 0.0013;
    }
    assert!(worst < 3e-7, "relative error {worst}");
    assert_eq!(fast_exp(0.0), 1.0);
    assert!(fast_exp(-1e30) > 0.0 && fast_exp(-1e30) < 1e-37);
    assert!(fast_exp(f32::NAN).is_finite());
    assert!(fast_exp(f32::NEG_INFINITY) < 1e-37);
    assert!(fast_exp(1e30).is_finite());
}

/// Hard mode, early termination on and off: backward matches central differences of
/// every splat quantity (on: the stopped splats get exactly zero; off: the stack is
/// blended past T = 1e-4 and the same check holds). The rectangles keep every kept
/// alpha far from 1/255 and the stop margins are large, so steps of 1e-3 (relative)
/// never change which splats a pixel keeps. Tolerance 1e-2 relative plus 1e-3 absolute
/// covers f32 noise of the ~1e-6 loss rounding over 2h.
fn check_backward_against_finite_differences(
    splats: &[Splat],
    channels: &[f32],
    early_termination: bool,
) {
    let n = splats.len();
    let list: Vec<u32> = (0..n as u32).collect();
    let (_, _, trans, last) = render_tile(splats, channels, early_termination);
    let (wc, wa, wd) = weights();
    let mut records = vec![f32::NAN; n * (REC_CHANNELS + NC)];
    let inputs = TileInputs {
        tile: &tile(),
        list: &list,
        splats,
        splat_channels: channels,
        n_channels: NC,
        background: &[0.25, 0.75],
        mode: AlphaMode { smooth: false },
    };
    blend_tile_backward(
        &inputs,
        TileForwardState {
            transmittance: &trans,
            last: &last,
        },
        &PixelGradsView {
            width: 48,
            d_color: &wc,
            d_alpha: Some(&wa),
            d_depth: Some(&wd),
        },
        &mut records,
    );
    let stride = REC_CHANNELS + NC;
    for i in 0..n {
        let rec = &records[i * stride..(i + 1) * stride];
        let check = |name: &str, an: f32, bump: Bump| {
            let h = 1e-3f32;
            let (mut sp, mut ch) = (splats.to_vec(), channels.to_vec());
            bump(&mut sp, &mut ch, h);
            let plus = loss(&sp, &ch, early_termination);
            let (mut sp, mut ch) = (splats.to_vec(), channels.to_vec());
            bump(&mut sp, &mut ch, -h);
            let minus = loss(&sp, &ch, early_termination);
            let fd = (plus - minus) / (2.0 * h as f64);
            let tol = 1e-3 + 1e-2 * fd.abs().max(an.abs() as f64);
            assert!(
                (fd - an as f64).abs() < tol,
                "early {early_termination} splat {i} {name}: fd {fd} analytic {an}"
            );
        };
        check("mean x", rec[REC_MEAN_X], &|s, _, h| s[i].mean_px[0] += h);
        check("mean y", rec[REC_MEAN_Y], &|s, _, h| s[i].mean_px[1] += h);
        // Conic entries are ~5e-3: perturb them relatively.
        for k in 0..3 {
            let an = rec[REC_CONIC + k] * 1e-3;
            check("conic", an, &|s, _, h| s[i].conic[k] += h * 1e-3);
        }
        check("opacity", rec[REC_OPACITY], &|s, _, h| s[i].opacity += h);
        check("depth", rec[REC_DEPTH], &|s, _, h| s[i].depth += h);
        for k in 0..NC {
            check("channel", rec[REC_CHANNELS + k], &|_, c, h| {
                c[i * NC + k] += h;
            });
        }
    }
}

#[test]
fn hard_mode_backward_matches_finite_differences_with_early_stop() {
    let (splats, channels) = splats();
    let (_, _, trans, last) = render_tile(&splats, &channels, true);
    // The stack really stops early in some pixels and not in others.
    assert!(trans.iter().any(|&t| t < 2e-4 && t > 1e-4));
    assert!(last.contains(&5));
    check_backward_against_finite_differences(&splats, &channels, true);
}

/// Early termination off: the pixels that stopped above now blend the fourth splat
/// (T down to ~1.25e-5), and the backward is still the exact gradient.
#[test]
fn hard_mode_backward_matches_finite_differences_without_early_stop() {
    let (splats, channels) = splats();
    let (color_on, _, trans_on, _) = render_tile(&splats, &channels, true);
    let (color_off, _, trans_off, _) = render_tile(&splats, &channels, false);
    assert!(trans_off.iter().all(|&t| t >= TRANSMITTANCE_FLOOR));
    assert!(trans_off.iter().any(|&t| t < TRANSMITTANCE_STOP));
    assert!(trans_on.iter().all(|&t| t >= TRANSMITTANCE_STOP));
    // The difference per pixel is bounded by the residual transmittance of the stopped
    // pixel times the largest |channel - background| (here 0.75 - 0.1 = 0.65).
    let mut differ = 0;
    for p in 0..TILE_PIXELS {
        for k in 0..NC {
            let d = (color_on[p * NC + k] - color_off[p * NC + k]).abs();
            assert!(d <= trans_on[p] * 0.65 + 1e-6, "pixel {p}: {d}");
            differ += usize::from(d > 0.0);
        }
    }
    assert!(differ > 0);
    check_backward_against_finite_differences(&splats, &channels, false);
}

/// A stack of 40 near-opaque splats: with early termination off the transmittance
/// stops at the normal-float floor instead of underflowing, so the backward's rebuilt
/// `T_i` keep full precision and the front splats' gradients still match.
#[test]
fn deep_stack_without_early_stop_keeps_exact_gradients() {
    let rect = PixelRect {
        x0: 18,
        y0: 34,
        x1: 22,
        y1: 38,
    };
    let splats: Vec<Splat> = (0..40)
        .map(|i| Splat {
            mean_px: [20.0 + 0.05 * i as f32, 36.0 - 0.03 * i as f32],
            conic: [0.004, 0.001, 0.006],
            opacity: 0.97,
            depth: 1.0 + 0.1 * i as f32,
            rect,
        })
        .collect();
    let channels: Vec<f32> = (0..40 * NC).map(|i| 0.1 + 0.02 * (i % 37) as f32).collect();
    let (_, _, trans, last) = render_tile(&splats, &channels, false);
    let inside = ((36 - 32) * TILE_PX + (20 - 16)) as usize;
    assert!(trans[inside] >= TRANSMITTANCE_FLOOR && trans[inside] < 1e-30);
    assert!(last[inside] > 20 && last[inside] < 40);
    check_backward_against_finite_differences(&splats, &channels, false);
}

/// Renders `list` (a subset of the splats' indices, in order) over the test tile.
fn render_list(list: &[u32], splats: &[Splat], channels: &[f32]) -> TileImages {
    forward_on(
        &tile(),
        list,
        splats,
        channels,
        AlphaMode { smooth: false },
        true,
    )
}

/// Four tile-wide layers: raw alpha 0.99, 0.98 (T = 2e-4), 0.9 (would take every pixel
/// to 2e-5 < 1e-4: it stops them all and is blended nowhere), 0.3; and a faint splat
/// below the cutoff everywhere. The flags name the stopper, the list without the
/// zero-flag entries renders the same bits, and without the stopper too the last
/// layer would be blended (so stoppers must stay in a compacted list).
#[test]
fn contribution_flags_keep_stoppers_and_drop_only_silent_entries() {
    let wide = |o: f32, z: f32| Splat {
        mean_px: [24.0, 40.0],
        conic: [1e-6, 0.0, 1e-6],
        opacity: o,
        depth: z,
        rect: tile(),
    };
    let splats = vec![
        wide(1.0, 1.0),
        wide(0.003, 1.5),
        wide(0.98, 2.0),
        wide(0.9, 3.0),
        wide(0.3, 4.0),
    ];
    let channels: Vec<f32> = (0..splats.len() * NC).map(|i| 0.1 * i as f32).collect();
    let all: Vec<u32> = (0..splats.len() as u32).collect();
    let mut flags = vec![0u8; all.len()];
    tile_contributions(
        &tile(),
        &all,
        &splats,
        AlphaMode { smooth: false },
        true,
        &mut flags,
    );
    assert_eq!(flags, [ENTRY_BLENDS, 0, ENTRY_BLENDS, ENTRY_STOPS, 0]);
    let kept: Vec<u32> = all
        .iter()
        .copied()
        .filter(|&j| flags[j as usize] != 0)
        .collect();
    let (c_all, d_all, t_all, l_all) = render_list(&all, &splats, &channels);
    let (c_kept, d_kept, t_kept, l_kept) = render_list(&kept, &splats, &channels);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&c_all), bits(&c_kept));
    assert_eq!(bits(&d_all), bits(&d_kept));
    assert_eq!(bits(&t_all), bits(&t_kept));
    // `last` counts list positions: entry 2 of the full list is entry 1 of the kept one.
    assert!(l_all.iter().all(|&l| l == 3));
    assert!(l_kept.iter().all(|&l| l == 2));
    let blenders: Vec<u32> = vec![0, 2, 4];
    let (c_wrong, ..) = render_list(&blenders, &splats, &channels);
    assert_ne!(bits(&c_all), bits(&c_wrong));
}
/// Random splats over the test tile (some clipped by the tile's edge, some tiny,
/// faint or near-opaque), in a random depth order.
fn random_splats(seed: u64, count: usize, nc: usize) -> (Vec<Splat>, Vec<f32>) {
    let mut rng = crate::rng::SplitMix64::new(seed);
    let t = tile();
    let splats: Vec<Splat> = (0..count)
        .map(|_| {
            let mx = rng.uniform(t.x0 as f32 - 6.0, t.x1 as f32 + 6.0);
            let my = rng.uniform(t.y0 as f32 - 6.0, t.y1 as f32 + 6.0);
            let sx = rng.uniform(0.3, 8.0);
            let sy = rng.uniform(0.3, 8.0);
            let rho = rng.uniform(-0.8, 0.8);
            // Conic of a covariance with these sigmas and correlation.
            let det = sx * sx * sy * sy * (1.0 - rho * rho);
            let conic = [sy * sy / det, -rho * sx * sy / det, sx * sx / det];
            let ext_x = 3.5 * sx;
            let ext_y = 3.5 * sy;
            let clip = |v: f32| v.clamp(0.0, 64.0) as u32;
            let opacity = match rng.uniform(0.0, 1.0) {
                u if u < 0.15 => rng.uniform(0.002, 0.01),
                u if u < 0.4 => rng.uniform(0.95, 1.0),
                _ => rng.uniform(0.05, 0.95),
            };
            Splat {
                mean_px: [mx, my],
                conic,
                opacity,
                depth: rng.uniform(0.5, 9.0),
                rect: PixelRect {
                    x0: clip((mx - ext_x).floor()),
                    y0: clip((my - ext_y).floor()),
                    x1: clip((mx + ext_x).ceil() + 1.0),
                    y1: clip((my + ext_y).ceil() + 1.0),
                },
            }
        })
        .collect();
    let channels = (0..count * nc).map(|_| rng.uniform(-0.5, 1.5)).collect();
    (splats, channels)
}

/// The backward's skip of rows no pixel of which blended anything at or behind an
/// entry writes the same records, bit for bit, as evaluating every row the splat's
/// rectangle meets (random tiles: clipped, tiny, faint and near-opaque splats; early
/// termination on and off, smooth mode, a partial tile).
#[test]
fn skipping_unreached_rows_writes_the_same_records() {
    let mut partial = tile();
    partial.x1 = partial.x0 + 11;
    partial.y1 = partial.y0 + 5;
    let (wc, wa, wd) = weights();
    let mut skipped_somewhere = false;
    for seed in 0..12u64 {
        for (smooth, early_termination) in [(false, true), (false, false), (true, true)] {
            for t in [tile(), partial] {
                let count = 20 + 37 * (seed as usize % 4);
                let (splats, channels) = random_splats(seed * 31 + 7, count, NC);
                let list: Vec<u32> = (0..count as u32).collect();
                let mode = AlphaMode { smooth };
                let (_, _, trans, last) =
                    forward_on(&t, &list, &splats, &channels, mode, early_termination);
                let grads = PixelGradsView {
                    width: 48,
                    d_color: &wc,
                    d_alpha: Some(&wa),
                    d_depth: Some(&wd),
                };
                let run = |skip: bool| {
                    let mut records = vec![f32::NAN; count * (REC_CHANNELS + NC)];
                    backward_entry(
                        &TileInputs {
                            tile: &t,
                            list: &list,
                            splats: &splats,
                            splat_channels: &channels,
                            n_channels: NC,
                            background: &[0.25, 0.75],
                            mode,
                        },
                        BackwardPass {
                            state: TileForwardState {
                                transmittance: &trans,
                                last: &last,
                            },
                            grads: &grads,
                            records: &mut records,
                            skip_unreached: skip,
                        },
                    );
                    records.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                };
                assert_eq!(run(true), run(false), "seed {seed}, smooth {smooth}");
                // Some pixel stopped in front of a splat that still reaches it.
                skipped_somewhere |= last.iter().any(|&l| l > 0 && (l as usize) < count / 2);
            }
        }
    }
    assert!(skipped_somewhere);
}

/// The builds of the tile loops this CPU runs (the portable one always).
fn builds() -> Vec<Isa> {
    let mut isas = vec![Isa::Portable];
    #[cfg(target_arch = "x86_64")]
    {
        if avx2_build_supported() {
            isas.push(Isa::Avx2);
        }
        if let Some(ops) = lanes::Avx512::detect() {
            isas.push(Isa::Avx512(ops));
        }
    }
    isas
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Every build of the 16-lane row loops (AVX-512, AVX2, portable) against the scalar
/// and 8-lane loops they replaced (`reference`), bit for bit: forward colour, depth,
/// transmittance and last entry, the alpha-only pass's flags, and the backward's
/// records with the skip of unreached rows on and off. Random tiles (clipped, tiny,
/// faint and near-opaque splats in random depth order), 0 to 5 channels (the fixed
/// counts 1, 3, 4 and the general loop), hard mode with early termination on and off,
/// smooth mode, a full and a partial tile, a background, compacted lists.
#[test]
fn row_loops_match_the_reference_bit_for_bit_on_every_build() {
    let mut partial = tile();
    partial.x1 = partial.x0 + 11;
    partial.y1 = partial.y0 + 5;
    let isas = builds();
    assert!(isas.contains(&Isa::best()));
    let mut stopped = 0usize;
    let mut compacted = 0usize;
    for seed in 0..10u64 {
        for nc in 0..=5usize {
            let count = 15 + 29 * ((seed as usize + nc) % 5);
            let (splats, channels) = random_splats(seed * 131 + nc as u64, count, nc);
            let background: Vec<f32> = (0..nc).map(|k| 0.2 * k as f32).collect();
            let mut rng = crate::rng::SplitMix64::new(seed + 1000);
            let n_px = 48 * 48;
            let d_color: Vec<f32> = (0..n_px * nc).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let d_alpha: Vec<f32> = (0..n_px).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let d_depth: Vec<f32> = (0..n_px).map(|_| rng.uniform(-1.0, 1.0)).collect();
            for (smooth, early_termination) in [(false, true), (false, false), (true, false)] {
                let mode = AlphaMode { smooth };
                for t in [tile(), partial] {
                    let full: Vec<u32> = (0..count as u32).collect();
                    let inp_full = TileInputs {
                        tile: &t,
                        list: &full,
                        splats: &splats,
                        splat_channels: &channels,
                        n_channels: nc,
                        background: &background,
                        mode,
                    };
                    let mut flags_ref = vec![0u8; count];
                    reference::contributions(&inp_full, early_termination, &mut flags_ref);
                    for &isa in &isas {
                        let mut flags = vec![7u8; count];
                        contributions_with(isa, &inp_full, early_termination, &mut flags);
                        assert_eq!(flags, flags_ref, "{isa:?} seed {seed} nc {nc}");
                    }
                    stopped += flags_ref.iter().filter(|&&f| f & ENTRY_STOPS != 0).count();
                    let kept: Vec<u32> = full
                        .iter()
                        .copied()
                        .filter(|&j| flags_ref[j as usize] != 0)
                        .collect();
                    compacted += count - kept.len();
                    for list in [&full, &kept] {
                        let inp = TileInputs { list, ..inp_full };
                        let run_forward = |isa: Option<Isa>| {
                            let mut color = vec![f32::NAN; TILE_PIXELS * nc];
                            let mut depth = vec![f32::NAN; TILE_PIXELS];
                            let mut trans = vec![f32::NAN; TILE_PIXELS];
                            let mut last = vec![u32::MAX; TILE_PIXELS];
                            let out = TileForwardOut {
                                color: &mut color,
                                depth: &mut depth,
                                transmittance: &mut trans,
                                last: &mut last,
                            };
                            match isa {
                                Some(isa) => forward_with(isa, &inp, early_termination, out),
                                None => reference::forward::<0>(&inp, early_termination, out),
                            }
                            (color, depth, trans, last)
                        };
                        let (c_ref, d_ref, t_ref, l_ref) = run_forward(None);
                        for &isa in &isas {
                            let (c, d, tr, l) = run_forward(Some(isa));
                            let what = format!("{isa:?} seed {seed} nc {nc} mode {mode:?}");
                            assert_eq!(bits(&c), bits(&c_ref), "{what}: colour");
                            assert_eq!(bits(&d), bits(&d_ref), "{what}: depth");
                            assert_eq!(bits(&tr), bits(&t_ref), "{what}: transmittance");
                            assert_eq!(l, l_ref, "{what}: last");
                        }
                        let grads = PixelGradsView {
                            width: 48,
                            d_color: &d_color,
                            d_alpha: Some(&d_alpha),
                            d_depth: Some(&d_depth),
                        };
                        let run_backward = |isa: Option<Isa>, skip: bool| {
                            let mut records = vec![f32::NAN; list.len() * (REC_CHANNELS + nc)];
                            let pass = BackwardPass {
                                state: TileForwardState {
                                    transmittance: &t_ref,
                                    last: &l_ref,
                                },
                                grads: &grads,
                                records: &mut records,
                                skip_unreached: skip,
                            };
                            match (isa, smooth) {
                                (Some(isa), _) => backward_with(isa, &inp, pass),
                                (None, true) => reference::backward::<0, true>(&inp, pass),
                                (None, false) => reference::backward::<0, false>(&inp, pass),
                            }
                            bits(&records)
                        };
                        let r_ref = run_backward(None, true);
                        assert_eq!(run_backward(None, false), r_ref);
                        for &isa in &isas {
                            for skip in [true, false] {
                                assert_eq!(
                                    run_backward(Some(isa), skip),
                                    r_ref,
                                    "{isa:?} seed {seed} nc {nc} mode {mode:?} skip {skip}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }
    // The random tiles do stop pixels early and do drop entries from the lists.
    assert!(stopped > 50 && compacted > 50, "{stopped} {compacted}");
}
