#!/usr/bin/env bash
# Install optitac-edge as a systemd service on a Raspberry Pi (Raspberry Pi OS) or a Jetson (JetPack).
#
#   sudo tools/install.sh BOARD [--start] [--dry-run]
#
# BOARD is a packaged board name (see board_configs/: rpi5-gs, rpi4-cm3, jetson-orin-nano-usb,
# jetson-csi, sim) or the path of your own board TOML. Safe to run again (after a git pull, or to
# switch boards): every step checks before it changes anything. See docs/deploy.md.
#
#   --start     (re)start the service at the end (default: enable only)
#   --dry-run   print what would be done, change nothing (needs no root)
#
# The board config is checked first, before anything changes (with this checkout's package and
# $OPTITAC_PYTHON, default /usr/bin/python3).
#
# The package is built once per source into a wheel kept in $OPTITAC_WHEEL_CACHE (default
# /var/cache/optitac-edge/wheels): its compiled per-frame kernel needs gcc and python3-dev (installed
# here) and a minute on a Pi; running this again on the same source installs that wheel, no rebuild.
set -euo pipefail

PREFIX=/opt/optitac-edge
VENV="$PREFIX/venv"
ETC=/etc/optitac-edge
SERVICE=optitac-edge.service
TEMPLATE=optitac-edge@.service
UNIT_DIR=/etc/systemd/system
RULES_DIR=/etc/udev/rules.d
USER_NAME=optitac
SYS_PY=/usr/bin/python3
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

usage() {
    sed -n '2,14p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
    exit "${1:-2}"
}

BOARD=""
START=0
DRY_RUN=0
while [ $# -gt 0 ]; do
    case "$1" in
        --start) START=1 ;;
        --dry-run) DRY_RUN=1 ;;
        -h|--help) usage 0 ;;
        -*) echo "install.sh: unknown option $1" >&2; usage 2 ;;
        *)
            if [ -n "$BOARD" ]; then echo "install.sh: one BOARD only" >&2; usage 2; fi
            BOARD="$1" ;;
    esac
    shift
done
[ -n "$BOARD" ] || usage 2

log() { printf 'install.sh: %s\n' "$*"; }

# run CMD...: run it, or only print it with --dry-run.
run() {
    if [ "$DRY_RUN" -eq 1 ]; then
        printf '+ %s\n' "$*"
    else
        "$@"
    fi
}

if [ "$DRY_RUN" -eq 0 ] && [ "$(id -u)" -ne 0 ]; then
    echo "install.sh: run as root (sudo $0 $BOARD)" >&2
    exit 1
fi

# --- the board config file: checked before anything is changed ----------------------------------
case "$BOARD" in
    */*|*.toml) BOARD_FILE="$BOARD" ;;
    *) BOARD_FILE="$REPO/board_configs/$BOARD.toml" ;;
esac
if [ ! -f "$BOARD_FILE" ]; then
    known=""
    for f in "$REPO"/board_configs/*.toml; do known="$known $(basename "$f" .toml)"; done
    echo "install.sh: no board config $BOARD_FILE (packaged:$known)" >&2
    exit 2
fi
BOARD_FILE="$(cd "$(dirname "$BOARD_FILE")" && pwd)/$(basename "$BOARD_FILE")"  # absolute: later steps cd
# The config loader needs the standard library only (and tomli on Python 3.10): check with the
# checkout's package now, before apt, the user, the venv or pip touch anything.
CHECK_PY="${OPTITAC_PYTHON:-$SYS_PY}"
if ! "$CHECK_PY" -c 'import sys; sys.version_info >= (3, 11) or __import__("tomli")' 2> /dev/null; then
    echo "install.sh: $CHECK_PY needs Python >= 3.11 or the tomli package to check the board config" \
         "(sudo apt install python3-tomli)" >&2
    exit 2
fi
CHECK='import sys
from optitac_edge.errors import OptiTacError
from optitac_edge.config import load_board_config
try:
    c = load_board_config(sys.argv[1], env={})
except OptiTacError as exc:
    sys.exit(f"install.sh: {exc}")
extras = ["board"] + [name for name in ("zenoh", "mcap", "foxglove") if name in c.publish]
net = "zenoh" in c.publish or "foxglove" in c.publish
print("pipeline" if c.camera.pipeline else "device", "zenoh" if net else "none", ",".join(extras))'
checked="$(cd / && PYTHONPATH="$REPO" "$CHECK_PY" -c "$CHECK" "$BOARD_FILE")" || exit 2
read -r camera_kind publish_kind extras <<< "$checked"

# --- platform ---------------------------------------------------------------------------------
PLATFORM=generic
if [ -r /proc/device-tree/model ] && tr -d '\0' < /proc/device-tree/model | grep -q "Raspberry Pi"; then
    PLATFORM=raspberrypi
elif [ -e /etc/nv_tegra_release ]; then
    PLATFORM=jetson
fi
log "board $BOARD_FILE on a $PLATFORM system"

# --- system packages --------------------------------------------------------------------------
# gcc and python3-dev: pip builds the compiled per-frame kernel (without them it runs the numpy pipeline)
PACKAGES=(python3 python3-venv python3-pip python3-numpy python3-dev gcc i2c-tools can-utils)
case "$PLATFORM" in
    raspberrypi) PACKAGES+=(python3-picamera2 python3-libcamera) ;;
    jetson) PACKAGES+=(python3-opencv python3-tomli) ;;  # JetPack's OpenCV has GStreamer; Python 3.10
esac
missing=()
for pkg in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
    log "installing ${missing[*]}"
    run apt-get update
    run env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "${missing[@]}"
fi

# --- user and groups --------------------------------------------------------------------------
for group in video dialout i2c "$USER_NAME"; do
    getent group "$group" > /dev/null || run groupadd --system "$group"
done
if ! getent passwd "$USER_NAME" > /dev/null; then
    run useradd --system --gid "$USER_NAME" --groups video,dialout,i2c --home-dir /var/lib/optitac-edge \
        --no-create-home --shell /usr/sbin/nologin --comment "optitac-edge service" "$USER_NAME"
else
    run usermod --append --groups video,dialout,i2c "$USER_NAME"
fi

# --- virtual environment and the package ------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
    run install -d -m 0755 "$PREFIX"
    # System site packages: picamera2/libcamera (Pi) and GStreamer-enabled OpenCV (Jetson) come from apt.
    run "$SYS_PY" -m venv --system-site-packages "$VENV"
fi
# Keep the system's numpy: apt's picamera2/simplejpeg are built against it, and a newer numpy in
# the venv would shadow it and break them.
CONSTRAINTS="$PREFIX/constraints.txt"
if sys_numpy="$("$SYS_PY" -c 'import numpy; print(numpy.__version__)' 2> /dev/null)"; then
    if [ "$DRY_RUN" -eq 1 ]; then
        printf '+ echo numpy==%s > %s\n' "$sys_numpy" "$CONSTRAINTS"
    else
        printf 'numpy==%s\n' "$sys_numpy" > "$CONSTRAINTS"
    fi
else
    run rm -f "$CONSTRAINTS"
    CONSTRAINTS=""
fi
# The package as a wheel built once per source (the kernel compiles for a minute on a Pi): the key is a hash
# of every file the build reads; the three most recent sources' wheels are kept.
WHEEL_CACHE="${OPTITAC_WHEEL_CACHE:-/var/cache/optitac-edge/wheels}"
source_key="$(cd "$REPO" && find optitac_edge kernel setup.py pyproject.toml MANIFEST.in README.md -type f \
    ! -name '*.so' ! -name '*.pyc' ! -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum \
    | sha256sum | cut -c1-16)"
WHEEL_DIR="$WHEEL_CACHE/$source_key"
shopt -s nullglob
built=("$WHEEL_DIR"/optitac_edge-*.whl)
shopt -u nullglob
if [ "${#built[@]}" -gt 0 ]; then
    wheel="${built[0]}"
    log "installing $wheel (built from this source before: no rebuild)"
else
    log "building the package from $REPO (the compiled kernel: about a minute on a Pi 4)"
    run install -d -m 0755 "$WHEEL_DIR"
    run "$VENV/bin/python" -m pip wheel --no-deps --disable-pip-version-check --wheel-dir "$WHEEL_DIR" "$REPO"
    wheel="$WHEEL_DIR/optitac_edge.whl"
    if [ "$DRY_RUN" -eq 0 ]; then
        shopt -s nullglob
        built=("$WHEEL_DIR"/optitac_edge-*.whl)
        shopt -u nullglob
        [ "${#built[@]}" -gt 0 ] || { echo "install.sh: pip built no wheel in $WHEEL_DIR" >&2; exit 1; }
        wheel="${built[0]}"
    fi
    # keep the three most recent sources' wheels
    if [ -d "$WHEEL_CACHE" ]; then
        find "$WHEEL_CACHE" -mindepth 1 -maxdepth 1 -type d -printf '%T@ %p\n' | sort -rn | tail -n +4 \
            | cut -d' ' -f2- | while read -r old; do run rm -rf "$old"; done
    fi
fi
# its dependencies (pip caches the wheels it builds for them itself), then the package itself again: the
# same version number from another source would count as installed
run "$VENV/bin/python" -m pip install --upgrade --disable-pip-version-check ${CONSTRAINTS:+--constraint "$CONSTRAINTS"} \
    "${wheel}[${extras}]"
run "$VENV/bin/python" -m pip install --force-reinstall --no-deps --disable-pip-version-check "$wheel"

PY="$VENV/bin/python"
[ -x "$PY" ] || PY="$CHECK_PY"  # dry run before the venv exists

if [ "$camera_kind" = pipeline ] && [ "$PLATFORM" = jetson ]; then
    # pip's opencv-python-headless has no GStreamer: let JetPack's cv2 (system site packages) through.
    if "$PY" -m pip show opencv-python-headless > /dev/null 2>&1; then
        run "$VENV/bin/python" -m pip uninstall -y opencv-python-headless
    fi
fi

if [ "$DRY_RUN" -eq 0 ]; then  # one line: what will run the frames
    log "$("$VENV/bin/python" -c 'from optitac_edge.core.compiled import kernel_status; print(kernel_status()[1])')"
fi

# --- configuration ----------------------------------------------------------------------------
run install -d -m 0755 "$ETC"
if [ -f "$ETC/board.toml" ] && ! cmp -s "$BOARD_FILE" "$ETC/board.toml"; then
    backup="$ETC/board.toml.$(date +%Y%m%d-%H%M%S).bak"
    log "keeping the previous $ETC/board.toml as $backup"
    run cp -p "$ETC/board.toml" "$backup"
fi
cmp -s "$BOARD_FILE" "$ETC/board.toml" 2> /dev/null || run install -m 0644 "$BOARD_FILE" "$ETC/board.toml"
if [ ! -f "$ETC/environment" ]; then
    if [ "$DRY_RUN" -eq 1 ]; then
        printf '+ write %s\n' "$ETC/environment"
    else
        printf '%s\n' "# OPTITAC_<SECTION>_<KEY>=value overrides $ETC/board.toml, e.g." \
            "# OPTITAC_LINK_SERIAL_URL=/dev/ttyACM1" > "$ETC/environment"
        chmod 0644 "$ETC/environment"
    fi
fi

# --- systemd unit, drop-in, udev rule ---------------------------------------------------------
# optitac-edge.service runs the whole board; optitac-edge@ID.service one sensor of it (docs/deploy.md)
for unit in "$SERVICE" "$TEMPLATE"; do
    run install -m 0644 "$REPO/systemd/$unit" "$UNIT_DIR/$unit"
    DROP_IN_DIR="$UNIT_DIR/$unit.d"
    if [ "$camera_kind" = pipeline ] && [ "$PLATFORM" != raspberrypi ]; then
        run install -d -m 0755 "$DROP_IN_DIR"
        run install -m 0644 "$REPO/systemd/jetson-csi.conf" "$DROP_IN_DIR/jetson-csi.conf"
    elif [ -f "$DROP_IN_DIR/jetson-csi.conf" ]; then
        run rm -f "$DROP_IN_DIR/jetson-csi.conf"
    fi
    # IP networking only for a board that publishes on Zenoh or serves Foxglove (docs/network.md)
    if [ "$publish_kind" = zenoh ]; then
        run install -d -m 0755 "$DROP_IN_DIR"
        run install -m 0644 "$REPO/systemd/zenoh.conf" "$DROP_IN_DIR/zenoh.conf"
    elif [ -f "$DROP_IN_DIR/zenoh.conf" ]; then
        run rm -f "$DROP_IN_DIR/zenoh.conf"
    fi
done
run install -m 0644 "$REPO/systemd/99-optitac-edge.rules" "$RULES_DIR/99-optitac-edge.rules"
if command -v udevadm > /dev/null; then
    run udevadm control --reload-rules
    run udevadm trigger --subsystem-match=tty --subsystem-match=i2c-dev
fi

if [ "$PLATFORM" = raspberrypi ] && command -v raspi-config > /dev/null; then
    run raspi-config nonint do_i2c 0  # enable I2C for the LED driver (idempotent)
fi

run systemctl daemon-reload
run systemctl enable "$SERVICE"
if [ "$START" -eq 1 ]; then
    run systemctl restart "$SERVICE"
    log "started; follow it with: journalctl -fu $SERVICE"
else
    log "enabled; start it with: systemctl start $SERVICE (then: journalctl -fu $SERVICE)"
fi
