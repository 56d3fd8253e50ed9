//! The `NetIo` uniform of the network kernels (netio_common.wgsl) as the host writes it,
//! and the checks of host arguments that every `encode_*` of [`super::NetworkIo`] runs
//! before recording (a [`GpuError::Invalid`] or [`GpuError::TooLarge`]).

use super::{NetworkBatch, ROW_HEAD, SUN_CODE_CAPACITY, SUN_CODE_WORD, UNIFORM_BYTES};
use crate::{u32_bytes, GpuError};
use gs_core::model::Param;
use gs_core::nn::SceneBox;
use gs_core::sunaware::shading::{MIN_HALF_NORM2, MIN_NORMAL_NORM2};

/// What one kernel's uniform says (the `NetIo` struct of netio_common.wgsl).
#[derive(Default)]
pub(super) struct Uniform {
    pub(super) offsets: [u32; Param::COUNT + 1],
    pub(super) n: usize,
    pub(super) nc: usize,
    pub(super) width: usize,
    pub(super) dim: usize,
    pub(super) freqs: usize,
    /// `Some(gain)`: Psi's output multiplies `gain * V` (ShadowRefinement::Multiply).
    pub(super) multiply_gain: Option<f32>,
    pub(super) camera_centre: [f32; 3],
    pub(super) box_min: [f32; 3],
    pub(super) box_extent: [f32; 3],
    pub(super) box_inv_extent: [f32; 3],
    pub(super) sun_code: Vec<f32>,
    /// The learned normal's terms (the shading in Phi's scatter and output gradient, the
    /// local inputs in Phi's input rows and input gradient).
    pub(super) normal: Option<NormalTerms>,
    /// The kernel applies the learned-normal shading (`normal` is set).
    pub(super) shaded: bool,
    /// Phi's rows end in the local inputs `[n.s, n.v, n.h]` (`normal` is set).
    pub(super) local: bool,
}

/// What the `NetIo` uniform holds for the learned normal: the start of the Normal group,
/// the unit Sun vector as the CPU uses it and the shading's ambient floor.
#[derive(Clone, Copy)]
pub(super) struct NormalTerms {
    pub(super) normal_offset: u32,
    pub(super) sun_unit: [f32; 3],
    pub(super) ambient: f32,
}

impl Uniform {
    pub(super) fn bytes(&self) -> Vec<u8> {
        let mut words = [0u32; UNIFORM_BYTES / 4];
        words[..8].copy_from_slice(&self.offsets[..8]);
        for (w, v) in words[8..14].iter_mut().zip([
            self.n,
            self.nc,
            self.width,
            self.dim,
            self.freqs,
            usize::from(self.multiply_gain.is_some()),
        ]) {
            // Validated to fit u32 before any uniform is built.
            *w = v as u32;
        }
        words[14] = self.multiply_gain.unwrap_or(1.0).to_bits();
        words[15] = u32::from(self.local);
        let vec4 = |words: &mut [u32], at: usize, v: [f32; 3]| {
            for (w, x) in words[at..at + 3].iter_mut().zip(v) {
                *w = x.to_bits();
            }
        };
        vec4(&mut words, 16, self.camera_centre);
        vec4(&mut words, 20, self.box_min);
        vec4(&mut words, 24, self.box_extent);
        vec4(&mut words, 28, self.box_inv_extent);
        if let Some(t) = self.normal {
            vec4(&mut words, 32, t.sun_unit);
            words[35] = MIN_HALF_NORM2.to_bits();
            words[36] = t.normal_offset;
            words[37] = u32::from(self.shaded);
            words[38] = MIN_NORMAL_NORM2.to_bits();
            words[39] = t.ambient.to_bits();
        }
        for (w, x) in words[SUN_CODE_WORD..].iter_mut().zip(&self.sun_code) {
            *w = x.to_bits();
        }
        u32_bytes(&words)
    }
}

/// `v` scaled to unit length in f64, as `nn::gather::unit_vector` (the CPU's Sun
/// normalisation); a non-finite or zero vector is an error.
pub(super) fn unit_vector(what: &str, v: [f32; 3]) -> Result<[f32; 3], GpuError> {
    if v.iter().any(|x| !x.is_finite()) {
        return Err(GpuError::Invalid(format!("{what} {v:?} is not finite")));
    }
    let norm = (v[0] as f64).hypot(v[1] as f64).hypot(v[2] as f64);
    if norm < 1e-12 {
        return Err(GpuError::Invalid(format!("{what} {v:?} has zero length")));
    }
    Ok([
        (v[0] as f64 / norm) as f32,
        (v[1] as f64 / norm) as f32,
        (v[2] as f64 / norm) as f32,
    ])
}

/// gamma_L of the unit Sun direction, by the CPU encoding (the same bits as its rows).
pub(super) fn sun_code(
    encoding: gs_core::nn::PositionalEncoding,
    sun_dir: [f32; 3],
) -> Result<Vec<f32>, GpuError> {
    let sun = unit_vector("Sun direction", sun_dir)?;
    let mut code = vec![0.0f32; encoding.width(3)];
    encoding
        .encode(&sun, &mut code)
        .map_err(|e| GpuError::Invalid(format!("Sun direction encoding: {e}")))?;
    if code.len() > SUN_CODE_CAPACITY {
        return Err(GpuError::Invalid(format!(
            "{} Sun-code values exceed the uniform's {SUN_CODE_CAPACITY}",
            code.len()
        )));
    }
    Ok(code)
}

/// `buf` holds at least `floats` 4-byte values.
pub(super) fn check_buffer(what: &str, buf: &wgpu::Buffer, floats: usize) -> Result<(), GpuError> {
    let need = floats as u64 * 4;
    if buf.size() < need {
        return Err(GpuError::Invalid(format!(
            "{what} buffer has {} bytes, needs {need}",
            buf.size()
        )));
    }
    Ok(())
}

impl NetworkBatch<'_> {
    /// The batch's rows, `widest` values at most, fit 32-bit indexing ([`check_rows`]),
    /// and its list and count buffers hold it ([`check_batch`]).
    pub(super) fn check(&self, widest: usize) -> Result<(), GpuError> {
        check_rows(self.n, widest)?;
        check_batch(self.n, self.list, self.count)
    }

    /// [`NetworkBatch::check`] for the kernels over the rasterizer's rows: `nc` is one of
    /// `allowed` channel counts and the rows are `ROW_HEAD + nc` wide.
    pub(super) fn check_raster_rows(&self, nc: usize, allowed: &[usize]) -> Result<(), GpuError> {
        check_channels(nc, allowed)?;
        self.check(ROW_HEAD + nc)
    }
}

/// `n` and every row-index product the kernels form (`n * widest`) fit u32.
fn check_rows(n: usize, widest: usize) -> Result<(), GpuError> {
    if (n as u64).saturating_mul(widest.max(1) as u64) > u32::MAX as u64 {
        return Err(GpuError::TooLarge(format!(
            "{n} rows of {widest} values exceed 32-bit indexing"
        )));
    }
    Ok(())
}

/// `list` (max(n, 1) u32) and `count` (1 u32).
fn check_batch(n: usize, list: &wgpu::Buffer, count: &wgpu::Buffer) -> Result<(), GpuError> {
    check_buffer("list", list, n.max(1))?;
    check_buffer("count", count, 1)
}

/// The offsets are a packed layout of `n` rows whose Mean group is `3n` wide and whose
/// `group` is `n * dim` wide, and `params` (and `grads`, when given) hold all of it.
pub(super) fn check_layout(
    offsets: &[u32; Param::COUNT + 1],
    n: usize,
    group: Param,
    dim: usize,
    buffers: &[(&str, &wgpu::Buffer)],
) -> Result<(), GpuError> {
    if offsets[0] != 0 || offsets.windows(2).any(|w| w[1] < w[0]) {
        return Err(GpuError::Invalid(format!(
            "parameter offsets {offsets:?} do not start at 0 and increase"
        )));
    }
    let size = |p: Param| (offsets[p.index() + 1] - offsets[p.index()]) as u64;
    for (p, width) in [(Param::Mean, 3), (group, dim)] {
        if size(p) != (n * width) as u64 {
            return Err(GpuError::Invalid(format!(
                "parameter offsets {offsets:?}: group {p:?} holds {} values, expected {n} x {width}",
                size(p)
            )));
        }
    }
    for (what, buf) in buffers {
        check_buffer(what, buf, offsets[Param::COUNT] as usize)?;
    }
    Ok(())
}

pub(super) fn check_finite3(what: &str, v: [f32; 3]) -> Result<(), GpuError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(GpuError::Invalid(format!("{what} {v:?} is not finite")))
    }
}

/// The scene box's corner, extent and inverse extent as shadow.rs forms them (f32).
pub(super) fn box_terms(scene_box: &SceneBox) -> ([f32; 3], [f32; 3], [f32; 3]) {
    let (min, max) = (scene_box.min_m(), scene_box.max_m());
    let extent: [f32; 3] = std::array::from_fn(|a| max[a] - min[a]);
    let inv: [f32; 3] = std::array::from_fn(|a| 1.0 / (max[a] - min[a]));
    (min, extent, inv)
}

fn check_channels(nc: usize, allowed: &[usize]) -> Result<(), GpuError> {
    if allowed.contains(&nc) {
        Ok(())
    } else {
        Err(GpuError::Invalid(format!(
            "{nc} channels per Gaussian, expected one of {allowed:?}"
        )))
    }
}
