//! Cyphal/CAN v1.0 transport: frame IDs and tail bytes ([`frame`]), splitting a message or
//! service transfer into frames ([`tx`]), bounded message reassembly ([`rx`]) and the DSDL
//! serialisation of the standard node types the component publishes and serves ([`node`]).
//! The message reassembler counts and rejects service frames; the component answers the
//! single-frame requests of the services it serves (see [`node`]) before reassembly.

pub mod frame;
pub mod node;
pub mod rx;
pub mod tx;

pub use frame::{CanFrame, MessageCanId, Mtu, Priority, ServiceCanId, TailByte};
pub use rx::{CanReassembler, CanRxCounters, CanRxError, ReceivedTransfer};
pub use tx::{service_transfer_frames, transfer_frames, TransferFrames, TransferHeader};
