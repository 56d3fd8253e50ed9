//! The blocking shared by the x86 f32 kernels (`avx512.rs`, `avx2.rs`): packing of B, the
//! loops over reduction chunks, row tiles and column panels. Each kernel supplies only its
//! register tile ([`Tiles`]); one copy of the blocking serves both, so both keep the same
//! summation contract (stated in `avx512.rs`): every element is one fused multiply-add
//! chain along the reduction index in increasing order, from `+0.0` or from `C`, with
//! partial sums passing through `C` as f32 between chunks (which changes no bit).
//!
//! A is read in place through its strides (one broadcast per row and reduction index). B is
//! read a panel of `2 * LANES` columns at a time, either in place when row-major or from
//! panels packed into thread-local, 64-byte aligned scratch (see [`product`] for which).
//! The rows are spread evenly over tiles of at most `TILE_ROWS` rows; the reduction runs in
//! chunks of `CHUNK` indices so a tile's slice of A and a panel's slice of B stay in L1.
//!
//! Invariants: [`product`] is reached only through a kernel's detection type (its value
//! proves the CPU has the features the tile needs); the operands were checked against
//! their shape by `matmul.rs` before. Each call runs on the calling thread only.

use std::cell::RefCell;

/// One ISA's register tile.
///
/// # Safety
/// Implementors' `tile` reads and writes only what its contract below names, and computes
/// each element of `C` as the `fma` chain stated in the module header.
pub(super) unsafe trait Tiles {
    /// f32 lanes of one vector register; a panel of B is two vectors wide.
    const LANES: usize;
    /// Rows of the largest register tile.
    const TILE_ROWS: usize;
    /// Reduction indices per chunk.
    const CHUNK: usize;
    /// Pack a row-major B also when its row stride is a multiple of this many floats (0:
    /// never; else only when `m > k`, see [`product`]): a panel read in place then puts
    /// every reduction index in the same few L1 cache sets.
    const PACK_B_STRIDE: usize;

    /// `C(r, j) <- fma(A(r, t), B(t, j), C(r, j))` for `t = 0..kc` in order, for `r < rows`,
    /// `j < cols`, starting from the values in `c` when `from_c`, else from `+0.0`.
    ///
    /// # Safety
    /// The CPU has the ISA's features; `1 <= rows <= TILE_ROWS`, `1 <= cols <= 2 * LANES`;
    /// `a` addresses `A(r, t) = a[r * a_rs + t * a_cs]` for `r < rows`, `t < kc`; `b`
    /// addresses `B(t, j) = b[t * b_ts + j]` for `t < kc`, `j < cols` (and, when `b` is a
    /// packed panel, `j < 2 * LANES`); `c` holds `rows` rows of stride `ldc` with `cols`
    /// valid columns each.
    unsafe fn tile(
        rows: usize,
        a: *const f32,
        a_rs: usize,
        a_cs: usize,
        b: *const f32,
        b_ts: usize,
        kc: usize,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        from_c: bool,
    );
}

/// f32 per line of packed B.
const LINE: usize = 16;

/// One 64-byte line of packed B, so every panel row starts on a cache line (a panel is 16
/// or 32 columns: one or two lines per row).
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line([f32; LINE]);

thread_local! {
    /// Packed B of the last call on this thread (reused: no allocation per call).
    static SCRATCH: RefCell<Vec<Line>> = const { RefCell::new(Vec::new()) };
}

/// Packs B (`B(t, j) = b[t * ts + j * js]`) into panels of `panel_cols` columns: the value
/// of index `t`, column `j` is at `panel(j) * k * panel_cols + t * panel_cols + j %
/// panel_cols`. Columns past `n` are zero. `panel_cols` is a multiple of [`LINE`].
fn pack_b(
    k: usize,
    n: usize,
    panel_cols: usize,
    (b, ts, js): (&[f32], usize, usize),
    out: &mut Vec<Line>,
) {
    assert_eq!(panel_cols % LINE, 0);
    let panels = n.div_ceil(panel_cols);
    let lines = panels * k * (panel_cols / LINE);
    // Every value is written below (padding columns with zeros), so no zeroing.
    out.resize(lines, Line([0.0; LINE]));
    // SAFETY: `Line` is `repr(C)` around `[f32; LINE]`, so the lines are exactly
    // `lines * LINE` contiguous floats, borrowed exclusively through `out`.
    let floats =
        unsafe { std::slice::from_raw_parts_mut(out.as_mut_ptr() as *mut f32, lines * LINE) };
    for (panel, dst) in floats.chunks_exact_mut(k * panel_cols).enumerate() {
        let j0 = panel * panel_cols;
        let cols = panel_cols.min(n - j0);
        if js == 1 {
            for (t, row) in dst.chunks_exact_mut(panel_cols).enumerate() {
                row[..cols].copy_from_slice(&b[t * ts + j0..t * ts + j0 + cols]);
                row[cols..].fill(0.0);
            }
        } else {
            // B^T stored row-major (ts == 1): read each stored row in order.
            debug_assert_eq!(ts, 1);
            for jj in 0..cols {
                let src = &b[(j0 + jj) * js..(j0 + jj) * js + k];
                for (t, &v) in src.iter().enumerate() {
                    dst[t * panel_cols + jj] = v;
                }
            }
            if cols < panel_cols {
                for row in dst.chunks_exact_mut(panel_cols) {
                    row[cols..].fill(0.0);
                }
            }
        }
    }
}

/// `C = A B`, or `C += A B` when `accumulate`, on `K`'s register tiles.
///
/// # Safety
/// The CPU has `K`'s features; `a` holds `A(i, t) = a.0[i * a.1 + t * a.2]` for `i < m,
/// t < k`, `b` holds `B(t, j) = b.0[t * b.1 + j * b.2]` for `t < k, j < n`, with `b.2 == 1`
/// or `b.1 == 1`, and `c` is `m x n` row-major; `m, n, k >= 1`.
pub(super) unsafe fn product<K: Tiles>(
    m: usize,
    k: usize,
    n: usize,
    (a, a_rs, a_cs): (&[f32], usize, usize),
    (b, b_ts, b_js): (&[f32], usize, usize),
    c: &mut [f32],
    accumulate: bool,
) {
    let panel_cols = 2 * K::LANES;
    SCRATCH.with(|scratch| {
        let mut packed = scratch.borrow_mut();
        // A transposed B (the weight matrix of `dZ W^T`) is packed; a row-major one is
        // packed only when more rows than it has are multiplied by it (the forward `X W`:
        // 2048 x 256 by 256 x 256 ran at 156 against 150 GFLOP/s in place), and read in
        // place otherwise (the weight gradient's `dZ`, 2048 x 256: 139 in place against
        // 128 packed; an Intel Xeon, AVX-512, one thread), unless its stride is a multiple
        // of `PACK_B_STRIDE`.
        let aliasing = K::PACK_B_STRIDE > 0 && b_ts % K::PACK_B_STRIDE == 0;
        let in_place = b_js == 1 && m <= k && !aliasing;
        if !in_place {
            pack_b(k, n, panel_cols, (b, b_ts, b_js), &mut packed);
        }
        let panels = n.div_ceil(panel_cols);
        // Rows spread evenly over the tiles (72 rows of 14-row tiles: 6 x 12, not 5 x 14
        // + 2), which changes no bit (each element's chain is the same in any tile).
        let tiles = m.div_ceil(K::TILE_ROWS);
        let (a_ptr, c_ptr) = (a.as_ptr(), c.as_mut_ptr());
        let (b_ptr, b_step) = if in_place {
            (b.as_ptr(), b_ts)
        } else {
            (packed.as_ptr() as *const f32, panel_cols)
        };
        let run_tile = |t0: usize, kc: usize, from_c: bool, tile: usize| {
            let (i0, rows) = (tile * m / tiles, (tile + 1) * m / tiles - tile * m / tiles);
            for panel in 0..panels {
                let j0 = panel * panel_cols;
                let cols = panel_cols.min(n - j0);
                // SAFETY: the caller's contract bounds `A` and `B`; the offsets below stay
                // inside them (`i0 + rows <= m`, `t0 + kc <= k`, `j0 + cols <= n`, a packed
                // panel is `k * panel_cols` floats), and `C`'s tile is rows `i0..i0 + rows`,
                // columns `j0..j0 + cols` of the `m x n` output.
                unsafe {
                    K::tile(
                        rows,
                        a_ptr.add(i0 * a_rs + t0 * a_cs),
                        a_rs,
                        a_cs,
                        if in_place {
                            b_ptr.add(t0 * b_ts + j0)
                        } else {
                            b_ptr.add((panel * k + t0) * panel_cols)
                        },
                        b_step,
                        kc,
                        c_ptr.add(i0 * n + j0),
                        n,
                        cols,
                        from_c,
                    );
                }
            }
        };
        for t0 in (0..k).step_by(K::CHUNK) {
            let kc = K::CHUNK.min(k - t0);
            let from_c = accumulate || t0 > 0;
            for tile in 0..tiles {
                run_tile(t0, kc, from_c, tile);
            }
        }
    });
}
