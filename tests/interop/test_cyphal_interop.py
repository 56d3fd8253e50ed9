"""Interoperability of our Cyphal/CAN framing (Rust crate `interfaces`) with pycyphal, an
independent implementation of the Cyphal/CAN v1.0 specification.

How it runs:
    python=$(bash tests/setup_venv.sh)        # venv with the pinned pycyphal, python-can, pytest
    "$python" -m pytest tests/interop -q

The test builds `cargo build -p interfaces --example cyphal_frames` itself (honouring
CARGO_TARGET_DIR), or uses the binary named by the environment variable CYPHAL_FRAMES_BIN.
No CAN hardware or kernel support is needed: frames travel over python-can's in-process
`virtual` bus.

1. Rust -> pycyphal: our encoder's frames are put on a virtual bus; a pycyphal CANTransport
   (PythonCANMedia on the same virtual channel) must reassemble each transfer, with the same
   payload, source node-ID and transfer-ID. Single- and multi-frame, classic CAN and CAN FD.
2. pycyphal -> Rust: pycyphal publishes transfers on the virtual bus; the frames it emits are
   captured, must be byte-identical to what our encoder produces for the same transfer, and
   our decoder (`cyphal_frames decode`) must reassemble them to the same payloads.
"""

import asyncio
import random
import subprocess
import uuid

import can
from conftest import example_binary
import pytest
from pycyphal.transport import (
    InputSessionSpecifier,
    MessageDataSpecifier,
    OutputSessionSpecifier,
    PayloadMetadata,
    Priority,
    Timestamp,
    Transfer,
)
from pycyphal.transport.can import CANTransport
from pycyphal.transport.can.media.pythoncan import PythonCANMedia

EXTENT_BYTES = 4096

# Payload sizes around every framing boundary: empty, classic single-frame limit (7),
# FD single-frame limit (63), CRC split across frames, FD padding cases, long transfers.
SIZES = [0, 1, 5, 7, 8, 11, 12, 13, 14, 30, 47, 60, 61, 62, 63, 64, 94, 120, 125, 126, 200, 1000]


@pytest.fixture(scope="module")
def frames_bin() -> str:
    return example_binary("interfaces", "cyphal_frames", "CYPHAL_FRAMES_BIN")


def payload_of(size: int, seed: int) -> bytes:
    rng = random.Random(seed)
    return bytes(rng.randrange(256) for _ in range(size))


def parse_frame_line(line: str) -> tuple[int, bytes, bool]:
    ident, _, rest = line.strip().partition("#")
    is_fd = rest.startswith("#")
    data = rest[2:] if is_fd else rest
    return int(ident, 16), bytes.fromhex(data), is_fd


def format_frame(msg: can.Message) -> str:
    sep = "##0" if msg.is_fd else "#"
    return f"{msg.arbitration_id:08X}{sep}{bytes(msg.data).hex().upper()}"


def rust_encode(frames_bin: str, subject: int, node: int, tid: int, mtu: int, payload: bytes) -> list[str]:
    out = subprocess.run(
        [frames_bin, "encode", "--subject", str(subject), "--node", str(node), "--tid", str(tid),
         "--mtu", str(mtu), "--payload", payload.hex()],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return [line for line in out.splitlines() if line.strip()]


def rust_decode(frames_bin: str, lines: list[str]) -> list[str]:
    out = subprocess.run(
        [frames_bin, "decode"], input="\n".join(lines) + "\n", check=True, capture_output=True, text=True
    ).stdout
    return out.splitlines()


def same_up_to_padding(received: bytes, sent: bytes) -> bool:
    """CAN FD pads the last frame with zeros; the receiver cannot tell padding from payload."""
    return received[: len(sent)] == sent and set(received[len(sent):]) <= {0} and len(received) - len(sent) <= 15


def media(channel: str, mtu: int) -> PythonCANMedia:
    if mtu == 8:
        return PythonCANMedia(f"virtual:{channel}", 1_000_000, 8)
    return PythonCANMedia(f"virtual:{channel}", (1_000_000, 4_000_000), 64)


@pytest.mark.parametrize("mtu", [8, 64])
def test_pycyphal_receives_our_frames(frames_bin: str, mtu: int) -> None:
    async def run() -> None:
        channel = f"ifc-{uuid.uuid4().hex}"
        transport = CANTransport(media(channel, mtu), local_node_id=None)
        bus = can.Bus(interface="virtual", channel=channel)
        subject = 1234
        session = transport.get_input_session(
            InputSessionSpecifier(MessageDataSpecifier(subject), None), PayloadMetadata(EXTENT_BYTES)
        )
        loop = asyncio.get_running_loop()
        try:
            for index, size in enumerate(SIZES):
                payload = payload_of(size, index)
                tid = (index * 7) % 40  # includes values >= 32 to check the modulo
                lines = rust_encode(frames_bin, subject, 17, tid, mtu, payload)
                capacity = mtu - 1
                expected_frames = 1 if size <= capacity else -(-(size + 2) // capacity)
                assert len(lines) == expected_frames, (size, lines)
                for line in lines:
                    ident, data, is_fd = parse_frame_line(line)
                    assert len(data) <= mtu
                    bus.send(can.Message(arbitration_id=ident, is_extended_id=True, data=data, is_fd=is_fd))
                transfer = await session.receive(loop.time() + 2.0)
                assert transfer is not None, f"pycyphal did not reassemble size {size} at MTU {mtu}"
                received = b"".join(bytes(f) for f in transfer.fragmented_payload)
                assert same_up_to_padding(received, payload), (size, received.hex(), payload.hex())
                assert transfer.source_node_id == 17
                assert transfer.priority == Priority.NOMINAL
                assert transfer.transfer_id == tid % 32
            stats = session.sample_statistics()
            assert stats.transfers == len(SIZES)
            assert stats.errors == 0
        finally:
            transport.close()
            bus.shutdown()

    asyncio.run(run())


@pytest.mark.parametrize("mtu", [8, 64])
def test_we_reassemble_pycyphal_frames_and_match_them_byte_for_byte(frames_bin: str, mtu: int) -> None:
    async def run() -> list[tuple[int, int, bytes, list[str]]]:
        channel = f"ifc-{uuid.uuid4().hex}"
        transport = CANTransport(media(channel, mtu), local_node_id=42)
        bus = can.Bus(interface="virtual", channel=channel)
        subject = 2345
        out_session = transport.get_output_session(
            OutputSessionSpecifier(MessageDataSpecifier(subject), None), PayloadMetadata(EXTENT_BYTES)
        )
        loop = asyncio.get_running_loop()
        sent = []
        try:
            for index, size in enumerate(SIZES):
                payload = payload_of(size, 100 + index)
                tid = index % 32
                ok = await out_session.send(
                    Transfer(
                        timestamp=Timestamp.now(),
                        priority=Priority.NOMINAL,
                        transfer_id=tid,
                        fragmented_payload=[memoryview(payload)],
                    ),
                    loop.time() + 2.0,
                )
                assert ok
                lines = []
                while True:
                    msg = bus.recv(timeout=0.2)
                    if msg is None:
                        break
                    lines.append(format_frame(msg))
                assert lines, f"no frames captured for size {size}"
                sent.append((size, tid, payload, lines))
        finally:
            transport.close()
            bus.shutdown()
        return sent

    sent = asyncio.run(run())
    all_lines = []
    for size, tid, payload, lines in sent:
        # Byte-for-byte the same frames as our encoder (ID, padding, CRC, tail bytes).
        ours = rust_encode(frames_bin, 2345, 42, tid, mtu, payload)
        assert [parse_frame_line(x)[:2] for x in ours] == [parse_frame_line(x)[:2] for x in lines], size
        all_lines.extend(lines)
    out = rust_decode(frames_bin, all_lines)
    transfers = [line for line in out if line.startswith("TRANSFER")]
    assert not [line for line in out if line.startswith("REJECT")], out
    assert len(transfers) == len(sent)
    for line, (size, tid, payload, _) in zip(transfers, sent):
        fields = dict(kv.split("=", 1) for kv in line.split()[1:])
        assert fields["subject"] == "2345"
        assert fields["source"] == "42"
        assert int(fields["tid"]) == tid
        assert same_up_to_padding(bytes.fromhex(fields["payload"]), payload), size
    assert out[-1] == f"COUNTERS frames={len(all_lines)} transfers={len(sent)} rejected=0"


def test_our_decoder_rejects_what_pycyphal_would_reject(frames_bin: str) -> None:
    """Corrupted CRC, a lost frame and a duplicated transfer: counted, never delivered."""
    payload = payload_of(40, 7)
    lines = rust_encode(frames_bin, 10, 3, 5, 8, payload)
    ident, data, _ = parse_frame_line(lines[-1])
    corrupted = lines[:-1] + [f"{ident:08X}#{(bytes([data[0] ^ 1]) + data[1:]).hex().upper()}"]
    out = rust_decode(frames_bin, corrupted)
    assert not [x for x in out if x.startswith("TRANSFER")]
    assert any("CrcMismatch" in x for x in out)

    out = rust_decode(frames_bin, lines[:2] + lines[3:])
    assert not [x for x in out if x.startswith("TRANSFER")]
    assert any("ToggleMismatch" in x for x in out)

    out = rust_decode(frames_bin, lines + lines)
    assert len([x for x in out if x.startswith("TRANSFER")]) == 1
    assert any("DuplicateTransfer" in x for x in out)


def test_our_decoder_reads_candump_logs_with_timestamps(frames_bin: str) -> None:
    """candump `.log` lines carry timestamps: the same transfer-ID repeated within the 2 s
    transfer-ID timeout is a duplicate, after it a new transfer (the sender restarted)."""
    lines = rust_encode(frames_bin, 100, 9, 4, 64, payload_of(80, 3))
    assert len(lines) == 2

    def log(t: float) -> list[str]:
        return [f"({t:.6f}) vcan0 {line}" for line in lines]

    out = rust_decode(frames_bin, log(1700000000.0) + log(1700000001.5) + log(1700000003.1))
    transfers = [x for x in out if x.startswith("TRANSFER")]
    assert len(transfers) == 2, out
    assert sum("DuplicateTransfer" in x for x in out) == 1
    assert out[-1] == "COUNTERS frames=6 transfers=2 rejected=2"
