//! The MLP's resident path: a network's device state ([`DeviceNetwork`]: flat
//! parameters, gradient, Adam moments), the recording entry points the resident step calls
//! (`GpuMlp::encode_forward`, `encode_backward`, `encode_adam`), and their host drivers
//! for tests and benchmarks ([`DeviceBatch`], [`GpuMlp::run_forward_backward`],
//! [`GpuMlp::run_adam`]).
//!
//! Invariants: non-finite parameters or moments are refused on upload and on download
//! (the host model is left unchanged); the host's Adam step counter advances only through
//! [`DeviceNetwork::mark_stepped`]; recording never submits or reads back.

use super::*;

/// Lengths and finiteness of a host network and its moments.
fn check_host_state(mlp: &Mlp, m: &[f32], v: &[f32]) -> Result<(), GpuError> {
    let n = mlp.num_params();
    if m.len() != n || v.len() != n {
        return Err(GpuError::Invalid(format!(
            "Adam moments of {} and {} values for a network of {n} parameters",
            m.len(),
            v.len()
        )));
    }
    for (name, values) in [("parameters", mlp.params()), ("Adam m", m), ("Adam v", v)] {
        if let Some(i) = values.iter().position(|x| !x.is_finite()) {
            return Err(GpuError::Invalid(format!(
                "network {name}: non-finite value {} at {i}",
                values[i]
            )));
        }
    }
    Ok(())
}

impl DeviceNetwork {
    /// The device copy of `mlp` with Adam moments `m`, `v` after `adam_step` steps; the
    /// gradient starts at zero.
    pub fn new(
        ctx: &GpuContext,
        mlp: &Mlp,
        m: &[f32],
        v: &[f32],
        adam_step: u64,
    ) -> Result<Self, GpuError> {
        check_host_state(mlp, m, v)?;
        let bytes = (mlp.num_params() * 4) as u64;
        let mut out = Self {
            widths: mlp.widths().to_vec(),
            hidden: mlp.hidden_activation(),
            len: mlp.num_params(),
            params: ctx.storage("mlp network params", bytes)?,
            grads: ctx.storage("mlp network grads", bytes)?,
            m: ctx.storage("mlp network adam m", bytes)?,
            v: ctx.storage("mlp network adam v", bytes)?,
            adam_step,
        };
        out.upload(ctx, mlp, m, v, adam_step)?;
        Ok(out)
    }

    fn check_same_network(&self, mlp: &Mlp) -> Result<(), GpuError> {
        if mlp.widths() != self.widths.as_slice() || mlp.hidden_activation() != self.hidden {
            return Err(GpuError::Invalid(format!(
                "network of widths {:?} ({:?}) differs from the device's {:?} ({:?})",
                mlp.widths(),
                mlp.hidden_activation(),
                self.widths,
                self.hidden
            )));
        }
        Ok(())
    }

    /// Overwrites the parameters, moments and step counter (same widths and activation,
    /// else [`GpuError::Invalid`]); takes effect at the next submission.
    pub fn upload(
        &mut self,
        ctx: &GpuContext,
        mlp: &Mlp,
        m: &[f32],
        v: &[f32],
        adam_step: u64,
    ) -> Result<(), GpuError> {
        self.check_same_network(mlp)?;
        check_host_state(mlp, m, v)?;
        ctx.queue
            .write_buffer(&self.params, 0, &f32_bytes(mlp.params()));
        ctx.queue.write_buffer(&self.m, 0, &f32_bytes(m));
        ctx.queue.write_buffer(&self.v, 0, &f32_bytes(v));
        self.adam_step = adam_step;
        Ok(())
    }

    /// Copies the parameters into `mlp` and the moments into `m`, `v` (one wait). A
    /// non-finite device value is [`GpuError::Invalid`] and changes nothing on the host.
    pub fn download(
        &self,
        ctx: &GpuContext,
        mlp: &mut Mlp,
        m: &mut [f32],
        v: &mut [f32],
    ) -> Result<(), GpuError> {
        self.check_same_network(mlp)?;
        if m.len() != self.len || v.len() != self.len {
            return Err(GpuError::Invalid(format!(
                "Adam moments of {} and {} values for a network of {} parameters",
                m.len(),
                v.len(),
                self.len
            )));
        }
        let bytes = (self.len * 4) as u64;
        let back = ctx.read_back(
            ctx.encoder("mlp network download"),
            &[(&self.params, bytes), (&self.m, bytes), (&self.v, bytes)],
        )?;
        let values: Vec<Vec<f32>> = back.iter().map(|b| bytes_f32(b)).collect();
        for (name, vals) in ["parameters", "Adam m", "Adam v"].iter().zip(&values) {
            if let Some(i) = vals.iter().position(|x| !x.is_finite()) {
                return Err(GpuError::Invalid(format!(
                    "device network {name}: non-finite value {} at {i}",
                    vals[i]
                )));
            }
        }
        mlp.params_mut().copy_from_slice(&values[0]);
        m.copy_from_slice(&values[1]);
        v.copy_from_slice(&values[2]);
        Ok(())
    }

    /// The gradient buffer's contents (tests; one wait).
    pub fn download_grads(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        let back = ctx.read_back(
            ctx.encoder("mlp network grads"),
            &[(&self.grads, (self.len * 4) as u64)],
        )?;
        Ok(bytes_f32(&back[0]))
    }

    /// Overwrites the gradient buffer (tests of the Adam step on its own).
    pub fn upload_grads(&self, ctx: &GpuContext, grads: &[f32]) -> Result<(), GpuError> {
        if grads.len() != self.len {
            return Err(GpuError::Invalid(format!(
                "gradient of {} values for a network of {} parameters",
                grads.len(),
                self.len
            )));
        }
        ctx.queue.write_buffer(&self.grads, 0, &f32_bytes(grads));
        Ok(())
    }

    /// Flat parameters (`nn::mlp` layout).
    pub fn params(&self) -> &wgpu::Buffer {
        &self.params
    }

    /// Flat parameter gradient (same layout), overwritten by each
    /// `GpuMlp::encode_backward`.
    pub fn grads(&self) -> &wgpu::Buffer {
        &self.grads
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Always false (a network has at least one weight); for clippy's `len` convention.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn widths(&self) -> &[usize] {
        &self.widths
    }

    pub fn hidden_activation(&self) -> HiddenActivation {
        self.hidden
    }

    /// Adam steps applied (the next step's bias correction uses `adam_step() + 1`).
    pub fn adam_step(&self) -> u64 {
        self.adam_step
    }

    /// Records that the caller's readback said the recorded Adam step was applied.
    pub fn mark_stepped(&mut self) {
        self.adam_step += 1;
    }
}

impl DeviceBatch {
    /// Buffers for up to `max_rows` rows of `net`'s input and output widths.
    pub fn new(gpu: &GpuMlp, net: &DeviceNetwork, max_rows: usize) -> Result<Self, GpuError> {
        let ctx = &gpu.ctx;
        let (in_width, out_width) = (net.widths[0], net.widths[net.widths.len() - 1]);
        let bytes_in = (max_rows * in_width * 4) as u64;
        let bytes_out = (max_rows * out_width * 4) as u64;
        Ok(Self {
            max_rows,
            in_width,
            out_width,
            input: ctx.storage("mlp batch input", bytes_in)?,
            count: ctx.storage("mlp batch count", 4)?,
            d_output: ctx.storage("mlp batch d_output", bytes_out)?,
            output: ctx.storage("mlp batch output", bytes_out)?,
            d_input: ctx.storage("mlp batch d_input", bytes_in)?,
        })
    }

    /// Writes the batch: `max_rows x in` inputs, `max_rows x out` output gradients (rows
    /// from `live_rows` on are dead: never read, any value) and the live count.
    pub fn write(
        &self,
        gpu: &GpuMlp,
        input: &[f32],
        live_rows: usize,
        d_output: &[f32],
    ) -> Result<(), GpuError> {
        if input.len() != self.max_rows * self.in_width
            || d_output.len() != self.max_rows * self.out_width
            || live_rows > self.max_rows
        {
            return Err(GpuError::Invalid(format!(
                "batch of {} inputs, {} output gradients, {live_rows} live rows for {} rows \
                 of {} in, {} out",
                input.len(),
                d_output.len(),
                self.max_rows,
                self.in_width,
                self.out_width
            )));
        }
        let q = &gpu.ctx.queue;
        if !input.is_empty() {
            q.write_buffer(&self.input, 0, &f32_bytes(input));
            q.write_buffer(&self.d_output, 0, &f32_bytes(d_output));
        }
        q.write_buffer(&self.count, 0, &u32_bytes(&[live_rows as u32]));
        Ok(())
    }

    /// Reads back the output (`max_rows x out`) and the input gradient (`max_rows x in`;
    /// what the last run left there, zeros before any run asked for it).
    pub fn read(&self, gpu: &GpuMlp) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let back = gpu.ctx.read_back(
            gpu.ctx.encoder("mlp batch read"),
            &[
                (&self.output, (self.max_rows * self.out_width * 4) as u64),
                (&self.d_input, (self.max_rows * self.in_width * 4) as u64),
            ],
        )?;
        Ok((bytes_f32(&back[0]), bytes_f32(&back[1])))
    }
}

/// Checks that `buffer` holds at least `values` f32.
fn check_buffer(name: &str, buffer: &wgpu::Buffer, values: usize) -> Result<(), GpuError> {
    if buffer.size() < (values * 4) as u64 {
        return Err(GpuError::Invalid(format!(
            "{name}: buffer of {} bytes, {values} values needed",
            buffer.size()
        )));
    }
    Ok(())
}

/// A device network as one recording sees it: the network, the pool its tape and
/// uniforms come from, and the label they are keyed by there (one label per network and
/// batch within a command buffer).
#[derive(Clone, Copy, Debug)]
pub(crate) struct MlpRecording<'a> {
    pub scratch: &'a Scratch,
    pub label: &'a str,
    pub net: &'a DeviceNetwork,
}

impl GpuMlp {
    /// Records the forward of `net` over `max_rows` rows of `input` (row-major, input
    /// width), of which only the first `count[0]` (u32 read on the device) are live; output
    /// rows beyond the count are written as 0. Output: `max_rows * out_width` f32 into
    /// `output`. The tape's activations are `scratch` buffers under `mlp {label} ...`
    /// (one label per network and batch within a command buffer); `input` must still hold
    /// the batch when the backward runs.
    pub(crate) fn encode_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rec: MlpRecording,
        input: &wgpu::Buffer,
        count: &wgpu::Buffer,
        max_rows: usize,
        output: &wgpu::Buffer,
    ) -> Result<DeviceTape, GpuError> {
        let (scratch, label, net) = (rec.scratch, rec.label, rec.net);
        let widths = net.widths();
        let n_out = widths[widths.len() - 1];
        check_buffer("MLP input", input, max_rows * widths[0])?;
        check_buffer("MLP output", output, max_rows * n_out)?;
        check_buffer("MLP row count", count, 1)?;
        let tape = self.record_forward(
            encoder,
            Some(scratch),
            label,
            (widths, net.hidden),
            &net.params,
            input,
            count,
            max_rows,
        )?;
        if max_rows > 0 {
            let last = &tape.activations[widths.len() - 2];
            encoder.copy_buffer_to_buffer(last, 0, output, 0, (max_rows * n_out * 4) as u64);
        }
        Ok(tape)
    }

    /// Records the backward for `d_output` (`max_rows * out_width`, rows beyond the count
    /// are ignored; the buffer is not modified): the parameter gradient into `net.grads()`
    /// (overwritten, not accumulated) and, when given, the input gradient into `d_input`
    /// (`max_rows * in_width`, rows beyond the count written 0). `net` must be the
    /// network of the tape's forward, its parameters unchanged since.
    pub(crate) fn encode_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rec: MlpRecording,
        tape: &DeviceTape,
        d_output: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let (scratch, label, net) = (rec.scratch, rec.label, rec.net);
        if tape.widths != net.widths || tape.hidden != net.hidden {
            return Err(GpuError::Invalid(format!(
                "MLP backward: tape of widths {:?} ({:?}) for a network of {:?} ({:?})",
                tape.widths, tape.hidden, net.widths, net.hidden
            )));
        }
        let widths = &tape.widths;
        check_buffer(
            "MLP output gradient",
            d_output,
            tape.max_rows * widths[widths.len() - 1],
        )?;
        if let Some(d) = d_input {
            check_buffer("MLP input gradient", d, tape.max_rows * widths[0])?;
        }
        self.record_backward(
            encoder,
            Some(scratch),
            label,
            (&net.params, &net.grads),
            tape,
            d_output,
            d_input,
        )
    }

    /// Records one Adam step on `net.params()` with `net.grads()` and learning rate `lr`:
    /// `FlatAdam::apply`'s rule for step `net.adam_step() + 1` (`shaders/adam.wgsl`, one
    /// group covering the whole vector), changing nothing at all when `flags[0] != 0` at
    /// the time it runs. The caller calls [`DeviceNetwork::mark_stepped`] when its
    /// readback of `flags` says the step applied. `lr` must be finite and non-negative.
    pub(crate) fn encode_adam(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rec: MlpRecording,
        lr: f32,
        flags: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (scratch, label, net) = (rec.scratch, rec.label, rec.net);
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(GpuError::Invalid(format!("MLP Adam learning rate {lr}")));
        }
        check_buffer("MLP Adam flags", flags, 1)?;
        let len = u32::try_from(net.len)
            .map_err(|_| GpuError::TooLarge(format!("{} network parameters", net.len)))?;
        // FlatAdam::apply, step t = adam_step + 1 (its counter is incremented first).
        let t = (net.adam_step + 1) as i32;
        let bias1 = 1.0 - (ADAM_BETA1 as f64).powi(t);
        let bias2 = 1.0 - (ADAM_BETA2 as f64).powi(t);
        let mut words = [0u32; 32];
        // adam.wgsl's group offsets: group 0 is [0, len), groups 1..8 empty at len, and
        // the total (word 9).
        words[1..10].fill(len);
        words[12] = ((lr as f64 / bias1) as f32).to_bits();
        // Group 0 always active: FlatAdam moves the moments even at learning rate 0.
        words[20] = 1;
        words[21] = ADAM_BETA1.to_bits();
        words[22] = ADAM_BETA2.to_bits();
        words[23] = gs_core::optim::ADAM_EPS.to_bits();
        words[24] = ((1.0 / bias2.sqrt()) as f32).to_bits();
        let uniform =
            scratch.uniform(&self.ctx, &format!("mlp {label} adam"), &u32_bytes(&words))?;
        let bind = self.ctx.bind_group(
            &self.adam,
            &[&uniform, &net.params, &net.grads, &net.m, &net.v, flags],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.adam, &bind, net.len as u64);
        Ok(())
    }

    /// `GpuMlp::encode_forward` then `GpuMlp::encode_backward` on `batch` as one
    /// command buffer, submitted and waited for (no readback): the output and, when
    /// `input_gradient`, the input gradient land in `batch`, the parameter gradient in
    /// `net.grads()`. For tests and benchmarks outside the crate; its scratch is this
    /// `GpuMlp`'s, under one label, so runs must not overlap (one thread at a time).
    pub fn run_forward_backward(
        &self,
        net: &DeviceNetwork,
        batch: &DeviceBatch,
        input_gradient: bool,
    ) -> Result<(), GpuError> {
        if net.widths[0] != batch.in_width || net.widths[net.widths.len() - 1] != batch.out_width {
            return Err(GpuError::Invalid(format!(
                "{batch:?} for a network of widths {:?}",
                net.widths
            )));
        }
        let mut encoder = self.ctx.encoder("mlp run forward backward");
        let tape = self.encode_forward(
            &mut encoder,
            MlpRecording {
                scratch: &self.scratch,
                label: "run",
                net,
            },
            &batch.input,
            &batch.count,
            batch.max_rows,
            &batch.output,
        )?;
        self.encode_backward(
            &mut encoder,
            MlpRecording {
                scratch: &self.scratch,
                label: "run",
                net,
            },
            &tape,
            &batch.d_output,
            input_gradient.then_some(&batch.d_input),
        )?;
        self.ctx.queue.submit(Some(encoder.finish()));
        self.ctx
            .device
            .poll(wgpu::PollType::Wait)
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        Ok(())
    }

    /// `GpuMlp::encode_adam` on the gradient as it stands, with the refusal flag set to
    /// `refuse`, submitted with a readback of the flag; marks the step applied when the
    /// flag reads 0, as the resident step does. Returns whether it applied. For tests.
    pub fn run_adam(
        &self,
        net: &mut DeviceNetwork,
        lr: f32,
        refuse: bool,
    ) -> Result<bool, GpuError> {
        let flags = self.scratch.storage(&self.ctx, "mlp run flags", 4)?;
        self.ctx
            .queue
            .write_buffer(&flags, 0, &u32_bytes(&[refuse as u32]));
        let mut encoder = self.ctx.encoder("mlp run adam");
        self.encode_adam(
            &mut encoder,
            MlpRecording {
                scratch: &self.scratch,
                label: "run",
                net,
            },
            lr,
            &flags,
        )?;
        let back = self.ctx.read_back(encoder, &[(&flags, 4)])?;
        let applied = bytes_u32(&back[0])[0] == 0;
        if applied {
            net.mark_stepped();
        }
        Ok(applied)
    }
}
