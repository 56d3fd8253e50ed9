"""Rendered predictions on CAN FD: the flight component binary on a real vcan interface.

Runs inside the vcan micro-VM (tests/vcan/run-in-vm.sh sets VCAN_IFACE); skipped elsewhere.
Telemetry as Cyphal/CAN FD transfers, 16x16 RGB camera frames over loopback UDP, the
nearest-keyframe stand-in as the model. With the defaults (`[can] predictions = true`,
`prediction_max_bytes = 4096`) every prediction arrives twice, identical: on UDP and as a
multi-frame CAN FD transfer on subject 201 from the component's node-ID. With a limit below
the prediction's size, none goes on CAN, all still arrive on UDP, and exactly one
PredictionNotOnCan event (error code 17) carries the encoded size.
"""

import os

import pytest

from test_component_can import CanSide, send_step
from test_component_udp import SIZE, Component, write_config
from test_component_udp import listener  # noqa: F401  (pytest fixture)

IFACE = os.environ.get("VCAN_IFACE")
pytestmark = pytest.mark.skipif(
    not IFACE, reason="VCAN_IFACE not set: run through tests/vcan/run-in-vm.sh"
)
# Frames sent; the nearest-keyframe model predicts from the second on (none before a keyframe).
FRAMES = 5
PREDICTED = FRAMES - 1
EVENT_ERROR, PREDICTION_NOT_ON_CAN = 1, 17


def start(directory, listener, can_keys=""):  # noqa: F811
    """The component on CAN FD, with extra `[can]` keys."""
    config = directory / "component.toml"
    write_config(config, listener, directory / "checkpoint.bin", can_enabled=True,
                 interface=IFACE)
    config.write_text(config.read_text().replace("[can]\n", f"[can]\n{can_keys}\n", 1))
    return Component(config)


def feed(side, component, listener):  # noqa: F811
    """Telemetry on CAN around each frame, frames on UDP; waits for each UDP prediction."""
    for k in range(FRAMES):
        send_step(side, component, k)
        if k:
            listener.wait(lambda s: any(p["source"] == ("frame", k) for p in s.predictions),
                          timeout=20, what=f"prediction for frame {k} on UDP")


def test_small_predictions_go_on_can_fd_as_well(tmp_path, listener):  # noqa: F811
    side = CanSide()
    component = start(tmp_path, listener)
    try:
        feed(side, component, listener)
        side.wait(lambda s: len(s.predictions) >= PREDICTED,
                  what=f"{PREDICTED} predictions on CAN")
    finally:
        assert component.stop(timeout=20) == 0
        side.close()
    on_udp = {p["source"]: p for p in listener.predictions}
    assert len(side.predictions) == PREDICTED
    for p in side.predictions:
        assert (p["width"], p["height"]) == (SIZE, SIZE)
        assert p == on_udp[p["source"]], p["source"]
    assert not any(e["kind"] == EVENT_ERROR and e["code"] == PREDICTION_NOT_ON_CAN
                   for e in listener.events)


def test_larger_predictions_stay_on_udp_with_one_event(tmp_path, listener):  # noqa: F811
    side = CanSide()
    component = start(tmp_path, listener, "prediction_max_bytes = 100")
    try:
        feed(side, component, listener)
        too_large = listener.wait(
            lambda s: [e for e in s.events if e["kind"] == EVENT_ERROR
                       and e["code"] == PREDICTION_NOT_ON_CAN],
            timeout=20, what="the PredictionNotOnCan event")
    finally:
        assert component.stop(timeout=20) == 0
        side.close()
    assert len([p for p in listener.predictions if p["source"][0] == "frame"]) == PREDICTED
    assert side.predictions == []
    assert len(too_large) == 1, too_large
    # The encoded size: the pixels, their length varint and the fixed fields (<= 78 B).
    assert 3 * SIZE * SIZE + 2 < too_large[0]["detail"] <= 3 * SIZE * SIZE + 2 + 78
