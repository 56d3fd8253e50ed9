//! The component as a Cyphal node: the 1 Hz `uavcan.node.Heartbeat`, the
//! `uavcan.node.port.List` every 10 heartbeats (the first with the first heartbeat; the
//! ports are fixed at start, so there is no other change to announce), the
//! `uavcan.node.GetInfo` server and, with registers attached, the `uavcan.register.Access`
//! and `List` servers (`crate::registers`), framed for the CAN transport. A malformed
//! register request is counted in `requests_malformed` and not answered.
//!
//! Invariants: the node-ID is the configured, validated one (never anonymous: a node that
//! publishes heartbeats must have an ID); the heartbeat transfer-ID advances by one per
//! heartbeat; a response repeats its request's priority and transfer-ID (Cyphal v1.0, 4.2.1).
//! Health mapping (documented in the ICD, interfaces/README.md):
//! WARNING = the trainer gave up after repeated faults; CAUTION = the trainer is being
//! restarted after a fault; ADVISORY = frames dropped, decode or CRC errors or send errors
//! rose since the previous heartbeat; NOMINAL otherwise. Mode is always OPERATIONAL (the
//! component is listening in each of its modes); the vendor-specific status code is the
//! component's mode (0 Idle, 1 Train, 2 PredictOnly).

use crate::cyphal_config::{Direction, SubjectIds};
use crate::registers::Registers;
use crate::transport::RawCanFrame;
use interfaces::cyphal::node::{
    GetInfoResponse, Heartbeat, NodeHealth, NodeMode, PortList, ServiceRequest, GET_INFO_MAX_BYTES,
    GET_INFO_SERVICE_ID, HEARTBEAT_SUBJECT_ID, PORT_LIST_SUBJECT_ID,
};
use interfaces::cyphal::register::{
    decode_list_request, encode_list_response, AccessRequest, AccessResponse,
    ACCESS_RESPONSE_MAX_BYTES, ACCESS_SERVICE_ID, LIST_SERVICE_ID,
};
use interfaces::cyphal::{
    service_transfer_frames, transfer_frames, Mtu, Priority, ServiceCanId, TransferFrames,
    TransferHeader,
};
use interfaces::messages::{HealthStatus, Mode};

/// Heartbeats between two port lists (uavcan.node.port.List: at most every 10 s).
pub(crate) const PORT_LIST_EVERY_HEARTBEATS: u64 = 10;
/// Services the component serves without registers, and with them.
pub(crate) const SERVED_SERVICES: [u16; 1] = [GET_INFO_SERVICE_ID];
pub(crate) const SERVED_SERVICES_WITH_REGISTERS: [u16; 3] =
    [ACCESS_SERVICE_ID, LIST_SERVICE_ID, GET_INFO_SERVICE_ID];

/// What GetInfo reports about this node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeIdentity {
    /// At most 50 bytes (checked by the configuration).
    pub name: String,
    pub unique_id: [u8; 16],
    pub software_version: (u8, u8),
    pub software_vcs_revision_id: u64,
}

/// What a heartbeat is made from: the component's mode, uptime and the error-like counters
/// whose rise makes a heartbeat ADVISORY.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NodeStatus {
    pub mode: Mode,
    pub uptime_s: u32,
    pub frames_dropped: u32,
    pub decode_errors: u32,
    pub crc_errors: u32,
    pub send_errors: u64,
}

impl NodeStatus {
    /// From the 1 Hz health status and the core's send-error counter.
    pub(crate) fn from_health(status: &HealthStatus, send_errors: u64) -> Self {
        Self {
            mode: status.mode,
            uptime_s: status.uptime_s,
            frames_dropped: status.frames_dropped,
            decode_errors: status.decode_errors,
            crc_errors: status.crc_errors,
            send_errors,
        }
    }
}

/// Heartbeat publisher and service server state.
#[derive(Debug)]
pub struct CyphalNode {
    node_id: u8,
    mtu: Mtu,
    identity: NodeIdentity,
    heartbeat_transfer_id: u64,
    port_list_transfer_id: u64,
    last_troubles: Option<NodeStatus>,
    trainer_restarting: bool,
    trainer_gave_up: bool,
    /// Subjects published on CAN (predictions only when configured: [`Self::publish_also`])
    /// and taken from CAN; listed in port.List.
    published: Vec<u16>,
    subscribed: Vec<u16>,
    registers: Option<Registers>,
    /// Register requests that do not decode (not answered).
    pub requests_malformed: u64,
    /// Service requests answered, by any service.
    pub requests_answered: u64,
    /// Requests to this node for a service it does not serve (ignored, as the spec allows).
    pub requests_unserved: u64,
}

fn collect(frames: TransferFrames<'_>) -> Vec<RawCanFrame> {
    frames
        .filter_map(|f| {
            // Our own framer emits valid lengths only; a failure here would be a bug, so it
            // is dropped rather than sent malformed.
            if f.is_fd {
                RawCanFrame::fd(f.id, &f.data).ok()
            } else {
                RawCanFrame::classic(f.id, &f.data).ok()
            }
        })
        .collect()
}

impl CyphalNode {
    pub fn new(node_id: u8, fd: bool, identity: NodeIdentity) -> Self {
        Self {
            node_id,
            mtu: if fd { Mtu::Fd } else { Mtu::Classic },
            identity,
            heartbeat_transfer_id: 0,
            port_list_transfer_id: 0,
            last_troubles: None,
            trainer_restarting: false,
            trainer_gave_up: false,
            published: Vec::new(),
            subscribed: Vec::new(),
            registers: None,
            requests_malformed: 0,
            requests_answered: 0,
            requests_unserved: 0,
        }
        .with_subjects(&SubjectIds::default())
    }

    /// Announces these subject-IDs in `uavcan.node.port.List`.
    pub fn with_subjects(mut self, subjects: &SubjectIds) -> Self {
        self.published = [HEARTBEAT_SUBJECT_ID, PORT_LIST_SUBJECT_ID].to_vec();
        self.published.extend(subjects.of(Direction::Publish));
        self.subscribed = subjects.of(Direction::Subscribe);
        self
    }

    /// Serves `uavcan.register.Access` and `List` from `registers`.
    pub fn with_registers(mut self, registers: Registers) -> Self {
        self.registers = Some(registers);
        self
    }

    pub fn registers(&self) -> Option<&Registers> {
        self.registers.as_ref()
    }

    /// Lists `subject_id` as published too (predictions on CAN FD), before the first
    /// heartbeat: the ports are fixed at start.
    pub(crate) fn publish_also(&mut self, subject_id: u16) {
        if !self.published.contains(&subject_id) {
            self.published.push(subject_id);
        }
    }

    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    pub fn trainer_faulted(&mut self, gave_up: bool) {
        self.trainer_restarting = !gave_up;
        self.trainer_gave_up = gave_up;
    }

    pub fn trainer_restored(&mut self) {
        self.trainer_restarting = false;
        self.trainer_gave_up = false;
    }

    /// The heartbeat for this second, from the component's health status.
    pub fn heartbeat(&mut self, status: &NodeStatus) -> Heartbeat {
        // The first heartbeat compares with zero: errors before it are news too.
        let last = self.last_troubles.unwrap_or(NodeStatus {
            frames_dropped: 0,
            decode_errors: 0,
            crc_errors: 0,
            send_errors: 0,
            ..*status
        });
        let rose = status.frames_dropped > last.frames_dropped
            || status.decode_errors > last.decode_errors
            || status.crc_errors > last.crc_errors
            || status.send_errors > last.send_errors;
        self.last_troubles = Some(*status);
        let health = if self.trainer_gave_up {
            NodeHealth::Warning
        } else if self.trainer_restarting {
            NodeHealth::Caution
        } else if rose {
            NodeHealth::Advisory
        } else {
            NodeHealth::Nominal
        };
        Heartbeat {
            uptime_s: status.uptime_s,
            health,
            mode: NodeMode::Operational,
            vendor_specific_status_code: match status.mode {
                Mode::Idle => 0,
                Mode::Train => 1,
                Mode::PredictOnly => 2,
            },
        }
    }

    /// The CAN frames of one heartbeat, followed by those of the port list when it is due;
    /// advances the transfer-IDs.
    pub fn heartbeat_frames(&mut self, heartbeat: &Heartbeat) -> Vec<RawCanFrame> {
        let port_list_due = self
            .heartbeat_transfer_id
            .is_multiple_of(PORT_LIST_EVERY_HEARTBEATS);
        let mut frames = self.message_frames(HEARTBEAT_SUBJECT_ID, &heartbeat.encode());
        self.heartbeat_transfer_id += 1;
        if port_list_due {
            let list = PortList {
                publishers: &self.published,
                subscribers: &self.subscribed,
                servers: if self.registers.is_some() {
                    &SERVED_SERVICES_WITH_REGISTERS
                } else {
                    &SERVED_SERVICES
                },
            };
            let mut payload = vec![0u8; list.encoded_len()];
            if let Ok(len) = list.encode(&mut payload) {
                frames.extend(self.message_frames(PORT_LIST_SUBJECT_ID, &payload[..len]));
                self.port_list_transfer_id += 1;
            }
        }
        frames
    }

    fn message_frames(&self, subject_id: u16, payload: &[u8]) -> Vec<RawCanFrame> {
        let header = TransferHeader {
            priority: Priority::Nominal,
            subject_id,
            source_node_id: self.node_id,
            transfer_id: if subject_id == PORT_LIST_SUBJECT_ID {
                self.port_list_transfer_id
            } else {
                self.heartbeat_transfer_id
            },
        };
        match transfer_frames(&header, payload, self.mtu) {
            Ok(frames) => collect(frames),
            Err(_) => Vec::new(), // unreachable: node-ID validated at start
        }
    }

    /// The response payload to a request, or `None` (unserved or malformed, counted).
    fn respond(&mut self, request: &ServiceRequest<'_>, out: &mut [u8]) -> Option<usize> {
        match (request.id.service_id, self.registers.as_mut()) {
            (GET_INFO_SERVICE_ID, _) => {
                let mut payload = [0u8; GET_INFO_MAX_BYTES];
                let len = GetInfoResponse {
                    hardware_version: (0, 0),
                    software_version: self.identity.software_version,
                    software_vcs_revision_id: self.identity.software_vcs_revision_id,
                    unique_id: self.identity.unique_id,
                    name: &self.identity.name,
                }
                .encode(&mut payload)
                .ok()?;
                out.get_mut(..len)?.copy_from_slice(&payload[..len]);
                Some(len)
            }
            (ACCESS_SERVICE_ID, Some(registers)) => {
                let Ok(access) = AccessRequest::decode(request.payload) else {
                    self.requests_malformed += 1;
                    return None;
                };
                let outcome = registers.access(access.name, &access.value);
                let empty = crate::registers::RegValue::empty();
                let (value, mutable, persistent) = match &outcome {
                    Some(o) => (&o.value, o.mutable, o.persistent),
                    None => (&empty, false, false),
                };
                AccessResponse {
                    timestamp_us: 0, // no time synchronisation: unknown
                    mutable,
                    persistent,
                    value: value.as_value(),
                }
                .encode(out)
                .ok()
            }
            (LIST_SERVICE_ID, Some(registers)) => {
                let index = decode_list_request(request.payload);
                let name = registers.name_at(index).unwrap_or("");
                encode_list_response(name.as_bytes(), out).ok()
            }
            _ => {
                self.requests_unserved += 1;
                None
            }
        }
    }

    /// The response frames to a request addressed to this node, or `None` for a service it
    /// does not serve (counted in `requests_unserved`) or a malformed request (counted in
    /// `requests_malformed`).
    pub fn answer(&mut self, request: &ServiceRequest<'_>) -> Option<Vec<RawCanFrame>> {
        let mut payload = [0u8; ACCESS_RESPONSE_MAX_BYTES];
        let len = self.respond(request, &mut payload)?;
        let response = ServiceCanId {
            priority: request.id.priority,
            service_id: request.id.service_id,
            is_request: false,
            destination_node_id: request.id.source_node_id,
            source_node_id: self.node_id,
        };
        let frames = service_transfer_frames(
            &response,
            u64::from(request.transfer_id),
            &payload[..len],
            self.mtu,
        )
        .ok()?;
        self.requests_answered += 1;
        Some(collect(frames))
    }
}

/// GetInfo's default node name.
pub const DEFAULT_NODE_NAME: &str = "org.example.gsplat.fsw";

/// A configured unique-ID: exactly 32 hex digits.
pub fn parse_unique_id(text: &str) -> Option<[u8; 16]> {
    if text.len() != 32 || !text.is_ascii() {
        return None;
    }
    let mut id = [0u8; 16];
    for (i, byte) in id.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(id)
}

/// The unique-ID when none is configured: /etc/machine-id (128 bits, per machine) with the
/// node-ID XORed into the last byte so that two components on one machine differ; without
/// that file, FNV-1a of the name and node-ID (stable, but unique only per name and node-ID).
pub(crate) fn derived_unique_id(name: &str, node_id: u8) -> [u8; 16] {
    let machine = std::fs::read_to_string("/etc/machine-id")
        .ok()
        .and_then(|text| parse_unique_id(text.trim()));
    let mut id = machine.unwrap_or_else(|| {
        let mut id = [0u8; 16];
        for (half, seed) in [0xcbf2_9ce4_8422_2325u64, 0x84222325_cbf29ce4]
            .iter()
            .enumerate()
        {
            let mut hash = *seed;
            for &b in name.as_bytes().iter().chain([node_id].iter()) {
                hash = (hash ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
            id[8 * half..8 * half + 8].copy_from_slice(&hash.to_le_bytes());
        }
        id
    });
    id[15] ^= node_id;
    id
}

/// The software version GetInfo reports: this crate's major and minor version.
pub fn software_version() -> (u8, u8) {
    let major = env!("CARGO_PKG_VERSION_MAJOR").parse().unwrap_or(0);
    let minor = env!("CARGO_PKG_VERSION_MINOR").parse().unwrap_or(0);
    (major, minor)
}

#[cfg(test)]
mod tests {
    use super::*;
    use interfaces::cyphal::node::parse_service_request;
    use interfaces::cyphal::TailByte;

    fn status(mode: Mode, uptime_s: u32, frames_dropped: u32) -> NodeStatus {
        NodeStatus {
            mode,
            uptime_s,
            frames_dropped,
            decode_errors: 0,
            crc_errors: 0,
            send_errors: 0,
        }
    }

    fn node() -> CyphalNode {
        CyphalNode::new(
            42,
            false,
            NodeIdentity {
                name: "org.example.gsplat.fsw".into(),
                unique_id: [7; 16],
                software_version: (0, 1),
                software_vcs_revision_id: 0,
            },
        )
    }

    #[test]
    fn health_follows_counters_and_trainer_state() {
        let mut n = node();
        let hb = n.heartbeat(&status(Mode::Train, 3, 0));
        assert_eq!(hb.health, NodeHealth::Nominal);
        assert_eq!(hb.vendor_specific_status_code, 1);
        assert_eq!(hb.uptime_s, 3);
        let hb = n.heartbeat(&status(Mode::Train, 4, 2));
        assert_eq!(hb.health, NodeHealth::Advisory, "drops rose");
        let hb = n.heartbeat(&status(Mode::Train, 5, 2));
        assert_eq!(hb.health, NodeHealth::Nominal, "no new drops");
        assert_eq!(
            n.heartbeat(&NodeStatus {
                send_errors: 1,
                ..status(Mode::Train, 6, 2)
            })
            .health,
            NodeHealth::Advisory
        );
        n.trainer_faulted(false);
        let hb = n.heartbeat(&NodeStatus {
            send_errors: 1,
            ..status(Mode::PredictOnly, 7, 2)
        });
        assert_eq!(hb.health, NodeHealth::Caution);
        assert_eq!(hb.vendor_specific_status_code, 2);
        n.trainer_faulted(true);
        let hb = n.heartbeat(&NodeStatus {
            send_errors: 1,
            ..status(Mode::Idle, 8, 2)
        });
        assert_eq!(hb.health, NodeHealth::Warning);
        assert_eq!(hb.vendor_specific_status_code, 0);
        n.trainer_restored();
        assert_eq!(
            n.heartbeat(&NodeStatus {
                send_errors: 1,
                ..status(Mode::Train, 9, 2)
            })
            .health,
            NodeHealth::Nominal
        );
        assert!(
            n.heartbeat(&NodeStatus {
                send_errors: 1,
                ..status(Mode::Train, 9, 2)
            })
            .mode
                == NodeMode::Operational,
            "every component mode is operational"
        );
    }

    #[test]
    fn heartbeat_frames_carry_node_id_and_advancing_transfer_ids() {
        let mut n = node();
        let hb = n.heartbeat(&status(Mode::Train, 0, 0));
        for expected_tid in 0..3u8 {
            let frames = n.heartbeat_frames(&hb);
            let port_list = frames.len() - 1;
            // 166-byte port list + CRC on classic CAN: 24 frames, with the first heartbeat only.
            assert_eq!(port_list, if expected_tid == 0 { 24 } else { 0 });
            if port_list > 0 {
                let id = frames[1].id();
                assert_eq!((id >> 8) & 0x1FFF, u32::from(PORT_LIST_SUBJECT_ID));
            }
            assert_eq!(frames[0].id(), 0x107D_552A, "subject 7509 from node 42");
            let tail = TailByte::from_byte(*frames[0].data().last().unwrap());
            assert_eq!(tail.transfer_id, expected_tid);
            assert_eq!(&frames[0].data()[..7], &hb.encode());
        }
    }

    #[test]
    fn unique_ids_parse_and_derive() {
        let id = parse_unique_id("000102030405060708090a0b0c0d0eFF").unwrap();
        assert_eq!(id[1], 1);
        assert_eq!(id[15], 0xFF);
        assert!(parse_unique_id("0001").is_none());
        assert!(parse_unique_id("zz0102030405060708090a0b0c0d0e0f").is_none());
        let a = derived_unique_id("n", 1);
        assert_eq!(a, derived_unique_id("n", 1), "stable");
        assert_ne!(a, derived_unique_id("n", 2), "node-ID changes it");
    }

    #[test]
    fn node_name_and_unique_id_are_validated_in_the_config() {
        use crate::config::ComponentConfig;
        use std::path::Path;
        let parse = |text: &str| ComponentConfig::from_toml_str(text, Path::new("t.toml"));
        let config =
            parse("[node]\nname = \"a.b\"\nunique_id = \"000102030405060708090a0b0c0d0e0f\"\n")
                .unwrap();
        assert_eq!(config.node.name, "a.b");
        for bad in [
            "[node]\nname = \"\"\n",
            &format!("[node]\nname = \"{}\"\n", "n".repeat(51)),
            "[node]\nunique_id = \"0011\"\n",
        ] {
            let message = parse(bad).unwrap_err().to_string();
            assert!(message.contains("node."), "{message}");
        }
    }

    #[test]
    fn get_info_is_answered_and_other_services_are_not() {
        let mut n = node();
        // GetInfo request from node 123, transfer-ID 5, priority High.
        let id = ServiceCanId {
            priority: Priority::High,
            service_id: GET_INFO_SERVICE_ID,
            is_request: true,
            destination_node_id: 42,
            source_node_id: 123,
        }
        .to_raw()
        .unwrap();
        let data = [0xE5];
        let request = parse_service_request(id, &data, 42).unwrap();
        let frames = n.answer(&request).unwrap();
        let response = ServiceCanId::from_raw(frames[0].id()).unwrap();
        assert!(!response.is_request);
        assert_eq!(response.priority, Priority::High);
        assert_eq!(response.destination_node_id, 123);
        assert_eq!(response.source_node_id, 42);
        assert!(frames
            .iter()
            .all(|f| TailByte::from_byte(*f.data().last().unwrap()).transfer_id == 5));
        assert_eq!(n.requests_answered, 1);
        let other = ServiceRequest {
            id: ServiceCanId {
                service_id: 384,
                ..request.id
            },
            ..request
        };
        assert!(n.answer(&other).is_none());
        assert_eq!(n.requests_unserved, 1);
    }

    #[test]
    fn register_requests_are_answered_and_malformed_ones_counted() {
        use crate::config::ComponentConfig;
        use crate::registers::{RegValue, Registers};
        use interfaces::cyphal::service_rx::ServiceRequestRx;
        use interfaces::cyphal::{service_transfer_frames, Mtu};
        let mut n = node().with_registers(Registers::new(&ComponentConfig::default()));
        let mut rx = ServiceRequestRx::<_, 1>::new(vec![0u8; 1024]);
        let mut call = |n: &mut CyphalNode, service_id: u16, payload: &[u8], tid: u64| {
            let id = ServiceCanId {
                priority: Priority::Nominal,
                service_id,
                is_request: true,
                destination_node_id: 42,
                source_node_id: 9,
            };
            let frames: Vec<_> = service_transfer_frames(&id, tid, payload, Mtu::Classic)
                .unwrap()
                .collect();
            let mut answer = None;
            for f in &frames {
                if let Some(request) = rx.push(f.id, &f.data, 42, 0).unwrap() {
                    answer = n.answer(&request);
                }
            }
            answer.map(|frames| {
                // Our response's payload: the frames' data without tail bytes (and the CRC).
                let mut bytes: Vec<u8> = frames
                    .iter()
                    .flat_map(|f| f.data()[..f.data().len() - 1].to_vec())
                    .collect();
                if frames.len() > 1 {
                    bytes.truncate(bytes.len() - 2);
                }
                bytes
            })
        };
        // Access read of a port-ID register: a multi-frame request on classic CAN.
        let mut request = vec![27u8];
        request.extend_from_slice(b"uavcan.pub.health_status.id");
        request.push(0);
        let response = call(&mut n, ACCESS_SERVICE_ID, &request, 0).unwrap();
        let decoded = AccessResponse::decode(&response).unwrap();
        assert_eq!(
            RegValue::from_value(&decoded.value),
            RegValue::natural16(400)
        );
        assert!(decoded.persistent && !decoded.mutable);
        // List index 0 is uavcan.node.id; far past the end the name is empty.
        let response = call(&mut n, LIST_SERVICE_ID, &[0, 0], 1).unwrap();
        assert_eq!(&response[..15], b"\x0euavcan.node.id");
        assert_eq!(
            call(&mut n, LIST_SERVICE_ID, &[0xFF, 0xFF], 2).unwrap(),
            [0]
        );
        // An unknown union tag is malformed: counted, not answered.
        let bad = [1u8, b'x', 99];
        assert!(call(&mut n, ACCESS_SERVICE_ID, &bad, 3).is_none());
        assert_eq!(n.requests_malformed, 1);
        assert_eq!(n.requests_answered, 3);
    }
}
