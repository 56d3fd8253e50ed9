//! Sixteen `f32::exp` at once for the Sun visibility walk, with the bits of the scalar
//! calls.
//!
//! The walk's alphas and weights come from `f32::exp`, which on Linux is glibc's `expf`.
//! Since glibc 2.28 that is one algorithm (from Arm's optimized-routines, `e_expf.c`): in
//! double precision, `k = round(x 32 / ln 2)`, `r = x 32 / ln 2 - k`, `2^(k/32)` from a
//! 32-entry table, a cubic in `r`, one rounding to f32 at the end; on x86-64 CPUs with FMA
//! glibc runs its FMA build (`__expf_fma`), whose multiply-adds are fused. [`Avx512Exp`]
//! does exactly those operations, in the same order and with the same constants, eight
//! doubles per register, so it returns the same bits wherever the scalar call is that
//! code. Lanes outside its range (`|x| >= 88`, NaN) take the scalar call.
//!
//! Why not trust that blindly: another C library (or a future glibc) may compute `expf`
//! otherwise. [`ExpLanes::detect`] therefore compares the vector code with `f32::exp` on
//! this machine, once per process, on a probe set covering the walk's range; on any
//! difference the walk keeps the scalar calls. Either way the walk's results are the bits
//! of `f32::exp`, as before this module existed.
//!
//! Invariant: [`ExpLanes::exp16`] equals `f32::exp` lane for lane, bit for bit, on every
//! lane whose bit is set in `live` (other lanes are unspecified).

/// How the walk takes its exponentials.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ExpLanes {
    /// `f32::exp` per live lane.
    Scalar,
    /// [`Avx512Exp`]; only constructed where the CPU has AVX-512F and the vector code
    /// matched `f32::exp` on the probe set.
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl ExpLanes {
    /// The vector build where the CPU has AVX-512F and it gives `f32::exp`'s bits here
    /// (checked once per process), else the scalar calls.
    pub(super) fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            static MATCHES: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
            let ok = *MATCHES.get_or_init(|| {
                if !std::arch::is_x86_feature_detected!("avx512f") {
                    return false;
                }
                let probes: Vec<f32> = probe_values().collect();
                probes.chunks(16).all(|chunk| {
                    let mut x = [0.0f32; 16];
                    x[..chunk.len()].copy_from_slice(chunk);
                    // SAFETY: the CPU has AVX-512F (checked just above).
                    let v = unsafe { avx512::exp16_array(&x, u16::MAX) };
                    x.iter()
                        .zip(&v)
                        .all(|(a, b)| a.exp().to_bits() == b.to_bits())
                })
            });
            if ok {
                return ExpLanes::Avx512;
            }
        }
        ExpLanes::Scalar
    }

    /// `exp` of the lanes of `x` whose bit is set in `live` (see the module docs).
    /// Call [`ExpLanes::Avx512`]'s only from code compiled with AVX-512F.
    #[inline(always)]
    pub(super) fn exp16(self, x: &[f32; 16], live: u16) -> [f32; 16] {
        match self {
            ExpLanes::Scalar => scalar_exp16(x, live),
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `Avx512` is only constructed where the CPU has AVX-512F (`detect`).
            ExpLanes::Avx512 => unsafe { avx512::exp16_array(x, live) },
        }
    }
}

/// `f32::exp` of the live lanes, 0 elsewhere.
#[inline(always)]
fn scalar_exp16(x: &[f32; 16], live: u16) -> [f32; 16] {
    let mut out = [0.0f32; 16];
    scalar_exp_lanes(x, live, &mut out);
    out
}

/// `out[l] = f32::exp(x[l])` for each lane `l` set in `lanes`; other lanes untouched.
#[inline(always)]
fn scalar_exp_lanes(x: &[f32; 16], lanes: u16, out: &mut [f32; 16]) {
    let mut m = lanes;
    while m != 0 {
        let l = m.trailing_zeros() as usize;
        m &= m - 1;
        out[l] = x[l].exp();
    }
}

/// Values the vector code must reproduce before it is used (about 0.2 M, a few ms once per
/// process): a grid over the range where the walk's exponentials matter ([-104, 2]), every
/// 65,537th bit pattern (both signs, any magnitude), and the edges of the vector range.
pub(super) fn probe_values() -> impl Iterator<Item = f32> {
    let grid = (0..=106_000).map(|i| -104.0 + i as f32 * 1e-3);
    let spread = (0..u32::MAX / 65_537).map(|i| f32::from_bits(i * 65_537));
    let edges = [
        0.0f32, -0.0, 1e-30, -1e-30, 87.999_99, -87.999_99, 88.0, -88.0, 88.7, -103.9,
    ];
    grid.chain(spread).chain(edges)
}

#[cfg(target_arch = "x86_64")]
pub(super) mod avx512 {
    //! The AVX-512F build of glibc's `__expf_fma` (see the parent module).

    use std::arch::x86_64::*;

    /// `2^(i/32)` as glibc's `__exp2f_data.tab` stores it: the bits of the double with the
    /// exponent field's `i << 47` taken out (added back with `k`'s bits).
    const TABLE: [u64; 32] = [
        0x3ff0000000000000,
        0x3fefd9b0d3158574,
        0x3fefb5586cf9890f,
        0x3fef9301d0125b51,
        0x3fef72b83c7d517b,
        0x3fef54873168b9aa,
        0x3fef387a6e756238,
        0x3fef1e9df51fdee1,
        0x3fef06fe0a31b715,
        0x3feef1a7373aa9cb,
        0x3feedea64c123422,
        0x3feece086061892d,
        0x3feebfdad5362a27,
        0x3feeb42b569d4f82,
        0x3feeab07dd485429,
        0x3feea47eb03a5585,
        0x3feea09e667f3bcd,
        0x3fee9f75e8ec5f74,
        0x3feea11473eb0187,
        0x3feea589994cce13,
        0x3feeace5422aa0db,
        0x3feeb737b0cdc5e5,
        0x3feec49182a3f090,
        0x3feed503b23e255d,
        0x3feee89f995ad3ad,
        0x3feeff76f2fb5e47,
        0x3fef199bdd85529c,
        0x3fef3720dcef9069,
        0x3fef5818dcfba487,
        0x3fef7c97337b9b5f,
        0x3fefa4afa2a490da,
        0x3fefd0765b6e4540,
    ];
    /// `32 / ln 2` (`invln2_scaled`).
    const INV_LN2_N: u64 = 0x40471547652b82fe;
    /// `1.5 * 2^52`: adding it rounds to an integer held in the low mantissa bits.
    const SHIFT: u64 = 0x4338000000000000;
    /// The cubic's coefficients (`poly_scaled`).
    const C0: u64 = 0x3ebc6af84b912394;
    const C1: u64 = 0x3f2ebfce50fac4f3;
    const C2: u64 = 0x3f962e42ff0c52d6;

    #[inline]
    #[target_feature(enable = "avx512f")]
    fn d(bits: u64) -> __m512d {
        _mm512_set1_pd(f64::from_bits(bits))
    }

    /// Eight lanes: glibc's operations one for one (`xd = x`; `kd = fma(InvLn2N, xd,
    /// SHIFT)`; `ki = bits(kd)`; `kd -= SHIFT`; `r = fma(InvLn2N, xd, -kd)`; `s = T[ki %
    /// 32] + (ki << 47)`; `z = fma(C0, r, C1)`; `y = fma(C2, r, 1)`; `y = fma(z, r * r, y)`;
    /// `y * s` rounded to f32).
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn exp8(x: __m256) -> __m256 {
        let xd = _mm512_cvtps_pd(x);
        let kd = _mm512_fmadd_pd(d(INV_LN2_N), xd, d(SHIFT));
        let ki = _mm512_castpd_si512(kd);
        let kd = _mm512_sub_pd(kd, d(SHIFT));
        let r = _mm512_fmsub_pd(d(INV_LN2_N), xd, kd);
        let idx = _mm512_and_si512(ki, _mm512_set1_epi64(31));
        // SAFETY: each load reads 8 of TABLE's 32 values (unaligned load).
        let tab = |i: usize| unsafe { _mm512_loadu_si512(TABLE.as_ptr().add(i).cast()) };
        // Indices 0-15 from the first pair of registers, 16-31 from the second.
        let lo = _mm512_permutex2var_epi64(tab(0), idx, tab(8));
        let hi = _mm512_permutex2var_epi64(tab(16), idx, tab(24));
        let upper = _mm512_test_epi64_mask(idx, _mm512_set1_epi64(16));
        let t = _mm512_mask_blend_epi64(upper, lo, hi);
        let s = _mm512_castsi512_pd(_mm512_add_epi64(t, _mm512_slli_epi64::<47>(ki)));
        let z = _mm512_fmadd_pd(d(C0), r, d(C1));
        let r2 = _mm512_mul_pd(r, r);
        let y = _mm512_fmadd_pd(d(C2), r, _mm512_set1_pd(1.0));
        let y = _mm512_fmadd_pd(z, r2, y);
        _mm512_cvtpd_ps(_mm512_mul_pd(y, s))
    }

    /// Sixteen lanes of [`exp8`]; live lanes outside its range (`|x| >= 88` or NaN, where
    /// glibc branches to its special cases) take `f32::exp`.
    ///
    /// # Safety
    /// The CPU must have AVX-512F.
    #[target_feature(enable = "avx512f")]
    pub(in crate::sunaware::sun_visibility) unsafe fn exp16_array(
        x: &[f32; 16],
        live: u16,
    ) -> [f32; 16] {
        // SAFETY: `x` holds 16 floats; unaligned loads and stores.
        let v = unsafe { _mm512_loadu_ps(x.as_ptr()) };
        let lo = exp8(_mm512_castps512_ps256(v));
        let hi = exp8(_mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(
            _mm512_castps_pd(v),
        )));
        let mut out = [0.0f32; 16];
        // SAFETY: `out` holds 16 floats.
        unsafe {
            _mm256_storeu_ps(out.as_mut_ptr(), lo);
            _mm256_storeu_ps(out.as_mut_ptr().add(8), hi);
        }
        // `!(|x| < 88)`: glibc's test on the top 12 bits (`abstop >= top12(88)`), and NaN.
        let abs = _mm512_abs_ps(v);
        let far = _mm512_cmp_ps_mask::<_CMP_NLT_UQ>(abs, _mm512_set1_ps(88.0)) & live;
        super::scalar_exp_lanes(x, far, &mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// Live lanes of `ExpLanes::exp16` against `f32::exp`, bit for bit.
    fn check(exp: ExpLanes, x: &[f32; 16], live: u16) {
        let got = exp.exp16(x, live);
        for l in 0..16 {
            if live >> l & 1 == 1 {
                assert_eq!(
                    got[l].to_bits(),
                    x[l].exp().to_bits(),
                    "{exp:?} lane {l}: exp({:e}) = {:e}, f32::exp {:e}",
                    x[l],
                    got[l],
                    x[l].exp()
                );
            }
        }
    }

    /// Every build the CPU allows (the scalar one always); a CPU without the vector build
    /// is a visible skip of its part (a failure under `GS_REQUIRE_AVX512=1`).
    fn builds() -> Vec<ExpLanes> {
        let mut b = vec![ExpLanes::Scalar];
        if ExpLanes::detect() != ExpLanes::Scalar {
            b.push(ExpLanes::detect());
        } else {
            crate::machine::skip_unless_required(
                "GS_REQUIRE_AVX512",
                "no AVX-512 expf build here: only the scalar calls are tested",
            );
        }
        b
    }

    #[test]
    fn the_vector_build_is_chosen_on_glibc_with_avx512() {
        #[cfg(all(target_arch = "x86_64", target_os = "linux", target_env = "gnu"))]
        if std::arch::is_x86_feature_detected!("avx512f") {
            assert_eq!(ExpLanes::detect(), ExpLanes::Avx512);
        } else {
            crate::machine::skip_unless_required("GS_REQUIRE_AVX512", "no avx512f");
        }
    }

    #[test]
    fn lanes_match_f32_exp_on_a_spread_of_bit_patterns_and_random_masks() {
        let mut rng = SplitMix64::new(11);
        for exp in builds() {
            // Every 1021st bit pattern (both signs, NaN and infinities included) and
            // uniform values over the range the walk uses, with random live masks.
            let mut x = [0.0f32; 16];
            let mut i = 0u64;
            while i < u32::MAX as u64 {
                for (l, v) in x.iter_mut().enumerate() {
                    *v = f32::from_bits((i + l as u64 * 1021) as u32);
                }
                check(exp, &x, (rng.next_u64() as u16) | 1);
                i += 16 * 1021;
            }
            for _ in 0..20_000 {
                for v in x.iter_mut() {
                    *v = rng.uniform(-110.0, 90.0);
                }
                check(exp, &x, rng.next_u64() as u16);
            }
        }
    }

    #[test]
    fn edges_of_the_vector_range_and_special_values_match() {
        let specials = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            88.0,
            -88.0,
            f32::from_bits(88.0f32.to_bits() - 1),
            f32::from_bits((-88.0f32).to_bits() - 1),
            88.72284,
            88.72285,
            -103.278_93,
            -103.972_08,
            -104.0,
            0.0,
            -0.0,
            f32::MIN_POSITIVE / 2.0,
            -1e-45,
        ];
        for exp in builds() {
            check(exp, &specials, u16::MAX);
            // The same values in every lane position, beside ordinary ones.
            for shift in 0..16 {
                let x: [f32; 16] = std::array::from_fn(|l| {
                    if l == shift {
                        specials[l]
                    } else {
                        -(l as f32) * 0.37
                    }
                });
                check(exp, &x, u16::MAX);
                check(exp, &x, 1 << shift);
            }
        }
    }

    #[test]
    fn dead_lanes_are_left_alone_by_the_scalar_build() {
        let x: [f32; 16] = std::array::from_fn(|l| l as f32 * 0.25);
        let got = ExpLanes::Scalar.exp16(&x, 0b1010_0000_0000_0101);
        for (l, v) in got.iter().enumerate() {
            if 0b1010_0000_0000_0101u16 >> l & 1 == 0 {
                assert_eq!(*v, 0.0);
            }
        }
    }

    /// Every f32 against `f32::exp` (about a minute; run by hand after touching the
    /// constants or the operations: `cargo test --release -p gs-core exhaustive --
    /// --ignored`).
    #[test]
    #[ignore]
    fn exhaustive_every_f32_matches() {
        let exp = ExpLanes::detect();
        let mut x = [0.0f32; 16];
        for hi in 0..(1u64 << 28) {
            for (l, v) in x.iter_mut().enumerate() {
                *v = f32::from_bits((hi * 16 + l as u64) as u32);
            }
            check(exp, &x, u16::MAX);
        }
    }
}
