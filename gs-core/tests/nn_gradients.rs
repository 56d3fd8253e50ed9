//! Gradient checks of the `nn` module and the isotropic regulariser against central finite
//! differences of independent f64 reference implementations, plus determinism and error
//! handling of the MLP.
//!
//! Kinks are avoided by construction: every check asserts that no ReLU pre-activation lies
//! within a safe margin of zero, so a finite-difference step never crosses one.

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

// ---------------------------------------------------------------------------------------
// Phi and Psi: input assembly, network and scatter, end to end.

use gs_core::nn::{AppearanceNet, PositionalEncoding, SceneBox, ShadowNet};

fn gamma64(p: &[f64], num_frequencies: usize) -> Vec<f64> {
    let mut out = Vec::new();
    for &pc in p {
        for k in 0..num_frequencies {
            let arg = std::f64::consts::PI * (1u64 << k) as f64 * pc;
            out.push(arg.sin());
            out.push(arg.cos());
        }
    }
    out
}

fn normalised(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

struct PhiCase {
    gaussians: Vec<u32>,
    features: Vec<f32>,
    means: Vec<f32>,
    sun: [f32; 3],
    camera: [f32; 3],
}

fn phi_reference_input(
    case: &PhiCase,
    features: &[f64],
    means: &[f64],
    f_dim: usize,
    l: usize,
) -> Vec<f64> {
    let sun = normalised(case.sun.map(|v| v as f64));
    let mut rows = Vec::new();
    for &g in &case.gaussians {
        let g = g as usize;
        rows.extend_from_slice(&features[g * f_dim..(g + 1) * f_dim]);
        rows.extend(gamma64(&sun, l));
        let view = normalised(std::array::from_fn(|a| {
            case.camera[a] as f64 - means[g * 3 + a]
        }));
        rows.extend(gamma64(&view, l));
    }
    rows
}

#[test]
fn appearance_net_gradients_reach_features_and_means() {
    let (f_dim, l) = (72, 4);
    let net = AppearanceNet::new(f_dim, PositionalEncoding::new(l).unwrap(), 5).unwrap();
    assert_eq!(net.input_width(), 72 + 24 + 24);
    let count = 4;
    let h = 1e-7;
    let margin = 1e-4;
    let mut case = PhiCase {
        // Gaussian 1 is not listed (must get no gradient); Gaussian 2 is listed twice.
        gaussians: vec![2, 0, 3, 2],
        features: vec![0.0; count * f_dim],
        means: values(count * 3, 77).iter().map(|v| 0.8 * v).collect(),
        sun: [0.3, -0.5, 0.8],
        camera: [2.5, 1.0, -3.0],
    };
    // Kink-free by construction: draw each Gaussian's feature until its row keeps every
    // hidden pre-activation at least `margin` away from zero.
    let widths = net.mlp.widths().to_vec();
    let params64 = to_f64(net.mlp.params());
    let mut seed = 100;
    for g in 0..count {
        loop {
            let candidate = values(f_dim, seed);
            seed += 1;
            case.features[g * f_dim..(g + 1) * f_dim].copy_from_slice(&candidate);
            let single = PhiCase {
                gaussians: vec![g as u32],
                features: case.features.clone(),
                means: case.means.clone(),
                sun: case.sun,
                camera: case.camera,
            };
            let x = phi_reference_input(
                &single,
                &to_f64(&case.features),
                &to_f64(&case.means),
                f_dim,
                l,
            );
            if reference_forward(&widths, HiddenActivation::Relu, &params64, &x, 1).1 > margin {
                break;
            }
        }
    }

    let rows = case.gaussians.len();
    let mut input = Vec::new();
    net.assemble_input(
        &case.gaussians,
        &case.features,
        &case.means,
        case.sun,
        case.camera,
        &mut input,
    )
    .unwrap();
    let x_ref = phi_reference_input(
        &case,
        &to_f64(&case.features),
        &to_f64(&case.means),
        f_dim,
        l,
    );
    for (a, b) in input.iter().zip(&x_ref) {
        assert!(
            (*a as f64 - b).abs() < 1e-5,
            "assembled {a} vs reference {b}"
        );
    }
    let fwd = net
        .mlp
        .forward_train(&input, rows, TapeMode::Cache)
        .unwrap();
    let d_out = values(rows * 3, 9);
    let mut d_params = vec![0.0f32; net.mlp.num_params()];
    let mut d_input = vec![0.0f32; input.len()];
    net.mlp
        .backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
        .unwrap();
    let mut d_features = vec![0.0f32; count * f_dim];
    let mut d_means = vec![0.0f32; count * 3];
    net.scatter_input_grad(
        &case.gaussians,
        &case.means,
        case.camera,
        &d_input,
        &mut d_features,
        &mut d_means,
    )
    .unwrap();

    let objective = |features: &[f64], means: &[f64]| {
        let x = phi_reference_input(&case, features, means, f_dim, l);
        dot(
            &reference_forward(&widths, HiddenActivation::Relu, &params64, &x, rows).0,
            &d_out,
        )
    };
    let (f64s, m64s) = (to_f64(&case.features), to_f64(&case.means));
    let scale_f = d_features
        .iter()
        .map(|v| v.abs() as f64)
        .fold(0.0, f64::max);
    for k in 0..f64s.len() {
        let (mut plus, mut minus) = (f64s.clone(), f64s.clone());
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&plus, &m64s) - objective(&minus, &m64s)) / (2.0 * h);
        assert_grad_close("d_features", k, d_features[k], numeric, scale_f);
    }
    let scale_m = d_means.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    for k in 0..m64s.len() {
        let (mut plus, mut minus) = (m64s.clone(), m64s.clone());
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&f64s, &plus) - objective(&f64s, &minus)) / (2.0 * h);
        assert_grad_close("d_means", k, d_means[k], numeric, scale_m);
    }
    assert!(d_features[f_dim..2 * f_dim].iter().all(|v| *v == 0.0));
    assert!(d_means[3..6].iter().all(|v| *v == 0.0));
    assert!(
        d_means.iter().any(|v| v.abs() > 1e-6),
        "view direction must carry gradient"
    );
}

#[test]
fn appearance_net_rejects_bad_inputs() {
    let net = AppearanceNet::new(4, PositionalEncoding::default(), 1).unwrap();
    let features = vec![0.1f32; 8];
    let means = vec![0.0f32; 6];
    let mut input = Vec::new();
    let ok = net.assemble_input(
        &[0, 1],
        &features,
        &means,
        [1.0, 0.0, 0.0],
        [0.0, 0.0, 5.0],
        &mut input,
    );
    assert!(ok.is_ok());
    assert_eq!(input.len(), 2 * net.input_width());
    assert_eq!(
        net.assemble_input(
            &[2],
            &features,
            &means,
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            &mut input
        ),
        Err(NnError::Index { index: 2, len: 2 })
    );
    assert!(matches!(
        net.assemble_input(
            &[0],
            &features[..7],
            &means,
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            &mut input
        ),
        Err(NnError::Shape { .. })
    ));
    let mut bad = features.clone();
    bad[5] = f32::NAN;
    assert_eq!(
        net.assemble_input(
            &[0, 1],
            &bad,
            &means,
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            &mut input
        ),
        Err(NnError::NonFinite {
            what: "appearance feature",
            index: 1
        })
    );
    // A NaN in a Gaussian that is not listed is not this call's business.
    assert!(net
        .assemble_input(
            &[0],
            &bad,
            &means,
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            &mut input
        )
        .is_ok());
    assert!(matches!(
        net.assemble_input(
            &[0],
            &features,
            &means,
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 5.0],
            &mut input
        ),
        Err(NnError::Degenerate { .. })
    ));
    assert!(matches!(
        net.assemble_input(
            &[0],
            &features,
            &means,
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            &mut input
        ),
        Err(NnError::Degenerate { index: 0, .. })
    ));
    let mut d_features = vec![0.0f32; 8];
    let mut d_means = vec![0.0f32; 6];
    let mut d_input = vec![0.0f32; net.input_width()];
    d_input[0] = f32::NAN;
    assert!(matches!(
        net.scatter_input_grad(
            &[0],
            &means,
            [0.0, 0.0, 5.0],
            &d_input,
            &mut d_features,
            &mut d_means
        ),
        Err(NnError::NonFinite { .. })
    ));
    assert!(d_features.iter().all(|v| *v == 0.0));
    let wrong = AppearanceNet::from_mlp(
        Mlp::new(&[5, 3], HiddenActivation::Relu, Init::KaimingUniform, 0).unwrap(),
        4,
        PositionalEncoding::default(),
    );
    assert!(matches!(wrong, Err(NnError::Config(_))));
}

struct PsiCase {
    gaussians: Vec<u32>,
    visibility: Vec<f32>,
    latents: Vec<f32>,
    means: Vec<f32>,
    sun: [f32; 3],
    box_min: [f32; 3],
    box_max: [f32; 3],
}

fn psi_reference_input(
    case: &PsiCase,
    latents: &[f64],
    means: &[f64],
    latent_dim: usize,
    l: usize,
) -> Vec<f64> {
    let sun = normalised(case.sun.map(|v| v as f64));
    let mut rows = Vec::new();
    for &g in &case.gaussians {
        let g = g as usize;
        rows.push(case.visibility[g] as f64);
        rows.extend(gamma64(&sun, l));
        let p: [f64; 3] = std::array::from_fn(|a| {
            (means[g * 3 + a] - case.box_min[a] as f64)
                / (case.box_max[a] as f64 - case.box_min[a] as f64)
                - 0.5
        });
        rows.extend(gamma64(&p, l));
        rows.extend_from_slice(&latents[g * latent_dim..(g + 1) * latent_dim]);
    }
    rows
}

#[test]
fn shadow_net_gradients_reach_latents_and_means_but_not_visibility() {
    let (latent_dim, l) = (6, 4);
    let net = ShadowNet::new(latent_dim, PositionalEncoding::new(l).unwrap(), 8).unwrap();
    assert_eq!(net.input_width(), 1 + 24 + 24 + 6);
    let count = 5;
    let h = 1e-7;
    let margin = 1e-4;
    let mut case = PsiCase {
        gaussians: vec![4, 1, 0, 1, 3],
        visibility: values(count, 21).iter().map(|v| 0.5 + 0.5 * v).collect(),
        latents: vec![1.0; count * latent_dim],
        means: values(count * 3, 22).iter().map(|v| 1.5 * v).collect(),
        sun: [-0.2, 0.9, 0.4],
        box_min: [-2.0, -1.5, -1.8],
        box_max: [2.0, 1.7, 1.6],
    };
    let widths = net.mlp.widths().to_vec();
    let params64 = to_f64(net.mlp.params());
    let mut seed = 300;
    for g in 0..count {
        loop {
            let jitter = values(latent_dim, seed);
            seed += 1;
            for (dst, j) in case.latents[g * latent_dim..(g + 1) * latent_dim]
                .iter_mut()
                .zip(&jitter)
            {
                *dst = 1.0 + 0.3 * j;
            }
            let single = PsiCase {
                gaussians: vec![g as u32],
                ..case_clone(&case)
            };
            let x = psi_reference_input(
                &single,
                &to_f64(&case.latents),
                &to_f64(&case.means),
                latent_dim,
                l,
            );
            if reference_forward(&widths, HiddenActivation::LeakyRelu, &params64, &x, 1).1 > margin
            {
                break;
            }
        }
    }
    let scene_box = SceneBox::new(case.box_min, case.box_max).unwrap();
    let rows = case.gaussians.len();
    let mut input = Vec::new();
    net.assemble_input(
        &case.gaussians,
        &case.visibility,
        &case.latents,
        &case.means,
        case.sun,
        &scene_box,
        &mut input,
    )
    .unwrap();
    let x_ref = psi_reference_input(
        &case,
        &to_f64(&case.latents),
        &to_f64(&case.means),
        latent_dim,
        l,
    );
    for (a, b) in input.iter().zip(&x_ref) {
        assert!(
            (*a as f64 - b).abs() < 1e-5,
            "assembled {a} vs reference {b}"
        );
    }
    let fwd = net
        .mlp
        .forward_train(&input, rows, TapeMode::Recompute)
        .unwrap();
    let d_out = values(rows, 31);
    let mut d_params = vec![0.0f32; net.mlp.num_params()];
    let mut d_input = vec![0.0f32; input.len()];
    net.mlp
        .backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
        .unwrap();
    let mut d_latents = vec![0.0f32; count * latent_dim];
    let mut d_means = vec![0.0f32; count * 3];
    net.scatter_input_grad(
        &case.gaussians,
        &case.means,
        &scene_box,
        &d_input,
        &mut d_latents,
        &mut d_means,
    )
    .unwrap();

    let objective = |latents: &[f64], means: &[f64]| {
        let x = psi_reference_input(&case, latents, means, latent_dim, l);
        dot(
            &reference_forward(&widths, HiddenActivation::LeakyRelu, &params64, &x, rows).0,
            &d_out,
        )
    };
    let (l64, m64) = (to_f64(&case.latents), to_f64(&case.means));
    let scale_l = d_latents.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    for k in 0..l64.len() {
        let (mut plus, mut minus) = (l64.clone(), l64.clone());
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&plus, &m64) - objective(&minus, &m64)) / (2.0 * h);
        assert_grad_close("d_latents", k, d_latents[k], numeric, scale_l);
    }
    let scale_m = d_means.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    for k in 0..m64.len() {
        let (mut plus, mut minus) = (m64.clone(), m64.clone());
        plus[k] += h;
        minus[k] -= h;
        let numeric = (objective(&l64, &plus) - objective(&l64, &minus)) / (2.0 * h);
        assert_grad_close("d_means", k, d_means[k], numeric, scale_m);
    }
    // Gaussian 2 is not listed.
    assert!(d_latents[2 * latent_dim..3 * latent_dim]
        .iter()
        .all(|v| *v == 0.0));
    assert!(d_means[6..9].iter().all(|v| *v == 0.0));
    // The visibility column carries an input gradient, but scatter has nowhere to send it:
    // changing d_input[.., 0] must not change anything scattered.
    let mut d_input_v = d_input.clone();
    for row in d_input_v.chunks_exact_mut(net.input_width()) {
        row[0] += 10.0;
    }
    let mut d_latents_v = vec![0.0f32; count * latent_dim];
    let mut d_means_v = vec![0.0f32; count * 3];
    net.scatter_input_grad(
        &case.gaussians,
        &case.means,
        &scene_box,
        &d_input_v,
        &mut d_latents_v,
        &mut d_means_v,
    )
    .unwrap();
    assert_eq!(d_latents, d_latents_v);
    assert_eq!(d_means, d_means_v);
}

fn case_clone(case: &PsiCase) -> PsiCase {
    PsiCase {
        gaussians: case.gaussians.clone(),
        visibility: case.visibility.clone(),
        latents: case.latents.clone(),
        means: case.means.clone(),
        sun: case.sun,
        box_min: case.box_min,
        box_max: case.box_max,
    }
}

#[test]
fn shadow_net_rejects_bad_inputs() {
    assert!(SceneBox::new([0.0; 3], [1.0, 0.0, 1.0]).is_err());
    assert!(SceneBox::new([0.0; 3], [1.0, f32::NAN, 1.0]).is_err());
    let scene_box = SceneBox::new([-1.0; 3], [1.0; 3]).unwrap();
    let net = ShadowNet::new(6, PositionalEncoding::default(), 1).unwrap();
    let latents = vec![1.0f32; 12];
    let means = vec![0.0f32; 6];
    let mut input = Vec::new();
    assert!(net
        .assemble_input(
            &[1, 0],
            &[1.0, 0.5],
            &latents,
            &means,
            [0.0, 0.0, 1.0],
            &scene_box,
            &mut input
        )
        .is_ok());
    assert!(matches!(
        net.assemble_input(
            &[0],
            &[1.0],
            &latents,
            &means,
            [0.0, 0.0, 1.0],
            &scene_box,
            &mut input
        ),
        Err(NnError::Shape { .. })
    ));
    assert_eq!(
        net.assemble_input(
            &[1],
            &[1.0, f32::NAN],
            &latents,
            &means,
            [0.0, 0.0, 1.0],
            &scene_box,
            &mut input
        ),
        Err(NnError::NonFinite {
            what: "Sun visibility",
            index: 1
        })
    );
    assert!(matches!(
        net.assemble_input(
            &[5],
            &[1.0, 1.0],
            &latents,
            &means,
            [0.0, 0.0, 1.0],
            &scene_box,
            &mut input
        ),
        Err(NnError::Index { index: 5, len: 2 })
    ));
}

// ---------------------------------------------------------------------------------------
// Isotropic scale loss.

use gs_core::regularizer::{IsoReduction, IsotropicLoss};

/// f64 reference of Eq. 6 with the given per-Gaussian factor.
fn iso_reference(log_scales: &[f64], factor: f64) -> f64 {
    log_scales
        .chunks_exact(3)
        .map(|u| {
            let s: Vec<f64> = u.iter().map(|v| v.exp()).collect();
            let mean = s.iter().sum::<f64>() / 3.0;
            s.iter().map(|v| (v - mean).abs()).sum::<f64>()
        })
        .sum::<f64>()
        * factor
}

#[test]
fn isotropic_loss_gradient_matches_finite_differences() {
    let n = 40;
    // Kinks (a scale equal to its Gaussian's mean scale) are avoided by construction: the
    // three log-scales sit 0.3 apart plus a jitter of at most 0.1; the assert confirms it.
    let mut log_scales = Vec::with_capacity(3 * n);
    let base = values(n, 55);
    let spread = values(3 * n, 56);
    for i in 0..n {
        for a in 0..3 {
            log_scales.push(-3.0 + base[i] + 0.3 * a as f32 + 0.1 * spread[3 * i + a]);
        }
    }
    let log64 = to_f64(&log_scales);
    for u in log64.chunks_exact(3) {
        let s: Vec<f64> = u.iter().map(|v| v.exp()).collect();
        let mean = s.iter().sum::<f64>() / 3.0;
        assert!(
            s.iter().all(|v| (v - mean).abs() > 1e-4),
            "kink too close: {s:?}"
        );
    }
    for (reduction, lambda, factor) in [
        (IsoReduction::Sum, 0.7f32, 0.7f64),
        (IsoReduction::MeanOverEntries, 10.0, 10.0 / (3 * n) as f64),
    ] {
        let loss = IsotropicLoss::new(lambda, reduction).unwrap();
        let mut grad = vec![0.0f32; 3 * n];
        let value = loss.value_and_grad(&log_scales, &mut grad).unwrap();
        let reference = iso_reference(&log64, factor);
        assert!(
            (value as f64 - reference).abs() <= 1e-5 * reference,
            "{value} vs {reference}"
        );
        let h = 1e-6;
        let scale = grad.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
        for k in 0..log64.len() {
            let (mut plus, mut minus) = (log64.clone(), log64.clone());
            plus[k] += h;
            minus[k] -= h;
            let numeric =
                (iso_reference(&plus, factor) - iso_reference(&minus, factor)) / (2.0 * h);
            assert_grad_close("d_log_scales", k, grad[k], numeric, scale);
        }
    }
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
