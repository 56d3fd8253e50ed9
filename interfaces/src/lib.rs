//! Message catalogue and bus framing shared by the flight component and its peers.
//!
//! `no_std`: everything here must build for a flight computer without an allocator.
#![no_std]
