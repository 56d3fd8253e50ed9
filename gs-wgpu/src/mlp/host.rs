//! The MLP's host path ([`GpuMlp::forward`], [`GpuMlp::backward`], used by `nn::Mlp` on
//! a device): one command buffer and one wait per call; the input, parameters and
//! activations stay on the device in the [`MlpTape`] between forward and backward.
//!
//! Invariants: shapes are checked before any device work; only the output (forward) and
//! the parameter and, when asked, input gradients (backward) are read back.

use super::*;

impl GpuMlp {
    /// Forward of `mlp` on `rows` row-major inputs: the sigmoid outputs (`rows x out`)
    /// and the tape for [`GpuMlp::backward`].
    pub fn forward(
        &self,
        mlp: &Mlp,
        input: &[f32],
        rows: usize,
    ) -> Result<(Vec<f32>, MlpTape), GpuError> {
        let widths = mlp.widths().to_vec();
        if input.len() != rows * widths[0] {
            return Err(GpuError::Invalid(format!(
                "MLP input: expected {} values, got {}",
                rows * widths[0],
                input.len()
            )));
        }
        self.check_sizes(&widths, rows)?;
        if rows == 0 {
            let tape = MlpTape {
                rows,
                widths,
                device: None,
            };
            return Ok((Vec::new(), tape));
        }
        let params = self.upload("mlp params", mlp.params())?;
        let x = self.upload("mlp input", input)?;
        let count = self
            .ctx
            .storage_init("mlp row count", &u32_bytes(&[rows as u32]));
        let mut encoder = self.ctx.encoder("mlp forward");
        let tape = self.record_forward(
            &mut encoder,
            None,
            "host",
            (&widths, mlp.hidden_activation()),
            &params,
            &x,
            &count,
            rows,
        )?;
        let n_out = widths[widths.len() - 1];
        let back = self.ctx.read_back(
            encoder,
            &[(
                &tape.activations[widths.len() - 2],
                (rows * n_out * 4) as u64,
            )],
        )?;
        let tape = MlpTape {
            rows,
            widths,
            device: Some((tape, params)),
        };
        Ok((bytes_f32(&back[0]), tape))
    }

    /// Backward of [`GpuMlp::forward`]: the parameter gradient (flat layout, not added to
    /// anything) and, when `want_input_gradient`, the input gradient.
    pub fn backward(
        &self,
        tape: &MlpTape,
        d_output: &[f32],
        want_input_gradient: bool,
    ) -> Result<MlpGradients, GpuError> {
        let widths = &tape.widths;
        let rows = tape.rows;
        let n_out = widths[widths.len() - 1];
        if d_output.len() != rows * n_out {
            return Err(GpuError::Invalid(format!(
                "MLP output gradient: expected {} values, got {}",
                rows * n_out,
                d_output.len()
            )));
        }
        let num_params = layer_starts(widths)[widths.len() - 1];
        let Some((device_tape, params)) = tape.device.as_ref().filter(|_| rows > 0) else {
            let input = want_input_gradient.then(Vec::new);
            return Ok(MlpGradients {
                params: vec![0.0; num_params],
                input,
            });
        };
        let dz = self.upload("mlp dY", d_output)?;
        let grads = self.ctx.storage("mlp dparams", (num_params * 4) as u64)?;
        let d_input = if want_input_gradient {
            Some(self.ctx.storage("mlp dX", (rows * widths[0] * 4) as u64)?)
        } else {
            None
        };
        let mut encoder = self.ctx.encoder("mlp backward");
        self.record_backward(
            &mut encoder,
            None,
            "host",
            (params, &grads),
            device_tape,
            &dz,
            d_input.as_ref(),
        )?;
        let mut ranges: Vec<(&wgpu::Buffer, u64)> = vec![(&grads, (num_params * 4) as u64)];
        if let Some(d) = &d_input {
            ranges.push((d, (rows * widths[0] * 4) as u64));
        }
        let back = self.ctx.read_back(encoder, &ranges)?;
        Ok(MlpGradients {
            params: bytes_f32(&back[0]),
            input: d_input.map(|_| bytes_f32(&back[1])),
        })
    }
}
