//! DSDL serialisation of the standard `uavcan.node` types a Cyphal node must speak:
//! `uavcan.node.Heartbeat.1.0` (subject 7509), `uavcan.node.port.List.1.0` (subject 7510)
//! and `uavcan.node.GetInfo.1.0` (service 430).
//!
//! Layouts follow the DSDL definitions of the public regulated data types (little-endian,
//! composite fields byte-aligned, variable-length arrays with a `uint8` length prefix):
//! - Heartbeat: `uint32 uptime | Health.1.0 (uint2, padded to a byte) | Mode.1.0 (uint3,
//!   padded) | uint8 vendor_specific_status_code` = 7 bytes, one classic CAN frame.
//! - port.List (`uavcan.node.port.List.1.0`, sealed): four delimited fields, each
//!   `uint32 delimiter (its byte length) | body`: publishers and subscribers as
//!   `SubjectIDList.1.0` (a union: `uint8 tag = 1 | uint8 count | count x uint16 subject-ID`,
//!   the sparse list), clients and servers as `ServiceIDList.1.0` (`bool[512]` mask, 64 bytes,
//!   service-ID `i` at bit `i % 8` of byte `i / 8`).
//! - GetInfo response: `Version protocol | Version hardware | Version software` (2 bytes each)
//!   `| uint64 software_vcs_revision_id | uint8[16] unique_id | uint8[<=50] name
//!   | uint64[<=1] software_image_crc | uint8[<=222] certificate_of_authenticity`.
//!   The request is empty.
//!
//! Encoders never panic: a name longer than 50 bytes is an error, not a truncation.

use super::frame::{ServiceCanId, TailByte};

/// Fixed subject-ID of `uavcan.node.Heartbeat`.
pub const HEARTBEAT_SUBJECT_ID: u16 = 7509;
/// Fixed subject-ID of `uavcan.node.port.List`.
pub const PORT_LIST_SUBJECT_ID: u16 = 7510;
/// Fixed service-ID of `uavcan.node.GetInfo`.
pub const GET_INFO_SERVICE_ID: u16 = 430;
/// The Cyphal specification version this node implements (GetInfo's protocol_version).
pub const PROTOCOL_VERSION: (u8, u8) = (1, 0);
/// Heartbeat serialised size, bytes.
pub const HEARTBEAT_BYTES: usize = 7;
/// Longest node name GetInfo can carry, bytes.
pub const MAX_NAME_BYTES: usize = 50;
/// Largest GetInfo response this encoder writes (no image CRC, no certificate), bytes.
pub const GET_INFO_MAX_BYTES: usize = 30 + 1 + MAX_NAME_BYTES + 1 + 1;

/// `uavcan.node.Health.1.0`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum NodeHealth {
    Nominal = 0,
    Advisory = 1,
    Caution = 2,
    Warning = 3,
}

/// `uavcan.node.Mode.1.0`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeMode {
    Operational = 0,
    Initialization = 1,
    Maintenance = 2,
    SoftwareUpdate = 3,
}

/// `uavcan.node.Heartbeat.1.0`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Heartbeat {
    pub uptime_s: u32,
    pub health: NodeHealth,
    pub mode: NodeMode,
    pub vendor_specific_status_code: u8,
}

impl Heartbeat {
    pub fn encode(&self) -> [u8; HEARTBEAT_BYTES] {
        let u = self.uptime_s.to_le_bytes();
        [
            u[0],
            u[1],
            u[2],
            u[3],
            self.health as u8,
            self.mode as u8,
            self.vendor_specific_status_code,
        ]
    }
}

/// `uavcan.node.GetInfo.1.0` response (no image CRC, no certificate of authenticity).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GetInfoResponse<'a> {
    pub hardware_version: (u8, u8),
    pub software_version: (u8, u8),
    pub software_vcs_revision_id: u64,
    pub unique_id: [u8; 16],
    /// At most [`MAX_NAME_BYTES`]; by convention a reversed domain name.
    pub name: &'a str,
}

/// The node name does not fit GetInfo's 50 bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NameTooLong;

impl GetInfoResponse<'_> {
    /// Writes the response; returns the used length.
    pub fn encode(&self, out: &mut [u8; GET_INFO_MAX_BYTES]) -> Result<usize, NameTooLong> {
        let name = self.name.as_bytes();
        if name.len() > MAX_NAME_BYTES {
            return Err(NameTooLong);
        }
        let versions = [
            PROTOCOL_VERSION,
            self.hardware_version,
            self.software_version,
        ];
        for (i, (major, minor)) in versions.into_iter().enumerate() {
            out[2 * i] = major;
            out[2 * i + 1] = minor;
        }
        out[6..14].copy_from_slice(&self.software_vcs_revision_id.to_le_bytes());
        out[14..30].copy_from_slice(&self.unique_id);
        out[30] = name.len() as u8;
        let end = 31 + name.len();
        out[31..end].copy_from_slice(name);
        out[end] = 0; // software_image_crc: empty
        out[end + 1] = 0; // certificate_of_authenticity: empty
        Ok(end + 2)
    }
}

/// `uavcan.node.port.List.1.0`: the ports a node uses (it is a client of no service here).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PortList<'a> {
    pub publishers: &'a [u16],
    pub subscribers: &'a [u16],
    pub servers: &'a [u16],
}

/// Why a port list cannot be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PortListError {
    /// A subject-ID above 8191, a service-ID above 511, or 256 subjects or more in one list.
    OutOfRange,
    /// The output buffer is too small.
    BufferTooSmall,
}

const SERVICE_MASK_BYTES: usize = 64;

impl PortList<'_> {
    /// Serialised size, bytes.
    pub fn encoded_len(&self) -> usize {
        let subjects = |list: &[u16]| 4 + 2 + 2 * list.len();
        subjects(self.publishers) + subjects(self.subscribers) + 2 * (4 + SERVICE_MASK_BYTES)
    }

    /// Writes the list into `out`; returns the used length.
    pub fn encode(&self, out: &mut [u8]) -> Result<usize, PortListError> {
        if out.len() < self.encoded_len() {
            return Err(PortListError::BufferTooSmall);
        }
        let mut at = 0;
        for list in [self.publishers, self.subscribers] {
            if list.len() > 255 || list.iter().any(|&id| id > super::frame::MAX_SUBJECT_ID) {
                return Err(PortListError::OutOfRange);
            }
            let body = 2 + 2 * list.len();
            out[at..at + 4].copy_from_slice(&(body as u32).to_le_bytes());
            out[at + 4] = 1; // union tag: sparse_list
            out[at + 5] = list.len() as u8;
            at += 6;
            for id in list {
                out[at..at + 2].copy_from_slice(&id.to_le_bytes());
                at += 2;
            }
        }
        for list in [&[][..], self.servers] {
            out[at..at + 4].copy_from_slice(&(SERVICE_MASK_BYTES as u32).to_le_bytes());
            let mask = &mut out[at + 4..at + 4 + SERVICE_MASK_BYTES];
            mask.fill(0);
            for &id in list {
                let id = usize::from(id);
                if id >= SERVICE_MASK_BYTES * 8 {
                    return Err(PortListError::OutOfRange);
                }
                mask[id / 8] |= 1 << (id % 8);
            }
            at += 4 + SERVICE_MASK_BYTES;
        }
        Ok(at)
    }
}

/// A single-frame service request addressed to `local_node_id`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ServiceRequest<'a> {
    pub id: ServiceCanId,
    pub transfer_id: u8,
    /// Without the tail byte (may keep CAN FD padding zeros).
    pub payload: &'a [u8],
}

/// Why a service frame is not a request this node answers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ServiceFrameError {
    /// Not a service frame (a message, or not a Cyphal ID): the message path takes it.
    NotService,
    /// A response, or a request for another node: not ours, ignored without counting.
    NotForUs,
    /// A request to us that is not a single frame (start, end, toggle 1) or has no tail byte.
    NotSingleFrame,
}

/// Classifies a received extended frame: a single-frame service request to `local_node_id`.
/// The services this node serves all have requests that fit one frame (GetInfo's is empty).
pub fn parse_service_request(
    can_id: u32,
    data: &[u8],
    local_node_id: u8,
) -> Result<ServiceRequest<'_>, ServiceFrameError> {
    let id = ServiceCanId::from_raw(can_id).map_err(|_| ServiceFrameError::NotService)?;
    if !id.is_request || id.destination_node_id != local_node_id {
        return Err(ServiceFrameError::NotForUs);
    }
    let (&tail, payload) = data.split_last().ok_or(ServiceFrameError::NotSingleFrame)?;
    let tail = TailByte::from_byte(tail);
    if !(tail.start_of_transfer && tail.end_of_transfer && tail.toggle) {
        return Err(ServiceFrameError::NotSingleFrame);
    }
    Ok(ServiceRequest {
        id,
        transfer_id: tail.transfer_id,
        payload,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cyphal::Priority;

    #[test]
    fn heartbeat_layout() {
        let hb = Heartbeat {
            uptime_s: 0x0102_0304,
            health: NodeHealth::Caution,
            mode: NodeMode::Maintenance,
            vendor_specific_status_code: 0xAB,
        };
        assert_eq!(hb.encode(), [4, 3, 2, 1, 2, 2, 0xAB]);
    }

    #[test]
    fn get_info_layout_and_name_limit() {
        let mut out = [0xEEu8; GET_INFO_MAX_BYTES];
        let info = GetInfoResponse {
            hardware_version: (0, 0),
            software_version: (2, 7),
            software_vcs_revision_id: 0x1122_3344_5566_7788,
            unique_id: [9; 16],
            name: "org.example.x",
        };
        let n = info.encode(&mut out).unwrap();
        assert_eq!(n, 30 + 1 + 13 + 2);
        assert_eq!(&out[..6], &[1, 0, 0, 0, 2, 7]);
        assert_eq!(&out[6..14], &0x1122_3344_5566_7788u64.to_le_bytes());
        assert_eq!(&out[14..30], &[9; 16]);
        assert_eq!(out[30], 13);
        assert_eq!(&out[31..44], b"org.example.x");
        assert_eq!(&out[44..46], &[0, 0]);
        let long = "n".repeat(51);
        let too_long = GetInfoResponse {
            name: &long,
            ..info
        };
        assert_eq!(too_long.encode(&mut out), Err(NameTooLong));
        let fits = "n".repeat(50);
        let max = GetInfoResponse {
            name: &fits,
            ..info
        };
        assert_eq!(max.encode(&mut out), Ok(GET_INFO_MAX_BYTES));
    }

    #[test]
    fn port_list_layout_and_limits() {
        let list = PortList {
            publishers: &[7509, 301],
            subscribers: &[100],
            servers: &[430, 0],
        };
        let mut out = [0xEEu8; 200];
        let n = list.encode(&mut out).unwrap();
        assert_eq!(n, list.encoded_len());
        assert_eq!(n, 10 + 8 + 68 + 68);
        assert_eq!(&out[..10], &[6, 0, 0, 0, 1, 2, 0x55, 0x1D, 0x2D, 0x01]);
        assert_eq!(&out[10..18], &[4, 0, 0, 0, 1, 1, 100, 0]);
        assert_eq!(&out[18..22], &[64, 0, 0, 0]);
        assert!(out[22..86].iter().all(|&b| b == 0), "no clients");
        let servers = &out[90..154];
        assert_eq!(servers[0], 1, "service 0");
        assert_eq!(servers[430 / 8], 1 << (430 % 8));
        assert_eq!(servers.iter().map(|b| b.count_ones()).sum::<u32>(), 2);
        assert_eq!(
            list.encode(&mut [0u8; 100]),
            Err(PortListError::BufferTooSmall)
        );
        let bad = PortList {
            servers: &[512],
            ..list
        };
        assert_eq!(bad.encode(&mut out), Err(PortListError::OutOfRange));
        let bad = PortList {
            publishers: &[8192],
            ..list
        };
        assert_eq!(bad.encode(&mut out), Err(PortListError::OutOfRange));
    }

    #[test]
    fn service_requests_are_classified() {
        // Spec example: GetInfo request from 123 to 42, transfer-ID 1.
        let req = parse_service_request(0x136B_957B, &[0xE1], 42).unwrap();
        assert_eq!(req.id.service_id, GET_INFO_SERVICE_ID);
        assert_eq!(req.id.source_node_id, 123);
        assert_eq!(req.id.priority, Priority::Nominal);
        assert_eq!(req.transfer_id, 1);
        assert!(req.payload.is_empty());
        assert_eq!(
            parse_service_request(0x136B_957B, &[0xE1], 43),
            Err(ServiceFrameError::NotForUs)
        );
        assert_eq!(
            parse_service_request(0x126B_BDAA, &[0xE1], 123),
            Err(ServiceFrameError::NotForUs),
            "responses are not requests"
        );
        assert_eq!(
            parse_service_request(0x107D_552A, &[0xE0], 42),
            Err(ServiceFrameError::NotService)
        );
        assert_eq!(
            parse_service_request(0x136B_957B, &[0xA1], 42),
            Err(ServiceFrameError::NotSingleFrame)
        );
        assert_eq!(
            parse_service_request(0x136B_957B, &[], 42),
            Err(ServiceFrameError::NotSingleFrame)
        );
    }
}
