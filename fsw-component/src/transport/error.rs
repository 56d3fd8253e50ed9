//! The one error type of the transports: each variant says what went wrong and where, so
//! a misconfigured interface or a kernel without CAN is diagnosed from the message alone.

use std::fmt;
use std::io;

/// Why a transport could not be opened, or a frame or datagram could not be moved.
#[derive(Debug)]
pub enum TransportError {
    /// A CAN identifier above 29 bits.
    InvalidCanId { id: u32 },
    /// A data length a CAN frame cannot carry (classic: 0..=8; FD: 0..=8, 12, 16, 20, 24,
    /// 32, 48, 64; padding to a valid FD length is the framing layer's job).
    InvalidCanDataLength { len: usize, fd: bool },
    /// The kernel refuses CAN sockets (no AF_CAN / can-raw), as on hosts without CAN support.
    NoKernelCanSupport {
        interface: String,
        source: io::Error,
    },
    /// No network interface of that name.
    CanInterfaceNotFound {
        interface: String,
        source: io::Error,
    },
    /// The interface exists but is not a CAN interface (its link type is not ARPHRD_CAN).
    NotACanInterface { interface: String, link_type: u32 },
    /// An FD transport was asked for on an interface whose MTU only carries classic frames.
    NotFdCapable { interface: String, mtu_bytes: u32 },
    /// An FD frame was handed to a transport opened in classic mode.
    FdFrameOnClassicTransport { interface: String },
    /// Opening a socket needs a running tokio runtime (its reactor polls the socket).
    NoTokioRuntime,
    /// A datagram larger than the transport's limit was handed over for sending.
    DatagramTooLarge { len: usize, max: usize },
    /// An operating-system error on an open socket or while opening one.
    Io {
        operation: &'static str,
        target: String,
        source: io::Error,
    },
}

impl fmt::Display for TransportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::InvalidCanId { id } => {
                write!(f, "CAN ID {id:#x} does not fit in 29 bits (max 0x1fffffff)")
            }
            Self::InvalidCanDataLength { len, fd: false } => {
                write!(f, "classic CAN frame cannot carry {len} data bytes (max 8)")
            }
            Self::InvalidCanDataLength { len, fd: true } => write!(
                f,
                "CAN FD frame cannot carry {len} data bytes \
                 (valid: 0-8, 12, 16, 20, 24, 32, 48, 64; pad first)"
            ),
            Self::NoKernelCanSupport { interface, source } => write!(
                f,
                "cannot open CAN interface {interface}: this kernel has no SocketCAN \
                 support ({source}); run CAN tests with tests/vcan/run-in-vm.sh"
            ),
            Self::CanInterfaceNotFound { interface, source } => write!(
                f,
                "CAN interface {interface} does not exist ({source}); create it, e.g. \
                 `ip link add dev {interface} type vcan && ip link set up {interface}`"
            ),
            Self::NotACanInterface {
                interface,
                link_type,
            } => write!(
                f,
                "interface {interface} is not a CAN interface (link type {link_type}, CAN is 280)"
            ),
            Self::NotFdCapable {
                interface,
                mtu_bytes,
            } => write!(
                f,
                "interface {interface} has MTU {mtu_bytes}: it carries classic CAN only, \
                 CAN FD needs MTU 72 (`ip link set {interface} mtu 72`)"
            ),
            Self::FdFrameOnClassicTransport { interface } => write!(
                f,
                "cannot send a CAN FD frame on {interface}: the transport was opened in \
                 classic mode"
            ),
            Self::NoTokioRuntime => {
                write!(f, "transport sockets must be opened inside a tokio runtime")
            }
            Self::DatagramTooLarge { len, max } => {
                write!(f, "datagram of {len} bytes exceeds the {max}-byte limit")
            }
            Self::Io {
                operation,
                target,
                source,
            } => write!(f, "{operation} on {target} failed: {source}"),
        }
    }
}

impl std::error::Error for TransportError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::NoKernelCanSupport { source, .. }
            | Self::CanInterfaceNotFound { source, .. }
            | Self::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}
