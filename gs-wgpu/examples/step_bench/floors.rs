//! The networks' GEMM floors: each layer's products on matrices of the stage's shape,
//! timed right after a step so each stage's ratio pairs it with its own floor.

use super::*;

fn seconds_ms(f: impl FnOnce()) -> f64 {
    let t0 = Instant::now();
    f();
    t0.elapsed().as_secs_f64() * 1e3
}

/// Operands of one layer's products over `rows` rows, `k -> n` widths.
struct LayerOperands {
    rows: usize,
    k: usize,
    n: usize,
    x: Vec<f32>,
    w: Vec<f32>,
    dz: Vec<f32>,
    y: Vec<f32>,
    dx: Vec<f32>,
}

impl LayerOperands {
    pub(super) fn new(rows: usize, k: usize, n: usize, rng: &mut SplitMix64) -> Self {
        let mut fill = |len: usize| (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect();
        Self {
            rows,
            k,
            n,
            x: fill(rows * k),
            w: fill(k * n),
            dz: fill(rows * n),
            y: vec![0.0; rows * n],
            dx: vec![0.0; rows * k],
        }
    }

    /// `Y = X W`, blocked over `BLOCK_ROWS` rows in parallel as the MLP runs it.
    pub(super) fn forward(&mut self, products: Products) {
        let (k, n) = (self.k, self.n);
        let (x, w) = (&self.x, &self.w);
        self.y
            .par_chunks_mut(BLOCK_ROWS * n)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / n;
                let s = b * BLOCK_ROWS;
                products.matmul(&x[s * k..(s + r) * k], w, out, r, k, n, false);
            });
    }

    /// `dW = X^T dZ` (per-block partials summed in block order) and `dX = dZ W^T`.
    pub(super) fn backward(&mut self, products: Products) {
        let (rows, k, n) = (self.rows, self.k, self.n);
        let (x, w, dz) = (&self.x, &self.w, &self.dz);
        let partials: Vec<Vec<f32>> = (0..rows.div_ceil(BLOCK_ROWS))
            .into_par_iter()
            .map(|b| {
                let s = b * BLOCK_ROWS;
                let r = BLOCK_ROWS.min(rows - s);
                let mut p = vec![0.0f32; k * n];
                products.matmul_at_b(
                    &x[s * k..(s + r) * k],
                    &dz[s * n..(s + r) * n],
                    &mut p,
                    r,
                    k,
                    n,
                    false,
                );
                p
            })
            .collect();
        let mut dw = vec![0.0f32; k * n];
        for p in &partials {
            for (a, b) in dw.iter_mut().zip(p) {
                *a += b;
            }
        }
        std::hint::black_box(&dw);
        self.dx
            .par_chunks_mut(BLOCK_ROWS * k)
            .enumerate()
            .for_each(|(b, out)| {
                let r = out.len() / k;
                let s = b * BLOCK_ROWS;
                products.matmul_a_bt(&dz[s * n..(s + r) * n], w, out, r, n, k, false);
            });
    }
}

/// The GEMMs of one network over `rows` rows (its layer shapes, its own products), built
/// once and timed right after each measured step, so a stage and its floor are measured
/// seconds apart under the same machine state.
struct FloorOperands {
    products: Products,
    layers: Vec<LayerOperands>,
}

impl FloorOperands {
    pub(super) fn new(mlp: &Mlp, rows: usize) -> Self {
        let mut rng = SplitMix64::new(99);
        let mut layers: Vec<LayerOperands> = if rows == 0 {
            Vec::new()
        } else {
            mlp.widths()
                .windows(2)
                .map(|p| LayerOperands::new(rows, p[0], p[1], &mut rng))
                .collect()
        };
        // One untimed pass: first-touch page faults are not GEMM time.
        for l in &mut layers {
            l.forward(mlp.products());
            l.backward(mlp.products());
        }
        Self {
            products: mlp.products(),
            layers,
        }
    }

    /// One forward and one backward of every layer: (forward ms, backward ms).
    pub(super) fn time_once(&mut self) -> (f64, f64) {
        let products = self.products;
        let fwd = self
            .layers
            .iter_mut()
            .map(|l| seconds_ms(|| l.forward(products)))
            .sum();
        let bwd = self
            .layers
            .iter_mut()
            .map(|l| seconds_ms(|| l.backward(products)))
            .sum();
        (fwd, bwd)
    }
}

/// The networks' stages against their GEMM floors, paired: after the measured steps (so
/// the floors' operands do not count in the peak memory), `repeats` more steps, each
/// followed at once by one timing of the same GEMMs on `rows` rows. Each stage's ratio is
/// the median of its per-step ratios, so a change in the machine's speed between the
/// steps and the floors (a shared host) does not pass for distance from the floor.
pub(super) fn paired_floors(
    trainer: &mut SunAwareTrainer,
    obs: &Observation,
    rows: usize,
    repeats: usize,
) -> Result<Vec<NetStage>, String> {
    let model = &trainer.model;
    let phi = &model
        .appearance
        .as_ref()
        .ok_or("configuration d has Phi")?
        .mlp;
    let psi = &model.shadow.as_ref().ok_or("configuration d has Psi")?.mlp;
    let gflop = |mlp: &Mlp| (rows * mlp.flops_per_row_forward()) as f64 / 1e9;
    let (phi_gflop, psi_gflop) = (gflop(phi), gflop(psi));
    let mut floors = [FloorOperands::new(phi, rows), FloorOperands::new(psi, rows)];
    // [phi_f, phi_b, psi_f, psi_b]: (stage ms, floor ms) per repeat.
    let mut pairs: [Vec<(f64, f64)>; 4] = Default::default();
    for r in 0..repeats {
        let stats = trainer
            .step(obs, r as f32 / repeats as f32)
            .map_err(|e| format!("step: {e}"))?;
        let t = &stats.timings;
        let (phi_f, phi_b) = floors[0].time_once();
        let (psi_f, psi_b) = floors[1].time_once();
        pairs[0].push((t.phi_forward_ms, phi_f));
        pairs[1].push((t.phi_backward_ms, phi_b));
        pairs[2].push((t.psi_forward_ms, psi_f));
        pairs[3].push((t.psi_backward_ms, psi_b));
    }
    let names = ["phi_forward", "phi_backward", "psi_forward", "psi_backward"];
    let gflops = [phi_gflop, 2.0 * phi_gflop, psi_gflop, 2.0 * psi_gflop];
    Ok(names
        .iter()
        .zip(gflops)
        .zip(&pairs)
        .map(|((&name, gflop), p)| NetStage {
            name,
            rows,
            gflop,
            stage_ms: median(p.iter().map(|&(s, _)| s).collect()),
            floor_ms: median(p.iter().map(|&(_, f)| f).collect()),
            ratio: median(p.iter().map(|&(s, f)| s / f).collect()),
        })
        .collect())
}
