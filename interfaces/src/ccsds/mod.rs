//! CCSDS Space Packets over UDP: one packet per datagram (<= 1472 bytes), APID = message
//! port ID, large messages segmented with sequence flags and counts, a CRC-32 at the end of
//! every message. [`header`] encodes the primary header, [`tx`] segments, [`rx`] reassembles.

pub mod header;
pub mod rx;
pub mod tx;

pub use header::{PacketType, PrimaryHeader, SequenceFlags, MAX_DATAGRAM_BYTES};
pub use rx::{CcsdsReassembler, CcsdsRxCounters, CcsdsRxError, ReceivedMessage};
pub use tx::{message_packets, Datagram, MessagePackets};
