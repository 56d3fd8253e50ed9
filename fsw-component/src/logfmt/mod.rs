//! Traffic logs: candump .log text for CAN, a datagram recording for UDP.
