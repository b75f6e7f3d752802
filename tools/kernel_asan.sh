#!/usr/bin/env bash
# The compiled per-frame kernel under AddressSanitizer and UndefinedBehaviorSanitizer: the extension built with
# -fsanitize=address,undefined, loaded in place of the installed one in every Python the kernel tests start
# (a sitecustomize.py on PYTHONPATH; libasan preloaded, Python itself is not instrumented), then
# tests/test_kernel.py run: its parity tests, the odd mesh sides, the striped masks, the bad plans; and the
# motion and vibration steps against their Python references (tests/test_motion.py, tests/test_vibration.py).
#
#   tools/kernel_asan.sh [WORKDIR] [PYTEST ARGS...]
#
# Exit 0 only when every test passed and the sanitizers reported nothing (ASan aborts on its first error,
# UBSan is made to). CI runs it once after the suite (.ci/run).
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-${TMPDIR:-/tmp}/optitac-asan}"
shift || true
mkdir -p "$work/optitac_asan"
asan="$(gcc -print-file-name=libasan.so)"
[ -e "$asan" ] || { echo "kernel_asan: no libasan.so for gcc (apt-get install libasan8 or gcc)" >&2; exit 2; }
include="$(python3 -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
suffix="$(python3 -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))')"
so="$work/optitac_asan/_frame_kernel$suffix"
# as setup.py builds it, plus the sanitizers (-O1 keeps the reports' lines exact)
gcc -std=c99 -O1 -g -fno-omit-frame-pointer -ffp-contract=off -fsanitize=address,undefined \
    -fno-sanitize-recover=undefined -shared -fPIC -I"$include" -o "$so" \
    kernel/module.c kernel/frame_kernel.c kernel/gradient_solve.c kernel/vibration.c kernel/vibration_type.c \
    kernel/motion.c kernel/motion_type.c -lm
cat > "$work/optitac_asan/sitecustomize.py" <<EOF
"""Load the sanitized kernel as optitac_edge.core._frame_kernel before anything imports the installed one."""
import importlib.util
import sys

import optitac_edge.core

spec = importlib.util.spec_from_file_location("optitac_edge.core._frame_kernel", "$so")
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
sys.modules["optitac_edge.core._frame_kernel"] = module
optitac_edge.core._frame_kernel = module
EOF
export PYTHONPATH="$work/optitac_asan${PYTHONPATH:+:$PYTHONPATH}"
export LD_PRELOAD="$asan"
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:halt_on_error=1"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"
python3 -c 'import optitac_edge.core._frame_kernel as k, sys; assert "optitac_asan" in k.__file__, k.__file__'
# the aarch64 test builds its own harness; the allocation test counts Python's allocations (ASan's differ)
python3 -m pytest -q -p no:randomly -n 0 tests/test_kernel.py tests/test_motion.py tests/test_vibration.py \
    -k "not aarch64 and not allocates" "$@"
echo "kernel_asan: every kernel test passed under AddressSanitizer and UndefinedBehaviorSanitizer"
