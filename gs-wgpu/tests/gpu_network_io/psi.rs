//! Psi's (the shadow network's) input rows, their refusals, the output scatter and output
//! gradient in both refinement modes, and the input gradient's scatter, against the CPU.

use super::*;

fn visibility(seed: u64, n: usize) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    (0..n).map(|_| rng.next_f32()).collect()
}

/// `q = (m - min) / extent` of Gaussian `g` on `axis`, the CPU's box coordinate plus 0.5.
fn box_q(s: &Scene, g: usize, axis: usize) -> f32 {
    let (min, max) = (scene_box().min_m(), scene_box().max_m());
    (s.group(Param::Mean)[3 * g + axis] - min[axis]) / (max[axis] - min[axis])
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
                b.rows(&scratch, n),
                &net,
                &scene_box(),
                b.packed(&s.offsets),
                SUN,
                &vis_buf,
                &input,
                &flags,
            )
            .unwrap();
            let gpu = probe.finish_f32(enc, &[(&input, n * width)]).unwrap();
            let (code_start, code_end) = (1 + 6 * freqs, 1 + 12 * freqs);
            // The position encoding's argument, the box coordinate, may differ by
            // box_coordinate_err.
            let tol = |r: usize, c: usize| {
                if !(code_start..code_end).contains(&c) {
                    return None;
                }
                let i = c - code_start;
                let (axis, k) = (i / (2 * freqs), (i % (2 * freqs)) / 2);
                let g = s.live()[r] as usize;
                Some(encoding_tol(k, box_coordinate_err(box_q(&s, g, axis))))
            };
            worst = worst.max(compare_rows("Psi input", &cpu, &gpu[0], width, count, &tol));
            assert_eq!(probe.read_u32(&flags, 1).unwrap(), [0], "flags");
        }
    }
    eprintln!("Psi input: worst encoding error / tolerance {worst:.3}");
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
        b.rows(scratch, s.n),
        net,
        &scene_box(),
        b.packed(&s.offsets),
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
    // Gain 1, the demo's 2 and an inexact one under Multiply, in the CPU's order.
    for (mode, gain) in [
        (ShadowRefinement::Multiply, 1.0f32),
        (ShadowRefinement::Multiply, 2.0),
        (ShadowRefinement::Multiply, 1.37),
        (ShadowRefinement::Replace, 2.0),
    ] {
        let multiply = mode == ShadowRefinement::Multiply;
        let multiply_gain = multiply.then_some(gain);
        for count in [s.count, 0] {
            let b = upload(&probe, &s, count);
            let vis_buf = probe.buffer_f32("visibility", &vis);
            let out_buf = probe.buffer_f32("output", &output);
            let chans = probe.buffer_f32("chans", &chans0);
            let rows_buf = probe.buffer_f32("rows", &rows);
            let d_out = probe.buffer_f32("d_out", &junk(55, n));
            let mut enc = probe.encoder();
            io.encode_psi_scatter(
                &mut enc,
                b.rows(&scratch, n),
                nc,
                &vis_buf,
                &out_buf,
                multiply_gain,
                &chans,
            )
            .unwrap();
            io.encode_psi_d_output(
                &mut enc,
                b.rows(&scratch, n),
                nc,
                &vis_buf,
                &rows_buf,
                multiply_gain,
                &d_out,
            )
            .unwrap();
            let gpu = probe
                .finish_f32(enc, &[(&chans, n * nc), (&d_out, n)])
                .unwrap();
            // The model's loops (sunaware/model/forward.rs forward_with, model/backward.rs backward_timed).
            let mut want_chans = chans0.clone();
            let mut want_d_out = vec![0.0f32; n];
            for (r, &g) in s.list[..count].iter().enumerate() {
                let g = g as usize;
                want_chans[g * nc + 3] = if multiply {
                    gain * vis[g] * output[r]
                } else {
                    output[r]
                };
                let d = rows[g * (13 + nc) + 13 + 3];
                want_d_out[r] = if multiply { d * gain * vis[g] } else { d };
            }
            assert_eq!(
                bits(&gpu[0]),
                bits(&want_chans),
                "channels, {mode:?} gain {gain}"
            );
            assert_eq!(
                bits(&gpu[1]),
                bits(&want_d_out),
                "d_out, {mode:?} gain {gain}"
            );
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
                b.rows(&scratch, n),
                &net,
                &scene_box(),
                b.packed(&s.offsets),
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
                    let code = &d_input[cols..cols + two_l];
                    let scale = code_scale(code, freqs, inv) + grads0[i].abs();
                    let tol = MEAN_GRAD_TOL * scale
                        + box_coordinate_err(box_q(&s, g, a)) * code_arg_scale(code, freqs, inv);
                    let err = (gpu[i] - d_means[i]).abs();
                    assert!(
                        err <= tol,
                        "Psi mean grad of {g}.{a}: gpu {} cpu {} (tolerance {tol:e})",
                        gpu[i],
                        d_means[i]
                    );
                    worst = worst.max(err / tol);
                }
            }
        }
    }
    eprintln!("Psi mean gradient: worst error / tolerance {worst:.3}");
}
