//! Socket options the transports need that neither tokio nor `socketcan` expose: the
//! kernel receive buffer size, and the kernel's count of datagrams a UDP socket dropped.
//!
//! The receive buffer bounds how large a burst (a camera frame is hundreds of datagrams)
//! the kernel holds while the reader is busy; past it the kernel drops, so the transports
//! count those drops instead of losing data silently.

use std::io;
use std::os::fd::RawFd;

/// Asks for a kernel receive buffer of `bytes` and returns the size the kernel granted.
///
/// Tries SO_RCVBUFFORCE first (needs CAP_NET_ADMIN, ignores net.core.rmem_max), then
/// SO_RCVBUF (capped at rmem_max). Linux doubles the request for its bookkeeping and
/// reports the doubled value.
pub(super) fn set_receive_buffer(fd: RawFd, bytes: usize) -> io::Result<usize> {
    let requested = libc::c_int::try_from(bytes).unwrap_or(libc::c_int::MAX);
    let forced = set_int_option(fd, libc::SO_RCVBUFFORCE, requested);
    if forced.is_err() {
        set_int_option(fd, libc::SO_RCVBUF, requested)?;
    }
    receive_buffer(fd)
}

/// The socket's kernel receive buffer size in bytes (as the kernel reports it).
pub(super) fn receive_buffer(fd: RawFd) -> io::Result<usize> {
    let mut value: libc::c_int = 0;
    let mut len = size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: `fd` is an open socket owned by the caller; `value` and `len` are valid,
    // writable and sized for the c_int SO_RCVBUF returns.
    let result = unsafe {
        libc::getsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVBUF,
            (&mut value as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    if result != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(usize::try_from(value).unwrap_or(0))
}

fn set_int_option(fd: RawFd, option: libc::c_int, value: libc::c_int) -> io::Result<()> {
    // SAFETY: `fd` is an open socket owned by the caller; the option value is a c_int
    // that lives for the duration of the call, and its size is passed exactly.
    let result = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            option,
            (&value as *const libc::c_int).cast(),
            size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if result == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// The socket inode behind `fd` (from /proc/self/fd), which names it in /proc/net tables.
pub(super) fn socket_inode(fd: RawFd) -> Option<u64> {
    let target = std::fs::read_link(format!("/proc/self/fd/{fd}")).ok()?;
    let text = target.to_str()?;
    text.strip_prefix("socket:[")?
        .strip_suffix(']')?
        .parse()
        .ok()
}

/// The `drops` column of the /proc/net/udp-style `table` row whose inode is `inode`.
pub(super) fn drops_from_proc_table(table: &str, inode: u64) -> Option<u64> {
    // Columns: sl local rem st tx:rx tr:when retrnsmt uid timeout inode ref pointer drops.
    const INODE_COLUMN: usize = 9;
    const DROPS_COLUMN: usize = 12;
    let inode_text = inode.to_string();
    table.lines().skip(1).find_map(|line| {
        let columns: Vec<&str> = line.split_whitespace().collect();
        if columns.get(INODE_COLUMN) == Some(&inode_text.as_str()) {
            columns.get(DROPS_COLUMN)?.parse().ok()
        } else {
            None
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const TABLE: &str = "   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode ref pointer drops
10130: 0100007F:B793 00000000:0000 07 00000000:00033C00 00:00000000 00000000     0        0 172970 2 000000000929e2bf 2908
10131: 0100007F:B794 00000000:0000 07 00000000:00000000 00:00000000 00000000     0        0 172971 2 000000000929e2c0 0
";

    #[test]
    fn drops_are_read_from_the_row_of_the_inode() {
        assert_eq!(drops_from_proc_table(TABLE, 172970), Some(2908));
        assert_eq!(drops_from_proc_table(TABLE, 172971), Some(0));
        assert_eq!(drops_from_proc_table(TABLE, 2908), None);
        assert_eq!(drops_from_proc_table("", 172970), None);
        assert_eq!(drops_from_proc_table("header\ngarbage line", 1), None);
    }

    #[test]
    fn receive_buffer_can_be_grown_and_is_reported() {
        let socket = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let fd = std::os::fd::AsRawFd::as_raw_fd(&socket);
        let before = receive_buffer(fd).unwrap();
        assert!(before > 0);
        // Shrinking is never capped, so this checks the round trip on any machine.
        let granted = set_receive_buffer(fd, 8192).unwrap();
        assert_eq!(granted, 2 * 8192, "Linux reports twice the requested size");
        assert!(socket_inode(fd).is_some());
    }
}
