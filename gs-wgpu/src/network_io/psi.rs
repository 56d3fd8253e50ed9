//! Psi's (the shadow network's) kernels of [`NetworkIo`]: its full input rows, the
//! output scatter into channel 3, the output gradient and the input gradient's scatter
//! (`nn::shadow_net::ShadowNet::{assemble_input, scatter_input_grad}` and the channel
//! routing of `sunaware::model`), under the conventions of the parent module's header.

use super::uniform::{box_terms, check_buffer, check_layout, sun_code, Uniform};
use super::{NetworkBatch, NetworkIo, PackedParams, ROW_HEAD, SHADOWED_CHANNELS};
use crate::GpuError;
use gs_core::model::Param;
use gs_core::nn::{SceneBox, ShadowNet};

impl NetworkIo {
    /// Psi's full input rows (`n * input_width` f32 in `input`) for `list[0..count]`: row r
    /// is `[V_g | gamma_L(sun) | gamma_L(p_g) | l_g]` of g = `list[r]`, V_g from `visibility`
    /// (n f32), p_g the mean normalised over `scene_box`; rows `>= count` are written as 0.
    /// A non-finite V, mean or latent sets `flags` bit 0.
    pub fn encode_psi_input(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        net: &ShadowNet,
        scene_box: &SceneBox,
        params: PackedParams,
        sun_dir: [f32; 3],
        visibility: &wgpu::Buffer,
        input: &wgpu::Buffer,
        flags: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (params, offsets) = (params.buffer, params.offsets);
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        let width = net.input_width();
        batch.check(width)?;
        check_layout(
            offsets,
            n,
            Param::ShadowLatent,
            net.latent_dim(),
            &[("params", params)],
        )?;
        check_buffer("visibility", visibility, n)?;
        check_buffer("Psi input", input, n * width)?;
        check_buffer("flags", flags, 1)?;
        let (box_min, box_extent, box_inv_extent) = box_terms(scene_box);
        let uniform = Uniform {
            offsets: *offsets,
            n,
            width,
            dim: net.latent_dim(),
            freqs: net.encoding().num_frequencies(),
            box_min,
            box_extent,
            box_inv_extent,
            sun_code: sun_code(net.encoding(), sun_dir)?,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, params, input, flags, visibility];
        self.record(
            encoder,
            scratch,
            "netio psi input",
            &self.psi_input,
            &uniform,
            &buffers,
        )
    }

    /// Psi's output P (`n`, row r = `list[r]`'s) into channel 3: `chans[g * nc + 3] = gain *
    /// V_g * P_r` when `multiply_gain` is `Some(gain)` (ShadowRefinement::Multiply), else
    /// `P_r`, for r < count, g = `list[r]`; other Gaussians' channels are not touched. `nc`
    /// must be 4.
    pub fn encode_psi_scatter(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        nc: usize,
        visibility: &wgpu::Buffer,
        output: &wgpu::Buffer,
        multiply_gain: Option<f32>,
        chans: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        batch.check_raster_rows(nc, &[SHADOWED_CHANNELS])?;
        check_buffer("visibility", visibility, n)?;
        check_buffer("Psi output", output, n)?;
        check_buffer("channels", chans, n * nc)?;
        let uniform = Uniform {
            n,
            nc,
            multiply_gain,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, visibility, output, chans];
        self.record(
            encoder,
            scratch,
            "netio psi scatter",
            &self.psi_scatter,
            &uniform,
            &buffers,
        )
    }

    /// Psi's output gradient (`n`): `d_out[r] = rows[g * (13 + nc) + 16]` (channel 3's
    /// gradient) times `gain * V_g` when `multiply_gain` is `Some(gain)`, for r < count, g =
    /// `list[r]`; 0 for rows `>= count`. `nc` must be 4.
    pub fn encode_psi_d_output(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        nc: usize,
        visibility: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        multiply_gain: Option<f32>,
        d_out: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        batch.check_raster_rows(nc, &[SHADOWED_CHANNELS])?;
        check_buffer("visibility", visibility, n)?;
        check_buffer("rasterizer gradient rows", rows, n * (ROW_HEAD + nc))?;
        check_buffer("Psi output gradient", d_out, n)?;
        let uniform = Uniform {
            n,
            nc,
            multiply_gain,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, visibility, rows, d_out];
        self.record(
            encoder,
            scratch,
            "netio psi d_output",
            &self.psi_d_output,
            &uniform,
            &buffers,
        )
    }

    /// Psi's input gradient (`d_input`, `n * input_width`) into `grads` (packed like
    /// `params`): for r < count, g = `list[r]`, the ShadowLatent row g is set to the row's
    /// latent columns, and the chain rule of its position columns through the encoding and
    /// the box normalisation is ADDED to the Mean row g. The V column gets nothing.
    pub fn encode_psi_input_grad(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        net: &ShadowNet,
        scene_box: &SceneBox,
        params: PackedParams,
        d_input: &wgpu::Buffer,
        grads: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (params, offsets) = (params.buffer, params.offsets);
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        let width = net.input_width();
        batch.check(width)?;
        check_layout(
            offsets,
            n,
            Param::ShadowLatent,
            net.latent_dim(),
            &[("params", params), ("grads", grads)],
        )?;
        check_buffer("Psi input gradient", d_input, n * width)?;
        let (box_min, box_extent, box_inv_extent) = box_terms(scene_box);
        let uniform = Uniform {
            offsets: *offsets,
            n,
            width,
            dim: net.latent_dim(),
            freqs: net.encoding().num_frequencies(),
            box_min,
            box_extent,
            box_inv_extent,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, params, d_input, grads];
        self.record(
            encoder,
            scratch,
            "netio psi input grad",
            &self.psi_input_grad,
            &uniform,
            &buffers,
        )
    }
}
