//! Device MLP timings: a Phi-like [37, 256, 256, 256, 3] network, forward +
//! backward with the input gradient, over `--rows` rows (default 10,000):
//! - the CPU `nn::Mlp` (f32, for scale);
//! - the host path (`GpuMlp::forward`/`backward`: uploads of the input, the parameters and
//!   the output gradient, readback of the output and the gradients);
//! - the resident path (`run_forward_backward`: one command buffer on device buffers, one
//!   wait);
//! - the resident path with the batch's upload and readback.
//!
//! `cargo run --release -p gs-wgpu --example gpu_network_bench -- [--rows N]
//! [--runs N]`
//!
//! Wall and process CPU time per path, medians of `--runs` (default 5) alternated repeats
//! after a warm-up. On Mesa's software Vulkan driver (lavapipe) the device columns measure a
//! CPU emulation of a GPU: compare them only on a machine with a real one.

#[path = "../../gs-core/examples/bench_util/mod.rs"]
mod bench_util;
use bench_util::{arg, exit_if_help, init_threads, median, process_cpu_ms};

use gs_core::nn::{HiddenActivation, Init, Mlp, TapeMode};
use gs_core::rng::SplitMix64;
use gs_wgpu::mlp::{DeviceBatch, DeviceNetwork};
use gs_wgpu::{GpuContext, GpuMlp, GpuOptions};

const USAGE: &str = "gpu_network_bench: device MLP timings, host path against resident path
usage: gpu_network_bench [--rows N] [--runs N]
  --rows N   rows of the Phi-like [37, 256, 256, 256, 3] batch (default 10000)
  --runs N   alternated timed repeats per path after one warm-up (default 5)";

/// The network with non-zero biases (Kaiming weights, biases uniform in +-0.2), so that no
/// product is trivially zero.
fn network_with_biases(widths: &[usize], seed: u64) -> Mlp {
    let mut net =
        Mlp::new(widths, HiddenActivation::Relu, Init::KaimingUniform, seed).expect("valid widths");
    let mut rng = SplitMix64::new(seed ^ 0xb1a5);
    for l in 0..net.num_layers() {
        let range = net.bias_range(l);
        for b in &mut net.params_mut()[range] {
            *b = rng.uniform_symmetric(0.2);
        }
    }
    net
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    exit_if_help(&args, USAGE);
    init_threads("gpu_network_bench", None);
    let rows = arg(&args, "--rows").unwrap_or(10_000).max(1);
    let runs = arg(&args, "--runs").unwrap_or(5).max(1);
    let ctx = match GpuContext::with_options(GpuOptions::default()) {
        Ok(ctx) => ctx,
        Err(e) => {
            eprintln!("gpu_network_bench: no GPU adapter: {e}");
            std::process::exit(2);
        }
    };
    let gpu = GpuMlp::new(ctx).expect("device MLP pipelines");
    let mlp = network_with_biases(&[37, 256, 256, 256, 3], 5);
    let mut rng = SplitMix64::new(55);
    let input: Vec<f32> = (0..rows * 37).map(|_| rng.normal()).collect();
    let d_out: Vec<f32> = (0..rows * 3).map(|_| rng.normal()).collect();
    let zeros = vec![0.0f32; mlp.num_params()];
    let net = DeviceNetwork::new(gpu.context(), &mlp, &zeros, &zeros, 0).expect("upload");
    let batch = DeviceBatch::new(&gpu, &net, rows).expect("batch");
    batch
        .write(&gpu, &input, rows, &d_out)
        .expect("batch upload");
    let cpu = || {
        let forward = mlp.forward_train(&input, rows, TapeMode::Cache).unwrap();
        let mut d_params = vec![0.0f32; mlp.num_params()];
        let mut d_input = vec![0.0f32; input.len()];
        mlp.backward(&input, &forward, &d_out, &mut d_params, Some(&mut d_input))
            .unwrap();
    };
    let host = || {
        let (_, tape) = gpu.forward(&mlp, &input, rows).unwrap();
        gpu.backward(&tape, &d_out, true).unwrap();
    };
    let resident = || gpu.run_forward_backward(&net, &batch, true).unwrap();
    let resident_io = || {
        batch.write(&gpu, &input, rows, &d_out).unwrap();
        gpu.run_forward_backward(&net, &batch, true).unwrap();
        batch.read(&gpu).unwrap();
        net.download_grads(gpu.context()).unwrap();
    };
    let paths: [(&str, &dyn Fn()); 4] = [
        ("CPU nn::Mlp (f32, for scale)", &cpu),
        ("host path (uploads + readbacks)", &host),
        ("resident (device buffers)", &resident),
        ("resident + batch upload/readback", &resident_io),
    ];
    for (_, f) in &paths {
        f();
    }
    let mut walls = vec![Vec::new(); paths.len()];
    let mut cpus = vec![Vec::new(); paths.len()];
    for _ in 0..runs {
        for (k, (_, f)) in paths.iter().enumerate() {
            let (t, c) = (std::time::Instant::now(), process_cpu_ms());
            f();
            walls[k].push(t.elapsed().as_secs_f64() * 1e3);
            cpus[k].push(process_cpu_ms() - c);
        }
    }
    println!("{}", gs_core::machine::header_line());
    println!("{}", gpu.context().describe());
    println!("Phi-like [37, 256, 256, 256, 3] x {rows} rows, forward + backward (+ dX), median of {runs}:");
    println!("{:<34} {:>10} {:>15}", "path", "wall ms", "process CPU ms");
    for (k, (name, _)) in paths.iter().enumerate() {
        let wall = median(walls[k].clone());
        let cpu = median(cpus[k].clone());
        println!("{name:<34} {wall:>10.1} {cpu:>15.1}");
    }
}
