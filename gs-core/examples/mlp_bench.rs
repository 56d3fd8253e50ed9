//! Throughput of the small networks: GEMM GFLOP/s per layer shape, and MLP forward/backward
//! time for the appearance (width 256) and shadow (width 32) networks at 10K/50K/100K rows,
//! on 1 and 2 threads. Each MLP row shows its "GEMM floor" (the summed time of its layer
//! products at the measured GEMM rate) and the ratio of the MLP time to that floor, so the
//! cost of everything around the GEMMs (bias, activation, tape, gradient reduction) shows.
//!
//! Run: `cargo run --release -p gs-core --example mlp_bench -- [--json] [--quick] [--reps N]
//! [--mlp-only] [--net phi|psi]` (`--mlp-only` skips the GEMM table but still measures the
//! floors quietly; `--net` keeps one network).
//! Times are the minimum over repetitions (the machine is shared; the minimum is the least
//! disturbed). `--json` prints one JSON object per line instead of the tables.

use std::time::Instant;

use gs_core::nn::matmul::{matmul, matmul_a_bt, matmul_at_b};
use gs_core::nn::mlp::BLOCK_ROWS;
use gs_core::nn::{AppearanceNet, Mlp, PositionalEncoding, ShadowNet, TapeMode};
use rayon::prelude::*;

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

/// Minimum wall time of `f` over `reps` runs after one warm-up, seconds.
fn min_time(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    (0..reps)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

#[derive(Clone, Copy)]
enum Product {
    /// `Y = X W`, the forward product.
    Forward,
    /// `dW = X^T dZ`, blocked like the MLP: per-block partials, summed in block order.
    WeightGrad,
    /// `dX = dZ W^T`.
    InputGrad,
}

impl Product {
    fn name(self) -> &'static str {
        match self {
            Product::Forward => "X*W",
            Product::WeightGrad => "X^T*dZ",
            Product::InputGrad => "dZ*W^T",
        }
    }
}

/// Time of one product over `rows` rows with `k -> n` widths, blocked over `BLOCK_ROWS`
/// rows in parallel as the MLP runs it.
fn gemm_time(product: Product, rows: usize, k: usize, n: usize, reps: usize) -> f64 {
    let x = values(rows * k, 1);
    let w = values(k * n, 2);
    let dz = values(rows * n, 3);
    let mut y = vec![0.0f32; rows * n];
    let mut dx = vec![0.0f32; rows * k];
    let mut dw = vec![0.0f32; k * n];
    min_time(reps, || match product {
        Product::Forward => y
            .par_chunks_mut(BLOCK_ROWS * n)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / n;
                let start = b * BLOCK_ROWS;
                matmul(&x[start * k..(start + r) * k], &w, out, r, k, n, false);
            }),
        Product::InputGrad => dx
            .par_chunks_mut(BLOCK_ROWS * k)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / k;
                let start = b * BLOCK_ROWS;
                matmul_a_bt(&dz[start * n..(start + r) * n], &w, out, r, n, k, false);
            }),
        Product::WeightGrad => {
            let partials: Vec<Vec<f32>> = (0..rows.div_ceil(BLOCK_ROWS))
                .into_par_iter()
                .map(|b| {
                    let start = b * BLOCK_ROWS;
                    let r = BLOCK_ROWS.min(rows - start);
                    let mut p = vec![0.0f32; k * n];
                    matmul_at_b(
                        &x[start * k..(start + r) * k],
                        &dz[start * n..(start + r) * n],
                        &mut p,
                        r,
                        k,
                        n,
                        false,
                    );
                    p
                })
                .collect();
            dw.fill(0.0);
            for p in &partials {
                for (a, b) in dw.iter_mut().zip(p) {
                    *a += b;
                }
            }
        }
    })
}

struct Net {
    name: &'static str,
    mlp: Mlp,
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let json = args.iter().any(|a| a == "--json");
    let quick = args.iter().any(|a| a == "--quick");
    let reps = args
        .iter()
        .position(|a| a == "--reps")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(if quick { 1 } else { 3 });
    let mlp_only = args.iter().any(|a| a == "--mlp-only");
    let row_counts: &[usize] = if quick {
        &[10_000]
    } else {
        &[10_000, 50_000, 100_000]
    };
    let net_filter = args
        .iter()
        .position(|a| a == "--net")
        .and_then(|i| args.get(i + 1))
        .cloned();
    let encoding = PositionalEncoding::default();
    let all_nets = [
        Net {
            name: "phi(256)",
            mlp: AppearanceNet::new(72, encoding, 1).unwrap().mlp,
        },
        Net {
            name: "psi(32)",
            mlp: ShadowNet::new(6, encoding, 2).unwrap().mlp,
        },
    ];
    let nets: Vec<Net> = all_nets
        .into_iter()
        .filter(|n| {
            net_filter
                .as_ref()
                .is_none_or(|f| n.name.starts_with(f.as_str()))
        })
        .collect();

    if !json && !mlp_only {
        println!("GEMM (row-blocked, {BLOCK_ROWS} rows per block), GFLOP/s");
        println!(
            "{:>8} {:>8} {:>7} {:>12} {:>12}",
            "product", "rows", "k->n", "1 thread", "2 threads"
        );
    }
    let pools: Vec<(usize, rayon::ThreadPool)> = [1usize, 2]
        .iter()
        .map(|&t| {
            (
                t,
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .expect("thread pool"),
            )
        })
        .collect();

    // Per-layer GEMM times, reused as the floor of each MLP measurement.
    let mut floor_fwd = vec![vec![vec![0.0f64; pools.len()]; row_counts.len()]; nets.len()];
    let mut floor_bwd = floor_fwd.clone();
    let mut seen_shapes: Vec<(usize, usize, usize)> = Vec::new();
    for (ni, net) in nets.iter().enumerate() {
        for (ri, &rows) in row_counts.iter().enumerate() {
            for pair in net.mlp.widths().windows(2) {
                let (k, n) = (pair[0], pair[1]);
                let flops = 2.0 * (rows * k * n) as f64;
                let mut rates = Vec::new();
                for product in [Product::Forward, Product::WeightGrad, Product::InputGrad] {
                    let mut per_thread = Vec::new();
                    for (pi, (threads, pool)) in pools.iter().enumerate() {
                        let t = pool.install(|| gemm_time(product, rows, k, n, reps));
                        match product {
                            Product::Forward => floor_fwd[ni][ri][pi] += t,
                            _ => floor_bwd[ni][ri][pi] += t,
                        }
                        per_thread.push(flops / t / 1e9);
                        if json && !mlp_only {
                            println!(
                                "{{\"kind\":\"gemm\",\"product\":\"{}\",\"rows\":{rows},\"k\":{k},\"n\":{n},\"threads\":{threads},\"seconds\":{t:.6},\"gflops\":{:.2}}}",
                                product.name(),
                                flops / t / 1e9
                            );
                        }
                    }
                    rates.push((product, per_thread));
                }
                if !json && !mlp_only && !seen_shapes.contains(&(rows, k, n)) {
                    for (product, per_thread) in rates {
                        println!(
                            "{:>8} {:>8} {:>7} {:>12.1} {:>12.1}",
                            product.name(),
                            rows,
                            format!("{k}->{n}"),
                            per_thread[0],
                            per_thread[1]
                        );
                    }
                }
                seen_shapes.push((rows, k, n));
            }
        }
    }

    if !json {
        println!();
        println!("MLP (forward = Cache-mode forward_train; backward with d_input), milliseconds");
        println!(
            "{:>9} {:>7} {:>3} {:>9} {:>9} {:>7} {:>9} {:>9} {:>7} {:>9} {:>9}",
            "net",
            "rows",
            "thr",
            "fwd ms",
            "floor ms",
            "ratio",
            "bwd ms",
            "floor ms",
            "ratio",
            "fwd GF/s",
            "bwd GF/s"
        );
    }
    for (ni, net) in nets.iter().enumerate() {
        let mlp = &net.mlp;
        for (ri, &rows) in row_counts.iter().enumerate() {
            let input = values(rows * mlp.input_width(), 7);
            let d_out = values(rows * mlp.output_width(), 8);
            let flops_fwd = (rows * mlp.flops_per_row_forward()) as f64;
            for (pi, (threads, pool)) in pools.iter().enumerate() {
                let (t_fwd, t_bwd) = pool.install(|| {
                    let t_fwd = min_time(reps, || {
                        let fwd = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
                        std::hint::black_box(&fwd.output);
                    });
                    let fwd = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
                    let mut d_params = vec![0.0f32; mlp.num_params()];
                    let mut d_input = vec![0.0f32; input.len()];
                    let t_bwd = min_time(reps, || {
                        mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
                            .unwrap();
                    });
                    (t_fwd, t_bwd)
                });
                let (ff, fb) = (floor_fwd[ni][ri][pi], floor_bwd[ni][ri][pi]);
                if json {
                    println!(
                        "{{\"kind\":\"mlp\",\"net\":\"{}\",\"rows\":{rows},\"threads\":{threads},\"forward_s\":{t_fwd:.6},\"forward_floor_s\":{ff:.6},\"backward_s\":{t_bwd:.6},\"backward_floor_s\":{fb:.6},\"forward_gflops\":{:.2},\"backward_gflops\":{:.2}}}",
                        net.name,
                        flops_fwd / t_fwd / 1e9,
                        2.0 * flops_fwd / t_bwd / 1e9
                    );
                } else {
                    println!(
                        "{:>9} {:>7} {:>3} {:>9.2} {:>9.2} {:>7.2} {:>9.2} {:>9.2} {:>7.2} {:>9.1} {:>9.1}",
                        net.name,
                        rows,
                        threads,
                        t_fwd * 1e3,
                        ff * 1e3,
                        t_fwd / ff,
                        t_bwd * 1e3,
                        fb * 1e3,
                        t_bwd / fb,
                        flops_fwd / t_fwd / 1e9,
                        2.0 * flops_fwd / t_bwd / 1e9
                    );
                }
            }
        }
    }
}
