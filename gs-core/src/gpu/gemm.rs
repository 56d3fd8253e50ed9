//! Tiled GEMM on the GPU for the MLP products (forward `X W`, weight gradient `X^T dZ`,
//! input gradient `dZ W^T`), the same three shapes as `crate::nn::matmul`.
//!
//! Invariants: matrices are dense row-major slices whose lengths are checked against
//! their shapes ([`GpuError::Invalid`] otherwise); transposes are strides, never copies;
//! each output is one thread's sum over the reduction dimension in order of `p`, so a
//! call is deterministic.

use super::{bytes_f32, f32_bytes, u32_bytes, GpuContext, GpuError};

const GEMM: &str = include_str!("shaders/gemm.wgsl");

/// Which operands are transposed, as in `crate::nn::matmul`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GemmOp {
    /// `C (m x n) = A (m x k) B (k x n)`.
    AB,
    /// `C (m x n) = A^T B`, `A` stored `k x m` (the weight-gradient product).
    AtB,
    /// `C (m x n) = A B^T`, `B` stored `n x k` (the input-gradient product).
    ABt,
}

/// A compiled GEMM pipeline on a device.
pub struct GpuGemm {
    ctx: GpuContext,
    pipeline: wgpu::ComputePipeline,
}

impl std::fmt::Debug for GpuGemm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuGemm({})", self.ctx.describe())
    }
}

impl GpuGemm {
    pub fn new(ctx: GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            pipeline: ctx.pipeline("gemm", GEMM)?,
            ctx,
        })
    }

    /// `op(A) op(B)` (m x n), plus `c` when given (`m * n` values): host in, host out.
    #[allow(clippy::too_many_arguments)]
    pub fn matmul(
        &self,
        op: GemmOp,
        a: &[f32],
        b: &[f32],
        c: Option<&[f32]>,
        m: usize,
        k: usize,
        n: usize,
    ) -> Result<Vec<f32>, GpuError> {
        let shape = |what: &str, expected: usize, got: usize| {
            if expected == got {
                Ok(())
            } else {
                Err(GpuError::Invalid(format!(
                    "gemm {what}: expected {expected} values, got {got}"
                )))
            }
        };
        shape("A", m * k, a.len())?;
        shape("B", k * n, b.len())?;
        if let Some(c) = c {
            shape("C", m * n, c.len())?;
        }
        let max = u32::MAX as usize;
        if m * k > max
            || k * n > max
            || m * n > max
            || m.div_ceil(16) > 65535
            || n.div_ceil(16) > 65535
        {
            return Err(GpuError::TooLarge(format!("gemm of {m} x {k} x {n}")));
        }
        if m == 0 || n == 0 {
            return Ok(Vec::new());
        }
        // (row stride, column stride) of op(A) (m x k) and op(B) (k x n).
        let (a_rs, a_cs, b_rs, b_cs) = match op {
            GemmOp::AB => (k, 1, n, 1),
            GemmOp::AtB => (1, m, n, 1),
            GemmOp::ABt => (k, 1, 1, k),
        };
        let ctx = &self.ctx;
        let params = ctx.uniform_init(
            "gemm params",
            &u32_bytes(&[
                m as u32,
                n as u32,
                k as u32,
                c.is_some() as u32,
                a_rs as u32,
                a_cs as u32,
                b_rs as u32,
                b_cs as u32,
            ]),
        );
        let a_buf = ctx.storage_init("gemm A", &f32_bytes(a));
        let b_buf = ctx.storage_init("gemm B", &f32_bytes(b));
        let c_buf = match c {
            Some(c) => ctx.storage_init("gemm C", &f32_bytes(c)),
            None => ctx.storage("gemm C", (m * n * 4) as u64)?,
        };
        let bind = ctx.bind_group(&self.pipeline, &[&params, &a_buf, &b_buf, &c_buf]);
        let mut encoder = ctx.encoder("gemm");
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(n.div_ceil(16) as u32, m.div_ceil(16) as u32, 1);
        }
        let back = ctx.read_back(encoder, &[(&c_buf, (m * n * 4) as u64)])?;
        Ok(bytes_f32(&back[0]))
    }
}
