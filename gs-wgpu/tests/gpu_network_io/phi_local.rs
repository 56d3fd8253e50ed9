//! Phi's local-frame inputs `[n.s, n.v, n.h]` (`appearance_inputs = "local"` and
//! `"local_no_sun"`) on the device against `sunaware::shading`: the input rows against
//! `assemble_phi_input`, the input gradient against `AppearanceNet::scatter_input_grad`
//! plus `scatter_local_input_grad` as the model sums them. Listed Gaussians include a zero,
//! a too-short and an infinite normal (zeros, no gradient) and one whose half vector is
//! degenerate (the Sun straight behind it from the camera: `n.h = 0`, no gradient
//! through it).

use super::*;
use glam::Vec3;
use gs_core::model::ParamSet;
use gs_core::nn::AppearanceInputs;
use gs_core::sunaware::shading::{assemble_phi_input, local_inputs, scatter_local_input_grad};

/// A scene with learned normals, three degenerate ones and a degenerate half vector on
/// listed Gaussians (returned: the degenerate normals' Gaussians, then the half
/// vector's), and the same parameters as a `ParamSet`.
fn local_scene(seed: u64, n: usize, f_dim: usize, sun: Vec3) -> (Scene, ParamSet, [usize; 4]) {
    let mut s = Scene::with_normals(seed, n, f_dim, 0.6);
    let no = s.offsets[Param::Normal.index()] as usize;
    let live: Vec<usize> = s.live().iter().map(|&g| g as usize).collect();
    let special = [live[1], live[2], live[3], live[5]];
    for (g, v) in [
        (special[0], [0.0f32; 3]),
        (special[1], [1e-4, 0.0, 0.0]),
        (special[2], [f32::INFINITY, 0.0, 1.0]),
    ] {
        s.params[no + 3 * g..no + 3 * g + 3].copy_from_slice(&v);
    }
    // Behind the Gaussian, from the camera, along the Sun: s + v = 0 up to rounding.
    let behind = Vec3::from(CAMERA) + sun * 2.0;
    s.params[3 * special[3]..3 * special[3] + 3].copy_from_slice(&behind.to_array());
    let mut set = ParamSet::new(s.dims);
    set.push_zeros(n);
    for p in Param::ALL {
        set.get_mut(p).copy_from_slice(s.group(p));
    }
    (s, set, special)
}

fn local_net(s: &Scene, freqs: usize, inputs: AppearanceInputs) -> AppearanceNet {
    let enc = PositionalEncoding::new(freqs).unwrap();
    let f_dim = s.dims[Param::Feature.index()];
    AppearanceNet::with_inputs(f_dim, 16, enc, inputs, 5).unwrap()
}

/// The rows with local inputs match `assemble_phi_input` (the paper's columns as
/// `phi_input_matches_the_cpu_rows` checks them, the local block within
/// `phi_view_column_tol`: dot products of unit vectors formed by the same operations,
/// whose roots and divisions WGSL does not round correctly everywhere), the
/// Sun's code is zeros under `LocalNoSun`, degenerate normals give three exact zeros and a
/// degenerate half vector an exact `n.h = 0`.
#[test]
fn phi_local_input_matches_the_cpu_rows() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let sun = Vec3::from(SUN).normalize();
    let mut worst = 0.0f32;
    for inputs in [AppearanceInputs::Local, AppearanceInputs::LocalNoSun] {
        for (seed, n, f_dim, freqs) in [(80, 700, 8, 4), (81, 60, 5, 10)] {
            let (s, set, special) = local_scene(seed, n, f_dim, sun);
            let net = local_net(&s, freqs, inputs);
            let (width, start) = (net.input_width(), net.local_start());
            let mut cpu = Vec::new();
            let cam = Vec3::from(CAMERA);
            assemble_phi_input(&net, &set, s.live(), cam, sun, &mut cpu).unwrap();
            for count in [s.count, 0] {
                let b = upload(&probe, &s, count);
                let input = probe.buffer_f32("input", &junk(seed, n * width));
                let flags = probe.buffer_u32("flags", &[0]);
                let mut enc = probe.encoder();
                io.encode_phi_input(
                    &mut enc,
                    b.rows(&scratch, n),
                    &net,
                    b.packed(&s.offsets),
                    sun.to_array(),
                    CAMERA,
                    &input,
                    &flags,
                )
                .unwrap();
                let gpu = probe.finish_f32(enc, &[(&input, n * width)]).unwrap();
                let gpu = &gpu[0];
                let view_start = f_dim + 6 * freqs;
                let means = s.group(Param::Mean);
                let tol = |r: usize, c: usize| {
                    let g = s.live()[r] as usize;
                    (c >= view_start).then(|| {
                        phi_view_column_tol(&means[3 * g..3 * g + 3], sun, c, view_start, freqs)
                    })
                };
                worst = worst.max(compare_rows(
                    &format!("Phi {inputs} input"),
                    &cpu,
                    gpu,
                    width,
                    count,
                    &tol,
                ));
                assert_eq!(probe.read_u32(&flags, 1).unwrap(), [0], "flags");
                if count == 0 {
                    continue;
                }
                let row_of = |g: usize| s.live().iter().position(|&x| x as usize == g).unwrap();
                for (r, &g) in s.live().iter().enumerate() {
                    let sun_code = &gpu[r * width + f_dim..r * width + f_dim + 6 * freqs];
                    let zeros = sun_code.iter().all(|&x| x == 0.0);
                    assert_eq!(
                        zeros,
                        inputs == AppearanceInputs::LocalNoSun,
                        "Sun code {g}"
                    );
                }
                for &g in &special[..3] {
                    let r = row_of(g);
                    let block = &gpu[r * width + start..(r + 1) * width];
                    assert_eq!(bits(block), [0; 3], "degenerate normal of {g}");
                }
                let r = row_of(special[3]);
                let block = &gpu[r * width + start..(r + 1) * width];
                assert_eq!(block[2].to_bits(), 0, "n.h of a degenerate half vector");
                assert!(block[0] != 0.0 && block[1] != 0.0, "{block:?}");
                assert_eq!(
                    &cpu[r * width + start..(r + 1) * width],
                    &local_inputs(&set, special[3], cam, sun)
                );
            }
        }
    }
    eprintln!("Phi local input: worst error / tolerance {worst:.3}");
}

/// The input gradient with local inputs: features set (bit for bit), the Normal group
/// gains `local_inputs_backward`'s term and the Mean group the view direction's plus the
/// local term, as the model sums them (backward.rs: `scatter_input_grad`, then
/// `scatter_local_input_grad`, then into the means), within MEAN_GRAD_TOL of each row's
/// scale; degenerate normals and a row whose local gradient is zero leave the Normal row
/// bit for bit; every other value is untouched. A zero or non-finite Sun is refused.
#[test]
fn phi_local_input_gradient_matches_the_cpu_scatter() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let sun = Vec3::from(SUN).normalize();
    let cam = Vec3::from(CAMERA);
    let (mut worst_mean, mut worst_normal) = (0.0f32, 0.0f32);
    for inputs in [AppearanceInputs::Local, AppearanceInputs::LocalNoSun] {
        let (seed, n, f_dim, freqs) = (90, 600, 8, 4);
        let (s, set, special) = local_scene(seed, n, f_dim, sun);
        let net = local_net(&s, freqs, inputs);
        let (width, start) = (net.input_width(), net.local_start());
        let mut d_input = junk(seed + 1, n * width);
        // One ordinary row whose local gradient is zero: no normal gradient.
        let quiet = s.live()[8] as usize;
        d_input[8 * width + start..9 * width].fill(0.0);
        let grads0 = junk(seed + 2, s.params.len());
        let no = s.offsets[Param::Normal.index()] as usize;
        let f0 = s.offsets[Param::Feature.index()] as usize;
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let d_in = probe.buffer_f32("d_input", &d_input);
            let grads = probe.buffer_f32("grads", &grads0);
            let mut enc = probe.encoder();
            // The local inputs need a Sun: a zero or non-finite one records nothing.
            for bad_sun in [[0.0; 3], [f32::NAN, 0.0, 1.0]] {
                let r = io.encode_phi_input_grad(
                    &mut enc,
                    b.rows(&scratch, n),
                    &net,
                    b.packed(&s.offsets),
                    CAMERA,
                    bad_sun,
                    &d_in,
                    &grads,
                );
                assert!(matches!(r, Err(GpuError::Invalid(_))), "{bad_sun:?}: {r:?}");
            }
            io.encode_phi_input_grad(
                &mut enc,
                b.rows(&scratch, n),
                &net,
                b.packed(&s.offsets),
                CAMERA,
                sun.to_array(),
                &d_in,
                &grads,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&grads, grads0.len())]).unwrap();
            let gpu = &gpu[0];
            // The model (backward.rs backward_timed).
            let live = &s.list[..count];
            let mut d_features = listed_rows_cleared(&grads0[f0..f0 + n * f_dim], f_dim, live);
            let mut d_means = vec![0.0f32; 3 * n];
            let d_rows = &d_input[..count * width];
            net.scatter_input_grad(
                live,
                s.group(Param::Mean),
                CAMERA,
                d_rows,
                &mut d_features,
                &mut d_means,
            )
            .unwrap();
            let mut d_normal = grads0[no..no + 3 * n].to_vec();
            scatter_local_input_grad(
                &net,
                &set,
                live,
                cam,
                sun,
                d_rows,
                &mut d_normal,
                &mut d_means,
            );
            let mut want = grads0.clone();
            want[f0..f0 + n * f_dim].copy_from_slice(&d_features);
            for (w, d) in want[..3 * n].iter_mut().zip(&d_means) {
                *w += d;
            }
            want[no..no + 3 * n].copy_from_slice(&d_normal);
            let listed = s.is_listed();
            for (i, (&a, &w)) in gpu.iter().zip(&want).enumerate() {
                let in_listed = |at: usize| i >= at && i < at + 3 * n && listed[(i - at) / 3];
                if count == 0 || !(in_listed(0) || in_listed(no)) {
                    assert_eq!(a.to_bits(), w.to_bits(), "grads[{i}]: {a} vs {w}");
                }
            }
            let view_start = f_dim + 6 * freqs;
            for (r, &g) in live.iter().enumerate() {
                let g = g as usize;
                let mean = Vec3::from_slice(&s.group(Param::Mean)[g * 3..g * 3 + 3]);
                let dist = (cam - mean).length();
                let view = (cam - mean) / dist;
                let half_len = (sun + view).length().max(1e-4);
                let v = Vec3::from_slice(&s.params[no + 3 * g..no + 3 * g + 3]);
                let d = &d_input[r * width + start..(r + 1) * width];
                // The local term's size: each d through unit vectors, 1 / |s + v| for n.h,
                // then 1 / |v| (normal) or 1 / distance (mean).
                let local = d[0].abs() + d[1].abs() + d[2].abs() * (1.0 + 2.0 / half_len);
                let degenerate = special[..3].contains(&g);
                for a in 0..3 {
                    let i = g * 3 + a;
                    let row = &d_input[r * width + view_start..r * width + start];
                    let scale =
                        code_scale(row, freqs, 2.0 / dist) + grads0[i].abs() + 2.0 * local / dist;
                    let err = (gpu[i] - want[i]).abs() / scale;
                    assert!(
                        err <= MEAN_GRAD_TOL,
                        "{inputs}: mean grad of {g}.{a}: gpu {} cpu {} (scale {scale})",
                        gpu[i],
                        want[i]
                    );
                    worst_mean = worst_mean.max(err);
                    let i = no + g * 3 + a;
                    if degenerate || g == quiet {
                        assert_eq!(gpu[i].to_bits(), grads0[i].to_bits(), "normal of {g}");
                        continue;
                    }
                    let scale = grads0[i].abs() + 2.0 * local / v.length();
                    let err = (gpu[i] - want[i]).abs() / scale;
                    assert!(
                        err <= MEAN_GRAD_TOL,
                        "{inputs}: normal grad of {g}.{a}: gpu {} cpu {} (scale {scale})",
                        gpu[i],
                        want[i]
                    );
                    worst_normal = worst_normal.max(err);
                }
            }
        }
    }
    eprintln!(
        "Phi local input gradient: worst error / scale, means {worst_mean:e}, normals \
         {worst_normal:e} (tolerance {MEAN_GRAD_TOL:e})"
    );
}
