#!/usr/bin/env bash
# Installs Mesa's software Vulkan driver (lavapipe) and the Vulkan loader, which the
# wgpu parity tests (gs-wgpu/tests/gpu_*.rs) run on where the machine has no GPU.
# Idempotent: installs only what dpkg does not report as installed. Debian/Ubuntu only.
set -euo pipefail

packages=(mesa-vulkan-drivers libvulkan1)
missing=()
for p in "${packages[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$p")
    fi
done

if ((${#missing[@]})); then
    sudo=""
    if [ "$(id -u)" -ne 0 ]; then
        sudo="sudo"
    fi
    echo "installing ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
    echo "already installed: ${packages[*]}"
fi

# The driver registers itself as a Vulkan ICD; without it wgpu finds no adapter.
if ! ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then
    echo "error: lavapipe's ICD file (/usr/share/vulkan/icd.d/lvp_icd*.json) is missing" >&2
    exit 1
fi
