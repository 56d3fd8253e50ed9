"""The component's Cyphal node functions against pycyphal and the DSDL definitions.

How it runs (no CAN hardware or kernel support: python-can's in-process `virtual` bus):
    .venv/bin/python -m pytest -q -p no:cacheprovider tests/interop

The Rust side is fsw-component's example `cyphal_node` (built here, or named by the
environment variable CYPHAL_NODE_BIN), which runs the same `fsw_component::node` code as the
live component. pycyphal compiles the vendored `uavcan` DSDL (tests/interop/dsdl/) and:
1. decodes our `uavcan.node.Heartbeat.1.0` transfers on subject 7509 (uptime, health, mode,
   vendor-specific status, source node-ID, advancing transfer-IDs), classic CAN and CAN FD,
   and the `uavcan.node.port.List.1.0` sent with the first heartbeat (subject 7510);
2. calls `uavcan.node.GetInfo.1.0` (service 430) as a client: its request frames go to our
   server, our response frames go back on the bus, and pycyphal's client must accept the
   response (right IDs, transfer-ID, CRC) and decode name, versions and unique-ID;
3. lists our registers with `uavcan.register.List.1.0` (385), reads them with
   `uavcan.register.Access.1.0` (384), writes a port-ID register (a multi-frame request on
   classic CAN), sees a bad write refused with the unchanged value, restarts the node
   binary and reads the written value back from the register file, and sees the new
   subject-ID in the restarted node's port.List.
"""

import asyncio
import importlib
import pathlib
import subprocess
import sys
import uuid

import can
from conftest import example_binary
import pycyphal.dsdl
import pytest
from pycyphal.presentation import Presentation
from pycyphal.transport.can import CANTransport
from pycyphal.transport.can.media.pythoncan import PythonCANMedia

DSDL_ROOT = pathlib.Path(__file__).resolve().parent / "dsdl" / "uavcan"
NODE_ID = 42
CLIENT_NODE_ID = 123
TIMEOUT_S = 3.0


@pytest.fixture(scope="module")
def uavcan(tmp_path_factory):
    out = tmp_path_factory.mktemp("dsdl")
    pycyphal.dsdl.compile(DSDL_ROOT, output_directory=out)
    sys.path.insert(0, str(out))
    try:
        node = importlib.import_module("uavcan.node")
        node.port = importlib.import_module("uavcan.node.port")
        node.register = importlib.import_module("uavcan.register")
        node.primitive = importlib.import_module("uavcan.primitive")
        node.primitive.array = importlib.import_module("uavcan.primitive.array")
        yield node
    finally:
        sys.path.remove(str(out))


@pytest.fixture(scope="module")
def node_bin() -> str:
    return example_binary("fsw-component", "cyphal_node", "CYPHAL_NODE_BIN")


def media(channel: str, mtu: int) -> PythonCANMedia:
    if mtu == 8:
        return PythonCANMedia(f"virtual:{channel}", 1_000_000, 8)
    return PythonCANMedia(f"virtual:{channel}", (1_000_000, 4_000_000), 64)


def to_message(token: str) -> can.Message:
    ident, _, rest = token.strip().partition("#")
    is_fd = rest.startswith("#")
    data = bytes.fromhex(rest[2:] if is_fd else rest)
    return can.Message(arbitration_id=int(ident, 16), is_extended_id=True, data=data, is_fd=is_fd)


def format_frame(msg: can.Message) -> str:
    sep = "##0" if msg.is_fd else "#"
    return f"{msg.arbitration_id:08X}{sep}{bytes(msg.data).hex().upper()}"


@pytest.mark.parametrize("mtu", [8, 64])
@pytest.mark.parametrize(
    "mode,trainer,dropped,expected_health,expected_vssc",
    [
        ("train", "ok", 0, [0, 0, 0], 1),
        ("predict", "ok", 5, [0, 1, 1], 2),
        ("predict", "restarting", 0, [2, 2, 2], 2),
        ("idle", "gave-up", 0, [3, 3, 3], 0),
    ],
)
def test_pycyphal_decodes_our_heartbeat(uavcan, node_bin, mtu, mode, trainer, dropped, expected_health, expected_vssc):
    lines = subprocess.run(
        [node_bin, "heartbeat", "--node", str(NODE_ID), "--mtu", str(mtu), "--mode", mode, "--trainer", trainer,
         "--uptime", "1000", "--count", "3", "--dropped-per-beat", str(dropped)],
        check=True, capture_output=True, text=True,
    ).stdout.split()
    heartbeat_lines = [line for line in lines if line.startswith("107D55")]
    assert len(heartbeat_lines) == 3, "a heartbeat is one frame"

    async def run():
        channel = f"hb-{uuid.uuid4().hex}"
        presentation = Presentation(CANTransport(media(channel, mtu), local_node_id=None))
        subscriber = presentation.make_subscriber(uavcan.Heartbeat_1_0, pycyphal.dsdl.get_fixed_port_id(uavcan.Heartbeat_1_0))
        port_lists = presentation.make_subscriber(uavcan.port.List_1_0, pycyphal.dsdl.get_fixed_port_id(uavcan.port.List_1_0))
        bus = can.Bus(interface="virtual", channel=channel)
        received = []
        try:
            for line in lines:
                bus.send(to_message(line))
                if line in heartbeat_lines:
                    got = await subscriber.receive(asyncio.get_running_loop().time() + TIMEOUT_S)
                    assert got is not None, f"pycyphal did not accept heartbeat frame {line}"
                    received.append(got)
            port_list = await port_lists.receive(asyncio.get_running_loop().time() + TIMEOUT_S)
            assert await port_lists.receive(asyncio.get_running_loop().time() + 0.2) is None, "one list"
        finally:
            presentation.close()
            bus.shutdown()
        return received, port_list

    received, port_list = asyncio.run(run())
    assert port_list is not None, "pycyphal did not accept our port.List"
    ports, transfer = port_list
    assert transfer.source_node_id == NODE_ID and transfer.transfer_id == 0
    assert [p.value for p in ports.publishers.sparse_list] == [7509, 7510, 301, 400, 401]
    assert [p.value for p in ports.subscribers.sparse_list] == [100, 101, 200, 300]
    assert not ports.clients.mask.any()
    assert [i for i, bit in enumerate(ports.servers.mask) if bit] == [384, 385, 430]
    for k, (message, transfer) in enumerate(received):
        assert transfer.source_node_id == NODE_ID
        assert transfer.transfer_id == k
        assert message.uptime == 1000 + k
        assert message.health.value == expected_health[k]
        assert message.mode.value == uavcan.Mode_1_0.OPERATIONAL
        assert message.vendor_specific_status_code == expected_vssc


def relay(bus, server, answers):
    """Our side of the bus: each request frame to the server, its answer back, until
    `answers` requests are answered."""
    while answers > 0:
        msg = bus.recv(timeout=TIMEOUT_S)
        assert msg is not None, "no request frame from pycyphal"
        server.stdin.write(format_frame(msg) + "\n")
        server.stdin.flush()
        answer = server.stdout.readline().strip()
        assert answer != "IGNORED", f"our server ignored {format_frame(msg)}"
        if answer == "PENDING":
            continue
        for token in answer.split():
            bus.send(to_message(token))
        answers -= 1


@pytest.mark.parametrize("mtu", [8, 64])
def test_pycyphal_client_gets_our_node_info(uavcan, node_bin, mtu):
    unique_id = bytes(range(0xA0, 0xB0))
    name = "org.example.gsplat.fsw"
    server = subprocess.Popen(
        [node_bin, "serve", "--node", str(NODE_ID), "--mtu", str(mtu), "--name", name, "--unique-id", unique_id.hex()],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )

    async def run():
        channel = f"gi-{uuid.uuid4().hex}"
        presentation = Presentation(CANTransport(media(channel, mtu), local_node_id=CLIENT_NODE_ID))
        client = presentation.make_client(uavcan.GetInfo_1_0, pycyphal.dsdl.get_fixed_port_id(uavcan.GetInfo_1_0), NODE_ID)
        client.response_timeout = TIMEOUT_S
        bus = can.Bus(interface="virtual", channel=channel)
        loop = asyncio.get_running_loop()

        relay_task = loop.run_in_executor(None, relay, bus, server, 2)
        try:
            results = []
            for _ in range(2):  # two calls: transfer-IDs 0 and 1
                results.append(await client.call(uavcan.GetInfo_1_0.Request()))
            await relay_task
        finally:
            presentation.close()
            bus.shutdown()
        return results

    try:
        results = asyncio.run(run())
    finally:
        server.stdin.close()
        server.wait(timeout=TIMEOUT_S)
    for k, result in enumerate(results):
        assert result is not None, f"pycyphal client got no (valid) response to call {k}"
        response, transfer = result
        assert transfer.source_node_id == NODE_ID
        assert transfer.transfer_id == k
        assert (response.protocol_version.major, response.protocol_version.minor) == (1, 0)
        assert (response.hardware_version.major, response.hardware_version.minor) == (0, 0)
        assert response.software_version.major == 0
        assert bytes(response.unique_id) == unique_id
        assert bytes(response.name).decode() == name
        assert len(response.software_image_crc) == 0
        assert len(response.certificate_of_authenticity) == 0


def call_registers(uavcan, node_bin, config, mtu, calls):
    """Runs `calls` (a list of (service type, request)) against a freshly started node with
    `config`; returns the responses."""
    server = subprocess.Popen(
        [node_bin, "serve", "--config", str(config), "--mtu", str(mtu)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )

    async def run():
        channel = f"reg-{uuid.uuid4().hex}"
        presentation = Presentation(CANTransport(media(channel, mtu), local_node_id=CLIENT_NODE_ID))
        clients = {}
        bus = can.Bus(interface="virtual", channel=channel)
        relay_task = asyncio.get_running_loop().run_in_executor(None, relay, bus, server, len(calls))
        try:
            results = []
            for dtype, request in calls:
                if dtype not in clients:
                    clients[dtype] = presentation.make_client(dtype, pycyphal.dsdl.get_fixed_port_id(dtype), NODE_ID)
                    clients[dtype].response_timeout = TIMEOUT_S
                result = await clients[dtype].call(request)
                assert result is not None, f"no (valid) response to {request}"
                assert result[1].source_node_id == NODE_ID
                results.append(result[0])
            await relay_task
        finally:
            presentation.close()
            bus.shutdown()
        return results

    try:
        return asyncio.run(run())
    finally:
        server.stdin.close()
        server.wait(timeout=TIMEOUT_S)


@pytest.mark.parametrize("mtu", [8, 64])
def test_pycyphal_lists_reads_and_persists_registers(uavcan, node_bin, tmp_path, mtu):
    reg = uavcan.register
    register_file = tmp_path / "registers.toml"
    config = tmp_path / "component.toml"
    config.write_text(
        f'[node]\nnode_id = {NODE_ID}\ndescription = "bench unit 3"\n'
        f'[cyphal]\nregister_file = "{register_file}"\n'
    )
    name = lambda text: reg.Name_1_0(name=text)  # noqa: E731
    read = lambda text: (reg.Access_1_0, reg.Access_1_0.Request(name=name(text)))  # noqa: E731

    def write(text, value):
        return reg.Access_1_0, reg.Access_1_0.Request(name=name(text), value=value)

    natural16 = lambda n: reg.Value_1_0(natural16=uavcan.primitive.array.Natural16_1_0([n]))  # noqa: E731
    listing = [(reg.List_1_0, reg.List_1_0.Request(index=i)) for i in range(40)]
    first = call_registers(uavcan, node_bin, config, mtu, listing + [
        read("uavcan.node.description"),
        read("uavcan.sub.sun_vector.type"),
        read("no.such.register"),
        write("uavcan.pub.health_status.id", natural16(500)),
        write("uavcan.sub.command.id", natural16(500)),  # a duplicate: refused
    ])
    names = [bytes(r.name.name).decode() for r in first[:40]]
    count = names.index("")
    assert all(n == "" for n in names[count:]), "the list ends once"
    listed = set(names[:count])
    for expected in ["uavcan.node.id", "uavcan.node.description", "uavcan.can.iface", "uavcan.can.mtu",
                     "uavcan.sub.sun_vector.id", "uavcan.sub.target_pose.id", "uavcan.sub.camera_frame.id",
                     "uavcan.sub.command.id", "uavcan.pub.command_ack.id", "uavcan.pub.health_status.id",
                     "uavcan.pub.event.id", "uavcan.pub.event.type"]:
        assert expected in listed, expected
    description, type_name, missing, written, refused = first[40:]
    assert bytes(description.value.string.value).decode() == "bench unit 3"
    assert description.mutable and description.persistent
    assert description.timestamp.microsecond == 0, "no time synchronisation: unknown"
    assert bytes(type_name.value.string.value).decode() == "gsplat.SunVector.1.1"
    assert not type_name.mutable
    assert missing.value.empty is not None, "unknown register: empty value"
    assert list(written.value.natural16.value) == [500]
    assert list(refused.value.natural16.value) == [300], "refused: the unchanged value"
    assert "uavcan.pub.health_status.id" in register_file.read_text()

    # Restarted, the node reads the register file: the written value is there, the port moved.
    again = call_registers(uavcan, node_bin, config, mtu, [read("uavcan.pub.health_status.id")])
    assert list(again[0].value.natural16.value) == [500]
    lines = subprocess.run(
        [node_bin, "heartbeat", "--config", str(config), "--mtu", str(mtu), "--count", "1"],
        check=True, capture_output=True, text=True,
    ).stdout.split()

    async def port_list():
        channel = f"pl-{uuid.uuid4().hex}"
        presentation = Presentation(CANTransport(media(channel, mtu), local_node_id=None))
        subscriber = presentation.make_subscriber(uavcan.port.List_1_0, pycyphal.dsdl.get_fixed_port_id(uavcan.port.List_1_0))
        bus = can.Bus(interface="virtual", channel=channel)
        try:
            for line in lines:
                bus.send(to_message(line))
            return await subscriber.receive(asyncio.get_running_loop().time() + TIMEOUT_S)
        finally:
            presentation.close()
            bus.shutdown()

    got = asyncio.run(port_list())
    assert got is not None, "no port.List from the restarted node"
    assert [p.value for p in got[0].publishers.sparse_list] == [7509, 7510, 301, 500, 401]
