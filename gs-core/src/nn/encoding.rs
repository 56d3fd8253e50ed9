//! NeRF positional encoding `gamma_L` and its derivative.
//!
//! For a vector `p` of `D` components and `L` frequencies the output has `D * 2L` values,
//! component-major, then frequency, then sine before cosine (the paper's Eq. for
//! `gamma_L(p)` applied to each component in turn):
//!
//! `[sin(2^0 pi p_0), cos(2^0 pi p_0), ..., sin(2^{L-1} pi p_0), cos(2^{L-1} pi p_0),
//!   sin(2^0 pi p_1), ...]`
//!
//! i.e. `out[c * 2L + 2k] = sin(2^k pi p_c)` and `out[c * 2L + 2k + 1] = cos(2^k pi p_c)`.
//! The raw `p` is not appended (the paper's definition has only the sinusoids).
//! The lowest frequency has period 2, so inputs should lie in a range shorter than 2
//! (unit vectors in [-1, 1] alias only at the two poles of each axis, which is harmless).
//!
//! Sines and cosines come from [`sin_cos_pi`], not from libm: each argument `2^k p` is
//! formed exactly (a power-of-two scale), reduced exactly to a quarter turn and evaluated
//! by two short polynomials in lanes of [`LANES`] values, so a row of the encoding
//! vectorises (plain SSE2 and AVX builds give the same bits: Rust never fuses a multiply
//! and an add). Every value is within [`SIN_COS_PI_MAX_ERROR`] of the exact
//! `sin(2^k pi p)` / `cos(2^k pi p)` for every `k` (the error does not grow with `k`; libm
//! on the rounded product `(2^k pi) * p` was off by up to `|2^k pi p| * 2^-24`), and
//! exact (0, +-1) at multiples of `1/2`.

use super::error::{check_finite, check_len, NnError};

/// Most frequencies accepted: `2^15 pi` already resolves 1e-4 of the input range.
pub const MAX_FREQUENCIES: usize = 16;

/// Values per call of the lane kernel of [`sin_cos_pi`].
pub const LANES: usize = 16;

/// Largest distance of [`sin_cos_pi`]'s results from `sin(pi x)`, `cos(pi x)` evaluated
/// in f64 on the same (exact) `x`: 2^-23 (f32 rounding of results in [-1, 1] alone is
/// 2^-25; polynomial error ~1e-9; the rest is the f32 Horner steps).
pub const SIN_COS_PI_MAX_ERROR: f32 = 1.0 / 8_388_608.0;

/// `1.5 * 2^23`: adding and subtracting it rounds any `|v| < 2^22` to the nearest integer
/// (ties to even), and the sum's low mantissa bits are that integer modulo 4.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// `|x|` from which the magic-number reduction of `2x` is not exact: those lanes (in
/// practice never: `x = 2^k p` with `|p| <= 1` stays below `2^16`) take the f64 path.
const FAST_REDUCE_LIMIT: f32 = 2_097_152.0;

/// `sin(pi r) / r` on `r in [-1/4, 1/4]` as a polynomial in `r^2` (Chebyshev fit, error
/// 1e-8 of the f64 function; coefficients are the fit rounded to f32).
const SIN_POLY: [f32; 4] = [std::f32::consts::PI, -5.167_708, 2.549_767, -0.589_075_1];

/// `cos(pi r)` on `r in [-1/4, 1/4]` as a polynomial in `r^2` (fit error 5e-11).
const COS_POLY: [f32; 5] = [1.0, -4.934_802, 4.058_707, -1.335_044_5, 0.231_328_79];

/// `sin(pi x)` and `cos(pi x)` of each of [`LANES`] values (the lane loop vectorises).
/// `2x` rounds to the nearest integer `n` (a quarter-turn count), `r = x - n/2` is exact
/// and in `[-1/4, 1/4]`, the polynomials give `sin(pi r)`, `cos(pi r)`, and `n mod 4`
/// swaps and negates them. Lanes with `|x| >= 2^21` (or non-finite: NaN comes out) are
/// redone in f64 after exact reduction modulo 2.
#[inline(always)]
fn sin_cos_pi_lanes(x: &[f32; LANES], sin: &mut [f32; LANES], cos: &mut [f32; LANES]) {
    let mut slow_lanes = 0u32;
    for i in 0..LANES {
        let shifted = 2.0 * x[i] + ROUND_MAGIC;
        let quarter_turns = shifted - ROUND_MAGIC;
        let quadrant = shifted.to_bits();
        let r = x[i] - 0.5 * quarter_turns;
        let z = r * r;
        let s = r * (SIN_POLY[0] + z * (SIN_POLY[1] + z * (SIN_POLY[2] + z * SIN_POLY[3])));
        let c = COS_POLY[0]
            + z * (COS_POLY[1] + z * (COS_POLY[2] + z * (COS_POLY[3] + z * COS_POLY[4])));
        // Quadrant 1 and 3 swap sine and cosine; 2 and 3 negate the sine, 1 and 2 the
        // cosine (sin(t + q pi/2), cos(t + q pi/2)).
        let swap = 0u32.wrapping_sub(quadrant & 1);
        let (s_bits, c_bits) = (s.to_bits(), c.to_bits());
        let sin_bits = (s_bits & !swap) | (c_bits & swap);
        let cos_bits = (c_bits & !swap) | (s_bits & swap);
        sin[i] = f32::from_bits(sin_bits ^ ((quadrant & 2) << 30));
        cos[i] = f32::from_bits(cos_bits ^ (((quadrant ^ (quadrant >> 1)) & 1) << 31));
        // NaN fails the comparison too.
        slow_lanes |= u32::from(x[i].abs() < FAST_REDUCE_LIMIT) ^ 1;
    }
    if slow_lanes != 0 {
        for i in 0..LANES {
            if x[i].abs() < FAST_REDUCE_LIMIT {
                continue;
            }
            // fmod is exact; pi * (x mod 2) in f64 is far below f32 resolution.
            let turns = x[i] as f64 % 2.0;
            let (s, c) = (std::f64::consts::PI * turns).sin_cos();
            sin[i] = s as f32;
            cos[i] = c as f32;
        }
    }
}

/// `sin(pi x)` and `cos(pi x)` for every value of `x` into `sin` and `cos` (same lengths),
/// within [`SIN_COS_PI_MAX_ERROR`] of the exact values; the same bits for a value wherever
/// it sits in the slice, and on every instruction set (AVX-512 or AVX2 when the CPU has
/// them: the same operations in wider registers). Panics on mismatched lengths (a bug in
/// the caller).
pub fn sin_cos_pi(x: &[f32], sin: &mut [f32], cos: &mut [f32]) {
    assert!(x.len() == sin.len() && x.len() == cos.len());
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            unsafe { sin_cos_pi_avx512(x, sin, cos) };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            unsafe { sin_cos_pi_avx2(x, sin, cos) };
            return;
        }
    }
    sin_cos_pi_body(x, sin, cos);
}

/// [`sin_cos_pi_body`] compiled for AVX-512 (same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn sin_cos_pi_avx512(x: &[f32], sin: &mut [f32], cos: &mut [f32]) {
    sin_cos_pi_body(x, sin, cos);
}

/// [`sin_cos_pi_body`] compiled for AVX2 (same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn sin_cos_pi_avx2(x: &[f32], sin: &mut [f32], cos: &mut [f32]) {
    sin_cos_pi_body(x, sin, cos);
}

/// [`sin_cos_pi`] on the build's own instruction set.
#[inline(always)]
fn sin_cos_pi_body(x: &[f32], sin: &mut [f32], cos: &mut [f32]) {
    let whole = x.len() / LANES * LANES;
    let (x_whole, x_rest) = x.split_at(whole);
    let (sin_whole, sin_rest) = sin.split_at_mut(whole);
    let (cos_whole, cos_rest) = cos.split_at_mut(whole);
    for ((xs, ss), cs) in x_whole
        .chunks_exact(LANES)
        .zip(sin_whole.chunks_exact_mut(LANES))
        .zip(cos_whole.chunks_exact_mut(LANES))
    {
        // Whole chunks in place: no copies through the stack (a copy's narrow stores
        // then a wide load stall the store forwarding).
        if let (Ok(xs), Ok(ss), Ok(cs)) = (
            <&[f32; LANES]>::try_from(xs),
            <&mut [f32; LANES]>::try_from(ss),
            <&mut [f32; LANES]>::try_from(cs),
        ) {
            sin_cos_pi_lanes(xs, ss, cs);
        }
    }
    if !x_rest.is_empty() {
        let mut lanes = [0.0f32; LANES];
        let (mut s, mut c) = ([0.0f32; LANES], [0.0f32; LANES]);
        lanes[..x_rest.len()].copy_from_slice(x_rest);
        sin_cos_pi_lanes(&lanes, &mut s, &mut c);
        sin_rest.copy_from_slice(&s[..x_rest.len()]);
        cos_rest.copy_from_slice(&c[..x_rest.len()]);
    }
}

/// The encoding `gamma_L` with a fixed number of frequencies `L`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PositionalEncoding {
    num_frequencies: usize,
}

impl Default for PositionalEncoding {
    /// `L = 4`, as in DESIGN.md.
    fn default() -> Self {
        Self { num_frequencies: 4 }
    }
}

impl PositionalEncoding {
    /// `L` in `1..=MAX_FREQUENCIES`.
    pub fn new(num_frequencies: usize) -> Result<Self, NnError> {
        if (1..=MAX_FREQUENCIES).contains(&num_frequencies) {
            Ok(Self { num_frequencies })
        } else {
            Err(NnError::Config(format!(
                "positional encoding needs 1..={MAX_FREQUENCIES} frequencies, got {num_frequencies}"
            )))
        }
    }

    pub fn num_frequencies(&self) -> usize {
        self.num_frequencies
    }

    /// Output width for an input of `dim` components: `dim * 2L`.
    pub fn width(&self, dim: usize) -> usize {
        dim * 2 * self.num_frequencies
    }

    /// Angular frequency of band `k`: `2^k pi`.
    fn omega(k: usize) -> f32 {
        std::f32::consts::PI * (1u32 << k) as f32
    }

    /// Writes `gamma_L(p)` into `out` (`out.len() == width(p.len())`). Unchecked for speed:
    /// the callers in this module validate finiteness once per batch.
    pub(crate) fn encode_unchecked(&self, p: &[f32], out: &mut [f32]) {
        let l = self.num_frequencies;
        // Arguments 2^k p_c (exact) in output order, LANES at a time.
        let mut args = [0.0f32; LANES];
        let (mut s, mut c) = ([0.0f32; LANES], [0.0f32; LANES]);
        let mut filled = 0;
        let mut written = 0;
        let mut flush = |args: &[f32; LANES], filled: usize, written: &mut usize| {
            sin_cos_pi_lanes(args, &mut s, &mut c);
            let dst = &mut out[2 * *written..2 * (*written + filled)];
            for (pair, (&sv, &cv)) in dst.chunks_exact_mut(2).zip(s.iter().zip(&c)) {
                pair[0] = sv;
                pair[1] = cv;
            }
            *written += filled;
        };
        for &pc in p {
            for k in 0..l {
                args[filled] = pc * (1u32 << k) as f32;
                filled += 1;
                if filled == LANES {
                    flush(&args, filled, &mut written);
                    filled = 0;
                }
            }
        }
        if filled > 0 {
            args[filled..].fill(0.0);
            flush(&args, filled, &mut written);
        }
    }

    /// Writes `gamma_L` of each of the points (`points`, `n x dim` flat) into rows of
    /// `out`: point `i`'s code goes to `out[i * stride + offset..][..width(dim)]`. The same
    /// bits as [`Self::encode_unchecked`] per point; faster for many points (whole vectors
    /// of arguments per kernel pass). Unchecked like it.
    pub(crate) fn encode_rows_unchecked(
        &self,
        points: &[f32],
        dim: usize,
        out: &mut [f32],
        stride: usize,
        offset: usize,
    ) {
        const PASS: usize = 64 * LANES;
        let l = self.num_frequencies;
        let per_point = dim * l;
        let width = 2 * per_point;
        if per_point == 0 {
            return;
        }
        let points_per_pass = PASS / per_point;
        if points_per_pass == 0 {
            for (i, p) in points.chunks_exact(dim).enumerate() {
                self.encode_unchecked(p, &mut out[i * stride + offset..][..width]);
            }
            return;
        }
        let scales: [f32; MAX_FREQUENCIES] = std::array::from_fn(|k| (1u32 << k) as f32);
        let mut args = [0.0f32; PASS];
        let (mut sin, mut cos) = ([0.0f32; PASS], [0.0f32; PASS]);
        for (pass, pass_points) in points.chunks(points_per_pass * dim).enumerate() {
            let n = pass_points.len() / dim;
            for (arg_row, &pc) in args.chunks_exact_mut(l).zip(pass_points) {
                for (a, &scale) in arg_row.iter_mut().zip(&scales) {
                    *a = pc * scale;
                }
            }
            let used = n * per_point;
            sin_cos_pi(&args[..used], &mut sin[..used], &mut cos[..used]);
            let first_row = pass * points_per_pass;
            for i in 0..n {
                let dst = &mut out[(first_row + i) * stride + offset..][..width];
                let (s, c) = (
                    &sin[i * per_point..(i + 1) * per_point],
                    &cos[i * per_point..(i + 1) * per_point],
                );
                for (pair, (&sv, &cv)) in dst.chunks_exact_mut(2).zip(s.iter().zip(c)) {
                    pair[0] = sv;
                    pair[1] = cv;
                }
            }
        }
    }

    /// Writes `gamma_L(p)` into `out`, checking sizes and finiteness.
    pub fn encode(&self, p: &[f32], out: &mut [f32]) -> Result<(), NnError> {
        check_len("encoding output", out.len(), self.width(p.len()))?;
        check_finite("encoding input", p)?;
        self.encode_unchecked(p, out);
        Ok(())
    }

    /// Adds `d_p += (d gamma / d p)^T d_out` (chain rule through the encoding). The same
    /// bits as [`Self::backward_from_code`] on this encoding's output for `p`.
    pub(crate) fn backward_unchecked(&self, p: &[f32], d_out: &[f32], d_p: &mut [f32]) {
        const GROUP: usize = 3;
        let two_l = 2 * self.num_frequencies;
        let mut code = [0.0f32; GROUP * 2 * MAX_FREQUENCIES];
        for ((p, d_out), d_p) in p
            .chunks(GROUP)
            .zip(d_out.chunks(GROUP * two_l))
            .zip(d_p.chunks_mut(GROUP))
        {
            let code = &mut code[..p.len() * two_l];
            self.encode_unchecked(p, code);
            self.backward_from_code(code, d_out, d_p);
        }
    }

    /// [`Self::backward_unchecked`] with the sines and cosines read from `code`, the output
    /// of [`Self::encode_unchecked`] for the same `p` (the input assembly keeps it). Same
    /// bits as recomputing them: the same arithmetic on the same values.
    pub(crate) fn backward_from_code(&self, code: &[f32], d_out: &[f32], d_p: &mut [f32]) {
        let two_l = 2 * self.num_frequencies;
        for (c, dpc) in d_p.iter_mut().enumerate() {
            let row = &d_out[c * two_l..(c + 1) * two_l];
            let sin_cos = &code[c * two_l..(c + 1) * two_l];
            let mut acc = 0.0f32;
            for k in 0..self.num_frequencies {
                let w = Self::omega(k);
                let (s, co) = (sin_cos[2 * k], sin_cos[2 * k + 1]);
                acc += w * (co * row[2 * k] - s * row[2 * k + 1]);
            }
            *dpc += acc;
        }
    }

    /// Adds the encoding's vector-Jacobian product to `d_p`, checking sizes and finiteness.
    pub fn backward(&self, p: &[f32], d_out: &[f32], d_p: &mut [f32]) -> Result<(), NnError> {
        check_len("encoding gradient output", d_out.len(), self.width(p.len()))?;
        check_len("encoding input gradient", d_p.len(), p.len())?;
        check_finite("encoding input", p)?;
        check_finite("encoding output gradient", d_out)?;
        self.backward_unchecked(p, d_out, d_p);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// Largest distance of `sin_cos_pi` from f64 over `xs` (each `x` exact in f32).
    fn worst_error(xs: &[f32]) -> f64 {
        let (mut s, mut c) = (vec![0.0f32; xs.len()], vec![0.0f32; xs.len()]);
        sin_cos_pi(xs, &mut s, &mut c);
        let mut worst = 0.0f64;
        for ((&x, &sv), &cv) in xs.iter().zip(&s).zip(&c) {
            let (s64, c64) = (std::f64::consts::PI * (x as f64 % 2.0)).sin_cos();
            worst = worst
                .max((sv as f64 - s64).abs())
                .max((cv as f64 - c64).abs());
        }
        worst
    }

    #[test]
    fn sin_cos_pi_is_within_its_bound_of_f64() {
        // Every f32 step of 2^-20 over two full turns, and every value in [0, 1/4] near
        // zero where the sine is tiny.
        let dense: Vec<f32> = (-(4 << 20)..=(4 << 20))
            .map(|i| i as f32 / (1 << 21) as f32)
            .collect();
        let near_zero: Vec<f32> = (0..1 << 20).map(|i| i as f32 * 1e-7).collect();
        // The encoding's arguments 2^k p for every k up to MAX_FREQUENCIES - 1, p in [-2, 2].
        let mut rng = SplitMix64::new(5);
        let scaled: Vec<f32> = (0..200_000)
            .map(|i| rng.uniform(-2.0, 2.0) * (1u32 << (i % MAX_FREQUENCIES)) as f32)
            .collect();
        // Around and beyond the fast reduction's limit (the f64 path).
        let large: Vec<f32> = (0..20_000)
            .map(|i| {
                let v = FAST_REDUCE_LIMIT * (0.5 + rng.next_f32() * 4.0);
                let v = if i % 3 == 0 { v * 1e6 } else { v };
                if i % 2 == 0 {
                    v
                } else {
                    -v
                }
            })
            .collect();
        let bound = SIN_COS_PI_MAX_ERROR as f64;
        for (name, xs) in [
            ("dense", &dense),
            ("near zero", &near_zero),
            ("scaled", &scaled),
            ("large", &large),
        ] {
            let worst = worst_error(xs);
            eprintln!("sin_cos_pi {name}: worst error {worst:.3e} (bound {bound:.3e})");
            assert!(worst <= bound, "{name}: {worst:e} > {bound:e}");
        }
    }

    #[test]
    fn sin_cos_pi_is_exact_at_multiples_of_a_half() {
        let xs: Vec<f32> = (-40..=40).map(|i| i as f32 * 0.5).collect();
        let (mut s, mut c) = (vec![0.0f32; xs.len()], vec![0.0f32; xs.len()]);
        sin_cos_pi(&xs, &mut s, &mut c);
        for ((&x, &sv), &cv) in xs.iter().zip(&s).zip(&c) {
            let quarter = ((2.0 * x) as i32).rem_euclid(4);
            let want = [(0.0, 1.0), (1.0, 0.0), (0.0, -1.0), (-1.0, 0.0)][quarter as usize];
            assert_eq!((sv, cv), want, "x = {x}");
        }
    }

    #[test]
    fn results_do_not_depend_on_the_lane_or_the_chunk() {
        let mut rng = SplitMix64::new(9);
        let xs: Vec<f32> = (0..3 * LANES + 5)
            .map(|_| rng.uniform(-40.0, 40.0))
            .collect();
        let (mut s, mut c) = (vec![0.0f32; xs.len()], vec![0.0f32; xs.len()]);
        sin_cos_pi(&xs, &mut s, &mut c);
        for (i, &x) in xs.iter().enumerate() {
            let (mut s1, mut c1) = ([0.0f32], [0.0f32]);
            sin_cos_pi(&[x], &mut s1, &mut c1);
            assert_eq!(
                (s[i].to_bits(), c[i].to_bits()),
                (s1[0].to_bits(), c1[0].to_bits())
            );
        }
        // Offset by one: every value moves to another lane.
        let (mut s2, mut c2) = (vec![0.0f32; xs.len() - 1], vec![0.0f32; xs.len() - 1]);
        sin_cos_pi(&xs[1..], &mut s2, &mut c2);
        assert_eq!(s[1..], s2[..]);
        assert_eq!(c[1..], c2[..]);
    }

    #[test]
    fn every_band_is_within_the_bound_for_sixteen_frequencies() {
        let enc = PositionalEncoding::new(MAX_FREQUENCIES).unwrap();
        let mut rng = SplitMix64::new(13);
        let mut worst = 0.0f64;
        for _ in 0..2000 {
            let p = [rng.uniform(-1.0, 1.0), rng.uniform(-0.5, 0.5), rng.normal()];
            let mut out = vec![0.0; enc.width(3)];
            enc.encode(&p, &mut out).unwrap();
            for (c, &pc) in p.iter().enumerate() {
                for k in 0..MAX_FREQUENCIES {
                    // 2^k p is exact in f64; reduce modulo 2 before the f64 sin/cos.
                    let turns = (pc as f64 * (1u64 << k) as f64) % 2.0;
                    let (s64, c64) = (std::f64::consts::PI * turns).sin_cos();
                    let i = c * 2 * MAX_FREQUENCIES + 2 * k;
                    worst = worst
                        .max((out[i] as f64 - s64).abs())
                        .max((out[i + 1] as f64 - c64).abs());
                }
            }
        }
        assert!(worst <= SIN_COS_PI_MAX_ERROR as f64, "{worst:e}");
    }

    #[test]
    fn backward_from_the_code_gives_the_same_bits_as_recomputing() {
        let enc = PositionalEncoding::new(5).unwrap();
        let mut rng = SplitMix64::new(17);
        for dim in [1, 3, 4, 7] {
            let p: Vec<f32> = (0..dim).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let d_out: Vec<f32> = (0..enc.width(dim)).map(|_| rng.normal()).collect();
            let mut code = vec![0.0; enc.width(dim)];
            enc.encode(&p, &mut code).unwrap();
            let (mut a, mut b) = (vec![0.5f32; dim], vec![0.5f32; dim]);
            enc.backward(&p, &d_out, &mut a).unwrap();
            enc.backward_from_code(&code, &d_out, &mut b);
            assert_eq!(a, b);
            assert!(a.iter().all(|v| *v != 0.5));
        }
    }

    #[test]
    fn layout_is_component_major_then_frequency_then_sin_cos() {
        let enc = PositionalEncoding::new(3).unwrap();
        let p = [0.1f32, -0.7];
        let mut out = vec![0.0; enc.width(2)];
        enc.encode(&p, &mut out).unwrap();
        for (c, &pc) in p.iter().enumerate() {
            for k in 0..3 {
                let arg = std::f64::consts::PI * (1u32 << k) as f64 * pc as f64;
                assert!((out[c * 6 + 2 * k] as f64 - arg.sin()).abs() < 1e-6);
                assert!((out[c * 6 + 2 * k + 1] as f64 - arg.cos()).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn backward_matches_central_differences() {
        let enc = PositionalEncoding::new(4).unwrap();
        let p = [0.31f32, -0.52, 0.83];
        let d_out: Vec<f32> = (0..enc.width(3))
            .map(|i| ((i * 7 % 11) as f32 - 5.0) / 5.0)
            .collect();
        let mut d_p = [0.0f32; 3];
        enc.backward(&p, &d_out, &mut d_p).unwrap();
        // f64 reference of the scalar objective sum(d_out * gamma(p)).
        let objective = |q: &[f64]| -> f64 {
            let mut total = 0.0;
            for (c, &qc) in q.iter().enumerate() {
                for k in 0..4 {
                    let arg = std::f64::consts::PI * (1u32 << k) as f64 * qc;
                    total += d_out[c * 8 + 2 * k] as f64 * arg.sin()
                        + d_out[c * 8 + 2 * k + 1] as f64 * arg.cos();
                }
            }
            total
        };
        let h = 1e-6;
        for c in 0..3 {
            let mut plus: Vec<f64> = p.iter().map(|&v| v as f64).collect();
            let mut minus = plus.clone();
            plus[c] += h;
            minus[c] -= h;
            let numeric = (objective(&plus) - objective(&minus)) / (2.0 * h);
            assert!(
                (d_p[c] as f64 - numeric).abs() <= 1e-4 * (1.0 + numeric.abs()),
                "component {c}: analytic {} numeric {numeric}",
                d_p[c]
            );
        }
    }

    #[test]
    fn bad_sizes_and_nan_are_errors() {
        assert!(PositionalEncoding::new(0).is_err());
        assert!(PositionalEncoding::new(MAX_FREQUENCIES + 1).is_err());
        let enc = PositionalEncoding::default();
        let mut out = vec![0.0; 5];
        assert!(matches!(
            enc.encode(&[0.0; 3], &mut out),
            Err(NnError::Shape { .. })
        ));
        let mut out = vec![0.0; enc.width(3)];
        assert_eq!(
            enc.encode(&[0.0, f32::NAN, 0.0], &mut out),
            Err(NnError::NonFinite {
                what: "encoding input",
                index: 1
            })
        );
    }
}
