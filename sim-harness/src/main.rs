//! `sim-harness`: rendezvous simulator command line.
//!
//! `sim-harness generate --scenario FILE --out DIR [--frames N] [--downsample K]
//! [--eval-views N] [--overwrite]` renders a dataset (see `sim_harness::dataset`). Progress goes
//! to stderr; a one-line JSON summary goes to stdout. Errors exit with status 1 and a message
//! naming the bad file, field or value.
//!
//! `sim-harness table --preset NAME --out DIR [--scenario FILE]... [--keep-data]` trains the
//! paper's configurations a-d online on each target and writes the results table and figure
//! (see `sim_harness::experiment::table_job`). `sim-harness demo [--out DIR]` runs the
//! README's demo (see `sim_harness::experiment::demo`). `sim-harness ablation-init --out DIR
//! [--preset NAME] [--inits surface,random,hull-silhouette]` compares initialisations (see
//! `sim_harness::experiment::ablation_init`).
//!
//! `sim-harness pareto --out DIR [--scenario FILE | --target NAME] [--preset NAME]` sweeps
//! the time-for-error knobs; `sim-harness skips --out DIR [...]` measures each switchable
//! skip; `sim-harness ablation-window --out DIR [--windows 5,10,20,40]` is the window
//! ablation (see `sim_harness::experiment::{pareto, skips, ablation}`).
//!
//! `sim-harness shadow-study --out DIR [--target NAME | --scenario FILE] [--preset NAME]
//! [--views N] [--cache DIR] [--no-train]` checks shadow splatting against the ray tracer's
//! ground-truth shadows (see `sim_harness::experiment::shadow_study`).
//!
//! `sim-harness buslogs --dataset DIR [--out DIR/bus] [--config FILE]` writes the dataset as
//! the component's bus logs (`can.log`, `udp.rec`) for `fsw-component --replay`;
//! `sim-harness play --dataset DIR --udp HOST:PORT [--telemetry-udp HOST:PORT] [--can IFACE]
//! [--speed X|max]` plays it onto the live bus (see `sim_harness::busfeed`).
//!
//! Every subcommand runs its threads in the denormal mode `GS_DENORMALS=ftz|ieee` asks for
//! (default flush-to-zero, `gs_core::fpmode`).

use clap::{Parser, Subcommand};
use sim_harness::busfeed::{
    play, write_bus_logs, BusFeedOptions, PlaySpeed, PlayTargets, AOCS_NODE_ID, NAVIGATION_NODE_ID,
};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::experiment::ablation::{
    run_window_ablation, to_markdown as window_markdown, WindowJob,
};
use sim_harness::experiment::ablation_init::{self, run_init_ablation, InitAblationJob};
use sim_harness::experiment::demo::{demo_inputs, run_demo_with};
use sim_harness::experiment::pareto::{
    builtin_scenario, from_csv as pareto_from_csv, run_pareto, select_settings,
    to_markdown as pareto_markdown, write_outputs as write_pareto_outputs, ParetoJob,
};
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::shadow_study::{
    run_shadow_study, to_markdown as shadow_markdown, ShadowStudyJob,
};
use sim_harness::experiment::skips::{
    run_skips, switchable_skips, to_markdown as skips_markdown, SkipsJob,
};
use sim_harness::experiment::table::to_markdown;
use sim_harness::experiment::table_job::{builtin_scenarios, run_table, TableJob};
use sim_harness::scenario::Scenario;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

#[derive(Parser)]
#[command(
    name = "sim-harness",
    about = "Rendezvous simulator with ray-traced ground truth",
    after_help = gs_core::fpmode::ENV_HELP
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Where the rasterizer, the shadow pass's per-pixel walk and the networks' products run
    /// in `table`, `demo` and `pareto`: cpu or wgpu (a build with `--features wgpu` and a
    /// Vulkan adapter); overrides the preset's `backend`. Adam and the networks' input
    /// assembly stay on the CPU either way (docs/gpu.md).
    #[arg(long, global = true)]
    backend: Option<String>,
}

/// `preset` with `--backend` applied, validated (wgpu without the cargo feature is an error
/// naming it; a missing adapter is one when the first run opens it).
fn with_backend(
    mut preset: Preset,
    backend: &Option<String>,
) -> Result<Preset, Box<dyn std::error::Error>> {
    if let Some(name) = backend {
        preset.backend = name.clone();
    }
    preset.validate()?;
    Ok(preset)
}

#[derive(Subcommand)]
enum Command {
    /// Render frames, masks, depth, telemetry, evaluation views, surface points and plots.
    Generate {
        /// Scenario TOML file (see config/scenarios/).
        #[arg(long)]
        scenario: PathBuf,
        /// Output folder (created; must be empty unless --overwrite).
        #[arg(long)]
        out: PathBuf,
        /// Render only the first N frames (same cadence).
        #[arg(long)]
        frames: Option<u32>,
        /// Divide the full-resolution camera by K (overrides camera.downsample).
        #[arg(long)]
        downsample: Option<u32>,
        /// Number of evaluation views (overrides sequence.eval_views).
        #[arg(long)]
        eval_views: Option<u32>,
        /// Write into a non-empty folder, replacing files of the same name.
        #[arg(long)]
        overwrite: bool,
        /// Also write the bus logs to OUT/bus (as `buslogs` with config/component.toml).
        #[arg(long)]
        bus_logs: bool,
    },
    /// Write a dataset as the component's bus logs: can.log (telemetry) and udp.rec (frames).
    Buslogs {
        /// Dataset folder written by `generate`.
        #[arg(long)]
        dataset: PathBuf,
        /// Output folder (default DATASET/bus).
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        bus: BusArgs,
    },
    /// Play a dataset onto the live bus: frames over UDP, telemetry over UDP or SocketCAN.
    Play {
        /// Dataset folder written by `generate`.
        #[arg(long)]
        dataset: PathBuf,
        /// The component's frame port.
        #[arg(long)]
        udp: SocketAddr,
        /// The component's telemetry port (default: --udp unless --can is given).
        #[arg(long)]
        telemetry_udp: Option<SocketAddr>,
        /// Send the telemetry as Cyphal/CAN on this SocketCAN interface.
        #[arg(long)]
        can: Option<String>,
        /// Scenario time divided by X (1 = real time), or "max".
        #[arg(long, default_value = "max")]
        speed: PlaySpeed,
        #[command(flatten)]
        bus: BusArgs,
    },
    /// Train configurations a-d online on each target and write the results table.
    Table {
        /// Preset name (config/presets/NAME.toml) or file.
        #[arg(long)]
        preset: String,
        /// Output folder (table.csv, table.md, figure.png, runs.json, cache/).
        #[arg(long)]
        out: PathBuf,
        /// Scenario file to use instead of the three built-in targets (repeatable).
        #[arg(long)]
        scenario: Vec<PathBuf>,
        /// Also write each scenario's dataset to OUT/data/NAME.
        #[arg(long)]
        keep_data: bool,
    },
    /// Sweep the knobs that trade training time for error on one target; write
    /// pareto.csv, pareto.md and pareto.png (time against PSNR, Pareto front marked).
    Pareto {
        /// Output folder (pareto.csv, pareto.md, pareto.png, cache/).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        target: TargetArgs,
        /// Base preset the settings change one knob of at a time.
        #[arg(long, default_value = "pareto-base")]
        preset: String,
        /// Run only these settings (comma-separated names; default: the whole sweep).
        #[arg(long, value_delimiter = ',')]
        settings: Vec<String>,
    },
    /// Re-plot rows of pareto-schema CSV files together (e.g. the sweep and the skips'
    /// runs): pareto.csv, pareto.md and pareto.png in OUT with the front over all rows.
    ParetoPlot {
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// CSV files written by `pareto` (pareto.csv) or `skips` (skips-runs.csv).
        #[arg(long, required = true)]
        csv: Vec<PathBuf>,
    },
    /// Time saved and error cost of each switchable skip: skips.csv and skips.md.
    Skips {
        /// Output folder (skips.csv, skips.md, cache/).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        target: TargetArgs,
        /// Base preset (every skip at its default).
        #[arg(long, default_value = "pareto-base")]
        preset: String,
    },
    /// Keyframe-window ablation (the paper's Fig. 6): W values on the three built-in targets;
    /// window.csv, window.md and window.png.
    AblationWindow {
        /// Output folder (window.csv, window.md, window.png, cache/).
        #[arg(long)]
        out: PathBuf,
        /// Preset the window sizes change.
        #[arg(long, default_value = "window-ablation")]
        preset: String,
        /// Window sizes, comma-separated.
        #[arg(long, value_delimiter = ',', default_values_t = [5usize, 10, 20, 40])]
        windows: Vec<usize>,
        /// Scenario file to use instead of the three built-in targets (repeatable).
        #[arg(long)]
        scenario: Vec<PathBuf>,
    },
    /// Initialisation ablation: configuration d from surface samples, random points and a
    /// visual hull carved from the first keyframes' masks (init.csv, init.md, init.png).
    AblationInit {
        /// Preset name (config/presets/NAME.toml) or file; its configs are ignored (d only).
        #[arg(long, default_value = "cpu")]
        preset: String,
        /// Output folder (init.csv, init.md, init_curves.csv, init.png, runs.json, cache/).
        #[arg(long)]
        out: PathBuf,
        /// Scenario file to use instead of the three built-in targets (repeatable).
        #[arg(long)]
        scenario: Vec<PathBuf>,
        /// Initialisations to compare, in order: surface, random, or a hull start named
        /// hull with any of the suffixes -grey, -volume, -silhouette, -photo, -recarve, e.g.
        /// hull-silhouette, the best hull start (docs/initialisation.md).
        #[arg(long, value_delimiter = ',', default_value = "surface,random,hull")]
        inits: Vec<String>,
        /// Evaluate every N rounds during training (0: only at the end).
        #[arg(long, default_value_t = 100)]
        eval_every: u64,
        /// Keyframes the hull is carved from (0: the window size W).
        #[arg(long)]
        hull_views: Option<usize>,
        /// Voxels along the side of the hull's cube.
        #[arg(long)]
        hull_resolution: Option<u32>,
        /// Only write hull.png (surface samples beside each target's hull), no training.
        #[arg(long)]
        hull_figure_only: bool,
    },
    /// The tables and figure of several `ablation-init` jobs together (e.g. one job per
    /// target): init.csv, init.md and init.png from their runs.json files.
    AblationInitPlot {
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// runs.json files written by `ablation-init`, in the order their runs are listed.
        #[arg(long, value_delimiter = ',', required = true)]
        runs: Vec<PathBuf>,
    },
    /// Shadow splatting (configuration c) against the ray tracer's ground-truth shadows on
    /// one target: shadow_study.json, shadow_study.md, before.png, after.png.
    ShadowStudy {
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Preset name (config/presets/NAME.toml) or file.
        #[arg(long, default_value = "cpu")]
        preset: String,
        /// Scenario file (default: the built-in target named by --target).
        #[arg(long)]
        scenario: Option<PathBuf>,
        /// Built-in target: cassini, rosetta or starlink.
        #[arg(long, default_value = "cassini")]
        target: String,
        /// Evaluation views and training frames scored and drawn (each).
        #[arg(long, default_value_t = 4)]
        views: usize,
        /// Rendered-scene cache (default OUT/cache; a table's OUT/cache is reused as is).
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Only the ground truth, the Sun coverage and the light pass on known geometry.
        #[arg(long)]
        no_train: bool,
    },
    /// Train configuration d online on a small embedded Cassini-like scenario.
    Demo {
        /// Output folder.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
    },
}

/// One target: a scenario file or a built-in target's name (default cassini).
#[derive(clap::Args)]
struct TargetArgs {
    /// Scenario TOML file.
    #[arg(long, conflicts_with = "target")]
    scenario: Option<PathBuf>,
    /// Built-in target: cassini, rosetta or starlink.
    #[arg(long)]
    target: Option<String>,
}

impl TargetArgs {
    fn scenario(&self) -> Result<Scenario, Box<dyn std::error::Error>> {
        match &self.scenario {
            Some(path) => Ok(Scenario::load(path)?),
            None => Ok(builtin_scenario(
                self.target.as_deref().unwrap_or("cassini"),
            )?),
        }
    }
}

/// How the simulated spacecraft's nodes talk to the component.
#[derive(clap::Args)]
struct BusArgs {
    /// Component configuration (CAN FD flag, interface name, frame port, node-ID).
    #[arg(long, default_value = "config/component.toml")]
    config: PathBuf,
    /// Node-ID of the AOCS (Sun vector source).
    #[arg(long, default_value_t = AOCS_NODE_ID)]
    aocs_node: u8,
    /// Node-ID of relative navigation (pose source).
    #[arg(long, default_value_t = NAVIGATION_NODE_ID)]
    navigation_node: u8,
    /// 1-sigma position uncertainty sent with each pose, metres.
    #[arg(long, default_value_t = 0.0)]
    position_sigma_m: f32,
    /// 1-sigma attitude uncertainty sent with each pose, degrees.
    #[arg(long, default_value_t = 0.0)]
    attitude_sigma_deg: f32,
    /// Leave the target masks out of the camera frames.
    #[arg(long)]
    no_mask: bool,
}

impl BusArgs {
    fn options(&self) -> Result<(BusFeedOptions, u8), Box<dyn std::error::Error>> {
        bus_options(&self.config, |o| {
            o.aocs_node_id = self.aocs_node;
            o.navigation_node_id = self.navigation_node;
            o.position_sigma_m = self.position_sigma_m;
            o.attitude_sigma_rad = self.attitude_sigma_deg.to_radians();
            o.include_mask = !self.no_mask;
        })
    }
}

/// The scenario files given on the command line, else the three built-in targets.
fn scenarios_or_builtin(files: &[PathBuf]) -> Result<Vec<Scenario>, Box<dyn std::error::Error>> {
    if files.is_empty() {
        return Ok(builtin_scenarios()?);
    }
    Ok(files
        .iter()
        .map(|p| Scenario::load(p))
        .collect::<Result<_, _>>()?)
}

fn bus_options(
    config: &Path,
    adjust: impl FnOnce(&mut BusFeedOptions),
) -> Result<(BusFeedOptions, u8), Box<dyn std::error::Error>> {
    let config = fsw_component::config::ComponentConfig::load(config)?;
    let mut options = BusFeedOptions::from_config(&config);
    adjust(&mut options);
    Ok((options, config.node.node_id))
}

fn buslogs(
    dataset: &Path,
    out: &Path,
    options: &BusFeedOptions,
    node_id: u8,
) -> Result<(), Box<dyn std::error::Error>> {
    let summary = write_bus_logs(dataset, out, options, node_id)?;
    eprintln!(
        "wrote {} frames: {} CAN frames to {}, {} datagrams to {}",
        summary.frames,
        summary.can_frames,
        out.join(fsw_component::recorder::CAN_FILE).display(),
        summary.frame_datagrams,
        out.join(fsw_component::recorder::UDP_FILE).display()
    );
    println!("{}", serde_json::to_string(&summary)?);
    Ok(())
}

fn run(cli: Cli) -> Result<(), Box<dyn std::error::Error>> {
    let backend = cli.backend;
    let uses_backend = matches!(
        cli.command,
        Command::Table { .. } | Command::Pareto { .. } | Command::Demo { .. }
    );
    if backend.is_some() && !uses_backend {
        return Err("--backend applies to table, demo and pareto only".into());
    }
    match cli.command {
        Command::Generate {
            scenario,
            out,
            frames,
            downsample,
            eval_views,
            overwrite,
            bus_logs,
        } => {
            let scenario =
                Scenario::load(&scenario)?.with_overrides(frames, downsample, eval_views)?;
            let summary = generate(
                &scenario,
                &out,
                GenerateOptions { overwrite },
                &mut |line| eprintln!("{line}"),
            )?;
            println!("{}", serde_json::to_string(&summary)?);
            if bus_logs {
                let (options, node_id) = bus_options(Path::new("config/component.toml"), |_| {})?;
                buslogs(&out, &out.join("bus"), &options, node_id)?;
            }
            Ok(())
        }
        Command::Buslogs { dataset, out, bus } => {
            let (options, node_id) = bus.options()?;
            let out = out.unwrap_or_else(|| dataset.join("bus"));
            buslogs(&dataset, &out, &options, node_id)
        }
        Command::Play {
            dataset,
            udp,
            telemetry_udp,
            can,
            speed,
            bus,
        } => {
            let (options, node_id) = bus.options()?;
            let targets = PlayTargets {
                frames_udp: udp,
                telemetry_udp,
                can_interface: can,
            };
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()?;
            let summary = runtime.block_on(play(&dataset, &options, node_id, &targets, speed))?;
            eprintln!(
                "played {} frames: {} datagrams to {udp}, {} telemetry datagrams, {} CAN frames",
                summary.frames,
                summary.frame_datagrams,
                summary.telemetry_datagrams,
                summary.can_frames
            );
            println!("{}", serde_json::to_string(&summary)?);
            Ok(())
        }
        Command::Table {
            preset,
            out,
            scenario,
            keep_data,
        } => {
            let preset = with_backend(Preset::load(&preset)?, &backend)?;
            let scenarios = scenarios_or_builtin(&scenario)?;
            let job = TableJob {
                preset,
                scenarios,
                out_dir: out.clone(),
                keep_data,
            };
            let result = run_table(&job, &mut |line| eprintln!("{line}"))?;
            eprintln!("\n{}", to_markdown(&result.rows));
            eprintln!(
                "{} runs in {:.0} s (rendering {:.0} s); wrote {}",
                result.runs.len(),
                result.total_s,
                result.render_s,
                ["table.csv", "table.md", "figure.png", "runs.json"]
                    .map(|f| out.join(f).display().to_string())
                    .join(", ")
            );
            Ok(())
        }
        Command::Pareto {
            out,
            target,
            preset,
            settings,
        } => {
            let job = ParetoJob {
                base: with_backend(Preset::load(&preset)?, &backend)?,
                scenario: target.scenario()?,
                settings: select_settings(&settings)?,
                out_dir: out.clone(),
            };
            let (rows, front) = run_pareto(&job, &mut |line| eprintln!("{line}"))?;
            eprintln!("\n{}", pareto_markdown(&rows, &front));
            eprintln!(
                "wrote {}",
                ["pareto.csv", "pareto.md", "pareto.png"]
                    .map(|f| out.join(f).display().to_string())
                    .join(", ")
            );
            Ok(())
        }
        Command::ParetoPlot { out, csv } => {
            let mut rows = Vec::new();
            for path in &csv {
                let text = std::fs::read_to_string(path)
                    .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
                rows.extend(
                    pareto_from_csv(&text).map_err(|e| format!("{}: {e}", path.display()))?,
                );
            }
            let front = write_pareto_outputs(&out, &rows)?;
            eprintln!("{}", pareto_markdown(&rows, &front));
            eprintln!("wrote {}", out.join("pareto.png").display());
            Ok(())
        }
        Command::Skips {
            out,
            target,
            preset,
        } => {
            let job = SkipsJob {
                base: Preset::load(&preset)?,
                scenario: target.scenario()?,
                skips: switchable_skips(),
                out_dir: out.clone(),
            };
            let table = run_skips(&job, &mut |line| eprintln!("{line}"))?;
            eprintln!("\n{}", skips_markdown(&table));
            eprintln!("wrote {}", out.join("skips.md").display());
            Ok(())
        }
        Command::AblationWindow {
            out,
            preset,
            windows,
            scenario,
        } => {
            let scenarios = scenarios_or_builtin(&scenario)?;
            let job = WindowJob {
                base: Preset::load(&preset)?,
                scenarios,
                windows,
                out_dir: out.clone(),
            };
            let rows = run_window_ablation(&job, &mut |line| eprintln!("{line}"))?;
            eprintln!("\n{}", window_markdown(&rows));
            eprintln!("wrote {}", out.join("window.md").display());
            Ok(())
        }
        Command::AblationInit {
            preset,
            out,
            scenario,
            inits,
            eval_every,
            hull_views,
            hull_resolution,
            hull_figure_only,
        } => {
            let mut preset = Preset::load(&preset)?;
            preset.eval_every_rounds = eval_every;
            preset.hull_views = hull_views.unwrap_or(preset.hull_views);
            preset.hull_resolution = hull_resolution.unwrap_or(preset.hull_resolution);
            preset.validate()?;
            let scenarios = scenarios_or_builtin(&scenario)?;
            let job = InitAblationJob {
                preset,
                scenarios,
                inits,
                out_dir: out.clone(),
            };
            if hull_figure_only {
                ablation_init::write_hull_figure(&job, &mut |line| eprintln!("{line}"))?;
                eprintln!("wrote {}", out.join("hull.png").display());
                return Ok(());
            }
            let result = run_init_ablation(&job, &mut |line| eprintln!("{line}"))?;
            if job.inits.iter().any(|i| i.starts_with("hull")) {
                ablation_init::write_hull_figure(&job, &mut |line| eprintln!("{line}"))?;
            }
            eprintln!("\n{}", ablation_init::to_markdown(&result.runs));
            eprintln!(
                "{} runs in {:.0} s wall, {:.0} s process CPU (rendering {:.0} s); wrote init.csv, init.md, init_curves.csv, init.png, runs.json (and hull.png) to {}",
                result.runs.len(),
                result.total_s,
                result.total_cpu_s,
                result.render_s,
                out.display()
            );
            Ok(())
        }
        Command::AblationInitPlot { out, runs } => {
            let merged = ablation_init::merge_runs(&runs, &out)?;
            eprintln!("{}", ablation_init::to_markdown(&merged));
            eprintln!(
                "{} runs; wrote init.csv, init.md, init.png to {}",
                merged.len(),
                out.display()
            );
            Ok(())
        }
        Command::ShadowStudy {
            out,
            preset,
            scenario,
            target,
            views,
            cache,
            no_train,
        } => {
            let scenario = match scenario {
                Some(path) => Scenario::load(&path)?,
                None => builtin_scenarios()?
                    .into_iter()
                    .find(|s| s.name == target)
                    .ok_or_else(|| {
                        format!("no built-in target {target:?} (cassini, rosetta, starlink)")
                    })?,
            };
            let job = ShadowStudyJob {
                preset: Preset::load(&preset)?,
                scenario,
                cache_dir: cache.unwrap_or_else(|| out.join("cache")),
                out_dir: out.clone(),
                views,
                train: !no_train,
            };
            let report = run_shadow_study(&job, &mut |line| eprintln!("{line}"))?;
            eprintln!("\n{}", shadow_markdown(&report));
            eprintln!("wrote {}", out.join("shadow_study.md").display());
            Ok(())
        }
        Command::Demo { out } => {
            let (scenario, preset) = demo_inputs()?;
            let preset = with_backend(preset, &backend)?;
            let summary = run_demo_with(&scenario, &preset, &out, &mut |line| eprintln!("{line}"))?;
            let e = &summary.run.eval;
            eprintln!(
                "demo: {} frames of {}x{}, configuration d: {} rounds, {} Gaussians; \
                 evaluation on {} views: PSNR {:.2} dB, SSIM {:.4} (target pixels: {:.2} dB, {:.4}); \
                 {:.0} s in all; wrote renders.png, loss_curve.csv/png, metrics.json, model.ply, \
                 checkpoint.bin to {}",
                summary.frames,
                summary.width,
                summary.height,
                summary.run.rounds,
                summary.run.gaussians,
                e.views,
                e.psnr_db,
                e.ssim,
                e.masked_psnr_db,
                e.masked_ssim,
                summary.total_s,
                out.display()
            );
            Ok(())
        }
    }
}

fn main() {
    // Training steps allocate the same large buffers again and again: keep them mapped
    // (gs_core::heap; same results, less page faulting).
    gs_core::heap::retain_freed_memory();
    let cli = Cli::parse();
    // The main thread and rayon's global pool train and render: both in the denormal mode
    // GS_DENORMALS asks for (default flush-to-zero; gs_core::fpmode), set before any work.
    if let Err(e) = gs_core::fpmode::init_from_env(None) {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
    if let Err(e) = run(cli) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Runs `sim-harness LINE` with `OUT` replaced by `out`.
    fn run_line(line: &str, out: &str) -> Result<(), String> {
        let args = std::iter::once("sim-harness").chain(line.split_whitespace().map(|a| {
            if a == "OUT" {
                out
            } else {
                a
            }
        }));
        let cli = Cli::try_parse_from(args).map_err(|e| e.to_string())?;
        run(cli).map_err(|e| e.to_string())
    }

    /// `--backend` is checked before any work: an unknown name, `wgpu` in a build without
    /// the feature, and the flag on a subcommand that trains nothing are clear errors.
    #[test]
    fn backend_flag_errors_are_clear() {
        let out = std::env::temp_dir().join("sim-harness-backend-flag-test");
        let out = out.to_str().unwrap();
        let e = run_line("--backend cuda demo --out OUT", out).unwrap_err();
        assert!(e.contains("cuda") && e.contains("wgpu"), "{e}");
        if !cfg!(feature = "wgpu") {
            for line in [
                "--backend wgpu demo --out OUT",
                "demo --out OUT --backend wgpu",
                "table --preset cpu --out OUT --backend wgpu",
                "pareto --out OUT --backend wgpu",
            ] {
                let e = run_line(line, out).unwrap_err();
                assert!(e.contains("feature `wgpu`"), "{line}: {e}");
            }
        }
        let e = run_line("--backend cpu buslogs --dataset OUT", out).unwrap_err();
        assert!(e.contains("table, demo and pareto"), "{e}");
        assert!(!Path::new(out).exists(), "an erroring run wrote {out}");
    }
}
