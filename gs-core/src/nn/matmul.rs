//! Single-threaded row-major f32 matrix products, and [`Products`]: the networks' choice
//! between these and the bfloat16 kernels of `amx.rs` (AMX tiles) and `bf16.rs` (AVX-512
//! BF16), [`Bf16Kernel`].
//!
//! The f32 products run on the AVX-512 kernels of `avx512.rs` where the CPU has AVX-512F,
//! else on the AVX2 kernels of `avx2.rs` where it has AVX2 and FMA, else on the portable
//! `gemm` crate ([`F32Kernel`]); each is detected at run time, never by compile flags, so
//! the same binary runs on every x86 CPU. `avx512` and `avx2` sum every element in the same
//! order (one `fma` chain in increasing reduction index), so they give the same bits: an
//! AVX-512 machine and an AVX2-only one train alike. The `gemm` crate sums in another
//! order, so its results differ from theirs in the last bits; each kernel is
//! bit-reproducible on its own.
//!
//! Invariants: every matrix is a dense row-major slice whose length is checked against its
//! shape before the unsafe call (a mismatch is a bug in this crate, so it panics here rather
//! than reading out of bounds). Each call runs on the calling thread only
//! (`Parallelism::None`): callers parallelise over fixed row blocks, which keeps results
//! independent of the thread count. For fixed shapes, strides and CPU the kernel is fixed,
//! so results are bit-reproducible.
//!
//! `gemm` was chosen over `matrixmultiply` by measurement on the target machine (see
//! `examples/mlp_bench.rs`): similar on the 256-wide shapes, several times faster on the
//! narrow shapes of the shadow network (55 x 32, 32 x 32). It is now the fallback for CPUs
//! without AVX2 and FMA; `mlp_bench --kernel` and `kernel_ab` compare the kernels.

use gemm::Parallelism;

use super::amx::AmxKernels;
use super::avx2::Avx2Kernels;
use super::avx512::Avx512Kernels;
use super::bf16::Bf16Kernels;
use super::error::NnError;

/// Arithmetic of the networks' matrix products.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MatmulPrecision {
    /// f32 inputs, f32 accumulation ([`F32Kernel::detect`] picks the kernel).
    #[default]
    F32,
    /// Inputs rounded to bfloat16, f32 accumulation ([`Bf16Kernel::detect`] picks the
    /// kernel: AMX tiles, else AVX-512 BF16; a CPU with neither refuses it).
    Bf16,
}

impl MatmulPrecision {
    /// `Ok` when this CPU runs products of this precision; for `Bf16` without AMX or
    /// AVX-512 BF16 a configuration error naming the missing feature (never a silent
    /// fallback).
    pub fn check_supported(self) -> Result<(), NnError> {
        Products::new(self).map(|_| ())
    }
}

/// The kernel of the f32 products.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum F32Kernel {
    /// The `gemm` crate (AVX2/FMA or scalar, its own run-time choice): runs everywhere.
    Portable,
    /// `avx2.rs` (its value proves the CPU has AVX2 and FMA): the same bits as `Avx512`.
    Avx2(Avx2Kernels),
    /// `avx512.rs` (its value proves the CPU has AVX-512F).
    Avx512(Avx512Kernels),
}

impl F32Kernel {
    /// The names [`F32Kernel::named`] takes, in the order [`F32Kernel::detect`] prefers.
    pub const NAMES: [&'static str; 3] = ["avx512", "avx2", "gemm-crate"];

    /// The kernel this CPU runs by default: AVX-512 where present, else AVX2 with FMA, else
    /// the portable `gemm` crate.
    pub fn detect() -> Self {
        Avx512Kernels::detect()
            .map(Self::Avx512)
            .or_else(|| Avx2Kernels::detect().map(Self::Avx2))
            .unwrap_or(Self::Portable)
    }

    /// The kernel called `name` ([`F32Kernel::name`]), to force one (benchmarks), or why
    /// this CPU cannot run it.
    pub fn named(name: &str) -> Result<Self, String> {
        let missing = |feature: &str| format!("f32 kernel {name}: this CPU lacks {feature}");
        match name {
            "gemm-crate" => Ok(Self::Portable),
            "avx2" => Avx2Kernels::detect()
                .map(Self::Avx2)
                .ok_or_else(|| missing("avx2 or fma")),
            "avx512" => Avx512Kernels::detect()
                .map(Self::Avx512)
                .ok_or_else(|| missing("avx512f")),
            other => Err(format!(
                "f32 kernel {other:?}: expected one of {}",
                Self::NAMES.join(", ")
            )),
        }
    }

    /// [`F32Kernel::detect`]'s kernel, unless the environment variable [`KERNEL_ENV_VAR`]
    /// names another (`avx512`, `avx2` or `gemm-crate`: to compare kernels end to end, or to
    /// reproduce results made with the `gemm` crate's order). A name this CPU cannot run,
    /// or an unknown one, is a configuration error, never a silent fallback.
    pub fn from_env() -> Result<Self, NnError> {
        Self::from_setting(std::env::var(KERNEL_ENV_VAR).ok().as_deref())
    }

    /// [`F32Kernel::from_env`] for the variable's value (`None` or empty: unset).
    pub fn from_setting(setting: Option<&str>) -> Result<Self, NnError> {
        match setting {
            Some(name) if !name.is_empty() => {
                Self::named(name).map_err(|e| NnError::Config(format!("{KERNEL_ENV_VAR}: {e}")))
            }
            _ => Ok(Self::detect()),
        }
    }

    /// The name the benchmarks print.
    pub fn name(self) -> &'static str {
        match self {
            Self::Portable => "gemm-crate",
            Self::Avx2(_) => "avx2",
            Self::Avx512(_) => "avx512",
        }
    }
}

/// The environment variable that forces the f32 kernel ([`F32Kernel::from_env`]).
pub const KERNEL_ENV_VAR: &str = "GS_F32_KERNEL";

impl Default for F32Kernel {
    fn default() -> Self {
        Self::detect()
    }
}

/// The kernel of the bfloat16 products. The two sum the same bfloat16 products in
/// different orders, so their results differ in the last bits; each is bit-reproducible.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bf16Kernel {
    /// `amx.rs` (its value proves the CPU has AMX-BF16 and Linux granted the tiles).
    Amx(AmxKernels),
    /// `bf16.rs` (its value proves the CPU has AVX-512 BF16).
    Avx512Bf16(Bf16Kernels),
}

impl Bf16Kernel {
    /// The names [`Bf16Kernel::named`] takes, in the order [`Bf16Kernel::detect`] prefers.
    pub const NAMES: [&'static str; 2] = ["amx", "avx512bf16"];

    /// The kernel this CPU runs by default: AMX where present, else AVX-512 BF16, else
    /// the error of the missing feature.
    pub fn detect() -> Result<Self, NnError> {
        match AmxKernels::detect() {
            Ok(amx) => Ok(Self::Amx(amx)),
            Err(_) => Bf16Kernels::detect().map(Self::Avx512Bf16),
        }
    }

    /// The kernel called `name` ([`Bf16Kernel::name`]), or why this CPU cannot run it.
    pub fn named(name: &str) -> Result<Self, String> {
        let reason = |e: NnError| format!("bf16 kernel {name}: {e}");
        match name {
            "amx" => AmxKernels::detect().map(Self::Amx).map_err(reason),
            "avx512bf16" => Bf16Kernels::detect().map(Self::Avx512Bf16).map_err(reason),
            other => Err(format!(
                "bf16 kernel {other:?}: expected one of {}",
                Self::NAMES.join(", ")
            )),
        }
    }

    /// [`Bf16Kernel::detect`]'s kernel, unless [`BF16_KERNEL_ENV_VAR`] names one (`amx`
    /// or `avx512bf16`: to compare them, or to reproduce results of the other). A name
    /// this CPU cannot run, or an unknown one, is a configuration error.
    pub fn from_env() -> Result<Self, NnError> {
        Self::forced_by_env().unwrap_or_else(Self::detect)
    }

    /// [`Bf16Kernel::from_env`] for the variable's value (`None` or empty: unset).
    pub fn from_setting(setting: Option<&str>) -> Result<Self, NnError> {
        Self::forced(setting).unwrap_or_else(Self::detect)
    }

    /// The kernel [`BF16_KERNEL_ENV_VAR`] names, or why this CPU cannot run it; `None`
    /// when the variable is unset or empty (then [`Bf16Kernel::detect`] picks).
    pub fn forced_by_env() -> Option<Result<Self, NnError>> {
        Self::forced(std::env::var(BF16_KERNEL_ENV_VAR).ok().as_deref())
    }

    fn forced(setting: Option<&str>) -> Option<Result<Self, NnError>> {
        let name = setting.filter(|name| !name.is_empty())?;
        Some(Self::named(name).map_err(|e| NnError::Config(format!("{BF16_KERNEL_ENV_VAR}: {e}"))))
    }

    /// The name the benchmarks print.
    pub fn name(self) -> &'static str {
        match self {
            Self::Amx(_) => "amx",
            Self::Avx512Bf16(_) => "avx512bf16",
        }
    }
}

/// The environment variable that forces the bf16 kernel ([`Bf16Kernel::from_env`]).
pub const BF16_KERNEL_ENV_VAR: &str = "GS_BF16_KERNEL";

/// Checks both kernel variables (`GS_F32_KERNEL`; `GS_BF16_KERNEL` when set), so that a
/// binary stops at start on a kernel name this CPU cannot run, not at its first network.
/// An unset `GS_BF16_KERNEL` is no error on a CPU without bf16 kernels: only the bf16
/// precision needs one, and it reports its own error.
pub fn check_kernel_env() -> Result<(), NnError> {
    F32Kernel::from_env()?;
    Bf16Kernel::forced_by_env().transpose().map(|_| ())
}

/// The matrix products of one precision, checked against the CPU when chosen: the three
/// layouts the MLP uses, each single-threaded and deterministic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Products {
    /// `Some` for bfloat16 products (its existence proves the CPU runs them).
    bf16: Option<Bf16Kernel>,
    /// The f32 products' kernel (unused when `bf16` is set).
    f32_kernel: F32Kernel,
}

impl Products {
    /// Products of `precision`, or an error when the CPU lacks what it needs. f32 products
    /// take [`F32Kernel::from_env`]'s kernel (the CPU's default unless `GS_F32_KERNEL`
    /// names one), bf16 products [`Bf16Kernel::from_env`]'s (`GS_BF16_KERNEL`).
    pub fn new(precision: MatmulPrecision) -> Result<Self, NnError> {
        Ok(Self {
            bf16: match precision {
                MatmulPrecision::F32 => None,
                MatmulPrecision::Bf16 => Some(Bf16Kernel::from_env()?),
            },
            f32_kernel: F32Kernel::from_env()?,
        })
    }

    /// f32 products on `kernel` (benchmarks and tests compare kernels).
    pub fn f32_on(kernel: F32Kernel) -> Self {
        Self {
            bf16: None,
            f32_kernel: kernel,
        }
    }

    /// bfloat16 products on `kernel` (benchmarks and tests compare kernels).
    pub fn bf16_on(kernel: Bf16Kernel) -> Self {
        Self {
            bf16: Some(kernel),
            f32_kernel: F32Kernel::detect(),
        }
    }

    /// The kernel of the bfloat16 products (`None` for f32 products).
    pub fn bf16_kernel(self) -> Option<Bf16Kernel> {
        self.bf16
    }

    /// The kernel's name: [`F32Kernel::name`] or [`Bf16Kernel::name`].
    pub fn kernel_name(self) -> &'static str {
        match self.bf16 {
            Some(kernel) => kernel.name(),
            None => self.f32_kernel.name(),
        }
    }

    /// The kernel of the f32 products (`None` for bfloat16 products).
    pub fn f32_kernel(self) -> Option<F32Kernel> {
        self.bf16.is_none().then_some(self.f32_kernel)
    }

    pub fn precision(self) -> MatmulPrecision {
        match self.bf16 {
            None => MatmulPrecision::F32,
            Some(_) => MatmulPrecision::Bf16,
        }
    }

    /// [`matmul`] in this precision.
    pub fn matmul(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        m: usize,
        k: usize,
        n: usize,
        accumulate: bool,
    ) {
        self.run(Layout::AB, a, b, c, (m, k, n), accumulate);
    }

    /// [`matmul_at_b`] in this precision.
    pub fn matmul_at_b(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        k: usize,
        m: usize,
        n: usize,
        accumulate: bool,
    ) {
        self.run(Layout::AtB, a, b, c, (m, k, n), accumulate);
    }

    /// [`matmul_a_bt`] in this precision.
    pub fn matmul_a_bt(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        m: usize,
        k: usize,
        n: usize,
        accumulate: bool,
    ) {
        self.run(Layout::ABt, a, b, c, (m, k, n), accumulate);
    }

    /// `C (m x n)` from `A` and `B` stored as `layout` says, on this value's kernel.
    fn run(
        self,
        layout: Layout,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        (m, k, n): (usize, usize, usize),
        accumulate: bool,
    ) {
        let Some((a, b)) = layout.operands(a, b, c, (m, k, n), accumulate) else {
            return;
        };
        match (self.bf16, self.f32_kernel) {
            (Some(Bf16Kernel::Amx(kernel)), _) => kernel.product((m, k, n), a, b, c, accumulate),
            (Some(Bf16Kernel::Avx512Bf16(kernel)), _) => {
                kernel.product((m, k, n), a, b, c, accumulate);
            }
            (None, F32Kernel::Avx512(kernel)) => kernel.product((m, k, n), a, b, c, accumulate),
            (None, F32Kernel::Avx2(kernel)) => kernel.product((m, k, n), a, b, c, accumulate),
            (None, F32Kernel::Portable) => portable::product((m, k, n), a, b, c, accumulate),
        }
    }
}

/// One operand of a strided product: `X(r, s) = slice[r * .1 + s * .2]`.
pub(crate) type Strided<'a> = (&'a [f32], usize, usize);

/// How the operands of `C (m x n) = A (m x k) B (k x n)` are stored (all row-major).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Layout {
    /// `A` is `m x k`, `B` is `k x n` ([`matmul`]).
    AB,
    /// `A` is stored `k x m` ([`matmul_at_b`]).
    AtB,
    /// `B` is stored `n x k` ([`matmul_a_bt`]).
    ABt,
}

impl Layout {
    /// `A` and `B` as strided operands, after checking every slice against the shape (a
    /// mismatch is a bug in this crate: it panics). `None` when nothing is left to compute
    /// (`m` or `n` zero; `k` zero, with `C` zeroed unless accumulating).
    fn operands<'a>(
        self,
        a: &'a [f32],
        b: &'a [f32],
        c: &mut [f32],
        (m, k, n): (usize, usize, usize),
        accumulate: bool,
    ) -> Option<(Strided<'a>, Strided<'a>)> {
        assert_eq!((a.len(), b.len(), c.len()), (m * k, k * n, m * n));
        if m == 0 || n == 0 {
            return None;
        }
        if k == 0 {
            if !accumulate {
                c.fill(0.0);
            }
            return None;
        }
        Some(match self {
            Layout::AB => ((a, k, 1), (b, n, 1)),
            Layout::AtB => ((a, 1, m), (b, n, 1)),
            Layout::ABt => ((a, k, 1), (b, 1, k)),
        })
    }
}

/// The `gemm` crate's product on strided operands.
mod portable {
    use super::{Parallelism, Strided};

    /// `C = A B`, or `C += A B`; `m, n, k >= 1`, operands checked by `Layout::operands`.
    pub fn product(
        (m, k, n): (usize, usize, usize),
        (a, a_rs, a_cs): Strided,
        (b, b_rs, b_cs): Strided,
        c: &mut [f32],
        accumulate: bool,
    ) {
        // Re-checked here because the unsafe call below relies on it: the largest index
        // addressed in each operand lies inside its slice.
        assert!(a.len() > (m - 1) * a_rs + (k - 1) * a_cs);
        assert!(b.len() > (k - 1) * b_rs + (n - 1) * b_cs);
        assert_eq!(c.len(), m * n);
        // SAFETY: the asserts above bound every element addressed through the strides,
        // `(i, t) -> i * rs + t * cs` with `i < rows`, `t < cols`, by the slices' lengths.
        // `c` is borrowed mutably and cannot alias `a` or `b`.
        unsafe {
            gemm::gemm(
                m,
                n,
                k,
                c.as_mut_ptr(),
                1,
                n as isize,
                accumulate,
                a.as_ptr(),
                a_cs as isize,
                a_rs as isize,
                b.as_ptr(),
                b_cs as isize,
                b_rs as isize,
                1.0f32,
                1.0f32,
                false,
                false,
                false,
                Parallelism::None,
            );
        }
    }
}

/// `C (m x n) = A (m x k) * B (k x n)`, or `C += ...` when `accumulate`, on the fastest f32
/// kernel of this CPU ([`F32Kernel::detect`]).
pub fn matmul(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize, accumulate: bool) {
    Products::default().matmul(a, b, c, m, k, n, accumulate);
}

/// `C (m x n) = A^T * B` with `A` stored `k x m` and `B` stored `k x n`, or `C += ...`.
/// This is the weight-gradient product `X^T dZ` (reduction over the `k` batch rows).
pub fn matmul_at_b(
    a: &[f32],
    b: &[f32],
    c: &mut [f32],
    k: usize,
    m: usize,
    n: usize,
    accumulate: bool,
) {
    Products::default().matmul_at_b(a, b, c, k, m, n, accumulate);
}

/// `C (m x n) = A (m x k) * B^T` with `B` stored `n x k`, or `C += ...`.
/// This is the input-gradient product `dZ W^T`.
pub fn matmul_a_bt(
    a: &[f32],
    b: &[f32],
    c: &mut [f32],
    m: usize,
    k: usize,
    n: usize,
    accumulate: bool,
) {
    Products::default().matmul_a_bt(a, b, c, m, k, n, accumulate);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::kernel_tests::transpose;

    fn naive(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f64> {
        let mut c = vec![0.0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                c[i * n + j] = (0..k)
                    .map(|t| a[i * k + t] as f64 * b[t * n + j] as f64)
                    .sum();
            }
        }
        c
    }

    fn filled(len: usize, seed: u32) -> Vec<f32> {
        (0..len)
            .map(|i| {
                ((i as u32).wrapping_mul(2654435761).wrapping_add(seed) % 1000) as f32 / 500.0 - 1.0
            })
            .collect()
    }

    fn assert_close(got: &[f32], want: &[f64]) {
        for (g, w) in got.iter().zip(want) {
            assert!(
                (*g as f64 - w).abs() <= 1e-4 * (1.0 + w.abs()),
                "{g} vs {w}"
            );
        }
    }

    /// Every f32 kernel this CPU runs.
    fn kernels() -> Vec<Products> {
        F32Kernel::NAMES
            .iter()
            .filter_map(|name| F32Kernel::named(name).ok())
            .map(Products::f32_on)
            .collect()
    }

    #[test]
    fn products_match_naive_reference_in_all_three_layouts() {
        // Odd sizes exercise the kernels' edge handling.
        let (m, k, n) = (37, 19, 23);
        let a = filled(m * k, 1);
        let b = filled(k * n, 2);
        let want = naive(&a, &b, m, k, n);
        let a_t = transpose(&a, m, k); // stored k x m
        let b_t = transpose(&b, k, n); // stored n x k
        for products in kernels() {
            let mut c = vec![0.0; m * n];
            products.matmul(&a, &b, &mut c, m, k, n, false);
            assert_close(&c, &want);

            let mut c2 = vec![0.0; m * n];
            products.matmul_at_b(&a_t, &b, &mut c2, k, m, n, false);
            assert_close(&c2, &want);

            let mut c3 = vec![0.0; m * n];
            products.matmul_a_bt(&a, &b_t, &mut c3, m, k, n, false);
            assert_close(&c3, &want);

            // Accumulation adds to what is there.
            products.matmul(&a, &b, &mut c, m, k, n, true);
            let doubled: Vec<f64> = want.iter().map(|w| 2.0 * w).collect();
            assert_close(&c, &doubled);
        }
    }

    #[test]
    fn the_detected_kernel_is_the_fastest_present_and_the_default() {
        let detected = F32Kernel::detect();
        assert_eq!(Products::default().f32_kernel(), Some(detected));
        assert_eq!(
            Products::new(MatmulPrecision::F32).unwrap().f32_kernel(),
            Some(F32Kernel::from_env().unwrap())
        );
        assert_eq!(F32Kernel::from_setting(None), Ok(detected));
        assert_eq!(F32Kernel::from_setting(Some("")), Ok(detected));
        assert_eq!(
            F32Kernel::from_setting(Some("gemm-crate")),
            Ok(F32Kernel::Portable)
        );
        let unknown = F32Kernel::from_setting(Some("sse"))
            .unwrap_err()
            .to_string();
        assert!(
            unknown.contains("GS_F32_KERNEL") && unknown.contains("sse"),
            "{unknown}"
        );
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            let avx512 = has!("avx512f");
            let avx2 = has!("avx2") && has!("fma");
            assert_eq!(matches!(detected, F32Kernel::Avx512(_)), avx512);
            assert_eq!(matches!(detected, F32Kernel::Avx2(_)), avx2 && !avx512);
            assert_eq!(F32Kernel::named("avx2").is_ok(), avx2);
        }
        assert_eq!(F32Kernel::named(detected.name()), Ok(detected));
        assert_eq!(F32Kernel::named("gemm-crate"), Ok(F32Kernel::Portable));
        assert!(F32Kernel::named("sse").is_err());
    }

    #[test]
    fn the_bf16_kernel_is_amx_where_usable_and_follows_the_setting() {
        let amx = AmxKernels::detect().is_ok();
        let avx512bf16 = Bf16Kernels::detect().is_ok();
        let detected = Bf16Kernel::detect();
        assert_eq!(detected.is_ok(), amx || avx512bf16);
        if let Ok(kernel) = detected {
            assert_eq!(matches!(kernel, Bf16Kernel::Amx(_)), amx);
            assert_eq!(Bf16Kernel::named(kernel.name()), Ok(kernel));
            assert_eq!(Bf16Kernel::from_setting(None), Ok(kernel));
            assert_eq!(Bf16Kernel::from_setting(Some("")), Ok(kernel));
            assert_eq!(Products::bf16_on(kernel).kernel_name(), kernel.name());
            assert_eq!(Products::bf16_on(kernel).f32_kernel(), None);
        }
        assert_eq!(Bf16Kernel::named("amx").is_ok(), amx);
        assert_eq!(Bf16Kernel::named("avx512bf16").is_ok(), avx512bf16);
        let unknown = Bf16Kernel::from_setting(Some("fp8"))
            .unwrap_err()
            .to_string();
        assert!(
            unknown.contains("GS_BF16_KERNEL") && unknown.contains("fp8"),
            "{unknown}"
        );
        // f32 products name their f32 kernel.
        let f32_products = Products::f32_on(F32Kernel::Portable);
        assert_eq!(f32_products.kernel_name(), "gemm-crate");
        assert_eq!(f32_products.bf16_kernel(), None);
    }

    #[test]
    fn empty_reduction_gives_zero_or_leaves_accumulator() {
        for products in kernels() {
            let mut c = vec![5.0; 6];
            products.matmul(&[], &[], &mut c, 2, 0, 3, true);
            assert_eq!(c, vec![5.0; 6]);
            products.matmul(&[], &[], &mut c, 2, 0, 3, false);
            assert_eq!(c, vec![0.0; 6]);
        }
    }
}
