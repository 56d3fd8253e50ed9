//! Fits a Gaussian model to a synthetic satellite-like scene with the vanilla 3DGS loop.
//!
//! The ground truth is a few hundred flat Gaussians on the faces of a box-shaped bus and
//! on two solar wings, rendered by the same rasterizer from cameras on a sphere. Training
//! starts from random points in a sphere (random colours) and uses densification, opacity
//! resets and the SH degree schedule. Writes to `out/fit_synthetic/`:
//! - `heldout_NN.png`, `train_NN.png`: ground truth (left) beside the render (right);
//! - `model.ply`: the trained model (standard 3DGS layout, opens in common viewers);
//! - `loss.csv`: per iteration loss, L1, SSIM, Gaussian count;
//! - `summary.txt`: the printed summary.
//!
//! Usage: `cargo run --release -p gs-core --example fit_synthetic [-- --iterations N
//! --size W H --out DIR --seed S]` (`--help` lists them).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

mod bench_util;
use bench_util::{exit_if_help, init_threads};

use glam::{Quat, Vec3};
use gs_core::init::{inverse_sigmoid, random_in_sphere, SplitMix64};
use gs_core::ply::save_ply;
use gs_core::sh::rgb_to_sh_dc;
use gs_core::train::{evaluate, render_rgb, train, TrainConfig, TrainView, ViewScore};
use gs_core::{Camera, GaussianModel, Intrinsics, ModelLayout, Param};

struct Args {
    iterations: usize,
    width: u32,
    height: u32,
    out: PathBuf,
    seed: u64,
}

const USAGE: &str = "\
usage: cargo run --release -p gs-core --example fit_synthetic -- [FLAGS]

  --iterations N   training iterations (default 3000; the schedules scale with it)
  --size W H       image width and height in pixels (default 128 96)
  --out DIR        output folder (default out/fit_synthetic)
  --seed S         seed of the scene, the start and the training (default 7)
  -h, --help       this text";

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        iterations: 3000,
        width: 128,
        height: 96,
        out: PathBuf::from("out/fit_synthetic"),
        seed: 7,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    exit_if_help(&argv, USAGE);
    let mut i = 0;
    let num = |s: Option<&String>, what: &str| -> Result<u64, String> {
        s.ok_or(format!("{what} needs a value"))?
            .parse::<u64>()
            .map_err(|e| format!("{what}: {e}"))
    };
    while i < argv.len() {
        match argv[i].as_str() {
            "--iterations" => {
                a.iterations = num(argv.get(i + 1), "--iterations")? as usize;
                i += 2;
            }
            "--size" => {
                a.width = num(argv.get(i + 1), "--size")? as u32;
                a.height = num(argv.get(i + 2), "--size")? as u32;
                i += 3;
            }
            "--out" => {
                a.out = PathBuf::from(argv.get(i + 1).ok_or("--out needs a value")?);
                i += 2;
            }
            "--seed" => {
                a.seed = num(argv.get(i + 1), "--seed")?;
                i += 2;
            }
            other => return Err(format!("unknown argument '{other}'")),
        }
    }
    if a.width == 0 || a.height == 0 || a.iterations == 0 {
        return Err("size and iterations must be positive".into());
    }
    Ok(a)
}

/// Adds a flat Gaussian at `centre` lying in the plane of `rotation`'s x-y axes.
fn push_flat(m: &mut GaussianModel, centre: Vec3, rotation: Quat, size: f32, rgb: [f32; 3]) {
    let row: [Vec<f32>; Param::COUNT] = [
        centre.to_array().to_vec(),
        vec![size.ln(), size.ln(), (0.15 * size).ln()],
        vec![rotation.w, rotation.x, rotation.y, rotation.z],
        vec![inverse_sigmoid(0.9)],
        rgb.iter().map(|&c| rgb_to_sh_dc(c)).collect(),
        vec![],
        vec![],
        vec![],
        vec![],
    ];
    m.params
        .push_row(|p| &row[p.index()])
        .expect("row widths match layout sh(0)");
}

/// A box bus (gold foil) with two dark-blue solar wings along y.
fn satellite(rng: &mut SplitMix64) -> GaussianModel {
    let mut m = GaussianModel::new(ModelLayout::sh(0)).expect("degree 0 is valid");
    let half = Vec3::new(0.5, 0.4, 0.4);
    // Faces: normal axis, sign.
    for axis in 0..3 {
        for sign in [-1.0f32, 1.0] {
            let normal = Vec3::AXES[axis] * sign;
            let rotation = Quat::from_rotation_arc(Vec3::Z, normal);
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let steps = 6;
            for a in 0..steps {
                for b in 0..steps {
                    let mut p = normal * half[axis];
                    p[u] = half[u] * (2.0 * (a as f32 + 0.5) / steps as f32 - 1.0);
                    p[v] = half[v] * (2.0 * (b as f32 + 0.5) / steps as f32 - 1.0);
                    let shade = 0.75 + 0.2 * rng.next_f32();
                    let gold = [shade, 0.62 * shade, 0.15 + 0.1 * rng.next_f32()];
                    push_flat(&mut m, p, rotation, 0.09, gold);
                }
            }
        }
    }
    // Wings in the x-y plane, from |y| = 0.55 to 1.6.
    for sign in [-1.0f32, 1.0] {
        for a in 0..12 {
            for b in 0..5 {
                let y = sign * (0.6 + 0.09 * a as f32);
                let x = -0.3 + 0.15 * b as f32;
                let cell = if (a + b) % 2 == 0 { 0.18 } else { 0.28 };
                let blue = [0.1, 0.15 + 0.05 * rng.next_f32(), cell + 0.2];
                push_flat(&mut m, Vec3::new(x, y, 0.0), Quat::IDENTITY, 0.07, blue);
            }
        }
    }
    m
}

fn sphere_cameras(n: usize, offset: f32, radius: f32, k: Intrinsics) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = (i as f32 + offset) * std::f32::consts::PI * (3.0 - 5f32.sqrt());
            let eye = Vec3::new(r * phi.cos(), r * phi.sin(), z) * radius;
            Camera::look_at(k, eye, Vec3::ZERO, Vec3::Z)
        })
        .collect()
}

fn to_rgb8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Ground truth and render side by side.
fn save_pair(
    path: &std::path::Path,
    gt: &[f32],
    render: &[f32],
    w: u32,
    h: u32,
) -> Result<(), String> {
    let mut img = image::RgbImage::new(2 * w, h);
    for y in 0..h {
        for x in 0..w {
            let i = ((y * w + x) * 3) as usize;
            let px = |s: &[f32]| image::Rgb([to_rgb8(s[i]), to_rgb8(s[i + 1]), to_rgb8(s[i + 2])]);
            img.put_pixel(x, y, px(gt));
            img.put_pixel(w + x, y, px(render));
        }
    }
    img.save(path)
        .map_err(|e| format!("{}: {e}", path.display()))
}

fn mean(scores: &[ViewScore]) -> (f32, f32) {
    let n = scores.len() as f32;
    (
        scores.iter().map(|s| s.psnr_db).sum::<f32>() / n,
        scores.iter().map(|s| s.ssim).sum::<f32>() / n,
    )
}

fn run() -> Result<(), String> {
    let args = parse_args()?;
    init_threads("fit_synthetic", None);
    std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;
    let mut rng = SplitMix64::new(args.seed);
    let gt = satellite(&mut rng);
    let k = Intrinsics::from_fov_x(40f32.to_radians(), args.width, args.height);
    let black = [0.0f32; 3];
    let make_view = |c: Camera| -> Result<TrainView, String> {
        Ok(TrainView {
            camera: c,
            image: render_rgb(&gt, &c, 0, black).map_err(|e| e.to_string())?,
            mask: None,
        })
    };
    let train_views = sphere_cameras(32, 0.0, 5.0, k)
        .into_iter()
        .map(make_view)
        .collect::<Result<Vec<_>, _>>()?;
    let test_views = sphere_cameras(8, 0.43, 5.3, k)
        .into_iter()
        .map(make_view)
        .collect::<Result<Vec<_>, _>>()?;

    let start = random_in_sphere(500, Vec3::ZERO, 1.6, ModelLayout::sh(1), args.seed)
        .map_err(|e| e.to_string())?
        .model;
    let scale = args.iterations as f64 / 3000.0;
    let at = |i: f64| ((i * scale).round() as usize).max(1);
    let config = TrainConfig {
        iterations: args.iterations,
        densify_from_iter: at(200.0),
        densify_until_iter: at(2000.0),
        densify_interval: at(100.0),
        opacity_reset_interval: at(1000.0),
        sh_degree_interval: at(1000.0),
        seed: args.seed,
        background: black,
        ..TrainConfig::default()
    };
    println!("{}", gs_core::machine::header_line());
    println!(
        "fit_synthetic: {} ground-truth Gaussians, {} train + {} held-out views of {}x{}, \
         start from {} random Gaussians, {} iterations, {} threads",
        gt.len(),
        train_views.len(),
        test_views.len(),
        args.width,
        args.height,
        start.len(),
        args.iterations,
        rayon::current_num_threads()
    );
    let before = mean(&evaluate(&start, &test_views, black).map_err(|e| e.to_string())?);

    let mut csv = String::from("iteration,loss,l1,ssim,gaussians\n");
    let t = Instant::now();
    let (mut fwd_ms, mut loss_ms, mut bwd_ms, mut step_ms) = (0.0, 0.0, 0.0, 0.0);
    let report_every = (args.iterations / 10).max(1);
    let result = train(start, &train_views, &config, |s| {
        fwd_ms += s.forward_ms;
        loss_ms += s.loss_ms;
        bwd_ms += s.backward_ms;
        step_ms += s.step_ms;
        let _ = writeln!(
            csv,
            "{},{},{},{},{}",
            s.iteration, s.loss, s.l1, s.ssim, s.gaussians
        );
        if let Some(d) = s.densified {
            if s.iteration % (report_every / 2).max(1) == 0 {
                println!(
                    "  iter {:>5}: densify +{} clones, {} splits, -{} pruned -> {}",
                    s.iteration, d.cloned, d.split, d.pruned, d.after
                );
            }
        }
        if s.opacity_reset {
            println!("  iter {:>5}: opacity reset", s.iteration);
        }
        if s.iteration % report_every == 0 {
            println!(
                "  iter {:>5}: loss {:.4} (L1 {:.4}, SSIM {:.3}), {} Gaussians, SH degree {}, {:.1} s",
                s.iteration,
                s.loss,
                s.l1,
                s.ssim,
                s.gaussians,
                s.active_sh_degree,
                t.elapsed().as_secs_f64()
            );
        }
    })
    .map_err(|e| e.to_string())?;
    let elapsed = t.elapsed().as_secs_f64();

    let train_scores = evaluate(&result.model, &train_views, black).map_err(|e| e.to_string())?;
    let test_scores = evaluate(&result.model, &test_views, black).map_err(|e| e.to_string())?;
    let (train_psnr, train_ssim) = mean(&train_scores);
    let (test_psnr, test_ssim) = mean(&test_scores);
    let degree = result.model.layout().sh_degree;
    for (name, views) in [("train", &train_views[..4]), ("heldout", &test_views[..])] {
        for (i, v) in views.iter().enumerate() {
            let img =
                render_rgb(&result.model, &v.camera, degree, black).map_err(|e| e.to_string())?;
            save_pair(
                &args.out.join(format!("{name}_{i:02}.png")),
                &v.image,
                &img,
                args.width,
                args.height,
            )?;
        }
    }
    save_ply(&result.model, args.out.join("model.ply")).map_err(|e| e.to_string())?;
    std::fs::write(args.out.join("loss.csv"), csv).map_err(|e| e.to_string())?;

    let n = args.iterations as f64;
    let mut summary = String::new();
    let _ = writeln!(summary, "trained {} iterations in {elapsed:.1} s ({:.2} ms/iter: render {:.2}, loss {:.2}, backward {:.2}, step+densify {:.2})",
        args.iterations, 1e3 * elapsed / n, fwd_ms / n, loss_ms / n, bwd_ms / n, step_ms / n);
    let _ = writeln!(
        summary,
        "Gaussians: {} ground truth, {} trained; {} densify steps; {} skipped steps",
        gt.len(),
        result.model.len(),
        result.densify_reports.len(),
        result.skipped_non_finite_steps
    );
    let _ = writeln!(
        summary,
        "held-out PSNR {:.2} dB before -> {test_psnr:.2} dB after, SSIM {test_ssim:.4}",
        before.0
    );
    let _ = writeln!(
        summary,
        "train    PSNR {train_psnr:.2} dB, SSIM {train_ssim:.4}"
    );
    let _ = writeln!(summary, "wrote {}", args.out.display());
    print!("{summary}");
    std::fs::write(args.out.join("summary.txt"), summary).map_err(|e| e.to_string())?;
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("fit_synthetic: {e}");
        std::process::exit(1);
    }
}
