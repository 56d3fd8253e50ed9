//! The device MLP (`gs_wgpu::GpuMlp::forward` and `backward`) against the CPU MLP:
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

use std::sync::Arc;

use gs_core::nn::{HiddenActivation, Init, Mlp, TapeMode};
use gs_core::rng::SplitMix64;
use gs_core::sunaware::trainer::FlatAdam;
use gs_wgpu::mlp::{DeviceBatch, DeviceNetwork};
use gs_wgpu::{context_or_skip, GpuError, GpuMlp, GpuOptions};

fn device() -> Option<Arc<GpuMlp>> {
    let ctx = context_or_skip(GpuOptions::default())?;
    Some(Arc::new(GpuMlp::new(ctx).unwrap()))
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

/// [`run`] on the device: `GpuMlp`'s forward and backward of `mlp`'s weights (the tape
/// mode is the CPU's choice; the device keeps its activations either way).
fn run_device(gpu: &GpuMlp, mlp: &Mlp, input: &[f32], rows: usize, d_out: &[f32], dx: bool) -> Run {
    let (output, tape) = gpu.forward(mlp, input, rows).unwrap();
    assert_eq!(tape.rows(), rows);
    let grads = gpu.backward(&tape, d_out, dx).unwrap();
    assert_eq!(grads.params.len(), mlp.num_params());
    (output, grads.params, grads.input)
}

fn check_case(gpu: &Arc<GpuMlp>, case: &Case, seed: u64) {
    let cpu_net = Mlp::new(case.widths, case.hidden, Init::KaimingUniform, seed).unwrap();
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
    let (y_g, p_g, x_g) = run_device(gpu, &cpu_net, &input, rows, &d_out, dx);
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
    let (y_2, p_2, x_2) = run_device(gpu, &cpu_net, &input, rows, &d_out, dx);
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

/// Zero rows give an empty output and a zero parameter gradient, as on the CPU; an input
/// or output gradient of the wrong length is an error before any device work.
#[test]
fn device_mlp_edge_cases_match_the_cpu() {
    let Some(gpu) = device() else {
        return;
    };
    let cpu_net = Mlp::new(&[5, 32, 2], HiddenActivation::Relu, Init::KaimingUniform, 3).unwrap();
    let empty_c = run(&cpu_net, &[], 0, TapeMode::Cache, &[], true);
    let empty_g = run_device(&gpu, &cpu_net, &[], 0, &[], true);
    assert_eq!(empty_c, empty_g);
    assert!(empty_g.0.is_empty() && empty_g.1.iter().all(|&v| v == 0.0));
    let bad = vec![0.5f32; 14];
    assert!(cpu_net.forward_train(&bad, 3, TapeMode::Cache).is_err());
    assert!(matches!(
        gpu.forward(&cpu_net, &bad, 3),
        Err(GpuError::Invalid(_))
    ));
    let input = vec![0.25f32; 3 * 5];
    let (_, tape) = gpu.forward(&cpu_net, &input, 3).unwrap();
    assert!(matches!(
        gpu.backward(&tape, &[1.0; 5], false),
        Err(GpuError::Invalid(_))
    ));
}

// ---- The resident path (`gs_wgpu::mlp::DeviceNetwork`, `GpuMlp::encode_*`, driven from the
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

/// Values of magnitude 1e-20 to 1e3 times `scale`, both signs.
fn random_magnitudes(len: usize, rng: &mut SplitMix64, scale: f32) -> Vec<f32> {
    (0..len)
        .map(|_| {
            let magnitude = 10f32.powf(rng.uniform(-20.0, 3.0));
            scale * magnitude * if rng.next_f32() < 0.5 { -1.0 } else { 1.0 }
        })
        .collect()
}

/// The device state of `net` as (parameters, m, v).
fn download_state(gpu: &GpuMlp, net: &DeviceNetwork, like: &Mlp) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut mlp = like.clone();
    let mut m = vec![0.0f32; net.len()];
    let mut v = vec![0.0f32; net.len()];
    net.download(gpu.context(), &mut mlp, &mut m, &mut v)
        .unwrap();
    (mlp.params().to_vec(), m, v)
}

fn state_bits(state: &(Vec<f32>, Vec<f32>, Vec<f32>)) -> Vec<u32> {
    state
        .0
        .iter()
        .chain(&state.1)
        .chain(&state.2)
        .map(|x| x.to_bits())
        .collect()
}

/// `FlatAdam::apply` (the reference of the device Adam below) refuses lengths that
/// differ and changes nothing then; its first step moves each parameter by the learning
/// rate against the gradient's sign (m / sqrt(v) = sign(g) after bias correction).
#[test]
fn flat_adam_refuses_mismatched_lengths() {
    let mut adam = FlatAdam::new(3);
    let mut params = [1.0f32, 2.0, 3.0];
    assert!(
        adam.apply(&mut params, &[0.5; 2], 1e-3).is_err(),
        "short gradient"
    );
    assert!(
        adam.apply(&mut params[..2], &[0.5; 2], 1e-3).is_err(),
        "moments longer than the parameters"
    );
    assert_eq!(params, [1.0, 2.0, 3.0]);
    assert_eq!(adam, FlatAdam::new(3));
    adam.apply(&mut params, &[0.5, -0.5, 0.5], 1e-3).unwrap();
    assert_eq!(adam.step, 1);
    for (x, expected) in params.iter().zip([0.999f32, 2.001, 2.999]) {
        assert!((x - expected).abs() < 1e-6, "{x} vs {expected}");
    }
}

/// The device Adam step (`GpuMlp::encode_adam`) against FlatAdam's rule, from moments
/// and a step counter of a run in progress: four steps (learning rates 1e-3, 5e-4 and 0,
/// where the moments still move) and a refused one (flags[0] set) between them, which
/// changes no bit and does not count.
///
/// Tolerance as tests/gpu_resident.rs's Adam test (the same kernel, same reasoning): per
/// step the kernel computes the same operations in the same order, differing by FMA
/// contraction and the Vulkan precision of division (2.5 ulp) and sqrt, so `|m_gpu -
/// m_cpu| <= 8 eps (|m| + 0.1 sum|g|)`, `|v_gpu - v_cpu| <= 8 eps (|v| + 0.001 sum g^2)`,
/// `|x_gpu - x_cpu| <= 8 eps (|x| + sum|dx|)` (eps = f32::EPSILON, `dx` the reference's
/// per-step changes).
#[test]
fn resident_adam_matches_flat_adam() {
    let Some(gpu) = device() else {
        return;
    };
    let mut mlp = network_with_biases(&[19, 32, 32, 32, 1], HiddenActivation::LeakyRelu, 7);
    let n = mlp.num_params();
    let mut rng = SplitMix64::new(70);
    let mut reference = FlatAdam {
        m: random_magnitudes(n, &mut rng, 1e-2),
        v: random_magnitudes(n, &mut rng, 1e-4)
            .iter()
            .map(|x| x.abs())
            .collect(),
        step: 5,
    };
    let ctx = gpu.context();
    let mut net = DeviceNetwork::new(ctx, &mlp, &reference.m, &reference.v, 5).unwrap();
    let mut sum_dx = vec![0.0f32; n];
    let mut sum_g = vec![0.0f32; n];
    let mut sum_g2 = vec![0.0f32; n];
    for (lr, refuse) in [(1e-3, false), (2e-3, true), (5e-4, false), (0.0, false)] {
        let grads = random_magnitudes(n, &mut rng, 1e-2);
        net.upload_grads(ctx, &grads).unwrap();
        if refuse {
            let before = download_state(&gpu, &net, &mlp);
            let step = net.adam_step();
            assert!(!gpu.run_adam(&mut net, lr, true).unwrap());
            assert_eq!(net.adam_step(), step, "a refused step counted");
            let after = download_state(&gpu, &net, &mlp);
            assert!(
                state_bits(&before) == state_bits(&after),
                "a refused step changed the network"
            );
            continue;
        }
        let before = mlp.params().to_vec();
        reference.apply(mlp.params_mut(), &grads, lr).unwrap();
        assert!(gpu.run_adam(&mut net, lr, false).unwrap());
        for i in 0..n {
            sum_dx[i] += (mlp.params()[i] - before[i]).abs();
            sum_g[i] += grads[i].abs();
            sum_g2[i] += grads[i] * grads[i];
        }
    }
    assert_eq!((net.adam_step(), reference.step), (8, 8));
    let (x_g, m_g, v_g) = download_state(&gpu, &net, &mlp);
    let eps = 8.0 * f32::EPSILON;
    let mut worst = 0.0f32;
    let mut differ = 0usize;
    for i in 0..n {
        let (x, m, v) = (mlp.params()[i], reference.m[i], reference.v[i]);
        differ += [(x_g[i], x), (m_g[i], m), (v_g[i], v)]
            .iter()
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count();
        let tol_x = eps * (x.abs() + sum_dx[i]);
        let tol_m = eps * (m.abs() + 0.1 * sum_g[i]);
        let tol_v = eps * (v.abs() + 0.001 * sum_g2[i]);
        assert!(
            (x_g[i] - x).abs() <= tol_x,
            "x[{i}]: gpu {} cpu {x}",
            x_g[i]
        );
        assert!(
            (m_g[i] - m).abs() <= tol_m,
            "m[{i}]: gpu {} cpu {m}",
            m_g[i]
        );
        assert!(
            (v_g[i] - v).abs() <= tol_v,
            "v[{i}]: gpu {} cpu {v}",
            v_g[i]
        );
        for (err, tol) in [
            ((x_g[i] - x).abs(), tol_x),
            ((m_g[i] - m).abs(), tol_m),
            ((v_g[i] - v).abs(), tol_v),
        ] {
            if tol > 0.0 {
                worst = worst.max(err / tol);
            }
        }
    }
    assert!(
        sum_dx.iter().any(|&d| d > 0.0),
        "the steps moved nothing, the comparison would be idle"
    );
    eprintln!(
        "resident Adam: worst error / tolerance {worst:.3}, {differ} of {} values not \
         bit-identical",
        3 * n
    );
    // A non-finite or negative learning rate is refused before any device work.
    for lr in [f32::NAN, f32::INFINITY, -1e-3] {
        assert!(matches!(
            gpu.run_adam(&mut net, lr, false),
            Err(GpuError::Invalid(_))
        ));
    }
    assert_eq!(net.adam_step(), 8);
}

/// Upload and download move every bit (subnormals, -0, extremes included); a network of
/// another shape or activation, moments of the wrong length, non-finite values and
/// mismatched batches are errors that change nothing.
#[test]
fn resident_network_round_trip_and_bad_input() {
    let Some(gpu) = device() else {
        return;
    };
    let ctx = gpu.context();
    let widths = [5, 32, 2];
    let n = Mlp::new(&widths, HiddenActivation::Relu, Init::KaimingUniform, 1)
        .unwrap()
        .num_params();
    let mut rng = SplitMix64::new(90);
    let special = [-0.0f32, 1e-40, -1e-45, f32::MAX, f32::MIN_POSITIVE, 1.0];
    let mut values = |len: usize| -> Vec<f32> {
        let mut out = random_magnitudes(len, &mut rng, 1.0);
        out[..special.len()].copy_from_slice(&special);
        out
    };
    let a = Mlp::from_params(&widths, HiddenActivation::Relu, values(n)).unwrap();
    let (m_a, v_a) = (values(n), values(n));
    let mut net = DeviceNetwork::new(ctx, &a, &m_a, &v_a, 12).unwrap();
    assert_eq!(
        (net.len(), net.widths(), net.adam_step()),
        (n, &widths[..], 12)
    );
    let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    let got = download_state(&gpu, &net, &a);
    assert_eq!(bits(&got.0), bits(a.params()));
    assert_eq!((bits(&got.1), bits(&got.2)), (bits(&m_a), bits(&v_a)));
    // A second upload replaces everything.
    let b = Mlp::from_params(&widths, HiddenActivation::Relu, values(n)).unwrap();
    let (m_b, v_b) = (values(n), values(n));
    net.upload(ctx, &b, &m_b, &v_b, 3).unwrap();
    assert_eq!(net.adam_step(), 3);
    let got = download_state(&gpu, &net, &a);
    assert_eq!(bits(&got.0), bits(b.params()));
    assert_eq!((bits(&got.1), bits(&got.2)), (bits(&m_b), bits(&v_b)));
    // Shapes and activations must match; nothing changes on refusal.
    let other_width =
        Mlp::new(&[5, 16, 2], HiddenActivation::Relu, Init::KaimingUniform, 2).unwrap();
    let other_act =
        Mlp::from_params(&widths, HiddenActivation::LeakyRelu, b.params().to_vec()).unwrap();
    let short = vec![0.0f32; n - 1];
    let mut nan_m = m_b.clone();
    nan_m[4] = f32::NAN;
    let (m_w, v_w) = (
        vec![0.0f32; other_width.num_params()],
        vec![0.0f32; other_width.num_params()],
    );
    let refusals = [
        net.upload(ctx, &other_width, &m_w, &v_w, 1),
        net.upload(ctx, &other_act, &m_b, &v_b, 1),
        net.upload(ctx, &b, &short, &v_b, 1),
        net.upload(ctx, &b, &nan_m, &v_b, 1),
    ];
    for r in refusals {
        assert!(matches!(r, Err(GpuError::Invalid(_))), "{r:?}");
    }
    assert!(matches!(
        DeviceNetwork::new(ctx, &b, &nan_m, &v_b, 0),
        Err(GpuError::Invalid(_))
    ));
    assert_eq!(net.adam_step(), 3);
    let got = download_state(&gpu, &net, &a);
    assert_eq!(bits(&got.0), bits(b.params()));
    let mut into = other_width.clone();
    let (mut m_o, mut v_o) = (m_w.clone(), v_w.clone());
    assert!(matches!(
        net.download(ctx, &mut into, &mut m_o, &mut v_o),
        Err(GpuError::Invalid(_))
    ));
    assert!(into == other_width);
    let mut into = b.clone();
    let mut m_short = short.clone();
    let mut v_full = v_b.clone();
    assert!(matches!(
        net.download(ctx, &mut into, &mut m_short, &mut v_full),
        Err(GpuError::Invalid(_))
    ));
    assert!(matches!(
        net.upload_grads(ctx, &short),
        Err(GpuError::Invalid(_))
    ));
    // Batches: lengths, live count, widths.
    let batch = DeviceBatch::new(&gpu, &net, 10).unwrap();
    let (x, d) = (vec![0.5f32; 10 * 5], vec![1.0f32; 10 * 2]);
    assert!(batch.write(&gpu, &x[..49], 10, &d).is_err());
    assert!(batch.write(&gpu, &x, 10, &d[..19]).is_err());
    assert!(batch.write(&gpu, &x, 11, &d).is_err());
    let other_net = DeviceNetwork::new(ctx, &other_width, &m_w, &v_w, 0).unwrap();
    let wrong = Mlp::new(&[6, 32, 2], HiddenActivation::Relu, Init::KaimingUniform, 3).unwrap();
    let zeros = vec![0.0f32; wrong.num_params()];
    let wrong_net = DeviceNetwork::new(ctx, &wrong, &zeros, &zeros, 0).unwrap();
    batch.write(&gpu, &x, 10, &d).unwrap();
    assert!(gpu.run_forward_backward(&other_net, &batch, true).is_ok());
    // A batch of no rows at all records no kernels but still overwrites the gradient.
    let empty = DeviceBatch::new(&gpu, &net, 0).unwrap();
    empty.write(&gpu, &[], 0, &[]).unwrap();
    net.upload_grads(ctx, &vec![f32::NAN; n]).unwrap();
    gpu.run_forward_backward(&net, &empty, true).unwrap();
    assert_all_zero_bits(
        "0-row parameter gradient",
        &net.download_grads(ctx).unwrap(),
    );
    let (y, dx) = empty.read(&gpu).unwrap();
    assert!(y.is_empty() && dx.is_empty());
    assert!(matches!(
        gpu.run_forward_backward(&wrong_net, &batch, true),
        Err(GpuError::Invalid(_))
    ));
}
