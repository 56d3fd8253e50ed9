//! The device MLP (`gpu::GpuMlp`, through `nn::Mlp::set_device`) against the CPU MLP:
//! forward output and every gradient (each layer's weights and bias, the input) on random
//! inputs and odd shapes (rows not a multiple of the 16-row workgroup tile, over the CPU's
//! 2048-row block boundary and over several of the device's 256-row weight-gradient
//! chunks, widths 1, 32 and 256), both hidden activations and both tape modes; the
//! device's repeat runs are bit-identical.
//!
//! Tolerance (f32, the two sides sum the same products in other orders and the GPU's
//! `exp` differs from Rust's by an ulp or two): every value within
//! `2e-5 max|cpu| + 1e-4 |cpu|` of the CPU's (max over the compared group: one layer's
//! weights, one bias, the output, the input gradient), except at most 0.1% of the values,
//! which must stay within `1e-2 max|cpu|`. The exception is for ReLU kinks: a hidden
//! pre-activation within rounding of 0 can land on the other side, which changes that
//! unit's gradient for that row.
//!
//! Without an adapter the tests print a skip notice, unless `GS_REQUIRE_GPU=1` (CI).
#![cfg(feature = "wgpu")]

use std::sync::Arc;

use gs_core::gpu::mlp::{DeviceBatch, DeviceNetwork};
use gs_core::gpu::{GpuContext, GpuMlp};
use gs_core::nn::{HiddenActivation, Init, Mlp, TapeMode};
use gs_core::rng::SplitMix64;

fn device() -> Option<Arc<GpuMlp>> {
    match GpuContext::new() {
        Ok(ctx) => {
            eprintln!("GPU: {}", ctx.describe());
            Some(Arc::new(GpuMlp::new(ctx).unwrap()))
        }
        Err(e) => {
            if std::env::var("GS_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                panic!("GS_REQUIRE_GPU=1 but no usable GPU: {e}");
            }
            eprintln!("SKIPPED (set GS_REQUIRE_GPU=1 to fail instead): {e}");
            None
        }
    }
}

/// See the module docs for the tolerance. Returns the worst error / tolerance.
fn assert_close(name: &str, cpu: &[f32], gpu: &[f32]) -> f32 {
    assert_eq!(cpu.len(), gpu.len(), "{name}: lengths");
    let big = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(big > 0.0, "{name}: all zero, the comparison would be idle");
    let mut worst = 0.0f32;
    let mut n_off = 0usize;
    for (a, b) in cpu.iter().zip(gpu) {
        assert!(b.is_finite(), "{name}: non-finite device value");
        let err = (a - b).abs();
        let tol = 2e-5 * big + 1e-4 * a.abs();
        worst = worst.max(err / tol);
        if err > tol {
            n_off += 1;
            assert!(
                err <= 1e-2 * big,
                "{name}: cpu {a} gpu {b} (max |cpu| {big})"
            );
        }
    }
    assert!(
        n_off as f64 <= 1e-3 * cpu.len() as f64,
        "{name}: {n_off} of {} values beyond tolerance (worst {worst})",
        cpu.len()
    );
    worst
}

struct Case {
    widths: &'static [usize],
    hidden: HiddenActivation,
    rows: usize,
    mode: TapeMode,
    input_gradient: bool,
}

type Run = (Vec<f32>, Vec<f32>, Option<Vec<f32>>);

fn run(mlp: &Mlp, input: &[f32], rows: usize, mode: TapeMode, d_out: &[f32], dx: bool) -> Run {
    let forward = mlp.forward_train(input, rows, mode).unwrap();
    // Gradients are added to what is there: start from ones, subtract after.
    let mut d_params = vec![1.0f32; mlp.num_params()];
    let mut d_input = dx.then(|| vec![f32::NAN; input.len()]);
    mlp.backward(
        input,
        &forward,
        d_out,
        &mut d_params,
        d_input.as_deref_mut(),
    )
    .unwrap();
    for d in &mut d_params {
        *d -= 1.0;
    }
    (forward.output, d_params, d_input)
}

fn check_case(gpu: &Arc<GpuMlp>, case: &Case, seed: u64) {
    let cpu_net = Mlp::new(case.widths, case.hidden, Init::KaimingUniform, seed).unwrap();
    let mut gpu_net = cpu_net.clone();
    gpu_net.set_device(Some(gpu.clone()));
    assert!(cpu_net.device().is_cpu() && !gpu_net.device().is_cpu());
    assert!(gpu_net == cpu_net, "the device is no part of the value");
    let mut rng = SplitMix64::new(seed ^ 0x5eed);
    let input: Vec<f32> = (0..case.rows * cpu_net.input_width())
        .map(|_| rng.normal())
        .collect();
    let d_out: Vec<f32> = (0..case.rows * cpu_net.output_width())
        .map(|_| rng.normal())
        .collect();
    let (rows, mode, dx) = (case.rows, case.mode, case.input_gradient);
    let (y_c, p_c, x_c) = run(&cpu_net, &input, rows, mode, &d_out, dx);
    let t = std::time::Instant::now();
    let (y_g, p_g, x_g) = run(&gpu_net, &input, rows, mode, &d_out, dx);
    let device_s = t.elapsed().as_secs_f64();
    let label = format!("{:?} {:?} x{}", case.widths, case.hidden, rows);
    let mut worst = assert_close(&format!("{label} output"), &y_c, &y_g);
    for l in 0..cpu_net.num_layers() {
        let (w, b) = (cpu_net.weight_range(l), cpu_net.bias_range(l));
        worst = worst.max(assert_close(
            &format!("{label} dW{l}"),
            &p_c[w.clone()],
            &p_g[w],
        ));
        worst = worst.max(assert_close(
            &format!("{label} db{l}"),
            &p_c[b.clone()],
            &p_g[b],
        ));
    }
    match (x_c, &x_g) {
        (Some(c), Some(g)) => worst = worst.max(assert_close(&format!("{label} dX"), &c, g)),
        (None, None) => assert!(!dx),
        _ => panic!("{label}: input gradient on one side only"),
    }
    eprintln!(
        "{label}: worst error / tolerance {worst:.3}; device forward + backward {:.1} ms \
         (wall, shared machine)",
        device_s * 1e3
    );
    // Deterministic: a second device run gives the same bits.
    let (y_2, p_2, x_2) = run(&gpu_net, &input, rows, mode, &d_out, dx);
    assert!(
        y_2 == y_g && p_2 == p_g && x_2 == x_g,
        "{label}: not repeatable"
    );
}

#[test]
fn device_mlp_matches_the_cpu_mlp() {
    let Some(gpu) = device() else {
        return;
    };
    let cases = [
        // Phi as the training tests run it (32 wide), four weight-gradient chunks.
        Case {
            widths: &[80, 32, 32, 32, 3],
            hidden: HiddenActivation::Relu,
            rows: 976,
            mode: TapeMode::Cache,
            input_gradient: true,
        },
        // Phi-like: three hidden layers of 256, 300 rows (18 tiles and 12).
        Case {
            widths: &[37, 256, 256, 256, 3],
            hidden: HiddenActivation::Relu,
            rows: 300,
            mode: TapeMode::Cache,
            input_gradient: true,
        },
        // Psi-like, over the CPU's 2048-row block boundary, recompute mode on the CPU.
        Case {
            widths: &[19, 64, 64, 1],
            hidden: HiddenActivation::Relu,
            rows: 2085,
            mode: TapeMode::Recompute,
            input_gradient: true,
        },
        // Width 1 inside (LeakyReLU so the single unit is never dead), width 32.
        Case {
            widths: &[32, 1, 32, 1],
            hidden: HiddenActivation::LeakyRelu,
            rows: 77,
            mode: TapeMode::Cache,
            input_gradient: true,
        },
        // One row, one input.
        Case {
            widths: &[1, 32, 1],
            hidden: HiddenActivation::LeakyRelu,
            rows: 1,
            mode: TapeMode::Cache,
            input_gradient: true,
        },
        // A single affine layer, no input gradient asked for.
        Case {
            widths: &[4, 3],
            hidden: HiddenActivation::Relu,
            rows: 17,
            mode: TapeMode::Cache,
            input_gradient: false,
        },
    ];
    for (i, case) in cases.iter().enumerate() {
        check_case(&gpu, case, 11 + i as u64);
    }
}

/// Zero rows give an empty output and a zero parameter gradient, as on the CPU; bad input
/// is the same error on both (checked before any device work).
#[test]
fn device_mlp_edge_cases_match_the_cpu() {
    let Some(gpu) = device() else {
        return;
    };
    let cpu_net = Mlp::new(&[5, 32, 2], HiddenActivation::Relu, Init::KaimingUniform, 3).unwrap();
    let mut gpu_net = cpu_net.clone();
    gpu_net.set_device(Some(gpu));
    let empty_c = run(&cpu_net, &[], 0, TapeMode::Cache, &[], true);
    let empty_g = run(&gpu_net, &[], 0, TapeMode::Cache, &[], true);
    assert_eq!(empty_c, empty_g);
    assert!(empty_g.0.is_empty() && empty_g.1.iter().all(|&v| v == 0.0));
    let mut bad = vec![0.5f32; 3 * 5];
    bad[7] = f32::NAN;
    let e_c = cpu_net.forward_train(&bad, 3, TapeMode::Cache).unwrap_err();
    let e_g = gpu_net.forward_train(&bad, 3, TapeMode::Cache).unwrap_err();
    assert_eq!(e_c, e_g);
    let e_g = gpu_net
        .forward_train(&bad[..14], 3, TapeMode::Cache)
        .unwrap_err();
    let e_c = cpu_net
        .forward_train(&bad[..14], 3, TapeMode::Cache)
        .unwrap_err();
    assert_eq!(e_c, e_g);
    // A non-finite output gradient is refused on the device path too, nothing added.
    let input = vec![0.25f32; 3 * 5];
    let forward = gpu_net.forward_train(&input, 3, TapeMode::Cache).unwrap();
    let mut d_params = vec![0.0f32; gpu_net.num_params()];
    let mut d_out = vec![1.0f32; 6];
    d_out[2] = f32::INFINITY;
    assert!(gpu_net
        .backward(&input, &forward, &d_out, &mut d_params, None)
        .is_err());
    assert!(d_params.iter().all(|&v| v == 0.0));
}

// ---- The resident path (`gpu::mlp::DeviceNetwork`, `GpuMlp::encode_*`, driven from the
// host through `DeviceBatch`, `GpuMlp::run_forward_backward` and `GpuMlp::run_adam`, which
// record exactly what the resident Sun-aware step records).

/// A network with random non-zero biases (Kaiming leaves them 0, which would hide a bias
/// read from the wrong offset).
fn network_with_biases(widths: &[usize], hidden: HiddenActivation, seed: u64) -> Mlp {
    let mut net = Mlp::new(widths, hidden, Init::KaimingUniform, seed).unwrap();
    let mut rng = SplitMix64::new(seed ^ 0xb1a5);
    for l in 0..net.num_layers() {
        let range = net.bias_range(l);
        for b in &mut net.params_mut()[range] {
            *b = rng.uniform_symmetric(0.2);
        }
    }
    net
}

/// Rows `live..` of a `rows x width` batch set to NaN: the device must never read them.
fn poison_dead_rows(values: &mut [f32], width: usize, live: usize) {
    for v in &mut values[live * width..] {
        *v = f32::NAN;
    }
}

fn assert_all_zero_bits(name: &str, values: &[f32]) {
    if let Some(i) = values.iter().position(|v| v.to_bits() != 0) {
        panic!("{name}: value {} at {i}, expected +0", values[i]);
    }
}

struct ResidentCase {
    widths: &'static [usize],
    hidden: HiddenActivation,
    max_rows: usize,
    live: usize,
}

/// One resident forward + backward on `batch` of `live` of its rows: (output, input
/// gradient, parameter gradient), the parameter gradient first poisoned with NaN so a
/// value the backward does not overwrite shows.
fn resident_run(
    gpu: &GpuMlp,
    net: &DeviceNetwork,
    batch: &DeviceBatch,
    (input, d_out): (&[f32], &[f32]),
    live: usize,
) -> Run {
    let ctx = gpu.context();
    net.upload_grads(ctx, &vec![f32::NAN; net.len()]).unwrap();
    batch.write(gpu, input, live, d_out).unwrap();
    gpu.run_forward_backward(net, batch, true).unwrap();
    let (output, d_input) = batch.read(gpu).unwrap();
    (output, net.download_grads(ctx).unwrap(), Some(d_input))
}

fn check_resident_case(gpu: &Arc<GpuMlp>, case: &ResidentCase, seed: u64) {
    let cpu_net = network_with_biases(case.widths, case.hidden, seed);
    let (n_in, n_out) = (cpu_net.input_width(), cpu_net.output_width());
    let (max_rows, live) = (case.max_rows, case.live);
    let mut rng = SplitMix64::new(seed ^ 0x5eed);
    let mut input: Vec<f32> = (0..max_rows * n_in).map(|_| rng.normal()).collect();
    let mut d_out: Vec<f32> = (0..max_rows * n_out).map(|_| rng.normal()).collect();
    let zeros = vec![0.0f32; cpu_net.num_params()];
    let net = DeviceNetwork::new(gpu.context(), &cpu_net, &zeros, &zeros, 0).unwrap();
    let batch = DeviceBatch::new(gpu, &net, max_rows).unwrap();
    let label = format!("resident {:?} {:?}", case.widths, case.hidden);
    let compare = |name: &str, rows: usize, (input, d_out): (&[f32], &[f32]), got: &Run| {
        let (y_c, p_c, x_c) = run(
            &cpu_net,
            &input[..rows * n_in],
            rows,
            TapeMode::Cache,
            &d_out[..rows * n_out],
            true,
        );
        let (y_g, p_g, x_g) = got;
        let x_g = x_g.as_ref().unwrap();
        let mut worst = assert_close(&format!("{name} output"), &y_c, &y_g[..rows * n_out]);
        worst = worst.max(assert_close(
            &format!("{name} dX"),
            x_c.as_ref().unwrap(),
            &x_g[..rows * n_in],
        ));
        for l in 0..cpu_net.num_layers() {
            let (w, b) = (cpu_net.weight_range(l), cpu_net.bias_range(l));
            worst = worst.max(assert_close(
                &format!("{name} dW{l}"),
                &p_c[w.clone()],
                &p_g[w],
            ));
            worst = worst.max(assert_close(
                &format!("{name} db{l}"),
                &p_c[b.clone()],
                &p_g[b],
            ));
        }
        assert_all_zero_bits(&format!("{name} dead output rows"), &y_g[rows * n_out..]);
        assert_all_zero_bits(&format!("{name} dead dX rows"), &x_g[rows * n_in..]);
        worst
    };
    // Every row live first, so the dead rows of the next run held non-zero values.
    let full = resident_run(gpu, &net, &batch, (&input, &d_out), max_rows);
    let name = format!("{label} all {max_rows} live");
    let worst_full = compare(&name, max_rows, (&input, &d_out), &full);
    // Then `live` rows: the dead ones are NaN and must be neither read nor left stale.
    poison_dead_rows(&mut input, n_in, live);
    poison_dead_rows(&mut d_out, n_out, live);
    let t = std::time::Instant::now();
    let partial = resident_run(gpu, &net, &batch, (&input, &d_out), live);
    let device_s = t.elapsed().as_secs_f64();
    let name = format!("{label} {live} of {max_rows} live");
    let worst = compare(&name, live, (&input, &d_out), &partial);
    // The host path on the live rows runs the same kernels with the same chunk
    // boundaries: the same values (`==`: a dead chunk's +0 may flip the sign of a 0 sum).
    let (host_y, tape) = gpu.forward(&cpu_net, &input[..live * n_in], live).unwrap();
    let host = gpu.backward(&tape, &d_out[..live * n_out], true).unwrap();
    assert!(
        host_y[..] == partial.0[..live * n_out],
        "{name}: output differs from the host path"
    );
    assert!(
        host.params == partial.1,
        "{name}: parameter gradient differs from the host path"
    );
    assert!(
        host.input.unwrap()[..] == partial.2.as_ref().unwrap()[..live * n_in],
        "{name}: input gradient differs from the host path"
    );
    // Deterministic: the same run again gives the same bits.
    let again = resident_run(gpu, &net, &batch, (&input, &d_out), live);
    let bits = |r: &Run| -> Vec<u32> {
        let x = r.2.as_ref().unwrap();
        r.0.iter()
            .chain(&r.1)
            .chain(x)
            .map(|v| v.to_bits())
            .collect()
    };
    assert!(bits(&again) == bits(&partial), "{name}: not repeatable");
    eprintln!(
        "{name}: worst error / tolerance {worst_full:.3} (all live), {worst:.3}; device \
         forward + backward with transfers {:.1} ms (wall, shared machine)",
        device_s * 1e3
    );
    // No live row: zero output, gradients and input gradient (every dead input is NaN).
    poison_dead_rows(&mut input, n_in, 0);
    poison_dead_rows(&mut d_out, n_out, 0);
    let (y, p, x) = resident_run(gpu, &net, &batch, (&input, &d_out), 0);
    assert_all_zero_bits(&format!("{label} 0 live output"), &y);
    assert_all_zero_bits(&format!("{label} 0 live parameter gradient"), &p);
    assert_all_zero_bits(&format!("{label} 0 live dX"), &x.unwrap());
}

/// The resident forward and backward against the CPU MLP on the live rows of batches
/// whose dead rows hold NaN: outputs and every gradient within the module's tolerance,
/// dead rows exactly +0, the parameter gradient that of the live rows only (the same
/// values as the host path on those rows alone), repeat runs bit-identical, no live row
/// all zeros.
#[test]
fn resident_network_matches_the_cpu_on_the_live_rows() {
    let Some(gpu) = device() else {
        return;
    };
    let cases = [
        // Phi-like: three chunks of the weight gradient, the third dead.
        ResidentCase {
            widths: &[37, 256, 256, 256, 3],
            hidden: HiddenActivation::Relu,
            max_rows: 517,
            live: 300,
        },
        // Psi-like.
        ResidentCase {
            widths: &[19, 32, 32, 32, 1],
            hidden: HiddenActivation::LeakyRelu,
            max_rows: 517,
            live: 300,
        },
        // Phi as the training tests run it: the live count inside the fourth of five
        // chunks, not on a 16-row tile boundary.
        ResidentCase {
            widths: &[80, 32, 32, 32, 3],
            hidden: HiddenActivation::Relu,
            max_rows: 1100,
            live: 901,
        },
        // One chunk, one layer, one dead row.
        ResidentCase {
            widths: &[4, 3],
            hidden: HiddenActivation::Relu,
            max_rows: 17,
            live: 16,
        },
    ];
    for (i, case) in cases.iter().enumerate() {
        check_resident_case(&gpu, case, 31 + i as u64);
    }
}
