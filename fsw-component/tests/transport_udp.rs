//! UDP transport on loopback: round trips, the 1472-byte limit on both sides, counted
//! oversize drops, that no valid datagram is lost around an oversize one, and that a flood
//! beyond the kernel receive buffer is fully accounted for (received + kernel drops).

use std::net::{Ipv4Addr, SocketAddr};
use std::time::Duration;

use fsw_component::transport::{TransportError, UdpTransport, MAX_DATAGRAM_BYTES};

const RECV_TIMEOUT: Duration = Duration::from_secs(5);

fn loopback_any_port() -> SocketAddr {
    SocketAddr::from((Ipv4Addr::LOCALHOST, 0))
}

/// Deterministic payload bytes, different for each (seed, index).
fn payload(seed: u8, len: usize) -> Vec<u8> {
    (0..len)
        .map(|index| (index as u8).wrapping_mul(31).wrapping_add(seed))
        .collect()
}

async fn receive(transport: &UdpTransport) -> (Vec<u8>, SocketAddr) {
    let mut out = [0u8; MAX_DATAGRAM_BYTES];
    let (len, sender) = tokio::time::timeout(RECV_TIMEOUT, transport.recv_from(&mut out))
        .await
        .expect("datagram did not arrive in time")
        .expect("recv_from failed");
    (out[..len].to_vec(), sender)
}

#[tokio::test]
async fn datagrams_round_trip_in_order_with_exact_bytes_and_sender() {
    let a = UdpTransport::bind(loopback_any_port()).await.unwrap();
    let b = UdpTransport::bind(loopback_any_port()).await.unwrap();
    assert_ne!(a.local_addr().port(), 0);
    let lengths = [
        0,
        1,
        7,
        64,
        1000,
        MAX_DATAGRAM_BYTES - 1,
        MAX_DATAGRAM_BYTES,
    ];
    for (seed, &len) in lengths.iter().enumerate() {
        a.send_to(&payload(seed as u8, len), b.local_addr())
            .await
            .unwrap();
    }
    for (seed, &len) in lengths.iter().enumerate() {
        let (bytes, sender) = receive(&b).await;
        assert_eq!(
            bytes,
            payload(seed as u8, len),
            "datagram {seed} ({len} bytes)"
        );
        assert_eq!(sender, a.local_addr());
    }
    // And back the other way.
    b.send_to(b"ack", a.local_addr()).await.unwrap();
    assert_eq!(receive(&a).await, (b"ack".to_vec(), b.local_addr()));

    let sent_bytes: usize = lengths.iter().sum();
    let a_stats = a.stats();
    let b_stats = b.stats();
    assert_eq!(a_stats.datagrams_sent, lengths.len() as u64);
    assert_eq!(b_stats.datagrams_received, lengths.len() as u64);
    assert_eq!(b_stats.bytes_received, sent_bytes as u64);
    assert_eq!(a_stats.datagrams_received, 1);
    assert_eq!(b_stats.oversize_received_dropped, 0);
}

#[tokio::test]
async fn sending_more_than_the_limit_is_refused_and_counted() {
    let a = UdpTransport::bind(loopback_any_port()).await.unwrap();
    let b = UdpTransport::bind(loopback_any_port()).await.unwrap();
    let error = a
        .send_to(&payload(1, MAX_DATAGRAM_BYTES + 1), b.local_addr())
        .await
        .unwrap_err();
    assert!(
        matches!(
            error,
            TransportError::DatagramTooLarge {
                len: 1473,
                max: 1472
            }
        ),
        "{error}"
    );
    assert_eq!(a.stats().oversize_send_rejected, 1);
    assert_eq!(a.stats().datagrams_sent, 0);
    // Nothing was put on the wire: the next datagram b sees is the valid one.
    a.send_to(b"after", b.local_addr()).await.unwrap();
    assert_eq!(receive(&b).await.0, b"after");
}

#[tokio::test]
async fn oversize_incoming_datagrams_are_dropped_counted_and_do_not_hide_valid_ones() {
    let receiver = UdpTransport::bind(loopback_any_port()).await.unwrap();
    // A plain socket, so the sender is not held to our limit.
    let raw = std::net::UdpSocket::bind(loopback_any_port()).unwrap();
    let oversize_lengths = [MAX_DATAGRAM_BYTES + 1, 2000, 9000];
    raw.send_to(&payload(10, 100), receiver.local_addr())
        .unwrap();
    for (seed, &len) in oversize_lengths.iter().enumerate() {
        raw.send_to(&payload(seed as u8, len), receiver.local_addr())
            .unwrap();
    }
    raw.send_to(&payload(11, MAX_DATAGRAM_BYTES), receiver.local_addr())
        .unwrap();

    assert_eq!(receive(&receiver).await.0, payload(10, 100));
    assert_eq!(receive(&receiver).await.0, payload(11, MAX_DATAGRAM_BYTES));
    let stats = receiver.stats();
    assert_eq!(
        stats.oversize_received_dropped,
        oversize_lengths.len() as u64
    );
    assert_eq!(stats.datagrams_received, 2);
    assert_eq!(stats.bytes_received, (100 + MAX_DATAGRAM_BYTES) as u64);
}

#[tokio::test]
async fn a_flood_beyond_the_receive_buffer_is_received_or_counted_as_dropped() {
    const FLOOD_DATAGRAMS: usize = 1000;
    let receiver = UdpTransport::bind(loopback_any_port()).await.unwrap();
    // Small on purpose, so the flood overflows it on any machine (shrinking is never capped).
    let granted = receiver.set_receive_buffer_bytes(32 * 1024).unwrap();
    assert_eq!(granted, receiver.receive_buffer_bytes().unwrap());
    assert_eq!(receiver.stats().dropped_receive_queue_full, Some(0));

    let raw = std::net::UdpSocket::bind(loopback_any_port()).unwrap();
    for index in 0..FLOOD_DATAGRAMS {
        let mut datagram = payload(index as u8, 1000);
        datagram[..4].copy_from_slice(&(index as u32).to_le_bytes());
        raw.send_to(&datagram, receiver.local_addr()).unwrap();
    }
    let mut received_indices = Vec::new();
    let mut out = [0u8; MAX_DATAGRAM_BYTES];
    while let Ok(result) =
        tokio::time::timeout(Duration::from_millis(300), receiver.recv_from(&mut out)).await
    {
        let (len, _) = result.unwrap();
        assert_eq!(len, 1000);
        received_indices.push(u32::from_le_bytes([out[0], out[1], out[2], out[3]]) as usize);
    }
    assert!(
        received_indices.len() < FLOOD_DATAGRAMS,
        "the flood did not overflow a 32 KiB buffer"
    );
    assert!(received_indices.windows(2).all(|pair| pair[0] < pair[1]));
    let dropped = receiver.stats().dropped_receive_queue_full.unwrap();
    assert_eq!(
        received_indices.len() as u64 + dropped,
        FLOOD_DATAGRAMS as u64,
        "every datagram is either received or counted as dropped by the kernel"
    );
}

#[tokio::test]
async fn binding_an_address_in_use_is_a_descriptive_error() {
    let first = UdpTransport::bind(loopback_any_port()).await.unwrap();
    let error = UdpTransport::bind(first.local_addr()).await.unwrap_err();
    match &error {
        TransportError::Io {
            operation, target, ..
        } => {
            assert_eq!(*operation, "bind UDP socket");
            assert_eq!(target, &first.local_addr().to_string());
        }
        other => panic!("expected an I/O error naming the address, got {other}"),
    }
}

#[test]
fn binding_outside_a_runtime_is_an_error_not_a_panic() {
    let runtime_less = block_on_without_runtime(UdpTransport::bind(loopback_any_port()));
    assert!(matches!(runtime_less, Err(TransportError::NoTokioRuntime)));
}

/// Polls a future to completion without a tokio runtime (the point of the test above).
fn block_on_without_runtime<F: std::future::Future>(future: F) -> F::Output {
    use std::task::{Context, Poll, Waker};
    let mut future = std::pin::pin!(future);
    let mut context = Context::from_waker(Waker::noop());
    loop {
        if let Poll::Ready(output) = future.as_mut().poll(&mut context) {
            return output;
        }
    }
}
