#!/usr/bin/env bash
# The project's whole test command (README, .ci/run). Installs what it needs itself:
# the Python venv (python-can, pycyphal, pytest) and, for the SocketCAN tests, QEMU and a
# Debian kernel for the vcan micro-VM (tests/vcan/README.md).
set -euo pipefail
cd "$(dirname "$0")/.."
started=$SECONDS
step() { echo; echo "== $* (t+$((SECONDS - started)) s)"; }

step "commit subjects (at most 72 characters)"
bash tests/check_commit_subjects.sh
step "cargo fmt --check"
cargo fmt --all -- --check
step "cargo clippy"
cargo clippy --workspace --all-targets -- -D warnings
step "cargo doc (every intra-doc link resolves)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps
step "cargo test (unit, integration, gradient checks, fits, live UDP component)"
# Tests that need a CPU extension skip visibly where the CPU lacks it; where the CPU has
# it, a skip would hide a detection bug, so it is made a failure.
if grep -qw avx512f /proc/cpuinfo; then export GS_REQUIRE_AVX512=1; fi
if grep -qw avx2 /proc/cpuinfo && grep -qw fma /proc/cpuinfo; then export GS_REQUIRE_AVX2=1; fi
if grep -qw avx512_bf16 /proc/cpuinfo; then export GS_REQUIRE_BF16=1; fi
# AMX also needs Linux 5.16+ to grant the tile state; a kernel that refuses is a failure
# here too, since the CPU flags say the tiles exist.
if grep -qw amx_bf16 /proc/cpuinfo && grep -qw amx_tile /proc/cpuinfo; then
    export GS_REQUIRE_AMX=1
fi
echo "GS_REQUIRE_AVX512=${GS_REQUIRE_AVX512:-0} GS_REQUIRE_AVX2=${GS_REQUIRE_AVX2:-0}" \
    "GS_REQUIRE_BF16=${GS_REQUIRE_BF16:-0} GS_REQUIRE_AMX=${GS_REQUIRE_AMX:-0}"
# The GPU backend's tests run in the next step, where a missing adapter is a failure.
cargo test --workspace --exclude gs-wgpu

step "GPU backend: wgpu on Mesa's software Vulkan driver (lint and CPU parity tests)"
# The backend is crate gs-wgpu (linted above with the workspace); the component and the
# simulator take it with their feature `wgpu`. WGPU_BACKEND=vulkan keeps wgpu off the
# OpenGL path; GS_REQUIRE_GPU=1 makes a missing adapter fail the tests, never skip them.
bash tests/gpu/setup.sh
cargo clippy -p fsw-component -p sim-harness --features wgpu --all-targets -- -D warnings
# Parity with the CPU (rasterizer, shadow pass, networks, the resident Sun-aware step) and
# the online trainer's rounds on the device.
GS_REQUIRE_GPU=1 WGPU_BACKEND=vulkan cargo test -p gs-wgpu

step "python test environment"
python=$(bash tests/setup_venv.sh)

step "Cyphal interoperability with pycyphal"
"$python" -m pytest -q -p no:cacheprovider tests/interop

step "bus tests over loopback UDP: python-can and sockets against the component binary"
"$python" -m pytest -q -p no:cacheprovider tests/bus/test_component_udp.py

step "SocketCAN tests on a real vcan0 inside the micro-VM"
bash tests/vcan/run-can-tests.sh --workspace

step "all tests passed"
