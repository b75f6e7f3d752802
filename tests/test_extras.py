"""After `pip install .` (no extras): every feature missing its optional package says, in one line,
which extra installs it (issue 13.13). The packages are hidden from a subprocess by an import hook."""

from __future__ import annotations

import subprocess
import sys

import pytest

from optitac_edge.sim.scenarios import write_scenario

HIDE = """
import importlib.abc, sys
HIDDEN = set(sys.argv.pop(1).split(","))
class Hide(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in HIDDEN:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Hide())
from optitac_edge.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _without(hidden: str, *argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", HIDE, hidden, *argv], capture_output=True, text=True,
                          timeout=300, check=False)


def _one_line(proc: subprocess.CompletedProcess) -> str:
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    return err[-1]


def test_run_over_can_without_the_can_extra(tmp_path):
    line = _one_line(_without("can,cantools", "run", "--can", "vcan0", "--frames", "3"))
    assert line == ("optitac-edge: error: the can transport needs can, which is not installed: "
                    "pip install 'optitac-edge[can]'")


def test_an_led_ring_without_the_board_extra(tmp_path):
    board = tmp_path / "b.toml"
    board.write_text("[led]\nenabled = true\n")
    line = _one_line(_without("smbus2", "run", "--board", str(board), "--frames", "3"))
    assert line.endswith("the LED ring needs smbus2, which is not installed: pip install 'optitac-edge[board]'")


def test_calibrating_shapes_without_the_calibrate_extra(tmp_path, bundle_path):
    rec = write_scenario(tmp_path / "shapes", "shapes", seed=4, frames=150)
    cal = tmp_path / "cal.npz"
    cal.write_bytes(bundle_path.read_bytes())
    line = _one_line(_without("sklearn", "calibrate", "shapes", str(rec), "--cal", str(cal)))
    assert line == ("optitac-edge: error: optitac-edge calibrate needs sklearn, which is not installed: "
                    "pip install 'optitac-edge[calibrate]'")
    assert cal.read_bytes() == bundle_path.read_bytes()


def test_the_report_without_matplotlib(tmp_path, bundle_path):
    line = _one_line(_without("matplotlib", "report", str(bundle_path), "-o", str(tmp_path / "r")))
    assert line.endswith("the report needs matplotlib, which is not installed: pip install 'optitac-edge[calibrate]'")


@pytest.mark.parametrize("command", [["run", "--serial", "loop://", "--frames", "30"], ["run", "--frames", "30"]])
def test_the_serial_link_is_in_the_base_install(command):
    """pyserial and cobs are base dependencies: `run --serial` needs no extra (declared in pyproject)."""
    from pathlib import Path

    import tomllib

    deps = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.startswith("pyserial") for d in deps) and any(d.startswith("cobs") for d in deps)
    proc = _without("sklearn,matplotlib,onnx,onnxruntime,can,cantools,smbus2,threadpoolctl", *command)
    assert proc.returncode == 0, proc.stderr
    assert "processed 30 frames" in proc.stdout


@pytest.mark.parametrize(("hidden", "argv", "extra"), [
    ("zenoh", ["--publish", "zenoh"], "zenoh"),
    ("xxhash", ["--publish", "zenoh"], "zenoh"),
    ("mcap", ["--mcap", "run.mcap"], "mcap"),
    ("foxglove", ["--foxglove", "127.0.0.1:0"], "foxglove"),
])
def test_publishing_without_its_extra(tmp_path, hidden, argv, extra):
    proc = subprocess.run([sys.executable, "-c", HIDE, hidden, "run", *argv, "--frames", "3"], capture_output=True,
                          text=True, timeout=300, check=False, cwd=tmp_path)
    assert _one_line(proc).endswith(f"which is not installed: pip install 'optitac-edge[{extra}]'"), proc.stderr


def test_reading_an_mcap_recording_without_the_mcap_extra(tmp_path, bundle_path):
    rec = tmp_path / "r.mcap"
    rec.write_bytes(b"\x89MCAP0\r\n")
    line = _one_line(_without("mcap_ros2", "replay", str(rec), "--cal", str(bundle_path), "-o", str(tmp_path / "c")))
    assert line.endswith("needs mcap_ros2, which is not installed: pip install 'optitac-edge[mcap]'")
