//! The MLP's one recording: the GEMM and pointwise dispatches of a forward
//! (`record_forward`) and of a backward (`record_backward`), shared by the host path and
//! the resident path.
//!
//! Invariants: every output value is one thread's in-order sum (no atomics), so results
//! are deterministic; rows past the live count read nothing and are written 0; the
//! parameter gradient is overwritten, never accumulated.

use super::*;

impl GpuMlp {
    /// Records `C = op(A) op(B)` (see [`GemmShape`] and `GemmOp` for the strides) into
    /// `pass`, as `k.div_ceil(k_chunk)` partial products one after another in `c` (one
    /// when `k_chunk >= k`), the batch's live rows from `count`.
    pub(super) fn gemm(
        &self,
        pass: &mut wgpu::ComputePass,
        scratch: Option<&Scratch>,
        label: &str,
        s: &GemmShape,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        c: &wgpu::Buffer,
        count: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (a_rs, a_cs, b_rs, b_cs) = match s.op {
            GemmOp::AB => (s.k, 1, s.n, 1),
            GemmOp::AtB => (1, s.m, s.n, 1),
            GemmOp::ABt => (s.k, 1, 1, s.k),
        };
        let words = [
            s.m, s.n, s.k, s.k_chunk, a_rs, a_cs, b_rs, b_cs, s.a_off, s.b_off, s.c_off,
        ]
        .map(|w| w as u32);
        let mut data = u32_bytes(&words);
        data.extend_from_slice(&(s.live as u32).to_le_bytes());
        let params = uniform_in(&self.ctx, scratch, label, &data)?;
        let bind = self.ctx.bind_group(&self.gemm, &[&params, a, b, c, count]);
        pass.set_pipeline(&self.gemm);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(
            s.n.div_ceil(GEMM_BLOCK) as u32,
            s.m.div_ceil(GEMM_BLOCK) as u32,
            s.k.div_ceil(s.k_chunk) as u32,
        );
        Ok(())
    }

    /// Records `mlp_pointwise.wgsl`'s `op` on the `values / n` x `n` matrix `x`, with
    /// `aux` read from word `aux_off`.
    pub(super) fn pointwise(
        &self,
        pass: &mut wgpu::ComputePass,
        scratch: Option<&Scratch>,
        label: &str,
        op: Pointwise,
        x: &wgpu::Buffer,
        (aux, aux_off): (&wgpu::Buffer, usize),
        count: &wgpu::Buffer,
        (values, n): (usize, usize),
    ) -> Result<(), GpuError> {
        let mut data = u32_bytes(&[values as u32, n as u32, op as u32]);
        data.extend_from_slice(&gs_core::nn::mlp::LEAKY_SLOPE.to_le_bytes());
        data.extend_from_slice(&u32_bytes(&[aux_off as u32, 0, 0, 0]));
        let params = uniform_in(&self.ctx, scratch, label, &data)?;
        let bind = self
            .ctx
            .bind_group(&self.pointwise, &[&params, x, aux, count]);
        dispatch_1d(pass, &self.pointwise, &bind, values as u64);
        Ok(())
    }

    /// Records `mlp_sum_chunks.wgsl`: `dst[dst_off + i]` = the sum over the `chunks`
    /// partial results `partials[z * values + i]`, in chunk order, for i < `values`.
    fn sum_chunks(
        &self,
        pass: &mut wgpu::ComputePass,
        scratch: Option<&Scratch>,
        label: &str,
        partials: &wgpu::Buffer,
        chunks: usize,
        (dst, dst_off, values): (&wgpu::Buffer, usize, usize),
    ) -> Result<(), GpuError> {
        let data = u32_bytes(&[values as u32, chunks as u32, dst_off as u32, 0]);
        let uniform = uniform_in(&self.ctx, scratch, label, &data)?;
        let bind = self
            .ctx
            .bind_group(&self.sum_chunks, &[&uniform, partials, dst]);
        dispatch_1d(pass, &self.sum_chunks, &bind, values as u64);
        Ok(())
    }

    /// Records the forward of the network `widths`/`hidden` whose flat parameters are
    /// `params` over `max_rows` rows of `input` (live count in `count`), every layer's
    /// output into a fresh (host path) or scratch buffer of the returned tape.
    pub(super) fn record_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        label: &str,
        (widths, hidden): (&[usize], HiddenActivation),
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        count: &wgpu::Buffer,
        max_rows: usize,
    ) -> Result<DeviceTape, GpuError> {
        self.check_sizes(widths, max_rows)?;
        let layers = widths.len() - 1;
        let starts = layer_starts(widths);
        let mut activations = Vec::with_capacity(layers);
        for l in 0..layers {
            activations.push(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} activation {l}"),
                (max_rows * widths[l + 1] * 4) as u64,
            )?);
        }
        if max_rows > 0 {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            for l in 0..layers {
                let (n_in, n_out) = (widths[l], widths[l + 1]);
                let layer_input = if l == 0 { input } else { &activations[l - 1] };
                let shape = GemmShape {
                    op: GemmOp::AB,
                    m: max_rows,
                    k: n_in,
                    n: n_out,
                    k_chunk: n_in,
                    a_off: 0,
                    b_off: starts[l],
                    c_off: 0,
                    live: Live::OutputRows,
                };
                let gemm_label = format!("mlp {label} forward gemm {l}");
                let out = &activations[l];
                self.gemm(
                    &mut pass,
                    scratch,
                    &gemm_label,
                    &shape,
                    layer_input,
                    params,
                    out,
                    count,
                )?;
                let op = if l + 1 == layers {
                    Pointwise::BiasSigmoid
                } else {
                    match hidden {
                        HiddenActivation::Relu => Pointwise::BiasRelu,
                        HiddenActivation::LeakyRelu => Pointwise::BiasLeakyRelu,
                    }
                };
                self.pointwise(
                    &mut pass,
                    scratch,
                    &format!("mlp {label} forward pointwise {l}"),
                    op,
                    out,
                    (params, starts[l] + n_in * n_out),
                    count,
                    (max_rows * n_out, n_out),
                )?;
            }
        }
        Ok(DeviceTape {
            max_rows,
            widths: widths.to_vec(),
            hidden,
            input: input.clone(),
            count: count.clone(),
            activations,
        })
    }

    /// Records the backward of `tape` for `d_output` (copied, not modified): the flat
    /// parameter gradient into `grads` (overwritten) and, when given, the input gradient
    /// into `d_input`, reading the weights from `params`.
    pub(super) fn record_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        label: &str,
        (params, grads): (&wgpu::Buffer, &wgpu::Buffer),
        tape: &DeviceTape,
        d_output: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let widths = &tape.widths;
        let rows = tape.max_rows;
        let layers = widths.len() - 1;
        let starts = layer_starts(widths);
        if rows == 0 {
            encoder.clear_buffer(grads, 0, Some((starts[layers] * 4) as u64));
            return Ok(());
        }
        let count = &tape.count;
        let n_out_last = widths[layers];
        let mut dz = storage_in(
            &self.ctx,
            scratch,
            &format!("mlp {label} dz {}", layers - 1),
            (rows * n_out_last * 4) as u64,
        )?;
        encoder.copy_buffer_to_buffer(d_output, 0, &dz, 0, (rows * n_out_last * 4) as u64);
        let chunks = rows.div_ceil(WEIGHT_GRADIENT_CHUNK_ROWS);
        // One partials buffer serves every layer (wgpu orders the dispatches using it).
        let partials = if chunks > 1 {
            let widest = widths.windows(2).map(|p| p[0] * p[1]).max().unwrap_or(0);
            Some(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} weight gradient chunks"),
                (chunks * widest * 4) as u64,
            )?)
        } else {
            None
        };
        // Hidden layers' input gradients, allocated before the pass borrows them.
        let mut d_hidden = Vec::with_capacity(layers);
        for l in 0..layers.saturating_sub(1) {
            d_hidden.push(storage_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} dz {l}"),
                (rows * widths[l + 1] * 4) as u64,
            )?);
        }
        let mut pass = encoder.begin_compute_pass(&Default::default());
        self.pointwise(
            &mut pass,
            scratch,
            &format!("mlp {label} backward sigmoid"),
            Pointwise::SigmoidBackward,
            &dz,
            (&tape.activations[layers - 1], 0),
            count,
            (rows * n_out_last, n_out_last),
        )?;
        for l in (0..layers).rev() {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            let w_at = starts[l];
            let layer_input = if l == 0 {
                &tape.input
            } else {
                &tape.activations[l - 1]
            };
            let weight_gradient = GemmShape {
                op: GemmOp::AtB,
                m: n_in,
                k: rows,
                n: n_out,
                k_chunk: WEIGHT_GRADIENT_CHUNK_ROWS,
                a_off: 0,
                b_off: 0,
                c_off: if partials.is_some() { 0 } else { w_at },
                live: Live::ReductionRows,
            };
            self.gemm(
                &mut pass,
                scratch,
                &format!("mlp {label} backward dW {l}"),
                &weight_gradient,
                layer_input,
                &dz,
                partials.as_ref().unwrap_or(grads),
                count,
            )?;
            if let Some(partials) = &partials {
                let label = format!("mlp {label} backward dW sum {l}");
                let to = (grads, w_at, n_in * n_out);
                self.sum_chunks(&mut pass, scratch, &label, partials, chunks, to)?;
            }
            // The bias gradient: chunked like the weight gradient, into the same partials.
            let b_at = w_at + n_in * n_out;
            let (db_to, db_at, db_chunk_rows) = match &partials {
                Some(partials) => (partials, 0, WEIGHT_GRADIENT_CHUNK_ROWS),
                None => (grads, b_at, rows),
            };
            let colsum = uniform_in(
                &self.ctx,
                scratch,
                &format!("mlp {label} backward db {l}"),
                &u32_bytes(&[
                    rows as u32,
                    n_out as u32,
                    db_at as u32,
                    db_chunk_rows as u32,
                ]),
            )?;
            let bind = self
                .ctx
                .bind_group(&self.colsum, &[&colsum, &dz, db_to, count]);
            pass.set_pipeline(&self.colsum);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(n_out.div_ceil(64) as u32, chunks as u32, 1);
            if let Some(partials) = &partials {
                let label = format!("mlp {label} backward db sum {l}");
                let to = (grads, b_at, n_out);
                self.sum_chunks(&mut pass, scratch, &label, partials, chunks, to)?;
            }
            let d_prev = match (l, d_input) {
                (0, None) => break,
                (0, Some(d)) => d,
                _ => &d_hidden[l - 1],
            };
            let input_gradient = GemmShape {
                op: GemmOp::ABt,
                m: rows,
                k: n_out,
                n: n_in,
                k_chunk: n_out,
                a_off: 0,
                b_off: w_at,
                c_off: 0,
                live: Live::OutputRows,
            };
            self.gemm(
                &mut pass,
                scratch,
                &format!("mlp {label} backward dX {l}"),
                &input_gradient,
                &dz,
                params,
                d_prev,
                count,
            )?;
            if l > 0 {
                let op = match tape.hidden {
                    HiddenActivation::Relu => Pointwise::ReluBackward,
                    HiddenActivation::LeakyRelu => Pointwise::LeakyReluBackward,
                };
                self.pointwise(
                    &mut pass,
                    scratch,
                    &format!("mlp {label} backward activation {l}"),
                    op,
                    d_prev,
                    (&tape.activations[l - 1], 0),
                    count,
                    (rows * n_in, n_in),
                )?;
                dz = d_prev.clone();
            }
        }
        Ok(())
    }
}
