//! SocketCAN transport: `socketcan` sockets (classic or FD) driven by tokio's `AsyncFd`.
//!
//! Opening checks, in order, that the kernel has CAN sockets, that the interface exists,
//! that it is a CAN interface and (FD mode) that its MTU carries FD frames, so each
//! misconfiguration gets its own [`TransportError`]. Receiving passes on extended-ID data
//! frames only: standard-ID, remote and error frames are dropped and counted (Cyphal uses
//! extended IDs only), and frames the kernel dropped on a full receive queue are counted
//! too (SO_RXQ_OVFL, see `can_recv`), so nothing is lost silently. A classic transport
//! neither sends nor receives FD frames; an FD transport does both kinds. Counters are
//! atomics, so `&self` can be shared between a receiving task and sending tasks.

use std::fs;
use std::os::fd::{AsRawFd, RawFd};
use std::sync::atomic::{AtomicU64, Ordering};

use socketcan::{
    CanAddr, CanDataFrame, CanFdFrame, CanFrame, EmbeddedFrame, ExtendedId, Id, Socket,
};
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

use super::can_recv::{self, Received};
use super::{sockopt, RawCanFrame, TransportError};

/// Link type of CAN interfaces in /sys/class/net/IFACE/type (ARPHRD_CAN).
const ARPHRD_CAN: u32 = 280;
/// MTU of an interface that carries CAN FD frames (sizeof(struct canfd_frame)).
const CANFD_MTU_BYTES: u32 = can_recv::CANFD_MTU_BYTES as u32;

/// Which interface to open, and whether to use CAN FD.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CanTransportConfig {
    /// Network interface name, e.g. "can0" or "vcan0".
    pub interface: String,
    /// Open an FD socket (sends and receives classic and FD frames; needs MTU 72).
    pub fd: bool,
}

/// Counters of one CAN transport since it was opened.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CanStats {
    pub frames_sent: u64,
    pub frames_received: u64,
    pub send_errors: u64,
    pub dropped_standard_id: u64,
    pub dropped_remote: u64,
    pub dropped_error_frames: u64,
    /// Reads no kernel frame has the shape of (never seen in practice; counted, not trusted).
    pub dropped_malformed: u64,
    /// Frames the kernel dropped because this socket's receive queue was full, as reported
    /// with the next frame received (SO_RXQ_OVFL).
    pub dropped_receive_queue_full: u64,
}

#[derive(Default)]
struct CanCounters {
    frames_sent: AtomicU64,
    frames_received: AtomicU64,
    send_errors: AtomicU64,
    dropped_standard_id: AtomicU64,
    dropped_remote: AtomicU64,
    dropped_error_frames: AtomicU64,
    dropped_malformed: AtomicU64,
    dropped_receive_queue_full: AtomicU64,
}

fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

/// The blocking-API socket from `socketcan`, driven non-blocking through tokio's `AsyncFd`.
enum SyncSocket {
    Classic(socketcan::CanSocket),
    Fd(socketcan::CanFdSocket),
}

impl AsRawFd for SyncSocket {
    fn as_raw_fd(&self) -> RawFd {
        match self {
            Self::Classic(socket) => socket.as_raw_fd(),
            Self::Fd(socket) => socket.as_raw_fd(),
        }
    }
}

/// An open raw CAN socket on one interface.
pub struct CanTransport {
    interface: String,
    fd_mode: bool,
    socket: AsyncFd<SyncSocket>,
    counters: CanCounters,
}

impl std::fmt::Debug for CanTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CanTransport")
            .field("interface", &self.interface)
            .field("fd", &self.fd_mode)
            .field("stats", &self.stats())
            .finish()
    }
}

/// Reads a number from /sys/class/net/IFACE/FILE; `None` when sysfs does not have it.
fn read_sysfs_number(interface: &str, file: &str) -> Option<u32> {
    let text = fs::read_to_string(format!("/sys/class/net/{interface}/{file}")).ok()?;
    text.trim().parse().ok()
}

impl CanTransport {
    /// Opens a raw CAN socket on `config.interface`. Must be called inside a tokio runtime.
    pub fn open(config: &CanTransportConfig) -> Result<Self, TransportError> {
        let interface = config.interface.as_str();
        if tokio::runtime::Handle::try_current().is_err() {
            return Err(TransportError::NoTokioRuntime);
        }
        // Bound to "any interface" (index 0): fails only when the kernel has no CAN sockets.
        if let Err(source) = socketcan::CanSocket::open_addr(&CanAddr::new(0)) {
            return Err(TransportError::NoKernelCanSupport {
                interface: interface.to_string(),
                source,
            });
        }
        let address = CanAddr::from_iface(interface).map_err(|source| {
            TransportError::CanInterfaceNotFound {
                interface: interface.to_string(),
                source,
            }
        })?;
        if let Some(link_type) = read_sysfs_number(interface, "type") {
            if link_type != ARPHRD_CAN {
                return Err(TransportError::NotACanInterface {
                    interface: interface.to_string(),
                    link_type,
                });
            }
        }
        if config.fd {
            if let Some(mtu_bytes) = read_sysfs_number(interface, "mtu") {
                if mtu_bytes < CANFD_MTU_BYTES {
                    return Err(TransportError::NotFdCapable {
                        interface: interface.to_string(),
                        mtu_bytes,
                    });
                }
            }
        }
        let io_error = |operation| {
            move |source| TransportError::Io {
                operation,
                target: interface.to_string(),
                source,
            }
        };
        let socket = if config.fd {
            SyncSocket::Fd(
                socketcan::CanFdSocket::open_addr(&address).map_err(io_error("open CAN socket"))?,
            )
        } else {
            SyncSocket::Classic(
                socketcan::CanSocket::open_addr(&address).map_err(io_error("open CAN socket"))?,
            )
        };
        match &socket {
            SyncSocket::Classic(inner) => inner.set_nonblocking(true),
            SyncSocket::Fd(inner) => inner.set_nonblocking(true),
        }
        .map_err(io_error("make CAN socket non-blocking"))?;
        can_recv::enable_drop_count(socket.as_raw_fd())
            .map_err(io_error("enable SO_RXQ_OVFL on CAN socket"))?;
        // SAFETY: `SyncSocket` owns its file descriptor for its whole life and `as_raw_fd`
        // always returns that same descriptor, as `register` requires.
        let socket = unsafe { AsyncFd::register(socket) }
            .map_err(|error| io_error("register CAN socket with tokio")(error.into_parts().1))?;
        Ok(Self {
            interface: interface.to_string(),
            fd_mode: config.fd,
            socket,
            counters: CanCounters::default(),
        })
    }

    /// The interface this transport is bound to.
    pub fn interface(&self) -> &str {
        &self.interface
    }

    /// Whether this transport was opened in FD mode.
    pub fn is_fd(&self) -> bool {
        self.fd_mode
    }

    /// Asks for a kernel receive buffer of `bytes` and returns the size granted (Linux
    /// reports twice the request; without CAP_NET_ADMIN it is capped at net.core.rmem_max).
    pub fn set_receive_buffer_bytes(&self, bytes: usize) -> Result<usize, TransportError> {
        sockopt::set_receive_buffer(self.socket.as_raw_fd(), bytes).map_err(|source| {
            TransportError::Io {
                operation: "set CAN receive buffer size",
                target: self.interface.clone(),
                source,
            }
        })
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> CanStats {
        let c = &self.counters;
        CanStats {
            frames_sent: c.frames_sent.load(Ordering::Relaxed),
            frames_received: c.frames_received.load(Ordering::Relaxed),
            send_errors: c.send_errors.load(Ordering::Relaxed),
            dropped_standard_id: c.dropped_standard_id.load(Ordering::Relaxed),
            dropped_remote: c.dropped_remote.load(Ordering::Relaxed),
            dropped_error_frames: c.dropped_error_frames.load(Ordering::Relaxed),
            dropped_malformed: c.dropped_malformed.load(Ordering::Relaxed),
            dropped_receive_queue_full: c.dropped_receive_queue_full.load(Ordering::Relaxed),
        }
    }

    /// Sends one frame; waits while the socket's send buffer is full. Kernel errors (e.g.
    /// ENOBUFS when a real controller's queue is full, ENETDOWN) are returned and counted.
    pub async fn send(&self, frame: &RawCanFrame) -> Result<(), TransportError> {
        if frame.is_fd() && !self.fd_mode {
            return Err(TransportError::FdFrameOnClassicTransport {
                interface: self.interface.clone(),
            });
        }
        let id = Id::Extended(frame_id(frame));
        let result = if frame.is_fd() {
            let fd_frame = fd_data_frame(id, frame)?;
            self.socket
                .async_io(Interest::WRITABLE, |socket| match socket {
                    SyncSocket::Fd(inner) => inner.write_frame(&fd_frame),
                    // Refused above: an FD frame never reaches a classic socket.
                    SyncSocket::Classic(_) => Err(std::io::ErrorKind::Unsupported.into()),
                })
                .await
        } else {
            let classic_frame = classic_data_frame(id, frame)?;
            self.socket
                .async_io(Interest::WRITABLE, |socket| match socket {
                    SyncSocket::Classic(inner) => inner.write_frame(&CanFrame::Data(classic_frame)),
                    SyncSocket::Fd(inner) => inner.write_frame(&classic_frame),
                })
                .await
        };
        match result {
            Ok(()) => {
                bump(&self.counters.frames_sent);
                Ok(())
            }
            Err(source) => {
                bump(&self.counters.send_errors);
                Err(TransportError::Io {
                    operation: "send CAN frame",
                    target: self.interface.clone(),
                    source,
                })
            }
        }
    }

    /// Waits for the next extended-ID data frame, dropping (and counting) anything else.
    pub async fn recv(&self) -> Result<RawCanFrame, TransportError> {
        let mut buffer = [0u8; can_recv::CANFD_MTU_BYTES];
        loop {
            let (len, drops_total) = self
                .socket
                .async_io(Interest::READABLE, |socket| {
                    can_recv::recv_frame(socket.as_raw_fd(), &mut buffer)
                })
                .await
                .map_err(|source| TransportError::Io {
                    operation: "receive CAN frame",
                    target: self.interface.clone(),
                    source,
                })?;
            if let Some(total) = drops_total {
                // The kernel's count is cumulative per socket; concurrent readers may see
                // them out of order, so keep the largest.
                self.counters
                    .dropped_receive_queue_full
                    .fetch_max(u64::from(total), Ordering::Relaxed);
            }
            let counter = match can_recv::parse_frame(&buffer[..len]) {
                Received::Frame(frame) => {
                    bump(&self.counters.frames_received);
                    return Ok(frame);
                }
                Received::StandardId => &self.counters.dropped_standard_id,
                Received::Remote => &self.counters.dropped_remote,
                Received::ErrorFrame => &self.counters.dropped_error_frames,
                Received::Malformed => &self.counters.dropped_malformed,
            };
            bump(counter);
        }
    }
}

fn frame_id(frame: &RawCanFrame) -> ExtendedId {
    // RawCanFrame guarantees the ID fits in 29 bits; ZERO is unreachable but keeps this total.
    ExtendedId::new(frame.id()).unwrap_or(ExtendedId::ZERO)
}

fn classic_data_frame(id: Id, frame: &RawCanFrame) -> Result<CanDataFrame, TransportError> {
    CanDataFrame::new(id, frame.data()).ok_or(TransportError::InvalidCanDataLength {
        len: frame.data().len(),
        fd: false,
    })
}

fn fd_data_frame(id: Id, frame: &RawCanFrame) -> Result<CanFdFrame, TransportError> {
    CanFdFrame::new(id, frame.data()).ok_or(TransportError::InvalidCanDataLength {
        len: frame.data().len(),
        fd: true,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(interface: &str, fd: bool) -> CanTransportConfig {
        CanTransportConfig {
            interface: interface.to_string(),
            fd,
        }
    }

    #[test]
    fn opening_outside_a_runtime_is_an_error_not_a_panic() {
        let error = CanTransport::open(&config("vcan0", false)).unwrap_err();
        assert!(matches!(error, TransportError::NoTokioRuntime), "{error}");
    }

    #[tokio::test]
    async fn a_missing_interface_is_diagnosed() {
        // Whether or not this kernel has CAN, an interface that does not exist must fail with
        // one of the two diagnoses, never with a generic I/O error.
        let error = CanTransport::open(&config("nosuchcan9", true)).unwrap_err();
        assert!(
            matches!(
                error,
                TransportError::NoKernelCanSupport { .. }
                    | TransportError::CanInterfaceNotFound { .. }
            ),
            "{error}"
        );
        assert!(error.to_string().contains("nosuchcan9"), "{error}");
    }

    #[tokio::test]
    async fn a_non_can_interface_is_refused() {
        let error = CanTransport::open(&config("lo", false)).unwrap_err();
        assert!(
            matches!(
                error,
                TransportError::NoKernelCanSupport { .. }
                    | TransportError::NotACanInterface { link_type: 772, .. }
            ),
            "{error}"
        );
    }
}
