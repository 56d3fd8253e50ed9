//! The networks' input assembly and output scatter on the device (`gs_wgpu::network_io`,
//! `NetworkIo::encode_*` recorded from here) against the CPU: `AppearanceNet::{assemble_input,
//! scatter_input_grad}`, `ShadowNet::{assemble_input, scatter_input_grad}` and the channel
//! routing of `SunAwareModel::{forward, backward}` (written out here as the model does
//! it). Random Gaussians, some listed (ascending, with gaps; the list buffer's tail past
//! `count` holds junk the kernels must not read), `count < n` and `count = 0`; output
//! buffers start full of junk so every write (and every non-write) is checked.
//!
//! Exact (bit for bit): copied columns (features, the Sun's code from the host, V,
//! latents), the channel scatters and output gradients (copies and one product, as the
//! CPU forms them), every value the kernels must not touch (unlisted Gaussians' channels
//! and gradients, other parameter groups), dead rows (exactly 0).
//!
//! Within tolerance (the encodings and the mean gradients): see [`ENCODING_TOL`],
//! [`MEAN_GRAD_TOL`] and, for the arguments that the device computes with WGSL's
//! division and square root (not correctly rounded on every GPU), [`VIEW_REL_ERR`] and
//! [`box_coordinate_err`]; the worst error of each comparison is printed.
//!
//! This file holds the rig, the scene and the shared checks; `gpu_network_io/phi.rs` and
//! `psi.rs` the tests of each network's kernels, `phi_local.rs` those of Phi's
//! local-frame inputs.
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (CI).

use gs_core::model::Param;
use gs_core::nn::{AppearanceNet, PositionalEncoding, SceneBox, ShadowNet};
use gs_core::rng::SplitMix64;
use gs_core::sunaware::config::ShadowRefinement;
use gs_wgpu::network_io::{packed_offsets, NetworkBatch, NetworkIo, NetworkIoProbe, PackedParams};
use gs_wgpu::{context_or_skip, GpuError, GpuOptions, Scratch};

/// Largest |gpu - cpu| of an encoded value (a sine or cosine of `2^k pi x`, in [-1, 1])
/// when both sides evaluate it on the same argument `x`: both run the same quarter-turn
/// reduction and polynomials; what may differ is the device compiler fusing the
/// polynomial's multiply-adds, a few f32 ulps of 1. 2^-21 = 4.8e-7 (the encoding's own
/// accuracy is 2^-23). Where the argument itself may differ, [`encoding_tol`] adds its
/// effect.
const ENCODING_TOL: f32 = 1.0 / 2_097_152.0;

/// f32's epsilon, 2^-23: one ulp of a value `x` is at most `EPS |x|`.
const EPS: f32 = f32::EPSILON;

/// WGSL's f32 accuracy (WGSL section 15.7.4.1): `+ - *` correctly rounded (and `a * b + c`
/// may be fused), `x / y` within 2.5 ULP, `sqrt` inherited from `1.0 / inverseSqrt(x)`
/// (2 ULP, then a 2.5 ULP division: 4.5 ULP); the CPU rounds each correctly (0.5 ULP).
/// Lavapipe rounds them correctly too; an NVIDIA H200 does not (docs/gpu.md).
///
/// Phi's unit view direction `v = d / |d|` (`d` the same bits on both sides): the sum of
/// squares fused or not (1 eps of `|d|^2`, half of it in `|d|`), the root 4.5 + 0.5 eps,
/// the division 2.5 + 0.5 eps, so `|v_gpu - v_cpu| <= VIEW_REL_ERR |v|`.
const VIEW_REL_ERR: f32 = 9.0 * EPS;

/// Tolerance of Phi's column `c >= view_start` (the view direction's encoding, then the
/// local block `[n.s, n.v, n.h]` when Phi has one) for the Gaussian at `mean`, seen from
/// [`CAMERA`] with the Sun along `sun`. The encoding: its argument, the view direction's
/// component, may differ by [`VIEW_REL_ERR`] of itself. The local block: the normal
/// `n = v / |v|` and the view direction `u` are each within 9 eps of themselves (the same
/// root and division as [`VIEW_REL_ERR`]), and a dot product of unit vectors rounds
/// within 3 eps (fused or not): `n.s` 9 + 3 eps, `n.v` 9 + 9 + 3 eps; the half vector
/// `h = (s + u) / |s + u|` moves by u's 9 eps over `|s + u|`, plus its sum's rounding and
/// normalisation (2 + 9 eps), so `n.h` within (23 + 9 / |s + u|) eps.
fn phi_view_column_tol(
    mean: &[f32],
    sun: glam::Vec3,
    c: usize,
    view_start: usize,
    freqs: usize,
) -> f32 {
    let d = glam::Vec3::from(CAMERA) - glam::Vec3::from_slice(mean);
    let u = d / d.length();
    let i = c - view_start;
    if i < 6 * freqs {
        let (axis, k) = (i / (2 * freqs), (i % (2 * freqs)) / 2);
        return encoding_tol(k, VIEW_REL_ERR * u[axis].abs());
    }
    match i - 6 * freqs {
        0 => 12.0 * EPS,
        1 => 21.0 * EPS,
        _ => (23.0 + 9.0 / (sun + u).length()) * EPS,
    }
}

/// One ulp of `x` (f32, normal range): `2^floor(log2 |x|) * EPS`.
fn ulp(x: f32) -> f32 {
    f32::from_bits(x.abs().to_bits() & 0x7f80_0000) * EPS
}

/// Psi's box coordinate `p = (m - min) / extent - 0.5` (`m - min` the same bits on both
/// sides): the device's division is within 2.5 ULP of `q = (m - min) / extent`, the
/// CPU's within 0.5, and each side rounds the subtraction of 0.5 once, so
/// `|p_gpu - p_cpu| <= 3 EPS |q| + ulp(p)`.
fn box_coordinate_err(q: f32) -> f32 {
    3.0 * EPS * q.abs() + ulp(q - 0.5)
}

/// Tolerance of band `k`'s sine or cosine `f(2^k pi x)` when the two sides' arguments `x`
/// may differ by `arg_err`: the polynomials' [`ENCODING_TOL`] plus the largest slope,
/// `2^k pi`, times the argument's error.
fn encoding_tol(k: usize, arg_err: f32) -> f32 {
    ENCODING_TOL + std::f32::consts::PI * (1u32 << k) as f32 * arg_err
}

/// Mean gradients: |gpu - cpu| <= MEAN_GRAD_TOL * scale, with scale the row's sum of
/// the magnitudes that enter it: `sum_k 2^k pi (|d_sin| + |d_cos|)` per component, times
/// the chain rule's factor (2 / distance for Phi's view direction, 1 / extent for Psi's
/// box normalisation), plus |preexisting value|. A sine/cosine off by ENCODING_TOL moves
/// the sum by at most ENCODING_TOL of that scale; the sums, the projection and the final
/// addition round a few more ulps: 4 * 2^-21. Where the encoding's argument may differ
/// (Psi's box coordinate), [`code_arg_scale`] adds its effect.
const MEAN_GRAD_TOL: f32 = 4.0 / 2_097_152.0;

/// The kernels, the scratch pool they record with, and host-side buffer helpers.
struct Rig {
    io: NetworkIo,
    scratch: Scratch,
    probe: NetworkIoProbe,
}

fn rig() -> Option<Rig> {
    let ctx = context_or_skip(GpuOptions::default())?;
    Some(Rig {
        io: NetworkIo::new(&ctx).unwrap(),
        scratch: Scratch::default(),
        probe: NetworkIoProbe::new(&ctx),
    })
}

/// Random Gaussians in the packed layout, a sorted list with gaps, junk past `count`.
struct Scene {
    n: usize,
    dims: [usize; Param::COUNT],
    offsets: [u32; Param::COUNT + 1],
    params: Vec<f32>,
    /// `n` entries: the live list, then junk indices (some out of range).
    list: Vec<u32>,
    count: usize,
}

impl Scene {
    fn new(seed: u64, n: usize, feature_dim: usize, latent_dim: usize, keep: f32) -> Self {
        Self::with_dims(
            seed,
            n,
            [3, 3, 4, 1, 3, 9, feature_dim, latent_dim, 0],
            keep,
        )
    }

    /// [`Scene::new`] with a learned shading normal group (3 per Gaussian, normal values).
    fn with_normals(seed: u64, n: usize, feature_dim: usize, keep: f32) -> Self {
        Self::with_dims(seed, n, [3, 3, 4, 1, 3, 9, feature_dim, 6, 3], keep)
    }

    fn with_dims(seed: u64, n: usize, dims: [usize; Param::COUNT], keep: f32) -> Self {
        let offsets = packed_offsets(&dims, n).unwrap();
        let mut rng = SplitMix64::new(seed);
        let mut params: Vec<f32> = (0..offsets[Param::COUNT]).map(|_| rng.normal()).collect();
        // Means fill a box a little larger than Psi's scene box (some lie outside it).
        for v in &mut params[..3 * n] {
            *v = rng.uniform(-1.6, 1.6);
        }
        let mut list: Vec<u32> = (0..n as u32).filter(|_| rng.next_f32() < keep).collect();
        let count = list.len();
        while list.len() < n {
            list.push(if rng.next_f32() < 0.5 {
                u32::MAX
            } else {
                rng.below(n) as u32
            });
        }
        Self {
            n,
            dims,
            offsets,
            params,
            list,
            count,
        }
    }

    fn group(&self, p: Param) -> &[f32] {
        &self.params[self.offsets[p.index()] as usize..self.offsets[p.index() + 1] as usize]
    }

    fn live(&self) -> &[u32] {
        &self.list[..self.count]
    }

    fn is_listed(&self) -> Vec<bool> {
        let mut listed = vec![false; self.n];
        for &g in self.live() {
            listed[g as usize] = true;
        }
        listed
    }
}

fn junk(seed: u64, len: usize) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    (0..len).map(|_| rng.normal() * 3.0 + 0.5).collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Device buffers of a scene: params, list, count.
struct Batch {
    params: wgpu::Buffer,
    list: wgpu::Buffer,
    count: wgpu::Buffer,
}

impl Batch {
    /// The kernels' batch: `n` Gaussians, this list and count, uniforms from `scratch`.
    fn rows<'a>(&'a self, scratch: &'a Scratch, n: usize) -> NetworkBatch<'a> {
        NetworkBatch {
            scratch,
            n,
            list: &self.list,
            count: &self.count,
        }
    }

    /// These parameters with the group starts `offsets`.
    fn packed<'a>(&'a self, offsets: &'a [u32; Param::COUNT + 1]) -> PackedParams<'a> {
        PackedParams {
            buffer: &self.params,
            offsets,
        }
    }
}

fn upload(probe: &NetworkIoProbe, s: &Scene, count: usize) -> Batch {
    Batch {
        params: probe.buffer_f32("params", &s.params),
        list: probe.buffer_u32("list", &s.list),
        count: probe.buffer_u32("count", &[count as u32]),
    }
}

fn phi_net(s: &Scene, freqs: usize) -> AppearanceNet {
    let enc = PositionalEncoding::new(freqs).unwrap();
    AppearanceNet::with_hidden_width(s.dims[Param::Feature.index()], 16, enc, 5).unwrap()
}

fn psi_net(s: &Scene, freqs: usize) -> ShadowNet {
    let enc = PositionalEncoding::new(freqs).unwrap();
    ShadowNet::new(s.dims[Param::ShadowLatent.index()], enc, 6).unwrap()
}

const SUN: [f32; 3] = [0.3, 0.4, -0.8];
const CAMERA: [f32; 3] = [0.5, -1.0, 6.0];

fn scene_box() -> SceneBox {
    SceneBox::new([-1.5, -1.4, -1.2], [1.4, 1.5, 1.3]).unwrap()
}

/// Compares assembled rows: columns where `tol(row, column)` is `None` bit for bit, the
/// others within the tolerance it gives; rows past `count` exactly 0. Returns the worst
/// ratio of error to tolerance.
fn compare_rows(
    what: &str,
    cpu: &[f32],
    gpu: &[f32],
    width: usize,
    count: usize,
    tol: &dyn Fn(usize, usize) -> Option<f32>,
) -> f32 {
    let mut worst = 0.0f32;
    for (r, row) in gpu.chunks_exact(width).enumerate() {
        for (c, &v) in row.iter().enumerate() {
            if r >= count {
                assert_eq!(v.to_bits(), 0, "{what}: dead row {r} column {c} is {v}");
                continue;
            }
            let want = cpu[r * width + c];
            match tol(r, c) {
                None => assert_eq!(v.to_bits(), want.to_bits(), "{what}: row {r} column {c}"),
                Some(t) => {
                    let err = (v - want).abs();
                    assert!(
                        err <= t,
                        "{what}: row {r} column {c}: gpu {v} cpu {want} (tolerance {t:e})"
                    );
                    worst = worst.max(err / t);
                }
            }
        }
    }
    worst
}

/// Per-row scale of a mean gradient (see MEAN_GRAD_TOL): `factor * sum over the row's
/// code columns of 2^k pi |d|`.
fn code_scale(d_code: &[f32], freqs: usize, factor: f32) -> f32 {
    let mut sum = 0.0f32;
    for (i, d) in d_code.iter().enumerate() {
        let k = (i % (2 * freqs)) / 2;
        sum += std::f32::consts::PI * (1u32 << k) as f32 * d.abs();
    }
    sum * factor
}

/// Per-row weight of the encoding's argument error in a mean gradient: the CPU's sum
/// `factor * sum_k 2^k pi (d_sin cos - d_cos sin)` moves by at most
/// `factor * sum_k (2^k pi)^2 (|d_sin| + |d_cos|)` per unit of argument error.
fn code_arg_scale(d_code: &[f32], freqs: usize, factor: f32) -> f32 {
    let mut sum = 0.0f32;
    for (i, d) in d_code.iter().enumerate() {
        let omega = std::f32::consts::PI * (1u32 << ((i % (2 * freqs)) / 2)) as f32;
        sum += omega * omega * d.abs();
    }
    sum * factor
}

/// `group` (`dim` floats per Gaussian) with the rows of the `live` Gaussians zeroed: the
/// input-gradient scatter sets those rows (the rasterizer leaves the group zero and the
/// CPU's scatter adds into it).
fn listed_rows_cleared(group: &[f32], dim: usize, live: &[u32]) -> Vec<f32> {
    let mut out = group.to_vec();
    for &g in live {
        out[g as usize * dim..(g as usize + 1) * dim].fill(0.0);
    }
    out
}

/// `gpu` equals `want` bit for bit everywhere but the means of the Gaussians listed in
/// `s` (when `count > 0`), which the callers compare within tolerance.
fn assert_bits_but_listed_means(what: &str, gpu: &[f32], want: &[f32], s: &Scene, count: usize) {
    let listed = s.is_listed();
    let is_listed_mean = |i: usize| i < 3 * s.n && listed[i / 3] && count > 0;
    for (i, (&a, &w)) in gpu.iter().zip(want).enumerate() {
        if !is_listed_mean(i) {
            assert_eq!(a.to_bits(), w.to_bits(), "{what}[{i}]: {a} vs {w}");
        }
    }
}

#[test]
fn bad_host_arguments_are_rejected_before_recording() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let s = Scene::new(70, 100, 8, 6, 0.5);
    let n = s.n;
    let phi = phi_net(&s, 4);
    let psi = psi_net(&s, 4);
    let b = upload(&probe, &s, s.count);
    let flags = probe.buffer_u32("flags", &[0]);
    let phi_input = probe.buffer_f32("phi input", &vec![0.0; n * phi.input_width()]);
    let short = probe.buffer_f32("short", &vec![0.0; n]);
    let vis = probe.buffer_f32("visibility", &vec![0.5; n]);
    let chans4 = probe.buffer_f32("chans", &vec![0.0; n * 4]);
    let rows = probe.buffer_f32("rows", &vec![0.0; n * 17]);
    let invalid = |r: Result<(), GpuError>, what: &str| {
        assert!(matches!(r, Err(GpuError::Invalid(_))), "{what}: {r:?}");
    };
    let mut enc = probe.encoder();
    let phi_in = |enc: &mut wgpu::CommandEncoder,
                  offsets: &[u32; Param::COUNT + 1],
                  sun: [f32; 3],
                  cam: [f32; 3],
                  input: &wgpu::Buffer| {
        io.encode_phi_input(
            enc,
            b.rows(&scratch, n),
            &phi,
            b.packed(offsets),
            sun,
            cam,
            input,
            &flags,
        )
    };
    phi_in(&mut enc, &s.offsets, SUN, CAMERA, &phi_input).unwrap();
    invalid(
        phi_in(&mut enc, &s.offsets, SUN, CAMERA, &short),
        "short input",
    );
    invalid(
        phi_in(&mut enc, &s.offsets, [0.0; 3], CAMERA, &phi_input),
        "zero Sun",
    );
    invalid(
        phi_in(&mut enc, &s.offsets, SUN, [f32::NAN, 0.0, 0.0], &phi_input),
        "NaN camera",
    );
    // Offsets of a 16-wide feature group: not this network's.
    let wrong = packed_offsets(&[3, 3, 4, 1, 3, 9, 16, 6, 0], n).unwrap();
    invalid(
        phi_in(&mut enc, &wrong, SUN, CAMERA, &phi_input),
        "feature width",
    );
    // Offsets of more Gaussians than n.
    let more = packed_offsets(&s.dims, n + 1).unwrap();
    invalid(phi_in(&mut enc, &more, SUN, CAMERA, &phi_input), "rows");
    invalid(
        io.encode_phi_scatter(&mut enc, b.rows(&scratch, n), 5, &short, None, &chans4),
        "5 channels",
    );
    invalid(
        io.encode_phi_scatter(&mut enc, b.rows(&scratch, n), 4, &short, None, &chans4),
        "short Phi output",
    );
    invalid(
        io.encode_phi_d_output(&mut enc, b.rows(&scratch, n), 4, &short, None, &chans4),
        "short rows",
    );
    invalid(
        io.encode_psi_scatter(
            &mut enc,
            b.rows(&scratch, n),
            3,
            &vis,
            &short,
            Some(1.0),
            &chans4,
        ),
        "Psi with 3 channels",
    );
    let tiny = probe.buffer_f32("tiny", &vec![0.5; n / 2]);
    invalid(
        io.encode_psi_d_output(
            &mut enc,
            b.rows(&scratch, n),
            4,
            &tiny,
            &rows,
            Some(1.0),
            &short,
        ),
        "short visibility",
    );
    let psi_d_input = probe.buffer_f32("psi d_input", &vec![0.0; n * psi.input_width()]);
    let grads = probe.buffer_f32("grads", &s.params);
    let psi_grad = |enc: &mut wgpu::CommandEncoder,
                    offsets: &[u32; Param::COUNT + 1],
                    d_input: &wgpu::Buffer| {
        io.encode_psi_input_grad(
            enc,
            b.rows(&scratch, n),
            &psi,
            &scene_box(),
            b.packed(offsets),
            d_input,
            &grads,
        )
    };
    psi_grad(&mut enc, &s.offsets, &psi_d_input).unwrap();
    invalid(psi_grad(&mut enc, &s.offsets, &short), "short Psi d_input");
    // Offsets of a 3-wide latent group: not this network's.
    let latent3 = packed_offsets(&[3, 3, 4, 1, 3, 9, 8, 3, 0], n).unwrap();
    invalid(psi_grad(&mut enc, &latent3, &psi_d_input), "latent width");
    probe.finish_f32(enc, &[]).unwrap();
}

#[path = "gpu_network_io/phi.rs"]
mod phi;
#[path = "gpu_network_io/phi_local.rs"]
mod phi_local;
#[path = "gpu_network_io/psi.rs"]
mod psi;
