//! Command authorisation: who may command, arm-then-execute for destructive commands, and
//! a rate limit and size bound for expensive ones (the `[commands]` configuration section).
//!
//! - **Sources**: on CAN, the transfer's source node-ID must be in `can_source_nodes`;
//!   anonymous transfers never command. On UDP, a command must arrive as a CCSDS
//!   telecommand packet on the socket named by `udp_socket` (default: the telemetry port,
//!   never the camera-frame port). A replayed UDP recording does not record the socket, so
//!   replayed telecommand packets count as arriving on the command socket.
//! - **Arming**: RESET_MODEL and LOAD_CHECKPOINT execute only within `arm_timeout_ms` after
//!   an ARM naming their opcode, from the same source; executing consumes the arm.
//! - **RENDER**: a token bucket (`render_burst` tokens, one more every `render_interval_ms`)
//!   and an image bounded to `render_max_pixels` (larger frame sizes are divided by the
//!   smallest integer factor that fits).
//!
//! Invariants: the gate never panics on any input; its decisions depend only on the
//! commands and the receive times given to it (deterministic on replay).

use interfaces::ccsds::PacketType;
use interfaces::messages::CommandKind;
use serde::{Deserialize, Serialize};
use std::fmt;

/// Largest Cyphal/CAN node-ID.
const MAX_NODE_ID: u8 = 127;
/// Upper bound of `arm_timeout_ms`: an arm must not outlive an operator's attention.
pub(crate) const MAX_ARM_TIMEOUT_MS: u64 = 600_000;
/// Upper bound of `render_burst` (the command queue holds 16 by default).
pub(crate) const MAX_RENDER_BURST: u32 = 64;
/// Upper bound of `render_max_pixels` (the largest UDP camera frame is ~1 MiB).
pub(crate) const MAX_RENDER_PIXELS: u32 = 1 << 20;

/// The receiving UDP socket a datagram came in on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UdpIngress {
    Frames,
    Telemetry,
    /// From a replayed recording, which does not record the socket.
    Replayed,
}

/// Where a command came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum CommandSource {
    /// `node_id` is `None` for anonymous transfers.
    Can { node_id: Option<u8> },
    Udp {
        ingress: UdpIngress,
        packet_type: PacketType,
    },
}

/// The UDP socket that accepts commands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum UdpCommandSocket {
    Telemetry,
    Frames,
    /// No commanding over UDP.
    None,
}

/// The `[commands]` section of the configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CommandConfig {
    /// Cyphal/CAN source node-IDs allowed to command; anonymous transfers never command.
    pub can_source_nodes: Vec<u8>,
    /// The UDP socket that accepts telecommand packets.
    pub udp_socket: UdpCommandSocket,
    /// How long an ARM stays valid, milliseconds.
    pub arm_timeout_ms: u64,
    /// RENDER commands accepted back to back.
    pub render_burst: u32,
    /// One more RENDER token per this interval, milliseconds.
    pub render_interval_ms: u64,
    /// Largest RENDER image, pixels.
    pub render_max_pixels: u32,
}

impl Default for CommandConfig {
    fn default() -> Self {
        Self {
            can_source_nodes: vec![1],
            udp_socket: UdpCommandSocket::Telemetry,
            arm_timeout_ms: 10_000,
            render_burst: 4,
            render_interval_ms: 1_000,
            render_max_pixels: 512 * 512,
        }
    }
}

impl CommandConfig {
    /// The validated policy, or the offending key and why.
    pub fn policy(&self) -> Result<CommandPolicy, (&'static str, String)> {
        let mut can_nodes = 0u128;
        for &node in &self.can_source_nodes {
            if node > MAX_NODE_ID {
                return Err((
                    "commands.can_source_nodes",
                    format!("{node} is above the Cyphal maximum {MAX_NODE_ID}"),
                ));
            }
            can_nodes |= 1 << node;
        }
        if !(1..=MAX_ARM_TIMEOUT_MS).contains(&self.arm_timeout_ms) {
            return Err((
                "commands.arm_timeout_ms",
                format!("must be within 1..={MAX_ARM_TIMEOUT_MS}"),
            ));
        }
        if !(1..=MAX_RENDER_BURST).contains(&self.render_burst) {
            return Err((
                "commands.render_burst",
                format!("must be within 1..={MAX_RENDER_BURST}"),
            ));
        }
        if self.render_interval_ms == 0 {
            return Err(("commands.render_interval_ms", "must be at least 1".into()));
        }
        if !(1..=MAX_RENDER_PIXELS).contains(&self.render_max_pixels) {
            return Err((
                "commands.render_max_pixels",
                format!("must be within 1..={MAX_RENDER_PIXELS}"),
            ));
        }
        Ok(CommandPolicy {
            can_nodes,
            udp_socket: self.udp_socket,
            arm_timeout_us: self.arm_timeout_ms * 1_000,
            render_burst: self.render_burst,
            render_interval_us: self.render_interval_ms.saturating_mul(1_000),
            render_max_pixels: self.render_max_pixels,
        })
    }
}

/// Validated authorisation settings (times in microseconds).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CommandPolicy {
    /// Bit n set: node-ID n may command.
    can_nodes: u128,
    udp_socket: UdpCommandSocket,
    arm_timeout_us: u64,
    render_burst: u32,
    render_interval_us: u64,
    render_max_pixels: u32,
}

impl Default for CommandPolicy {
    fn default() -> Self {
        match CommandConfig::default().policy() {
            Ok(policy) => policy,
            Err((key, why)) => unreachable!("default {key} invalid: {why}"),
        }
    }
}

/// Why a command from an authorised source was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// A destructive command without a valid ARM from the same source.
    NotArmed,
    /// RENDER above the rate limit.
    RateLimited,
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NotArmed => write!(f, "destructive command without a valid ARM"),
            Self::RateLimited => write!(f, "RENDER above its rate limit"),
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Armed {
    opcode: u32,
    source: CommandSource,
    expires_us: u64,
}

/// Authorisation state: the pending arm and the RENDER tokens.
#[derive(Clone, Debug)]
pub struct CommandGate {
    policy: CommandPolicy,
    armed: Option<Armed>,
    render_tokens: u32,
    /// Receive time the tokens were last topped up to.
    render_refilled_us: Option<u64>,
}

impl CommandGate {
    pub fn new(policy: CommandPolicy) -> Self {
        Self {
            policy,
            armed: None,
            render_tokens: policy.render_burst,
            render_refilled_us: None,
        }
    }

    /// Whether `source` may command at all (checked before the bytes are decoded).
    pub(crate) fn authorises(&self, source: CommandSource) -> bool {
        match source {
            CommandSource::Can { node_id: None } => false,
            CommandSource::Can {
                node_id: Some(node),
            } => node <= MAX_NODE_ID && self.policy.can_nodes & (1 << node) != 0,
            CommandSource::Udp {
                ingress,
                packet_type,
            } => {
                packet_type == PacketType::Telecommand
                    && match (ingress, self.policy.udp_socket) {
                        (_, UdpCommandSocket::None) => false,
                        (UdpIngress::Replayed, _) => true,
                        (UdpIngress::Telemetry, socket) => socket == UdpCommandSocket::Telemetry,
                        (UdpIngress::Frames, socket) => socket == UdpCommandSocket::Frames,
                    }
            }
        }
    }

    /// Arming, arm checks and rate limits for a decoded command from an authorised source.
    pub(crate) fn admit(
        &mut self,
        kind: &CommandKind,
        source: CommandSource,
        now_us: u64,
    ) -> Result<(), Refusal> {
        match *kind {
            CommandKind::Arm(opcode) => {
                self.armed = Some(Armed {
                    opcode,
                    source,
                    expires_us: now_us.saturating_add(self.policy.arm_timeout_us),
                });
                Ok(())
            }
            CommandKind::ResetModel | CommandKind::LoadCheckpoint => {
                let opcode = kind.opcode();
                match self.armed {
                    Some(a)
                        if a.opcode == opcode && a.source == source && now_us <= a.expires_us =>
                    {
                        self.armed = None;
                        Ok(())
                    }
                    _ => Err(Refusal::NotArmed),
                }
            }
            CommandKind::Render(_) => self.take_render_token(now_us),
            _ => Ok(()),
        }
    }

    fn take_render_token(&mut self, now_us: u64) -> Result<(), Refusal> {
        let interval = self.policy.render_interval_us;
        match self.render_refilled_us {
            None => self.render_refilled_us = Some(now_us),
            Some(at) if now_us > at => {
                let earned = (now_us - at) / interval;
                let tokens = u64::from(self.render_tokens).saturating_add(earned);
                self.render_tokens = u32::try_from(tokens)
                    .unwrap_or(u32::MAX)
                    .min(self.policy.render_burst);
                // Keep the fraction of an interval already elapsed towards the next token.
                self.render_refilled_us = Some(if self.render_tokens == self.policy.render_burst {
                    now_us
                } else {
                    at + earned * interval
                });
            }
            // A receive time before the last refill (replay of merged logs): no new token.
            Some(_) => {}
        }
        if self.render_tokens == 0 {
            return Err(Refusal::RateLimited);
        }
        self.render_tokens -= 1;
        Ok(())
    }

    /// The smallest integer factor that brings a RENDER image of the camera frame's size
    /// within `render_max_pixels` (each side at least 1 pixel).
    pub(crate) fn render_downsample(&self, width: u16, height: u16) -> u16 {
        let max = u64::from(self.policy.render_max_pixels);
        let pixels = |k: u16| u64::from((width / k).max(1)) * u64::from((height / k).max(1));
        let mut k = 1u16;
        while pixels(k) > max && k < u16::MAX {
            k += 1;
        }
        k
    }

    /// The RENDER image size for a camera frame size: divided by
    /// `CommandGate::render_downsample` (at least 1 x 1).
    pub fn render_size(&self, width: u16, height: u16) -> (u16, u16) {
        let k = self.render_downsample(width, height);
        ((width / k).max(1), (height / k).max(1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use interfaces::messages::RenderRequest;

    const GROUND: CommandSource = CommandSource::Udp {
        ingress: UdpIngress::Telemetry,
        packet_type: PacketType::Telecommand,
    };

    fn render() -> CommandKind {
        CommandKind::Render(RenderRequest {
            q_camera_from_target: [1.0, 0.0, 0.0, 0.0],
            t_camera_from_target_m: [0.0, 0.0, 10.0],
            sun_target: [0.0, 0.0, 1.0],
        })
    }

    #[test]
    fn default_sources() {
        let gate = CommandGate::new(CommandPolicy::default());
        assert!(gate.authorises(GROUND));
        assert!(gate.authorises(CommandSource::Can { node_id: Some(1) }));
        for denied in [
            CommandSource::Can { node_id: None },
            CommandSource::Can { node_id: Some(10) },
            CommandSource::Can { node_id: Some(200) },
            CommandSource::Udp {
                ingress: UdpIngress::Frames,
                packet_type: PacketType::Telecommand,
            },
            CommandSource::Udp {
                ingress: UdpIngress::Telemetry,
                packet_type: PacketType::Telemetry,
            },
        ] {
            assert!(!gate.authorises(denied), "{denied:?}");
        }
        let none = CommandConfig {
            udp_socket: UdpCommandSocket::None,
            ..CommandConfig::default()
        };
        let gate = CommandGate::new(none.policy().unwrap());
        assert!(!gate.authorises(GROUND));
    }

    #[test]
    fn arm_then_execute_within_the_timeout_from_the_same_source() {
        let mut gate = CommandGate::new(CommandPolicy::default());
        let reset = CommandKind::ResetModel;
        assert_eq!(gate.admit(&reset, GROUND, 0), Err(Refusal::NotArmed));
        gate.admit(&CommandKind::Arm(CommandKind::RESET_MODEL), GROUND, 0)
            .unwrap();
        // Armed for RESET_MODEL, not for LOAD_CHECKPOINT, and not for another source.
        assert_eq!(
            gate.admit(&CommandKind::LoadCheckpoint, GROUND, 1),
            Err(Refusal::NotArmed)
        );
        let can = CommandSource::Can { node_id: Some(1) };
        assert_eq!(gate.admit(&reset, can, 1), Err(Refusal::NotArmed));
        assert_eq!(gate.admit(&reset, GROUND, 10_000_000), Ok(()));
        assert_eq!(
            gate.admit(&reset, GROUND, 10_000_001),
            Err(Refusal::NotArmed)
        );
        gate.admit(&CommandKind::Arm(CommandKind::RESET_MODEL), GROUND, 0)
            .unwrap();
        assert_eq!(
            gate.admit(&reset, GROUND, 10_000_001),
            Err(Refusal::NotArmed)
        );
    }

    #[test]
    fn render_tokens_refill_at_the_configured_interval() {
        let mut gate = CommandGate::new(CommandPolicy::default());
        for _ in 0..4 {
            assert_eq!(gate.admit(&render(), GROUND, 5_000_000), Ok(()));
        }
        assert_eq!(
            gate.admit(&render(), GROUND, 5_000_000),
            Err(Refusal::RateLimited)
        );
        assert_eq!(
            gate.admit(&render(), GROUND, 5_999_999),
            Err(Refusal::RateLimited)
        );
        assert_eq!(gate.admit(&render(), GROUND, 6_000_000), Ok(()));
        assert_eq!(
            gate.admit(&render(), GROUND, 6_500_000),
            Err(Refusal::RateLimited)
        );
        // A long pause fills the bucket up to the burst, not beyond.
        for _ in 0..4 {
            assert_eq!(gate.admit(&render(), GROUND, 100_000_000), Ok(()));
        }
        assert_eq!(
            gate.admit(&render(), GROUND, 100_000_000),
            Err(Refusal::RateLimited)
        );
    }

    #[test]
    fn render_size_is_bounded() {
        let gate = CommandGate::new(CommandPolicy::default());
        assert_eq!(gate.render_size(64, 64), (64, 64));
        assert_eq!(gate.render_size(512, 512), (512, 512));
        assert_eq!(gate.render_size(1024, 1024), (512, 512));
        assert_eq!(gate.render_size(640, 480), (320, 240));
        assert_eq!(gate.render_size(u16::MAX, 1), (65535, 1));
        let (w, h) = gate.render_size(u16::MAX, u16::MAX);
        assert!(u32::from(w) * u32::from(h) <= 512 * 512 && w > 0 && h > 0);
    }

    #[test]
    fn config_names_the_key() {
        let key = |f: fn(&mut CommandConfig)| {
            let mut c = CommandConfig::default();
            f(&mut c);
            c.policy().unwrap_err().0
        };
        assert_eq!(
            key(|c| c.can_source_nodes = vec![1, 128]),
            "commands.can_source_nodes"
        );
        assert_eq!(key(|c| c.arm_timeout_ms = 0), "commands.arm_timeout_ms");
        assert_eq!(key(|c| c.render_burst = 0), "commands.render_burst");
        assert_eq!(
            key(|c| c.render_interval_ms = 0),
            "commands.render_interval_ms"
        );
        assert_eq!(
            key(|c| c.render_max_pixels = 0),
            "commands.render_max_pixels"
        );
    }
}
