//! Property tests of the register service codecs and the service request reassembler:
//! arbitrary bytes never panic and never decode to a value that overruns its input; every
//! representable value and request survives encode then decode (also with CAN FD padding);
//! request frames split at any MTU reassemble to the sent payload.

use interfaces::cyphal::register::{
    decode_list_request, raw_len, AccessRequest, AccessResponse, Value, ValueKind,
    ACCESS_REQUEST_MAX_BYTES, ACCESS_RESPONSE_MAX_BYTES,
};
use interfaces::cyphal::service_rx::ServiceRequestRx;
use interfaces::cyphal::{service_transfer_frames, Mtu, Priority, ServiceCanId};
use proptest::prelude::*;

fn value_strategy() -> impl Strategy<Value = (ValueKind, usize, Vec<u8>)> {
    (0..ValueKind::ALL.len()).prop_flat_map(|k| {
        let kind = ValueKind::ALL[k];
        (0..=kind.capacity()).prop_flat_map(move |count| {
            proptest::collection::vec(any::<u8>(), raw_len(kind, count))
                .prop_map(move |raw| (kind, count, raw))
        })
    })
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        if let Ok((value, used)) = Value::decode(&bytes) {
            prop_assert!(used <= bytes.len());
            prop_assert_eq!(value.raw.len(), raw_len(value.kind, value.count));
            prop_assert!(value.count <= value.kind.capacity());
        }
        if let Ok(request) = AccessRequest::decode(&bytes) {
            prop_assert!(request.name.len() < 256);
            let mut out = [0u8; ACCESS_REQUEST_MAX_BYTES];
            let n = request.encode(&mut out).unwrap();
            // A request that ends after the name reads an empty value (zero extension).
            let mut padded = bytes.clone();
            padded.resize(padded.len().max(n), 0);
            prop_assert_eq!(&out[..n], &padded[..n], "re-encodes to its own prefix");
        }
        let _ = AccessResponse::decode(&bytes);
        let _ = decode_list_request(&bytes);
    }

    #[test]
    fn values_round_trip_with_padding(
        (kind, count, raw) in value_strategy(),
        name in proptest::collection::vec(any::<u8>(), 0..256),
        padding in 0usize..16,
        mutable: bool,
        persistent: bool,
    ) {
        let value = Value::new(kind, count, &raw).unwrap();
        let request = AccessRequest { name: &name, value };
        let mut out = vec![0u8; ACCESS_REQUEST_MAX_BYTES + 16];
        let n = request.encode(&mut out).unwrap();
        prop_assert_eq!(AccessRequest::decode(&out[..n + padding]), Ok(request));
        let response = AccessResponse { timestamp_us: 0, mutable, persistent, value };
        let mut out = [0u8; ACCESS_RESPONSE_MAX_BYTES];
        let n = response.encode(&mut out).unwrap();
        prop_assert_eq!(AccessResponse::decode(&out[..n]), Ok(response));
    }

    #[test]
    fn requests_reassemble_at_any_mtu(
        payload in proptest::collection::vec(any::<u8>(), 0..ACCESS_REQUEST_MAX_BYTES),
        fd: bool,
        tid in 0u64..32,
    ) {
        let id = ServiceCanId {
            priority: Priority::Nominal,
            service_id: 384,
            is_request: true,
            destination_node_id: 42,
            source_node_id: 100,
        };
        let mtu = if fd { Mtu::Fd } else { Mtu::Classic };
        let frames: Vec<_> = service_transfer_frames(&id, tid, &payload, mtu).unwrap().collect();
        let mut rx = ServiceRequestRx::<_, 2>::new(vec![0u8; 2 * 1024]);
        let mut got = None;
        for (i, f) in frames.iter().enumerate() {
            let r = rx.push(f.id, &f.data, 42, 0).unwrap();
            prop_assert_eq!(r.is_some(), i + 1 == frames.len());
            if let Some(request) = r {
                got = Some(request.payload.to_vec());
            }
        }
        let got = got.unwrap();
        prop_assert!(got.starts_with(&payload));
        prop_assert!(got[payload.len()..].iter().all(|&b| b == 0));
    }

    #[test]
    fn arbitrary_frames_never_panic(
        frames in proptest::collection::vec((any::<u32>(), proptest::collection::vec(any::<u8>(), 0..65)), 0..40),
    ) {
        let mut rx = ServiceRequestRx::<_, 2>::new(vec![0u8; 2 * 300]);
        for (i, (id, data)) in frames.iter().enumerate() {
            if let Ok(Some(request)) = rx.push(*id & 0x1FFF_FFFF, data, 42, i as u64) {
                prop_assert!(request.payload.len() <= 300);
            }
        }
    }
}
