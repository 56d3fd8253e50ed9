//! The machine's tuned f32 GEMM rate, measured in the same run as a benchmark so that its
//! network rates can be stated as a fraction of what this CPU does: numpy's `matmul` (the
//! BLAS numpy links, OpenBLAS in the PyPI wheels, with its run-time picked kernel, e.g.
//! SkylakeX AVX-512) in a Python subprocess, one subprocess per thread count (the BLAS
//! reads its thread count from the environment when loaded).
//!
//! Never faked: without a Python that imports numpy the measurement is an error saying so,
//! and the benchmarks print that instead of a rate. Rates are the best of `reps` timed
//! products after one warm-up, in GFLOP/s (`2 m k n / s`).

use std::process::Command;

/// The shapes the benchmarks compare with: the networks' widest layer over 100,000 rows
/// (tall-skinny) and a square product (the BLAS's best case).
pub const SHAPES: [(usize, usize, usize); 2] = [(100_000, 256, 256), (2048, 2048, 2048)];

/// One measured rate.
#[derive(Clone, Debug)]
pub struct Rate {
    pub m: usize,
    pub k: usize,
    pub n: usize,
    pub threads: usize,
    pub gflops: f64,
}

/// The reference rates and what produced them.
#[derive(Clone, Debug)]
pub struct Reference {
    /// E.g. `numpy 2.3.5, scipy-openblas 0.3.30 (core SkylakeX)`.
    pub library: String,
    pub rates: Vec<Rate>,
}

impl Reference {
    /// The rate of `(m, k, n)` on `threads`, if measured.
    pub fn rate(&self, (m, k, n): (usize, usize, usize), threads: usize) -> Option<f64> {
        self.rates
            .iter()
            .find(|r| (r.m, r.k, r.n, r.threads) == (m, k, n, threads))
            .map(|r| r.gflops)
    }

    /// The tall-skinny rate (the networks' shape) on `threads`.
    pub fn tall_skinny(&self, threads: usize) -> Option<f64> {
        self.rate(SHAPES[0], threads)
    }
}

/// The Python side: prints `library ...` once and `rate m k n gflops` per shape.
const SCRIPT: &str = r#"
import sys, time, glob, os, ctypes
import numpy as np
lib = "numpy " + np.__version__
try:
    blas = np.__config__.CONFIG["Build Dependencies"]["blas"]
    lib += ", " + blas["name"] + " " + str(blas.get("version", ""))
except Exception:
    pass
for path in glob.glob(os.path.join(os.path.dirname(np.__file__), "..", "numpy.libs", "*openblas*")):
    try:
        so = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename64_", "openblas_get_corename"):
            if hasattr(so, name):
                f = getattr(so, name); f.restype = ctypes.c_char_p
                lib += " (core " + f().decode() + ")"
                break
    except Exception:
        pass
print("library", lib)
reps = int(sys.argv[1])
for shape in sys.argv[2:]:
    m, k, n = (int(v) for v in shape.split("x"))
    rng = np.random.default_rng(1)
    a = rng.uniform(-1, 1, (m, k)).astype(np.float32)
    b = rng.uniform(-1, 1, (k, n)).astype(np.float32)
    c = np.empty((m, n), dtype=np.float32)
    np.matmul(a, b, out=c)
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        np.matmul(a, b, out=c)
        best = min(best, time.perf_counter() - t0)
    print("rate", m, k, n, 2.0 * m * k * n / best / 1e9, flush=True)
"#;

/// Measures [`SHAPES`] on each of `threads` with `python` (a path or a name on `PATH`).
pub fn measure(python: &str, threads: &[usize], reps: usize) -> Result<Reference, String> {
    let mut library = String::new();
    let mut rates = Vec::new();
    for &t in threads {
        let mut cmd = Command::new(python);
        cmd.arg("-c").arg(SCRIPT).arg(reps.max(1).to_string());
        for (m, k, n) in SHAPES {
            cmd.arg(format!("{m}x{k}x{n}"));
        }
        for var in ["OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"] {
            cmd.env(var, t.to_string());
        }
        let out = cmd
            .output()
            .map_err(|e| format!("cannot run {python}: {e}"))?;
        if !out.status.success() {
            let err = String::from_utf8_lossy(&out.stderr);
            let last = err.lines().last().unwrap_or("no message");
            return Err(format!("{python} with numpy failed: {last}"));
        }
        for line in String::from_utf8_lossy(&out.stdout).lines() {
            if let Some(lib) = line.strip_prefix("library ") {
                library = lib.to_string();
            } else if let Some(rest) = line.strip_prefix("rate ") {
                let v: Vec<&str> = rest.split_whitespace().collect();
                let parsed = (|| -> Option<Rate> {
                    Some(Rate {
                        m: v.first()?.parse().ok()?,
                        k: v.get(1)?.parse().ok()?,
                        n: v.get(2)?.parse().ok()?,
                        threads: t,
                        gflops: v.get(3)?.parse().ok()?,
                    })
                })();
                rates.push(parsed.ok_or_else(|| format!("unreadable line from numpy: {line}"))?);
            }
        }
    }
    if rates.len() != SHAPES.len() * threads.len() {
        return Err(format!(
            "numpy reported {} of {} rates",
            rates.len(),
            SHAPES.len() * threads.len()
        ));
    }
    Ok(Reference { library, rates })
}
