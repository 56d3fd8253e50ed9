#!/usr/bin/env bash
# run-in-vm.sh: run one command against a real SocketCAN interface (vcan0) inside a QEMU micro-VM.
#
# Usage:  bash tests/vcan/run-in-vm.sh <command> [args...]
#
# Why: the CI kernel (and most dev containers) has no CAN at all (no AF_CAN, no vcan module), so
# SocketCAN code cannot be exercised on the host. This script boots Debian's stock kernel under
# QEMU (TCG, no KVM, no network) with a tiny busybox initramfs that:
#   1. insmods the virtio, 9p and CAN modules (found through the kernel's modules.dep, so the list
#      follows whatever kernel is installed; .ko.xz/.ko.zst/.ko.gz are decompressed at build time),
#   2. mounts the host's / read-only over 9p at /host, and a writable 9p share (this run's results
#      folder) at the same path it has on the host,
#   3. creates vcan0 (mtu 72: carries classic and CAN FD frames) and vcan1 (mtu 16: classic only),
#   4. bind-mounts /proc /sys /dev into /host, chroots there and runs <command> with the caller's
#      environment and working directory, so host binaries (prebuilt Rust test binaries, the
#      project's venv python) run unchanged against vcan0,
#   5. writes the command's exit status to the results share and powers off.
# Inside the command: VCAN_IFACE=vcan0, VCAN_CLASSIC_IFACE=vcan1, VCAN_RESULTS=<writable folder>,
# TMPDIR inside that folder (the host root is read-only in the VM).
#
# The script exits with the command's exit status. It exits non-zero with a clear message when the
# VM does not reach the command within VCAN_BOOT_TIMEOUT_S (default 120) or the whole run exceeds
# VCAN_RUN_TIMEOUT_S (default 900). Console output (the command's stdout and stderr) is streamed.
#
# Needs: qemu-system-x86_64, a Debian kernel with its modules (linux-image-amd64), a static
# busybox (busybox-static), cpio and xz. Missing ones are installed with apt-get (root, Debian), as CI
# does on a fresh machine. Build artefacts go to tests/vcan/build/ (git-ignored).
#
# Speed (TCG emulates every instruction): the kernel is booted as its uncompressed ELF vmlinux
# through the PVH entry point (extracted once and cached; skips ~6 s of in-guest xz
# decompression), and with mitigations=off (no page-table isolation flushes on every syscall,
# which 9p-heavy work such as Python imports is full of). Neither matters for a throwaway VM.
#
# Knobs: VCAN_VM_MEM_MB (default 1024), VCAN_VM_CPUS (default 2), VCAN_KEEP_RESULTS=1 keeps the
# per-run results folder (console log, exit status) for inspection.
#
# Caveat: the emulated CPU (-cpu max under TCG) has AVX2/FMA but no AVX-512: binaries run here must
# not be built with -C target-cpu=native on an AVX-512 host.
set -euo pipefail

if [ "$#" -eq 0 ]; then
    echo "usage: $0 <command> [args...]" >&2
    exit 2
fi

script_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
build_dir="$script_dir/build"
boot_timeout_s=${VCAN_BOOT_TIMEOUT_S:-120}
run_timeout_s=${VCAN_RUN_TIMEOUT_S:-900}
vm_mem_mb=${VCAN_VM_MEM_MB:-1024}
vm_cpus=${VCAN_VM_CPUS:-2}

log() { echo "[vcan] $*" >&2; }
die() {
    echo "[vcan] ERROR: $*" >&2
    exit 1
}

# ---------------------------------------------------------------------------------------------
# 1. Tools: install what is missing (apt-get update at most once).
# ---------------------------------------------------------------------------------------------
newest_kernel_with_vcan() {
    local version
    for vmlinuz in $(printf '%s\n' /boot/vmlinuz-* | sort -rV); do
        version=${vmlinuz#/boot/vmlinuz-}
        if [ -r "$vmlinuz" ] && [ -f "/lib/modules/$version/modules.dep" ] &&
            grep -qE '(^|/)vcan\.ko(\.[a-z]+)?:' "/lib/modules/$version/modules.dep"; then
            echo "$version"
            return 0
        fi
    done
    return 1
}

busybox_is_static() {
    [ -x /bin/busybox ] && ! ldd /bin/busybox >/dev/null 2>&1
}

missing_packages=()
command -v qemu-system-x86_64 >/dev/null 2>&1 || missing_packages+=(qemu-system-x86)
newest_kernel_with_vcan >/dev/null || missing_packages+=(linux-image-amd64)
busybox_is_static || missing_packages+=(busybox-static)
command -v cpio >/dev/null 2>&1 || missing_packages+=(cpio)
# xz unpacks the kernel for the fast PVH boot (and .ko.xz modules); without it: bzImage boot.
command -v xz >/dev/null 2>&1 || missing_packages+=(xz-utils)
if [ "${#missing_packages[@]}" -gt 0 ]; then
    command -v apt-get >/dev/null 2>&1 ||
        die "missing ${missing_packages[*]} and no apt-get to install them"
    [ "$(id -u)" -eq 0 ] || die "missing ${missing_packages[*]}: run as root (or install them)"
    log "installing ${missing_packages[*]} (apt-get, quiet)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "${missing_packages[@]}" >/dev/null ||
        die "apt-get install ${missing_packages[*]} failed"
fi
command -v qemu-system-x86_64 >/dev/null 2>&1 || die "qemu-system-x86_64 not found after install"
busybox_is_static || die "/bin/busybox is not a static busybox (install busybox-static)"
kernel_version=$(newest_kernel_with_vcan) ||
    die "no /boot/vmlinuz-* with a vcan module under /lib/modules (install linux-image-amd64)"
kernel_image=/boot/vmlinuz-$kernel_version
modules_dir=/lib/modules/$kernel_version

# ---------------------------------------------------------------------------------------------
# 2. Initramfs: busybox, the modules (dependency order from modules.dep), and /init.
# ---------------------------------------------------------------------------------------------
# Module names as modules.dep spells their file stems; '-' and '_' are interchangeable.
wanted_modules=(virtio_pci 9pnet_virtio 9p can_raw vcan)

# Sets $module_name from a modules.dep path (pure bash: modules.dep has thousands of lines).
normalise_module_name() {
    module_name=${1##*/}
    module_name=${module_name%%.ko*}
    module_name=${module_name//-/_}
}

declare -A module_path_by_name=() module_deps_by_name=()
while IFS=: read -r path deps; do
    normalise_module_name "$path"
    module_path_by_name[$module_name]=$path
    module_deps_by_name[$module_name]=$deps
done <"$modules_dir/modules.dep"

declare -A module_is_ordered=()
ordered_modules=()
add_module_with_deps() {
    local name=$1 path dep
    [ -n "${module_is_ordered[$name]:-}" ] && return 0
    path=${module_path_by_name[$name]:-}
    if [ -z "$path" ]; then
        # Built into this kernel: nothing to load.
        if grep -qE "(^|/)${name//_/[-_]}\.ko$" "$modules_dir/modules.builtin" 2>/dev/null; then
            module_is_ordered[$name]=builtin
            return 0
        fi
        die "kernel $kernel_version has no module '$name' (needed for 9p/virtio/CAN)"
    fi
    for dep in ${module_deps_by_name[$name]}; do
        normalise_module_name "$dep"
        add_module_with_deps "$module_name"
    done
    module_is_ordered[$name]=yes
    ordered_modules+=("$path")
}
for name in "${wanted_modules[@]}"; do
    add_module_with_deps "$name"
done

mkdir -p "$build_dir"

# Under TCG, the bzImage's own xz decompressor takes ~6 s of a ~10 s boot. The kernel also
# has a PVH entry point (CONFIG_PVH), through which QEMU boots the uncompressed ELF vmlinux
# directly: extract it once per kernel version (cached), fall back to the bzImage otherwise.
uncompressed_kernel() {
    local vmlinux=$build_dir/vmlinux-$kernel_version offset
    if [ -s "$vmlinux" ] && [ "$vmlinux" -nt "$kernel_image" ]; then
        echo "$vmlinux"
        return 0
    fi
    grep -q '^CONFIG_PVH=y' "/boot/config-$kernel_version" 2>/dev/null || return 1
    command -v xz >/dev/null 2>&1 || return 1
    offset=$(LC_ALL=C grep -obUaP '\xfd7zXZ\x00' "$kernel_image" | head -n 1 | cut -d: -f1)
    [ -n "$offset" ] || return 1
    tail -c "+$((offset + 1))" "$kernel_image" | xz -dc --single-stream >"$vmlinux.tmp.$$" \
        2>/dev/null || true
    if [ "$(head -c 4 "$vmlinux.tmp.$$" | od -An -c | tr -d ' ')" = '177ELF' ]; then
        mv "$vmlinux.tmp.$$" "$vmlinux"
        echo "$vmlinux"
        return 0
    fi
    rm -f "$vmlinux.tmp.$$"
    return 1
}
boot_image=$(uncompressed_kernel) || boot_image=$kernel_image

initramfs=$build_dir/initramfs-$kernel_version.$$.cpio.gz
staging=$(mktemp -d "$build_dir/initramfs-staging.XXXXXX")
results_dir=$(mktemp -d "$build_dir/run.XXXXXX")
qemu_pid=
# shellcheck disable=SC2317  # called through the EXIT trap
cleanup() {
    if [ -n "$qemu_pid" ] && kill -0 "$qemu_pid" 2>/dev/null; then
        kill "$qemu_pid" 2>/dev/null || true
    fi
    rm -rf "$staging"
    rm -f "$initramfs"
    if [ "${VCAN_KEEP_RESULTS:-0}" != 1 ]; then
        rm -rf "$results_dir"
    fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

mkdir -p "$staging"/{bin,dev,proc,sys,host,modules}
cp /bin/busybox "$staging/bin/busybox"
index=0
for path in "${ordered_modules[@]}"; do
    index=$((index + 1))
    normalise_module_name "$path"
    target=$(printf '%s/modules/%02d-%s.ko' "$staging" "$index" "$module_name")
    case "$path" in
    *.ko.xz) command -v xz >/dev/null 2>&1 || die "modules are .ko.xz: install xz-utils" ;;
    *.ko.zst) command -v zstd >/dev/null 2>&1 || die "modules are .ko.zst: install zstd" ;;
    esac
    case "$path" in
    *.ko) cp "$modules_dir/$path" "$target" ;;
    *.ko.xz) xz -dc "$modules_dir/$path" >"$target" ;;
    *.ko.zst) zstd -qdc "$modules_dir/$path" >"$target" ;;
    *.ko.gz) gzip -dc "$modules_dir/$path" >"$target" ;;
    *) die "unknown module format: $path" ;;
    esac
done

# The writable share is mounted at the results folder's own host path, so paths are the same
# inside the chroot as outside.
cat >"$staging/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
fail() { echo "[vcan-vm] FAILED: \$*"; poweroff -f; }
for module in /modules/*.ko; do
    insmod "\$module" || fail "insmod \$module"
done
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=512000,cache=loose host /host ||
    fail "mount host root over 9p"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 results "/host$results_dir" ||
    fail "mount results share"
ip link add dev vcan0 type vcan || fail "create vcan0"
ip link set dev vcan0 mtu 72 || fail "vcan0 mtu 72 (CAN FD)"
ip link set dev vcan0 up || fail "vcan0 up"
ip link add dev vcan1 type vcan || fail "create vcan1"
ip link set dev vcan1 mtu 16 || fail "vcan1 mtu 16 (classic only)"
ip link set dev vcan1 up || fail "vcan1 up"
ip link set dev lo up
mount --bind /proc /host/proc
mount --bind /sys /host/sys
mount --bind /dev /host/dev
mkdir -p /dev/shm && mount -t tmpfs tmpfs /dev/shm
cut -d' ' -f1 /proc/uptime > "/host$results_dir/booted"
chroot /host /bin/bash "$results_dir/command.sh"
echo \$? > "/host$results_dir/exit_status"
cut -d' ' -f1 /proc/uptime > "/host$results_dir/finished"
sync
poweroff -f
EOF
chmod +x "$staging/init"
(cd "$staging" && find . | cpio --quiet -o -H newc | gzip -1) >"$initramfs"

# ---------------------------------------------------------------------------------------------
# 3. The command, with the caller's environment and working directory.
# ---------------------------------------------------------------------------------------------
mkdir -p "$results_dir/tmp"
{
    echo "# generated by run-in-vm.sh"
    while IFS= read -r -d '' entry; do
        name=${entry%%=*}
        case "$name" in
        '' | *[!A-Za-z0-9_]* | [0-9]*) continue ;;
        PWD | OLDPWD | SHLVL | _ | SHELLOPTS | BASHOPTS | BASH_* | TMPDIR) continue ;;
        esac
        printf 'export %s=%q\n' "$name" "${entry#*=}"
    done < <(env -0)
    printf 'export VCAN_IFACE=vcan0 VCAN_CLASSIC_IFACE=vcan1 VCAN_RESULTS=%q TMPDIR=%q\n' \
        "$results_dir" "$results_dir/tmp"
    printf 'cd %q || exit 125\n' "$PWD"
    printf '%q ' "$@"
    echo
} >"$results_dir/command.sh"

# ---------------------------------------------------------------------------------------------
# 4. Boot, stream the console, enforce the time limits, report.
# ---------------------------------------------------------------------------------------------
console_log=$results_dir/console.log
: >"$console_log"
log "kernel $kernel_version ($(basename "$boot_image")), ${#ordered_modules[@]} modules," \
    "TCG, ${vm_cpus} vCPU, ${vm_mem_mb} MiB"
now_ms() { echo $(($(date +%s%N) / 1000000)); }
seconds() { awk -v ms="$1" 'BEGIN { printf "%.1f", ms / 1000 }'; }
started_ms=$(now_ms)
qemu-system-x86_64 \
    -accel tcg -cpu max -smp "$vm_cpus" -m "$vm_mem_mb" \
    -nodefaults -display none -no-reboot \
    -serial "file:$console_log" \
    -kernel "$boot_image" -initrd "$initramfs" \
    -append "console=ttyS0 quiet loglevel=3 panic=-1 mitigations=off" \
    -virtfs local,path=/,mount_tag=host,security_model=none,readonly=on,multidevs=remap \
    -virtfs "local,path=$results_dir,mount_tag=results,security_model=none" \
    </dev/null >"$results_dir/qemu.log" 2>&1 &
qemu_pid=$!
tail -n +1 -f --pid="$qemu_pid" "$console_log" &
tail_pid=$!

failure=
booted_after_ms=
while kill -0 "$qemu_pid" 2>/dev/null; do
    elapsed_ms=$(($(now_ms) - started_ms))
    if [ -z "$booted_after_ms" ] && [ -f "$results_dir/booted" ]; then
        booted_after_ms=$elapsed_ms
    fi
    if [ -z "$booted_after_ms" ] && [ "$elapsed_ms" -gt $((boot_timeout_s * 1000)) ]; then
        failure="the VM did not boot to the command within ${boot_timeout_s} s (VCAN_BOOT_TIMEOUT_S)"
        break
    fi
    if [ "$elapsed_ms" -gt $((run_timeout_s * 1000)) ]; then
        failure="the VM run exceeded ${run_timeout_s} s (VCAN_RUN_TIMEOUT_S)"
        break
    fi
    sleep 0.2
done
if [ -n "$failure" ]; then
    kill "$qemu_pid" 2>/dev/null || true
fi
wait "$qemu_pid" 2>/dev/null || true
wait "$tail_pid" 2>/dev/null || true
total_ms=$(($(now_ms) - started_ms))

if [ -n "$failure" ]; then
    sed 's/^/[qemu] /' "$results_dir/qemu.log" >&2
    die "$failure"
fi
if [ ! -f "$results_dir/exit_status" ]; then
    sed 's/^/[qemu] /' "$results_dir/qemu.log" >&2
    die "the VM stopped without reporting the command's exit status (see the console output above)"
fi
exit_status=$(cat "$results_dir/exit_status")
if [ -f "$results_dir/booted" ] && [ -f "$results_dir/finished" ]; then
    command_s=$(awk -v a="$(cat "$results_dir/booted")" -v b="$(cat "$results_dir/finished")" \
        'BEGIN { printf "%.1f", b - a }')
    log "timing: boot $(seconds "${booted_after_ms:-0}") s, command $command_s s (VM clock)," \
        "total $(seconds "$total_ms") s"
fi
log "command exited with status $exit_status"
exit "$exit_status"
