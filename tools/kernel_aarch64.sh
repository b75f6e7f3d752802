#!/usr/bin/env bash
# The compiled per-frame kernel on aarch64 (the Raspberry Pi 4/5, Jetson): built with Debian's cross
# compiler, run under qemu-user, compared frame by frame with this machine's build (tools/kernel_aarch64.py).
#
#   tools/kernel_aarch64.sh [WORKDIR]
#
# Installs gcc-aarch64-linux-gnu, libc6-dev-arm64-cross and qemu-user with apt when they are missing (as
# root). The harness (kernel/harness.c) is the kernel with no Python: static, so qemu needs no arm64 root.
# The vector unit: the kernel's 4- and 8-lane vector code (GCC vector extensions) compiles to NEON on
# aarch64 as to SSE2/AVX2 on x86-64; the script counts the NEON instructions of the surface step.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-${TMPDIR:-/tmp}/optitac-aarch64}"
mkdir -p "$work"
need() {  # need COMMAND PACKAGE...
    command -v "$1" > /dev/null && return 0
    if [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
        apt-get install -y -q "${@:2}" > /dev/null 2>&1 || { apt-get update -q > /dev/null && apt-get install -y -q "${@:2}" > /dev/null; }
    fi
    command -v "$1" > /dev/null || { echo "kernel_aarch64: $1 is missing (apt-get install ${*:2})" >&2; exit 2; }
}
need aarch64-linux-gnu-gcc gcc-aarch64-linux-gnu libc6-dev-arm64-cross
need qemu-aarch64 qemu-user
flags=(-std=c99 -O3 -Wall -Wextra -ffp-contract=off)  # as setup.py builds the extension
aarch64-linux-gnu-gcc "${flags[@]}" -static -o "$work/harness-aarch64" kernel/harness.c kernel/frame_kernel.c kernel/gradient_solve.c -lm
gcc "${flags[@]}" -o "$work/harness-x86_64" kernel/harness.c kernel/frame_kernel.c kernel/gradient_solve.c -lm
echo "NEON instructions in the aarch64 surface step (gradient product and solve): $(aarch64-linux-gnu-objdump \
    -d "$work/harness-aarch64" | awk '/<(matvec4?|gs_solves4|ok_gradient_solve|ok_surface)>:/,/^$/' \
    | grep -cE '\s(fmul|fadd|fsub)\s+v[0-9]+\.4s')"
python3 tools/kernel_aarch64.py --workdir "$work" --harness "$work/harness-x86_64" \
    --harness "qemu-aarch64 $work/harness-aarch64"
