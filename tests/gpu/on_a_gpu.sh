#!/usr/bin/env bash
# Measures and checks the wgpu backend on a machine with a real GPU (docs/gpu.md, "On a
# GPU"): the configuration-(d) step per stage at 10K-100K Gaussians, the demo trained on
# the device, and every gs-wgpu parity test. Two halves, because a GPU machine may have no
# Rust toolchain:
#   bash tests/gpu/on_a_gpu.sh build DIR   # here: release binaries, stripped, into DIR
#   bash tests/gpu/on_a_gpu.sh run DIR     # there: runs them; DIR/log.txt is the record
# `run` needs a Vulkan loader and the GPU's ICD (NVIDIA: VK_DRIVER_FILES, set below when
# the usual file exists); NVIDIA's Vulkan driver also loads glvnd's libGLX and libEGL
# (Debian: libglvnd0, libglx0, libegl1), without which wgpu finds no adapter. Nothing here is part of CI, which has no GPU.
set -uo pipefail

mode=${1:-}
dir=${2:-}
if [[ -z "$mode" || -z "$dir" || ("$mode" != build && "$mode" != run) ]]; then
    echo "usage: bash tests/gpu/on_a_gpu.sh build|run DIR" >&2
    exit 2
fi

if [[ "$mode" == build ]]; then
    set -e
    target=${CARGO_TARGET_DIR:-target}
    cargo build --release -p gs-wgpu --example step_bench
    cargo build --release -p sim-harness --features wgpu --bin sim-harness
    mkdir -p "$dir"
    cp "$target/release/examples/step_bench" "$target/release/sim-harness" "$dir/"
    # One binary per test file of gs-wgpu, named test_<file>.
    cargo test --release -p gs-wgpu --no-run --message-format=json 2>/dev/null |
        python3 -c '
import json, shutil, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["profile"]["test"]:
        shutil.copy(m["executable"], sys.argv[1] + "/test_" + m["target"]["name"])
' "$dir"
    strip "$dir"/*
    ls -la "$dir"
    exit 0
fi

nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if [[ -z "${VK_DRIVER_FILES:-}" && -f "$nvidia_icd" ]]; then
    export VK_DRIVER_FILES=$nvidia_icd
fi
export WGPU_BACKEND=vulkan GS_REQUIRE_GPU=1
t0=$(date +%s)
stamp() { echo "=== $1 (t=$(($(date +%s) - t0)) s)"; }
{
    stamp machine
    lscpu | grep -E 'Model name|^CPU\(s\)'
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv 2>/dev/null
    stamp step_bench
    timeout 150 "$dir/step_bench" --backend wgpu --sizes 10000,50000,100000 \
        --images 480x300,960x600 --repeats 20 --scene surface || exit 1
    stamp tests
    for t in "$dir"/test_*; do
        echo "--- $t"
        timeout 120 "$t" --test-threads 4 2>&1 | grep -E "test result|FAILED|panicked|gpu .* cpu"
    done
    # The demo's preset (learned normal, Phi's local-frame inputs) trained on the device;
    # its ladder lines ("masked PSNR") and summary ("demo:") or its error.
    stamp demo
    timeout 300 "$dir/sim-harness" --backend wgpu demo --out "$dir/demo" 2>&1 |
        grep -E "masked PSNR|^demo:|[Ee]rror|panicked"
    stamp end
} 2>&1 | tee "$dir/log.txt"
