//! Rendered predictions on CAN FD: a prediction within `[can] prediction_max_bytes` becomes
//! a multi-frame Cyphal/CAN FD transfer on the configured subject that the project's
//! receiver (`interfaces::cyphal::CanReassembler`) reassembles and decodes to the same
//! message, transfer after transfer; one byte over the limit stays on UDP, counted, and only
//! the first such prediction is flagged for the event.

use fsw_component::outbound::{CanPredictions, PredictionOnCan};
use fsw_component::transport::RawCanFrame;
use interfaces::cyphal::CanReassembler;
use interfaces::messages::{
    decode, encoded_len, FrameHeader, PixelFormat, PredictionSource, RenderedPrediction,
};

const NODE_ID: u8 = 42;
const SUBJECT_ID: u16 = 6000;
/// Data bytes of a full CAN FD frame.
const FD_DATA_BYTES: usize = 64;

fn prediction(frame_id: u32, (width, height): (u16, u16), pixels: &[u8]) -> RenderedPrediction<'_> {
    RenderedPrediction {
        header: FrameHeader {
            frame_id,
            time_us: 5_000_000 * u64::from(frame_id),
            width,
            height,
            format: PixelFormat::Rgb8,
        },
        source: PredictionSource::ObservedFrame { frame_id },
        q_camera_from_target: [0.5, 0.5, -0.5, 0.5],
        t_camera_from_target_m: [0.1, -0.2, 12.0],
        sun_target: [0.0, 0.6, 0.8],
        psnr_db: Some(23.5),
        ssim: Some(0.81),
        pixels,
    }
}

fn rgb((width, height): (u16, u16), seed: u32) -> Vec<u8> {
    (0..u32::from(width) * u32::from(height) * 3)
        .map(|i| (i.wrapping_mul(2_654_435_761) ^ seed) as u8)
        .collect()
}

fn frames(route: PredictionOnCan) -> Vec<RawCanFrame> {
    match route {
        PredictionOnCan::Frames(frames) => frames,
        other => panic!("expected CAN FD frames, got {other:?}"),
    }
}

#[test]
fn small_predictions_round_trip_as_can_fd_transfers() {
    let side = (16, 16);
    let max_bytes = 4096;
    let mut publisher = CanPredictions::new(NODE_ID, SUBJECT_ID, max_bytes);
    let mut rx: CanReassembler<Vec<u8>, 2> = CanReassembler::new(vec![0; 2 * 8192]);
    for frame_id in 0..3u32 {
        let pixels = rgb(side, frame_id);
        let sent = prediction(frame_id, side, &pixels);
        let encoded = encoded_len(&sent).unwrap();
        let frames = frames(publisher.route(&sent).unwrap());
        // Multi-frame FD: full 64-byte frames but the last, each with its tail byte.
        assert!(frames.len() > 1 && frames.iter().all(RawCanFrame::is_fd));
        assert_eq!(frames.len(), (encoded + 2).div_ceil(FD_DATA_BYTES - 1));
        let mut delivered = 0;
        for (i, f) in frames.iter().enumerate() {
            // Classic CAN could not carry a 64-byte frame.
            if i + 1 < frames.len() {
                assert_eq!(f.data().len(), FD_DATA_BYTES);
            }
            if let Some(transfer) = rx
                .push(f.id(), f.data(), u64::from(frame_id) * 1000)
                .unwrap()
            {
                assert_eq!(i + 1, frames.len(), "delivered on the last frame");
                assert_eq!(transfer.subject_id, SUBJECT_ID);
                assert_eq!(transfer.source_node_id, Some(NODE_ID));
                assert_eq!(u32::from(transfer.transfer_id), frame_id % 32);
                let got: RenderedPrediction = decode(transfer.payload).unwrap();
                assert_eq!(got, sent);
                delivered += 1;
            }
        }
        assert_eq!(delivered, 1, "prediction {frame_id}");
    }
    assert_eq!((publisher.framed, publisher.too_large), (3, 0));
}

#[test]
fn a_prediction_over_the_limit_stays_on_udp_and_is_flagged_once() {
    let side = (16, 16);
    let pixels = rgb(side, 7);
    let at_limit = encoded_len(&prediction(1, side, &pixels)).unwrap();
    let mut publisher = CanPredictions::new(NODE_ID, SUBJECT_ID, at_limit);
    assert!(
        matches!(
            publisher.route(&prediction(1, side, &pixels)).unwrap(),
            PredictionOnCan::Frames(_)
        ),
        "exactly the limit goes on CAN FD"
    );
    // One pixel column more: over the limit.
    let wider = rgb((17, 16), 7);
    let over = prediction(2, (17, 16), &wider);
    let over_bytes = encoded_len(&over).unwrap();
    assert!(over_bytes > at_limit);
    let mut firsts = Vec::new();
    for _ in 0..3 {
        match publisher.route(&over).unwrap() {
            PredictionOnCan::TooLarge {
                encoded_bytes,
                first,
            } => {
                assert_eq!(encoded_bytes, over_bytes);
                firsts.push(first);
            }
            other => panic!("expected UDP only, got {other:?}"),
        }
    }
    assert_eq!(firsts, [true, false, false], "flagged for the event once");
    assert_eq!((publisher.framed, publisher.too_large), (1, 3));
    // A small one after them still goes on CAN.
    assert!(matches!(
        publisher.route(&prediction(3, side, &pixels)).unwrap(),
        PredictionOnCan::Frames(_)
    ));
}
