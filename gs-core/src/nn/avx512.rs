//! f32 matrix products on AVX-512F: the networks' products on CPUs that have it (chosen at
//! run time by `matmul.rs`; elsewhere the portable `gemm` crate runs them).
//!
//! Summation order (what makes the bits reproducible): every element is one chain of fused
//! multiply-adds along the reduction index in increasing order,
//! `c <- fma(A(i, t), B(t, j), c)` for `t = 0, 1, ..., k - 1`, starting from `+0.0`, or
//! from the value already in `C` when accumulating. Each step rounds once. The chain is the
//! same for every element whatever its place in a register tile, the tile's size, the
//! chunking of the reduction (partial sums pass through `C` as f32, which changes no bit)
//! or the caller's split of the rows, so results depend only on the operands (and the
//! thread's denormal mode): bit-reproducible for any shape split and thread count. The
//! error against exact arithmetic is at most `gamma_k * (|c_0| + sum_t |A(i,t) B(t,j)|)`,
//! `gamma_k = k u / (1 - k u)`, `u = 2^-24` (one rounding per step, `k` steps).
//!
//! Blocking: A is read in place through its strides (one broadcast per row and reduction
//! index), so the row-major forward product and the transposed weight-gradient product
//! share one kernel. B is read 32 columns (two vectors) at a time, either in place when
//! row-major or from panels packed into thread-local, 64-byte aligned scratch (see
//! `product` for which). A register tile is up to [`TILE_ROWS`] rows by 32 columns (28
//! accumulators of the 32 vector registers), the rows spread evenly over the tiles; the
//! reduction runs in chunks of [`CHUNK`] indices so a tile's slice of A and a panel's
//! slice of B stay in L1 together. Measured on an Intel Xeon (AVX-512, one thread) at
//! 130-165 GFLOP/s on the networks' 2048-row block shapes, about twice the `gemm` crate.
//!
//! Invariants: the kernels run only behind an [`Avx512Kernels`] value, which exists only
//! when the running CPU reports `avx512f` ([`Avx512Kernels::detect`]); every slice length
//! is checked against its shape before any unsafe code (a mismatch is a bug in this crate
//! and panics, like `matmul.rs`). Each call runs on the calling thread only.

use super::matmul::Strided;

/// Rows of the largest register tile.
pub const TILE_ROWS: usize = 14;

/// Reduction indices per chunk: 14 rows x 128 of A (7 KB) and 128 x 32 of B (16 KB) stay in
/// L1 (128 measured faster than 256 on the weight gradient's 2048-long reductions).
pub const CHUNK: usize = 128;

/// Proof that the running CPU has AVX-512F: the only way to reach the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Avx512Kernels {
    _detected: (),
}

impl Avx512Kernels {
    /// The kernels when this CPU has AVX-512F, else `None`.
    pub fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Some(Self { _detected: () });
            }
        }
        None
    }

    /// `C = A B`, or `C += A B` when `accumulate` (`C` row-major `m x n`), for
    /// `Products`: `m, n, k >= 1` and every operand checked against its shape there.
    pub(crate) fn product(
        self,
        (m, k, n): (usize, usize, usize),
        a: Strided,
        b: Strided,
        c: &mut [f32],
        accumulate: bool,
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: `self` exists only when the CPU has avx512f (`detect`);
            // `Layout::operands` checked every slice against its shape.
            unsafe { x86::product(m, k, n, a, b, c, accumulate) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (m, k, n, a, b, c, accumulate);
            unreachable!("Avx512Kernels cannot be constructed off x86_64");
        }
    }
}

// The AVX-512 intrinsics are stable from Rust 1.89 (the workspace's `rust-version`).
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;
    use std::cell::RefCell;

    use super::{CHUNK, TILE_ROWS};

    /// f32 lanes of one vector.
    const LANES: usize = 16;
    /// Columns of one packed panel of B (two vectors).
    const PANEL_COLS: usize = 2 * LANES;

    /// One 64-byte line of packed B, so every panel row starts on a cache line.
    #[derive(Clone, Copy)]
    #[repr(C, align(64))]
    struct Line([f32; LANES]);

    thread_local! {
        /// Packed B of the last call on this thread (reused: no allocation per call).
        static SCRATCH: RefCell<Vec<Line>> = const { RefCell::new(Vec::new()) };
    }

    /// Packs B (`B(t, j) = b[t * ts + j * js]`) into panels of `PANEL_COLS` columns: the
    /// value of index `t`, column `j` is at `panel(j) * k * PANEL_COLS + t * PANEL_COLS +
    /// j % PANEL_COLS`. Columns past `n` are zero.
    fn pack_b(k: usize, n: usize, (b, ts, js): (&[f32], usize, usize), out: &mut Vec<Line>) {
        let panels = n.div_ceil(PANEL_COLS);
        let lines = panels * k * (PANEL_COLS / LANES);
        // Every value is written below (padding columns with zeros), so no zeroing.
        out.resize(lines, Line([0.0; LANES]));
        // SAFETY: `Line` is `repr(C)` around `[f32; LANES]`, so the lines are exactly
        // `lines * LANES` contiguous floats, borrowed exclusively through `out`.
        let floats =
            unsafe { std::slice::from_raw_parts_mut(out.as_mut_ptr() as *mut f32, lines * LANES) };
        for (panel, dst) in floats.chunks_exact_mut(k * PANEL_COLS).enumerate() {
            let j0 = panel * PANEL_COLS;
            let cols = PANEL_COLS.min(n - j0);
            if js == 1 {
                for (t, row) in dst.chunks_exact_mut(PANEL_COLS).enumerate() {
                    row[..cols].copy_from_slice(&b[t * ts + j0..t * ts + j0 + cols]);
                    row[cols..].fill(0.0);
                }
            } else {
                // B^T stored row-major (ts == 1): read each stored row in order.
                debug_assert_eq!(ts, 1);
                for jj in 0..cols {
                    let src = &b[(j0 + jj) * js..(j0 + jj) * js + k];
                    for (t, &v) in src.iter().enumerate() {
                        dst[t * PANEL_COLS + jj] = v;
                    }
                }
                if cols < PANEL_COLS {
                    for row in dst.chunks_exact_mut(PANEL_COLS) {
                        row[cols..].fill(0.0);
                    }
                }
            }
        }
    }

    /// One register tile: `R` rows by `V` vectors of columns (`cols` of them valid), over
    /// `kc` reduction indices, into `c` (row stride `ldc`), starting from the values in `c`
    /// when `from_c`, else from zero.
    ///
    /// # Safety
    /// The CPU has avx512f; `a` addresses `A(r, t) = a[r * a_rs + t * a_cs]` for `r < R`,
    /// `t < kc`; `b` one panel's `kc * PANEL_COLS` floats; `c` `R` rows of `ldc` floats
    /// with `cols <= V * LANES` valid columns from its start.
    #[target_feature(enable = "avx512f")]
    unsafe fn tile<const R: usize, const V: usize>(
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
    ) {
        let mask_of = |v: usize| -> __mmask16 {
            let valid = cols.saturating_sub(v * LANES).min(LANES);
            ((1u32 << valid) - 1) as u16
        };
        let mut acc = [[_mm512_setzero_ps(); V]; R];
        if from_c {
            for (r, acc_row) in acc.iter_mut().enumerate() {
                for (v, acc_v) in acc_row.iter_mut().enumerate() {
                    *acc_v = _mm512_maskz_loadu_ps(mask_of(v), c.add(r * ldc + v * LANES));
                }
            }
        }
        let full = cols == V * LANES;
        for t in 0..kc {
            let bp = b.add(t * b_ts);
            let bv: [__m512; V] = if full {
                std::array::from_fn(|v| _mm512_loadu_ps(bp.add(v * LANES)))
            } else {
                std::array::from_fn(|v| _mm512_maskz_loadu_ps(mask_of(v), bp.add(v * LANES)))
            };
            let ap = a.add(t * a_cs);
            for (r, acc_row) in acc.iter_mut().enumerate() {
                let av = _mm512_set1_ps(*ap.add(r * a_rs));
                for (acc_v, &bv_v) in acc_row.iter_mut().zip(&bv) {
                    *acc_v = _mm512_fmadd_ps(av, bv_v, *acc_v);
                }
            }
        }
        for (r, acc_row) in acc.iter().enumerate() {
            for (v, &sum) in acc_row.iter().enumerate() {
                _mm512_mask_storeu_ps(c.add(r * ldc + v * LANES), mask_of(v), sum);
            }
        }
    }

    /// # Safety
    /// As [`tile`], with `1 <= rows <= TILE_ROWS`.
    #[target_feature(enable = "avx512f")]
    unsafe fn tile_dispatch(
        rows: usize,
        wide: bool,
        a: *const f32,
        rs: usize,
        cs: usize,
        b: *const f32,
        b_ts: usize,
        kc: usize,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        acc: bool,
    ) {
        macro_rules! go {
            ($r:literal) => {
                if wide {
                    tile::<$r, 2>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                } else {
                    tile::<$r, 1>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                }
            };
        }
        match rows {
            14 => go!(14),
            13 => go!(13),
            12 => go!(12),
            11 => go!(11),
            10 => go!(10),
            9 => go!(9),
            8 => go!(8),
            7 => go!(7),
            6 => go!(6),
            5 => go!(5),
            4 => go!(4),
            3 => go!(3),
            2 => go!(2),
            _ => go!(1),
        }
    }

    /// # Safety
    /// The CPU has avx512f; `a` holds `A(i, t) = a.0[i * a.1 + t * a.2]` for `i < m,
    /// t < k`, `b` holds `B(t, j) = b.0[t * b.1 + j * b.2]` for `t < k, j < n`, and `c` is
    /// `m x n` row-major; `m, n, k >= 1`.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn product(
        m: usize,
        k: usize,
        n: usize,
        (a, a_rs, a_cs): (&[f32], usize, usize),
        (b, b_ts, b_js): (&[f32], usize, usize),
        c: &mut [f32],
        accumulate: bool,
    ) {
        const { assert!(TILE_ROWS <= 14, "tile_dispatch covers 14 rows at most") };
        SCRATCH.with(|scratch| {
            let mut packed = scratch.borrow_mut();
            // A transposed B (the weight matrix of `dZ W^T`) is packed; a row-major one
            // is packed only when more rows than it has are multiplied by it (the forward
            // `X W`: 2048 x 256 by 256 x 256 ran at 156 against 150 GFLOP/s in place), and
            // read in place otherwise (the weight gradient's `dZ`, 2048 x 256: 139 in place
            // against 128 packed; an Intel Xeon, one thread).
            let in_place = b_js == 1 && m <= k;
            if !in_place {
                pack_b(k, n, (b, b_ts, b_js), &mut packed);
            }
            let panels = n.div_ceil(PANEL_COLS);
            // Rows spread evenly over the tiles (72 rows: 6 x 12, not 5 x 14 + 2), which
            // changes no bit (each element's chain is the same in any tile).
            let tiles = m.div_ceil(TILE_ROWS);
            let (a_ptr, c_ptr) = (a.as_ptr(), c.as_mut_ptr());
            let (b_ptr, b_step) = if in_place {
                (b.as_ptr(), b_ts)
            } else {
                (packed.as_ptr() as *const f32, PANEL_COLS)
            };
            for t0 in (0..k).step_by(CHUNK) {
                let kc = CHUNK.min(k - t0);
                let from_c = accumulate || t0 > 0;
                for tile in 0..tiles {
                    let (i0, rows) = (tile * m / tiles, (tile + 1) * m / tiles - tile * m / tiles);
                    for panel in 0..panels {
                        let j0 = panel * PANEL_COLS;
                        let cols = PANEL_COLS.min(n - j0);
                        tile_dispatch(
                            rows,
                            cols > LANES,
                            a_ptr.add(i0 * a_rs + t0 * a_cs),
                            a_rs,
                            a_cs,
                            if in_place {
                                b_ptr.add(t0 * b_ts + j0)
                            } else {
                                b_ptr.add((panel * k + t0) * PANEL_COLS)
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
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use crate::nn::avx512::Avx512Kernels;
    use crate::nn::matmul::{F32Kernel, Products};
    use crate::rng::SplitMix64;

    /// The AVX-512 products (the kernels behind `Products`' shape checks), or `None` after
    /// a visible skip (a failure under `GS_REQUIRE_AVX512=1`).
    fn kernels() -> Option<Products> {
        let found = Avx512Kernels::detect();
        if found.is_none() {
            crate::machine::skip_unless_required("GS_REQUIRE_AVX512", "no avx512f");
        }
        found.map(|k| Products::f32_on(F32Kernel::Avx512(k)))
    }

    /// Values over several binades, signed, with exact zeros.
    fn operand(len: usize, rng: &mut SplitMix64) -> Vec<f32> {
        (0..len)
            .map(|_| {
                if rng.below(17) == 0 {
                    0.0
                } else {
                    rng.uniform(-1.0, 1.0) * 2f32.powi(rng.below(8) as i32 - 4)
                }
            })
            .collect()
    }

    fn transpose(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
        let mut t = vec![0.0; x.len()];
        for i in 0..rows {
            for j in 0..cols {
                t[j * rows + i] = x[i * cols + j];
            }
        }
        t
    }

    /// Per element of `c0 + A B` (`A` m x k, `B` k x n row-major): the module's stated
    /// summation order in scalar f32 (a chain of `mul_add` from `c0`), the exact value in
    /// f64, and `|c0| + sum |a b|`.
    fn references(
        a: &[f32],
        b: &[f32],
        c0: &[f32],
        (m, k, n): (usize, usize, usize),
    ) -> (Vec<f32>, Vec<f64>, Vec<f64>) {
        let mut chain = c0.to_vec();
        let mut exact: Vec<f64> = c0.iter().map(|&v| v as f64).collect();
        let mut magnitude: Vec<f64> = c0.iter().map(|&v| (v as f64).abs()).collect();
        for i in 0..m {
            for j in 0..n {
                let e = i * n + j;
                for t in 0..k {
                    let (x, y) = (a[i * k + t], b[t * n + j]);
                    chain[e] = x.mul_add(y, chain[e]);
                    exact[e] += x as f64 * y as f64;
                    magnitude[e] += (x as f64 * y as f64).abs();
                }
            }
        }
        (chain, exact, magnitude)
    }

    /// `got` equals the stated order bit for bit, and lies within `gamma_k` of exact.
    fn check(got: &[f32], refs: &(Vec<f32>, Vec<f64>, Vec<f64>), k: usize, what: &str) {
        let u = 2f64.powi(-24);
        let gamma = k as f64 * u / (1.0 - k as f64 * u);
        for (e, (&g, ((&chain, &exact), &mag))) in got
            .iter()
            .zip(refs.0.iter().zip(&refs.1).zip(&refs.2))
            .enumerate()
        {
            assert_eq!(
                g.to_bits(),
                chain.to_bits(),
                "{what}: element {e}: {g} vs the fma chain's {chain}"
            );
            // 1.01: the f64 reference's own rounding; 1e-30: a zero sum.
            let bound = gamma * 1.01 * mag + 1e-30;
            assert!(
                (g as f64 - exact).abs() <= bound,
                "{what}: element {e}: {g} vs exact {exact} (bound {bound})"
            );
        }
    }

    #[test]
    fn products_follow_the_stated_order_in_all_three_layouts_and_odd_shapes() {
        let Some(kernels) = kernels() else { return };
        let mut rng = SplitMix64::new(17);
        // m off the 14-row tile, n off the 16/32 columns, k = 1, and k past one chunk.
        let shapes = [
            (1, 1, 1),
            (1, 2, 17),
            (3, 5, 3),
            (14, 32, 32),
            (15, 33, 16),
            (17, 63, 33),
            (37, 19, 55),
            (40, 8, 33),
            (29, 1, 70),
            (28, 96, 64),
            (11, 256, 3),
            (64, 257, 1),
            (5, 600, 48),
        ];
        for (m, k, n) in shapes {
            let a = operand(m * k, &mut rng);
            let b = operand(k * n, &mut rng);
            let zero = vec![0.0; m * n];
            let refs = references(&a, &b, &zero, (m, k, n));
            let shape = format!("{m}x{k}x{n}");

            let mut c = vec![f32::NAN; m * n];
            kernels.matmul(&a, &b, &mut c, m, k, n, false);
            check(&c, &refs, k, &format!("matmul {shape}"));

            let mut c2 = vec![f32::NAN; m * n];
            kernels.matmul_at_b(&transpose(&a, m, k), &b, &mut c2, k, m, n, false);
            check(&c2, &refs, k, &format!("matmul_at_b {shape}"));

            let mut c3 = vec![f32::NAN; m * n];
            kernels.matmul_a_bt(&a, &transpose(&b, k, n), &mut c3, m, k, n, false);
            check(&c3, &refs, k, &format!("matmul_a_bt {shape}"));

            // Accumulating continues the chain from what is in C, in every layout.
            let c0 = operand(m * n, &mut rng);
            let refs = references(&a, &b, &c0, (m, k, n));
            let mut c = c0.clone();
            kernels.matmul(&a, &b, &mut c, m, k, n, true);
            check(&c, &refs, k, &format!("accumulated matmul {shape}"));
            let mut c2 = c0.clone();
            kernels.matmul_at_b(&transpose(&a, m, k), &b, &mut c2, k, m, n, true);
            check(&c2, &refs, k, &format!("accumulated matmul_at_b {shape}"));
            let mut c3 = c0;
            kernels.matmul_a_bt(&a, &transpose(&b, k, n), &mut c3, m, k, n, true);
            check(&c3, &refs, k, &format!("accumulated matmul_a_bt {shape}"));
        }
    }

    #[test]
    fn empty_shapes_leave_or_zero_the_output() {
        let Some(kernels) = kernels() else { return };
        // k = 0: an empty sum, so zero, or C unchanged when accumulating.
        let mut c = vec![5.0; 6];
        kernels.matmul(&[], &[], &mut c, 2, 0, 3, true);
        assert_eq!(c, vec![5.0; 6]);
        kernels.matmul_at_b(&[], &[], &mut c, 0, 2, 3, true);
        assert_eq!(c, vec![5.0; 6]);
        kernels.matmul_a_bt(&[], &[], &mut c, 2, 0, 3, false);
        assert_eq!(c, vec![0.0; 6]);
        // m = 0 or n = 0: nothing to write, nothing read.
        kernels.matmul(&[], &[1.0; 12], &mut [], 0, 4, 3, false);
        kernels.matmul(&[1.0; 8], &[], &mut [], 2, 4, 0, false);
        kernels.matmul_at_b(&[], &[1.0; 12], &mut [], 4, 0, 3, true);
        kernels.matmul_a_bt(&[1.0; 8], &[], &mut [], 2, 4, 0, true);
    }

    #[test]
    fn results_repeat_bit_for_bit_whatever_the_row_split_and_reduction_split() {
        let Some(kernels) = kernels() else { return };
        let mut rng = SplitMix64::new(5);
        let (m, k, n) = (45, 300, 40);
        let a = operand(m * k, &mut rng);
        let b = operand(k * n, &mut rng);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut whole = vec![0.0; m * n];
        kernels.matmul(&a, &b, &mut whole, m, k, n, false);
        let mut again = vec![0.0; m * n];
        kernels.matmul(&a, &b, &mut again, m, k, n, false);
        assert_eq!(bits(&whole), bits(&again));
        // Row blocks of any size give the same bits (callers split rows freely, in threads).
        for split in [1, 5, 14, 17] {
            let mut pieces = vec![0.0; m * n];
            for (rows_a, rows_c) in a.chunks(split * k).zip(pieces.chunks_mut(split * n)) {
                kernels.matmul(rows_a, &b, rows_c, rows_c.len() / n, k, n, false);
            }
            assert_eq!(bits(&whole), bits(&pieces), "split {split}");
        }
        // The reduction split over two calls at any index: the second one continues the
        // first one's chains (the MLP's weight gradient accumulates block by block).
        let a_t = transpose(&a, m, k); // k x m: the weight-gradient layout
        let mut at_b = vec![0.0; m * n];
        kernels.matmul_at_b(&a_t, &b, &mut at_b, k, m, n, false);
        assert_eq!(bits(&whole), bits(&at_b));
        for split in [1, 77, 256] {
            let mut parts = vec![0.0; m * n];
            let rest = k - split;
            kernels.matmul_at_b(
                &a_t[..split * m],
                &b[..split * n],
                &mut parts,
                split,
                m,
                n,
                false,
            );
            kernels.matmul_at_b(
                &a_t[split * m..],
                &b[split * n..],
                &mut parts,
                rest,
                m,
                n,
                true,
            );
            assert_eq!(bits(&whole), bits(&parts), "reduction split {split}");
        }
    }
}
