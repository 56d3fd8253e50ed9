//! Sends one bus-feed step to a component over loopback UDP, as the bus tests need it:
//! the telemetry datagrams, a 20 ms head start (telemetry and frames use different sockets,
//! whose order of arrival is not defined), then the frame's datagrams, pausing 2 ms every 32
//! so a frame does not overrun the receiver's socket buffer.

use sim_harness::busfeed::BusStep;
use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

pub async fn send_step(
    sender: &UdpSocket,
    step: &BusStep,
    telemetry: SocketAddr,
    frames: SocketAddr,
) {
    for d in &step.telemetry_datagrams {
        sender.send_to(d, telemetry).unwrap();
    }
    tokio::time::sleep(Duration::from_millis(20)).await;
    for (i, d) in step.frame_datagrams.iter().enumerate() {
        sender.send_to(d, frames).unwrap();
        if i % 32 == 31 {
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
}
