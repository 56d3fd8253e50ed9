//! A raw CAN frame as the bus carries it: 29-bit extended ID, data, and whether it is FD.
//!
//! Invariants: `id <= CAN_EXTENDED_ID_MAX`; classic frames hold 0..=8 bytes, FD frames a
//! valid FD length (0..=8, 12, 16, 20, 24, 32, 48, 64); bytes past `len` are zero, so the
//! derived equality compares exactly what is on the wire.

use super::TransportError;

/// Largest 29-bit extended CAN identifier.
pub const CAN_EXTENDED_ID_MAX: u32 = 0x1FFF_FFFF;
/// Data bytes in a classic CAN frame, at most.
pub(crate) const CLASSIC_CAN_MAX_DATA_BYTES: usize = 8;
/// Data bytes in a CAN FD frame, at most.
pub(crate) const CAN_FD_MAX_DATA_BYTES: usize = 64;

/// Whether a CAN FD frame can carry exactly `len` data bytes (one of the 16 DLC lengths).
pub fn is_valid_fd_data_len(len: usize) -> bool {
    matches!(len, 0..=8 | 12 | 16 | 20 | 24 | 32 | 48 | 64)
}

/// One CAN data frame with an extended (29-bit) identifier.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RawCanFrame {
    id: u32,
    len: u8,
    fd: bool,
    data: [u8; CAN_FD_MAX_DATA_BYTES],
}

impl RawCanFrame {
    /// A classic CAN frame: `data` is 0..=8 bytes.
    pub fn classic(id: u32, data: &[u8]) -> Result<Self, TransportError> {
        if data.len() > CLASSIC_CAN_MAX_DATA_BYTES {
            return Err(TransportError::InvalidCanDataLength {
                len: data.len(),
                fd: false,
            });
        }
        Self::build(id, data, false)
    }

    /// A CAN FD frame: `data` has a valid FD length (the caller pads; nothing is added here).
    pub fn fd(id: u32, data: &[u8]) -> Result<Self, TransportError> {
        if !is_valid_fd_data_len(data.len()) {
            return Err(TransportError::InvalidCanDataLength {
                len: data.len(),
                fd: true,
            });
        }
        Self::build(id, data, true)
    }

    fn build(id: u32, data: &[u8], fd: bool) -> Result<Self, TransportError> {
        if id > CAN_EXTENDED_ID_MAX {
            return Err(TransportError::InvalidCanId { id });
        }
        let mut frame = Self {
            id,
            len: data.len() as u8,
            fd,
            data: [0; CAN_FD_MAX_DATA_BYTES],
        };
        frame.data[..data.len()].copy_from_slice(data);
        Ok(frame)
    }

    /// The 29-bit extended identifier.
    pub fn id(&self) -> u32 {
        self.id
    }

    /// The data bytes (exactly as many as the frame carries).
    pub fn data(&self) -> &[u8] {
        &self.data[..usize::from(self.len)]
    }

    /// Whether this is a CAN FD frame (a classic frame otherwise).
    pub fn is_fd(&self) -> bool {
        self.fd
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classic_frames_hold_up_to_eight_bytes() {
        for len in 0..=8 {
            let data: Vec<u8> = (0..len as u8).collect();
            let frame = RawCanFrame::classic(0x1234_5678, &data).unwrap();
            assert_eq!(frame.id(), 0x1234_5678);
            assert_eq!(frame.data(), &data[..]);
            assert!(!frame.is_fd());
        }
        assert!(matches!(
            RawCanFrame::classic(1, &[0; 9]),
            Err(TransportError::InvalidCanDataLength { len: 9, fd: false })
        ));
    }

    #[test]
    fn fd_frames_accept_exactly_the_sixteen_dlc_lengths() {
        let valid: Vec<usize> = (0..=64).filter(|&len| is_valid_fd_data_len(len)).collect();
        assert_eq!(
            valid,
            [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
        );
        for len in 0..=70 {
            let data = vec![0xA5; len];
            match RawCanFrame::fd(7, &data) {
                Ok(frame) => {
                    assert!(valid.contains(&len));
                    assert_eq!(frame.data().len(), len);
                    assert!(frame.is_fd());
                }
                Err(TransportError::InvalidCanDataLength { len: bad, fd: true }) => {
                    assert_eq!(bad, len);
                    assert!(!valid.contains(&len));
                }
                Err(other) => panic!("unexpected error {other}"),
            }
        }
    }

    #[test]
    fn ids_above_29_bits_are_rejected() {
        assert!(RawCanFrame::classic(CAN_EXTENDED_ID_MAX, &[]).is_ok());
        for id in [CAN_EXTENDED_ID_MAX + 1, u32::MAX] {
            assert!(matches!(
                RawCanFrame::classic(id, &[]),
                Err(TransportError::InvalidCanId { id: bad }) if bad == id
            ));
            assert!(matches!(
                RawCanFrame::fd(id, &[]),
                Err(TransportError::InvalidCanId { .. })
            ));
        }
    }

    #[test]
    fn equality_compares_wire_content_only() {
        let a = RawCanFrame::classic(5, &[1, 2, 3]).unwrap();
        let b = RawCanFrame::classic(5, &[1, 2, 3]).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, RawCanFrame::fd(5, &[1, 2, 3]).unwrap());
        assert_ne!(a, RawCanFrame::classic(5, &[1, 2, 3, 0]).unwrap());
    }
}
