//! Phi's (the appearance network's) input rows, their refusals, the output scatter and
//! output gradient, and the input gradient's scatter, against the CPU.

use super::*;
use glam::Vec3;
use gs_core::model::ParamSet;
use gs_core::sunaware::shading::{shade_backward, shade_forward, Shading};
use gs_wgpu::network_io::{PhiShading, PhiShadingGrad};

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
                &mut enc,
                b.rows(&scratch, n),
                &net,
                b.packed(&s.offsets),
                SUN,
                CAMERA,
                &input,
                &flags,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&input, n * width)]).unwrap();
            let view_start = f_dim + 6 * freqs;
            let means = s.group(Param::Mean);
            let tol = |r: usize, c: usize| {
                let g = s.live()[r] as usize;
                (c >= view_start).then(|| {
                    let mean = &means[3 * g..3 * g + 3];
                    phi_view_column_tol(mean, Vec3::from(SUN), c, view_start, freqs)
                })
            };
            worst = worst.max(compare_rows("Phi input", &cpu, &gpu[0], width, count, &tol));
            assert_eq!(probe.read_u32(&flags, 1).unwrap(), [0], "flags");
        }
    }
    eprintln!("Phi input: worst encoding error / tolerance {worst:.3}");
}

/// Runs Phi's input assembly on `s` and returns flags[0].
fn phi_flags(rig: &Rig, s: &Scene, net: &AppearanceNet) -> u32 {
    let Rig { io, scratch, probe } = rig;
    let b = upload(probe, s, s.count);
    let input = probe.buffer_f32("input", &vec![0.0; s.n * net.input_width()]);
    let flags = probe.buffer_u32("flags", &[0]);
    let mut enc = probe.encoder();
    io.encode_phi_input(
        &mut enc,
        b.rows(scratch, s.n),
        net,
        b.packed(&s.offsets),
        SUN,
        CAMERA,
        &input,
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
            io.encode_phi_scatter(&mut enc, b.rows(&scratch, n), nc, &out_buf, None, &chans)
                .unwrap();
            io.encode_phi_d_output(&mut enc, b.rows(&scratch, n), nc, &rows_buf, None, &d_out)
                .unwrap();
            let gpu = probe
                .finish_f32(enc, &[(&chans, n * nc), (&d_out, n * 3)])
                .unwrap();
            // The model's loops (sunaware/model/forward.rs forward_with, model/backward.rs backward_timed).
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
                &mut enc,
                b.rows(&scratch, n),
                &net,
                b.packed(&s.offsets),
                CAMERA,
                SUN,
                &d_in,
                &grads,
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

/// The learned-normal shading (`Shading::LambertLearned`): both sides evaluate the same
/// f32 operations in the same order (the normal's and the view's sqrt and divisions are
/// correctly rounded on lavapipe); a device that fuses multiply-adds or rounds sqrt and
/// division to a few ulp moves each value by a few ulps of the terms that enter it:
/// |gpu - cpu| <= SHADE_TOL * scale, with scale the sum of those terms' magnitudes.
const SHADE_TOL: f32 = 1.0 / 1_048_576.0;

/// Phi's scatter and output gradient with the learned-normal Lambertian factor against
/// `shading::{shade_forward, shade_backward}` as the model calls them (forward.rs: the
/// listed Gaussians' Phi colour, shaded in place; backward.rs: the rasterizer's colour
/// gradient, unshaded in place, the normal's term added to its gradient): the shaded
/// channels, Phi's output gradient and the Normal group's gradient (added to junk, so the
/// add is checked too). Degenerate normals (zero, below `MIN_NORMAL_NORM2`, infinite) on
/// listed Gaussians get factor 1 and no gradient, bit for bit; unlisted Gaussians' channels
/// and every other gradient are untouched, dead rows of `d_out` exactly 0.
#[test]
fn phi_learned_shading_matches_the_cpu() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let ambient = 0.1f32;
    let sun = Vec3::from(SUN).normalize();
    let cam = Vec3::from(CAMERA);
    let mut worst = 0.0f32;
    let (mut lit, mut unlit, mut degenerate) = (0usize, 0usize, 0usize);
    for nc in [3usize, 4] {
        let mut s = Scene::with_normals(40 + nc as u64, 600, 8, 0.55);
        let n = s.n;
        let no = s.offsets[Param::Normal.index()] as usize;
        let live0: Vec<usize> = s.live().iter().map(|&g| g as usize).collect();
        for (g, v) in [
            (live0[1], [0.0f32; 3]),
            (live0[2], [1e-4, 0.0, 0.0]),
            (live0[3], [f32::INFINITY, 0.0, 1.0]),
        ] {
            s.params[no + 3 * g..no + 3 * g + 3].copy_from_slice(&v);
        }
        let mut set = ParamSet::new(s.dims);
        set.push_zeros(n);
        for p in Param::ALL {
            set.get_mut(p).copy_from_slice(s.group(p));
        }
        let output = junk(50, n * 3);
        let chans0 = junk(51, n * nc);
        let rows = junk(52, n * (13 + nc));
        let grads0 = junk(53, s.params.len());
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let out_buf = probe.buffer_f32("output", &output);
            let chans = probe.buffer_f32("chans", &chans0);
            let rows_buf = probe.buffer_f32("rows", &rows);
            let d_out = probe.buffer_f32("d_out", &junk(54, n * 3));
            let factors = probe.buffer_f32("factors", &junk(55, 2 * n));
            let grads = probe.buffer_f32("grads", &grads0);
            let shading = PhiShading {
                params: b.packed(&s.offsets),
                camera_centre: CAMERA,
                sun_dir: sun.to_array(),
                ambient,
                factors: &factors,
            };
            let mut enc = probe.encoder();
            io.encode_phi_scatter(
                &mut enc,
                b.rows(&scratch, n),
                nc,
                &out_buf,
                Some(shading),
                &chans,
            )
            .unwrap();
            io.encode_phi_d_output(
                &mut enc,
                b.rows(&scratch, n),
                nc,
                &rows_buf,
                Some(PhiShadingGrad {
                    shading,
                    output: &out_buf,
                    grads: &grads,
                }),
                &d_out,
            )
            .unwrap();
            let gpu = probe
                .finish_f32(
                    enc,
                    &[(&chans, n * nc), (&d_out, n * 3), (&grads, grads0.len())],
                )
                .unwrap();
            // The model (forward.rs forward_with, backward.rs backward_timed).
            let list = &s.list[..count];
            let mut colour = vec![0.0f32; n * 3];
            for (r, &g) in list.iter().enumerate() {
                let g = g as usize;
                colour[g * 3..g * 3 + 3].copy_from_slice(&output[r * 3..r * 3 + 3]);
            }
            let pass = shade_forward(
                Shading::LambertLearned,
                &set,
                list,
                cam,
                sun,
                ambient,
                &mut colour,
            );
            let stride = 13 + nc;
            let mut d_colour: Vec<f32> = (0..n)
                .flat_map(|g| rows[g * stride + 13..g * stride + 16].to_vec())
                .collect();
            let mut cpu_grads = set.zeros_like();
            cpu_grads
                .get_mut(Param::Normal)
                .copy_from_slice(&grads0[no..no + 3 * n]);
            shade_backward(&pass, &set, sun, ambient, &mut d_colour, &mut cpu_grads);

            let mut want_grads = grads0.clone();
            want_grads[no..no + 3 * n].copy_from_slice(cpu_grads.get(Param::Normal));
            let mut close = |what: &str, g: usize, gpu: f32, cpu: f32, scale: f32| {
                let err = (gpu - cpu).abs();
                assert!(
                    err <= SHADE_TOL * scale,
                    "{what} of Gaussian {g}, nc {nc}: gpu {gpu} cpu {cpu} (scale {scale})"
                );
                worst = worst.max(err / scale);
            };
            let mut listed = vec![false; n];
            for (r, &g) in list.iter().enumerate() {
                let g = g as usize;
                listed[g] = true;
                let f = pass.factor[g];
                let v = &s.params[no + 3 * g..no + 3 * g + 3];
                let degenerate_row = [1, 2, 3].iter().any(|&i| live0[i] == g);
                if degenerate_row {
                    assert_eq!(f, 1.0, "degenerate normal of {g}");
                    degenerate += 1;
                } else if f > ambient {
                    lit += 1;
                } else {
                    unlit += 1;
                }
                let mut d_f = 0.0f32;
                for k in 0..3 {
                    let (c, d) = (output[r * 3 + k], rows[g * stride + 13 + k]);
                    d_f += (c * d).abs();
                    if f == 1.0 {
                        // Factor 1: copies, bit for bit.
                        assert_eq!(gpu[0][g * nc + k].to_bits(), c.to_bits(), "chans {g}");
                        assert_eq!(gpu[1][r * 3 + k].to_bits(), d.to_bits(), "d_out {g}");
                    }
                    close("channel", g, gpu[0][g * nc + k], colour[g * 3 + k], c.abs());
                    close("d_out", g, gpu[1][r * 3 + k], d_colour[g * 3 + k], d.abs());
                }
                let v_norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                for k in 0..3 {
                    let i = no + 3 * g + k;
                    if f == 1.0 || f == ambient {
                        // No gradient (degenerate or unlit): the junk stays, bit for bit.
                        assert_eq!(gpu[2][i].to_bits(), grads0[i].to_bits(), "normal {g}");
                    }
                    let scale = grads0[i].abs() + 2.0 * d_f * (1.0 - ambient) / v_norm;
                    close("normal gradient", g, gpu[2][i], want_grads[i], scale);
                }
            }
            for g in (0..n).filter(|&g| !listed[g]) {
                for k in 0..3 {
                    let c = g * nc + k;
                    assert_eq!(gpu[0][c].to_bits(), chans0[c].to_bits(), "chans of {g}");
                }
            }
            for (i, (&a, &w)) in gpu[2].iter().zip(&grads0).enumerate() {
                let listed_normal = i >= no && i < no + 3 * n && listed[(i - no) / 3];
                if !listed_normal {
                    assert_eq!(a.to_bits(), w.to_bits(), "grads[{i}] touched");
                }
            }
            assert!(
                gpu[1][count * 3..].iter().all(|v| v.to_bits() == 0),
                "dead rows"
            );
        }
    }
    eprintln!(
        "learned shading: {lit} lit, {unlit} unlit, {degenerate} degenerate rows; \
         worst error / scale {worst:e} (tolerance {SHADE_TOL:e})"
    );
    assert!(lit > 50 && unlit > 50 && degenerate == 6);
}

/// The shading's arguments are checked before anything is recorded: a layout without the
/// Normal group, an ambient outside [0, 1), a short factor buffer, a zero Sun.
#[test]
fn phi_learned_shading_rejects_bad_arguments() {
    let Some(Rig { io, scratch, probe }) = rig() else {
        return;
    };
    let s = Scene::with_normals(60, 100, 8, 0.5);
    let n = s.n;
    let b = upload(&probe, &s, s.count);
    let output = probe.buffer_f32("output", &vec![0.5; n * 3]);
    let chans = probe.buffer_f32("chans", &vec![0.0; n * 3]);
    let factors = probe.buffer_f32("factors", &vec![0.0; 2 * n]);
    let short = probe.buffer_f32("short", &vec![0.0; n]);
    let plain = Scene::new(60, 100, 8, 6, 0.5);
    let good = PhiShading {
        params: b.packed(&s.offsets),
        camera_centre: CAMERA,
        sun_dir: Vec3::from(SUN).normalize().to_array(),
        ambient: 0.1,
        factors: &factors,
    };
    let mut enc = probe.encoder();
    let mut scatter = |shading: PhiShading| {
        io.encode_phi_scatter(
            &mut enc,
            b.rows(&scratch, n),
            3,
            &output,
            Some(shading),
            &chans,
        )
    };
    scatter(good).unwrap();
    for (what, bad) in [
        (
            "no normal group",
            PhiShading {
                params: b.packed(&plain.offsets),
                ..good
            },
        ),
        (
            "ambient 1",
            PhiShading {
                ambient: 1.0,
                ..good
            },
        ),
        (
            "short factors",
            PhiShading {
                factors: &short,
                ..good
            },
        ),
        (
            "zero Sun",
            PhiShading {
                sun_dir: [0.0; 3],
                ..good
            },
        ),
    ] {
        let r = scatter(bad);
        assert!(matches!(r, Err(GpuError::Invalid(_))), "{what}: {r:?}");
    }
    probe.finish_f32(enc, &[]).unwrap();
}
