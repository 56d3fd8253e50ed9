//! Traffic logs: candump .log text for CAN, a datagram recording for UDP.
//!
//! - [`candump`]: the can-utils log line `(1700000000.000000) vcan0 1A2B3C4D#0011...`
//!   (classic, remote, CAN FD `##<flags><data>`, error frames, optional ` R`/` T`
//!   direction as python-can and `candump -x` write it). Reader and writer.
//! - [`udprec`]: a small binary recording of UDP datagrams (time, ports, bytes).
//!
//! Both readers bound the memory a malformed input can make them use, report bad input
//! with its position (line number or byte offset), and never panic.

pub mod candump;
pub mod udprec;
