//! The packed, group-major layout of per-Gaussian values on the device, and the buffers
//! that hold the Gaussians' training state in it ([`GaussianBuffers`]).
//!
//! Layout: every per-Gaussian buffer (parameters, gradients, both Adam moments) is one
//! packed array in [`Param`] order: group `g` holds its `n * dim(g)` values, row-major,
//! starting at `offsets[g]` (a [`ParamSet`]'s groups laid end to end). The statistics
//! buffer holds `grad_accum`, `visible_count` and `max_radius_px`, `n` each
//! (resident_stats.wgsl).
//!
//! Invariants: [`pack`] and [`unpack`] are exact inverses (values are copied, never
//! converted); [`offsets`] refuses layouts whose values a `u32` cannot index; buffer
//! writes are padded to whole words ([`pad4`]).

use super::{bytes_f32, bytes_u32, f32_bytes, u32_bytes, GpuContext, GpuError};
use gs_core::densify::DensifyStats;
use gs_core::model::{Param, ParamSet};
use gs_core::optim::Adam;

/// A packed group-major parameter buffer (or its gradient) on the device and its group
/// starts (`offsets`).
#[derive(Clone, Copy, Debug)]
pub struct PackedParams<'a> {
    pub buffer: &'a wgpu::Buffer,
    pub offsets: &'a [u32; Param::COUNT + 1],
}

/// The Gaussians' device state, sized for `capacity` Gaussians: the packed parameters,
/// a gradient of the same layout, both Adam moments and the densification statistics
/// (`grad_accum`, `visible_count`, `max_radius_px`, `n` each: resident_stats.wgsl).
pub(crate) struct GaussianBuffers {
    pub capacity: usize,
    pub params: wgpu::Buffer,
    pub grads: wgpu::Buffer,
    pub m: wgpu::Buffer,
    pub v: wgpu::Buffer,
    pub stats: wgpu::Buffer,
}

impl GaussianBuffers {
    /// Buffers for `capacity` rows of `dims` (labels start with `label`).
    pub(crate) fn allocate(
        ctx: &GpuContext,
        label: &str,
        dims: &[usize; Param::COUNT],
        capacity: usize,
    ) -> Result<Self, GpuError> {
        let values = (row_width(dims) * capacity).max(1) as u64 * 4;
        Ok(Self {
            capacity,
            params: ctx.storage(&format!("{label} params"), values)?,
            grads: ctx.storage(&format!("{label} grads"), values)?,
            m: ctx.storage(&format!("{label} adam m"), values)?,
            v: ctx.storage(&format!("{label} adam v"), values)?,
            stats: ctx.storage(
                &format!("{label} densify stats"),
                capacity.max(1) as u64 * 12,
            )?,
        })
    }

    /// Writes the host's parameters, moments and statistics (the caller checked their
    /// shapes against each other and that they fit the capacity).
    pub(crate) fn write(
        &self,
        ctx: &GpuContext,
        params: &ParamSet,
        adam: &Adam,
        stats: &DensifyStats,
    ) {
        let q = &ctx.queue;
        q.write_buffer(&self.params, 0, &pad4(f32_bytes(&pack(params))));
        q.write_buffer(&self.m, 0, &pad4(f32_bytes(&pack(&adam.m))));
        q.write_buffer(&self.v, 0, &pad4(f32_bytes(&pack(&adam.v))));
        let mut words: Vec<u32> = stats.grad_accum.iter().map(|v| v.to_bits()).collect();
        words.extend_from_slice(&stats.visible_count);
        words.extend(stats.max_radius_px.iter().map(|v| v.to_bits()));
        q.write_buffer(&self.stats, 0, &pad4(u32_bytes(&words)));
    }

    /// Reads the first `params.len()` rows back into the host's parameters, moments and
    /// statistics (shapes checked by the caller; `adam.step` is the caller's to set).
    pub(crate) fn read(
        &self,
        ctx: &GpuContext,
        params: &mut ParamSet,
        adam: &mut Adam,
        stats: &mut DensifyStats,
    ) -> Result<(), GpuError> {
        let n = params.len();
        let values = (row_width(&params.dims()) * n) as u64 * 4;
        let back = ctx.read_back(
            ctx.encoder("resident download"),
            &[
                (&self.params, values),
                (&self.m, values),
                (&self.v, values),
                (&self.stats, n as u64 * 12),
            ],
        )?;
        unpack(&bytes_f32(&back[0]), params);
        unpack(&bytes_f32(&back[1]), &mut adam.m);
        unpack(&bytes_f32(&back[2]), &mut adam.v);
        let words = bytes_u32(&back[3]);
        stats.grad_accum = words[..n].iter().map(|w| f32::from_bits(*w)).collect();
        stats.visible_count = words[n..2 * n].to_vec();
        stats.max_radius_px = words[2 * n..3 * n]
            .iter()
            .map(|w| f32::from_bits(*w))
            .collect();
        Ok(())
    }
}

pub(crate) fn row_width(dims: &[usize; Param::COUNT]) -> usize {
    dims.iter().sum()
}

/// Start of each group in the packed layout for `n` rows, and the total.
pub(crate) fn offsets(
    dims: &[usize; Param::COUNT],
    n: usize,
) -> Result<[u32; Param::COUNT + 1], GpuError> {
    let mut out = [0u32; Param::COUNT + 1];
    let mut at = 0u64;
    for (g, d) in dims.iter().enumerate() {
        out[g] = u32::try_from(at)
            .map_err(|_| GpuError::TooLarge(format!("{n} Gaussians of {dims:?} values")))?;
        at += (*d as u64) * n as u64;
    }
    out[Param::COUNT] = u32::try_from(at)
        .map_err(|_| GpuError::TooLarge(format!("{n} Gaussians of {dims:?} values")))?;
    Ok(out)
}

/// A [`ParamSet`]'s groups end to end.
pub(crate) fn pack(set: &ParamSet) -> Vec<f32> {
    let mut out = Vec::with_capacity(set.len() * row_width(&set.dims()));
    for p in Param::ALL {
        out.extend_from_slice(set.get(p));
    }
    out
}

/// Packed values back into `set` (same dims and rows).
pub(crate) fn unpack(values: &[f32], set: &mut ParamSet) {
    let mut at = 0;
    for p in Param::ALL {
        let dst = set.get_mut(p);
        let len = dst.len();
        dst.copy_from_slice(&values[at..at + len]);
        at += len;
    }
}

/// Pads to a multiple of 4 bytes, at least 4 (`write_buffer` needs both).
pub(crate) fn pad4(mut bytes: Vec<u8>) -> Vec<u8> {
    bytes.resize(bytes.len().max(4).next_multiple_of(4), 0);
    bytes
}
