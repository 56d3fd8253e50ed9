//! Checks shared by the x86 f32 kernels' tests (`avx512.rs`, `avx2.rs`), each taking the
//! kernel under test as `Products`: the stated summation order against a scalar `mul_add`
//! chain (bit for bit) and an f64 bound, empty shapes, repeatability under row and
//! reduction splits, and agreement of two kernels bit for bit on random shapes; and the
//! operand helpers the bf16 and `matmul.rs` tests use too, and the bfloat16 kernels'
//! references and bound (`bf16.rs`, `amx.rs`).

use crate::nn::bf16::round_to_bf16;
use crate::nn::matmul::Products;
use crate::rng::SplitMix64;

/// Values over several binades, signed, with exact zeros.
pub(super) fn operand(len: usize, rng: &mut SplitMix64) -> Vec<f32> {
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

/// `x` (`rows x cols`, row-major) stored transposed (`cols x rows`).
pub(super) fn transpose(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
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

/// Every product form on odd shapes (rows off the tiles, columns off the vectors, `k = 1`,
/// `k` past one chunk), overwriting and accumulating, equals the stated order bit for bit.
pub(super) fn products_follow_the_stated_order(kernels: Products) {
    let mut rng = SplitMix64::new(17);
    // m off the 14- and 6-row tiles, n off the vectors, k = 1, and k past one chunk.
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
        // The AVX2 tile: 6 rows by 8 or 16 columns, chunks of 256.
        (6, 3, 8),
        (7, 40, 9),
        (13, 300, 24),
        // B's row stride a multiple of 4 KiB with m <= k: packed by the AVX2 kernel only.
        (4, 9, 1024),
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

/// `k = 0` zeroes `C` (or leaves it when accumulating); `m = 0` or `n = 0` touch nothing.
pub(super) fn empty_shapes_leave_or_zero_the_output(kernels: Products) {
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

/// The same bits on a repeat, for any split of the rows and for the kernel's reduction
/// splits over calls (f32: any index; bf16 kernels: their pair or chunk boundaries), on
/// `m x k x n` (`k` past the largest split).
pub(super) fn results_repeat_whatever_the_splits(
    kernels: Products,
    (m, k, n): (usize, usize, usize),
    reduction_splits: &[usize],
) {
    let mut rng = SplitMix64::new(5);
    let a = operand(m * k, &mut rng);
    let b = operand(k * n, &mut rng);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let mut whole = vec![0.0; m * n];
    kernels.matmul(&a, &b, &mut whole, m, k, n, false);
    let mut again = vec![0.0; m * n];
    kernels.matmul(&a, &b, &mut again, m, k, n, false);
    assert_eq!(bits(&whole), bits(&again));
    // Row blocks of any size give the same bits (callers split rows freely, in threads).
    for split in [1, 5, 14, 17, 33] {
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
    for &split in reduction_splits {
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

/// `first` and `second` give the same bits on random shapes, in every layout, overwriting
/// and accumulating.
pub(super) fn kernels_agree_bit_for_bit(first: Products, second: Products) {
    let mut rng = SplitMix64::new(29);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for _ in 0..40 {
        let (m, k, n) = (1 + rng.below(70), 1 + rng.below(600), 1 + rng.below(90));
        let shape = format!("{m}x{k}x{n}");
        let a = operand(m * k, &mut rng);
        let b = operand(k * n, &mut rng);
        let (a_t, b_t) = (transpose(&a, m, k), transpose(&b, k, n));
        let c0 = operand(m * n, &mut rng);
        for accumulate in [false, true] {
            let run = |p: Products| {
                let mut c = [c0.clone(), c0.clone(), c0.clone()];
                p.matmul(&a, &b, &mut c[0], m, k, n, accumulate);
                p.matmul_at_b(&a_t, &b, &mut c[1], k, m, n, accumulate);
                p.matmul_a_bt(&a, &b_t, &mut c[2], m, k, n, accumulate);
                c
            };
            let (x, y) = (run(first), run(second));
            for (layout, (x, y)) in x.iter().zip(&y).enumerate() {
                assert_eq!(
                    bits(x),
                    bits(y),
                    "{shape}, layout {layout}, accumulate {accumulate}"
                );
            }
        }
    }
}

// The bfloat16 kernels' references (`bf16.rs`, `amx.rs`).

/// `A (m x k)`, `B (k x n)`: per element of `C`, the exact f64 product, the product of
/// the bf16-rounded inputs in f64, and `sum |a b|`.
pub(super) fn bf16_references(
    a: &[f32],
    b: &[f32],
    (m, k, n): (usize, usize, usize),
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut exact = vec![0.0; m * n];
    let mut rounded = vec![0.0; m * n];
    let mut magnitude = vec![0.0; m * n];
    for i in 0..m {
        for j in 0..n {
            for t in 0..k {
                let (x, y) = (a[i * k + t], b[t * n + j]);
                exact[i * n + j] += x as f64 * y as f64;
                rounded[i * n + j] += round_to_bf16(x) as f64 * round_to_bf16(y) as f64;
                magnitude[i * n + j] += (x as f64 * y as f64).abs();
            }
        }
    }
    (exact, rounded, magnitude)
}

/// Checks `got` against both references: the stated bf16 bound against exact arithmetic,
/// and the f32-accumulation bound against the product of the rounded inputs (which a
/// kernel that skipped or truncated the rounding would miss).
pub(super) fn bf16_check(got: &[f32], refs: &(Vec<f64>, Vec<f64>, Vec<f64>), k: usize, what: &str) {
    let u = 2f64.powi(-24);
    let tiny = 1e-30;
    for (e, ((&g, (&exact, &rounded)), &mag)) in got
        .iter()
        .zip(refs.0.iter().zip(&refs.1))
        .zip(&refs.2)
        .enumerate()
    {
        let g = g as f64;
        let bound = (2f64.powi(-7) + 2f64.powi(-16) + (k as f64 + 2.0) * u) * mag + tiny;
        assert!(
            (g - exact).abs() <= bound,
            "{what}: element {e}: {g} vs exact {exact} (bound {bound})"
        );
        let accumulation = (k as f64 + 2.0) * u * 1.01 * mag + tiny;
        assert!(
            (g - rounded).abs() <= accumulation,
            "{what}: element {e}: {g} vs bf16-rounded {rounded} (bound {accumulation})"
        );
    }
}

/// Every layout of the bf16 `kernels` on `shapes` (random operands from `rng`) within
/// [`bf16_check`]'s bound: `matmul`, `matmul_at_b` and `matmul_a_bt`, which pack the same
/// words and so agree bit for bit, and `matmul` accumulating onto its own result.
pub(super) fn bf16_layouts_meet_the_bound(
    kernels: Products,
    shapes: &[(usize, usize, usize)],
    rng: &mut SplitMix64,
) {
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let name = kernels.kernel_name();
    for &(m, k, n) in shapes {
        let a = operand(m * k, rng);
        let b = operand(k * n, rng);
        let refs = bf16_references(&a, &b, (m, k, n));
        let shape = format!("{name} {m}x{k}x{n}");

        let mut c = vec![f32::NAN; m * n];
        kernels.matmul(&a, &b, &mut c, m, k, n, false);
        bf16_check(&c, &refs, k, &format!("matmul {shape}"));

        let mut c2 = vec![f32::NAN; m * n];
        kernels.matmul_at_b(&transpose(&a, m, k), &b, &mut c2, k, m, n, false);
        bf16_check(&c2, &refs, k, &format!("matmul_at_b {shape}"));

        let mut c3 = vec![f32::NAN; m * n];
        kernels.matmul_a_bt(&a, &transpose(&b, k, n), &mut c3, m, k, n, false);
        bf16_check(&c3, &refs, k, &format!("matmul_a_bt {shape}"));
        assert_eq!(bits(&c), bits(&c2), "{shape}");
        assert_eq!(bits(&c), bits(&c3), "{shape}");

        // Accumulation adds the product to what is there (here: the product again).
        kernels.matmul(&a, &b, &mut c, m, k, n, true);
        let doubled = (
            refs.0.iter().map(|v| 2.0 * v).collect(),
            refs.1.iter().map(|v| 2.0 * v).collect(),
            refs.2.iter().map(|v| 2.0 * v).collect(),
        );
        bf16_check(&c, &doubled, k, &format!("accumulated matmul {shape}"));
    }
}
