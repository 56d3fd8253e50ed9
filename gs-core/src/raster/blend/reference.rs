//! The scalar/8-lane tile loops the 16-lane rows in `blend.rs` replaced, kept unchanged
//! (test builds only) as the reference those rows must match bit for bit: per-pixel
//! alpha from 8-lane groups of `row_gauss`, a bit loop over the kept pixels in the
//! forward and the alpha-only pass, and the 8-lane backward with its skip of unreached
//! groups.

use super::backward::BackwardPass;
use super::*;
use crate::raster::bin::TILE_PIXELS;

/// `exp(power)` of splat `s` at the pixel centres of row `py`, lanes `i` (pixel
/// `x_origin + i`) for every 8-lane group that meets the columns `cols`, and the mask of
/// those lanes where `o exp(power)` reaches `cutoff` (exactly where [`alpha_of`] is
/// `Some`). Fixed-width and branch-free inside a group so it vectorises; other lanes of
/// `out` are left untouched and never in the mask.
#[inline(always)]
fn row_gauss(
    s: &Splat,
    py: f32,
    x_origin: u32,
    cutoff: f32,
    cols: u16,
    out: &mut [f32; TILE_PX as usize],
) -> u16 {
    let dy = s.mean_px[1] - py;
    let [a, b, c] = s.conic;
    let dx0 = s.mean_px[0] - (x_origin as f32 + 0.5);
    let base = -0.5 * c * dy * dy;
    let bdy = b * dy;
    let mut mask = 0u16;
    for (gi, group) in out.chunks_exact_mut(LANE_GROUP).enumerate() {
        let group_bits = ((1u32 << LANE_GROUP) - 1) << (gi * LANE_GROUP);
        if u32::from(cols) & group_bits == 0 {
            continue;
        }
        let first = (gi * LANE_GROUP) as f32;
        for (i, o) in group.iter_mut().enumerate() {
            let dx = dx0 - (first + i as f32);
            let power = -0.5 * a * dx * dx - bdy * dx + base;
            *o = fast_exp(power);
        }
        // A plain comparison per lane: compiles to one compare and a move-mask.
        let mut m = 0u32;
        for (i, &g) in group.iter().enumerate() {
            m |= u32::from(s.opacity * g >= cutoff) << i;
        }
        let m = m as u16;
        mask |= m << (gi * LANE_GROUP);
    }
    mask
}

/// `FIXED > 0`: the channel count is `FIXED` (loops unroll); 0: `n_channels`.
pub(super) fn forward<const FIXED: usize>(
    inp: &TileInputs,
    early_termination: bool,
    out: TileForwardOut,
) {
    let TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode,
    } = *inp;
    let nc = if FIXED > 0 { FIXED } else { n_channels };
    out.color.fill(0.0);
    out.depth.fill(0.0);
    out.transmittance.fill(1.0);
    out.last.fill(0);
    let full = column_mask(
        &PixelRect {
            x0: tile.x0,
            y0: 0,
            x1: tile.x1,
            y1: 0,
        },
        tile,
    );
    // Per tile row, the columns still blending.
    let mut row_active = [0u16; TILE_PX as usize];
    for m in row_active.iter_mut().take((tile.y1 - tile.y0) as usize) {
        *m = full;
    }
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [0.0f32; TILE_PX as usize];
    for (j, &rank) in list.iter().enumerate() {
        if n_active == 0 {
            break;
        }
        prefetch_splat(splats, list, j + PREFETCH_AHEAD);
        let s = &splats[rank as usize];
        let ch = &splat_channels[rank as usize * nc..rank as usize * nc + nc];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            continue;
        }
        let cols = column_mask(&r, tile);
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let live = row_active[ly] & cols;
            if live == 0 {
                continue;
            }
            let mut bits = live & row_gauss(s, y as f32 + 0.5, tile.x0, cutoff, live, &mut gauss);
            while bits != 0 {
                let lx = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let Some((alpha, _)) = alpha_of(s.opacity, gauss[lx], mode) else {
                    continue;
                };
                let p = ly * TILE_PX as usize + lx;
                let t = out.transmittance[p];
                let t_next = t * (1.0 - alpha);
                if t_next < stop {
                    row_active[ly] &= !(1u16 << lx);
                    n_active -= 1;
                    continue;
                }
                let w = alpha * t;
                for (acc, &c) in out.color[p * nc..p * nc + nc].iter_mut().zip(ch) {
                    *acc += w * c;
                }
                out.depth[p] += w * s.depth;
                out.transmittance[p] = t_next;
                out.last[p] = j as u32 + 1;
            }
        }
    }
    if background.iter().any(|&b| b != 0.0) {
        for p in 0..TILE_PIXELS {
            let t = out.transmittance[p];
            for (acc, &b) in out.color[p * nc..p * nc + nc].iter_mut().zip(background) {
                *acc += t * b;
            }
        }
    }
}

/// [`forward_body`] without channels or depth: only the transmittance and the flags.
pub(super) fn contributions(inp: &TileInputs, early_termination: bool, flags: &mut [u8]) {
    let TileInputs {
        tile,
        list,
        splats,
        mode,
        ..
    } = *inp;
    flags.fill(0);
    let mut transmittance = [1.0f32; TILE_PIXELS];
    let full = column_mask(
        &PixelRect {
            x0: tile.x0,
            y0: 0,
            x1: tile.x1,
            y1: 0,
        },
        tile,
    );
    let mut row_active = [0u16; TILE_PX as usize];
    for m in row_active.iter_mut().take((tile.y1 - tile.y0) as usize) {
        *m = full;
    }
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [0.0f32; TILE_PX as usize];
    for (j, &rank) in list.iter().enumerate() {
        if n_active == 0 {
            break;
        }
        prefetch_splat(splats, list, j + PREFETCH_AHEAD);
        let s = &splats[rank as usize];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            continue;
        }
        let cols = column_mask(&r, tile);
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let live = row_active[ly] & cols;
            if live == 0 {
                continue;
            }
            let mut bits = live & row_gauss(s, y as f32 + 0.5, tile.x0, cutoff, live, &mut gauss);
            while bits != 0 {
                let lx = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let Some((alpha, _)) = alpha_of(s.opacity, gauss[lx], mode) else {
                    continue;
                };
                let p = ly * TILE_PX as usize + lx;
                let t_next = transmittance[p] * (1.0 - alpha);
                if t_next < stop {
                    row_active[ly] &= !(1u16 << lx);
                    n_active -= 1;
                    flags[j] |= ENTRY_STOPS;
                    continue;
                }
                transmittance[p] = t_next;
                flags[j] |= ENTRY_BLENDS;
            }
        }
    }
}

/// [`alpha_of`] for a lane already known to pass the cutoff: the same operations, no
/// branch on the lane, so eight lanes evaluate together.
#[inline(always)]
fn alpha_lane<const SMOOTH: bool>(o: f32, gauss: f32) -> (f32, f32) {
    let raw = o * gauss;
    let clamped = raw > ALPHA_MAX;
    let alpha_c = if clamped { ALPHA_MAX } else { raw };
    let (alpha, d_alpha) = if SMOOTH && alpha_c < SMOOTH_HI {
        let u = (alpha_c - SMOOTH_LO) / (SMOOTH_HI - SMOOTH_LO);
        let ramp = u * u * (3.0 - 2.0 * u);
        let d_ramp = 6.0 * u * (1.0 - u) / (SMOOTH_HI - SMOOTH_LO);
        (alpha_c * ramp, ramp + alpha_c * d_ramp)
    } else {
        (alpha_c, 1.0)
    };
    (alpha, if clamped { 0.0 } else { d_alpha })
}

/// The 8 lanes of a tile-local plane starting at pixel `p0`.
#[inline(always)]
fn lanes(plane: &[f32], p0: usize) -> &Lanes {
    plane[p0..p0 + LANE_GROUP]
        .try_into()
        .expect("a lane group lies inside its tile")
}

#[inline(always)]
fn lanes_mut(plane: &mut [f32], p0: usize) -> &mut Lanes {
    (&mut plane[p0..p0 + LANE_GROUP])
        .try_into()
        .expect("a lane group lies inside its tile")
}

/// Backward over 8-lane groups: every lane of a group that holds a kept pixel is computed
/// together, with selects so that the other lanes change nothing. Per-pixel quantities are
/// the same operations as the scalar formulas; per-splat sums are kept per lane and added
/// in a fixed order at the end of each list entry.
pub(super) fn backward<const FIXED: usize, const SMOOTH: bool>(
    inp: &TileInputs,
    pass: BackwardPass,
) {
    // `mode` is rebuilt from `SMOOTH` so the alpha branch is resolved at compile time.
    let TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode: _,
    } = *inp;
    let BackwardPass {
        state,
        grads,
        records,
        skip_unreached,
    } = pass;
    const T: usize = TILE_PX as usize;
    const TP: usize = TILE_PIXELS;
    let mode = AlphaMode { smooth: SMOOTH };
    let nc = if FIXED > 0 { FIXED } else { n_channels };
    let stride = REC_CHANNELS + nc;
    // Planes of TILE_PIXELS values: behind-colour S per channel then depth; d_color per
    // channel.
    let mut behind = vec![0.0f32; TP * (nc + 1)];
    let mut trans = [0.0f32; TP];
    let mut d_color = vec![0.0f32; TP * nc];
    // d_alpha of a pixel times its final transmittance.
    let mut d_alpha_final = [0.0f32; TP];
    let mut d_depth_px = [0.0f32; TP];
    let mut last = [0u32; TP];
    let mut row_max_last = [0u32; T];
    for y in tile.y0..tile.y1 {
        let ly = (y - tile.y0) as usize;
        for x in tile.x0..tile.x1 {
            let p = ly * T + (x - tile.x0) as usize;
            let pix = y as usize * grads.width + x as usize;
            let t_final = state.transmittance[p];
            trans[p] = t_final;
            for k in 0..nc {
                behind[k * TP + p] = t_final * background[k];
                d_color[k * TP + p] = grads.d_color[pix * nc + k];
            }
            if let Some(da) = grads.d_alpha {
                d_alpha_final[p] = da[pix] * t_final;
            }
            if let Some(dd) = grads.d_depth {
                d_depth_px[p] = dd[pix];
            }
            last[p] = state.last[p];
            row_max_last[ly] = row_max_last[ly].max(state.last[p]);
        }
    }
    let max_last = row_max_last.iter().copied().max().unwrap_or(0) as usize;
    records[max_last * stride..].fill(0.0);
    let mut acc_ch = vec![[0.0f32; LANE_GROUP]; nc];
    let mut gauss = [0.0f32; T];
    let cutoff = mode.cutoff();
    for j in (0..max_last).rev() {
        let rank = list[j] as usize;
        if let Some(ahead) = j.checked_sub(PREFETCH_AHEAD) {
            prefetch_splat(splats, list, ahead);
        }
        let s = &splats[rank];
        let ch = &splat_channels[rank * nc..rank * nc + nc];
        let rec = &mut records[j * stride..(j + 1) * stride];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            rec.fill(0.0);
            continue;
        }
        let cols = column_mask(&r, tile);
        // Per-lane sums: mean x, mean y, conic a, b, c, opacity, depth; then channels.
        let mut acc = [[0.0f32; LANE_GROUP]; REC_CHANNELS];
        acc_ch.fill([0.0; LANE_GROUP]);
        let [ca, cb, cc] = s.conic;
        let o = s.opacity;
        let dx0 = s.mean_px[0] - (tile.x0 as f32 + 0.5);
        let j_u32 = j as u32;
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            if j_u32 >= row_max_last[ly] {
                continue;
            }
            // Only the pixels that blended something at or behind this entry can have
            // blended it: a lane group without one changes nothing (every lane would add
            // a zero), so it is not evaluated at all.
            let last_row: &[u32; T] = last[ly * T..(ly + 1) * T].try_into().expect("one tile row");
            let mut reach = 0u32;
            for (lx, &l) in last_row.iter().enumerate() {
                reach |= u32::from(j_u32 < l) << lx;
            }
            let live = if skip_unreached {
                cols & reach as u16
            } else {
                cols
            };
            if live == 0 {
                continue;
            }
            let py = y as f32 + 0.5;
            let bits = live & row_gauss(s, py, tile.x0, cutoff, live, &mut gauss);
            let dy = s.mean_px[1] - py;
            for gi in 0..T / LANE_GROUP {
                let group_bits = (bits >> (gi * LANE_GROUP)) & 0xff;
                if group_bits == 0 {
                    continue;
                }
                let p0 = ly * T + gi * LANE_GROUP;
                let g: &Lanes = gauss[gi * LANE_GROUP..(gi + 1) * LANE_GROUP]
                    .try_into()
                    .expect("two groups per row");
                let last_l = &last[p0..p0 + LANE_GROUP];
                let mut on = [false; LANE_GROUP];
                for i in 0..LANE_GROUP {
                    on[i] = (group_bits >> i) & 1 != 0 && j_u32 < last_l[i];
                }
                let mut alpha = [0.0f32; LANE_GROUP];
                let mut d_alpha_d_raw = [0.0f32; LANE_GROUP];
                for i in 0..LANE_GROUP {
                    (alpha[i], d_alpha_d_raw[i]) = alpha_lane::<SMOOTH>(o, g[i]);
                }
                let mut inv = [0.0f32; LANE_GROUP];
                let mut t = [0.0f32; LANE_GROUP];
                let mut w = [0.0f32; LANE_GROUP];
                {
                    let tr = lanes_mut(&mut trans, p0);
                    for i in 0..LANE_GROUP {
                        inv[i] = 1.0 / (1.0 - alpha[i]);
                        t[i] = tr[i] * inv[i];
                        tr[i] = if on[i] { t[i] } else { tr[i] };
                        w[i] = alpha[i] * t[i];
                    }
                }
                let mut d_alpha = [0.0f32; LANE_GROUP];
                for k in 0..nc {
                    let c = ch[k];
                    let dc = lanes(&d_color, k * TP + p0);
                    let a = &mut acc_ch[k];
                    let bh = lanes_mut(&mut behind, k * TP + p0);
                    for i in 0..LANE_GROUP {
                        a[i] += if on[i] { w[i] * dc[i] } else { 0.0 };
                        d_alpha[i] += dc[i] * (t[i] * c - bh[i] * inv[i]);
                        bh[i] = if on[i] { bh[i] + w[i] * c } else { bh[i] };
                    }
                }
                {
                    let gd = lanes(&d_depth_px, p0);
                    let bh = lanes_mut(&mut behind, nc * TP + p0);
                    let z = s.depth;
                    for i in 0..LANE_GROUP {
                        acc[REC_DEPTH][i] += if on[i] { w[i] * gd[i] } else { 0.0 };
                        d_alpha[i] += gd[i] * (t[i] * z - bh[i] * inv[i]);
                        bh[i] = if on[i] { bh[i] + w[i] * z } else { bh[i] };
                    }
                }
                let da_final = lanes(&d_alpha_final, p0);
                for i in 0..LANE_GROUP {
                    let d_a = d_alpha[i] + da_final[i] * inv[i];
                    let d_raw = if on[i] { d_a * d_alpha_d_raw[i] } else { 0.0 };
                    let d_power = d_raw * o * g[i];
                    let dx = dx0 - (gi * LANE_GROUP + i) as f32;
                    acc[REC_OPACITY][i] += d_raw * g[i];
                    acc[REC_MEAN_X][i] += d_power * (ca * dx + cb * dy);
                    acc[REC_MEAN_Y][i] += d_power * (cb * dx + cc * dy);
                    acc[REC_CONIC][i] += d_power * 0.5 * dx * dx;
                    acc[REC_CONIC + 1][i] += d_power * dx * dy;
                    acc[REC_CONIC + 2][i] += d_power * 0.5 * dy * dy;
                }
            }
        }
        // The power derivatives enter the mean and conic gradients with a minus sign.
        rec[REC_MEAN_X] = -lane_sum(&acc[REC_MEAN_X]);
        rec[REC_MEAN_Y] = -lane_sum(&acc[REC_MEAN_Y]);
        for k in 0..3 {
            rec[REC_CONIC + k] = -lane_sum(&acc[REC_CONIC + k]);
        }
        rec[REC_OPACITY] = lane_sum(&acc[REC_OPACITY]);
        rec[REC_DEPTH] = lane_sum(&acc[REC_DEPTH]);
        for (dst, a) in rec[REC_CHANNELS..].iter_mut().zip(&acc_ch) {
            *dst = lane_sum(a);
        }
    }
}
