//! Psi's training path with the Sun's encoding folded into the first layer
//! (`ShadowNet::forward_train_into` / `ShadowNet::backward`): its outputs and every
//! gradient (parameters in the full layout, latents, means) against an f64 reference of the
//! full network on the full input row `[V | gamma(sun) | gamma(p) | l]` (values and central
//! differences), against the folded network run by `Mlp` (the same bits), between tape
//! modes and thread counts (the same bits), and its errors.

use gs_core::nn::shadow_net::{ShadowBatch, ShadowPass};
use gs_core::nn::{
    MatmulPrecision, MlpForward, NnError, PositionalEncoding, SceneBox, ShadowNet, TapeMode,
};
use gs_core::rng::SplitMix64;

const LEAKY: f64 = 0.01;

struct Case {
    gaussians: Vec<u32>,
    visibility: Vec<f32>,
    latents: Vec<f32>,
    means: Vec<f32>,
    sun: [f32; 3],
    scene_box: SceneBox,
}

impl Case {
    fn random(count: usize, rows: usize, seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed);
        Self {
            // Any order, with repeats.
            gaussians: (0..rows).map(|_| rng.below(count) as u32).collect(),
            visibility: (0..count).map(|_| rng.next_f32()).collect(),
            latents: (0..count * 6).map(|_| 1.0 + 0.5 * rng.normal()).collect(),
            // Some means outside the box (not clamped).
            means: (0..count * 3).map(|_| rng.uniform(-1.8, 1.8)).collect(),
            sun: [0.3, -0.6, 0.7],
            scene_box: SceneBox::new([-1.5, -0.8, -0.7], [1.4, 0.9, 0.6]).unwrap(),
        }
    }

    fn batch(&self) -> ShadowBatch<'_> {
        ShadowBatch {
            gaussians: &self.gaussians,
            visibility: &self.visibility,
            latents: &self.latents,
            means: &self.means,
            sun_dir: self.sun,
            scene_box: &self.scene_box,
        }
    }
}

fn gamma64(p: &[f64], l: usize) -> Vec<f64> {
    let mut out = Vec::new();
    for &pc in p {
        for k in 0..l {
            let arg = std::f64::consts::PI * (1u64 << k) as f64 * pc;
            out.push(arg.sin());
            out.push(arg.cos());
        }
    }
    out
}

/// The full input rows in f64 (the module's definition of Psi's input).
fn full_rows64(case: &Case, latents: &[f64], means: &[f64], l: usize) -> Vec<f64> {
    let s = case.sun.map(|v| v as f64);
    let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
    let sun = [s[0] / n, s[1] / n, s[2] / n];
    let (lo, hi) = (case.scene_box.min_m(), case.scene_box.max_m());
    let mut rows = Vec::new();
    for &g in &case.gaussians {
        let g = g as usize;
        rows.push(case.visibility[g] as f64);
        rows.extend(gamma64(&sun, l));
        let p: [f64; 3] = std::array::from_fn(|a| {
            (means[g * 3 + a] - lo[a] as f64) / (hi[a] as f64 - lo[a] as f64) - 0.5
        });
        rows.extend(gamma64(&p, l));
        rows.extend_from_slice(&latents[g * 6..g * 6 + 6]);
    }
    rows
}

/// f64 forward of a LeakyReLU/sigmoid MLP in the module's layout; also the smallest
/// |pre-activation| (distance to a kink).
fn forward64(widths: &[usize], params: &[f64], input: &[f64]) -> (Vec<f64>, f64) {
    let layers = widths.len() - 1;
    let rows = input.len() / widths[0];
    let mut out = Vec::new();
    let mut nearest_kink = f64::INFINITY;
    for r in 0..rows {
        let mut x = input[r * widths[0]..(r + 1) * widths[0]].to_vec();
        let mut at = 0;
        for l in 0..layers {
            let (n_in, n_out) = (widths[l], widths[l + 1]);
            let w = &params[at..at + n_in * n_out];
            let mut z = params[at + n_in * n_out..at + n_in * n_out + n_out].to_vec();
            at += n_in * n_out + n_out;
            for (i, xi) in x.iter().enumerate() {
                for j in 0..n_out {
                    z[j] += xi * w[i * n_out + j];
                }
            }
            if l + 1 == layers {
                x = z.iter().map(|v| 1.0 / (1.0 + (-v).exp())).collect();
            } else {
                nearest_kink = z.iter().fold(nearest_kink, |m, v| m.min(v.abs()));
                x = z
                    .iter()
                    .map(|&v| if v > 0.0 { v } else { LEAKY * v })
                    .collect();
            }
        }
        out.extend(x);
    }
    (out, nearest_kink)
}

fn to_f64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x as f64).collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

struct Grads {
    params: Vec<f32>,
    latents: Vec<f32>,
    means: Vec<f32>,
}

fn run(net: &ShadowNet, case: &Case, mode: TapeMode, d_out: &[f32]) -> (Vec<f32>, Grads) {
    let mut pass = ShadowPass::default();
    net.forward_train_into(&case.batch(), mode, &mut pass)
        .unwrap();
    let count = case.visibility.len();
    let mut g = Grads {
        params: vec![0.0; net.mlp.num_params()],
        latents: vec![0.0; count * 6],
        means: vec![0.0; count * 3],
    };
    net.backward(
        &case.batch(),
        &pass,
        d_out,
        &mut g.params,
        &mut g.latents,
        &mut g.means,
    )
    .unwrap();
    (pass.output, g)
}

#[test]
fn folded_forward_matches_the_full_network_in_f64() {
    let net = ShadowNet::new(6, PositionalEncoding::default(), 11).unwrap();
    let case = Case::random(3000, 2 * 2048 + 301, 1);
    let (y, _) = run(
        &net,
        &case,
        TapeMode::Cache,
        &vec![0.0; case.gaussians.len()],
    );
    let x64 = full_rows64(&case, &to_f64(&case.latents), &to_f64(&case.means), 4);
    let (y64, _) = forward64(net.mlp.widths(), &to_f64(net.mlp.params()), &x64);
    let worst = y
        .iter()
        .zip(&y64)
        .map(|(a, b)| (*a as f64 - b).abs())
        .fold(0.0, f64::max);
    // f32 sums of ~30-term dot products through four layers: measured 6e-8 on outputs in
    // (0, 1). A Sun column left out of the fold or a wrong bias gives 1e-2 or more.
    eprintln!("folded forward vs f64: {worst:.2e}");
    assert!(worst < 5e-7, "{worst:e}");
    // And the old full-row path agrees to the same level.
    let mut input = Vec::new();
    net.assemble_input(
        &case.gaussians,
        &case.visibility,
        &case.latents,
        &case.means,
        case.sun,
        &case.scene_box,
        &mut input,
    )
    .unwrap();
    let full = net.mlp.forward(&input, case.gaussians.len()).unwrap();
    let worst_full = y
        .iter()
        .zip(&full)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst_full < 5e-7, "{worst_full:e}");
}

#[test]
fn gradients_match_central_differences_of_the_full_network() {
    let net = ShadowNet::new(6, PositionalEncoding::default(), 12).unwrap();
    let mut case = Case::random(4, 5, 2);
    case.gaussians = vec![3, 1, 0, 1, 2];
    let rows = case.gaussians.len();
    let d_out: Vec<f32> = (0..rows).map(|i| 0.5 - 0.3 * i as f32).collect();
    let (_, g) = run(&net, &case, TapeMode::Recompute, &d_out);
    let widths = net.mlp.widths().to_vec();
    let (p64, l64, m64) = (
        to_f64(net.mlp.params()),
        to_f64(&case.latents),
        to_f64(&case.means),
    );
    let objective = |params: &[f64], latents: &[f64], means: &[f64]| -> (f64, f64) {
        let x = full_rows64(&case, latents, means, 4);
        let (y, kink) = forward64(&widths, params, &x);
        (y.iter().zip(&d_out).map(|(a, b)| a * *b as f64).sum(), kink)
    };
    let (_, kink) = objective(&p64, &l64, &m64);
    assert!(
        kink > 1e-4,
        "a hidden unit sits on a kink ({kink:e}); pick another seed"
    );
    let h = 1e-6;
    let check = |what: &str, analytic: &[f32], base: &[f64], eval: &dyn Fn(&[f64]) -> f64| {
        let scale = analytic.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
        assert!(scale > 0.0, "{what}: all zero");
        for k in 0..base.len() {
            let (mut plus, mut minus) = (base.to_vec(), base.to_vec());
            plus[k] += h;
            minus[k] -= h;
            let numeric = (eval(&plus) - eval(&minus)) / (2.0 * h);
            let err = (analytic[k] as f64 - numeric).abs();
            assert!(
                err <= 1e-3 * numeric.abs() + 1e-5 * scale,
                "{what}[{k}]: analytic {} numeric {numeric} (scale {scale})",
                analytic[k]
            );
        }
    };
    // Every parameter, the Sun's rows of the first layer (folded away) included.
    check("d_params", &g.params, &p64, &|p| objective(p, &l64, &m64).0);
    check("d_latents", &g.latents, &l64, &|l| {
        objective(&p64, l, &m64).0
    });
    check("d_means", &g.means, &m64, &|m| objective(&p64, &l64, m).0);
    let sun_rows = net.mlp.weight_range(0).start + 32..net.mlp.weight_range(0).start + 25 * 32;
    assert!(g.params[sun_rows].iter().any(|v| *v != 0.0));
}

#[test]
fn the_fused_path_is_the_folded_mlp_bit_for_bit() {
    for precision in [MatmulPrecision::F32, MatmulPrecision::Bf16] {
        let mut net = ShadowNet::new(6, PositionalEncoding::default(), 13).unwrap();
        if net.mlp.set_precision(precision).is_err() {
            eprintln!("skipping {precision:?}: this CPU lacks it");
            continue;
        }
        let case = Case::random(5000, 2048 + 777, 3);
        let rows = case.gaussians.len();
        let mut rng = SplitMix64::new(4);
        let d_out: Vec<f32> = (0..rows).map(|_| rng.normal()).collect();
        let (y, g) = run(&net, &case, TapeMode::Cache, &d_out);

        // The same with Mlp on the assembled folded rows, and the fold's chain rule by hand.
        let folded = net.folded_mlp(case.sun).unwrap();
        let mut input = Vec::new();
        net.assemble_folded_input(&case.batch(), &mut input)
            .unwrap();
        assert_eq!(input.len(), rows * net.folded_input_width());
        let fwd: MlpForward = folded.forward_train(&input, rows, TapeMode::Cache).unwrap();
        assert_eq!(bits(&y), bits(&fwd.output), "{precision:?}");
        let mut d_folded = vec![0.0f32; folded.num_params()];
        let mut d_input = vec![0.0f32; input.len()];
        folded
            .backward(&input, &fwd, &d_out, &mut d_folded, Some(&mut d_input))
            .unwrap();
        let mut sun_code = vec![0.0f32; 24];
        let s = case.sun.map(|v| v as f64);
        let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        let sun = s.map(|v| (v / n) as f32);
        PositionalEncoding::default()
            .encode(&sun, &mut sun_code)
            .unwrap();
        let mut want = vec![0.0f32; net.mlp.num_params()];
        let h1 = 32;
        let (d_w0, rest) = d_folded.split_at(31 * h1);
        let d_b0 = &rest[..h1];
        want[..h1].copy_from_slice(&d_w0[..h1]);
        for (i, &c) in sun_code.iter().enumerate() {
            for j in 0..h1 {
                want[(1 + i) * h1 + j] = c * d_b0[j];
            }
        }
        want[25 * h1..55 * h1].copy_from_slice(&d_w0[h1..]);
        want[55 * h1..].copy_from_slice(rest);
        assert_eq!(bits(&g.params), bits(&want), "{precision:?}");
        // Latents: their columns, accumulated in list order.
        let mut d_latents = vec![0.0f32; case.latents.len()];
        for (row, &gi) in d_input.chunks_exact(31).zip(&case.gaussians) {
            for (acc, v) in d_latents[gi as usize * 6..gi as usize * 6 + 6]
                .iter_mut()
                .zip(&row[25..])
            {
                *acc += v;
            }
        }
        assert_eq!(bits(&g.latents), bits(&d_latents), "{precision:?}");
        assert!(g.means.iter().any(|v| *v != 0.0));
    }
}

#[test]
fn tape_modes_and_thread_counts_give_the_same_bits() {
    let net = ShadowNet::new(6, PositionalEncoding::default(), 14).unwrap();
    let case = Case::random(6000, 3 * 2048 + 5, 5);
    let mut rng = SplitMix64::new(6);
    let d_out: Vec<f32> = (0..case.gaussians.len()).map(|_| rng.normal()).collect();
    let (y_a, g_a) = run(&net, &case, TapeMode::Cache, &d_out);
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    for (mode, pool) in [
        (TapeMode::Recompute, None),
        (TapeMode::Cache, Some(&one_thread)),
        (TapeMode::Recompute, Some(&one_thread)),
    ] {
        let (y_b, g_b) = match pool {
            None => run(&net, &case, mode, &d_out),
            Some(p) => p.install(|| run(&net, &case, mode, &d_out)),
        };
        assert_eq!(bits(&y_a), bits(&y_b));
        assert_eq!(bits(&g_a.params), bits(&g_b.params));
        assert_eq!(bits(&g_a.latents), bits(&g_b.latents));
        assert_eq!(bits(&g_a.means), bits(&g_b.means));
    }
    // Recompute keeps no activations; Cache keeps 96 per row.
    let mut pass = ShadowPass::default();
    net.forward_train_into(&case.batch(), TapeMode::Recompute, &mut pass)
        .unwrap();
    assert_eq!(pass.tape_len(), 0);
    net.forward_train_into(&case.batch(), TapeMode::Cache, &mut pass)
        .unwrap();
    assert_eq!(pass.tape_len(), 96 * case.gaussians.len());
}

#[test]
fn bad_inputs_are_errors_and_nothing_is_written() {
    let net = ShadowNet::new(6, PositionalEncoding::default(), 15).unwrap();
    let mut case = Case::random(50, 40, 7);
    let rows = case.gaussians.len();
    let d_out = vec![0.1f32; rows];
    // A NaN latent of a listed Gaussian: the same error as the full assembly gives.
    let listed = case.gaussians[7] as usize;
    case.latents[listed * 6 + 2] = f32::NAN;
    let mut pass = ShadowPass::default();
    let err = net
        .forward_train_into(&case.batch(), TapeMode::Cache, &mut pass)
        .unwrap_err();
    assert_eq!(
        err,
        NnError::NonFinite {
            what: "shadow latent",
            index: listed
        }
    );
    assert_eq!(pass.rows(), 0);
    assert!(pass.output.is_empty());
    case.latents[listed * 6 + 2] = 1.0;
    // An index past the model.
    let mut bad = case.gaussians.clone();
    bad[3] = 50;
    let batch = ShadowBatch {
        gaussians: &bad,
        ..case.batch()
    };
    assert_eq!(
        net.forward_train_into(&batch, TapeMode::Cache, &mut pass),
        Err(NnError::Index { index: 50, len: 50 })
    );
    // A backward with another Sun, a short gradient or a pass of another batch.
    net.forward_train_into(&case.batch(), TapeMode::Cache, &mut pass)
        .unwrap();
    let mut d_params = vec![0.0f32; net.mlp.num_params()];
    let mut d_latents = vec![0.0f32; 50 * 6];
    let mut d_means = vec![0.0f32; 50 * 3];
    let other_sun = ShadowBatch {
        sun_dir: [0.0, 0.0, 1.0],
        ..case.batch()
    };
    assert!(matches!(
        net.backward(
            &other_sun,
            &pass,
            &d_out,
            &mut d_params,
            &mut d_latents,
            &mut d_means
        ),
        Err(NnError::Config(_))
    ));
    assert!(matches!(
        net.backward(
            &case.batch(),
            &pass,
            &d_out[1..],
            &mut d_params,
            &mut d_latents,
            &mut d_means
        ),
        Err(NnError::Shape { .. })
    ));
    let fewer = ShadowBatch {
        gaussians: &case.gaussians[1..],
        ..case.batch()
    };
    assert!(matches!(
        net.backward(
            &fewer,
            &pass,
            &d_out[1..],
            &mut d_params,
            &mut d_latents,
            &mut d_means
        ),
        Err(NnError::Shape { .. })
    ));
    let mut nan_out = d_out.clone();
    nan_out[4] = f32::INFINITY;
    assert!(matches!(
        net.backward(
            &case.batch(),
            &pass,
            &nan_out,
            &mut d_params,
            &mut d_latents,
            &mut d_means
        ),
        Err(NnError::NonFinite { .. })
    ));
    assert!(d_params
        .iter()
        .chain(&d_latents)
        .chain(&d_means)
        .all(|v| *v == 0.0));
}
