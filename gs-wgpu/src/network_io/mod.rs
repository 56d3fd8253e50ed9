//! Input assembly and output scatter of the Sun-aware networks (Phi, Psi) on the device,
//! forward and backward, for the device-resident Sun-aware step: [`NetworkIo`]'s
//! `encode_*` functions record kernels (../shaders/netio_*.wgsl) into the caller's command
//! encoder on the caller's device buffers; nothing is submitted or read back.
//!
//! Ported operation for operation from the CPU: `nn::appearance::AppearanceNet::
//! {assemble_input, scatter_input_grad}`, `nn::shadow_net::ShadowNet::{assemble_input,
//! scatter_input_grad}` (full rows, not the folded training path), `nn::encoding`
//! (`sin_cos_pi`'s quarter-turn reduction and polynomials, not the GPU's own sin/cos),
//! the channel routing of `sunaware::model::{forward_with, backward_timed}` and, with
//! `shading = "lambert_learned"`, the learned-normal Lambertian factor on Phi's colour
//! (`sunaware::shading::{shade_forward, shade_backward}`: [`PhiShading`] in Phi's scatter,
//! [`PhiShadingGrad`] in its output gradient, which also adds the normal's gradient), and
//! Phi's local-frame inputs `[n.s, n.v, n.h]` (`appearance_inputs = "local"` /
//! `"local_no_sun"`, `sunaware::shading::{local_inputs, local_inputs_backward}`: in Phi's
//! input rows, and in its input gradient into the Normal and Mean groups). The learned
//! normal's facing flip and the local frame are one WGSL copy (shaders/netio_normal.wgsl)
//! shared by those kernels.
//!
//! Files: this one holds the types and Phi's kernels; `psi.rs` Psi's; `uniform.rs` the
//! kernels' uniform and the host-side argument checks; `probe.rs` [`NetworkIoProbe`].
//!
//! Conventions: `params`/`grads` are the packed group-major parameter buffers with group
//! starts `offsets` ([`PackedParams`], [`packed_offsets`]); the batch ([`NetworkBatch`]):
//! `list` holds at least `max(n, 1)` u32 Gaussian indices, ascending, no repeats;
//! `count`'s word 0 is the live row count m (written on the device; values above n are read as n). Every kernel
//! runs over `n` rows; rows `r >= m` only write zeros to per-row outputs (input rows,
//! `d_out`).
//!
//! Invariants:
//! - the same arithmetic as the CPU (the Sun's encoding is computed on the host by the
//!   CPU encoding itself); see tests/gpu_network_io.rs for the measured agreement;
//! - host arguments that cannot describe the buffers (sizes, widths, offsets, channel
//!   counts, a non-finite or zero Sun vector, a non-finite camera centre) are a
//!   [`GpuError::Invalid`] before anything is recorded;
//! - where the CPU returns an error for device data (a non-finite feature, mean, latent
//!   or V of a listed Gaussian, a Gaussian at the camera centre, a list entry >= n), the
//!   input kernels set `flags[0]` bit 0 instead; the gradient kernels write what they
//!   compute (non-finite values included: the step's gradient check refuses them);
//! - each `encode_*` has its own uniform in the `Scratch` pool ("netio ..." labels),
//!   written through the queue: recording the same `encode_*` twice before one
//!   submission makes both read the second call's uniform;
//! - no float atomics: each listed Gaussian's rows have one writer, so results are
//!   deterministic.

pub use super::packed::PackedParams;
use super::{dispatch_1d, GpuContext, GpuError, Scratch};
use gs_core::model::Param;
use gs_core::nn::AppearanceNet;
pub use probe::NetworkIoProbe;
use uniform::{check_buffer, check_finite3, check_layout, sun_code, NormalTerms, Uniform};

mod probe;
mod psi;
mod uniform;

const NETIO_COMMON: &str = include_str!("../shaders/netio_common.wgsl");
const NETIO_ENCODING_BACKWARD: &str = include_str!("../shaders/netio_encoding_backward.wgsl");
const NETIO_NORMAL: &str = include_str!("../shaders/netio_normal.wgsl");
const NETIO_INPUT_ROWS: &str = include_str!("../shaders/netio_input_rows.wgsl");
const NETIO_PHI_INPUT: &str = include_str!("../shaders/netio_phi_input.wgsl");
const NETIO_PHI_SCATTER: &str = include_str!("../shaders/netio_phi_scatter.wgsl");
const NETIO_PHI_D_OUTPUT: &str = include_str!("../shaders/netio_phi_d_output.wgsl");
const NETIO_PHI_INPUT_GRAD: &str = include_str!("../shaders/netio_phi_input_grad.wgsl");
const NETIO_PSI_INPUT: &str = include_str!("../shaders/netio_psi_input.wgsl");
const NETIO_PSI_SCATTER: &str = include_str!("../shaders/netio_psi_scatter.wgsl");
const NETIO_PSI_D_OUTPUT: &str = include_str!("../shaders/netio_psi_d_output.wgsl");
const NETIO_PSI_INPUT_GRAD: &str = include_str!("../shaders/netio_psi_input_grad.wgsl");

/// Floats per rasterizer gradient row before the channels (project_backward.wgsl).
const ROW_HEAD: usize = 13;
/// Phi's outputs per row (RGB).
const PHI_OUT: usize = 3;
/// Channels with Psi's V' (RGB, V').
const SHADOWED_CHANNELS: usize = 4;
/// Sun-code floats the uniform holds: 6 L for L up to `nn::encoding::MAX_FREQUENCIES`.
const SUN_CODE_CAPACITY: usize = 96;
/// Bytes of the `NetIo` uniform (netio_common.wgsl).
const UNIFORM_BYTES: usize = 160 + SUN_CODE_CAPACITY * 4;
/// First word of the Sun code in the `NetIo` uniform.
const SUN_CODE_WORD: usize = 40;

/// Start of each group in the packed layout for `n` rows, and the total: the public face
/// of `packed::offsets` (tests and tools build packed buffers by hand with it).
pub fn packed_offsets(
    dims: &[usize; Param::COUNT],
    n: usize,
) -> Result<[u32; Param::COUNT + 1], GpuError> {
    super::packed::offsets(dims, n)
}

/// The rows a network runs over, recorded into one encoder: `n` Gaussians, the `list` of
/// those it evaluates (at least `max(n, 1)` ascending u32 indices) with the live count in
/// word 0 of `count` (on the device), and the pool the kernels' uniforms come from.
#[derive(Clone, Copy, Debug)]
pub struct NetworkBatch<'a> {
    pub scratch: &'a Scratch,
    pub n: usize,
    pub list: &'a wgpu::Buffer,
    pub count: &'a wgpu::Buffer,
}

/// The learned-normal Lambertian factor on Phi's colour (`Shading::LambertLearned`,
/// `gs_core::sunaware::shading`): what [`NetworkIo::encode_phi_scatter`] needs to
/// compute it. `params` holds the Normal group (3 per Gaussian) and the means;
/// `sun_dir` is the unit Sun vector exactly as the CPU's forward uses it (normalised by
/// the caller: the kernels do not normalise it again); `ambient` is `k_a` in [0, 1);
/// `factors` (`2n` f32) receives, per row, `f` and the normal's sign where the Gaussian is
/// lit (0 where `f` is constant), for [`NetworkIo::encode_phi_d_output`].
#[derive(Clone, Copy, Debug)]
pub struct PhiShading<'a> {
    pub params: PackedParams<'a>,
    pub camera_centre: [f32; 3],
    pub sun_dir: [f32; 3],
    pub ambient: f32,
    pub factors: &'a wgpu::Buffer,
}

/// The shading's backward in [`NetworkIo::encode_phi_d_output`]: the forward's
/// [`PhiShading`] (its `factors` as the scatter wrote them), Phi's unshaded output (`n *
/// 3`) and the packed gradient buffer whose Normal group receives the normal's term.
#[derive(Clone, Copy, Debug)]
pub struct PhiShadingGrad<'a> {
    pub shading: PhiShading<'a>,
    pub output: &'a wgpu::Buffer,
    pub grads: &'a wgpu::Buffer,
}

impl PhiShading<'_> {
    /// The uniform's terms after checking the arguments against `n` rows (`grads`, when
    /// given, must hold the packed layout too).
    fn terms(&self, n: usize, grads: Option<&wgpu::Buffer>) -> Result<NormalTerms, GpuError> {
        let offsets = self.params.offsets;
        let mut buffers = vec![("params", self.params.buffer)];
        if let Some(g) = grads {
            buffers.push(("grads", g));
        }
        check_layout(offsets, n, Param::Normal, 3, &buffers)?;
        check_finite3("camera centre", self.camera_centre)?;
        check_finite3("Sun direction", self.sun_dir)?;
        if self.sun_dir.iter().all(|&x| x == 0.0) {
            return Err(GpuError::Invalid("Sun direction has zero length".into()));
        }
        if !(self.ambient.is_finite() && (0.0..1.0).contains(&self.ambient)) {
            return Err(GpuError::Invalid(format!(
                "shading ambient {} is outside [0, 1)",
                self.ambient
            )));
        }
        check_buffer("shading factors", self.factors, 2 * n)?;
        Ok(NormalTerms {
            normal_offset: offsets[Param::Normal.index()],
            sun_unit: self.sun_dir,
            ambient: self.ambient,
        })
    }
}

/// Compiled kernels of the networks' input assembly and output scatter.
pub struct NetworkIo {
    ctx: GpuContext,
    phi_input: wgpu::ComputePipeline,
    phi_scatter: wgpu::ComputePipeline,
    phi_d_output: wgpu::ComputePipeline,
    phi_input_grad: wgpu::ComputePipeline,
    psi_input: wgpu::ComputePipeline,
    psi_scatter: wgpu::ComputePipeline,
    psi_d_output: wgpu::ComputePipeline,
    psi_input_grad: wgpu::ComputePipeline,
}

impl std::fmt::Debug for NetworkIo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "NetworkIo({})", self.ctx.adapter_name())
    }
}

impl NetworkIo {
    /// Compiles the eight kernels on `ctx`'s device.
    pub fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let common = format!("{NETIO_COMMON}\n");
        let rows = format!("{common}{NETIO_INPUT_ROWS}\n");
        let grad = format!("{common}{NETIO_ENCODING_BACKWARD}\n");
        // Phi's kernels that read the learned normal.
        let normal = format!("{common}{NETIO_NORMAL}\n");
        let phi_rows = format!("{normal}{NETIO_INPUT_ROWS}\n");
        let phi_grad = format!("{normal}{NETIO_ENCODING_BACKWARD}\n");
        Ok(Self {
            phi_input: ctx.pipeline("netio_phi_input", &format!("{phi_rows}{NETIO_PHI_INPUT}"))?,
            phi_scatter: ctx
                .pipeline("netio_phi_scatter", &format!("{normal}{NETIO_PHI_SCATTER}"))?,
            phi_d_output: ctx.pipeline(
                "netio_phi_d_output",
                &format!("{common}{NETIO_PHI_D_OUTPUT}"),
            )?,
            phi_input_grad: ctx.pipeline(
                "netio_phi_input_grad",
                &format!("{phi_grad}{NETIO_PHI_INPUT_GRAD}"),
            )?,
            psi_input: ctx.pipeline("netio_psi_input", &format!("{rows}{NETIO_PSI_INPUT}"))?,
            psi_scatter: ctx
                .pipeline("netio_psi_scatter", &format!("{common}{NETIO_PSI_SCATTER}"))?,
            psi_d_output: ctx.pipeline(
                "netio_psi_d_output",
                &format!("{common}{NETIO_PSI_D_OUTPUT}"),
            )?,
            psi_input_grad: ctx.pipeline(
                "netio_psi_input_grad",
                &format!("{grad}{NETIO_PSI_INPUT_GRAD}"),
            )?,
            ctx: ctx.clone(),
        })
    }

    /// Placeholder buffers for the shading's bindings of a kernel run without shading
    /// (read-only ones, which may alias each other, and a writable one).
    fn unused(&self, scratch: &Scratch) -> Result<(wgpu::Buffer, wgpu::Buffer), GpuError> {
        Ok((
            scratch.storage(&self.ctx, "netio unshaded in", 16)?,
            scratch.storage(&self.ctx, "netio unshaded out", 16)?,
        ))
    }

    /// Writes `uniform` to its scratch slot and records one pass of `pipeline` over `n`
    /// rows with `uniform` at binding 0 and `buffers` at 1, 2, ... (`list` and `count`
    /// first: the bindings netio_common.wgsl declares for every kernel).
    fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        scratch: &Scratch,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        uniform: &Uniform,
        buffers: &[&wgpu::Buffer],
    ) -> Result<(), GpuError> {
        let u = scratch.uniform(&self.ctx, label, &uniform.bytes())?;
        let mut all = vec![&u];
        all.extend_from_slice(buffers);
        let bind = self.ctx.bind_group(pipeline, &all);
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(label),
            timestamp_writes: None,
        });
        dispatch_1d(&mut pass, pipeline, &bind, uniform.n as u64);
        Ok(())
    }

    /// Phi's input rows (`n * input_width` f32 in `input`) for `list[0..count]`: row r is
    /// `[f_g | gamma_L(sun) | gamma_L(view_g)]` of g = `list[r]`, view_g the unit vector
    /// from mean_g to the camera centre; rows `>= count` are written as 0. A non-finite
    /// feature or mean, or a Gaussian at the camera centre (view distance not > 0 and
    /// finite), sets `flags` bit 0. With local inputs (`net.inputs()`), the row ends in
    /// `[n.s, n.v, n.h]` (`sunaware::shading::local_inputs`, the Normal group of
    /// `params`, `s = sun_dir` as given: the caller passes the unit vector the CPU's
    /// forward uses), and under `LocalNoSun` the Sun's code is zeros.
    pub fn encode_phi_input(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        net: &AppearanceNet,
        params: PackedParams,
        sun_dir: [f32; 3],
        camera_centre: [f32; 3],
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
            Param::Feature,
            net.feature_dim(),
            &[("params", params)],
        )?;
        check_buffer("Phi input", input, n * width)?;
        check_buffer("flags", flags, 1)?;
        check_finite3("camera centre", camera_centre)?;
        let local = local_terms(net, n, offsets, &[("params", params)], sun_dir)?;
        let mut code = sun_code(net.encoding(), sun_dir)?;
        if !net.inputs().encodes_sun() {
            code.fill(0.0);
        }
        let uniform = Uniform {
            offsets: *offsets,
            n,
            width,
            dim: net.feature_dim(),
            freqs: net.encoding().num_frequencies(),
            camera_centre,
            sun_code: code,
            normal: local,
            local: local.is_some(),
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, params, input, flags];
        self.record(
            encoder,
            scratch,
            "netio phi input",
            &self.phi_input,
            &uniform,
            &buffers,
        )
    }

    /// Phi's output (`n * 3`, row r = `list[r]`'s RGB) into the channels: `chans[g * nc + k]
    /// = output[r * 3 + k]`, k < 3, for r < count, g = `list[r]`; other Gaussians' channels
    /// are not touched. `nc` is 3 or 4. With `shading`, the colour is multiplied by the
    /// Gaussian's learned-normal Lambertian factor `f_g` (`shade_forward`: 1 for a
    /// degenerate or non-finite normal), and row r's `f_g` and sign go to
    /// `shading.factors`.
    pub fn encode_phi_scatter(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        nc: usize,
        output: &wgpu::Buffer,
        shading: Option<PhiShading>,
        chans: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        batch.check_raster_rows(nc, &[3, 4])?;
        check_buffer("Phi output", output, n * PHI_OUT)?;
        check_buffer("channels", chans, n * nc)?;
        let terms = shading.as_ref().map(|s| s.terms(n, None)).transpose()?;
        let uniform = Uniform {
            n,
            nc,
            offsets: shading.map_or([0; Param::COUNT + 1], |s| *s.params.offsets),
            camera_centre: shading.map_or([0.0; 3], |s| s.camera_centre),
            shaded: terms.is_some(),
            normal: terms,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let (unused_in, unused_out) = self.unused(scratch)?;
        let buffers = match shading {
            Some(s) => [list, count, output, chans, s.params.buffer, s.factors],
            None => [list, count, output, chans, &unused_in, &unused_out],
        };
        self.record(
            encoder,
            scratch,
            "netio phi scatter",
            &self.phi_scatter,
            &uniform,
            &buffers,
        )
    }

    /// Phi's output gradient (`n * 3`) from the rasterizer's gradient rows (`n * (13 +
    /// nc)`): `d_out[r * 3 + k] = rows[g * (13 + nc) + 13 + k]` for r < count, g = `list[r]`;
    /// 0 for rows `>= count`. With `shading` (`shade_backward`): that gradient times the
    /// row's `f_g`, and the normal's term of a lit Gaussian ADDED to its Normal row of
    /// `shading.grads` (which the caller cleared; Gaussians not lit get nothing).
    pub fn encode_phi_d_output(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        nc: usize,
        rows: &wgpu::Buffer,
        shading: Option<PhiShadingGrad>,
        d_out: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (scratch, n, list, count) = (batch.scratch, batch.n, batch.list, batch.count);
        batch.check_raster_rows(nc, &[3, 4])?;
        check_buffer("rasterizer gradient rows", rows, n * (ROW_HEAD + nc))?;
        check_buffer("Phi output gradient", d_out, n * PHI_OUT)?;
        let terms = match &shading {
            Some(s) => {
                check_buffer("Phi output", s.output, n * PHI_OUT)?;
                Some(s.shading.terms(n, Some(s.grads))?)
            }
            None => None,
        };
        let uniform = Uniform {
            n,
            nc,
            offsets: shading.map_or([0; Param::COUNT + 1], |s| *s.shading.params.offsets),
            shaded: terms.is_some(),
            normal: terms,
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let (unused_in, unused_out) = self.unused(scratch)?;
        let buffers = match shading {
            Some(s) => [
                list,
                count,
                rows,
                d_out,
                s.shading.params.buffer,
                s.shading.factors,
                s.output,
                s.grads,
            ],
            None => [
                list,
                count,
                rows,
                d_out,
                &unused_in,
                &unused_in,
                &unused_in,
                &unused_out,
            ],
        };
        self.record(
            encoder,
            scratch,
            "netio phi d_output",
            &self.phi_d_output,
            &uniform,
            &buffers,
        )
    }

    /// Phi's input gradient (`d_input`, `n * input_width`) into `grads` (packed like
    /// `params`): for r < count, g = `list[r]`, the Feature row g is set to the row's feature
    /// columns, and the view-direction chain rule of its view columns,
    /// `-(d_view - (d_view . v) v) / |c - mu_g|`, is ADDED to the Mean row g. With local
    /// inputs, the gradient of each row's `[n.s, n.v, n.h]` columns
    /// (`sunaware::shading::scatter_local_input_grad`, `sun_dir` as given to
    /// [`NetworkIo::encode_phi_input`]) is ADDED to the Normal row g, and its mean term
    /// joins the view direction's before their sum is added to the Mean row g (the CPU's
    /// order); a row whose local gradient is all zero, whose normal is degenerate or whose
    /// gradient is not finite adds nothing there. Without local inputs `sun_dir` is not
    /// read.
    #[allow(clippy::too_many_arguments)]
    pub fn encode_phi_input_grad(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        batch: NetworkBatch,
        net: &AppearanceNet,
        params: PackedParams,
        camera_centre: [f32; 3],
        sun_dir: [f32; 3],
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
            Param::Feature,
            net.feature_dim(),
            &[("params", params), ("grads", grads)],
        )?;
        check_buffer("Phi input gradient", d_input, n * width)?;
        check_finite3("camera centre", camera_centre)?;
        let buffers = [("params", params), ("grads", grads)];
        let local = local_terms(net, n, offsets, &buffers, sun_dir)?;
        let uniform = Uniform {
            offsets: *offsets,
            n,
            width,
            dim: net.feature_dim(),
            freqs: net.encoding().num_frequencies(),
            camera_centre,
            normal: local,
            local: local.is_some(),
            ..Uniform::default()
        };
        if n == 0 {
            return Ok(());
        }
        let buffers = [list, count, params, d_input, grads];
        self.record(
            encoder,
            scratch,
            "netio phi input grad",
            &self.phi_input_grad,
            &uniform,
            &buffers,
        )
    }
}

/// The learned normal's terms for Phi's local inputs (`None` without them), after checking
/// that `offsets` hold a Normal group of 3 per Gaussian and `sun_dir` is finite and not
/// zero.
fn local_terms(
    net: &AppearanceNet,
    n: usize,
    offsets: &[u32; Param::COUNT + 1],
    buffers: &[(&str, &wgpu::Buffer)],
    sun_dir: [f32; 3],
) -> Result<Option<NormalTerms>, GpuError> {
    if net.inputs().local_width() == 0 {
        return Ok(None);
    }
    check_layout(offsets, n, Param::Normal, 3, buffers)?;
    check_finite3("Sun direction", sun_dir)?;
    if sun_dir.iter().all(|&x| x == 0.0) {
        return Err(GpuError::Invalid("Sun direction has zero length".into()));
    }
    Ok(Some(NormalTerms {
        normal_offset: offsets[Param::Normal.index()],
        sun_unit: sun_dir,
        ambient: 0.0,
    }))
}
