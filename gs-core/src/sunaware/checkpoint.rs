//! Checkpoint of a whole [`SunAwareTrainer`]: resuming from it continues bit-exactly.
//!
//! File layout (all integers and floats little-endian):
//! ```text
//! magic     8 bytes  b"SUNGSCKP"
//! version   u32      8 (older ones are still read: 7 has no colour space byte,
//!                    meaning sRGB; 6 also no appearance inputs byte, meaning the paper's; 5 also no normal rate, meaning the default; 4 also no shading fields and means none; 3 also no shadow
//!                    gain, meaning 1; 2 also no hidden-width field, Phi is 256 wide; 1
//!                    also no shadow refinement byte, Replace)
//! length    u64      payload bytes
//! payload   length bytes (below)
//! checksum  u64      FNV-1a 64 of the payload
//! ```
//! Payload, in order:
//! 1. config: variant u8 (0..3 = a..d), sh_degree u32, sh_degree_interval u64,
//!    feature_dim u64, shadow_latent_dim u64, encoding_frequencies u64, lambda_dssim f32,
//!    lambda_iso f32, iso_reduction u8 (0 sum, 1 mean over entries), light projection u8
//!    (0 perspective, 1 orthographic), light resolution u32, footprint radius f32, depth bias
//!    fraction f32, fov margin f32, 11 learning rates f32 (position init, position final,
//!    sh dc, sh rest, opacity, scale, rotation, feature, shadow latent, appearance MLP, shadow
//!    MLP), densify 6 f32 (grad threshold, percent dense, min opacity, max screen radius,
//!    max world scale fraction, split divisor), size_prune u8, max_gaussians u64,
//!    densify_from_step u64,
//!    background 3 f32, near_m f32, seed u64, feature_init_std f32, from version 2
//!    shadow refinement u8 (0 replace, 1 multiply), from version 3 appearance hidden width
//!    u64 (the width of Phi's hidden layers: the weights' shape depends on it), from
//!    version 4 shadow gain f32, from version 5 shading u8 (0 none, 1 Lambert, 2 Lambert
//!    with a learned normal) and shading ambient f32, from version 6 the learned normal's
//!    learning rate f32, from version 7 Phi's appearance inputs u8 (0 paper, 1 local,
//!    2 local without the Sun's encoding: Phi's input width depends on it), from version 8
//!    the colour space u8 (0 sRGB, 1 linear);
//! 2. scene box: min 3 f32, max 3 f32;
//! 3. Gaussians: count u64, then each group of `Param::ALL` in order (count x width f32,
//!    widths from the config's layout);
//! 4. Gaussian Adam: beta1 f32, beta2 f32, eps f32, step u64, first moments (groups as in
//!    3), second moments;
//! 5. Phi then Psi, each: present u8; if 1: weight count u64, weights f32, Adam first
//!    moments f32, second moments f32 (same count), step u64;
//! 6. densification statistics: count x f32 gradient sums, count x u32 visible counts,
//!    count x f32 max radii;
//! 7. counters u64: steps, skipped_nonfinite, raster_dropped, densify_count.
//!
//! There is no other state: densification draws from streams seeded by the config's seed
//! and `densify_count`, and online rounds shuffle with seeds derived from the round number.
//! Loading checks the magic, version, length, checksum, every size field against its bound
//! (the configuration's limits on widths and counts, [`crate::nn::mlp::MAX_MLP_PARAMS`])
//! and every count against the bytes left, all before allocating (so no allocation exceeds
//! a small multiple of the file); then every value for finiteness, Adam's betas (in
//! [0, 1)), eps (in (0, 1]), step (at most [`MAX_ADAM_STEP`]) and second moments (>= 0).
//! Any failure is a [`SunAwareError::Checkpoint`] naming the problem. [`save`],
//! [`save_file`] and [`checked_to_bytes`] refuse a trainer the loader would refuse.

use std::io::{Read, Write};
use std::path::Path;

use crate::densify::{DensifyConfig, DensifyStats};
use crate::model::{GaussianModel, Param, ParamSet};
use crate::nn::{AppearanceNet, PositionalEncoding, SceneBox, ShadowNet};
use crate::optim::Adam;
use crate::regularizer::IsoReduction;

use super::config::{
    AppearanceInputs, ColourSpace, LightConfig, LightProjection, Shading, ShadowRefinement,
    SunAwareConfig, SunAwareRates, Variant,
};
use super::error::SunAwareError;
use super::model::SunAwareModel;
use super::trainer::{FlatAdam, SunAwareTrainer};

pub const MAGIC: [u8; 8] = *b"SUNGSCKP";
pub const VERSION: u32 = 8;
/// Oldest version [`from_bytes`] reads.
pub const OLDEST_READABLE_VERSION: u32 = 1;
/// Largest Adam step a checkpoint may hold: the bias correction raises the betas to the
/// step as an `i32`.
pub const MAX_ADAM_STEP: u64 = i32::MAX as u64;

/// FNV-1a, 64 bit.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

struct Writer(Vec<u8>);

impl Writer {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32s(&mut self, v: &[f32]) {
        for &x in v {
            self.f32(x);
        }
    }
    fn params(&mut self, p: &ParamSet) {
        for g in Param::ALL {
            self.f32s(p.get(g));
        }
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

fn ck(m: impl Into<String>) -> SunAwareError {
    SunAwareError::Checkpoint(m.into())
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], SunAwareError> {
        if self.buf.len() - self.pos < n {
            return Err(ck(format!("truncated while reading {what}")));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u8(&mut self, what: &str) -> Result<u8, SunAwareError> {
        Ok(self.take(1, what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32, SunAwareError> {
        Ok(u32::from_le_bytes(
            self.take(4, what)?.try_into().expect("4 bytes"),
        ))
    }
    fn u64(&mut self, what: &str) -> Result<u64, SunAwareError> {
        Ok(u64::from_le_bytes(
            self.take(8, what)?.try_into().expect("8 bytes"),
        ))
    }
    fn usize(&mut self, what: &str) -> Result<usize, SunAwareError> {
        usize::try_from(self.u64(what)?).map_err(|_| ck(format!("{what} does not fit in memory")))
    }
    fn f32(&mut self, what: &str) -> Result<f32, SunAwareError> {
        let v = f32::from_le_bytes(self.take(4, what)?.try_into().expect("4 bytes"));
        if v.is_finite() {
            Ok(v)
        } else {
            Err(ck(format!("{what} is not finite")))
        }
    }
    fn f32s(&mut self, n: usize, what: &str) -> Result<Vec<f32>, SunAwareError> {
        let bytes = n
            .checked_mul(4)
            .ok_or_else(|| ck(format!("{what}: count overflows")))?;
        let raw = self.take(bytes, what)?;
        let out: Vec<f32> = raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect();
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(ck(format!("{what}: value {i} is not finite")));
        }
        Ok(out)
    }
    fn params(&mut self, into: &mut ParamSet, what: &str) -> Result<(), SunAwareError> {
        for g in Param::ALL {
            let n = into.get(g).len();
            let v = self.f32s(n, &format!("{what} {}", g.name()))?;
            into.get_mut(g).copy_from_slice(&v);
        }
        Ok(())
    }
}

fn write_config(w: &mut Writer, c: &SunAwareConfig) {
    w.u8(c.variant.code());
    w.u32(c.sh_degree);
    w.u64(c.sh_degree_interval);
    w.u64(c.feature_dim as u64);
    w.u64(c.shadow_latent_dim as u64);
    w.u64(c.encoding_frequencies as u64);
    w.f32(c.lambda_dssim);
    w.f32(c.lambda_iso);
    w.u8(match c.iso_reduction {
        IsoReduction::Sum => 0,
        IsoReduction::MeanOverEntries => 1,
    });
    w.u8(match c.light.projection {
        LightProjection::Perspective => 0,
        LightProjection::Orthographic => 1,
    });
    w.u32(c.light.resolution_px);
    w.f32(c.light.footprint_radius_px);
    w.f32(c.light.depth_bias_fraction);
    w.f32(c.light.fov_margin);
    let r = &c.lr;
    w.f32s(&[
        r.position_init,
        r.position_final,
        r.sh_dc,
        r.sh_rest,
        r.opacity,
        r.scale,
        r.rotation,
        r.feature,
        r.shadow_latent,
        r.appearance_mlp,
        r.shadow_mlp,
    ]);
    let d = &c.densify;
    w.f32s(&[
        d.grad_threshold,
        d.percent_dense,
        d.min_opacity,
        d.max_screen_radius_px,
        d.max_world_scale_fraction,
        d.split_scale_divisor,
    ]);
    w.u8(c.size_prune as u8);
    w.u64(c.max_gaussians as u64);
    w.u64(c.densify_from_step);
    w.f32s(&c.background);
    w.f32(c.near_m);
    w.u64(c.seed);
    w.f32(c.feature_init_std);
    w.u8(match c.shadow_refinement {
        ShadowRefinement::Replace => 0,
        ShadowRefinement::Multiply => 1,
    });
    w.u64(c.appearance_hidden_width as u64);
    w.f32(c.shadow_gain);
    w.u8(c.shading.code());
    w.f32(c.shading_ambient);
    w.f32(c.lr.normal);
    w.u8(c.appearance_inputs.code());
    w.u8(c.colour_space.code());
}

fn read_config(r: &mut Reader, version: u32) -> Result<SunAwareConfig, SunAwareError> {
    let code = r.u8("variant")?;
    let variant = Variant::from_code(code).ok_or_else(|| ck(format!("unknown variant {code}")))?;
    let sh_degree = r.u32("sh_degree")?;
    let sh_degree_interval = r.u64("sh_degree_interval")?;
    let feature_dim = r.usize("feature_dim")?;
    let shadow_latent_dim = r.usize("shadow_latent_dim")?;
    let encoding_frequencies = r.usize("encoding_frequencies")?;
    let lambda_dssim = r.f32("lambda_dssim")?;
    let lambda_iso = r.f32("lambda_iso")?;
    let iso_reduction = match r.u8("iso_reduction")? {
        0 => IsoReduction::Sum,
        1 => IsoReduction::MeanOverEntries,
        other => return Err(ck(format!("unknown iso reduction {other}"))),
    };
    let projection = match r.u8("light projection")? {
        0 => LightProjection::Perspective,
        1 => LightProjection::Orthographic,
        other => return Err(ck(format!("unknown light projection {other}"))),
    };
    let light = LightConfig {
        projection,
        resolution_px: r.u32("light resolution")?,
        footprint_radius_px: r.f32("footprint radius")?,
        depth_bias_fraction: r.f32("depth bias")?,
        fov_margin: r.f32("fov margin")?,
    };
    let v = r.f32s(11, "learning rates")?;
    let lr = SunAwareRates {
        position_init: v[0],
        position_final: v[1],
        sh_dc: v[2],
        sh_rest: v[3],
        opacity: v[4],
        scale: v[5],
        rotation: v[6],
        feature: v[7],
        shadow_latent: v[8],
        appearance_mlp: v[9],
        shadow_mlp: v[10],
        // Version 6 stores it after the shading fields (read below).
        normal: SunAwareRates::default().normal,
    };
    // The grad threshold may be infinite in memory only transiently; stored values are finite.
    let d = r.f32s(6, "densify settings")?;
    let densify = DensifyConfig {
        grad_threshold: d[0],
        percent_dense: d[1],
        min_opacity: d[2],
        max_screen_radius_px: d[3],
        max_world_scale_fraction: d[4],
        split_scale_divisor: d[5],
    };
    let size_prune = r.u8("size_prune")? != 0;
    let max_gaussians = r.usize("max_gaussians")?;
    let densify_from_step = r.u64("densify_from_step")?;
    let bg = r.f32s(3, "background")?;
    let mut config = SunAwareConfig {
        variant,
        sh_degree,
        sh_degree_interval,
        feature_dim,
        shadow_latent_dim,
        encoding_frequencies,
        lambda_dssim,
        lambda_iso,
        iso_reduction,
        light,
        lr,
        densify,
        size_prune,
        max_gaussians,
        densify_from_step,
        background: [bg[0], bg[1], bg[2]],
        near_m: r.f32("near_m")?,
        seed: r.u64("seed")?,
        feature_init_std: r.f32("feature_init_std")?,
        // Version 1 predates the switch: its models were trained with Psi replacing V.
        shadow_refinement: if version >= 2 {
            match r.u8("shadow refinement")? {
                0 => ShadowRefinement::Replace,
                1 => ShadowRefinement::Multiply,
                other => return Err(ck(format!("unknown shadow refinement {other}"))),
            }
        } else {
            ShadowRefinement::Replace
        },
        // Before version 3 Phi's width was fixed at the paper's 256.
        appearance_hidden_width: if version >= 3 {
            r.usize("appearance hidden width")?
        } else {
            crate::nn::appearance::DEFAULT_APPEARANCE_HIDDEN_WIDTH
        },
        // Before version 4, V' = V * Psi.
        shadow_gain: if version >= 4 {
            r.f32("shadow gain")?
        } else {
            1.0
        },
        // Before version 5, the paper's unshaded colour.
        shading: if version >= 5 {
            let code = r.u8("shading")?;
            Shading::from_code(code).ok_or_else(|| ck(format!("unknown shading {code}")))?
        } else {
            Shading::None
        },
        shading_ambient: if version >= 5 {
            r.f32("shading ambient")?
        } else {
            SunAwareConfig::default().shading_ambient
        },
        ..SunAwareConfig::default()
    };
    // Before version 6, the default rate (no stored model had a learned normal).
    if version >= 6 {
        config.lr.normal = r.f32("normal learning rate")?;
    }
    // Before version 7, Phi read the paper's row.
    if version >= 7 {
        let code = r.u8("appearance inputs")?;
        config.appearance_inputs = AppearanceInputs::from_code(code)
            .ok_or_else(|| ck(format!("unknown appearance inputs {code}")))?;
    }
    // Before version 8, the model blended sRGB colours.
    if version >= 8 {
        let code = r.u8("colour space")?;
        config.colour_space = ColourSpace::from_code(code)
            .ok_or_else(|| ck(format!("unknown colour space {code}")))?;
    }
    config
        .validate()
        .map_err(|e| ck(format!("stored configuration is invalid: {e}")))?;
    Ok(config)
}

/// Weights of Phi and Psi for `config` (0 for an absent network), from the sizes alone.
fn network_weights(config: &SunAwareConfig) -> Result<[usize; 2], SunAwareError> {
    let encoding = PositionalEncoding::new(config.encoding_frequencies)?;
    let phi = if config.variant.uses_appearance_mlp() {
        AppearanceNet::param_count(
            config.feature_dim,
            config.appearance_hidden_width,
            encoding,
            config.appearance_inputs,
        )?
    } else {
        0
    };
    let psi = if config.variant.uses_shadow() {
        ShadowNet::param_count(config.shadow_latent_dim, encoding)?
    } else {
        0
    };
    Ok([phi, psi])
}

/// Bytes that follow the Gaussians for `n` Gaussians of `row_bytes` and networks of
/// `weights`: Adam (header and two moment sets), each network (presence byte; count,
/// weights, two moments and step when present), densify statistics and the counters.
fn bytes_after_gaussians(n: usize, row_bytes: usize, weights: [usize; 2]) -> Option<usize> {
    let net = |w: usize| match w {
        0 => Some(1),
        w => w.checked_mul(12)?.checked_add(17),
    };
    n.checked_mul(row_bytes)?
        .checked_mul(2)?
        .checked_add(20)?
        .checked_add(net(weights[0])?)?
        .checked_add(net(weights[1])?)?
        .checked_add(n.checked_mul(12)?)?
        .checked_add(32)
}

fn check_adam(
    beta1: f32,
    beta2: f32,
    eps: f32,
    step: u64,
    what: &str,
) -> Result<(), SunAwareError> {
    for (name, beta) in [("beta1", beta1), ("beta2", beta2)] {
        if !(0.0..1.0).contains(&beta) {
            return Err(ck(format!("{what} Adam {name} {beta} is outside [0, 1)")));
        }
    }
    if !(eps > 0.0 && eps <= 1.0) {
        return Err(ck(format!("{what} Adam eps {eps} is outside (0, 1]")));
    }
    if step > MAX_ADAM_STEP {
        return Err(ck(format!(
            "{what} Adam step {step} is above {MAX_ADAM_STEP}"
        )));
    }
    Ok(())
}

/// A negative second moment would put NaN (its square root) into the parameters.
fn check_second_moment(v: &[f32], what: &str) -> Result<(), SunAwareError> {
    match v.iter().position(|&x| x < 0.0) {
        Some(i) => Err(ck(format!("{what} second moment value {i} is negative"))),
        None => Ok(()),
    }
}

fn write_net(w: &mut Writer, params: Option<&[f32]>, adam: &FlatAdam) {
    match params {
        None => w.u8(0),
        Some(p) => {
            w.u8(1);
            w.u64(p.len() as u64);
            w.f32s(p);
            w.f32s(&adam.m);
            w.f32s(&adam.v);
            w.u64(adam.step);
        }
    }
}

fn read_net(
    r: &mut Reader,
    params: Option<&mut [f32]>,
    what: &str,
) -> Result<FlatAdam, SunAwareError> {
    let present = r.u8(what)? != 0;
    match (present, params) {
        (false, None) => Ok(FlatAdam::new(0)),
        (true, Some(params)) => {
            let n = r.usize(what)?;
            if n != params.len() {
                return Err(ck(format!(
                    "{what} has {n} weights, the configuration needs {}",
                    params.len()
                )));
            }
            params.copy_from_slice(&r.f32s(n, what)?);
            let m = r.f32s(n, what)?;
            let v = r.f32s(n, &format!("{what} second moment"))?;
            check_second_moment(&v, what)?;
            let step = r.u64(what)?;
            // The networks' Adam has fixed betas and eps; only the step is stored.
            check_adam(0.9, 0.999, crate::optim::ADAM_EPS, step, what)?;
            Ok(FlatAdam { m, v, step })
        }
        _ => Err(ck(format!(
            "{what}: presence does not match the configuration"
        ))),
    }
}

/// Serialises the trainer (model, optimiser, statistics, counters) to bytes.
pub fn to_bytes(t: &SunAwareTrainer) -> Vec<u8> {
    let mut w = Writer(Vec::new());
    let m = &t.model;
    write_config(&mut w, &m.config);
    w.f32s(&m.scene_box.min_m());
    w.f32s(&m.scene_box.max_m());
    w.u64(m.len() as u64);
    w.params(&m.gaussians.params);
    w.f32(t.adam.beta1);
    w.f32(t.adam.beta2);
    w.f32(t.adam.eps);
    w.u64(t.adam.step);
    w.params(&t.adam.m);
    w.params(&t.adam.v);
    write_net(
        &mut w,
        m.appearance.as_ref().map(|n| n.mlp.params()),
        &t.appearance_adam,
    );
    write_net(
        &mut w,
        m.shadow.as_ref().map(|n| n.mlp.params()),
        &t.shadow_adam,
    );
    w.f32s(&t.densify_stats.grad_accum);
    for &c in &t.densify_stats.visible_count {
        w.u32(c);
    }
    w.f32s(&t.densify_stats.max_radius_px);
    w.u64(t.steps);
    w.u64(t.skipped_nonfinite);
    w.u64(t.raster_dropped);
    w.u64(t.densify_count);
    let payload = w.0;
    let mut out = Vec::with_capacity(payload.len() + 28);
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&payload);
    out.extend_from_slice(&fnv1a64(&payload).to_le_bytes());
    out
}

/// [`to_bytes`], refusing a trainer that [`from_bytes`] would refuse (a non-finite or
/// negative moment, an out-of-range Adam setting): nothing is written that cannot be read.
pub fn checked_to_bytes(t: &SunAwareTrainer) -> Result<Vec<u8>, SunAwareError> {
    let bytes = to_bytes(t);
    match from_bytes(&bytes) {
        Ok(_) => Ok(bytes),
        Err(SunAwareError::Checkpoint(why)) => Err(ck(format!(
            "not written, the reader would refuse it: {why}"
        ))),
        Err(other) => Err(other),
    }
}

/// Restores a trainer from [`to_bytes`]'s output.
pub fn from_bytes(bytes: &[u8]) -> Result<SunAwareTrainer, SunAwareError> {
    if bytes.len() < 28 {
        return Err(ck("file is shorter than the header"));
    }
    if bytes[..8] != MAGIC {
        return Err(ck("not a Sun-aware checkpoint (bad magic)"));
    }
    let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if !(OLDEST_READABLE_VERSION..=VERSION).contains(&version) {
        return Err(ck(format!(
            "version {version} is not supported (this build reads \
             {OLDEST_READABLE_VERSION} to {VERSION})"
        )));
    }
    let len = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
    if len != (bytes.len() - 28) as u64 {
        return Err(ck(format!(
            "payload length {len} does not match the file ({} bytes of payload)",
            bytes.len() - 28
        )));
    }
    let payload = &bytes[20..bytes.len() - 8];
    let stored = u64::from_le_bytes(bytes[bytes.len() - 8..].try_into().expect("8 bytes"));
    if fnv1a64(payload) != stored {
        return Err(ck("checksum mismatch (file corrupted)"));
    }
    let mut r = Reader {
        buf: payload,
        pos: 0,
    };
    let config = read_config(&mut r, version)?;
    let lo = r.f32s(3, "scene box min")?;
    let hi = r.f32s(3, "scene box max")?;
    let scene_box = SceneBox::new([lo[0], lo[1], lo[2]], [hi[0], hi[1], hi[2]])?;
    let n = r.usize("Gaussian count")?;
    let layout = config.layout();
    let row_bytes: usize = layout.dims().iter().sum::<usize>() * 4;
    let fits = n
        .checked_mul(row_bytes)
        .is_some_and(|b| b <= payload.len() - r.pos);
    if !fits {
        return Err(ck(format!("Gaussian count {n} exceeds the file")));
    }
    // The networks' sizes follow from the (bounded) configuration; the file must hold them
    // and every other count-sized section before anything is allocated.
    let weights = network_weights(&config)?;
    let left = payload.len() - r.pos - n * row_bytes;
    match bytes_after_gaussians(n, row_bytes, weights) {
        Some(needed) if needed <= left => {}
        _ => {
            return Err(ck(format!(
                "Gaussian count {n} and networks of {} + {} weights exceed the file",
                weights[0], weights[1]
            )))
        }
    }
    let mut gaussians = GaussianModel::new(layout)?;
    gaussians.params.push_zeros(n);
    r.params(&mut gaussians.params, "Gaussians")?;
    // Networks are rebuilt with the configured shapes, then overwritten with the weights.
    let mut model = SunAwareModel::new(gaussians.clone(), scene_box, config)?;
    model.gaussians = gaussians;
    let mut adam = Adam::new(&model.gaussians.params);
    adam.beta1 = r.f32("Adam beta1")?;
    adam.beta2 = r.f32("Adam beta2")?;
    adam.eps = r.f32("Adam eps")?;
    adam.step = r.u64("Adam step")?;
    check_adam(adam.beta1, adam.beta2, adam.eps, adam.step, "Gaussian")?;
    r.params(&mut adam.m, "Adam first moment")?;
    r.params(&mut adam.v, "Adam second moment")?;
    for g in Param::ALL {
        check_second_moment(adam.v.get(g), &format!("Gaussian Adam {}", g.name()))?;
    }
    let appearance_adam = read_net(
        &mut r,
        model.appearance.as_mut().map(|n| n.mlp.params_mut()),
        "appearance MLP",
    )?;
    let shadow_adam = read_net(
        &mut r,
        model.shadow.as_mut().map(|n| n.mlp.params_mut()),
        "shadow MLP",
    )?;
    let mut stats = DensifyStats::new(n);
    stats.grad_accum = r.f32s(n, "densify gradient sums")?;
    for c in stats.visible_count.iter_mut() {
        *c = r.u32("densify visible counts")?;
    }
    stats.max_radius_px = r.f32s(n, "densify max radii")?;
    let steps = r.u64("steps")?;
    let skipped_nonfinite = r.u64("skipped steps")?;
    let raster_dropped = r.u64("dropped gradients")?;
    let densify_count = r.u64("densify count")?;
    if r.pos != payload.len() {
        return Err(ck(format!(
            "{} unexpected bytes after the last field",
            payload.len() - r.pos
        )));
    }
    Ok(SunAwareTrainer {
        model,
        adam,
        appearance_adam,
        shadow_adam,
        densify_stats: stats,
        steps,
        skipped_nonfinite,
        raster_dropped,
        densify_count,
        resident: Default::default(),
    })
}

/// Writes a checkpoint.
pub fn save<W: Write>(t: &SunAwareTrainer, mut out: W) -> Result<(), SunAwareError> {
    out.write_all(&checked_to_bytes(t)?)?;
    out.flush()?;
    Ok(())
}

/// Reads a checkpoint.
pub fn load<R: Read>(mut input: R) -> Result<SunAwareTrainer, SunAwareError> {
    let mut bytes = Vec::new();
    input.read_to_end(&mut bytes)?;
    from_bytes(&bytes)
}

/// Writes a checkpoint file (through a temporary beside it, renamed into place, so a crash
/// never leaves a half-written checkpoint under the final name).
pub fn save_file(t: &SunAwareTrainer, path: impl AsRef<Path>) -> Result<(), SunAwareError> {
    let path = path.as_ref();
    let bytes = checked_to_bytes(t)?;
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Reads a checkpoint file.
pub fn load_file(path: impl AsRef<Path>) -> Result<SunAwareTrainer, SunAwareError> {
    from_bytes(&std::fs::read(path)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config_bytes(refinement: ShadowRefinement) -> Vec<u8> {
        let mut w = Writer(Vec::new());
        write_v7_config(
            &mut w,
            &SunAwareConfig {
                shadow_refinement: refinement,
                ..SunAwareConfig::for_variant(Variant::C)
            },
        );
        w.0
    }

    /// The version-8 field at the very end: the colour space u8.
    const COLOUR_SPACE_BYTES: usize = 1;

    /// The config section as version 7 wrote it (the tests below derive older versions
    /// from it by cutting fields off its end).
    fn write_v7_config(w: &mut Writer, c: &SunAwareConfig) {
        assert_eq!(
            c.colour_space,
            ColourSpace::Srgb,
            "version 7 had no colour space"
        );
        write_config(w, c);
        w.0.truncate(w.0.len() - COLOUR_SPACE_BYTES);
    }

    #[test]
    fn colour_space_round_trips_and_versions_before_8_mean_srgb() {
        for space in ColourSpace::ALL {
            let config = SunAwareConfig {
                colour_space: space,
                ..SunAwareConfig::for_variant(Variant::D)
            };
            let mut w = Writer(Vec::new());
            write_config(&mut w, &config);
            assert_eq!(read(&w.0, 8).unwrap(), config);
            let v7 = read(&w.0[..w.0.len() - COLOUR_SPACE_BYTES], 7).unwrap();
            assert_eq!(v7.colour_space, ColourSpace::Srgb);
            let mut bad = w.0.clone();
            *bad.last_mut().unwrap() = 7;
            let err = read(&bad, 8).unwrap_err().to_string();
            assert!(err.contains("unknown colour space 7"), "{err}");
        }
    }

    fn read(bytes: &[u8], version: u32) -> Result<SunAwareConfig, SunAwareError> {
        read_config(&mut Reader { buf: bytes, pos: 0 }, version)
    }

    /// The version-5 fields at the end of the config section: shading u8, ambient f32.
    const SHADING_BYTES: usize = 5;
    /// The version-6 field after them: the learned normal's rate f32.
    const NORMAL_RATE_BYTES: usize = 4;
    /// The version-7 field after it: Phi's appearance inputs u8.
    const APPEARANCE_INPUTS_BYTES: usize = 1;
    /// Everything after the version-4 section.
    const AFTER_V4_BYTES: usize = SHADING_BYTES + NORMAL_RATE_BYTES + APPEARANCE_INPUTS_BYTES;

    #[test]
    fn appearance_inputs_round_trip_and_versions_before_7_mean_paper() {
        for inputs in AppearanceInputs::ALL {
            let config = SunAwareConfig {
                shading: Shading::LambertLearned,
                appearance_inputs: inputs,
                ..SunAwareConfig::for_variant(Variant::D)
            };
            let mut w = Writer(Vec::new());
            write_v7_config(&mut w, &config);
            let full = w.0;
            assert_eq!(read(&full, 7).unwrap(), config);
            // Version 6 ends before the byte: Phi read the paper's row.
            let v6 = read(&full[..full.len() - APPEARANCE_INPUTS_BYTES], 6).unwrap();
            assert_eq!(v6.appearance_inputs, AppearanceInputs::Paper);
            assert_eq!(v6.shading, Shading::LambertLearned);
        }
        let config = SunAwareConfig {
            shading: Shading::LambertLearned,
            appearance_inputs: AppearanceInputs::Local,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let mut w = Writer(Vec::new());
        write_v7_config(&mut w, &config);
        let mut bad = w.0.clone();
        *bad.last_mut().unwrap() = 9;
        let err = read(&bad, 7).unwrap_err().to_string();
        assert!(err.contains("unknown appearance inputs 9"), "{err}");
        // Local inputs without the learned normal are refused on load as in memory.
        let mut w = Writer(Vec::new());
        write_v7_config(
            &mut w,
            &SunAwareConfig {
                shading: Shading::None,
                ..config.clone()
            },
        );
        let err = read(&w.0, 7).unwrap_err().to_string();
        assert!(err.contains("appearance_inputs"), "{err}");
    }

    #[test]
    fn shading_round_trips_and_versions_before_5_mean_none() {
        let mut config = SunAwareConfig {
            shading: Shading::LambertLearned,
            shading_ambient: 0.25,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        config.lr.normal = 0.02;
        let mut w = Writer(Vec::new());
        write_v7_config(&mut w, &config);
        // The version-6 section: without the trailing appearance inputs byte.
        let full = w.0[..w.0.len() - APPEARANCE_INPUTS_BYTES].to_vec();
        let back = read(&full, 6).unwrap();
        assert_eq!(
            (back.shading, back.shading_ambient, back.lr.normal),
            (Shading::LambertLearned, 0.25, 0.02)
        );
        // Version 5: no normal rate, the default.
        let bytes = full[..full.len() - NORMAL_RATE_BYTES].to_vec();
        let v5 = read(&bytes, 5).unwrap();
        assert_eq!(
            (v5.shading, v5.lr.normal),
            (Shading::LambertLearned, SunAwareRates::default().normal)
        );
        let v4 = read(&bytes[..bytes.len() - SHADING_BYTES], 4).unwrap();
        assert_eq!(v4.shading, Shading::None);
        let mut bad = bytes.clone();
        let at = bad.len() - SHADING_BYTES;
        bad[at] = 9;
        let err = read(&bad, 5).unwrap_err().to_string();
        assert!(err.contains("unknown shading 9"), "{err}");
        let mut bad = bytes.clone();
        let at = bad.len() - 4;
        bad[at..].copy_from_slice(&1.5f32.to_le_bytes());
        let err = read(&bad, 5).unwrap_err().to_string();
        assert!(err.contains("shading_ambient"), "{err}");
        for (rate, named) in [
            (f32::NAN, "normal learning rate is not finite"),
            (-1.0, "learning rate normal"),
        ] {
            let mut bad = full.clone();
            let at = bad.len() - 4;
            bad[at..].copy_from_slice(&rate.to_le_bytes());
            let err = read(&bad, 6).unwrap_err().to_string();
            assert!(err.contains(named), "{err}");
        }
    }

    #[test]
    fn shadow_gain_round_trips_and_versions_before_4_mean_1() {
        let config = SunAwareConfig {
            shadow_gain: 2.0,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let mut w = Writer(Vec::new());
        write_v7_config(&mut w, &config);
        // The version-4 section: without the trailing shading fields.
        let bytes = w.0[..w.0.len() - AFTER_V4_BYTES].to_vec();
        assert_eq!(read(&bytes, 4).unwrap().shadow_gain, 2.0);
        assert_eq!(read(&bytes[..bytes.len() - 4], 3).unwrap().shadow_gain, 1.0);
        // A gain the model refuses is refused on load too.
        let mut bad = bytes.clone();
        let at = bad.len() - 4;
        bad[at..].copy_from_slice(&f32::NAN.to_le_bytes());
        let err = read(&bad, 4).unwrap_err().to_string();
        assert!(err.contains("shadow gain"), "{err}");
    }

    #[test]
    fn shadow_refinement_round_trips_and_version_1_means_replace() {
        for refinement in [ShadowRefinement::Replace, ShadowRefinement::Multiply] {
            let full = config_bytes(refinement);
            let bytes = &full[..full.len() - AFTER_V4_BYTES];
            assert_eq!(read(bytes, 4).unwrap().shadow_refinement, refinement);
            // A version-3 config section ends before the shadow gain (4 bytes), a version-2
            // one also before the hidden width (8 bytes), a version-1 one also before the
            // refinement byte.
            let v3 = read(&bytes[..bytes.len() - 4], 3).unwrap();
            assert_eq!(v3.shadow_refinement, refinement);
            let v2 = read(&bytes[..bytes.len() - 12], 2).unwrap();
            assert_eq!(v2.shadow_refinement, refinement);
            let v1 = read(&bytes[..bytes.len() - 13], 1).unwrap();
            assert_eq!(v1.shadow_refinement, ShadowRefinement::Replace);
        }
        let mut bad = config_bytes(ShadowRefinement::Multiply);
        bad.truncate(bad.len() - AFTER_V4_BYTES);
        let at = bad.len() - 13;
        bad[at] = 7;
        let err = read(&bad, 4).unwrap_err().to_string();
        assert!(err.contains("shadow refinement"), "{err}");
    }

    #[test]
    fn appearance_hidden_width_round_trips_and_older_versions_mean_256() {
        let mut w = Writer(Vec::new());
        let config = SunAwareConfig {
            appearance_hidden_width: 64,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        write_v7_config(&mut w, &config);
        // The version-3 section: without the trailing shadow gain (4 bytes) and shading.
        let bytes = &w.0[..w.0.len() - 4 - AFTER_V4_BYTES];
        assert_eq!(read(bytes, 3).unwrap().appearance_hidden_width, 64);
        let v2 = read(&bytes[..bytes.len() - 8], 2).unwrap();
        assert_eq!(v2.appearance_hidden_width, 256);
        // A stored width outside the validated range is a checkpoint error, not a model.
        let mut bad = bytes.to_vec();
        let at = bad.len() - 8;
        bad[at..].copy_from_slice(&0u64.to_le_bytes());
        let err = read(&bad, 3).unwrap_err().to_string();
        assert!(err.contains("appearance_hidden_width"), "{err}");
    }
}
