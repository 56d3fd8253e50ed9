//! `sim-harness`: rendezvous simulator command line.
//!
//! `sim-harness generate --scenario FILE --out DIR [--frames N] [--downsample K]
//! [--eval-views N] [--overwrite]` renders a dataset (see `sim_harness::dataset`). Progress goes
//! to stderr; a one-line JSON summary goes to stdout. Errors exit with status 1 and a message
//! naming the bad file, field or value.

use clap::{Parser, Subcommand};
use sim_harness::dataset::{generate, GenerateOptions};
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
    }
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
