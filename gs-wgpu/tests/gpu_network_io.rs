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
//! Within tolerance (the encodings and the mean gradients): see [`ENCODING_TOL`] and
//! [`MEAN_GRAD_TOL`]; the worst error of each comparison is printed.
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (CI).

use gs_core::model::Param;
use gs_core::nn::{AppearanceNet, PositionalEncoding, SceneBox, ShadowNet};
use gs_core::rng::SplitMix64;
use gs_core::sunaware::config::ShadowRefinement;
use gs_wgpu::network_io::{packed_offsets, NetworkIo, NetworkIoProbe};
use gs_wgpu::{context_or_skip, GpuError, GpuOptions, Scratch};

/// Largest |gpu - cpu| of an encoded value (a sine or cosine of `2^k pi x`, in [-1, 1]).
/// Both sides evaluate the same quarter-turn reduction and polynomials on the same
/// argument (the view direction's sqrt and divisions, the box normalisation's
/// subtraction and division are correctly rounded on both); what may differ is the
/// device compiler fusing the polynomial's multiply-adds, a few f32 ulps of 1.
/// 2^-21 = 4.8e-7 (the encoding's own accuracy is 2^-23).
const ENCODING_TOL: f32 = 1.0 / 2_097_152.0;

/// Mean gradients: |gpu - cpu| <= MEAN_GRAD_TOL * scale, with scale the row's sum of
/// the magnitudes that enter it: `sum_k 2^k pi (|d_sin| + |d_cos|)` per component, times
/// the chain rule's factor (2 / distance for Phi's view direction, 1 / extent for Psi's
/// box normalisation), plus |preexisting value|. A sine/cosine off by ENCODING_TOL moves
/// the sum by at most ENCODING_TOL of that scale; the sums, the projection and the final
/// addition round a few more ulps: 4 * 2^-21.
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
        let dims = [3, 3, 4, 1, 3, 9, feature_dim, latent_dim, 0];
        let offsets = packed_offsets(&dims, n).unwrap();
        let mut rng = SplitMix64::new(seed);
        let mut params: Vec<f32> = (0..offsets[8]).map(|_| rng.normal()).collect();
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

/// Compares assembled rows: columns in `exact` bit for bit, the others within
/// ENCODING_TOL; rows past `count` exactly 0. Returns the worst encoding error.
fn compare_rows(
    what: &str,
    cpu: &[f32],
    gpu: &[f32],
    width: usize,
    count: usize,
    exact: &dyn Fn(usize) -> bool,
) -> f32 {
    let mut worst = 0.0f32;
    for (r, row) in gpu.chunks_exact(width).enumerate() {
        for (c, &v) in row.iter().enumerate() {
            if r >= count {
                assert_eq!(v.to_bits(), 0, "{what}: dead row {r} column {c} is {v}");
                continue;
            }
            let want = cpu[r * width + c];
            if exact(c) {
                assert_eq!(v.to_bits(), want.to_bits(), "{what}: row {r} column {c}");
            } else {
                let err = (v - want).abs();
                assert!(
                    err <= ENCODING_TOL,
                    "{what}: row {r} column {c}: gpu {v} cpu {want}"
                );
                worst = worst.max(err);
            }
        }
    }
    worst
}

#[test]
fn phi_input_matches_the_cpu_rows() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let mut worst = 0.0f32;
    for (seed, n, f_dim, freqs, keep) in [
        (1, 700, 8, 4, 0.6),
        (2, 300, 72, 4, 0.9),
        (3, 40, 5, 10, 0.5),
    ] {
        let s = Scene::new(seed, n, f_dim, 6, keep);
        let net = phi_net(&s, freqs);
        let width = net.input_width();
        let mut cpu = Vec::new();
        net.assemble_input(
            s.live(),
            s.group(Param::Feature),
            s.group(Param::Mean),
            SUN,
            CAMERA,
            &mut cpu,
        )
        .unwrap();
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let input = probe.buffer_f32("input", &junk(seed, n * width));
            let flags = probe.buffer_u32("flags", &[0]);
            let mut enc = probe.encoder();
            io.encode_phi_input(
                &mut enc, &scratch, &net, &b.params, &s.offsets, n, &b.list, &b.count, SUN, CAMERA,
                &input, &flags,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&input, n * width)]).unwrap();
            let view_start = f_dim + 6 * freqs;
            worst = worst.max(compare_rows(
                "Phi input",
                &cpu,
                &gpu[0],
                width,
                count,
                &|c| c < view_start,
            ));
            assert_eq!(probe.read_u32(&flags, 1).unwrap(), [0], "flags");
        }
    }
    eprintln!("Phi input: worst encoding error {worst:e} (tolerance {ENCODING_TOL:e})");
}

/// Runs Phi's input assembly on `s` and returns flags[0].
fn phi_flags(rig: &Rig, s: &Scene, net: &AppearanceNet) -> u32 {
    let Rig { io, scratch, probe } = rig;
    let b = upload(probe, s, s.count);
    let input = probe.buffer_f32("input", &vec![0.0; s.n * net.input_width()]);
    let flags = probe.buffer_u32("flags", &[0]);
    let mut enc = probe.encoder();
    io.encode_phi_input(
        &mut enc, scratch, net, &b.params, &s.offsets, s.n, &b.list, &b.count, SUN, CAMERA, &input,
        &flags,
    )
    .unwrap();
    probe.finish_f32(enc, &[]).unwrap();
    probe.read_u32(&flags, 1).unwrap()[0]
}

#[test]
fn phi_input_flags_what_the_cpu_refuses() {
    let Some(rig) = rig() else { return };
    let base = Scene::new(4, 300, 8, 6, 0.5);
    let net = phi_net(&base, 4);
    let listed = base.live()[7] as usize;
    let unlisted = (0..base.n).find(|g| !base.is_listed()[*g]).unwrap();
    let f0 = base.offsets[Param::Feature.index()] as usize;
    let mean_at = |g: usize| 3 * g;
    assert_eq!(phi_flags(&rig, &base, &net), 0);

    // A NaN feature of a listed Gaussian: the CPU refuses, the device flags.
    let mut s = Scene::new(4, 300, 8, 6, 0.5);
    s.params[f0 + listed * 8 + 3] = f32::NAN;
    let mut cpu = Vec::new();
    let cpu_err = net.assemble_input(
        s.live(),
        s.group(Param::Feature),
        s.group(Param::Mean),
        SUN,
        CAMERA,
        &mut cpu,
    );
    assert!(cpu_err.is_err());
    assert_eq!(phi_flags(&rig, &s, &net), 1, "NaN feature");
    // An infinite mean.
    let mut s = Scene::new(4, 300, 8, 6, 0.5);
    s.params[mean_at(listed) + 1] = f32::INFINITY;
    assert_eq!(phi_flags(&rig, &s, &net), 1, "infinite mean");
    // A listed Gaussian at the camera centre.
    let mut s = Scene::new(4, 300, 8, 6, 0.5);
    s.params[mean_at(listed)..mean_at(listed) + 3].copy_from_slice(&CAMERA);
    let cpu_err = net.assemble_input(
        s.live(),
        s.group(Param::Feature),
        s.group(Param::Mean),
        SUN,
        CAMERA,
        &mut cpu,
    );
    assert!(cpu_err.is_err());
    assert_eq!(
        phi_flags(&rig, &s, &net),
        1,
        "Gaussian at the camera centre"
    );
    // The same faults on an unlisted Gaussian are not read: no flag.
    let mut s = Scene::new(4, 300, 8, 6, 0.5);
    s.params[f0 + unlisted * 8] = f32::NAN;
    s.params[mean_at(unlisted)..mean_at(unlisted) + 3].copy_from_slice(&CAMERA);
    assert_eq!(phi_flags(&rig, &s, &net), 0, "unlisted faults");
    // A list entry out of range inside count.
    let mut s = Scene::new(4, 300, 8, 6, 0.5);
    s.list[3] = s.n as u32;
    assert_eq!(phi_flags(&rig, &s, &net), 1, "list entry out of range");
}

#[test]
fn phi_scatter_and_output_gradient_route_rows() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    for nc in [3usize, 4] {
        let s = Scene::new(10 + nc as u64, 600, 8, 6, 0.55);
        let n = s.n;
        let output = junk(20, n * 3);
        let chans0 = junk(21, n * nc);
        let rows = junk(22, n * (13 + nc));
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let out_buf = probe.buffer_f32("output", &output);
            let chans = probe.buffer_f32("chans", &chans0);
            let rows_buf = probe.buffer_f32("rows", &rows);
            let d_out = probe.buffer_f32("d_out", &junk(23, n * 3));
            let mut enc = probe.encoder();
            io.encode_phi_scatter(
                &mut enc, &scratch, n, nc, &b.list, &b.count, &out_buf, &chans,
            )
            .unwrap();
            io.encode_phi_d_output(
                &mut enc, &scratch, n, nc, &b.list, &b.count, &rows_buf, &d_out,
            )
            .unwrap();
            let gpu = probe
                .finish_f32(enc, &[(&chans, n * nc), (&d_out, n * 3)])
                .unwrap();
            // The model's loops (sunaware/model.rs forward_with, backward_timed).
            let mut want_chans = chans0.clone();
            let mut want_d_out = vec![0.0f32; n * 3];
            for (r, &g) in s.list[..count].iter().enumerate() {
                let g = g as usize;
                want_chans[g * nc..g * nc + 3].copy_from_slice(&output[r * 3..r * 3 + 3]);
                want_d_out[r * 3..r * 3 + 3]
                    .copy_from_slice(&rows[g * (13 + nc) + 13..g * (13 + nc) + 16]);
            }
            assert_eq!(bits(&gpu[0]), bits(&want_chans), "channels, nc {nc}");
            assert_eq!(bits(&gpu[1]), bits(&want_d_out), "d_out, nc {nc}");
            if count > 0 {
                assert_ne!(bits(&gpu[0]), bits(&chans0), "nothing scattered");
            }
        }
    }
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
fn phi_input_gradient_matches_the_cpu_scatter() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let mut worst = 0.0f32;
    for (seed, n, f_dim, freqs, keep) in [(30, 700, 8, 4, 0.6), (31, 90, 72, 6, 0.8)] {
        let s = Scene::new(seed, n, f_dim, 6, keep);
        let net = phi_net(&s, freqs);
        let width = net.input_width();
        let d_input = junk(seed + 1, n * width);
        let grads0 = junk(seed + 2, s.params.len());
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let d_in = probe.buffer_f32("d_input", &d_input);
            let grads = probe.buffer_f32("grads", &grads0);
            let mut enc = probe.encoder();
            io.encode_phi_input_grad(
                &mut enc, &scratch, &net, &b.params, &s.offsets, n, &b.list, &b.count, CAMERA,
                &d_in, &grads,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&grads, grads0.len())]).unwrap();
            let gpu = &gpu[0];
            // The model: features of listed rows are written (the rasterizer leaves the
            // group zero, the scatter adds into it); means gain the chain rule.
            let live = &s.list[..count];
            let f0 = s.offsets[Param::Feature.index()] as usize;
            let mut d_features = listed_rows_cleared(&grads0[f0..f0 + n * f_dim], f_dim, live);
            let mut d_means = grads0[..3 * n].to_vec();
            net.scatter_input_grad(
                live,
                s.group(Param::Mean),
                CAMERA,
                &d_input[..count * width],
                &mut d_features,
                &mut d_means,
            )
            .unwrap();
            let mut want = grads0.clone();
            want[f0..f0 + n * f_dim].copy_from_slice(&d_features);
            assert_bits_but_listed_means("Phi grads", gpu, &want, &s, count);
            let view_start = f_dim + 6 * freqs;
            for (r, &g) in live.iter().enumerate() {
                let g = g as usize;
                let mean = &s.group(Param::Mean)[g * 3..g * 3 + 3];
                let d: Vec<f32> = (0..3).map(|a| CAMERA[a] - mean[a]).collect();
                let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let row = &d_input[r * width + view_start..(r + 1) * width];
                for a in 0..3 {
                    let i = g * 3 + a;
                    let scale = code_scale(row, freqs, 2.0 / dist) + grads0[i].abs();
                    let err = (gpu[i] - d_means[i]).abs() / scale;
                    assert!(
                        err <= MEAN_GRAD_TOL,
                        "Phi mean grad of {g}.{a}: gpu {} cpu {} (scale {scale})",
                        gpu[i],
                        d_means[i]
                    );
                    worst = worst.max(err);
                }
            }
        }
    }
    eprintln!("Phi mean gradient: worst error / scale {worst:e} (tolerance {MEAN_GRAD_TOL:e})");
}

fn visibility(seed: u64, n: usize) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    (0..n).map(|_| rng.next_f32()).collect()
}

#[test]
fn psi_input_matches_the_cpu_rows() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let mut worst = 0.0f32;
    // The last case has the most frequencies (a full Sun code) and means hundreds of box
    // widths outside the box: arguments 2^15 p beyond 2^21, where the CPU reduces in f64.
    let cases = [
        (40, 700, 6, 4, 0.6, false),
        (41, 50, 3, 10, 0.5, false),
        (42, 60, 6, 16, 0.7, true),
    ];
    for (seed, n, l_dim, freqs, keep, far) in cases {
        let mut s = Scene::new(seed, n, 8, l_dim, keep);
        if far {
            let mut rng = SplitMix64::new(seed + 7);
            for v in &mut s.params[..3 * n] {
                *v = rng.uniform(-900.0, 900.0);
            }
        }
        let net = psi_net(&s, freqs);
        let width = net.input_width();
        let vis = visibility(seed + 1, n);
        let mut cpu = Vec::new();
        net.assemble_input(
            s.live(),
            &vis,
            s.group(Param::ShadowLatent),
            s.group(Param::Mean),
            SUN,
            &scene_box(),
            &mut cpu,
        )
        .unwrap();
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let vis_buf = probe.buffer_f32("visibility", &vis);
            let input = probe.buffer_f32("input", &junk(seed, n * width));
            let flags = probe.buffer_u32("flags", &[0]);
            let mut enc = probe.encoder();
            io.encode_psi_input(
                &mut enc,
                &scratch,
                &net,
                &scene_box(),
                &b.params,
                &s.offsets,
                n,
                &b.list,
                &b.count,
                SUN,
                &vis_buf,
                &input,
                &flags,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&input, n * width)]).unwrap();
            let (code_start, code_end) = (1 + 6 * freqs, 1 + 12 * freqs);
            worst = worst.max(compare_rows(
                "Psi input",
                &cpu,
                &gpu[0],
                width,
                count,
                &|c| !(code_start..code_end).contains(&c),
            ));
            assert_eq!(probe.read_u32(&flags, 1).unwrap(), [0], "flags");
        }
    }
    eprintln!("Psi input: worst encoding error {worst:e} (tolerance {ENCODING_TOL:e})");
}

/// Runs Psi's input assembly on `s` with `vis` and returns flags[0].
fn psi_flags(rig: &Rig, s: &Scene, net: &ShadowNet, vis: &[f32]) -> u32 {
    let Rig { io, scratch, probe } = rig;
    let b = upload(probe, s, s.count);
    let vis_buf = probe.buffer_f32("visibility", vis);
    let input = probe.buffer_f32("input", &vec![0.0; s.n * net.input_width()]);
    let flags = probe.buffer_u32("flags", &[0]);
    let mut enc = probe.encoder();
    io.encode_psi_input(
        &mut enc,
        scratch,
        net,
        &scene_box(),
        &b.params,
        &s.offsets,
        s.n,
        &b.list,
        &b.count,
        SUN,
        &vis_buf,
        &input,
        &flags,
    )
    .unwrap();
    probe.finish_f32(enc, &[]).unwrap();
    probe.read_u32(&flags, 1).unwrap()[0]
}

#[test]
fn psi_input_flags_what_the_cpu_refuses() {
    let Some(rig) = rig() else { return };
    let fresh = || Scene::new(42, 300, 8, 6, 0.5);
    let base = fresh();
    let net = psi_net(&base, 4);
    let vis = visibility(43, base.n);
    let listed = base.live()[11] as usize;
    let unlisted = (0..base.n).find(|g| !base.is_listed()[*g]).unwrap();
    let l0 = base.offsets[Param::ShadowLatent.index()] as usize;
    assert_eq!(psi_flags(&rig, &base, &net, &vis), 0);

    let mut bad_vis = vis.clone();
    bad_vis[listed] = f32::NAN;
    let mut cpu = Vec::new();
    let cpu_err = net.assemble_input(
        base.live(),
        &bad_vis,
        base.group(Param::ShadowLatent),
        base.group(Param::Mean),
        SUN,
        &scene_box(),
        &mut cpu,
    );
    assert!(cpu_err.is_err());
    assert_eq!(psi_flags(&rig, &base, &net, &bad_vis), 1, "NaN V");
    let mut s = fresh();
    s.params[l0 + listed * 6 + 5] = f32::NEG_INFINITY;
    assert_eq!(psi_flags(&rig, &s, &net, &vis), 1, "infinite latent");
    let mut s = fresh();
    s.params[3 * listed + 2] = f32::NAN;
    assert_eq!(psi_flags(&rig, &s, &net, &vis), 1, "NaN mean");
    // Faults of an unlisted Gaussian are not read.
    let mut s = fresh();
    let mut unlisted_vis = vis.clone();
    unlisted_vis[unlisted] = f32::NAN;
    s.params[l0 + unlisted * 6] = f32::NAN;
    s.params[3 * unlisted] = f32::INFINITY;
    assert_eq!(
        psi_flags(&rig, &s, &net, &unlisted_vis),
        0,
        "unlisted faults"
    );
}

#[test]
fn psi_scatter_and_output_gradient_follow_the_refinement_mode() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let nc = 4;
    let s = Scene::new(50, 600, 8, 6, 0.55);
    let n = s.n;
    let vis = visibility(51, n);
    let output = visibility(52, n);
    let chans0 = junk(53, n * nc);
    let rows = junk(54, n * (13 + nc));
    for mode in [ShadowRefinement::Multiply, ShadowRefinement::Replace] {
        let multiply = mode == ShadowRefinement::Multiply;
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let vis_buf = probe.buffer_f32("visibility", &vis);
            let out_buf = probe.buffer_f32("output", &output);
            let chans = probe.buffer_f32("chans", &chans0);
            let rows_buf = probe.buffer_f32("rows", &rows);
            let d_out = probe.buffer_f32("d_out", &junk(55, n));
            let mut enc = probe.encoder();
            io.encode_psi_scatter(
                &mut enc, &scratch, n, nc, &b.list, &b.count, &vis_buf, &out_buf, multiply, &chans,
            )
            .unwrap();
            io.encode_psi_d_output(
                &mut enc, &scratch, n, nc, &b.list, &b.count, &vis_buf, &rows_buf, multiply, &d_out,
            )
            .unwrap();
            let gpu = probe
                .finish_f32(enc, &[(&chans, n * nc), (&d_out, n)])
                .unwrap();
            // The model's loops (sunaware/model.rs forward_with, backward_timed).
            let mut want_chans = chans0.clone();
            let mut want_d_out = vec![0.0f32; n];
            for (r, &g) in s.list[..count].iter().enumerate() {
                let g = g as usize;
                want_chans[g * nc + 3] = if multiply {
                    vis[g] * output[r]
                } else {
                    output[r]
                };
                let d = rows[g * (13 + nc) + 13 + 3];
                want_d_out[r] = if multiply { d * vis[g] } else { d };
            }
            assert_eq!(bits(&gpu[0]), bits(&want_chans), "channels, {mode:?}");
            assert_eq!(bits(&gpu[1]), bits(&want_d_out), "d_out, {mode:?}");
            if count > 0 {
                assert_ne!(bits(&gpu[0]), bits(&chans0), "nothing scattered");
            }
        }
    }
}

#[test]
fn psi_input_gradient_matches_the_cpu_scatter() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let mut worst = 0.0f32;
    let (box_min, box_max) = (scene_box().min_m(), scene_box().max_m());
    let extent_inv: Vec<f32> = (0..3).map(|a| 1.0 / (box_max[a] - box_min[a])).collect();
    for (seed, n, l_dim, freqs, keep) in [(60, 700, 6, 4, 0.6), (61, 90, 3, 8, 0.8)] {
        let s = Scene::new(seed, n, 8, l_dim, keep);
        let net = psi_net(&s, freqs);
        let width = net.input_width();
        let d_input = junk(seed + 1, n * width);
        let grads0 = junk(seed + 2, s.params.len());
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let d_in = probe.buffer_f32("d_input", &d_input);
            let grads = probe.buffer_f32("grads", &grads0);
            let mut enc = probe.encoder();
            io.encode_psi_input_grad(
                &mut enc,
                &scratch,
                &net,
                &scene_box(),
                &b.params,
                &s.offsets,
                n,
                &b.list,
                &b.count,
                &d_in,
                &grads,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&grads, grads0.len())]).unwrap();
            let gpu = &gpu[0];
            // The model: listed latents are written, means gain the chain rule.
            let live = &s.list[..count];
            let l0 = s.offsets[Param::ShadowLatent.index()] as usize;
            let mut d_latents = listed_rows_cleared(&grads0[l0..l0 + n * l_dim], l_dim, live);
            let mut d_means = grads0[..3 * n].to_vec();
            net.scatter_input_grad(
                live,
                s.group(Param::Mean),
                &scene_box(),
                &d_input[..count * width],
                &mut d_latents,
                &mut d_means,
            )
            .unwrap();
            let mut want = grads0.clone();
            want[l0..l0 + n * l_dim].copy_from_slice(&d_latents);
            assert_bits_but_listed_means("Psi grads", gpu, &want, &s, count);
            let two_l = 2 * freqs;
            let code_start = 1 + 6 * freqs;
            for (r, &g) in live.iter().enumerate() {
                let g = g as usize;
                for (a, &inv) in extent_inv.iter().enumerate() {
                    let i = g * 3 + a;
                    let cols = r * width + code_start + a * two_l;
                    let scale =
                        code_scale(&d_input[cols..cols + two_l], freqs, inv) + grads0[i].abs();
                    let err = (gpu[i] - d_means[i]).abs() / scale;
                    assert!(
                        err <= MEAN_GRAD_TOL,
                        "Psi mean grad of {g}.{a}: gpu {} cpu {} (scale {scale})",
                        gpu[i],
                        d_means[i]
                    );
                    worst = worst.max(err);
                }
            }
        }
    }
    eprintln!("Psi mean gradient: worst error / scale {worst:e} (tolerance {MEAN_GRAD_TOL:e})");
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
            enc, &scratch, &phi, &b.params, offsets, n, &b.list, &b.count, sun, cam, input, &flags,
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
        io.encode_phi_scatter(&mut enc, &scratch, n, 5, &b.list, &b.count, &short, &chans4),
        "5 channels",
    );
    invalid(
        io.encode_phi_scatter(&mut enc, &scratch, n, 4, &b.list, &b.count, &short, &chans4),
        "short Phi output",
    );
    invalid(
        io.encode_phi_d_output(&mut enc, &scratch, n, 4, &b.list, &b.count, &short, &chans4),
        "short rows",
    );
    invalid(
        io.encode_psi_scatter(
            &mut enc, &scratch, n, 3, &b.list, &b.count, &vis, &short, true, &chans4,
        ),
        "Psi with 3 channels",
    );
    let tiny = probe.buffer_f32("tiny", &vec![0.5; n / 2]);
    invalid(
        io.encode_psi_d_output(
            &mut enc, &scratch, n, 4, &b.list, &b.count, &tiny, &rows, true, &short,
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
            &scratch,
            &psi,
            &scene_box(),
            &b.params,
            offsets,
            n,
            &b.list,
            &b.count,
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
