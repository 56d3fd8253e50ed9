//! DSDL serialisation of the standard register services: `uavcan.register.Access.1.0`
//! (service 384) and `uavcan.register.List.1.0` (service 385), with `uavcan.register.Name.1.0`
//! and the `uavcan.register.Value.1.0` union.
//!
//! Layouts (all sealed, little-endian, byte-aligned; public regulated data types f9f6790):
//! - `Name.1.0`: `uint8 length | uint8[<256] name`.
//! - `Value.1.0`: `uint8 tag | field`, the field a `uavcan.primitive` type whose variable-length
//!   array has a `uint8` length prefix when its capacity is below 256 elements and a `uint16`
//!   one otherwise: string/unstructured (`uint8[<=256]`), bit (`bool[<=2048]`, bit `i` at
//!   bit `i % 8` of byte `i / 8`), integer/natural 64/32/16/8 (`[<=32]`, `[<=64]`, `[<=128]`,
//!   `[<=256]`), real 64/32/16 (`[<=32]`, `[<=64]`, `[<=128]`). Tag 0 is `empty`.
//! - Access request: `Name | Value`; response: `uint56 timestamp (0: unknown) | bool mutable
//!   | bool persistent | void6 | Value`.
//! - List request: `uint16 index`; response: `Name` (empty past the last register).
//!
//! Decoders never panic and never read past their input: an unknown union tag, a length
//! prefix above the array's capacity or an array cut short is an error. Bytes after a
//! complete request are ignored (CAN FD padding, the specification's implicit truncation),
//! and a request that ends where a field starts reads that field as zero (implicit zero
//! extension: an Access request without a value is a read).

/// Fixed service-ID of `uavcan.register.Access`.
pub const ACCESS_SERVICE_ID: u16 = 384;
/// Fixed service-ID of `uavcan.register.List`.
pub const LIST_SERVICE_ID: u16 = 385;
/// Longest register name, bytes.
pub const MAX_NAME_BYTES: usize = 255;
/// Largest serialised `Value.1.0`: tag, `uint16` length prefix and 256 bytes.
pub const VALUE_MAX_BYTES: usize = 1 + 2 + 256;
/// Largest serialised Access response.
pub const ACCESS_RESPONSE_MAX_BYTES: usize = 7 + 1 + VALUE_MAX_BYTES;
/// Largest serialised List response.
pub const LIST_RESPONSE_MAX_BYTES: usize = 1 + MAX_NAME_BYTES;
/// Largest serialised Access request (name and value).
pub const ACCESS_REQUEST_MAX_BYTES: usize = 1 + MAX_NAME_BYTES + VALUE_MAX_BYTES;

/// The union tag of `uavcan.register.Value.1.0`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ValueKind {
    Empty = 0,
    String = 1,
    Unstructured = 2,
    Bit = 3,
    Integer64 = 4,
    Integer32 = 5,
    Integer16 = 6,
    Integer8 = 7,
    Natural64 = 8,
    Natural32 = 9,
    Natural16 = 10,
    Natural8 = 11,
    Real64 = 12,
    Real32 = 13,
    Real16 = 14,
}

impl ValueKind {
    pub const ALL: [ValueKind; 15] = [
        Self::Empty,
        Self::String,
        Self::Unstructured,
        Self::Bit,
        Self::Integer64,
        Self::Integer32,
        Self::Integer16,
        Self::Integer8,
        Self::Natural64,
        Self::Natural32,
        Self::Natural16,
        Self::Natural8,
        Self::Real64,
        Self::Real32,
        Self::Real16,
    ];

    pub fn from_tag(tag: u8) -> Option<Self> {
        Self::ALL.get(usize::from(tag)).copied()
    }

    /// Bits per element (0 for `empty`).
    pub fn element_bits(self) -> usize {
        match self {
            Self::Empty => 0,
            Self::Bit => 1,
            Self::String | Self::Unstructured | Self::Integer8 | Self::Natural8 => 8,
            Self::Integer16 | Self::Natural16 | Self::Real16 => 16,
            Self::Integer32 | Self::Natural32 | Self::Real32 => 32,
            Self::Integer64 | Self::Natural64 | Self::Real64 => 64,
        }
    }

    /// Most elements the array holds.
    pub fn capacity(self) -> usize {
        match self {
            Self::Empty => 0,
            Self::Bit => 2048,
            _ => 2048 / self.element_bits(),
        }
    }

    /// Bytes of the array's length prefix: DSDL uses the narrowest unsigned integer that
    /// holds the capacity.
    fn prefix_bytes(self) -> usize {
        match self.capacity() {
            0 => 0,
            c if c <= 255 => 1,
            _ => 2,
        }
    }
}

/// A borrowed `Value.1.0`: the kind, the element count and the elements' bytes as on the
/// wire (`ceil(count * element_bits / 8)` bytes, little-endian elements, bits packed).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Value<'a> {
    pub kind: ValueKind,
    pub count: usize,
    pub raw: &'a [u8],
}

impl<'a> Value<'a> {
    pub const EMPTY: Value<'static> = Value {
        kind: ValueKind::Empty,
        count: 0,
        raw: &[],
    };

    /// A value with `count` elements of `kind` in `raw`; `None` when the count exceeds the
    /// capacity or `raw` has not exactly the bytes the count needs.
    pub fn new(kind: ValueKind, count: usize, raw: &'a [u8]) -> Option<Self> {
        let ok = count <= kind.capacity() && raw.len() == raw_len(kind, count);
        ok.then_some(Self { kind, count, raw })
    }

    /// Serialised size, bytes.
    pub fn encoded_len(&self) -> usize {
        1 + self.kind.prefix_bytes() + self.raw.len()
    }

    /// Writes the value; returns the used length.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, RegisterCodecError> {
        let len = self.encoded_len();
        if self.count > self.kind.capacity() || self.raw.len() != raw_len(self.kind, self.count) {
            return Err(RegisterCodecError::Invalid);
        }
        let out = out
            .get_mut(..len)
            .ok_or(RegisterCodecError::BufferTooSmall)?;
        out[0] = self.kind as u8;
        let prefix = self.kind.prefix_bytes();
        let count = (self.count as u16).to_le_bytes();
        out[1..1 + prefix].copy_from_slice(&count[..prefix]);
        out[1 + prefix..].copy_from_slice(self.raw);
        Ok(len)
    }

    /// Reads a value from the start of `bytes`; returns it and the bytes used. No bytes at
    /// all read as `empty` (implicit zero extension).
    pub fn decode(bytes: &'a [u8]) -> Result<(Self, usize), RegisterCodecError> {
        let Some((&tag, rest)) = bytes.split_first() else {
            return Ok((Value::EMPTY, 0));
        };
        let kind = ValueKind::from_tag(tag).ok_or(RegisterCodecError::UnknownTag(tag))?;
        let prefix = kind.prefix_bytes();
        let count = match prefix {
            0 => 0,
            1 => usize::from(*rest.first().ok_or(RegisterCodecError::Truncated)?),
            _ => {
                let b = rest.get(..2).ok_or(RegisterCodecError::Truncated)?;
                usize::from(u16::from_le_bytes([b[0], b[1]]))
            }
        };
        if count > kind.capacity() {
            return Err(RegisterCodecError::LengthAboveCapacity);
        }
        let n = raw_len(kind, count);
        let raw = rest
            .get(prefix..prefix + n)
            .ok_or(RegisterCodecError::Truncated)?;
        Ok((Self { kind, count, raw }, 1 + prefix + n))
    }

    /// The single unsigned integer this value holds (natural 8/16/32/64 with one element).
    pub fn as_natural(&self) -> Option<u64> {
        let width = match self.kind {
            ValueKind::Natural8
            | ValueKind::Natural16
            | ValueKind::Natural32
            | ValueKind::Natural64 => self.kind.element_bits() / 8,
            _ => return None,
        };
        if self.count != 1 {
            return None;
        }
        let mut le = [0u8; 8];
        le[..width].copy_from_slice(self.raw);
        Some(u64::from_le_bytes(le))
    }
}

/// Bytes of `count` elements of `kind`.
pub fn raw_len(kind: ValueKind, count: usize) -> usize {
    (count * kind.element_bits()).div_ceil(8)
}

/// Why a register message cannot be read or written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RegisterCodecError {
    /// A union tag above 14.
    UnknownTag(u8),
    /// An array length prefix above the array's capacity.
    LengthAboveCapacity,
    /// The input ends inside a field.
    Truncated,
    /// The output buffer is too small.
    BufferTooSmall,
    /// A value whose count and bytes disagree, or a name over 255 bytes.
    Invalid,
}

impl core::fmt::Display for RegisterCodecError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::UnknownTag(tag) => write!(f, "register value union tag {tag} is unknown"),
            Self::LengthAboveCapacity => f.write_str("array length above its capacity"),
            Self::Truncated => f.write_str("register message cut short"),
            Self::BufferTooSmall => f.write_str("output buffer too small"),
            Self::Invalid => f.write_str("value or name not representable"),
        }
    }
}

impl core::error::Error for RegisterCodecError {}

fn decode_name(bytes: &[u8]) -> Result<(&[u8], usize), RegisterCodecError> {
    let Some((&len, rest)) = bytes.split_first() else {
        return Ok((&[], 0));
    };
    let len = usize::from(len);
    let name = rest.get(..len).ok_or(RegisterCodecError::Truncated)?;
    Ok((name, 1 + len))
}

fn encode_name(name: &[u8], out: &mut [u8]) -> Result<usize, RegisterCodecError> {
    if name.len() > MAX_NAME_BYTES {
        return Err(RegisterCodecError::Invalid);
    }
    let out = out
        .get_mut(..1 + name.len())
        .ok_or(RegisterCodecError::BufferTooSmall)?;
    out[0] = name.len() as u8;
    out[1..].copy_from_slice(name);
    Ok(1 + name.len())
}

/// `uavcan.register.Access.1.0` request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AccessRequest<'a> {
    /// UTF-8 is not checked here: an unknown name is simply not found.
    pub name: &'a [u8],
    /// `empty` reads; anything else asks to write.
    pub value: Value<'a>,
}

impl<'a> AccessRequest<'a> {
    pub fn decode(bytes: &'a [u8]) -> Result<Self, RegisterCodecError> {
        let (name, used) = decode_name(bytes)?;
        let (value, _) = Value::decode(&bytes[used..])?;
        Ok(Self { name, value })
    }

    /// Writes the request (what a client sends; used by tests and tools).
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, RegisterCodecError> {
        let used = encode_name(self.name, out)?;
        let rest = out
            .get_mut(used..)
            .ok_or(RegisterCodecError::BufferTooSmall)?;
        Ok(used + self.value.encode(rest)?)
    }
}

/// `uavcan.register.Access.1.0` response.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AccessResponse<'a> {
    /// Microseconds of synchronised time, 56 bits; 0 = unknown.
    pub timestamp_us: u64,
    pub mutable: bool,
    pub persistent: bool,
    pub value: Value<'a>,
}

impl AccessResponse<'_> {
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, RegisterCodecError> {
        let head = out.get_mut(..8).ok_or(RegisterCodecError::BufferTooSmall)?;
        head[..7].copy_from_slice(&self.timestamp_us.to_le_bytes()[..7]);
        head[7] = u8::from(self.mutable) | (u8::from(self.persistent) << 1);
        Ok(8 + self.value.encode(&mut out[8..])?)
    }
}

impl<'a> AccessResponse<'a> {
    /// Reads a response (what a client receives; used by tests and tools).
    pub fn decode(bytes: &'a [u8]) -> Result<Self, RegisterCodecError> {
        let head = bytes.get(..8).ok_or(RegisterCodecError::Truncated)?;
        let mut ts = [0u8; 8];
        ts[..7].copy_from_slice(&head[..7]);
        let (value, _) = Value::decode(&bytes[8..])?;
        Ok(Self {
            timestamp_us: u64::from_le_bytes(ts),
            mutable: head[7] & 1 != 0,
            persistent: head[7] & 2 != 0,
            value,
        })
    }
}

/// `uavcan.register.List.1.0` request: the index of the register asked for. A short
/// request reads the missing bytes as zero.
pub fn decode_list_request(bytes: &[u8]) -> u16 {
    let lo = bytes.first().copied().unwrap_or(0);
    let hi = bytes.get(1).copied().unwrap_or(0);
    u16::from_le_bytes([lo, hi])
}

/// `uavcan.register.List.1.0` response: the name at the asked index, empty past the end.
pub fn encode_list_response(name: &[u8], out: &mut [u8]) -> Result<usize, RegisterCodecError> {
    encode_name(name, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_layouts_follow_the_dsdl_prefixes() {
        let mut out = [0u8; VALUE_MAX_BYTES];
        // natural16[<=128]: uint8 prefix.
        let v = Value::new(ValueKind::Natural16, 2, &[0x64, 0, 0xF4, 0x01]).unwrap();
        assert_eq!(v.encode(&mut out), Ok(6));
        assert_eq!(&out[..6], &[10, 2, 0x64, 0, 0xF4, 0x01]);
        // string uint8[<=256]: uint16 prefix.
        let v = Value::new(ValueKind::String, 3, b"abc").unwrap();
        assert_eq!(v.encode(&mut out), Ok(6));
        assert_eq!(&out[..6], &[1, 3, 0, b'a', b'b', b'c']);
        // bool[<=2048]: uint16 prefix, bits packed LSB first.
        let v = Value::new(ValueKind::Bit, 3, &[0b101]).unwrap();
        assert_eq!(v.encode(&mut out), Ok(4));
        assert_eq!(&out[..4], &[3, 3, 0, 0b101]);
        // natural8[<=256]: uint16 prefix; real64[<=32]: uint8 prefix.
        let v = Value::new(ValueKind::Natural8, 1, &[7]).unwrap();
        assert_eq!(v.encode(&mut out), Ok(4));
        assert_eq!(&out[..4], &[11, 1, 0, 7]);
        let one = 1.0f64.to_le_bytes();
        let v = Value::new(ValueKind::Real64, 1, &one).unwrap();
        assert_eq!(v.encode(&mut out), Ok(10));
        assert_eq!(&out[..2], &[12, 1]);
        assert_eq!(Value::EMPTY.encode(&mut out), Ok(1));
        assert_eq!(out[0], 0);
        for kind in ValueKind::ALL {
            let bytes = [0u8; 256];
            let full = Value::new(
                kind,
                kind.capacity(),
                &bytes[..raw_len(kind, kind.capacity())],
            )
            .unwrap();
            assert!(full.encoded_len() <= VALUE_MAX_BYTES, "{kind:?}");
            assert!(Value::new(kind, kind.capacity() + 1, &[]).is_none());
        }
    }

    #[test]
    fn values_round_trip_and_read_as_naturals() {
        let mut out = [0u8; VALUE_MAX_BYTES];
        let v = Value::new(ValueKind::Natural32, 1, &[1, 2, 0, 0]).unwrap();
        let n = v.encode(&mut out).unwrap();
        assert_eq!(Value::decode(&out[..n]), Ok((v, n)));
        assert_eq!(v.as_natural(), Some(0x0201));
        assert_eq!(
            Value::new(ValueKind::Natural16, 2, &[1, 0, 2, 0])
                .unwrap()
                .as_natural(),
            None,
            "two elements are not one number"
        );
        assert_eq!(
            Value::new(ValueKind::Integer16, 1, &[1, 0])
                .unwrap()
                .as_natural(),
            None
        );
    }

    #[test]
    fn bad_values_are_errors() {
        assert_eq!(
            Value::decode(&[15, 0]),
            Err(RegisterCodecError::UnknownTag(15))
        );
        assert_eq!(
            Value::decode(&[10, 129]),
            Err(RegisterCodecError::LengthAboveCapacity)
        );
        assert_eq!(
            Value::decode(&[1, 1, 1]),
            Err(RegisterCodecError::LengthAboveCapacity),
            "string of 257 bytes"
        );
        assert_eq!(
            Value::decode(&[10, 2, 1, 0, 2]),
            Err(RegisterCodecError::Truncated)
        );
        assert_eq!(Value::decode(&[1, 5]), Err(RegisterCodecError::Truncated));
        assert_eq!(Value::decode(&[]), Ok((Value::EMPTY, 0)));
    }

    #[test]
    fn access_request_and_response_layouts() {
        // Request "a.b" := natural16 [500], then FD padding.
        let bytes = [3, b'a', b'.', b'b', 10, 1, 0xF4, 0x01, 0, 0, 0];
        let req = AccessRequest::decode(&bytes).unwrap();
        assert_eq!(req.name, b"a.b");
        assert_eq!(req.value.as_natural(), Some(500));
        let mut out = [0u8; ACCESS_REQUEST_MAX_BYTES];
        let n = req.encode(&mut out).unwrap();
        assert_eq!(&out[..n], &bytes[..8]);
        // A request without a value is a read.
        let read = AccessRequest::decode(&[1, b'x']).unwrap();
        assert_eq!(read.value, Value::EMPTY);
        assert_eq!(
            AccessRequest::decode(&[4, b'x']),
            Err(RegisterCodecError::Truncated)
        );
        let response = AccessResponse {
            timestamp_us: 0x0102_0304_0506_0708,
            mutable: true,
            persistent: false,
            value: req.value,
        };
        let mut out = [0xEEu8; ACCESS_RESPONSE_MAX_BYTES];
        let n = response.encode(&mut out).unwrap();
        assert_eq!(n, 8 + 4);
        assert_eq!(&out[..7], &[8, 7, 6, 5, 4, 3, 2], "uint56, truncated");
        assert_eq!(out[7], 0b01);
        assert_eq!(&out[8..12], &[10, 1, 0xF4, 0x01]);
        let back = AccessResponse::decode(&out[..n]).unwrap();
        assert_eq!(back.timestamp_us, 0x0002_0304_0506_0708);
        assert!(back.mutable && !back.persistent);
        assert_eq!(back.value, req.value);
    }

    #[test]
    fn list_request_and_response_layouts() {
        assert_eq!(decode_list_request(&[0x34, 0x12]), 0x1234);
        assert_eq!(decode_list_request(&[5]), 5);
        assert_eq!(decode_list_request(&[]), 0);
        let mut out = [0u8; LIST_RESPONSE_MAX_BYTES];
        assert_eq!(encode_list_response(b"uavcan.node.id", &mut out), Ok(15));
        assert_eq!(out[0], 14);
        assert_eq!(&out[1..15], b"uavcan.node.id");
        assert_eq!(encode_list_response(b"", &mut out), Ok(1));
        assert_eq!(
            encode_list_response(&[b'n'; 256], &mut out),
            Err(RegisterCodecError::Invalid)
        );
    }
}
