//! bfloat16 matrix products with f32 accumulation on AMX tiles (`tdpbf16ps`).
//!
//! Arithmetic: as `bf16.rs` — both operands rounded to bfloat16 by `bf16::bf16_bits` (round to
//! nearest, ties to even), products of bfloat16 values summed in f32. The tile instruction
//! sums 32 reduction indices (16 pairs) of one row into each f32 accumulator in an order
//! the hardware fixes, flushing denormal inputs and outputs to zero; so results are
//! reproducible on one CPU but differ in the last bits from `bf16.rs`'s `vdpbf16ps` chain
//! (the bound `(2^-7 + 2^-16 + (k + 2) 2^-24) sum |a b|` holds for both).
//!
//! Layout: A is packed to `[row][pair]` words (two bfloat16 of consecutive reduction
//! indices per 32-bit word, the lower index in the low half), B to panels of 16 columns
//! `[panel][pair][column]` (Intel's "VNNI" layout), both zero-padded to whole tiles (rows
//! and columns to 32, pairs to 16; A's rows to an odd number of 64-byte lines, so that the
//! 16 rows a tile load reads fall in 16 different L1 sets). One micro-kernel call computes
//! a 32 x 32 block of C in four accumulator tiles (`tmm0..3`) over a chunk of the
//! reduction, loading two A tiles (`tmm4, 5`) and two B tiles (`tmm6, 7`) per 16 pairs.
//! The reduction runs in chunks of `x86::CHUNK_PAIRS` pairs whose partial sums pass
//! through C in f32 (exact), and every element's sum runs over the groups of 16 pairs in
//! increasing order whatever the block, so a row's result does not depend on the other
//! rows (callers split rows freely) nor on `m`.
//!
//! Invariants: the kernels run only behind an [`AmxKernels`] value, which exists only
//! when the CPU reports AMX-TILE and AMX-BF16 and Linux granted this process the tile data
//! state (`arch_prctl(ARCH_REQ_XCOMP_PERM)`, once per process; [`AmxKernels::detect`]).
//! Slices are checked against their shapes by `matmul.rs` before any unsafe code. Each call
//! loads the tile configuration, runs on the calling thread and releases the tiles
//! (`tilerelease`) before it returns, so no tile state outlives a call. No compiler
//! intrinsics exist for AMX on stable Rust, so the tile instructions are inline assembly.

use super::error::NnError;
use super::matmul::Strided;

/// Proof that the CPU has AMX-BF16 and the OS lets this process use the tiles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AmxKernels {
    _enabled: (),
}

impl AmxKernels {
    /// The kernels, or a configuration error saying what is missing (the CPU feature, or
    /// the kernel's permission for the tile data state).
    pub fn detect() -> Result<Self, NnError> {
        static ENABLED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
        ENABLED
            .get_or_init(enable)
            .clone()
            .map(|()| Self { _enabled: () })
            .map_err(NnError::Config)
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
            // SAFETY: `self` exists only when the CPU and OS run AMX (`detect`);
            // `Layout::operands` checked every slice against its shape.
            unsafe { x86::product(m, k, n, a, b, c, accumulate) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (m, k, n, a, b, c, accumulate);
            unreachable!("AmxKernels cannot be constructed off x86_64");
        }
    }
}

/// Checks the CPU's AMX feature bits and asks Linux for the tile data state.
fn enable() -> Result<(), String> {
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    {
        // CPUID leaf 7, sub-leaf 0, EDX: bit 22 AMX-BF16, bit 24 AMX-TILE.
        #[allow(unused_unsafe)]
        // SAFETY: CPUID leaf 7 exists on every x86_64 CPU that reports AVX2-era features and
        // returns zeros on older ones; it has no side effects.
        let leaf7 = unsafe { std::arch::x86_64::__cpuid_count(7, 0) };
        let bf16 = (leaf7.edx >> 22) & 1 == 1;
        let tile = (leaf7.edx >> 24) & 1 == 1;
        let avx512 = std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw");
        if !(bf16 && tile && avx512) {
            return Err(
                "AMX bf16 products need a CPU with AMX-TILE, AMX-BF16 and AVX-512 \
                        F/BW, which this one lacks: use GS_BF16_KERNEL=avx512bf16 or the F32 \
                        precision"
                    .into(),
            );
        }
        // Linux (5.16+) enables the tile data state per process on request.
        const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
        const XFEATURE_XTILEDATA: libc::c_long = 18;
        // SAFETY: arch_prctl with these arguments only changes this process's permitted
        // extended state; it reads and writes no memory of ours.
        let rc = unsafe {
            libc::syscall(
                libc::SYS_arch_prctl,
                ARCH_REQ_XCOMP_PERM,
                XFEATURE_XTILEDATA,
            )
        };
        if rc != 0 {
            return Err(format!(
                "AMX bf16 products: Linux refused the tile data state \
                 (arch_prctl ARCH_REQ_XCOMP_PERM: {})",
                std::io::Error::last_os_error()
            ));
        }
        Ok(())
    }
    #[cfg(not(all(target_arch = "x86_64", target_os = "linux")))]
    {
        Err("AMX bf16 products run on x86_64 Linux only".into())
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::asm;
    use std::arch::x86_64::*;
    use std::cell::RefCell;

    use super::super::matmul::Strided;

    /// Rows of a tile; also f32 columns of an accumulator tile and pairs of an A tile row.
    const TILE: usize = 16;
    /// Side of the C block one micro-kernel call computes (2 x 2 accumulator tiles).
    const BLOCK: usize = 2 * TILE;
    /// Reduction pairs per chunk: a chunk of 32 packed A rows and of a B panel pair (32 KB
    /// each at 256 pairs) stays in L1/L2 across the blocks of C that use it.
    pub(super) const CHUNK_PAIRS: usize = 256;
    /// Bytes of one tile row (64 = 16 f32 = 32 bfloat16, the most a tile row holds).
    const ROW_BYTES: usize = 64;

    /// Scratch of one thread: packed A, packed B, and a C block for the matrix's edges.
    struct Scratch {
        a: Vec<u32>,
        b: Vec<u32>,
        c_edge: [f32; BLOCK * BLOCK],
    }

    thread_local! {
        static SCRATCH: RefCell<Scratch> = const {
            RefCell::new(Scratch { a: Vec::new(), b: Vec::new(), c_edge: [0.0; BLOCK * BLOCK] })
        };
    }

    /// The 64-byte tile configuration `ldtilecfg` reads (palette 1): all eight tiles 16
    /// rows of 64 bytes.
    #[repr(C, align(64))]
    struct TileConfig {
        palette: u8,
        start_row: u8,
        reserved: [u8; 14],
        bytes_per_row: [u16; 16],
        rows: [u8; 16],
    }

    const CONFIG: TileConfig = TileConfig {
        palette: 1,
        start_row: 0,
        reserved: [0; 14],
        bytes_per_row: [64, 64, 64, 64, 64, 64, 64, 64, 0, 0, 0, 0, 0, 0, 0, 0],
        rows: [16, 16, 16, 16, 16, 16, 16, 16, 0, 0, 0, 0, 0, 0, 0, 0],
    };

    /// The bfloat16 bits of 16 floats (`bf16::bf16_bits`, lane by lane) in the low halves of
    /// 16 u32 lanes, the high halves zero.
    #[target_feature(enable = "avx512f")]
    pub(super) fn bf16_lanes(v: __m512) -> __m512i {
        let bits = _mm512_castps_si512(v);
        let odd = _mm512_and_si512(_mm512_srli_epi32::<16>(bits), _mm512_set1_epi32(1));
        let bias = _mm512_add_epi32(odd, _mm512_set1_epi32(0x7FFF));
        let rounded = _mm512_srli_epi32::<16>(_mm512_add_epi32(bits, bias));
        // NaN keeps its upper half, made quiet (rounding could carry into the sign).
        let quiet = _mm512_or_si512(_mm512_srli_epi32::<16>(bits), _mm512_set1_epi32(0x40));
        _mm512_mask_blend_epi32(_mm512_cmp_ps_mask::<_CMP_UNORD_Q>(v, v), rounded, quiet)
    }

    /// The mask of the first `valid.min(16)` lanes.
    fn lanes_mask(valid: usize) -> __mmask16 {
        (((1u32 << valid.min(TILE)) - 1) & 0xFFFF) as __mmask16
    }

    /// 16 words pairing `lo[j]` (low half) with `hi[j]` (high half), of `cols` valid
    /// floats each (the rest zero); `hi` absent reads as zeros.
    ///
    /// # Safety
    /// `lo` (and `hi` when given) address `cols <= 16` readable floats.
    #[target_feature(enable = "avx512f")]
    unsafe fn pair_lanes(lo: *const f32, hi: Option<*const f32>, cols: usize) -> __m512i {
        let mask = lanes_mask(cols);
        // SAFETY: masked loads read only the `cols` valid floats (caller's contract).
        unsafe {
            let low = bf16_lanes(_mm512_maskz_loadu_ps(mask, lo));
            match hi {
                Some(hi) => _mm512_or_si512(
                    low,
                    _mm512_slli_epi32::<16>(bf16_lanes(_mm512_maskz_loadu_ps(mask, hi))),
                ),
                None => low,
            }
        }
    }

    /// One contiguous row as words of consecutive pairs (its elements' halves in order),
    /// 16 floats at a time, zero past the row's end; `words.len()` is a multiple of 16
    /// and at least half the row's length.
    #[target_feature(enable = "avx512f,avx512bw")]
    fn pack_row(row: &[f32], words: &mut [u32]) {
        assert!(words.len().is_multiple_of(TILE) && 2 * words.len() >= row.len());
        let halves = words.as_mut_ptr() as *mut __m256i;
        for c in 0..2 * words.len() / TILE {
            let valid = row.len().saturating_sub(c * TILE);
            // SAFETY: `valid.min(16)` floats from `c * 16` lie in `row`; the 32 bytes
            // written are halves `16 c .. 16 c + 16` of `words` (checked above).
            unsafe {
                let v = if valid == 0 {
                    _mm512_setzero_si512()
                } else {
                    pair_lanes(row.as_ptr().add(c * TILE), None, valid)
                };
                _mm256_storeu_si256(halves.add(c), _mm512_cvtepi32_epi16(v));
            }
        }
    }

    /// Packs A (`A(i, t) = a[i * is + t * ts]`, row-major `ts == 1` or transposed `is ==
    /// 1`) into `out`: word `(i, p)` at `i * row_words + p`, rows padded to `rows_pad`,
    /// every padding word zero.
    #[target_feature(enable = "avx512f,avx512bw")]
    fn pack_a(
        (m, k): (usize, usize),
        (rows_pad, pairs_pad, row_words): (usize, usize, usize),
        (a, is, ts): Strided,
        out: &mut Vec<u32>,
    ) {
        out.resize(rows_pad * row_words, 0);
        out[m * row_words..].fill(0);
        if ts == 1 {
            // A row's pairs are its elements in order: 16 floats to 16 halves at a time.
            for (i, words) in out.chunks_exact_mut(row_words).take(m).enumerate() {
                pack_row(&a[i * is..i * is + k], words);
            }
        } else {
            // A(i, t) = a[t * ts + i]: stored rows 2p and 2p + 1 give pair p of every row
            // i. Blocks of 16 pairs x 16 rows are paired lane-wise into a stack block,
            // then written transposed, 16 contiguous words per packed row.
            debug_assert_eq!(is, 1);
            let pairs = k.div_ceil(2);
            let mut block = [[0u32; TILE]; TILE];
            for p0 in (0..pairs_pad).step_by(TILE) {
                for i0 in (0..m).step_by(TILE) {
                    let rows = TILE.min(m - i0);
                    for (pp, lanes) in block.iter_mut().enumerate() {
                        let p = p0 + pp;
                        // SAFETY: stored rows `2p` and `2p + 1` (when `< k`) hold `m`
                        // floats at `i0 .. i0 + rows`; the store writes the 16-word array.
                        unsafe {
                            let v = if p < pairs {
                                let lo = a.as_ptr().add(2 * p * ts + i0);
                                let hi =
                                    (2 * p + 1 < k).then(|| a.as_ptr().add((2 * p + 1) * ts + i0));
                                pair_lanes(lo, hi, rows)
                            } else {
                                _mm512_setzero_si512()
                            };
                            _mm512_storeu_si512(lanes.as_mut_ptr() as *mut __m512i, v);
                        }
                    }
                    for r in 0..rows {
                        let words = &mut out[(i0 + r) * row_words + p0..][..TILE];
                        for (pp, w) in words.iter_mut().enumerate() {
                            *w = block[pp][r];
                        }
                    }
                }
            }
        }
    }

    /// Packs B (`B(t, j) = b[t * ts + j * js]`) into panels of [`TILE`] columns: word
    /// `(p, j)` at `(j / TILE) * pairs_pad * TILE + p * TILE + j % TILE`, `panels` of
    /// them, every padding word zero.
    #[target_feature(enable = "avx512f,avx512bw")]
    fn pack_b(
        (k, n): (usize, usize),
        (panels, pairs_pad): (usize, usize),
        (b, ts, js): Strided,
        out: &mut Vec<u32>,
    ) {
        out.resize(panels * pairs_pad * TILE, 0);
        let pairs = k.div_ceil(2);
        if js == 1 {
            // Zero what the loop below leaves: whole panels past `n`, and every panel's
            // pairs past `pairs` (the weight gradient's B is large: no blanket zeroing).
            let filled = n.div_ceil(TILE);
            for (q, panel) in out.chunks_exact_mut(pairs_pad * TILE).enumerate() {
                let from = if q < filled { pairs * TILE } else { 0 };
                panel[from..].fill(0);
            }
            // Row-major: interleave stored rows 2p and 2p + 1, 16 columns at a time.
            for p in 0..pairs {
                let lo = b[2 * p * ts..].as_ptr();
                let hi = (2 * p + 1 < k).then(|| b[(2 * p + 1) * ts..].as_ptr());
                for j0 in (0..n).step_by(TILE) {
                    let words = &mut out[(j0 / TILE) * pairs_pad * TILE + p * TILE..][..TILE];
                    // SAFETY: rows `2p`, `2p + 1` hold `n` floats, `n - j0` of them from
                    // `j0`; the store writes the 16 words of `words`.
                    unsafe {
                        let v = pair_lanes(lo.add(j0), hi.map(|h| h.add(j0)), n - j0);
                        _mm512_storeu_si512(words.as_mut_ptr() as *mut __m512i, v);
                    }
                }
            }
        } else {
            // B(t, j) = b[j * js + t]: column j is a contiguous stored row whose halves, in
            // order, are its pairs; pack it, then spread it down its panel column.
            debug_assert_eq!(ts, 1);
            out.fill(0);
            let mut column = vec![0u32; pairs_pad];
            for j in 0..n {
                pack_row(&b[j * js..j * js + k], &mut column);
                let panel = &mut out[(j / TILE) * pairs_pad * TILE + j % TILE..];
                for (p, &w) in column.iter().enumerate() {
                    panel[p * TILE] = w;
                }
            }
        }
    }

    /// One 32 x 32 block of C over `steps` groups of 16 pairs: C (`ldc` bytes per row)
    /// starts from its stored values when `from_c`, else from zero.
    ///
    /// # Safety
    /// The tile configuration [`CONFIG`] is loaded; `a` addresses 32 packed A rows of
    /// `a_row_bytes` bytes holding `16 * steps` pairs from its start, `b` two panels
    /// `b_panel_bytes` apart each holding `16 * steps` rows of 64 bytes, `c` 32 rows of
    /// `ldc` bytes with 32 f32 each.
    unsafe fn block(
        a: *const u32,
        a_row_bytes: usize,
        b: *const u32,
        b_panel_bytes: usize,
        steps: usize,
        c: *mut f32,
        ldc: usize,
        from_c: bool,
    ) {
        debug_assert!(steps >= 1);
        // SAFETY: the caller's contract bounds every tile row addressed: A rows
        // `a + r * a_row_bytes + s * 64 .. + 64` for r < 32, s < steps; B rows
        // `b + q * b_panel_bytes + (16 s + r) * 64 .. + 64` for q < 2, r < 16; C rows
        // `c + r * ldc .. + 128` for r < 32.
        unsafe {
            asm!(
                "test {from_c}, {from_c}",
                "jz 3f",
                "tileloadd tmm0, [{c} + {ldc}*1]",
                "tileloadd tmm1, [{c} + {ldc}*1 + 64]",
                "tileloadd tmm2, [{c16} + {ldc}*1]",
                "tileloadd tmm3, [{c16} + {ldc}*1 + 64]",
                "jmp 4f",
                "3:",
                "tilezero tmm0",
                "tilezero tmm1",
                "tilezero tmm2",
                "tilezero tmm3",
                "4:",
                "tileloadd tmm4, [{a0} + {lda}*1]",
                "tileloadd tmm5, [{a16} + {lda}*1]",
                "tileloadd tmm6, [{b0} + {ldb}*1]",
                "tileloadd tmm7, [{b16} + {ldb}*1]",
                "tdpbf16ps tmm0, tmm4, tmm6",
                "tdpbf16ps tmm1, tmm4, tmm7",
                "tdpbf16ps tmm2, tmm5, tmm6",
                "tdpbf16ps tmm3, tmm5, tmm7",
                "add {a0}, 64",
                "add {a16}, 64",
                "add {b0}, 1024",
                "add {b16}, 1024",
                "dec {steps}",
                "jnz 4b",
                "tilestored [{c} + {ldc}*1], tmm0",
                "tilestored [{c} + {ldc}*1 + 64], tmm1",
                "tilestored [{c16} + {ldc}*1], tmm2",
                "tilestored [{c16} + {ldc}*1 + 64], tmm3",
                from_c = in(reg) from_c as usize,
                c = in(reg) c,
                c16 = in(reg) c.byte_add(TILE * ldc),
                ldc = in(reg) ldc,
                a0 = inout(reg) a => _,
                a16 = inout(reg) a.byte_add(TILE * a_row_bytes) => _,
                lda = in(reg) a_row_bytes,
                b0 = inout(reg) b => _,
                b16 = inout(reg) b.byte_add(b_panel_bytes) => _,
                ldb = in(reg) ROW_BYTES,
                steps = inout(reg) steps => _,
                out("tmm0") _, out("tmm1") _, out("tmm2") _, out("tmm3") _,
                out("tmm4") _, out("tmm5") _, out("tmm6") _, out("tmm7") _,
                options(nostack),
            );
        }
    }

    /// `C = A B` or `C += A B`; `m, n, k >= 1`.
    ///
    /// # Safety
    /// The CPU and OS run AMX (the caller holds an `AmxKernels`), and `Layout::operands`
    /// checked every operand against the shape.
    pub(super) unsafe fn product(
        m: usize,
        k: usize,
        n: usize,
        a: Strided,
        b: Strided,
        c: &mut [f32],
        accumulate: bool,
    ) {
        assert_eq!(c.len(), m * n);
        let rows_pad = m.next_multiple_of(BLOCK);
        let cols_pad = n.next_multiple_of(BLOCK);
        let pairs_pad = k.div_ceil(2).next_multiple_of(TILE);
        // A tile reads 16 packed rows: a row stride of an even number of 64-byte lines
        // (4 KB at 1024 pairs, the weight gradient's reduction) puts them in a few L1
        // sets, which then thrash; an odd number of lines spreads them over 16 sets.
        let row_words = if (pairs_pad / TILE).is_multiple_of(2) {
            pairs_pad + TILE
        } else {
            pairs_pad
        };
        let panels = cols_pad / TILE;
        SCRATCH.with(|scratch| {
            let mut scratch = scratch.borrow_mut();
            let Scratch {
                a: packed_a,
                b: packed_b,
                c_edge,
            } = &mut *scratch;
            // SAFETY: AMX implies AVX-512F and BW, which `enable` checked too.
            unsafe {
                pack_a((m, k), (rows_pad, pairs_pad, row_words), a, packed_a);
                pack_b((k, n), (panels, pairs_pad), b, packed_b);
            }
            let a_row_bytes = row_words * 4;
            let b_panel_bytes = pairs_pad * TILE * 4;
            // SAFETY: the CPU and OS run AMX (the caller holds an `AmxKernels`); the
            // configuration is valid for palette 1. Every block below stays inside the
            // padded packings (`rows_pad x row_words` words of A, `panels` panels of B) and
            // inside C or the 32 x 32 edge block.
            unsafe {
                asm!("ldtilecfg [{0}]", in(reg) &CONFIG, options(nostack, readonly));
                for p0 in (0..pairs_pad).step_by(CHUNK_PAIRS) {
                    let steps = CHUNK_PAIRS.min(pairs_pad - p0) / TILE;
                    let from_c = accumulate || p0 > 0;
                    for i0 in (0..m).step_by(BLOCK) {
                        let a_ptr = packed_a.as_ptr().add(i0 * row_words + p0);
                        for j0 in (0..n).step_by(BLOCK) {
                            let b_ptr = packed_b
                                .as_ptr()
                                .add((j0 / TILE) * pairs_pad * TILE + p0 * TILE);
                            let (rows, cols) = (BLOCK.min(m - i0), BLOCK.min(n - j0));
                            let whole = rows == BLOCK && cols == BLOCK;
                            // A block off C's edge runs in the edge buffer: loaded from
                            // C's valid part (zeros elsewhere), copied back after.
                            let (c_ptr, ldc, from) = if whole {
                                (c.as_mut_ptr().add(i0 * n + j0), n * 4, from_c)
                            } else {
                                c_edge.fill(0.0);
                                if from_c {
                                    for r in 0..rows {
                                        c_edge[r * BLOCK..r * BLOCK + cols]
                                            .copy_from_slice(&c[(i0 + r) * n + j0..][..cols]);
                                    }
                                }
                                (c_edge.as_mut_ptr(), BLOCK * 4, true)
                            };
                            block(
                                a_ptr,
                                a_row_bytes,
                                b_ptr,
                                b_panel_bytes,
                                steps,
                                c_ptr,
                                ldc,
                                from,
                            );
                            if !whole {
                                for r in 0..rows {
                                    c[(i0 + r) * n + j0..][..cols]
                                        .copy_from_slice(&c_edge[r * BLOCK..r * BLOCK + cols]);
                                }
                            }
                        }
                    }
                }
                asm!("tilerelease", options(nostack, nomem));
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::kernel_tests::operand;
    use crate::nn::kernel_tests::{
        bf16_layouts_meet_the_bound, results_repeat_whatever_the_splits,
    };
    use crate::nn::matmul::{Bf16Kernel, Products};
    use crate::rng::SplitMix64;

    /// The AMX products (behind `Products`' shape checks), or `None` with a visible skip.
    fn kernels() -> Option<Products> {
        match AmxKernels::detect() {
            Ok(k) => Some(Products::bf16_on(Bf16Kernel::Amx(k))),
            Err(e) => {
                crate::machine::skip_unless_required("GS_REQUIRE_AMX", &e.to_string());
                None
            }
        }
    }

    #[test]
    fn products_meet_the_bf16_bound_in_all_three_layouts_and_odd_shapes() {
        let Some(kernels) = kernels() else { return };
        let mut rng = SplitMix64::new(23);
        // Shapes off every tile edge: rows and columns off 16 and 32, the reduction odd, off
        // 32 and past one chunk (512 reduction indices).
        let shapes = [
            (1, 1, 1),
            (1, 2, 17),
            (3, 5, 3),
            (16, 32, 16),
            (32, 64, 32),
            (33, 33, 31),
            (17, 63, 48),
            (40, 600, 37),
            (64, 257, 1),
            (70, 1030, 66),
        ];
        bf16_layouts_meet_the_bound(kernels, &shapes, &mut rng);
    }

    /// The vector rounding that packs the operands equals `bf16_bits` on every class of
    /// input: ties both ways, carries into the exponent, overflow, denormals, NaN payloads.
    #[test]
    fn packing_rounds_like_bf16_bits() {
        if kernels().is_none() {
            return;
        }
        use std::arch::x86_64::*;
        let mut values = vec![
            0.0,
            -0.0,
            1.0,
            1.0 + 2f32.powi(-8),
            1.0 + 3.0 * 2f32.powi(-8),
            2.0 - 2f32.powi(-10),
            f32::MAX,
            -f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x007F_FFFF),
            f32::NAN,
            f32::from_bits(0x7FFF_FFFF),
            f32::from_bits(0xFFFF_FFFF),
            f32::from_bits(0x7F80_0001),
        ];
        let mut rng = SplitMix64::new(41);
        values.extend((0..4096).map(|_| f32::from_bits(rng.next_u64() as u32)));
        values.resize(values.len().next_multiple_of(16), 0.0);
        for chunk in values.chunks_exact(16) {
            let mut lanes = [0u32; 16];
            // SAFETY: AVX-512F is present (`kernels()` found AMX, which `enable` checks
            // with AVX-512F); the load and store cover the 16-element arrays.
            unsafe {
                let v = x86::bf16_lanes(_mm512_loadu_ps(chunk.as_ptr()));
                _mm512_storeu_si512(lanes.as_mut_ptr() as *mut __m512i, v);
            }
            for (&x, &got) in chunk.iter().zip(&lanes) {
                assert_eq!(
                    got,
                    crate::nn::bf16::bf16_bits(x) as u32,
                    "{x:e} ({:#x})",
                    x.to_bits()
                );
            }
        }
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Row splits, repeats and a reduction split at a chunk boundary (the chunks inside one
    /// call pass their sums through C the same way) keep the bits.
    #[test]
    fn rows_do_not_depend_on_their_neighbours_and_chunks_keep_the_bits() {
        let Some(kernels) = kernels() else { return };
        let chunk = 2 * x86::CHUNK_PAIRS;
        results_repeat_whatever_the_splits(kernels, (45, 2 * chunk + 6, 40), &[chunk, 2 * chunk]);
    }

    #[test]
    fn threads_use_the_tiles_independently() {
        let Some(kernels) = kernels() else { return };
        let mut rng = SplitMix64::new(37);
        let (m, k, n) = (64, 96, 48);
        let a = operand(m * k, &mut rng);
        let b = operand(k * n, &mut rng);
        let mut want = vec![0.0; m * n];
        kernels.matmul(&a, &b, &mut want, m, k, n, false);
        let results: Vec<Vec<f32>> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..4)
                .map(|_| {
                    s.spawn(|| {
                        let mut c = vec![0.0; m * n];
                        for _ in 0..20 {
                            kernels.matmul(&a, &b, &mut c, m, k, n, false);
                        }
                        c
                    })
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for c in results {
            assert_eq!(bits(&c), bits(&want));
        }
    }
}
