//! A/B of the product kernels (f32 and bf16) on one thread: the networks' layer shapes, each product
//! as the MLP runs it on one row block (`X W`, `X^T dZ`, `dZ W^T` over `BLOCK_ROWS` rows,
//! repeated over `--blocks` blocks), and large square products for the machine's best
//! f32 GEMM rate. The kernels run alternately within every repetition, so a change of
//! machine load hits each alike; the table shows the median GFLOP/s of each kernel over
//! the repetitions and the ratio of the medians.
//!
//! Run: `cargo run --release -p gs-core --example kernel_ab -- [--kernels a,b,...]
//! [--reps N] [--blocks N] [--square N] [--net phi|psi]`. Kernels: f32 `avx512`, `avx2`,
//! `gemm-crate`; bf16 `amx`, `avx512bf16` (default: every one this CPU runs). `--square 0`
//! skips the square product.

use std::time::Instant;

mod bench_util;
use bench_util::{arg, arg_str, exit_if_help, init_threads, median};

use gs_core::nn::mlp::BLOCK_ROWS;
use gs_core::nn::{AppearanceNet, Bf16Kernel, F32Kernel, PositionalEncoding, Products, ShadowNet};

const USAGE: &str = "\
usage: cargo run --release -p gs-core --example kernel_ab -- [FLAGS]

  --kernels A,B    kernels to compare: f32 avx512, avx2, gemm-crate; bf16 amx, avx512bf16
                   (default: all present)
  --reps N         repetitions, each kernel once per repetition, medians kept (default 7)
  --blocks N       row blocks of the network shapes per timing (default 4)
  --square N       side of the square product (default 1024; 0 skips it)
  --net NAME       phi or psi: keep one network's shapes
  -h, --help       this text";

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

/// One timed case: a name and a closure running it once on the given products.
struct Case {
    name: String,
    flops: f64,
    run: Box<dyn FnMut(Products)>,
}

/// The three products of a `k -> n` layer over `blocks` blocks of `BLOCK_ROWS` rows.
fn layer_cases(blocks: usize, k: usize, n: usize) -> Vec<Case> {
    let r = BLOCK_ROWS;
    let flops = 2.0 * (blocks * r * k * n) as f64;
    let x = values(blocks * r * k, 1);
    let w = values(k * n, 2);
    let dz = values(blocks * r * n, 3);
    let (x2, dz2, w2, dz3) = (x.clone(), dz.clone(), w.clone(), dz.clone());
    let mut y = vec![0.0; r * n];
    let mut dw = vec![0.0; k * n];
    let mut dx = vec![0.0; r * k];
    let rows = blocks * r;
    vec![
        Case {
            name: format!("X*W    {rows}x{k}->{n}"),
            flops,
            run: Box::new(move |p: Products| {
                for xs in x.chunks_exact(r * k) {
                    p.matmul(xs, &w, &mut y, r, k, n, false);
                }
                std::hint::black_box(&y);
            }),
        },
        Case {
            name: format!("X^T*dZ {rows}x{k}->{n}"),
            flops,
            run: Box::new(move |p: Products| {
                for (xs, dzs) in x2.chunks_exact(r * k).zip(dz.chunks_exact(r * n)) {
                    p.matmul_at_b(xs, dzs, &mut dw, r, k, n, false);
                }
                std::hint::black_box(&dw);
            }),
        },
        Case {
            name: format!("dZ*W^T {rows}x{k}->{n}"),
            flops,
            run: Box::new(move |p: Products| {
                for dzs in dz2.chunks_exact(r * n) {
                    p.matmul_a_bt(dzs, &w2, &mut dx, r, n, k, false);
                }
                std::hint::black_box((&dx, &dz3));
            }),
        },
    ]
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    exit_if_help(&args, USAGE);
    init_threads("kernel_ab", Some(1));
    let reps = arg(&args, "--reps").unwrap_or(7).max(1);
    let blocks = arg(&args, "--blocks").unwrap_or(4).max(1);
    let square = arg(&args, "--square").unwrap_or(1024);
    let net_filter = arg_str(&args, "--net");
    let named = |name: &str| -> Result<Products, String> {
        match F32Kernel::named(name) {
            Ok(kernel) => Ok(Products::f32_on(kernel)),
            Err(f32_err) if F32Kernel::NAMES.contains(&name) => Err(f32_err),
            Err(_) => Bf16Kernel::named(name).map(Products::bf16_on),
        }
    };
    let kernels: Vec<Products> = match arg_str(&args, "--kernels") {
        Some(list) => list
            .split(',')
            .map(|name| {
                named(name).unwrap_or_else(|e| {
                    eprintln!("kernel_ab: {e}");
                    std::process::exit(2);
                })
            })
            .collect(),
        None => F32Kernel::NAMES
            .iter()
            .chain(&Bf16Kernel::NAMES)
            .filter_map(|name| named(name).ok())
            .collect(),
    };

    let encoding = PositionalEncoding::default();
    let nets = [
        ("phi", AppearanceNet::new(72, encoding, 1).unwrap().mlp),
        ("psi", ShadowNet::new(6, encoding, 2).unwrap().mlp),
    ];
    let mut shapes: Vec<(usize, usize)> = Vec::new();
    for (name, mlp) in &nets {
        if net_filter.is_some_and(|f| !name.starts_with(f)) {
            continue;
        }
        for pair in mlp.widths().windows(2) {
            if !shapes.contains(&(pair[0], pair[1])) {
                shapes.push((pair[0], pair[1]));
            }
        }
    }
    let mut cases: Vec<Case> = Vec::new();
    if square > 0 {
        let (a, b) = (values(square * square, 4), values(square * square, 5));
        let mut c = vec![0.0; square * square];
        cases.push(Case {
            name: format!("square {square}^3"),
            flops: 2.0 * (square as f64).powi(3),
            run: Box::new(move |p: Products| {
                p.matmul(&a, &b, &mut c, square, square, square, false);
                std::hint::black_box(&c);
            }),
        });
    }
    for (k, n) in shapes {
        cases.extend(layer_cases(blocks, k, n));
    }

    println!("{}", gs_core::machine::header_line());
    println!("one thread, {reps} repetitions, kernels alternating; median GFLOP/s");
    let names: Vec<&str> = kernels.iter().map(|k| k.kernel_name()).collect();
    print!("{:>24}", "product");
    for name in &names {
        print!(" {name:>11}");
    }
    if kernels.len() == 2 {
        print!(" {:>16}", format!("{}/{}", names[0], names[1]));
    }
    println!();
    for case in &mut cases {
        let mut rates: Vec<Vec<f64>> = vec![Vec::new(); kernels.len()];
        // Warm-up: scratch, caches and page faults out of the timings.
        for &kernel in &kernels {
            (case.run)(kernel);
        }
        for rep in 0..reps {
            // Alternate which kernel goes first, too.
            for i in 0..kernels.len() {
                let i = if rep % 2 == 0 {
                    i
                } else {
                    kernels.len() - 1 - i
                };
                let t0 = Instant::now();
                (case.run)(kernels[i]);
                rates[i].push(case.flops / t0.elapsed().as_secs_f64() / 1e9);
            }
        }
        let medians: Vec<f64> = rates.into_iter().map(median).collect();
        print!("{:>24}", case.name);
        for m in &medians {
            print!(" {m:>11.1}");
        }
        if medians.len() == 2 {
            print!(" {:>16.2}", medians[0] / medians[1]);
        }
        println!();
    }
}
