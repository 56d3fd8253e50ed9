//! Gradient checks of Phi (appearance) and Psi (shadow network) end to end: input assembly,
//! network and scatter against an f64 reference, and their errors on bad inputs.

use super::*;

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
