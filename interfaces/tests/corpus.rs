//! Replays the committed fuzz corpus (`fuzz/corpus/decoders/`) through the fuzz harness on every
//! test run, and runs the same harness on random inputs. The seeds are valid encodings of
//! every catalogue message, Cyphal frame streams (classic and FD) and CCSDS packet streams, so
//! mutations start deep inside the decoders. `cargo test -p interfaces --test corpus --
//! --ignored` rewrites the seeds from the fixtures.

mod common;
#[path = "../fuzz/harness.rs"]
mod harness;

use common::{all_encoded, SplitMix64};
use interfaces::ccsds::{message_packets, PacketType};
use interfaces::cyphal::{transfer_frames, Mtu, Priority, TransferHeader};
use proptest::prelude::*;
use std::path::PathBuf;

fn corpus_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/decoders")
}

#[test]
fn committed_corpus_replays_without_findings() {
    let mut selectors = [0usize; 5];
    let mut files = 0;
    for entry in std::fs::read_dir(corpus_dir()).expect("corpus directory exists") {
        let path = entry.unwrap().path();
        let bytes = std::fs::read(&path).unwrap();
        harness::run(&bytes);
        if let Some(&s) = bytes.first() {
            selectors[usize::from(s % 5)] += 1;
        }
        files += 1;
    }
    assert!(files >= 20, "corpus has only {files} files");
    assert!(
        selectors.iter().all(|&n| n > 0),
        "every harness branch seeded: {selectors:?}"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]
    #[test]
    fn harness_survives_random_inputs(bytes in proptest::collection::vec(any::<u8>(), 0..3000)) {
        harness::run(&bytes);
    }
}

fn seeds() -> Vec<Vec<u8>> {
    let mut rng = SplitMix64(2026);
    let encoded = all_encoded(&mut rng);
    let mut out = Vec::new();
    for (_, bytes) in &encoded {
        let mut s = vec![0u8];
        s.extend(bytes);
        out.push(s);
    }
    for (i, (port, bytes)) in encoded.iter().enumerate() {
        let mtu = if i % 2 == 0 { Mtu::Classic } else { Mtu::Fd };
        let header = TransferHeader {
            priority: Priority::Nominal,
            subject_id: *port,
            source_node_id: 1 + (i % 3) as u8,
            transfer_id: i as u64,
        };
        let mut s = vec![1u8];
        for f in transfer_frames(&header, bytes, mtu).unwrap().take(40) {
            s.push(f.data.len() as u8);
            s.extend(f.id.to_le_bytes());
            s.extend(10u16.to_le_bytes());
            s.extend(&f.data);
        }
        out.push(s);
        let mut s = vec![2u8];
        for p in message_packets(
            PacketType::Telemetry,
            *port,
            bytes,
            i as u16,
            300 + (97 * i) % 1172,
        )
        .unwrap()
        .take(20)
        {
            s.extend((p.len() as u16).to_le_bytes());
            s.extend(10u16.to_le_bytes());
            s.extend(&p);
        }
        out.push(s);
        let mut s = vec![3u8, i as u8, (i * 13) as u8];
        s.extend(bytes.iter().take(700));
        out.push(s);
        let mut s = vec![4u8];
        s.extend(((i * 211) as u16).to_le_bytes());
        s.extend(((i * 4099) as u16).to_le_bytes());
        s.extend(bytes.iter().take(5000));
        out.push(s);
    }
    out
}

#[test]
#[ignore = "rewrites the committed seed corpus"]
fn regenerate_seed_corpus() {
    let dir = corpus_dir();
    std::fs::create_dir_all(&dir).unwrap();
    for (i, seed) in seeds().iter().enumerate() {
        std::fs::write(dir.join(format!("seed-{}-{i:03}", seed[0])), seed).unwrap();
    }
}
