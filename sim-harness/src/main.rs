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
//! README's demo (see `sim_harness::experiment::demo`).

use clap::{Parser, Subcommand};
use sim_harness::dataset::{generate, GenerateOptions};
use sim_harness::experiment::demo::run_demo;
use sim_harness::experiment::preset::Preset;
use sim_harness::experiment::table::to_markdown;
use sim_harness::experiment::table_job::{builtin_scenarios, run_table, TableJob};
use sim_harness::scenario::Scenario;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "sim-harness",
    about = "Rendezvous simulator with ray-traced ground truth"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
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
    /// Train configuration d online on a small embedded Cassini-like scenario.
    Demo {
        /// Output folder.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
    },
}

fn run(cli: Cli) -> Result<(), Box<dyn std::error::Error>> {
    match cli.command {
        Command::Generate {
            scenario,
            out,
            frames,
            downsample,
            eval_views,
            overwrite,
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
            Ok(())
        }
        Command::Table {
            preset,
            out,
            scenario,
            keep_data,
        } => {
            let preset = Preset::load(&preset)?;
            let scenarios = if scenario.is_empty() {
                builtin_scenarios()?
            } else {
                scenario
                    .iter()
                    .map(|p| Scenario::load(p))
                    .collect::<Result<_, _>>()?
            };
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
        Command::Demo { out } => {
            let summary = run_demo(&out, &mut |line| eprintln!("{line}"))?;
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
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
