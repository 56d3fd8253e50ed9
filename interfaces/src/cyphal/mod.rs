//! Cyphal/CAN v1.0 message transport: frame IDs and tail bytes ([`frame`]), splitting a
//! transfer into frames ([`tx`]) and bounded reassembly ([`rx`]).
//! Service transfers (request/response) are not implemented; their frames are counted and
//! rejected on receive.

pub mod frame;
pub mod rx;
pub mod tx;

pub use frame::{CanFrame, MessageCanId, Mtu, Priority, TailByte};
pub use rx::{CanReassembler, CanRxCounters, CanRxError, ReceivedTransfer};
pub use tx::{transfer_frames, TransferFrames, TransferHeader};
