//! `fsw-component`: runs the flight component live (UDP, and CAN when configured) or replays logs.
//!
//! ```text
//! fsw-component [--config PATH] [--learner sunaware|nearest] [--record DIR]
//! fsw-component [--config PATH] [--learner ...] --replay LOG [--replay LOG ...] [--replay-speed X|max]
//! ```
//! `--learner` picks the model: the Sun-aware online trainer (default) or the
//! nearest-keyframe baseline (cheap and exact, used by the bus tests).
//! Live mode prints one `listening frames=ADDR telemetry=ADDR` line on stdout once the sockets
//! are bound (useful with port 0), then runs until SIGINT or SIGTERM. Replay mode exits when
//! the logs are processed, printing a summary line. `--help` prints the usage and exits 0.
//! Exit status 2 for usage errors (a bad `GS_DENORMALS` or `GS_F32_KERNEL` included), 1 for configuration,
//! transport or replay errors, each with a message on stderr.
//!
//! `GS_DENORMALS=ftz|ieee`, read once at start, overrides `[training] denormals` (the
//! trainer threads' denormal mode, `gs_core::fpmode`), so a measurement can compare the two
//! without editing the config; the override is reported on stderr.

use fsw_component::config::ComponentConfig;
use fsw_component::runtime::{self, LearnerKind, ReplaySpeed};
use gs_core::fpmode::{self, DenormalMode};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

const USAGE: &str = "usage: fsw-component [--config PATH] [--learner sunaware|nearest] \
[--record DIR] [--replay LOG]... [--replay-speed X|max]";

const FLAGS: &str = "
  --config PATH          component configuration (default config/component.toml)
  --learner KIND         sunaware (default: the Sun-aware online trainer) or nearest
                         (the nearest-keyframe baseline)
  --record DIR           record the received bus traffic to DIR (live mode)
  --replay LOG           replay a candump or UDP recording instead of listening (repeatable)
  --replay-speed X|max   replay time scale (default 1; max or 0: as fast as possible)
  -h, --help             this text";

#[derive(Debug)]
struct Options {
    config: PathBuf,
    record: Option<PathBuf>,
    replay: Vec<PathBuf>,
    speed: ReplaySpeed,
    learner: LearnerKind,
    /// `GS_DENORMALS`, when set: replaces `[training] denormals`.
    denormals: Option<DenormalMode>,
}

/// The options, or None for `--help`.
fn parse(args: &[String]) -> Result<Option<Options>, String> {
    let mut options = Options {
        config: PathBuf::from("config/component.toml"),
        record: None,
        replay: Vec::new(),
        speed: ReplaySpeed::Scaled(1.0),
        learner: LearnerKind::SunAware,
        denormals: None,
    };
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = || {
            it.next()
                .cloned()
                .ok_or_else(|| format!("{flag} needs a value"))
        };
        match flag.as_str() {
            "--config" => options.config = value()?.into(),
            "--record" => options.record = Some(value()?.into()),
            "--replay" => options.replay.push(value()?.into()),
            "--replay-speed" => {
                let v = value()?;
                options.speed = match v.as_str() {
                    "max" | "0" => ReplaySpeed::AsFastAsPossible,
                    _ => match v.parse::<f64>() {
                        Ok(x) if x.is_finite() && x > 0.0 => ReplaySpeed::Scaled(x),
                        _ => return Err(format!("--replay-speed {v:?}: want a number > 0 or max")),
                    },
                };
            }
            "--learner" => options.learner = value()?.parse()?,
            "--help" | "-h" => return Ok(None),
            other => return Err(format!("unknown argument {other:?}")),
        }
    }
    if options.record.is_some() && !options.replay.is_empty() {
        return Err("--record and --replay exclude each other".into());
    }
    options.denormals = fpmode::mode_from_env()?;
    // A GS_F32_KERNEL or GS_BF16_KERNEL this CPU cannot run is a usage error now, not at
    // the first round.
    gs_core::nn::check_kernel_env().map_err(|e| e.to_string())?;
    Ok(Some(options))
}

async fn run(options: Options) -> Result<(), String> {
    let mut config = ComponentConfig::load(&options.config).map_err(|e| e.to_string())?;
    if let Some(mode) = options.denormals {
        if config.denormals().map_err(|e| e.to_string())? != mode {
            eprintln!(
                "fsw-component: {}={mode} overrides [training] denormals = {:?}",
                fpmode::ENV_VAR,
                config.training.denormals
            );
        }
        config.training.denormals = mode.name().to_string();
    }
    let learner = runtime::build_learner(&config, options.learner).map_err(|e| e.to_string())?;
    if !options.replay.is_empty() {
        let summary = runtime::run_replay(&config, learner, &options.replay, options.speed)
            .await
            .map_err(|e| e.to_string())?;
        println!(
            "replayed datagrams={} can_frames={} frames_received={} frames_used={} rounds={} predictions={}",
            summary.load.datagrams,
            summary.load.can_frames,
            summary.counters.bus.frames_received,
            summary.frames_used,
            summary.rounds,
            summary.predictions_sent
        );
        return Ok(());
    }
    let handle = runtime::start(&config, learner, options.record)
        .await
        .map_err(|e| e.to_string())?;
    println!(
        "listening frames={} telemetry={}",
        handle.frames_addr, handle.telemetry_addr
    );
    let _ = std::io::stdout().flush();
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| format!("install SIGTERM handler: {e}"))?;
    tokio::select! {
        _ = tokio::signal::ctrl_c() => {}
        _ = terminate.recv() => {}
    }
    handle.shutdown().await;
    Ok(())
}

fn main() -> ExitCode {
    // Training steps allocate the same large buffers again and again: keep them mapped
    // (gs_core::heap; same results, less page faulting, memory held at its high-water
    // mark instead of churning).
    gs_core::heap::retain_freed_memory();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let options = match parse(&args) {
        Ok(Some(o)) => o,
        Ok(None) => {
            println!(
                "{USAGE}\n{FLAGS}\n\n{}\n{:25}(overrides [training] denormals)",
                fpmode::ENV_HELP,
                ""
            );
            return ExitCode::SUCCESS;
        }
        Err(why) => {
            eprintln!("fsw-component: {why}");
            eprintln!("{USAGE}");
            return ExitCode::from(2);
        }
    };
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("fsw-component: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(options)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(why) => {
            eprintln!("fsw-component: {why}");
            ExitCode::FAILURE
        }
    }
}
