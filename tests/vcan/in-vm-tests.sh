#!/usr/bin/env bash
# in-vm-tests.sh: runs inside the vcan micro-VM (via run-can-tests.sh); not meant for the host.
#
# Usage: in-vm-tests.sh <fsw-component lib test binary> <transport_socketcan test binary>
#                       <can_echo_peer binary> <venv python>
# Runs the transport unit tests (their CAN error paths then meet a kernel with CAN), the Rust
# SocketCAN tests, then the pytests that need CAN (by convention tests/bus/test_*can*.py: the
# python-can <-> Rust peer, and the component binary named by FSW_COMPONENT_BIN on vcan), all
# against $VCAN_IFACE; runs all even if one fails, and fails if any does.
set -uo pipefail
if [ "$#" -ne 4 ] || [ -z "${VCAN_IFACE:-}" ]; then
    echo "usage (inside run-in-vm.sh): $0 <lib-test-binary> <test-binary> <peer-binary> <python>" >&2
    exit 2
fi
unit_test_binary=$1 test_binary=$2 peer_binary=$3 python=$4
status=0
now_ms() { echo $(($(date +%s%N) / 1000000)); }

started_ms=$(now_ms)
echo "== fsw-component transport unit tests ($unit_test_binary transport::)"
"$unit_test_binary" --color never transport:: || status=1
echo "[vcan] unit tests took $(($(now_ms) - started_ms)) ms"

started_ms=$(now_ms)
echo "== Rust SocketCAN transport tests on $VCAN_IFACE ($test_binary)"
"$test_binary" --color never || status=1
echo "[vcan] Rust tests took $(($(now_ms) - started_ms)) ms"

started_ms=$(now_ms)
echo "== python-can <-> Rust peer and component on $VCAN_IFACE"
PYTHONDONTWRITEBYTECODE=1 CAN_PEER_BIN=$peer_binary \
    "$python" -m pytest -q -p no:cacheprovider --color=no \
    tests/bus/test_*can*.py || status=1
echo "[vcan] pytest took $(($(now_ms) - started_ms)) ms"
exit "$status"
