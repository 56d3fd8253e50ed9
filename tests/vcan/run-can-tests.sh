#!/usr/bin/env bash
# run-can-tests.sh: the SocketCAN tests, on a real vcan0 inside the micro-VM of run-in-vm.sh.
#
# Usage: bash tests/vcan/run-can-tests.sh   (from anywhere; CARGO_TARGET_DIR is honoured)
#
# On the host: builds fsw-component's unit-test and transport_socketcan test binaries and the can_echo_peer
# example (default target CPU: the emulated CPU has no AVX-512), and the Python venv
# (tests/setup_venv.sh). In the VM: runs those prebuilt binaries (no cargo) and the python-can
# pytest in tests/bus/ against vcan0 (see in-vm-tests.sh). Exits non-zero if anything fails.
set -euo pipefail
cd "$(dirname "$0")/../.."

case "${RUSTFLAGS:-}${CARGO_ENCODED_RUSTFLAGS:-}" in
*target-cpu=native*)
    echo "[vcan] ERROR: RUSTFLAGS has target-cpu=native; the VM's CPU lacks AVX-512" >&2
    exit 1
    ;;
esac

# The executable of target "$1" that cargo builds for the rest of the arguments (it reports
# every artifact as JSON on stdout; a test build may also build the crate's binaries).
cargo_executable() {
    local target_name=$1
    shift
    cargo "$@" --message-format=json |
        python3 -c '
import json, sys
name = sys.argv[1]
paths = [m["executable"] for m in map(json.loads, sys.stdin)
         if m.get("reason") == "compiler-artifact" and m.get("executable")
         and m["target"]["name"] == name]
if len(paths) != 1:
    sys.exit(f"expected one executable for {name}, cargo reported {paths}")
print(paths[0])' "$target_name"
}

echo "[vcan] building the SocketCAN test binary and the Rust CAN peer" >&2
unit_test_binary=$(cargo_executable fsw_component test -p fsw-component --lib --no-run)
test_binary=$(cargo_executable transport_socketcan \
    test -p fsw-component --test transport_socketcan --no-run)
peer_binary=$(cargo_executable can_echo_peer build -p fsw-component --example can_echo_peer)
python=$(bash tests/setup_venv.sh)

bash tests/vcan/run-in-vm.sh bash tests/vcan/in-vm-tests.sh \
    "$unit_test_binary" "$test_binary" "$peer_binary" "$python"
