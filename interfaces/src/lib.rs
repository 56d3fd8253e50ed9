//! Message catalogue and bus framing shared by the flight component and its peers.
//!
//! `no_std`, no allocator: everything here must build for a flight computer. Large payloads
//! (camera frames, rendered images) are borrowed slices; reassemblers use bounded,
//! caller-provided storage and report every rejected input instead of panicking.
//!
//! - [`crc`]: CRC-16/CCITT-FALSE (Cyphal transfer CRC) and CRC-32/IEEE (CCSDS message CRC).
//! - [`cyphal`]: Cyphal/CAN v1.0 message transfers, classic CAN and CAN FD.
//! - [`messages`]: the catalogue (port IDs, versions, fields) and the validating postcard codec.
//! - [`ccsds`]: CCSDS Space Packets over UDP with segmentation and a per-message CRC-32.
//! - `sessions` (private): the bounded session table's life cycle both reassemblers share.
#![no_std]

pub mod ccsds;
pub mod crc;
pub mod cyphal;
pub mod messages;
mod sessions;
