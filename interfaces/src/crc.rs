//! Checksums used by the bus framing.
//!
//! - CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor): the Cyphal/CAN
//!   multi-frame transfer CRC. Check value: "123456789" -> 0x29B1. Appending the CRC big-endian
//!   and running the CRC over the result gives a residue of 0.
//! - CRC-32/ISO-HDLC ("IEEE", poly 0x04C11DB7 reflected, init and final xor 0xFFFFFFFF): the
//!   per-message CRC of reassembled CCSDS messages. Check value: "123456789" -> 0xCBF43926.
//!
//! Both use 256-entry tables built at compile time: no allocation, no runtime initialisation.

const fn crc16_table() -> [u16; 256] {
    let mut table = [0u16; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut crc = (byte as u16) << 8;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[byte] = crc;
        byte += 1;
    }
    table
}

const fn crc32_table() -> [u32; 256] {
    let mut table = [0u32; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut crc = byte as u32;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
            bit += 1;
        }
        table[byte] = crc;
        byte += 1;
    }
    table
}

static CRC16_TABLE: [u16; 256] = crc16_table();
static CRC32_TABLE: [u32; 256] = crc32_table();

/// Running CRC-16/CCITT-FALSE.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crc16CcittFalse(u16);

impl Default for Crc16CcittFalse {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc16CcittFalse {
    pub const INITIAL: u16 = 0xFFFF;

    pub const fn new() -> Self {
        Self(Self::INITIAL)
    }

    pub fn update(&mut self, bytes: &[u8]) {
        let mut crc = self.0;
        for &b in bytes {
            let index = ((crc >> 8) as u8 ^ b) as usize;
            crc = (crc << 8) ^ CRC16_TABLE[index];
        }
        self.0 = crc;
    }

    pub fn value(&self) -> u16 {
        self.0
    }
}

/// CRC-16/CCITT-FALSE of `bytes` in one call.
pub fn crc16_ccitt_false(bytes: &[u8]) -> u16 {
    let mut crc = Crc16CcittFalse::new();
    crc.update(bytes);
    crc.value()
}

/// Running CRC-32 (IEEE 802.3 / ISO-HDLC).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Crc32Ieee(u32);

impl Default for Crc32Ieee {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc32Ieee {
    pub const fn new() -> Self {
        Self(0xFFFF_FFFF)
    }

    pub fn update(&mut self, bytes: &[u8]) {
        let mut crc = self.0;
        for &b in bytes {
            crc = (crc >> 8) ^ CRC32_TABLE[((crc as u8) ^ b) as usize];
        }
        self.0 = crc;
    }

    pub fn value(&self) -> u32 {
        self.0 ^ 0xFFFF_FFFF
    }
}

/// CRC-32 (IEEE) of `bytes` in one call.
pub fn crc32_ieee(bytes: &[u8]) -> u32 {
    let mut crc = Crc32Ieee::new();
    crc.update(bytes);
    crc.value()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bit-by-bit reference straight from the polynomial definition, independent of the table.
    fn crc16_bitwise(bytes: &[u8]) -> u16 {
        let mut crc: u16 = 0xFFFF;
        for &b in bytes {
            for i in (0..8).rev() {
                let in_bit = (b >> i) & 1 != 0;
                let top = crc & 0x8000 != 0;
                crc <<= 1;
                if in_bit ^ top {
                    crc ^= 0x1021;
                }
            }
        }
        crc
    }

    #[test]
    fn crc16_check_value() {
        assert_eq!(crc16_ccitt_false(b"123456789"), 0x29B1);
        assert_eq!(crc16_bitwise(b"123456789"), 0x29B1);
        assert_eq!(crc16_ccitt_false(b""), 0xFFFF);
    }

    #[test]
    fn crc16_matches_bitwise_reference_and_is_incremental() {
        let data: [u8; 300] = core::array::from_fn(|i| (i as u8).wrapping_mul(37).wrapping_add(11));
        for len in [0usize, 1, 2, 7, 63, 64, 299, 300] {
            let mut inc = Crc16CcittFalse::new();
            let (a, b) = data[..len].split_at(len / 3);
            inc.update(a);
            inc.update(b);
            assert_eq!(inc.value(), crc16_bitwise(&data[..len]));
        }
    }

    #[test]
    fn crc16_residue_is_zero_after_appending_big_endian() {
        let mut buf = [0u8; 11];
        buf[..9].copy_from_slice(b"123456789");
        buf[9..].copy_from_slice(&0x29B1u16.to_be_bytes());
        assert_eq!(crc16_ccitt_false(&buf), 0);
    }

    #[test]
    fn crc32_check_value() {
        assert_eq!(crc32_ieee(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32_ieee(b""), 0);
        // "The quick brown fox jumps over the lazy dog" is a widely published vector.
        assert_eq!(
            crc32_ieee(b"The quick brown fox jumps over the lazy dog"),
            0x414F_A339
        );
    }
}
