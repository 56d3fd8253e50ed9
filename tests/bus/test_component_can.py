"""The flight component binary on a real vcan interface, python-can as the rest of the bus.

Runs inside the vcan micro-VM (tests/vcan/run-in-vm.sh sets VCAN_IFACE); skipped elsewhere.
Telemetry and commands travel as Cyphal/CAN FD message transfers written here from the
specification (29-bit ID, tail byte, toggle, transfer-ID, CRC-16/CCITT-FALSE with padding),
camera frames over loopback UDP. Checks: frames synchronised with CAN telemetry are predicted,
commands are acknowledged on CAN (subject 301, from the component's node-ID), health arrives
on CAN at 1 Hz, a transfer with a wrong CRC and commands from a node outside the allow-list
are counted and change nothing, and the CAN traffic recorded live (candump log) replays to
the same model. Run with the nearest-keyframe stand-in and with the real Sun-aware learner
(a small model: the VM's CPU is emulated); with the real one, the predictions of the last
frames must beat an all-black image.
"""

import math

import os
import struct
import subprocess
import threading
import time

import can
import pytest

from test_component_udp import (
    ACK_INVALID_OPCODE, ACK_OK, PORT_ACK, PORT_COMMAND, PORT_FRAME, PORT_HEALTH, PORT_POSE,
    PORT_PREDICTION, PORT_SUN, Component, camera_frame, command, component_binary, decode_ack,
    decode_health, decode_prediction, frame_pixels, sun_vector, target_pose, write_config,
)
from test_component_udp import listener  # noqa: F401  (pytest fixture)

IFACE = os.environ.get("VCAN_IFACE")
pytestmark = pytest.mark.skipif(
    not IFACE, reason="VCAN_IFACE not set: run through tests/vcan/run-in-vm.sh"
)
NODE = 42  # config/component.toml default, the component's node-ID
PEER_NODE = 10  # telemetry sender (AOCS)
COMMAND_NODE = 1  # the one node allowed to command by default ([commands] can_source_nodes)
FD_LENGTHS = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]


def crc16_ccitt_false(data):
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


assert crc16_ccitt_false(b"123456789") == 0x29B1


def can_id(subject, node):
    return (4 << 26) | (3 << 21) | (subject << 8) | node


def transfer_frames(subject, transfer_id, payload, corrupt_crc=False):
    """Data fields of one Cyphal/CAN FD message transfer (MTU 64)."""
    mtu = 63
    tid = transfer_id % 32
    if len(payload) <= mtu:
        total = next(n for n in FD_LENGTHS if n >= len(payload) + 1)
        return [payload + bytes(total - 1 - len(payload)) + bytes([0xE0 | tid])]
    # Multi-frame: pad so that the last frame (rest + CRC + tail) has a valid FD length.
    rest = (len(payload) + 2) % mtu or mtu
    padding = 0
    if rest >= 2:
        padding = next(n for n in FD_LENGTHS if n >= rest + 1) - 1 - rest
    stream = payload + bytes(padding)
    crc = crc16_ccitt_false(stream) ^ (0x5555 if corrupt_crc else 0)
    stream += struct.pack(">H", crc)
    pieces = [stream[i : i + mtu] for i in range(0, len(stream), mtu)]
    frames, toggle = [], 1
    for i, piece in enumerate(pieces):
        tail = (0x80 if i == 0 else 0) | (0x40 if i == len(pieces) - 1 else 0) | (toggle << 5) | tid
        frames.append(piece + bytes([tail]))
        toggle ^= 1
    return frames


class CanSide:
    """python-can on the vcan interface: sends transfers, collects the component's."""

    def __init__(self):
        self.bus = can.Bus(interface="socketcan", channel=IFACE, fd=True)
        self.tids = {}
        self.acks, self.health, self.predictions = [], [], []
        self.partial = {}
        self.stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def send(self, subject, payload, corrupt_crc=False, node=None):
        if node is None:
            node = COMMAND_NODE if subject == PORT_COMMAND else PEER_NODE
        tid = self.tids.get((subject, node), 0)
        self.tids[(subject, node)] = tid + 1
        for data in transfer_frames(subject, tid, payload, corrupt_crc):
            self.bus.send(can.Message(arbitration_id=can_id(subject, node),
                                      is_extended_id=True, is_fd=True, data=data))

    def _run(self):
        while not self.stop:
            m = self.bus.recv(0.2)
            if m is None or not m.is_extended_id or (m.arbitration_id & 0x7F) != NODE:
                continue
            subject = (m.arbitration_id >> 8) & 0x1FFF
            data, tail = bytes(m.data[:-1]), m.data[-1]
            start, end = tail & 0x80, tail & 0x40
            if start and end:
                payload = data
            else:
                self.partial[subject] = (self.partial.get(subject, b"") if not start else b"") + data
                if not end:
                    continue
                stream = self.partial.pop(subject)
                assert crc16_ccitt_false(stream[:-2]) == struct.unpack(">H", stream[-2:])[0]
                payload = stream[:-2]
            if subject == PORT_ACK:
                self.acks.append(decode_ack(payload))
            elif subject == PORT_HEALTH:
                self.health.append((time.monotonic(), decode_health(payload)))
            elif subject == PORT_PREDICTION:
                self.predictions.append(decode_prediction(payload))

    def wait(self, condition, timeout=20.0, what="condition"):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            result = condition(self)
            if result:
                return result
            time.sleep(0.02)
        raise AssertionError(f"timed out waiting for {what} on {IFACE}")

    def close(self):
        self.stop = True
        self.thread.join()
        self.bus.shutdown()


# The real learner in the VM (emulated CPU): a small starting model and a coarse hull.
SMALL_MODEL = "initial_gaussians = 200\nhull_resolution = 24"


def start_on_can(directory, listener, *extra, learner="nearest"):  # noqa: F811
    config = directory / "component.toml"
    write_config(config, listener, directory / "checkpoint.bin", can_enabled=True,
                 interface=IFACE, model=SMALL_MODEL if learner == "sunaware" else "")
    return Component(config, *extra, learner=learner)


def send_step(side, component, k):
    """Step k: telemetry on CAN at k + 1 s (and at 0 s first), then frame k (k + 0.5 s) on UDP."""
    if k == 0:
        side.send(PORT_POSE, target_pose(0))
        side.send(PORT_SUN, sun_vector(0))
    t = (k + 1) * 1_000_000
    side.send(PORT_POSE, target_pose(t))
    side.send(PORT_SUN, sun_vector(t))
    time.sleep(0.2)  # CAN and UDP are different sockets: telemetry first
    component.send(PORT_FRAME, camera_frame(k, k * 1_000_000 + 500_000), to=component.frames)


def black_psnr_db(pixels):
    """PSNR of an all-black image against `pixels` (8-bit), dB."""
    mse = sum((v / 255.0) ** 2 for v in pixels) / len(pixels)
    return -10.0 * math.log10(mse)


@pytest.mark.parametrize("learner", ["nearest", "sunaware"])
def test_telemetry_and_commands_on_can_frames_on_udp(tmp_path, listener, learner):  # noqa: F811
    wait_s = 20 if learner == "nearest" else 180
    side = CanSide()
    live = tmp_path / "live"
    live.mkdir()
    component = start_on_can(live, listener, "--record", str(live / "rec"), learner=learner)
    try:
        for k in range(6):
            send_step(side, component, k)
            if k:
                listener.wait(lambda s: any(p["source"] == ("frame", k) for p in s.predictions),
                              timeout=wait_s, what=f"prediction for frame {k}")
        side.send(PORT_COMMAND, command(1, 0))
        assert side.wait(lambda s: next((a for a in s.acks if a["sequence"] == 1), None),
                         what="NOOP ack on CAN")["status"] == ACK_OK
        side.send(PORT_COMMAND, command(2, 9))
        assert side.wait(lambda s: next((a for a in s.acks if a["sequence"] == 2), None),
                         what="error ack on CAN")["status"] == ACK_INVALID_OPCODE
        # A node outside the allow-list is not answered (counted as rejected in health).
        side.send(PORT_COMMAND, command(4, 0), node=PEER_NODE)
        side.send(PORT_COMMAND, command(5, 0))
        assert side.wait(lambda s: next((a for a in s.acks if a["sequence"] == 5), None),
                         what="NOOP ack after the stranger's")["status"] == ACK_OK
        time.sleep(0.2)
        assert not any(a["sequence"] == 4 for a in side.acks)
        side.send(PORT_POSE, bytes(range(70)), corrupt_crc=True)
        h = side.wait(lambda s: s.health[-1][1] if s.health and s.health[-1][1]["crc_errors"]
                      and s.health[-1][1]["rounds"] == 3 else None,
                      timeout=wait_s, what="CRC error and three rounds in health on CAN")
        assert h["crc_errors"] == 1 and h["frames_used"] == 6 and h["rounds"] == 3
        if learner == "sunaware":
            # After three rounds the model's predictions beat black on the frames it got.
            for k in (4, 5):
                p = next(p for p in listener.predictions if p["source"] == ("frame", k))
                assert p["psnr_db"] > black_psnr_db(frame_pixels(k)), (k, p["psnr_db"])
        times = [t for t, _ in side.health]
        assert all(0.7 < b - a < 1.3 for a, b in zip(times, times[1:])), times
        side.send(PORT_COMMAND, command(3, 3))  # SAVE_CHECKPOINT
        assert side.wait(lambda s: next((a for a in s.acks if a["sequence"] == 3), None),
                         timeout=wait_s, what="SAVE ack")["status"] == ACK_OK
    finally:
        assert component.stop(timeout=wait_s) == 0
        side.close()
    live_model = (live / "checkpoint.bin").read_bytes()
    replay = tmp_path / "replay"
    replay.mkdir()
    config = replay / "component.toml"
    write_config(config, listener, replay / "checkpoint.bin",
                 model=SMALL_MODEL if learner == "sunaware" else "")
    done = subprocess.run(
        [str(component_binary()), "--config", str(config), "--learner", learner,
         "--replay-speed", "max", "--replay", str(live / "rec" / "can.log"),
         "--replay", str(live / "rec" / "udp.rec")],
        capture_output=True, text=True, timeout=120 if learner == "nearest" else 900,
    )
    assert done.returncode == 0, done.stderr
    assert (replay / "checkpoint.bin").read_bytes() == live_model
