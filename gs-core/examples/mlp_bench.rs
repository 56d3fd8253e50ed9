//! Throughput of the small networks: GEMM GFLOP/s per layer shape, and MLP forward/backward
//! time for the appearance (width 256) and shadow (width 32) networks at 10K/50K/100K rows,
//! on 1 and 2 threads. Each MLP row shows its "GEMM floor" (the summed time of its layer
//! products, blocked exactly as the MLP runs them) and the ratio of the MLP time to that
//! floor, so the cost of everything around the GEMMs (bias, activation, tape allocation,
//! gradient reduction, finiteness checks) shows.
//!
//! Run: `cargo run --release -p gs-core --example mlp_bench -- [--json] [--quick] [--reps N]
//! [--mlp-only] [--net phi|psi] [--precision f32|bf16] [--kernel avx512|avx2|gemm-crate]
//! [--width N] [--reference-python PATH | --no-reference]`. `--mlp-only` skips the GEMM
//! table; `--net` keeps one network; `--precision` picks the products (both the networks'
//! and the floor's; bf16 needs AMX-BF16 or AVX-512 BF16, `GS_BF16_KERNEL` picks); `--kernel` the f32 kernel (default:
//! `F32Kernel::detect`; `kernel_ab` compares kernels alternately in one run); `--width` sets Phi's hidden width (default 256); `--json`
//! prints one JSON object per line instead of the tables.
//!
//! The machine's own rate: before the tables, numpy's `matmul` (its BLAS, OpenBLAS in the
//! PyPI wheels) is timed in a subprocess on 100,000 x 256 x 256 and 2048^3 on 1 and 2
//! threads (`bench_util/reference.rs`; `--reference-python` names the Python, default
//! `python3`). Every GEMM and MLP rate is then also printed as a percentage of the
//! tall-skinny reference on the same thread count ("%ref"). Without numpy the header says
//! the reference is unavailable and the percentages are left out.
//!
//! Times are minima over repetitions (the machine is shared; the minimum is the least
//! disturbed run). Floor and MLP are measured alternately within each repetition, so a
//! change of machine load between them does not distort the ratio.

use std::time::Instant;

mod bench_util;
use bench_util::reference::{self, Reference};
use bench_util::{arg_str, exit_if_help, init_threads, json_machine_fields};

use gs_core::nn::mlp::BLOCK_ROWS;
use gs_core::nn::{
    AppearanceNet, F32Kernel, MatmulPrecision, Mlp, PositionalEncoding, Products, ShadowNet,
    TapeMode,
};
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

fn seconds(f: impl FnOnce()) -> f64 {
    let t0 = Instant::now();
    f();
    t0.elapsed().as_secs_f64()
}

#[derive(Clone, Copy, PartialEq)]
enum Product {
    /// `Y = X W`, the forward product.
    Forward,
    /// `dW = X^T dZ`, as the MLP runs it: per-block partials summed in block order.
    WeightGrad,
    /// `dX = dZ W^T`.
    InputGrad,
}

impl Product {
    const ALL: [Product; 3] = [Product::Forward, Product::WeightGrad, Product::InputGrad];

    fn name(self) -> &'static str {
        match self {
            Product::Forward => "X*W",
            Product::WeightGrad => "X^T*dZ",
            Product::InputGrad => "dZ*W^T",
        }
    }
}

/// Operands of one layer's three products over `rows` rows, `k -> n` widths.
struct LayerOperands {
    rows: usize,
    k: usize,
    n: usize,
    x: Vec<f32>,
    w: Vec<f32>,
    dz: Vec<f32>,
    y: Vec<f32>,
    dx: Vec<f32>,
    dw: Vec<f32>,
}

impl LayerOperands {
    fn new(rows: usize, k: usize, n: usize) -> Self {
        Self {
            rows,
            k,
            n,
            x: values(rows * k, 1),
            w: values(k * n, 2),
            dz: values(rows * n, 3),
            y: vec![0.0; rows * n],
            dx: vec![0.0; rows * k],
            dw: vec![0.0; k * n],
        }
    }

    fn flops(&self) -> f64 {
        2.0 * (self.rows * self.k * self.n) as f64
    }

    /// Runs one product, blocked over `BLOCK_ROWS` rows in parallel as the MLP does.
    fn run(&mut self, product: Product, products: Products) {
        let (rows, k, n) = (self.rows, self.k, self.n);
        let (x, w, dz) = (&self.x, &self.w, &self.dz);
        match product {
            Product::Forward => {
                self.y
                    .par_chunks_mut(BLOCK_ROWS * n)
                    .enumerate()
                    .for_each(|(b, out)| {
                        let r = out.len() / n;
                        let s = b * BLOCK_ROWS;
                        products.matmul(&x[s * k..(s + r) * k], w, out, r, k, n, false);
                    });
            }
            Product::InputGrad => {
                self.dx
                    .par_chunks_mut(BLOCK_ROWS * k)
                    .enumerate()
                    .for_each(|(b, out)| {
                        let r = out.len() / k;
                        let s = b * BLOCK_ROWS;
                        products.matmul_a_bt(&dz[s * n..(s + r) * n], w, out, r, n, k, false);
                    });
            }
            Product::WeightGrad => {
                let partials: Vec<Vec<f32>> = (0..rows.div_ceil(BLOCK_ROWS))
                    .into_par_iter()
                    .map(|b| {
                        let s = b * BLOCK_ROWS;
                        let r = BLOCK_ROWS.min(rows - s);
                        let mut p = vec![0.0f32; k * n];
                        let (xs, dzs) = (&x[s * k..(s + r) * k], &dz[s * n..(s + r) * n]);
                        products.matmul_at_b(xs, dzs, &mut p, r, k, n, false);
                        p
                    })
                    .collect();
                self.dw.fill(0.0);
                for p in &partials {
                    for (a, b) in self.dw.iter_mut().zip(p) {
                        *a += b;
                    }
                }
            }
        }
    }
}

struct Net {
    name: &'static str,
    mlp: Mlp,
}

const USAGE: &str = "\
usage: cargo run --release -p gs-core --example mlp_bench -- [FLAGS]

  --json           one JSON object per line instead of the tables
  --quick          10K rows only, one repetition unless --reps
  --reps N         repetitions, the minimum is kept (default 3)
  --mlp-only       skip the GEMM table
  --net NAME       phi or psi: keep one network
  --precision P    f32 or bf16 products (bf16 needs AMX-BF16 or AVX-512 BF16;
                   default f32)
  --kernel K       f32 kernel: avx512, avx2 or gemm-crate (default: the one detected)
  --width N        Phi's hidden width (default 256)
  --reference-python PATH
                   Python with numpy for the reference SGEMM rate (default python3)
  --no-reference   skip the reference SGEMM
  -h, --help       this text";

fn main() {
    let args: Vec<String> = std::env::args().collect();
    exit_if_help(&args, USAGE);
    let mode = init_threads("mlp_bench", None);
    let json = args.iter().any(|a| a == "--json");
    let quick = args.iter().any(|a| a == "--quick");
    let mlp_only = args.iter().any(|a| a == "--mlp-only");
    let reps = arg_str(&args, "--reps")
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(if quick { 1 } else { 3 })
        .max(1);
    let net_filter = arg_str(&args, "--net");
    let precision = match arg_str(&args, "--precision").unwrap_or("f32") {
        "f32" => MatmulPrecision::F32,
        "bf16" => MatmulPrecision::Bf16,
        other => {
            eprintln!("mlp_bench: --precision {other:?}: expected f32 or bf16");
            std::process::exit(2);
        }
    };
    let products = match (Products::new(precision), arg_str(&args, "--kernel")) {
        (Err(e), _) => {
            eprintln!("mlp_bench: {e}");
            std::process::exit(2);
        }
        (Ok(p), None) => p,
        (Ok(_), Some(_)) if precision != MatmulPrecision::F32 => {
            eprintln!("mlp_bench: --kernel applies to f32 products only");
            std::process::exit(2);
        }
        (Ok(_), Some(name)) => match F32Kernel::named(name) {
            Ok(kernel) => Products::f32_on(kernel),
            Err(e) => {
                eprintln!("mlp_bench: --kernel: {e}");
                std::process::exit(2);
            }
        },
    };
    let phi_width = arg_str(&args, "--width")
        .and_then(|v| v.parse::<usize>().ok())
        .unwrap_or(256);
    let row_counts: &[usize] = if quick {
        &[10_000]
    } else {
        &[10_000, 50_000, 100_000]
    };
    let encoding = PositionalEncoding::default();
    let nets: Vec<Net> = [
        Net {
            name: "phi",
            mlp: AppearanceNet::with_hidden_width(72, phi_width, encoding, 1)
                .unwrap()
                .mlp,
        },
        Net {
            name: "psi",
            mlp: ShadowNet::new(6, encoding, 2).unwrap().mlp,
        },
    ]
    .into_iter()
    .filter(|n| net_filter.is_none_or(|f| n.name.starts_with(f)))
    .map(|mut n| {
        n.mlp.set_products(products);
        n
    })
    .collect();
    let pools: Vec<(usize, rayon::ThreadPool)> = [1usize, 2]
        .iter()
        .map(|&t| {
            // The global pool's denormal mode on these pools too (their workers compute).
            let pool = gs_core::fpmode::pool_builder(mode).num_threads(t).build();
            (t, pool.expect("thread pool"))
        })
        .collect();

    let machine = json_machine_fields();
    let kernel = products.kernel_name();
    let header = format!("{}; products: {kernel}", gs_core::machine::header_line());
    if json {
        eprintln!("{header}");
    } else {
        println!("{header}");
    }
    let reference = if args.iter().any(|a| a == "--no-reference") {
        Err("skipped (--no-reference)".to_string())
    } else {
        let python = arg_str(&args, "--reference-python").unwrap_or("python3");
        let threads: Vec<usize> = pools.iter().map(|(t, _)| *t).collect();
        reference::measure(python, &threads, reps.max(5))
    };
    print_reference(&reference, json, &machine);
    let reference = reference.ok();
    // "x.y" percent of the tall-skinny reference on `threads`, or "-" without one.
    let percent = |gflops: f64, threads: usize| -> String {
        reference
            .as_ref()
            .and_then(|r| r.tall_skinny(threads))
            .map_or("-".to_string(), |r| format!("{:.0}", 100.0 * gflops / r))
    };
    if !mlp_only {
        if !json {
            println!("GEMM (row-blocked, {BLOCK_ROWS} rows per block), GFLOP/s");
            println!(
                "{:>8} {:>8} {:>8} {:>10} {:>5} {:>10} {:>5}",
                "product", "rows", "k->n", "1 thread", "%ref", "2 threads", "%ref"
            );
        }
        let mut shapes: Vec<(usize, usize, usize)> = Vec::new();
        for net in &nets {
            for &rows in row_counts {
                for pair in net.mlp.widths().windows(2) {
                    if !shapes.contains(&(rows, pair[0], pair[1])) {
                        shapes.push((rows, pair[0], pair[1]));
                    }
                }
            }
        }
        for &(rows, k, n) in &shapes {
            let mut ops = LayerOperands::new(rows, k, n);
            for product in Product::ALL {
                let mut rates = Vec::new();
                for (threads, pool) in &pools {
                    ops.run(product, products);
                    let t = (0..reps)
                        .map(|_| pool.install(|| seconds(|| ops.run(product, products))))
                        .fold(f64::INFINITY, f64::min);
                    let gflops = ops.flops() / t / 1e9;
                    rates.push(gflops);
                    if json {
                        println!(
                            "{{\"kind\":\"gemm\",{machine},\"product\":\"{}\",\"rows\":{rows},\"k\":{k},\"n\":{n},\"threads\":{threads},\"seconds\":{t:.6},\"gflops\":{gflops:.2}}}",
                            product.name()
                        );
                    }
                }
                if !json {
                    println!(
                        "{:>8} {:>8} {:>8} {:>10.1} {:>5} {:>10.1} {:>5}",
                        product.name(),
                        rows,
                        format!("{k}->{n}"),
                        rates[0],
                        percent(rates[0], 1),
                        rates[1],
                        percent(rates[1], 2)
                    );
                }
            }
        }
        if !json {
            println!();
        }
    }

    if !json {
        println!(
            "MLP, milliseconds (fwd: forward_train_into, Cache, reused tape; infer: forward \
             without tape; bwd: backward with d_input)"
        );
        println!(
            "{:>9} {:>7} {:>3} {:>8} {:>8} {:>8} {:>6} {:>8} {:>8} {:>6} {:>8} {:>5} {:>8} {:>5}",
            "net",
            "rows",
            "thr",
            "fwd",
            "infer",
            "floor",
            "ratio",
            "bwd",
            "floor",
            "ratio",
            "fwd GF/s",
            "%ref",
            "bwd GF/s",
            "%ref"
        );
    }
    for net in &nets {
        let mlp = &net.mlp;
        for &rows in row_counts {
            let input = values(rows * mlp.input_width(), 7);
            let d_out = values(rows * mlp.output_width(), 8);
            let mut layers: Vec<LayerOperands> = mlp
                .widths()
                .windows(2)
                .map(|p| LayerOperands::new(rows, p[0], p[1]))
                .collect();
            let flops_fwd = (rows * mlp.flops_per_row_forward()) as f64;
            for (threads, pool) in &pools {
                let mut best = [f64::INFINITY; 5];
                let mut d_params = vec![0.0f32; mlp.num_params()];
                let mut d_input = vec![0.0f32; input.len()];
                pool.install(|| {
                    let fwd = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
                    let mut reused = fwd.clone();
                    for _ in 0..reps {
                        let floor_fwd: f64 = layers
                            .iter_mut()
                            .map(|l| seconds(|| l.run(Product::Forward, products)))
                            .sum();
                        let t_fwd = seconds(|| {
                            mlp.forward_train_into(&input, rows, TapeMode::Cache, &mut reused)
                                .unwrap();
                        });
                        let t_infer = seconds(|| {
                            std::hint::black_box(mlp.forward(&input, rows).unwrap());
                        });
                        let floor_bwd: f64 = layers
                            .iter_mut()
                            .map(|l| {
                                seconds(|| l.run(Product::WeightGrad, products))
                                    + seconds(|| l.run(Product::InputGrad, products))
                            })
                            .sum();
                        let t_bwd = seconds(|| {
                            mlp.backward(&input, &fwd, &d_out, &mut d_params, Some(&mut d_input))
                                .unwrap();
                        });
                        let now = [t_fwd, t_infer, floor_fwd, t_bwd, floor_bwd];
                        for (b, t) in best.iter_mut().zip(now) {
                            *b = b.min(t);
                        }
                    }
                });
                let [t_fwd, t_infer, ff, t_bwd, fb] = best;
                let (gf_fwd, gf_bwd) = (flops_fwd / t_fwd / 1e9, 2.0 * flops_fwd / t_bwd / 1e9);
                if json {
                    println!(
                        "{{\"kind\":\"mlp\",{machine},\"net\":\"{}\",\"rows\":{rows},\"threads\":{threads},\"forward_s\":{t_fwd:.6},\"inference_s\":{t_infer:.6},\"forward_floor_s\":{ff:.6},\"backward_s\":{t_bwd:.6},\"backward_floor_s\":{fb:.6},\"forward_gflops\":{gf_fwd:.2},\"backward_gflops\":{gf_bwd:.2}}}",
                        net.name
                    );
                } else {
                    println!(
                        "{:>9} {:>7} {:>3} {:>8.2} {:>8.2} {:>8.2} {:>6.2} {:>8.2} {:>8.2} {:>6.2} {:>8.1} {:>5} {:>8.1} {:>5}",
                        net.name,
                        rows,
                        threads,
                        t_fwd * 1e3,
                        t_infer * 1e3,
                        ff * 1e3,
                        t_fwd / ff,
                        t_bwd * 1e3,
                        fb * 1e3,
                        t_bwd / fb,
                        gf_fwd,
                        percent(gf_fwd, *threads),
                        gf_bwd,
                        percent(gf_bwd, *threads)
                    );
                }
            }
        }
    }
}

/// The reference block: a table (or JSON lines) of the numpy rates, or why there are none.
fn print_reference(reference: &Result<Reference, String>, json: bool, machine: &str) {
    match reference {
        Ok(r) if json => {
            for rate in &r.rates {
                println!(
                    "{{\"kind\":\"reference\",{machine},\"library\":{},\"m\":{},\"k\":{},\"n\":{},\"threads\":{},\"gflops\":{:.2}}}",
                    bench_util::json_string(&r.library),
                    rate.m,
                    rate.k,
                    rate.n,
                    rate.threads,
                    rate.gflops
                );
            }
        }
        Ok(r) => {
            println!("reference SGEMM in this run ({}), GFLOP/s", r.library);
            println!("{:>16} {:>10} {:>10}", "m x k x n", "1 thread", "2 threads");
            for shape in reference::SHAPES {
                let show = |t| r.rate(shape, t).map_or("-".into(), |g| format!("{g:.1}"));
                println!(
                    "{:>16} {:>10} {:>10}",
                    format!("{}x{}x{}", shape.0, shape.1, shape.2),
                    show(1),
                    show(2)
                );
            }
            println!(
                "(%ref below: percent of the {}x{}x{} rate on the same thread count)\n",
                reference::SHAPES[0].0,
                reference::SHAPES[0].1,
                reference::SHAPES[0].2
            );
        }
        Err(e) if json => eprintln!("reference SGEMM unavailable: {e}"),
        Err(e) => println!("reference SGEMM unavailable: {e}\n"),
    }
}
