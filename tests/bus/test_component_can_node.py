"""The live flight component as a Cyphal node on a real vcan interface, pycyphal as the peer.

Runs inside the vcan micro-VM (tests/vcan/run-in-vm.sh sets VCAN_IFACE); skipped elsewhere.
pycyphal (SocketCAN media, CAN FD, node-ID 123), with the `uavcan` DSDL vendored in
tests/interop/dsdl/, must see the component's uavcan.node.Heartbeat.1.0 from node 42 at about
1 Hz (uptime counting, mode OPERATIONAL, health NOMINAL on a quiet bus, vendor status 1 =
Train) and get a uavcan.node.GetInfo.1.0 response (name, unique-ID from the configuration).
A second test writes the HealthStatus port-ID register over classic CAN (multi-frame
uavcan.register.Access requests to the live component on vcan1), restarts the component and
sees the value read back from the register file and HealthStatus published on the new subject.
"""

import asyncio
import importlib
import os
import pathlib
import sys
import time

import pycyphal.dsdl
import pytest

from test_component_udp import Component, write_config
from test_component_udp import listener  # noqa: F401  (pytest fixture)

IFACE = os.environ.get("VCAN_IFACE")
pytestmark = pytest.mark.skipif(
    not IFACE, reason="VCAN_IFACE not set: run through tests/vcan/run-in-vm.sh"
)
NODE = 42
CLIENT_NODE = 123
DSDL_ROOT = pathlib.Path(__file__).resolve().parents[1] / "interop" / "dsdl" / "uavcan"
UNIQUE_ID = bytes(range(0x30, 0x40))


@pytest.fixture(scope="module")
def uavcan(tmp_path_factory):
    out = tmp_path_factory.mktemp("dsdl")
    pycyphal.dsdl.compile(DSDL_ROOT, output_directory=out)
    sys.path.insert(0, str(out))
    try:
        node = importlib.import_module("uavcan.node")
        node.register = importlib.import_module("uavcan.register")
        node.primitive_array = importlib.import_module("uavcan.primitive.array")
        yield node
    finally:
        sys.path.remove(str(out))


def test_pycyphal_sees_heartbeat_and_calls_get_info(tmp_path, listener, uavcan):  # noqa: F811
    from pycyphal.presentation import Presentation
    from pycyphal.transport.can import CANTransport
    from pycyphal.transport.can.media.socketcan import SocketCANMedia

    config = tmp_path / "component.toml"
    write_config(config, listener, tmp_path / "checkpoint.bin", can_enabled=True, interface=IFACE)
    config.write_text(config.read_text() + f'\n[node]\nunique_id = "{UNIQUE_ID.hex()}"\n')
    component = Component(config)

    async def run():
        presentation = Presentation(CANTransport(SocketCANMedia(IFACE, 64), local_node_id=CLIENT_NODE))
        heartbeats = presentation.make_subscriber(uavcan.Heartbeat_1_0, 7509)
        client = presentation.make_client(uavcan.GetInfo_1_0, 430, NODE)
        client.response_timeout = 3.0
        loop = asyncio.get_running_loop()
        try:
            beats = []
            deadline = loop.time() + 10.0
            # Four heartbeats; the first is dropped below: it may have waited in the socket
            # while pycyphal started, which skews its arrival time.
            while len(beats) < 4 and loop.time() < deadline:
                got = await heartbeats.receive(deadline)
                if got is not None and got[1].source_node_id == NODE:
                    # The kernel receive time (SO_TIMESTAMP), not when this loop got to it.
                    beats.append((float(got[1].timestamp.system), got[0]))
            beats = beats[1:]
            info = await client.call(uavcan.GetInfo_1_0.Request())
        finally:
            presentation.close()
        return beats, info

    try:
        beats, info = asyncio.run(run())
    finally:
        assert component.stop() == 0
    assert len(beats) == 3, "fewer than 3 heartbeats from node 42 in 10 s"
    times = [t for t, _ in beats]
    assert all(0.7 < b - a < 1.3 for a, b in zip(times, times[1:])), times
    uptimes = [m.uptime for _, m in beats]
    assert uptimes == sorted(uptimes) and uptimes[-1] - uptimes[0] in (1, 2, 3), uptimes
    for _, m in beats:
        assert m.mode.value == uavcan.Mode_1_0.OPERATIONAL
        assert m.health.value == uavcan.Health_1_0.NOMINAL
        assert m.vendor_specific_status_code == 1  # Train
    assert info is not None, "no GetInfo response from the component"
    response, transfer = info
    assert transfer.source_node_id == NODE
    assert bytes(response.name).decode() == "org.example.gsplat.fsw"
    assert bytes(response.unique_id) == UNIQUE_ID
    assert (response.protocol_version.major, response.protocol_version.minor) == (1, 0)


MOVED_HEALTH_SUBJECT = 1400


def test_register_write_persists_and_moves_the_port_on_restart(tmp_path, listener, uavcan):  # noqa: F811
    import can
    from pycyphal.presentation import Presentation
    from pycyphal.transport.can import CANTransport
    from pycyphal.transport.can.media.socketcan import SocketCANMedia

    classic = os.environ.get("VCAN_CLASSIC_IFACE", IFACE)
    register_file = tmp_path / "registers.toml"
    config = tmp_path / "component.toml"
    write_config(config, listener, tmp_path / "checkpoint.bin", can_enabled=True, interface=classic)
    config.write_text(config.read_text().replace("[can]\n", "[can]\nfd = false\n", 1)
                      + f'\n[node]\ndescription = "vm bench"\n[cyphal]\nregister_file = "{register_file}"\n')
    reg = uavcan.register

    def access(name, value=None):
        request = reg.Access_1_0.Request(name=reg.Name_1_0(name=name))
        if value is not None:
            request.value = reg.Value_1_0(natural16=uavcan.primitive_array.Natural16_1_0([value]))
        return request

    async def calls(requests):
        presentation = Presentation(CANTransport(SocketCANMedia(classic, 8), local_node_id=CLIENT_NODE))
        client = presentation.make_client(reg.Access_1_0, 384, NODE)
        client.response_timeout = 3.0
        try:
            return [await client.call(r) for r in requests]
        finally:
            presentation.close()

    component = Component(config)
    try:
        first = asyncio.run(calls([access("uavcan.node.description"),
                                   access("uavcan.pub.health_status.id", MOVED_HEALTH_SUBJECT)]))
    finally:
        assert component.stop() == 0
    assert all(r is not None for r in first), "no Access response from the component"
    assert bytes(first[0][0].value.string.value).decode() == "vm bench"
    assert list(first[1][0].value.natural16.value) == [MOVED_HEALTH_SUBJECT]

    component = Component(config)
    try:
        again = asyncio.run(calls([access("uavcan.pub.health_status.id")]))
        bus = can.Bus(interface="socketcan", channel=classic)
        subjects = set()
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            msg = bus.recv(timeout=0.5)
            if msg is not None and msg.arbitration_id & 0x7F == NODE and not msg.arbitration_id >> 25 & 1:
                subjects.add(msg.arbitration_id >> 8 & 0x1FFF)
        bus.shutdown()
    finally:
        assert component.stop() == 0
    assert again[0] is not None and list(again[0][0].value.natural16.value) == [MOVED_HEALTH_SUBJECT]
    assert MOVED_HEALTH_SUBJECT in subjects, f"HealthStatus not on the moved subject: {sorted(subjects)}"
    assert 400 not in subjects, "HealthStatus still on the default subject"
