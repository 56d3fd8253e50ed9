//! UDP transport: one tokio socket, datagrams of at most [`MAX_DATAGRAM_BYTES`].
//!
//! 1472 bytes is what fits in one Ethernet frame (1500 MTU - 20 IP - 8 UDP), so no
//! datagram is ever IP-fragmented. Sending more is refused with an error; a received
//! datagram above the limit is dropped and counted (it is read into a buffer one byte
//! larger than the limit, so "filled the whole buffer" means "oversize"; the kernel
//! truncates the rest). Datagrams the kernel dropped because the receive buffer was full
//! are read from the socket's row in /proc/net/udp{,6}; grow the buffer with
//! [`UdpTransport::set_receive_buffer_bytes`] for bursts such as camera frames. Counters
//! are atomics so `&self` can be shared between tasks.

use std::net::SocketAddr;
use std::os::fd::AsRawFd;
use std::sync::atomic::{AtomicU64, Ordering};

use tokio::net::UdpSocket;

use super::{sockopt, TransportError};

/// Reads of /proc/net/udp before the kernel drop count is given up as unknown.
const KERNEL_TABLE_READS: usize = 4;

/// Largest datagram payload sent or accepted, in bytes.
pub const MAX_DATAGRAM_BYTES: usize = 1472;

/// Counters of one UDP transport since it was bound.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UdpStats {
    pub datagrams_sent: u64,
    pub datagrams_received: u64,
    pub bytes_received: u64,
    pub send_errors: u64,
    pub oversize_send_rejected: u64,
    pub oversize_received_dropped: u64,
    /// Datagrams the kernel dropped on a full receive buffer (the socket's `drops` in
    /// /proc/net/udp); `None` when that table cannot be read here.
    pub dropped_receive_queue_full: Option<u64>,
}

#[derive(Debug, Default)]
struct UdpCounters {
    datagrams_sent: AtomicU64,
    datagrams_received: AtomicU64,
    bytes_received: AtomicU64,
    send_errors: AtomicU64,
    oversize_send_rejected: AtomicU64,
    oversize_received_dropped: AtomicU64,
}

fn add(counter: &AtomicU64, amount: u64) {
    counter.fetch_add(amount, Ordering::Relaxed);
}

/// A bound UDP socket.
#[derive(Debug)]
pub struct UdpTransport {
    socket: UdpSocket,
    local_addr: SocketAddr,
    socket_inode: Option<u64>,
    counters: UdpCounters,
}

impl UdpTransport {
    /// Binds to `address` (port 0 picks a free port; see [`Self::local_addr`]).
    pub async fn bind(address: SocketAddr) -> Result<Self, TransportError> {
        if tokio::runtime::Handle::try_current().is_err() {
            return Err(TransportError::NoTokioRuntime);
        }
        let io_error = |operation| {
            move |source| TransportError::Io {
                operation,
                target: address.to_string(),
                source,
            }
        };
        let socket = UdpSocket::bind(address)
            .await
            .map_err(io_error("bind UDP socket"))?;
        let local_addr = socket
            .local_addr()
            .map_err(io_error("read local address of UDP socket"))?;
        Ok(Self {
            socket_inode: sockopt::socket_inode(socket.as_raw_fd()),
            socket,
            local_addr,
            counters: UdpCounters::default(),
        })
    }

    /// The address actually bound (with the port the kernel picked for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// Asks for a kernel receive buffer of `bytes` and returns the size granted (Linux
    /// reports twice the request; without CAP_NET_ADMIN it is capped at net.core.rmem_max).
    pub fn set_receive_buffer_bytes(&self, bytes: usize) -> Result<usize, TransportError> {
        sockopt::set_receive_buffer(self.socket.as_raw_fd(), bytes).map_err(|source| {
            TransportError::Io {
                operation: "set UDP receive buffer size",
                target: self.local_addr.to_string(),
                source,
            }
        })
    }

    /// The kernel receive buffer size in bytes.
    pub fn receive_buffer_bytes(&self) -> Result<usize, TransportError> {
        sockopt::receive_buffer(self.socket.as_raw_fd()).map_err(|source| TransportError::Io {
            operation: "read UDP receive buffer size",
            target: self.local_addr.to_string(),
            source,
        })
    }

    /// The kernel's count of datagrams dropped on this socket's full receive queue, from
    /// the socket's row of /proc/net/udp(6); `None` where that row cannot be read.
    fn kernel_drops(&self) -> Option<u64> {
        let table_path = if self.local_addr.is_ipv6() {
            "/proc/net/udp6"
        } else {
            "/proc/net/udp"
        };
        let inode = self.socket_inode?;
        // The kernel writes the table a page per read() while sockets come and go, so a
        // concurrent close can shift the listing and skip our row in one read (seen once in
        // CI with the tests' sockets opening and closing in parallel): read it again.
        (0..KERNEL_TABLE_READS).find_map(|_| {
            let table = std::fs::read_to_string(table_path).ok()?;
            sockopt::drops_from_proc_table(&table, inode)
        })
    }

    /// A snapshot of the counters (reads /proc for the kernel's drop count).
    pub fn stats(&self) -> UdpStats {
        let c = &self.counters;
        UdpStats {
            datagrams_sent: c.datagrams_sent.load(Ordering::Relaxed),
            datagrams_received: c.datagrams_received.load(Ordering::Relaxed),
            bytes_received: c.bytes_received.load(Ordering::Relaxed),
            send_errors: c.send_errors.load(Ordering::Relaxed),
            oversize_send_rejected: c.oversize_send_rejected.load(Ordering::Relaxed),
            oversize_received_dropped: c.oversize_received_dropped.load(Ordering::Relaxed),
            dropped_receive_queue_full: self.kernel_drops(),
        }
    }

    /// Sends `payload` as one datagram to `destination`.
    pub async fn send_to(
        &self,
        payload: &[u8],
        destination: SocketAddr,
    ) -> Result<(), TransportError> {
        if payload.len() > MAX_DATAGRAM_BYTES {
            add(&self.counters.oversize_send_rejected, 1);
            return Err(TransportError::DatagramTooLarge {
                len: payload.len(),
                max: MAX_DATAGRAM_BYTES,
            });
        }
        let send_error = |source| TransportError::Io {
            operation: "send UDP datagram",
            target: destination.to_string(),
            source,
        };
        match self.socket.send_to(payload, destination).await {
            Ok(sent) if sent == payload.len() => {
                add(&self.counters.datagrams_sent, 1);
                Ok(())
            }
            Ok(sent) => {
                add(&self.counters.send_errors, 1);
                Err(send_error(std::io::Error::new(
                    std::io::ErrorKind::WriteZero,
                    format!("sent {sent} of {} bytes", payload.len()),
                )))
            }
            Err(source) => {
                add(&self.counters.send_errors, 1);
                Err(send_error(source))
            }
        }
    }

    /// Waits for the next datagram of at most [`MAX_DATAGRAM_BYTES`], copies it to the
    /// front of `out` and returns its length and sender. Larger ones are dropped and counted.
    pub async fn recv_from(
        &self,
        out: &mut [u8; MAX_DATAGRAM_BYTES],
    ) -> Result<(usize, SocketAddr), TransportError> {
        let mut buffer = [0u8; MAX_DATAGRAM_BYTES + 1];
        loop {
            let (len, sender) =
                self.socket
                    .recv_from(&mut buffer)
                    .await
                    .map_err(|source| TransportError::Io {
                        operation: "receive UDP datagram",
                        target: self.local_addr.to_string(),
                        source,
                    })?;
            if len > MAX_DATAGRAM_BYTES {
                add(&self.counters.oversize_received_dropped, 1);
                continue;
            }
            out[..len].copy_from_slice(&buffer[..len]);
            add(&self.counters.datagrams_received, 1);
            add(&self.counters.bytes_received, len as u64);
            return Ok((len, sender));
        }
    }
}
