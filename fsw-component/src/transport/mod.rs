//! Bus transports: SocketCAN (classic and FD) and UDP sockets, frame level only.
//!
//! These move raw CAN frames (29-bit extended ID, data, FD flag) and raw UDP datagrams
//! (at most [`udp::MAX_DATAGRAM_BYTES`]); the Cyphal/CAN and CCSDS framing on top of them
//! lives in the `interfaces` crate. Invariants: nothing here panics on bus input; every
//! frame or datagram that is not passed on is counted in the transport's stats; every
//! failure is a [`TransportError`] that names the interface or socket it happened on.

pub mod can;
pub mod can_frame;
mod can_recv;
mod error;
mod sockopt;
pub mod udp;

pub use can::{CanStats, CanTransport, CanTransportConfig};
pub use can_frame::RawCanFrame;
pub use error::TransportError;
pub use udp::{UdpStats, UdpTransport, MAX_DATAGRAM_BYTES};
