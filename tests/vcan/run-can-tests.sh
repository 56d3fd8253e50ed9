#!/usr/bin/env bash
# run-can-tests.sh: the SocketCAN tests, on a real vcan0 inside the micro-VM of run-in-vm.sh.
#
# Usage: bash tests/vcan/run-can-tests.sh [--workspace]   (CARGO_TARGET_DIR is honoured)
#   --workspace: build as `cargo test --workspace` does (same feature unification), so that
#   after a workspace test run nothing is rebuilt; the default builds fsw-component alone.
#
# On the host: builds fsw-component's unit-test and transport_socketcan test binaries and the
# can_echo_peer example (default target CPU: the emulated CPU has no AVX-512), and the venv
# (tests/setup_venv.sh). In the VM: runs those prebuilt binaries (no cargo) and the python-can
# pytests in tests/bus/ that need CAN (the Rust peer, and the fsw-component binary itself, whose
# path goes in FSW_COMPONENT_BIN) against vcan0 (see in-vm-tests.sh). Exits non-zero if anything
# fails.
set -euo pipefail
cd "$(dirname "$0")/../.."

case "${RUSTFLAGS:-}${CARGO_ENCODED_RUSTFLAGS:-}" in
*target-cpu=native*)
    echo "[vcan] ERROR: RUSTFLAGS has target-cpu=native; the VM's CPU lacks AVX-512" >&2
    exit 1
    ;;
esac

case "${1:-}" in
"") cargo_scope=(-p fsw-component) ;;
--workspace) cargo_scope=(--workspace) ;;
*)
    echo "usage: $0 [--workspace]" >&2
    exit 2
    ;;
esac

echo "[vcan] building the SocketCAN test binaries and the Rust CAN peer (${cargo_scope[*]})" >&2
# One `cargo test --no-run` builds the test binaries and the examples; its JSON messages
# name each artifact. The executables needed are picked by target name and kind.
artifacts=$(cargo test "${cargo_scope[@]}" --no-run --message-format=json) || {
    # With JSON output the compiler's diagnostics are on stdout: show them.
    python3 -c '
import json, sys
for line in sys.stdin:
    try:
        message = json.loads(line)
    except ValueError:
        continue
    if message.get("reason") == "compiler-message":
        print(message["message"].get("rendered") or "", end="", file=sys.stderr)' \
        <<<"$artifacts"
    echo "[vcan] ERROR: cargo test --no-run failed" >&2
    exit 1
}
# $1: target name, $2: target kind, $3: "test" for a test harness build, "run" otherwise.
executable_of() {
    python3 -c '
import json, sys
name, kind, harness = sys.argv[1], sys.argv[2], sys.argv[3] == "test"
paths = sorted({m["executable"] for m in map(json.loads, sys.stdin)
                if m.get("reason") == "compiler-artifact" and m.get("executable")
                and m["target"]["name"] == name and kind in m["target"]["kind"]
                and m["profile"]["test"] == harness})
if len(paths) != 1:
    sys.exit(f"expected one {kind} executable named {name}, cargo reported {paths}")
print(paths[0])' "$1" "$2" "$3" <<<"$artifacts"
}
unit_test_binary=$(executable_of fsw_component lib test)
test_binary=$(executable_of transport_socketcan test test)
peer_binary=$(executable_of can_echo_peer example run)
component_binary=$(executable_of fsw-component bin run)
python=$(bash tests/setup_venv.sh)

FSW_COMPONENT_BIN=$component_binary \
    bash tests/vcan/run-in-vm.sh bash tests/vcan/in-vm-tests.sh \
    "$unit_test_binary" "$test_binary" "$peer_binary" "$python"
