"""Round trips between python-can and the Rust SocketCAN transport on a real vcan interface.

Runs inside the vcan micro-VM (tests/vcan/run-in-vm.sh sets VCAN_IFACE); skipped elsewhere.
The Rust side is fsw-component's example `can_echo_peer` (path in CAN_PEER_BIN), which echoes
every frame with ID bit 28 flipped and its data reversed, answers a burst request with frames
computed from a formula, and reports its counters when asked to stop. python-can's socketcan
backend is an independent implementation of the frame layout, so agreement here checks our
transport (IDs, lengths, FD flag, both directions) against the kernel ABI as others use it.
"""

import os
import re
import subprocess
import threading

import can
import pytest

IFACE = os.environ.get("VCAN_IFACE")
pytestmark = pytest.mark.skipif(
    not IFACE, reason="VCAN_IFACE not set: run through tests/vcan/run-in-vm.sh"
)

STOP_ID = 0x1FFF_FF00
BURST_ID = 0x1FFF_FF01
BURST_REPLY_BASE_ID = 0x0F00_0000
ECHO_ID_FLIP = 1 << 28
FD_LENGTHS = [0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]
TIMEOUT_S = 10.0


def data_for(index, length):
    return bytes((37 * index + 11 * k + 5) % 256 for k in range(length))


class Peer:
    """The running Rust peer process, with its stdout read line by line."""

    def __init__(self, binary, iface):
        self.process = subprocess.Popen(
            [binary, iface], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.lines = []
        self.ready = threading.Event()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()
        if not self.ready.wait(TIMEOUT_S):
            self.process.kill()
            raise AssertionError(
                f"peer not ready: {self.process.stderr.read() if self.process.poll() else ''}"
            )

    def _read(self):
        for line in self.process.stdout:
            self.lines.append(line.strip())
            if line.startswith("READY"):
                self.ready.set()

    def stop(self, bus):
        bus.send(can.Message(arbitration_id=STOP_ID, is_extended_id=True, data=b""))
        status = self.process.wait(TIMEOUT_S)
        self.reader.join(TIMEOUT_S)
        assert status == 0, self.process.stderr.read()
        stats_line = next(line for line in self.lines if line.startswith("STATS"))
        return {key: int(value) for key, value in re.findall(r"(\w+)=(\d+)", stats_line)}


@pytest.fixture
def bus():
    with can.Bus(interface="socketcan", channel=IFACE, fd=True) as bus:
        yield bus


@pytest.fixture
def peer(bus):
    binary = os.environ.get("CAN_PEER_BIN")
    assert binary and os.path.isfile(binary), "CAN_PEER_BIN must name the can_echo_peer binary"
    peer = Peer(binary, IFACE)
    yield peer
    if peer.process.poll() is None:
        peer.process.kill()
        peer.process.wait()


def receive(bus):
    message = bus.recv(TIMEOUT_S)
    assert message is not None, "no frame from the Rust peer in time"
    return message


def test_python_frames_are_echoed_by_the_rust_transport(bus, peer):
    sent = []
    for index, arbitration_id in enumerate([0, 1, 0x0123_4567, 0x1000_0001, 0x1FFF_FFFE]):
        for length in range(9):
            sent.append((arbitration_id, data_for(index + length, length), False))
        for length in FD_LENGTHS:
            sent.append((arbitration_id, data_for(index + 2 * length, length), True))
    for arbitration_id, data, is_fd in sent:
        bus.send(
            can.Message(
                arbitration_id=arbitration_id, is_extended_id=True, is_fd=is_fd, data=data
            )
        )
        reply = receive(bus)
        assert reply.is_extended_id
        assert reply.arbitration_id == arbitration_id ^ ECHO_ID_FLIP
        assert reply.is_fd == is_fd
        assert bytes(reply.data) == data[::-1]
        assert not reply.is_remote_frame and not reply.is_error_frame
    stats = peer.stop(bus)
    assert stats["frames_received"] == len(sent) + 1  # + the stop frame
    assert stats["frames_sent"] == len(sent)
    assert stats["dropped_standard_id"] == 0
    assert stats["dropped_receive_queue_full"] == 0


def test_rust_burst_is_received_exactly_by_python(bus, peer):
    count = 40
    bus.send(can.Message(arbitration_id=BURST_ID, is_extended_id=True, data=bytes([count])))
    for index in range(count):
        message = receive(bus)
        assert message.is_extended_id
        assert message.arbitration_id == BURST_REPLY_BASE_ID + index
        if index % 2 == 0:
            assert not message.is_fd
            assert bytes(message.data) == data_for(index, index % 9)
        else:
            assert message.is_fd
            assert bytes(message.data) == data_for(index, FD_LENGTHS[(index // 2) % 16])
    stats = peer.stop(bus)
    assert stats["frames_sent"] == count


def test_standard_id_and_remote_frames_are_dropped_and_counted_by_rust(bus, peer):
    bus.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"))
    bus.send(
        can.Message(arbitration_id=0x1234, is_extended_id=True, is_remote_frame=True, dlc=4)
    )
    bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, is_fd=True, data=b"x" * 12))
    bus.send(can.Message(arbitration_id=0x1234, is_extended_id=True, data=b"\x09\x08"))
    reply = receive(bus)  # the only echo: of the valid frame
    assert (reply.arbitration_id, bytes(reply.data)) == (0x1234 ^ ECHO_ID_FLIP, b"\x08\x09")
    stats = peer.stop(bus)
    assert stats["dropped_standard_id"] == 2
    assert stats["dropped_remote"] == 1
    assert stats["frames_received"] == 2  # the valid frame and the stop frame
    assert bus.recv(0.2) is None, "the peer echoed a frame it should have dropped"
