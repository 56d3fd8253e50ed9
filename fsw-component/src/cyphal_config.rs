//! The `[cyphal]` section of component.toml: the subject-ID of each catalogue message on
//! CAN, the node-IDs telemetry is taken from, and the register file.
//!
//! Invariants (checked by [`CyphalConfig::validate`], at start): every subject-ID is in the
//! Cyphal unregulated range 0..=6143 and the eight are distinct (a subject published and
//! subscribed would be heard as our own input); a telemetry source node-ID is 0..=127, is not
//! this node's, and AOCS and navigation differ, or it is `ANY_NODE` (no source filter).
//! The defaults are the ICD's port numbers (`interfaces::messages::port`), so a file without
//! this section behaves as before. UDP keeps the ICD numbers as CCSDS APIDs whatever is set
//! here: these are Cyphal subject-IDs only.

use interfaces::messages::{
    port, CameraFrame, Command, CommandAck, Event, HealthStatus, Message, RenderedPrediction,
    SunVector, TargetPose,
};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// A telemetry source node-ID meaning "any node" (the Cyphal value for an unset node-ID).
pub(crate) const ANY_NODE: u16 = 0xFFFF;
/// Largest subject-ID outside the ranges reserved for fixed port-IDs.
pub(crate) const MAX_DYNAMIC_SUBJECT_ID: u16 = 6143;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CyphalConfig {
    /// Where register writes (`uavcan.register.Access`) are kept; read at start, its values
    /// override this file's. "" keeps no file, and then every register is read-only.
    pub register_file: PathBuf,
    /// Node-ID whose `SunVector` transfers are taken on CAN; 65535: any node.
    pub aocs_node_id: u16,
    /// Node-ID whose `TargetPose` transfers are taken on CAN; 65535: any node.
    pub navigation_node_id: u16,
    pub subjects: SubjectIds,
}

/// Subject-ID of each catalogue message on Cyphal/CAN.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SubjectIds {
    pub sun_vector: u16,
    pub target_pose: u16,
    pub camera_frame: u16,
    pub command: u16,
    pub command_ack: u16,
    pub health_status: u16,
    pub event: u16,
    /// Used only with predictions on CAN FD (`[can] predictions`).
    pub rendered_prediction: u16,
}

impl Default for CyphalConfig {
    fn default() -> Self {
        Self {
            register_file: PathBuf::new(),
            aocs_node_id: ANY_NODE,
            navigation_node_id: ANY_NODE,
            subjects: SubjectIds::default(),
        }
    }
}

impl Default for SubjectIds {
    fn default() -> Self {
        Self {
            sun_vector: port::SUN_VECTOR,
            target_pose: port::TARGET_POSE,
            camera_frame: port::CAMERA_FRAME,
            command: port::COMMAND,
            command_ack: port::COMMAND_ACK,
            health_status: port::HEALTH_STATUS,
            event: port::EVENT,
            rendered_prediction: port::RENDERED_PREDICTION,
        }
    }
}

/// Whether the component publishes or subscribes a port.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    Publish,
    Subscribe,
}

/// One catalogue message on CAN: its register name (`uavcan.pub|sub.<name>.id`), the ICD
/// port number (the subject-ID default and the UDP APID) and its type name.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PortSpec {
    pub name: &'static str,
    pub icd_port: u16,
    pub direction: Direction,
    /// False for a port in use only when configured (predictions on CAN FD): port.List
    /// and the inbound filter leave it out, its subject-ID is still reserved.
    pub always: bool,
    pub type_name: fn() -> String,
}

/// `<namespace>.<Name>.<major>.<minor>`, the `uavcan.pub|sub.*.type` register value (the
/// messages are postcard-encoded, not DSDL: the namespace says they are the project's).
fn type_name<M: Message>() -> String {
    format!(
        "gsplat.{}.{}.{}",
        M::NAME,
        M::VERSION.major,
        M::VERSION.minor
    )
}

/// Every port, subscriptions first; the order of the subject-ID fields.
pub(crate) const PORTS: [PortSpec; 8] = [
    PortSpec {
        name: "sun_vector",
        icd_port: port::SUN_VECTOR,
        direction: Direction::Subscribe,
        always: true,
        type_name: type_name::<SunVector>,
    },
    PortSpec {
        name: "target_pose",
        icd_port: port::TARGET_POSE,
        direction: Direction::Subscribe,
        always: true,
        type_name: type_name::<TargetPose>,
    },
    PortSpec {
        name: "camera_frame",
        icd_port: port::CAMERA_FRAME,
        direction: Direction::Subscribe,
        always: true,
        type_name: type_name::<CameraFrame<'static>>,
    },
    PortSpec {
        name: "command",
        icd_port: port::COMMAND,
        direction: Direction::Subscribe,
        always: true,
        type_name: type_name::<Command>,
    },
    PortSpec {
        name: "command_ack",
        icd_port: port::COMMAND_ACK,
        direction: Direction::Publish,
        always: true,
        type_name: type_name::<CommandAck>,
    },
    PortSpec {
        name: "health_status",
        icd_port: port::HEALTH_STATUS,
        direction: Direction::Publish,
        always: true,
        type_name: type_name::<HealthStatus>,
    },
    PortSpec {
        name: "event",
        icd_port: port::EVENT,
        direction: Direction::Publish,
        always: true,
        type_name: type_name::<Event>,
    },
    PortSpec {
        name: "rendered_prediction",
        icd_port: port::RENDERED_PREDICTION,
        direction: Direction::Publish,
        always: false,
        type_name: type_name::<RenderedPrediction<'static>>,
    },
];

impl SubjectIds {
    /// The subject-ID of `PORTS[index]`.
    pub fn get(&self, index: usize) -> Option<u16> {
        self.as_array().get(index).copied()
    }

    pub fn get_mut(&mut self, index: usize) -> Option<&mut u16> {
        let s = self;
        Some(match index {
            0 => &mut s.sun_vector,
            1 => &mut s.target_pose,
            2 => &mut s.camera_frame,
            3 => &mut s.command,
            4 => &mut s.command_ack,
            5 => &mut s.health_status,
            6 => &mut s.event,
            7 => &mut s.rendered_prediction,
            _ => return None,
        })
    }

    pub fn as_array(&self) -> [u16; 8] {
        [
            self.sun_vector,
            self.target_pose,
            self.camera_frame,
            self.command,
            self.command_ack,
            self.health_status,
            self.event,
            self.rendered_prediction,
        ]
    }

    /// The configured subject-ID of the message with ICD port `icd_port`.
    pub(crate) fn subject_of(&self, icd_port: u16) -> Option<u16> {
        let index = PORTS.iter().position(|p| p.icd_port == icd_port)?;
        self.get(index)
    }

    /// The ICD port of the message configured on subject `subject_id`.
    pub(crate) fn icd_port_of(&self, subject_id: u16) -> Option<u16> {
        let index = self.as_array().iter().position(|&s| s == subject_id)?;
        Some(PORTS[index].icd_port)
    }

    /// The configured subject-IDs of one direction's always-used ports, in `PORTS` order.
    pub fn of(&self, direction: Direction) -> Vec<u16> {
        PORTS
            .iter()
            .zip(self.as_array())
            .filter(|(p, _)| p.direction == direction && p.always)
            .map(|(_, s)| s)
            .collect()
    }
}

/// What is wrong, and with which key (`cyphal.` + the key).
#[derive(Debug, PartialEq, Eq)]
pub struct CyphalConfigError {
    pub key: String,
    pub problem: String,
}

impl CyphalConfig {
    pub fn validate(&self, own_node_id: u8) -> Result<(), CyphalConfigError> {
        let error = |key: String, problem: String| Err(CyphalConfigError { key, problem });
        let ids = self.subjects.as_array();
        for (i, (spec, &id)) in PORTS.iter().zip(ids.iter()).enumerate() {
            let key = format!("cyphal.subjects.{}", spec.name);
            if id > MAX_DYNAMIC_SUBJECT_ID {
                return error(
                    key,
                    format!(
                        "{id} is outside 0..={MAX_DYNAMIC_SUBJECT_ID} (higher subject-IDs are \
                         reserved for fixed port-IDs)"
                    ),
                );
            }
            if let Some(j) = ids[..i].iter().position(|&other| other == id) {
                return error(
                    key,
                    format!("{id} is also cyphal.subjects.{}", PORTS[j].name),
                );
            }
        }
        for (key, id) in [
            ("cyphal.aocs_node_id", self.aocs_node_id),
            ("cyphal.navigation_node_id", self.navigation_node_id),
        ] {
            if id == ANY_NODE {
                continue;
            }
            if id > u16::from(crate::config::MAX_NODE_ID) {
                return error(
                    key.into(),
                    format!("{id} is neither a node-ID (0..=127) nor {ANY_NODE} (any node)"),
                );
            }
            if id == u16::from(own_node_id) {
                return error(key.into(), format!("{id} is this component's node-ID"));
            }
        }
        if self.aocs_node_id != ANY_NODE && self.aocs_node_id == self.navigation_node_id {
            return error(
                "cyphal.navigation_node_id".into(),
                format!("{} is also cyphal.aocs_node_id", self.navigation_node_id),
            );
        }
        Ok(())
    }

    /// Whether a telemetry transfer on ICD port `icd_port` from `source` is taken: Sun
    /// vectors from the AOCS node, poses from the navigation node (when configured).
    pub(crate) fn accepts_source(&self, icd_port: u16, source: Option<u8>) -> bool {
        let wanted = match icd_port {
            port::SUN_VECTOR => self.aocs_node_id,
            port::TARGET_POSE => self.navigation_node_id,
            _ => return true,
        };
        wanted == ANY_NODE || source.map(u16::from) == Some(wanted)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_icd_ports_and_validate() {
        let config = CyphalConfig::default();
        assert_eq!(config.validate(42), Ok(()));
        for spec in PORTS {
            assert_eq!(
                config.subjects.subject_of(spec.icd_port),
                Some(spec.icd_port)
            );
        }
        assert_eq!(
            config.subjects.of(Direction::Subscribe),
            [
                port::SUN_VECTOR,
                port::TARGET_POSE,
                port::CAMERA_FRAME,
                port::COMMAND
            ]
        );
        assert_eq!(
            config.subjects.of(Direction::Publish),
            [port::COMMAND_ACK, port::HEALTH_STATUS, port::EVENT]
        );
        assert_eq!((PORTS[0].type_name)(), "gsplat.SunVector.1.1");
        assert!(config.accepts_source(port::SUN_VECTOR, None));
    }

    #[test]
    fn moved_ports_map_both_ways() {
        let mut config = CyphalConfig::default();
        config.subjects.sun_vector = 1000;
        assert_eq!(config.subjects.icd_port_of(1000), Some(port::SUN_VECTOR));
        assert_eq!(config.subjects.icd_port_of(port::SUN_VECTOR), None);
        assert_eq!(config.subjects.subject_of(port::SUN_VECTOR), Some(1000));
        *config.subjects.get_mut(6).unwrap() = 7;
        assert_eq!(config.subjects.event, 7);
        *config.subjects.get_mut(7).unwrap() = 8;
        assert_eq!(config.subjects.rendered_prediction, 8);
        assert!(config.subjects.get_mut(PORTS.len()).is_none());
    }

    #[test]
    fn bad_ids_name_their_key() {
        let key = |f: fn(&mut CyphalConfig)| {
            let mut config = CyphalConfig::default();
            f(&mut config);
            config.validate(42).unwrap_err().key
        };
        assert_eq!(key(|c| c.subjects.event = 7509), "cyphal.subjects.event");
        assert_eq!(key(|c| c.subjects.command = 100), "cyphal.subjects.command");
        assert_eq!(key(|c| c.aocs_node_id = 128), "cyphal.aocs_node_id");
        assert_eq!(key(|c| c.aocs_node_id = 42), "cyphal.aocs_node_id");
        assert_eq!(
            key(|c| {
                c.aocs_node_id = 10;
                c.navigation_node_id = 10;
            }),
            "cyphal.navigation_node_id"
        );
    }

    #[test]
    fn telemetry_sources_are_filtered_when_configured() {
        let config = CyphalConfig {
            aocs_node_id: 10,
            navigation_node_id: 11,
            ..CyphalConfig::default()
        };
        assert!(config.accepts_source(port::SUN_VECTOR, Some(10)));
        assert!(!config.accepts_source(port::SUN_VECTOR, Some(11)));
        assert!(!config.accepts_source(port::SUN_VECTOR, None));
        assert!(config.accepts_source(port::TARGET_POSE, Some(11)));
        assert!(!config.accepts_source(port::TARGET_POSE, Some(10)));
        assert!(config.accepts_source(port::CAMERA_FRAME, Some(99)));
    }
}
