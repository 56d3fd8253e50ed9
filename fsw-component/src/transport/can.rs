//! SocketCAN transport over the `socketcan` crate's tokio sockets, classic or FD.
//!
//! Opening checks, in order, that the kernel has CAN sockets, that the interface exists,
//! that it is a CAN interface and (FD mode) that its MTU carries FD frames, so each
//! misconfiguration gets its own [`TransportError`]. Receiving passes on extended-ID data
//! frames only: standard-ID, remote and error frames are dropped and counted (Cyphal uses
//! extended IDs only). A classic transport neither sends nor receives FD frames; an FD
//! transport does both kinds. Counters are atomics, so `&self` can be shared between a
//! receiving task and sending tasks.

use std::fs;
use std::sync::atomic::{AtomicU64, Ordering};

use socketcan::{
    CanAddr, CanAnyFrame, CanDataFrame, CanFdFrame, CanFrame, EmbeddedFrame, ExtendedId, Id, Socket,
};

use super::{RawCanFrame, TransportError};

/// Link type of CAN interfaces in /sys/class/net/IFACE/type (ARPHRD_CAN).
const ARPHRD_CAN: u32 = 280;
/// MTU of an interface that carries CAN FD frames (sizeof(struct canfd_frame)).
const CANFD_MTU_BYTES: u32 = 72;

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
}

#[derive(Default)]
struct CanCounters {
    frames_sent: AtomicU64,
    frames_received: AtomicU64,
    send_errors: AtomicU64,
    dropped_standard_id: AtomicU64,
    dropped_remote: AtomicU64,
    dropped_error_frames: AtomicU64,
}

fn bump(counter: &AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

enum CanSocketKind {
    Classic(socketcan::tokio::CanSocket),
    Fd(socketcan::tokio::CanFdSocket),
}

/// An open raw CAN socket on one interface.
pub struct CanTransport {
    interface: String,
    socket: CanSocketKind,
    counters: CanCounters,
}

impl std::fmt::Debug for CanTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CanTransport")
            .field("interface", &self.interface)
            .field("fd", &self.is_fd())
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
        let open_error = |source| TransportError::Io {
            operation: "open CAN socket",
            target: interface.to_string(),
            source,
        };
        let socket = if config.fd {
            CanSocketKind::Fd(
                socketcan::tokio::CanFdSocket::open_addr(&address).map_err(open_error)?,
            )
        } else {
            CanSocketKind::Classic(
                socketcan::tokio::CanSocket::open_addr(&address).map_err(open_error)?,
            )
        };
        Ok(Self {
            interface: interface.to_string(),
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
        matches!(self.socket, CanSocketKind::Fd(_))
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
        }
    }

    /// Sends one frame; waits while the socket's send buffer is full. Kernel errors (e.g.
    /// ENOBUFS when a real controller's queue is full, ENETDOWN) are returned and counted.
    pub async fn send(&self, frame: &RawCanFrame) -> Result<(), TransportError> {
        let id = Id::Extended(frame_id(frame));
        let result = match (&self.socket, frame.is_fd()) {
            (CanSocketKind::Classic(_), true) => {
                return Err(TransportError::FdFrameOnClassicTransport {
                    interface: self.interface.clone(),
                });
            }
            (CanSocketKind::Classic(socket), false) => {
                socket
                    .write_frame(CanFrame::Data(classic_data_frame(id, frame)?))
                    .await
            }
            (CanSocketKind::Fd(socket), false) => {
                socket.write_frame(&classic_data_frame(id, frame)?).await
            }
            (CanSocketKind::Fd(socket), true) => {
                socket.write_frame(&fd_data_frame(id, frame)?).await
            }
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
        loop {
            let any = match &self.socket {
                CanSocketKind::Classic(socket) => socket.read_frame().await.map(CanAnyFrame::from),
                CanSocketKind::Fd(socket) => socket.read_frame().await,
            }
            .map_err(|source| TransportError::Io {
                operation: "receive CAN frame",
                target: self.interface.clone(),
                source,
            })?;
            if let Some(frame) = self.accept(&any) {
                bump(&self.counters.frames_received);
                return Ok(frame);
            }
        }
    }

    /// The frame as a [`RawCanFrame`] when it is an extended-ID data frame; counts the rest.
    fn accept(&self, any: &CanAnyFrame) -> Option<RawCanFrame> {
        let (id, data, fd) = match any {
            CanAnyFrame::Normal(frame) => (frame.id(), frame.data(), false),
            CanAnyFrame::Fd(frame) => (frame.id(), frame.data(), true),
            CanAnyFrame::Remote(_) => {
                bump(&self.counters.dropped_remote);
                return None;
            }
            CanAnyFrame::Error(_) => {
                bump(&self.counters.dropped_error_frames);
                return None;
            }
        };
        let Id::Extended(id) = id else {
            bump(&self.counters.dropped_standard_id);
            return None;
        };
        // The kernel only hands out frames of valid lengths, so these cannot fail; a frame
        // that did would be dropped as an error frame rather than passed on.
        let frame = if fd {
            RawCanFrame::fd(id.as_raw(), data)
        } else {
            RawCanFrame::classic(id.as_raw(), data)
        };
        match frame {
            Ok(frame) => Some(frame),
            Err(_) => {
                bump(&self.counters.dropped_error_frames);
                None
            }
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
