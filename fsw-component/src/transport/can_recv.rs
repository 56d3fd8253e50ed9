//! Receiving raw CAN frames with the kernel's drop count: one `recvmsg` per frame on a
//! CAN_RAW socket with SO_RXQ_OVFL enabled, and a pure parser of the kernel's frame layout.
//!
//! Why not the `socketcan` crate's `read_frame`: it uses `read`, which cannot see frames
//! the kernel dropped because the socket's receive queue was full. With SO_RXQ_OVFL each
//! frame carries the socket's cumulative drop count, so overflow is counted, not silent.
//! Layout (linux/can.h, native endian): `can_id: u32` (bit 31 extended, 30 remote, 29
//! error), `len: u8`, `flags: u8`, 2 reserved bytes, data; 16 bytes in all for a classic
//! frame (8 data bytes), 72 for an FD frame (64). The parser never panics on any input.

use std::io;
use std::os::fd::RawFd;

use super::can_frame::{is_valid_fd_data_len, CLASSIC_CAN_MAX_DATA_BYTES};
use super::RawCanFrame;

/// Bytes of a classic `struct can_frame`.
pub(super) const CAN_MTU_BYTES: usize = 16;
/// Bytes of a `struct canfd_frame`.
pub(super) const CANFD_MTU_BYTES: usize = 72;

const CAN_EFF_FLAG: u32 = 0x8000_0000;
const CAN_RTR_FLAG: u32 = 0x4000_0000;
const CAN_ERR_FLAG: u32 = 0x2000_0000;
const CAN_EFF_MASK: u32 = 0x1FFF_FFFF;
const DATA_OFFSET: usize = 8;

/// What one read from a CAN_RAW socket held.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Received {
    /// An extended-ID data frame, classic or FD.
    Frame(RawCanFrame),
    StandardId,
    Remote,
    ErrorFrame,
    /// A length or size no kernel frame has.
    Malformed,
}

/// Parses one frame as the kernel delivers it (16 bytes classic, 72 bytes FD).
pub(super) fn parse_frame(bytes: &[u8]) -> Received {
    let fd = match bytes.len() {
        CAN_MTU_BYTES => false,
        CANFD_MTU_BYTES => true,
        _ => return Received::Malformed,
    };
    let can_id = u32::from_ne_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]);
    if can_id & CAN_ERR_FLAG != 0 {
        return Received::ErrorFrame;
    }
    if can_id & CAN_RTR_FLAG != 0 {
        return Received::Remote;
    }
    if can_id & CAN_EFF_FLAG == 0 {
        return Received::StandardId;
    }
    let len = usize::from(bytes[4]);
    let valid_len = if fd {
        is_valid_fd_data_len(len)
    } else {
        len <= CLASSIC_CAN_MAX_DATA_BYTES
    };
    if !valid_len {
        return Received::Malformed;
    }
    let id = can_id & CAN_EFF_MASK;
    let data = &bytes[DATA_OFFSET..DATA_OFFSET + len];
    let frame = if fd {
        RawCanFrame::fd(id, data)
    } else {
        RawCanFrame::classic(id, data)
    };
    frame.map_or(Received::Malformed, Received::Frame)
}

/// Turns on SO_RXQ_OVFL: every received frame then says how many the socket dropped so far.
pub(super) fn enable_drop_count(fd: RawFd) -> io::Result<()> {
    let enable: libc::c_int = 1;
    // SAFETY: `fd` is an open socket owned by the caller; the option value is a c_int that
    // lives for the duration of the call, and its size is passed exactly.
    let result = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RXQ_OVFL,
            (&enable as *const libc::c_int).cast(),
            size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if result == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// One non-blocking `recvmsg`: the frame's byte count in `buffer`, and the socket's
/// cumulative kernel drop count when the kernel attached one (only once it is non-zero).
pub(super) fn recv_frame(
    fd: RawFd,
    buffer: &mut [u8; CANFD_MTU_BYTES],
) -> io::Result<(usize, Option<u32>)> {
    // u64 storage keeps the control buffer aligned for cmsghdr.
    let mut control = [0u64; 8];
    let mut iov = libc::iovec {
        iov_base: buffer.as_mut_ptr().cast(),
        iov_len: buffer.len(),
    };
    // SAFETY: an all-zero msghdr is a valid empty header; the pointers set below point at
    // `iov` and `control`, which outlive the recvmsg call, with their exact sizes.
    let mut header: libc::msghdr = unsafe { std::mem::zeroed() };
    header.msg_iov = &mut iov;
    header.msg_iovlen = 1;
    header.msg_control = control.as_mut_ptr().cast();
    header.msg_controllen = size_of_val(&control) as _;
    // SAFETY: `header` describes valid, writable buffers (see above); MSG_DONTWAIT makes the
    // call non-blocking whatever the socket's mode.
    let received = unsafe { libc::recvmsg(fd, &mut header, libc::MSG_DONTWAIT) };
    if received < 0 {
        return Err(io::Error::last_os_error());
    }
    let mut drops_total = None;
    // SAFETY: CMSG_FIRSTHDR/CMSG_NXTHDR walk the control buffer the kernel filled, bounded
    // by msg_controllen; a cmsg is read only when its length covers a u32 payload.
    unsafe {
        let mut message = libc::CMSG_FIRSTHDR(&header);
        while !message.is_null() {
            let item = &*message;
            let payload_fits = item.cmsg_len as usize >= libc::CMSG_LEN(4) as usize;
            if item.cmsg_level == libc::SOL_SOCKET
                && item.cmsg_type == libc::SO_RXQ_OVFL
                && payload_fits
            {
                drops_total = Some(std::ptr::read_unaligned(
                    libc::CMSG_DATA(message).cast::<u32>(),
                ));
            }
            message = libc::CMSG_NXTHDR(&header, message);
        }
    }
    Ok((received as usize, drops_total))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kernel_bytes(can_id: u32, len: u8, data: &[u8], fd: bool) -> Vec<u8> {
        let mut bytes = vec![0u8; if fd { CANFD_MTU_BYTES } else { CAN_MTU_BYTES }];
        bytes[..4].copy_from_slice(&can_id.to_ne_bytes());
        bytes[4] = len;
        bytes[DATA_OFFSET..DATA_OFFSET + data.len()].copy_from_slice(data);
        bytes
    }

    #[test]
    fn extended_data_frames_parse_with_id_data_and_kind() {
        let classic = kernel_bytes(CAN_EFF_FLAG | 0x1ABC_DEF0, 3, &[1, 2, 3], false);
        assert_eq!(
            parse_frame(&classic),
            Received::Frame(RawCanFrame::classic(0x1ABC_DEF0, &[1, 2, 3]).unwrap())
        );
        let data: Vec<u8> = (0..48).collect();
        let fd = kernel_bytes(CAN_EFF_FLAG | 0x42, 48, &data, true);
        assert_eq!(
            parse_frame(&fd),
            Received::Frame(RawCanFrame::fd(0x42, &data).unwrap())
        );
        // An FD frame of 5 bytes stays FD: the kind comes from the size read, not the length.
        let short_fd = kernel_bytes(CAN_EFF_FLAG | 7, 5, &[9; 5], true);
        assert_eq!(
            parse_frame(&short_fd),
            Received::Frame(RawCanFrame::fd(7, &[9; 5]).unwrap())
        );
    }

    #[test]
    fn non_data_and_standard_frames_are_classified() {
        assert_eq!(
            parse_frame(&kernel_bytes(0x123, 2, &[1, 2], false)),
            Received::StandardId
        );
        assert_eq!(
            parse_frame(&kernel_bytes(
                CAN_EFF_FLAG | CAN_RTR_FLAG | 5,
                4,
                &[],
                false
            )),
            Received::Remote
        );
        assert_eq!(
            parse_frame(&kernel_bytes(CAN_ERR_FLAG | 0x4, 8, &[0; 8], false)),
            Received::ErrorFrame
        );
    }

    #[test]
    fn impossible_sizes_and_lengths_are_malformed_not_panics() {
        for size in [0, 1, 8, 15, 17, 71, 73, 200] {
            assert_eq!(
                parse_frame(&vec![0xFF; size]),
                Received::Malformed,
                "{size}"
            );
        }
        assert_eq!(
            parse_frame(&kernel_bytes(CAN_EFF_FLAG | 1, 9, &[], false)),
            Received::Malformed
        );
        for len in [9, 13, 63, 65, 255] {
            assert_eq!(
                parse_frame(&kernel_bytes(CAN_EFF_FLAG | 1, len, &[], true)),
                Received::Malformed,
                "{len}"
            );
        }
    }
}
