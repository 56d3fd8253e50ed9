//! Gradient checks of the `nn` module and the isotropic regulariser against central finite
//! differences of independent f64 reference implementations, plus determinism and error
//! handling of the MLP.
//!
//! Kinks are avoided by construction: every check asserts that no ReLU pre-activation lies
//! within a safe margin of zero, so a finite-difference step never crosses one.
//!
//! Files: this one (the MLP, and the helpers the others share), `nn_gradients/networks.rs`
//! (Phi and Psi end to end: input assembly, network, scatter), `nn_gradients/isotropic.rs`
//! (the isotropic scale loss).

use gs_core::nn::{HiddenActivation, Init, Mlp, NnError, TapeMode};

const LEAKY: f64 = 0.01;

/// Deterministic pseudo-random values in [-1, 1).
fn values(len: usize, seed: u64) -> Vec<f32> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..len)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

/// f64 reference forward. Returns the outputs and the smallest |pre-activation| of any
/// hidden unit (the distance to the nearest kink).
fn reference_forward(
    widths: &[usize],
    act: HiddenActivation,
    params: &[f64],
    input: &[f64],
    rows: usize,
) -> (Vec<f64>, f64) {
    let layers = widths.len() - 1;
    let mut out = Vec::with_capacity(rows * widths[layers]);
    let mut min_abs_z = f64::INFINITY;
    for r in 0..rows {
        let mut x: Vec<f64> = input[r * widths[0]..(r + 1) * widths[0]].to_vec();
        let mut at = 0;
        for l in 0..layers {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            let w = &params[at..at + n_in * n_out];
            let b = &params[at + n_in * n_out..at + n_in * n_out + n_out];
            at += n_in * n_out + n_out;
            let mut z: Vec<f64> = b.to_vec();
            for (i, xi) in x.iter().enumerate() {
                for j in 0..n_out {
                    z[j] += xi * w[i * n_out + j];
                }
            }
            if l + 1 == layers {
                x = z.iter().map(|v| 1.0 / (1.0 + (-v).exp())).collect();
            } else {
                for v in &z {
                    min_abs_z = min_abs_z.min(v.abs());
                }
                x = z
                    .iter()
                    .map(|&v| match act {
                        HiddenActivation::Relu => v.max(0.0),
                        HiddenActivation::LeakyRelu => {
                            if v > 0.0 {
                                v
                            } else {
                                LEAKY * v
                            }
                        }
                    })
                    .collect();
            }
        }
        out.extend(x);
    }
    (out, min_abs_z)
}

/// `rows` input rows whose hidden pre-activations all stay at least `margin` from zero:
/// candidate rows are drawn in a fixed sequence and those near a kink are skipped.
fn kink_free_input(
    widths: &[usize],
    act: HiddenActivation,
    params: &[f32],
    rows: usize,
    margin: f64,
) -> Vec<f32> {
    let params64 = to_f64(params);
    let mut kept = Vec::with_capacity(rows * widths[0]);
    let mut seed = 3;
    while kept.len() < rows * widths[0] {
        let candidate = values(widths[0], seed);
        seed += 1;
        let (_, min_abs_z) = reference_forward(widths, act, &params64, &to_f64(&candidate), 1);
        if min_abs_z > margin {
            kept.extend(candidate);
        }
    }
    kept
}

fn dot(a: &[f64], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * *y as f64).sum()
}

fn to_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

fn assert_grad_close(what: &str, index: usize, analytic: f32, numeric: f64, scale: f64) {
    let err = (analytic as f64 - numeric).abs();
    assert!(
        err <= 2e-3 * numeric.abs() + 1e-4 * scale,
        "{what}[{index}]: analytic {analytic} vs numeric {numeric} (scale {scale})"
    );
}

/// Checks d_params (every `param_stride`-th) and d_input (every `input_stride`-th) of the
/// objective `sum(d_out * y)` against central differences of the f64 reference.
fn check_mlp_gradients(
    widths: &[usize],
    act: HiddenActivation,
    rows: usize,
    mode: TapeMode,
    param_stride: usize,
    input_stride: usize,
) {
    let mlp = Mlp::new(widths, act, Init::KaimingUniform, 11).unwrap();
    let h = 1e-6;
    let input = kink_free_input(widths, act, mlp.params(), rows, 1e3 * h);
    let d_out = values(rows * widths[widths.len() - 1], 5);
    let fwd = mlp.forward_train(&input, rows, mode).unwrap();

    let params64 = to_f64(mlp.params());
    let input64 = to_f64(&input);
    let (y_ref, min_abs_z) = reference_forward(widths, act, &params64, &input64, rows);
    // Inputs and weights are O(1), so a step of h moves a pre-activation by at most ~h * width.
    assert!(
        min_abs_z > 1e3 * h,
        "test setup too close to a kink: {min_abs_z}"
    );
    for (a, b) in fwd.output.iter().zip(&y_ref) {
        assert!((*a as f64 - b).abs() < 1e-5, "forward {a} vs reference {b}");
    }

    let mut d_params = vec![0.0f32; mlp.num_params()];
    let mut d_input = vec![0.0f32; input.len()];
    mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
        .unwrap();
    let scale = d_params.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);

    let objective =
        |p: &[f64], x: &[f64]| dot(&reference_forward(widths, act, p, x, rows).0, &d_out);
    for k in (0..params64.len()).step_by(param_stride) {
        let mut plus = params64.clone();
        let mut minus = params64.clone();
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&plus, &input64) - objective(&minus, &input64)) / (2.0 * h);
        assert_grad_close("d_params", k, d_params[k], numeric, scale);
    }
    let scale_in = d_input.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    for k in (0..input64.len()).step_by(input_stride) {
        let mut plus = input64.clone();
        let mut minus = input64.clone();
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&params64, &plus) - objective(&params64, &minus)) / (2.0 * h);
        assert_grad_close("d_input", k, d_input[k], numeric, scale_in);
    }
}

#[test]
fn mlp_relu_gradients_match_finite_differences() {
    check_mlp_gradients(
        &[7, 16, 12, 3],
        HiddenActivation::Relu,
        9,
        TapeMode::Cache,
        1,
        1,
    );
}

#[test]
fn mlp_leaky_relu_gradients_match_finite_differences() {
    check_mlp_gradients(
        &[6, 10, 10, 10, 1],
        HiddenActivation::LeakyRelu,
        8,
        TapeMode::Recompute,
        1,
        1,
    );
}

#[test]
fn mlp_gradients_over_several_blocks_match_finite_differences() {
    // More rows than two blocks, so the block split and the ordered reduction are covered.
    let rows = 2 * gs_core::nn::mlp::BLOCK_ROWS + 37;
    check_mlp_gradients(
        &[4, 6, 5, 2],
        HiddenActivation::LeakyRelu,
        rows,
        TapeMode::Cache,
        3,
        97,
    );
}

#[test]
fn cache_and_recompute_give_identical_gradients() {
    let widths = [9, 32, 32, 32, 2];
    let rows = 3 * gs_core::nn::mlp::BLOCK_ROWS + 5;
    let mlp = Mlp::new(&widths, HiddenActivation::Relu, Init::TorchLinearDefault, 2).unwrap();
    let input = values(rows * widths[0], 8);
    let d_out = values(rows * 2, 9);
    let run = |mode| {
        let fwd = mlp.forward_train(&input, rows, mode).unwrap();
        let mut d_params = vec![0.0f32; mlp.num_params()];
        let mut d_input = vec![0.0f32; input.len()];
        mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
            .unwrap();
        let tape_len = fwd.tape_len();
        (fwd.output, d_params, d_input, tape_len)
    };
    let cached = run(TapeMode::Cache);
    let recomputed = run(TapeMode::Recompute);
    assert_eq!(cached.0, recomputed.0);
    assert_eq!(cached.1, recomputed.1);
    assert_eq!(cached.2, recomputed.2);
    assert_eq!(cached.3, rows * 96);
    assert_eq!(recomputed.3, 0);
    // Inference forward equals the training forward bit for bit.
    assert_eq!(mlp.forward(&input, rows).unwrap(), cached.0);
}

#[test]
fn results_are_bit_identical_on_one_and_two_threads() {
    let widths = [120, 64, 64, 3];
    let rows = 2 * gs_core::nn::mlp::BLOCK_ROWS + 999;
    let mlp = Mlp::new(&widths, HiddenActivation::Relu, Init::TorchLinearDefault, 4).unwrap();
    let input = values(rows * widths[0], 10);
    let d_out = values(rows * 3, 12);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let fwd = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
            let mut d_params = vec![0.0f32; mlp.num_params()];
            let mut d_input = vec![0.0f32; input.len()];
            mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
                .unwrap();
            (fwd.output, d_params, d_input)
        })
    };
    let one = run(1);
    let two = run(2);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&one.0), bits(&two.0));
    assert_eq!(bits(&one.1), bits(&two.1));
    assert_eq!(bits(&one.2), bits(&two.2));
    // And the same thread count twice.
    let again = run(2);
    assert_eq!(bits(&two.1), bits(&again.1));
}

#[test]
fn param_gradients_accumulate() {
    let mlp = Mlp::new(&[3, 4, 2], HiddenActivation::Relu, Init::KaimingUniform, 1).unwrap();
    let input = values(6, 1);
    let d_out = values(4, 2);
    let fwd = mlp.forward_train(&input, 2, TapeMode::Cache).unwrap();
    let mut once = vec![0.0f32; mlp.num_params()];
    mlp.backward(&input, &fwd, &d_out, &mut once, None).unwrap();
    let mut twice = once.clone();
    mlp.backward(&input, &fwd, &d_out, &mut twice, None)
        .unwrap();
    for (a, b) in once.iter().zip(&twice) {
        assert_eq!(2.0 * a, *b);
    }
    assert!(once.iter().any(|v| *v != 0.0));
}

#[test]
fn mlp_bad_shapes_and_non_finite_values_are_errors() {
    assert!(matches!(
        Mlp::new(&[3], HiddenActivation::Relu, Init::KaimingUniform, 0),
        Err(NnError::Config(_))
    ));
    assert!(matches!(
        Mlp::new(&[3, 0, 1], HiddenActivation::Relu, Init::KaimingUniform, 0),
        Err(NnError::Config(_))
    ));
    let mut mlp = Mlp::new(&[3, 4, 2], HiddenActivation::Relu, Init::KaimingUniform, 0).unwrap();
    assert!(matches!(
        mlp.forward(&[0.0; 5], 2),
        Err(NnError::Shape { .. })
    ));
    assert_eq!(
        mlp.forward(&[0.0, 1.0, f32::NAN, 0.0, 0.0, 0.0], 2),
        Err(NnError::NonFinite {
            what: "MLP input",
            index: 2
        })
    );
    let input = [0.5f32; 6];
    let fwd = mlp.forward_train(&input, 2, TapeMode::Cache).unwrap();
    let mut d_params = vec![0.0f32; mlp.num_params()];
    assert!(matches!(
        mlp.backward(&input, &fwd, &[0.0; 3], &mut d_params, None),
        Err(NnError::Shape { .. })
    ));
    assert!(matches!(
        mlp.backward(
            &input,
            &fwd,
            &[0.0, f32::INFINITY, 0.0, 0.0],
            &mut d_params,
            None
        ),
        Err(NnError::NonFinite { .. })
    ));
    assert!(matches!(
        mlp.backward(&input, &fwd, &[0.0; 4], &mut d_params[1..], None),
        Err(NnError::Shape { .. })
    ));
    let mut wrong_input_grad = vec![0.0f32; 5];
    assert!(matches!(
        mlp.backward(
            &input,
            &fwd,
            &[0.0; 4],
            &mut d_params,
            Some(&mut wrong_input_grad)
        ),
        Err(NnError::Shape { .. })
    ));
    assert!(
        d_params.iter().all(|v| *v == 0.0),
        "failed calls must not write"
    );
    mlp.params_mut()[3] = f32::NAN;
    assert!(matches!(
        mlp.forward(&input, 2),
        Err(NnError::NonFinite {
            what: "MLP parameters",
            ..
        })
    ));
    assert!(matches!(
        Mlp::from_params(&[3, 4, 2], HiddenActivation::Relu, vec![0.0; 7]),
        Err(NnError::Shape { .. })
    ));
}

#[test]
fn initialisation_is_seeded_and_follows_the_documented_layout() {
    let widths = [10, 20, 3];
    let a = Mlp::new(
        &widths,
        HiddenActivation::Relu,
        Init::TorchLinearDefault,
        42,
    )
    .unwrap();
    let b = Mlp::new(
        &widths,
        HiddenActivation::Relu,
        Init::TorchLinearDefault,
        42,
    )
    .unwrap();
    let c = Mlp::new(
        &widths,
        HiddenActivation::Relu,
        Init::TorchLinearDefault,
        43,
    )
    .unwrap();
    assert_eq!(a, b);
    assert_ne!(a.params(), c.params());
    assert_eq!(a.num_params(), 10 * 20 + 20 + 20 * 3 + 3);
    assert_eq!(a.weight_range(0), 0..200);
    assert_eq!(a.bias_range(0), 200..220);
    assert_eq!(a.weight_range(1), 220..280);
    assert_eq!(a.bias_range(1), 280..283);
    let bound0 = 1.0 / 10f32.sqrt();
    assert!(a.params()[0..220].iter().all(|v| v.abs() <= bound0));
    let k = Mlp::new(&widths, HiddenActivation::Relu, Init::KaimingUniform, 42).unwrap();
    assert!(k.params()[k.bias_range(0)].iter().all(|v| *v == 0.0));
    let kaiming_bound = 2f32.sqrt() * (3.0f32 / 10.0).sqrt();
    let w0 = &k.params()[k.weight_range(0)];
    assert!(w0.iter().all(|v| v.abs() <= kaiming_bound));
    assert!(
        w0.iter().any(|v| v.abs() > bound0),
        "Kaiming spreads wider than torch default"
    );
}

#[test]
fn zero_rows_is_a_valid_empty_batch() {
    let mlp = Mlp::new(&[3, 4, 2], HiddenActivation::Relu, Init::KaimingUniform, 1).unwrap();
    for mode in [TapeMode::Cache, TapeMode::Recompute] {
        let fwd = mlp.forward_train(&[], 0, mode).unwrap();
        assert!(fwd.output.is_empty());
        let mut d_params = vec![0.5f32; mlp.num_params()];
        let mut d_input: Vec<f32> = Vec::new();
        mlp.backward(&[], &fwd, &[], &mut d_params, Some(&mut d_input))
            .unwrap();
        assert!(d_params.iter().all(|v| *v == 0.5));
    }
}

#[test]
fn forward_train_into_reuses_memory_with_identical_results() {
    let widths = [10, 24, 24, 2];
    let mlp = Mlp::new(
        &widths,
        HiddenActivation::LeakyRelu,
        Init::TorchLinearDefault,
        6,
    )
    .unwrap();
    let mut reused = gs_core::nn::MlpForward::default();
    // A large batch, then a smaller one, then Recompute: stale blocks must not leak through.
    for (rows, mode) in [
        (2 * gs_core::nn::mlp::BLOCK_ROWS + 3, TapeMode::Cache),
        (700, TapeMode::Cache),
        (900, TapeMode::Recompute),
    ] {
        let input = values(rows * widths[0], rows as u64);
        let d_out = values(rows * 2, 1 + rows as u64);
        mlp.forward_train_into(&input, rows, mode, &mut reused)
            .unwrap();
        let fresh = mlp.forward_train(&input, rows, mode).unwrap();
        assert_eq!(reused.rows(), rows);
        assert_eq!(reused.output, fresh.output);
        assert_eq!(reused.tape_len(), fresh.tape_len());
        let grads = |fwd: &gs_core::nn::MlpForward| {
            let mut d_params = vec![0.0f32; mlp.num_params()];
            let mut d_input = vec![0.0f32; input.len()];
            mlp.backward(&input, fwd, &d_out, &mut d_params, Some(&mut d_input))
                .unwrap();
            (d_params, d_input)
        };
        assert_eq!(grads(&reused), grads(&fresh));
    }
    // A failed forward leaves an empty result that backward rejects.
    let bad = vec![f32::NAN; 10];
    assert!(mlp
        .forward_train_into(&bad, 1, TapeMode::Cache, &mut reused)
        .is_err());
    assert_eq!(reused.rows(), 0);
    assert!(reused.output.is_empty());
    let mut d_params = vec![0.0f32; mlp.num_params()];
    assert!(mlp
        .backward(&[0.0; 10], &reused, &[0.0; 2], &mut d_params, None)
        .is_err());
}

#[path = "nn_gradients/isotropic.rs"]
mod isotropic;
#[path = "nn_gradients/networks.rs"]
mod networks;
