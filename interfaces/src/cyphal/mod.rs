//! Cyphal/CAN v1.0 transport: frame IDs and tail bytes ([`frame`]), splitting a message or
//! service transfer into frames ([`tx`]), bounded message reassembly ([`rx`]) and the DSDL
//! serialisation of the standard node types the component publishes and serves ([`node`],
//! [`register`]). The message reassembler counts and rejects service frames; requests to
//! this node are reassembled apart ([`service_rx`]) before the message path.

pub mod frame;
pub mod node;
pub mod register;
pub mod rx;
pub mod service_rx;
pub mod tx;

pub use frame::{CanFrame, MessageCanId, Mtu, Priority, ServiceCanId, TailByte};
pub use rx::{CanReassembler, CanRxCounters, CanRxError, ReceivedTransfer, SubjectSet};
pub use tx::{service_transfer_frames, transfer_frames, TransferFrames, TransferHeader};
