"""The systemd unit, its drop-in and the udev rule: required directives, and systemd-analyze's score."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "optitac-edge.service"
TEMPLATE = REPO / "systemd" / "optitac-edge@.service"
MAX_EXPOSURE = 2.5


def parse_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """{section: {key: [values in order]}} of a systemd unit file (comments, blanks skipped)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, {})
            continue
        assert section is not None, f"{path}: directive outside a section: {line}"
        key, sep, value = line.partition("=")
        assert sep, f"{path}: not key=value: {line}"
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


@pytest.fixture(scope="module")
def unit():
    return parse_unit(UNIT)


def one(unit, key, section="Service"):
    values = unit[section][key]
    assert len(values) == 1, f"{key} given {len(values)} times"
    return values[0]


def test_service_type_watchdog_restart(unit):
    assert one(unit, "Type") == "notify"
    assert one(unit, "NotifyAccess") == "main"
    assert re.fullmatch(r"\d+s?", one(unit, "WatchdogSec"))
    assert one(unit, "Restart") == "on-failure"
    assert one(unit, "RestartSec")
    exec_start = one(unit, "ExecStart").split()
    assert exec_start[:4] == ["/opt/optitac-edge/venv/bin/optitac-edge", "run", "--board",
                              "/etc/optitac-edge/board.toml"]
    assert one(unit, "WantedBy", "Install") == "multi-user.target"


def test_unprivileged_user_and_state_directory(unit):
    assert one(unit, "User") == "optitac" and one(unit, "Group") == "optitac"
    assert set(one(unit, "SupplementaryGroups").split()) == {"video", "dialout", "i2c"}
    assert one(unit, "StateDirectory") == "optitac-edge"
    assert one(unit, "StateDirectoryMode") == "0750"
    assert one(unit, "CapabilityBoundingSet") == ""
    assert one(unit, "NoNewPrivileges") == "yes"


def test_sandbox(unit):
    svc = unit["Service"]
    for key, value in {"ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
                       "DevicePolicy": "closed", "IPAddressDeny": "any", "RestrictNamespaces": "yes",
                       "ProtectKernelTunables": "yes", "ProtectKernelModules": "yes",
                       "ProtectControlGroups": "yes", "LockPersonality": "yes",
                       "SystemCallArchitectures": "native"}.items():
        assert svc[key] == [value], key
    assert one(unit, "RestrictAddressFamilies").split() == ["AF_UNIX", "AF_CAN", "AF_NETLINK"]
    assert "@system-service" in svc["SystemCallFilter"]
    assert "PrivateNetwork" not in svc  # SocketCAN interfaces are in the host's namespace
    assert "PrivateDevices" not in svc  # the camera, serial port and I2C are devices


def test_device_allow_covers_camera_serial_i2c(unit):
    allowed = {v.split()[0] for v in unit["Service"]["DeviceAllow"]}
    for needed in ("char-video4linux", "char-media", "char-dma_heap", "char-ttyACM", "char-ttyUSB",
                   "char-ttyAMA", "char-i2c"):
        assert needed in allowed


def test_jetson_drop_in_only_relaxes_what_argus_needs():
    drop_in = parse_unit(REPO / "systemd" / "jetson-csi.conf")
    assert set(drop_in) == {"Service"}
    assert set(drop_in["Service"]) == {"PrivateTmp", "DevicePolicy", "MemoryDenyWriteExecute"}


def test_udev_rule_names_the_mcu_port():
    rules = [line for line in (REPO / "systemd" / "99-optitac-edge.rules").read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    mcu = [r for r in rules if 'SYMLINK+="optitac-mcu"' in r]
    assert len(mcu) == 1
    assert 'SUBSYSTEM=="tty"' in mcu[0] and 'ATTRS{idVendor}==' in mcu[0] and 'GROUP="dialout"' in mcu[0]
    for rule in rules:
        for part in rule.split(", "):
            assert re.fullmatch(r'[A-Z_]+(\{[A-Za-z_]+\})?(==|\+=|=|!=)"[^"]*"', part.strip()), part


def analyze_exposure(unit_path: Path) -> float:
    tool = shutil.which("systemd-analyze")
    assert tool
    proc = subprocess.run(check=False, args=[tool, "security", "--offline=yes", "--no-pager", unit_path.name],
                          cwd=unit_path.parent, capture_output=True, text=True, timeout=120)
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", proc.stdout + proc.stderr)
    assert match, f"unexpected output (rc {proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return float(match.group(1))


def test_the_template_unit_is_the_unit_but_for_its_instance_lines():
    """optitac-edge@ID.service runs one sensor (``--sensor %i``) with the same sandbox as the whole board's."""
    lines = TEMPLATE.read_text().splitlines()
    instance = {i + 1 for i, line in enumerate(lines) if line.startswith("# instance")}
    kept = [line for i, line in enumerate(lines) if i not in instance and not line.startswith("# instance")
            and not (line.startswith("#") and i < 6)]
    replaced = ("Description=", "ExecStart=")  # the instance's own versions of these
    unit_lines = [line for i, line in enumerate(UNIT.read_text().splitlines())
                  if not (line.startswith("#") and i < 3) and not line.startswith(replaced)]
    assert kept == unit_lines
    template = parse_unit(TEMPLATE)
    assert one(template, "ExecStart").endswith("run --board /etc/optitac-edge/board.toml --sensor %i")
    assert template["Service"]["EnvironmentFile"] == ["-/etc/optitac-edge/environment", "-/etc/optitac-edge/%i.env"]
    assert one(template, "Conflicts", "Unit") == "optitac-edge.service"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize(("source", "name"), [(UNIT, UNIT.name), (TEMPLATE, "optitac-edge@1.service")])
def test_systemd_analyze_security_exposure(tmp_path, source, name):
    copy = tmp_path / name
    copy.write_text(source.read_text())
    exposure = analyze_exposure(copy)
    assert exposure <= MAX_EXPOSURE, f"exposure {exposure} > {MAX_EXPOSURE}"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize(("source", "name"), [(UNIT, UNIT.name), (TEMPLATE, "optitac-edge@1.service")])
def test_systemd_analyze_verify_has_no_syntax_errors(tmp_path, source, name):
    copy = tmp_path / name
    copy.write_text(source.read_text())
    proc = subprocess.run(check=False, args=["systemd-analyze", "verify", "--man=no", str(copy)], capture_output=True,
                          text=True, timeout=120)
    # The only acceptable complaint off a board: the venv's executable does not exist here.
    problems = [line for line in (proc.stdout + proc.stderr).splitlines()
                if line.strip() and "is not executable" not in line and "No such file" not in line]
    assert not problems, "\n".join(problems)


# ---------------------------------------------------------------- tools/install.sh

INSTALL = REPO / "tools" / "install.sh"


def test_install_script_is_strict_and_executable():
    text = INSTALL.read_text()
    assert text.startswith("#!/usr/bin/env bash\n") and "set -euo pipefail" in text
    assert INSTALL.stat().st_mode & 0o111


@pytest.mark.parametrize("board", ["rpi5-gs", "jetson-csi", "sim"])
def test_install_dry_run(board):
    """The dry run checks the board config with the interpreter that has the package (not whichever
    python3 is first on PATH): the Jetson CSI board's GStreamer pipeline gets its drop-in."""
    proc = subprocess.run(check=False, args=["bash", str(INSTALL), "--dry-run", board], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "OPTITAC_PYTHON": sys.executable,
                                            "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert f"install -m 0644 {REPO}/board_configs/{board}.toml /etc/optitac-edge/board.toml" in out
    assert "/etc/systemd/system/optitac-edge.service" in out and "/etc/systemd/system/optitac-edge@.service" in out
    assert "/etc/udev/rules.d/99-optitac-edge.rules" in out
    assert "systemctl enable optitac-edge.service" in out
    assert ("jetson-csi.conf" in out) == (board == "jetson-csi")
    assert "zenoh.conf" not in out and ".whl[board]" in out  # no board here publishes: no IP
    assert "could not check the config" not in out


@pytest.mark.parametrize(("publish", "extras"), [
    ('[publish.zenoh]\nconnect = ["tcp/192.168.1.10:7447"]\n', "board,zenoh,mcap"),
    ('[publish.foxglove]\nbind = "0.0.0.0:8765"\n', "board,mcap,foxglove"),
])
def test_install_a_publishing_board_gets_the_zenoh_drop_in_and_extras(tmp_path, publish, extras):
    board = tmp_path / "robot.toml"
    board.write_text(f'{publish}[publish.mcap]\npath = "/var/lib/x.mcap"\n')
    proc = subprocess.run(check=False, args=["bash", str(INSTALL), "--dry-run", str(board)], capture_output=True,
                          text=True, timeout=120, env={**os.environ, "OPTITAC_PYTHON": sys.executable,
                                                       "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert f".whl[{extras}]" in out
    for unit in ("optitac-edge.service", "optitac-edge@.service"):
        assert f"install -m 0644 {REPO}/systemd/zenoh.conf /etc/systemd/system/{unit}.d/zenoh.conf" in out


DROP_IN = REPO / "systemd" / "zenoh.conf"


def _with_drop_in(tmp_path: Path) -> Path:
    """The unit as systemd reads it with the Zenoh drop-in: the drop-in's lines added to [Service]."""
    body = DROP_IN.read_text().replace("[Service]\n", "")
    merged = tmp_path / UNIT.name
    merged.write_text(UNIT.read_text().replace("\n[Install]", "\n" + body + "\n[Install]"))
    return merged


def test_the_zenoh_drop_in_opens_ip_and_nothing_else():
    drop_in = parse_unit(DROP_IN)
    assert set(drop_in) == {"Service"}
    assert set(drop_in["Service"]) == {"RestrictAddressFamilies", "IPAddressAllow"}
    assert drop_in["Service"]["RestrictAddressFamilies"] == ["AF_INET AF_INET6"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_with_the_zenoh_drop_in_only_the_network_items_change(tmp_path):
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / UNIT.name).write_text(UNIT.read_text())

    def items(path: Path) -> set[str]:
        proc = subprocess.run(check=False, args=["systemd-analyze", "security", "--offline=yes", "--no-pager",
                                                 path.name], cwd=path.parent, capture_output=True, text=True,
                              timeout=120)
        return {" ".join(line.split()[:2]) for line in proc.stdout.splitlines() if line[:1] in "✓✗"}

    before, after = items(plain / UNIT.name), items(_with_drop_in(tmp_path))
    changed = {i.split()[1].split("=")[0] for i in before ^ after}
    assert changed == {"RestrictAddressFamilies", "IPAddressDeny"}, before ^ after
    assert analyze_exposure(plain / UNIT.name) < analyze_exposure(_with_drop_in(tmp_path)) <= MAX_EXPOSURE


def _dry_run(env: dict[str, str]) -> str:
    proc = subprocess.run(["bash", str(INSTALL), "--dry-run", "sim"], capture_output=True, text=True, timeout=120,
                          check=False, env={**os.environ, "OPTITAC_PYTHON": sys.executable, "PATH": "/usr/bin:/bin",
                                            **env})
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_install_builds_the_wheel_once_per_source_and_reuses_it(tmp_path):
    """Issue 28.6: the kernel compiles for a minute on a Pi; the second install of the same source takes the
    cached wheel. The cache key changes with any source file (here: the wheel directory must not be reused
    for another tree, so a fake wheel under another key is not taken)."""
    cache = tmp_path / "wheels"
    first = _dry_run({"OPTITAC_WHEEL_CACHE": str(cache)})
    built = re.search(rf"pip wheel --no-deps --disable-pip-version-check --wheel-dir ({re.escape(str(cache))}/\w+) "
                      rf"{re.escape(str(REPO))}$", first, re.MULTILINE)
    assert built, first
    (cache / "0123456789abcdef").mkdir(parents=True)
    (cache / "0123456789abcdef" / "optitac_edge-0.1.0-cp311-cp311-linux_x86_64.whl").write_bytes(b"")
    assert "pip wheel" in _dry_run({"OPTITAC_WHEEL_CACHE": str(cache)})  # another source's wheel: built again
    key = Path(built.group(1))
    key.mkdir(parents=True)
    wheel = key / "optitac_edge-0.1.0-cp311-cp311-linux_x86_64.whl"
    wheel.write_bytes(b"")
    second = _dry_run({"OPTITAC_WHEEL_CACHE": str(cache)})
    assert "pip wheel" not in second and f"installing {wheel} (built from this source before: no rebuild)" in second
    assert f"pip install --force-reinstall --no-deps --disable-pip-version-check {wheel}" in second
    assert f"{wheel}[board]" in second


def test_install_unknown_board_fails_in_one_line():
    proc = subprocess.run(check=False, args=["bash", str(INSTALL), "--dry-run", "nope"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "no board config" in proc.stderr and "rpi5-gs" in proc.stderr


@pytest.mark.skipif(shutil.which("shellcheck") is None, reason="shellcheck not installed")
def test_install_script_is_shellcheck_clean():
    proc = subprocess.run(check=False, args=["shellcheck", str(INSTALL)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout


def test_modemmanager_leaves_the_mcu_port_alone():
    """Issue 13.16: ModemManager (JetPack) probes new serial ports with AT commands unless udev says not to."""
    rules = (REPO / "systemd" / "99-optitac-edge.rules").read_text().splitlines()
    mcu = [r.lstrip("# ") for r in rules if "optitac-mcu" in r and "SUBSYSTEM" in r]
    uarts = [r for r in rules if "ttyTHS" in r and not r.startswith("#")]
    assert len(mcu) >= 4 and uarts
    assert all('ENV{ID_MM_DEVICE_IGNORE}="1"' in r for r in mcu + uarts)


def test_the_unit_allows_every_serial_device_a_packaged_board_can_name():
    """/dev/serial0 is ttyAMA0 or, on a Pi 4 with Bluetooth on, ttyS0 (major 4, 'ttyS')."""
    unit = (REPO / "systemd" / "optitac-edge.service").read_text()
    allowed = set(re.findall(r"^DeviceAllow=char-(\S+) rw$", unit, re.MULTILINE))
    assert {"ttyS", "ttyAMA", "ttyACM", "ttyUSB", "ttyTHS"} <= allowed


def test_install_checks_a_relative_board_path_before_changing_anything(tmp_path):
    """Issue 13.15: `install.sh ./my-board.toml` ran apt, useradd, the venv and pip, then failed its
    config check after `cd /` with a traceback. The config is checked first, by its absolute path."""
    (tmp_path / "my-board.toml").write_text((REPO / "board_configs" / "rpi5-gs.toml").read_text())
    ok = subprocess.run(["bash", str(INSTALL), "--dry-run", "./my-board.toml"], capture_output=True, text=True,
                        timeout=120, check=False, cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr
    assert f"install -m 0644 {tmp_path}/my-board.toml /etc/optitac-edge/board.toml" in ok.stdout
    (tmp_path / "bad.toml").write_text("[camera]\nfps = 0\n")
    bad = subprocess.run(["bash", str(INSTALL), "--dry-run", "./bad.toml"], capture_output=True, text=True,
                         timeout=120, check=False, cwd=tmp_path)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().startswith(f"install.sh: {tmp_path}/bad.toml: camera.fps: must be a number in 1..1000")
    assert "+ " not in bad.stdout  # nothing was (or would have been) done
