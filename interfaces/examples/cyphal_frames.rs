//! Command-line bridge between our Cyphal/CAN framing and text, used by the interoperability
//! tests in `tests/interop/` (pycyphal on the other side) and handy for looking at frames.
//!
//! `cyphal_frames encode --subject S --node N --tid T [--priority P] [--mtu 8|64] --payload HEX`
//!   prints the transfer's frames, one per line, in cansend/candump notation:
//!   `IIIIIIII#DATA` (classic) or `IIIIIIII##0DATA` (CAN FD, flags nibble 0).
//! `cyphal_frames decode`
//!   reads frames from stdin, one per line, in the same notation or as candump log lines
//!   `(1700000000.000000) vcan0 IIIIIIII#DATA` (the timestamp is then used; 3-digit IDs are
//!   standard frames, counted and rejected), reassembles them
//!   and prints `TRANSFER subject=S source=N tid=T payload=HEX` per completed transfer,
//!   `REJECT line=L reason=R` per rejected frame and a final `COUNTERS frames=F transfers=T
//!   rejected=R` line.
//!
//! Exit status 2 on bad arguments or unparsable input lines.

use interfaces::cyphal::{transfer_frames, CanReassembler, Mtu, Priority, TransferHeader};
use std::io::{self, BufRead, Write};
use std::process::ExitCode;

fn hex_decode(text: &str) -> Result<Vec<u8>, String> {
    if !text.len().is_multiple_of(2) {
        return Err(format!("odd number of hex digits in {text:?}"));
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).map_err(|e| format!("{text:?}: {e}")))
        .collect()
}

fn hex_encode(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02X}")).collect()
}

fn arg<'a>(args: &'a [String], name: &str) -> Option<&'a str> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(String::as_str)
}

fn parse_num<T: std::str::FromStr>(
    args: &[String],
    name: &str,
    default: Option<T>,
) -> Result<T, String> {
    match arg(args, name) {
        Some(v) => v.parse().map_err(|_| format!("{name}: cannot parse {v:?}")),
        None => default.ok_or(format!("{name} is required")),
    }
}

fn encode(args: &[String]) -> Result<(), String> {
    let header = TransferHeader {
        priority: Priority::from_bits(parse_num(args, "--priority", Some(4u8))?),
        subject_id: parse_num(args, "--subject", None)?,
        source_node_id: parse_num(args, "--node", None)?,
        transfer_id: parse_num(args, "--tid", None)?,
    };
    let mtu = match parse_num(args, "--mtu", Some(8usize))? {
        8 => Mtu::Classic,
        64 => Mtu::Fd,
        other => return Err(format!("--mtu must be 8 or 64, not {other}")),
    };
    let payload = hex_decode(arg(args, "--payload").unwrap_or(""))?;
    let frames = transfer_frames(&header, &payload, mtu).map_err(|e| e.to_string())?;
    let mut out = io::stdout().lock();
    for f in frames {
        let sep = if f.is_fd { "##0" } else { "#" };
        writeln!(out, "{:08X}{sep}{}", f.id, hex_encode(&f.data)).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// (timestamp_us, is_extended, can_id, data) from one text line. As in candump, an ID of 8
/// hex digits is extended (29-bit), of 3 digits standard (11-bit).
fn parse_line(line: &str, line_no: u64) -> Result<(u64, bool, u32, Vec<u8>), String> {
    let tokens: Vec<&str> = line.split_whitespace().collect();
    let frame = tokens
        .iter()
        .rev()
        .find(|t| t.contains('#'))
        .ok_or(format!("line {line_no}: no ID#DATA token"))?;
    let timestamp_us = match tokens.first() {
        Some(t) if t.starts_with('(') && t.ends_with(')') => {
            let seconds: f64 = t[1..t.len() - 1]
                .parse()
                .map_err(|_| format!("line {line_no}: bad timestamp {t}"))?;
            (seconds * 1e6).round() as u64
        }
        _ => line_no * 1000,
    };
    let (id_text, rest) = frame.split_once('#').unwrap_or((frame, ""));
    let data_text = match rest.strip_prefix('#') {
        Some(fd) => fd.get(1..).unwrap_or(""),
        None => rest,
    };
    let id = u32::from_str_radix(id_text, 16)
        .map_err(|_| format!("line {line_no}: bad ID {id_text}"))?;
    Ok((timestamp_us, id_text.len() > 3, id, hex_decode(data_text)?))
}

fn decode() -> Result<(), String> {
    let mut rx: CanReassembler<Vec<u8>, 64> = CanReassembler::new(vec![0u8; 64 * 8192]);
    let mut out = io::stdout().lock();
    for (index, line) in io::stdin().lock().lines().enumerate() {
        let line = line.map_err(|e| e.to_string())?;
        if line.trim().is_empty() {
            continue;
        }
        let line_no = index as u64 + 1;
        let (timestamp_us, is_extended, id, data) = parse_line(&line, line_no)?;
        let text = match rx.push_frame(is_extended, id, &data, timestamp_us) {
            Ok(Some(t)) => format!(
                "TRANSFER subject={} source={} tid={} payload={}",
                t.subject_id,
                t.source_node_id
                    .map_or("anonymous".to_string(), |n| n.to_string()),
                t.transfer_id,
                hex_encode(t.payload)
            ),
            Ok(None) => continue,
            Err(e) => format!("REJECT line={line_no} reason={e:?}"),
        };
        writeln!(out, "{text}").map_err(|e| e.to_string())?;
    }
    let c = rx.counters();
    writeln!(
        out,
        "COUNTERS frames={} transfers={} rejected={}",
        c.frames,
        c.transfers,
        c.rejected_total()
    )
    .map_err(|e| e.to_string())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("encode") => encode(&args[1..]),
        Some("decode") => decode(),
        _ => Err("usage: cyphal_frames encode --subject S --node N --tid T [--priority P] [--mtu 8|64] --payload HEX | cyphal_frames decode < frames".to_string()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("cyphal_frames: {message}");
            ExitCode::from(2)
        }
    }
}
