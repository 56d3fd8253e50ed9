//! Measuring one configuration: the warm-up and measured steps on a backend, the stage
//! medians, peak memory and CPU time, switches from `--set`, and each configuration in its
//! own child process (its report to the parent a line of numbers).

use super::*;

pub(super) fn measure(
    n: usize,
    (width, height): (u32, u32),
    kind: SceneKind,
    repeats: usize,
    config: &SunAwareConfig,
    backend: BackendKind,
    label: &str,
) -> Result<Measured, String> {
    let gaussians = scene(n, kind, config, 7);
    let h = BOX_HALF_M;
    let scene_box = SceneBox::new([-h[0], -h[1], -h[2]], h).expect("box");
    let model = SunAwareModel::new(gaussians, scene_box, config.clone())
        .map_err(|e| format!("model: {e}"))?;
    let mut trainer = SunAwareTrainer::new(model);
    // The float-atomic backward (last bits vary run to run) with --gpu-atomic; the
    // component's default is the deterministic one.
    let deterministic = !std::env::args().any(|a| a == "--gpu-atomic");
    let opened = backend
        .open(&ENGINES, deterministic)
        .map_err(|e| e.to_string())?;
    if let Some(adapter) = opened.describe() {
        eprintln!("step_bench: backend wgpu on {adapter}");
    }
    trainer
        .set_backend(&opened)
        .map_err(|e| format!("backend {backend}: {e}"))?;
    let resident = trainer.is_device_resident();
    let cam = camera(width, height);
    let mut rng = SplitMix64::new(11);
    let target: Vec<f32> = (0..width as usize * height as usize * 3)
        .map(|_| rng.next_f32())
        .collect();
    let obs = Observation {
        camera: cam,
        sun_dir: Vec3::new(0.3, 0.5, 0.8).normalize(),
        image: &target,
        mask: None,
    };
    let warm = trainer.step(&obs, 0.0).expect("warm-up step");
    assert!(!warm.skipped, "warm-up step was skipped (non-finite)");
    reset_peak_rss();
    let mut all = Vec::new();
    let mut cpu = Vec::new();
    let mut visible = Vec::new();
    let mut rows = Vec::new();
    if resident {
        // Device-resident: the repeats run as one batch (state uploaded once, downloaded
        // once, as a training round runs); each step's time is its own recording and wait,
        // its stages the device's timestamps (zeros without timestamp queries).
        let batch: Vec<(Observation, f32)> = (0..repeats)
            .map(|r| (obs, r as f32 / repeats as f32))
            .collect();
        let c0 = process_cpu_ms();
        let steps = trainer.step_many(&batch).expect("steps");
        let per_step = (process_cpu_ms() - c0) / repeats.max(1) as f64;
        for stats in steps {
            cpu.push(per_step);
            assert!(!stats.skipped, "step was skipped (non-finite)");
            visible.push(stats.visible as f64);
            rows.push(stats.network_rows as f64);
            all.push(stats.timings);
        }
    }
    for r in 0..if resident { 0 } else { repeats } {
        let c0 = process_cpu_ms();
        let stats = trainer.step(&obs, r as f32 / repeats as f32).expect("step");
        cpu.push(process_cpu_ms() - c0);
        assert!(!stats.skipped, "step was skipped (non-finite)");
        visible.push(stats.visible as f64);
        rows.push(stats.network_rows as f64);
        all.push(stats.timings);
    }
    let peak = peak_rss_mb();
    let med = |f: fn(&StepTimings) -> f64| median(all.iter().map(f).collect());
    let stages = StepTimings {
        project_ms: med(|t| t.project_ms),
        sort_bin_ms: med(|t| t.sort_bin_ms),
        contribution_ms: med(|t| t.contribution_ms),
        shadow_pass_ms: med(|t| t.shadow_pass_ms),
        phi_forward_ms: med(|t| t.phi_forward_ms),
        psi_forward_ms: med(|t| t.psi_forward_ms),
        blend_forward_ms: med(|t| t.blend_forward_ms),
        loss_ms: med(|t| t.loss_ms),
        blend_backward_ms: med(|t| t.blend_backward_ms),
        project_backward_ms: med(|t| t.project_backward_ms),
        phi_backward_ms: med(|t| t.phi_backward_ms),
        psi_backward_ms: med(|t| t.psi_backward_ms),
        optimizer_ms: med(|t| t.optimizer_ms),
        total_ms: med(|t| t.total_ms),
    };
    let rows = median(rows) as usize;
    // The floors are CPU GEMMs: no meaning next to a device-resident step's stages.
    let nets = if resident {
        Vec::new()
    } else {
        paired_floors(&mut trainer, &obs, rows, repeats)?
    };
    Ok(Measured {
        label: label.to_string(),
        gaussians: n,
        width,
        height,
        visible: median(visible) as usize,
        rows,
        stages,
        other_ms: median(all.iter().map(StepTimings::other_ms).collect()),
        cpu_ms: median(cpu),
        peak_rss_mb: peak,
        nets,
        precision: config.mlp_precision,
    })
}

/// The speed switches of [`SunAwareConfig`] this bench can set by name. `mlp_precision`
/// counts as a switch: off is f32, on is bf16.
pub(super) fn set_switch(config: &mut SunAwareConfig, name: &str, on: bool) -> Result<(), String> {
    match name {
        "skip_noncontributing_in_mlp" => config.skip_noncontributing_in_mlp = on,
        "mlp_recompute_activations" => config.mlp_recompute_activations = on,
        "reuse_step_buffers" => config.reuse_step_buffers = on,
        "mlp_precision" => {
            config.mlp_precision = if on {
                MatmulPrecision::Bf16
            } else {
                MatmulPrecision::F32
            }
        }
        _ => return Err(format!("unknown switch {name:?}")),
    }
    Ok(())
}

/// One `--set NAME=VALUE`: a switch (on/off/true/false), `mlp_precision=f32|bf16`, or
/// `appearance_hidden_width=N`.
pub(super) fn set_value(
    config: &mut SunAwareConfig,
    name: &str,
    value: &str,
) -> Result<(), String> {
    let bad = || format!("--set {name}={value}: bad value");
    match (name, value) {
        ("mlp_precision", "f32") => set_switch(config, name, false),
        ("mlp_precision", "bf16") => set_switch(config, name, true),
        ("appearance_hidden_width", v) => {
            config.appearance_hidden_width = v.parse().map_err(|_| bad())?;
            Ok(())
        }
        (_, "on" | "true") => set_switch(config, name, true),
        (_, "off" | "false") => set_switch(config, name, false),
        _ => Err(bad()),
    }
}

/// Runs one configuration in a child process (this executable with `--child-variant`), so
/// memory the allocator kept from an earlier configuration does not count in its peak.
pub(super) fn measure_in_child(
    args: &[String],
    n: usize,
    (width, height): (u32, u32),
    variant: usize,
    label: &str,
) -> Result<Measured, String> {
    let mut child_args: Vec<String> = Vec::new();
    let mut i = 0;
    while i < args.len() {
        if args[i] == "--sizes" || args[i] == "--images" || args[i] == "--json" {
            i += if args[i] == "--json" { 1 } else { 2 };
            continue;
        }
        child_args.push(args[i].clone());
        i += 1;
    }
    child_args.extend([
        "--sizes".to_string(),
        n.to_string(),
        "--images".to_string(),
        format!("{width}x{height}"),
        "--child-variant".to_string(),
        variant.to_string(),
    ]);
    let exe = std::env::current_exe().map_err(|e| format!("own executable: {e}"))?;
    let out = std::process::Command::new(exe)
        .args(&child_args)
        .stderr(std::process::Stdio::inherit())
        .output()
        .map_err(|e| format!("child process: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "child for {n} at {width}x{height} failed: {}",
            out.status
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find_map(|l| l.strip_prefix("MEASURED "))
        .ok_or("child printed no result")?;
    Measured::from_line(line, label)
}

impl Measured {
    pub(super) const NET_NAMES: [&'static str; 4] =
        ["phi_forward", "phi_backward", "psi_forward", "psi_backward"];

    /// Whitespace-separated numbers (the child's report to the parent).
    pub(super) fn to_line(&self) -> String {
        let mut v: Vec<String> = vec![
            self.gaussians.to_string(),
            self.width.to_string(),
            self.height.to_string(),
            self.visible.to_string(),
            self.rows.to_string(),
        ];
        v.extend(self.stages.stages().iter().map(|(_, ms)| format!("{ms:e}")));
        for x in [
            self.stages.total_ms,
            self.other_ms,
            self.cpu_ms,
            self.peak_rss_mb,
        ] {
            v.push(format!("{x:e}"));
        }
        for net in &self.nets {
            v.push(net.rows.to_string());
            for x in [net.gflop, net.stage_ms, net.floor_ms, net.ratio] {
                v.push(format!("{x:e}"));
            }
        }
        v.push(u8::from(self.precision == MatmulPrecision::Bf16).to_string());
        v.join(" ")
    }

    pub(super) fn from_line(line: &str, label: &str) -> Result<Self, String> {
        let f: Vec<f64> = line
            .split_whitespace()
            .map(|s| {
                s.parse::<f64>()
                    .map_err(|e| format!("child result {s:?}: {e}"))
            })
            .collect::<Result<_, _>>()?;
        // The network floors are absent for a device-resident run.
        let with_nets = f.len() == 5 + 13 + 4 + 4 * 5 + 1;
        if !with_nets && f.len() != 5 + 13 + 4 + 1 {
            return Err(format!("child result has {} numbers", f.len()));
        }
        let st = &f[5..18];
        let stages = StepTimings {
            project_ms: st[0],
            sort_bin_ms: st[1],
            contribution_ms: st[2],
            shadow_pass_ms: st[3],
            phi_forward_ms: st[4],
            psi_forward_ms: st[5],
            blend_forward_ms: st[6],
            loss_ms: st[7],
            blend_backward_ms: st[8],
            project_backward_ms: st[9],
            phi_backward_ms: st[10],
            psi_backward_ms: st[11],
            optimizer_ms: st[12],
            total_ms: f[18],
        };
        let named = if with_nets { &Self::NET_NAMES[..] } else { &[] };
        let nets = named
            .iter()
            .enumerate()
            .map(|(k, &name)| {
                let o = 22 + 5 * k;
                NetStage {
                    name,
                    rows: f[o] as usize,
                    gflop: f[o + 1],
                    stage_ms: f[o + 2],
                    floor_ms: f[o + 3],
                    ratio: f[o + 4],
                }
            })
            .collect();
        Ok(Self {
            label: label.to_string(),
            gaussians: f[0] as usize,
            width: f[1] as u32,
            height: f[2] as u32,
            visible: f[3] as usize,
            rows: f[4] as usize,
            stages,
            other_ms: f[19],
            cpu_ms: f[20],
            peak_rss_mb: f[21],
            nets,
            precision: if f[f.len() - 1] == 1.0 {
                MatmulPrecision::Bf16
            } else {
                MatmulPrecision::F32
            },
        })
    }
}
