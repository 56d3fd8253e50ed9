//! Command-line face of the component's Cyphal node code (`fsw_component::node`), used by
//! the pycyphal interoperability test `tests/interop/test_cyphal_node.py`: it runs the very
//! code the live component runs for the Heartbeat and the GetInfo server, without a CAN
//! interface, with frames as text in cansend notation (`IIIIIIII#DATA`, FD `IIIIIIII##0DATA`).
//!
//! `cyphal_node heartbeat --node N [--mtu 8|64] [--mode idle|train|predict] [--uptime U]
//!   [--count K] [--dropped-per-beat D] [--trainer ok|restarting|gave-up]`
//!   prints K heartbeats' frames, one line each, the first followed by the port.List frames;
//!   heartbeat k has uptime U + k and D * k dropped frames (so with D > 0 every heartbeat
//!   after the first is ADVISORY).
//! `cyphal_node serve --node N [--mtu 8|64] [--name NAME] [--unique-id HEX32]`
//!   reads request frames from stdin, one per line, and prints for each either the response
//!   frames on one line separated by spaces, `PENDING` (a frame of a multi-frame request
//!   not yet complete), or `IGNORED` (not a request this node answers).
//!
//! Both take `--config FILE`: a component.toml whose `[cyphal]` subject-IDs the port list
//! announces and whose registers (with its register file, read at start and written by
//! register Access requests) the node serves, as the live component does; without it, the
//! default configuration's (registers read-only). `--node` defaults to the file's node-ID.
//!
//! Exit status 2 on bad arguments or unparsable lines.

use fsw_component::config::ComponentConfig;
use fsw_component::node::{
    parse_unique_id, software_version, CyphalNode, NodeIdentity, NodeStatus,
};
use fsw_component::registers::Registers;
use fsw_component::transport::RawCanFrame;
use interfaces::cyphal::service_rx::{ServiceRequestRx, ServiceRxError};
use interfaces::messages::Mode;
use std::io::{self, BufRead};
use std::process::ExitCode;

fn arg<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

fn num<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> Result<T, String> {
    match arg(args, name) {
        Some(v) => v.parse().map_err(|_| format!("{name}: cannot parse {v:?}")),
        None => Ok(default),
    }
}

fn format_frame(frame: &RawCanFrame) -> String {
    let data: String = frame.data().iter().map(|b| format!("{b:02X}")).collect();
    let sep = if frame.is_fd() { "##0" } else { "#" };
    format!("{:08X}{sep}{data}", frame.id())
}

fn parse_line(line: &str) -> Result<(u32, Vec<u8>), String> {
    let (id, rest) = line
        .trim()
        .split_once('#')
        .ok_or(format!("no '#' in {line:?}"))?;
    let hex = rest.strip_prefix("#0").unwrap_or(rest);
    let id = u32::from_str_radix(id, 16).map_err(|e| format!("{id:?}: {e}"))?;
    if !hex.len().is_multiple_of(2) {
        return Err(format!("odd hex length in {line:?}"));
    }
    let data = (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).map_err(|e| format!("{hex:?}: {e}")))
        .collect::<Result<_, _>>()?;
    Ok((id, data))
}

fn node(args: &[String]) -> Result<CyphalNode, String> {
    let config = match arg(args, "--config") {
        Some(path) => {
            ComponentConfig::load(std::path::Path::new(path)).map_err(|e| e.to_string())?
        }
        None => ComponentConfig::default(),
    };
    let unique_id = match arg(args, "--unique-id") {
        Some(text) => parse_unique_id(text).ok_or("--unique-id: not 32 hex digits")?,
        None => [0; 16],
    };
    let fd = match num(args, "--mtu", 8usize)? {
        8 => false,
        64 => true,
        other => return Err(format!("--mtu {other}: 8 or 64")),
    };
    Ok(CyphalNode::new(
        num(args, "--node", config.node.node_id)?,
        fd,
        NodeIdentity {
            name: arg(args, "--name")
                .unwrap_or(fsw_component::node::DEFAULT_NODE_NAME)
                .to_string(),
            unique_id,
            software_version: software_version(),
            software_vcs_revision_id: 0,
        },
    )
    .with_subjects(&config.cyphal.subjects)
    .with_registers(Registers::new(&config)))
}

fn heartbeat(args: &[String]) -> Result<(), String> {
    let mut node = node(args)?;
    let mode = match arg(args, "--mode").unwrap_or("train") {
        "idle" => Mode::Idle,
        "train" => Mode::Train,
        "predict" => Mode::PredictOnly,
        other => return Err(format!("--mode {other}: idle, train or predict")),
    };
    match arg(args, "--trainer").unwrap_or("ok") {
        "ok" => {}
        "restarting" => node.trainer_faulted(false),
        "gave-up" => node.trainer_faulted(true),
        other => return Err(format!("--trainer {other}: ok, restarting or gave-up")),
    }
    let uptime_s: u32 = num(args, "--uptime", 0)?;
    let dropped: u32 = num(args, "--dropped-per-beat", 0)?;
    for k in 0..num(args, "--count", 1u32)? {
        let beat = node.heartbeat(&NodeStatus {
            mode,
            uptime_s: uptime_s + k,
            frames_dropped: dropped * k,
            decode_errors: 0,
            crc_errors: 0,
            send_errors: 0,
        });
        for frame in node.heartbeat_frames(&beat) {
            println!("{}", format_frame(&frame));
        }
    }
    Ok(())
}

fn serve(args: &[String]) -> Result<(), String> {
    let mut node = node(args)?;
    let mut requests = ServiceRequestRx::<_, 4>::new(vec![0u8; 4 * 1024]);
    let started = std::time::Instant::now();
    for line in io::stdin().lock().lines() {
        let line = line.map_err(|e| e.to_string())?;
        if line.trim().is_empty() {
            continue;
        }
        let (id, data) = parse_line(&line)?;
        let answer = match requests.push(
            id,
            &data,
            node.node_id(),
            started.elapsed().as_micros() as u64,
        ) {
            Ok(Some(request)) => node.answer(&request),
            Ok(None) => {
                println!("PENDING");
                continue;
            }
            Err(ServiceRxError::NotOurs(_) | ServiceRxError::Rejected(_)) => None,
        };
        match answer {
            Some(frames) => {
                let text: Vec<String> = frames.iter().map(format_frame).collect();
                println!("{}", text.join(" "));
            }
            None => println!("IGNORED"),
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("heartbeat") => heartbeat(&args),
        Some("serve") => serve(&args),
        _ => Err("usage: cyphal_node heartbeat|serve [options] (see the source header)".into()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(why) => {
            eprintln!("cyphal_node: {why}");
            ExitCode::from(2)
        }
    }
}
