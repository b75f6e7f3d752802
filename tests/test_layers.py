"""The package's layers (docs/architecture.md): imports only downward, and a lean runtime."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Never imported by ``optitac-edge run`` with an existing bundle and a real camera or a recording.
OFFLINE = ("scipy", "sklearn", "matplotlib", "onnx", "onnxruntime", "tqdm", "optitac_edge.sim",
           "optitac_edge.calibration", "optitac_edge.devtools")


def test_the_layer_contract_holds() -> None:
    """cli > devtools > service | sim > calibration > io > core > errors (pyproject.toml)."""
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    assert exe, "import-linter is a test dependency"
    out = subprocess.run([exe, "--config", str(ROOT / "pyproject.toml"), "--no-cache"], cwd=ROOT,
                         capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "1 kept, 0 broken" in out.stdout.replace("Contracts: ", "")


PROBE = """
import json, sys
from optitac_edge.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "modules": sorted(sys.modules)}))
"""


@pytest.mark.parametrize("backend", ["recording", "v4l2"])
def test_run_with_an_existing_bundle_imports_no_simulator_and_no_offline_library(
        tmp_path, unseen_rec, bundle_path, backend) -> None:
    """A board's start-up pays for numpy, OpenCV and its devices only: no scipy, scikit-learn,
    matplotlib, no simulator, no calibration code."""
    if backend == "recording":
        camera = f'backend = "recording"\nrecording = "{unseen_rec}"\n'
        args = ["--frames", "20"]
    else:  # a real camera backend: the device is absent here, so the run ends with a camera error
        camera = f'backend = "v4l2"\ndevice = "{tmp_path / "video-absent"}"\n'
        args = []
    board = tmp_path / "board.toml"
    board.write_text(f"[camera]\n{camera}[calibration]\nbundle = \"{bundle_path}\"\n")
    out = subprocess.run([sys.executable, "-c", PROBE, "run", "--board", str(board), *args],
                         capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
    last = out.stdout.strip().splitlines()[-1]
    result = json.loads(last)
    if backend == "recording":
        assert result["code"] == 0, out.stdout + out.stderr
        assert "processed 20 frames" in out.stdout
    else:
        assert result["code"] == 2 and "video-absent" in out.stderr, out.stderr
    if backend == "recording":  # the loop ran
        assert "optitac_edge.service.loop" in result["modules"]
    heavy = [m for m in result["modules"] if m.split(".")[0] in OFFLINE or m.startswith(OFFLINE)]
    assert heavy == []


#: Optional packages (the ``board`` and ``onnx`` extras): ``pip install .`` has none of them.
EXTRAS = ("cobs", "serial", "can", "cantools", "smbus2", "onnxruntime", "picamera2", "zenoh", "xxhash", "rosbags",
          "mcap", "mcap_ros2")


def test_the_default_run_needs_no_optional_package(tmp_path) -> None:
    """README's first command: `pip install .` (no extras) then `optitac-edge run` on the simulated
    sensor, no link: nothing of the board extras may be imported."""
    out = subprocess.run([sys.executable, "-c", PROBE, "run", "--frames", "30"], capture_output=True, text=True,
                         timeout=120, check=False, cwd=tmp_path)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["code"] == 0, out.stderr
    assert [m for m in result["modules"] if m.split(".")[0] in EXTRAS] == []


def test_the_board_config_loader_needs_only_the_standard_library(tmp_path: Path) -> None:
    """tools/install.sh checks a board config with the system Python before it installs anything: every
    packaged board, and one with every publisher's section (each declared beside its publisher, whose
    optional library is imported only when it opens)."""
    board = tmp_path / "all.toml"
    board.write_text("[publish.zenoh]\nmode = 'client'\n[publish.foxglove]\n[publish.mcap]\npath = 'r.mcap'\n"
                     "[publish.virtual]\n[led]\nenabled = true\n[link]\ntransport = 'can'\n")
    code = ("import sys; from optitac_edge.config import available_boards, describe_schema, load_board_config\n"
            "[load_board_config(n, env={}) for n in available_boards()]\n"
            f"assert len(load_board_config({str(board)!r}, env={{}}).publish) == 4\n"
            "describe_schema()\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'cv2', 'scipy', 'serial', 'cobs', "
            "'zenoh', 'foxglove', 'mcap', 'can', 'smbus2'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"


def test_the_simulator_registers_its_own_camera_and_io_names_no_layer_above():
    """io's camera table holds io's cameras only; the simulator's comes through the package's entry point."""
    from optitac_edge.io import cameras

    source = Path(cameras.__file__).read_text()
    assert "optitac_edge.sim" not in source
    assert cameras.CAMERAS["sim"].target == "optitac_edge.sim.camera:SimCamera"


def test_the_board_config_accepts_the_transport_registrys_names_only():
    from optitac_edge.config import load_board_config
    from optitac_edge.errors import ConfigError
    from optitac_edge.io.transports import TRANSPORTS

    for name in TRANSPORTS:
        urls = {"link.serial_url": "loop://", "link.can_channel": "vcan0"}
        assert load_board_config("sim", env={}, overrides={"link.transport": name, **urls}).link.transport == name
    with pytest.raises(ConfigError, match="link.transport: must be one of 'serial', 'can', 'none', got 'null'"):
        load_board_config("sim", env={}, overrides={"link.transport": "null"})


def _imports(path: Path, package: str) -> set[str]:
    """The package's modules ``path`` imports, type-only imports included (``from a import b``: ``a.b`` when
    that is a module, else ``a``)."""
    import ast

    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
               for p in (ROOT / package).rglob("*.py")}
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                name = f"{node.module}.{a.name}"
                if name in modules:
                    out.add(name)
                elif node.module in modules:
                    out.add(node.module)
    return out


def test_no_module_imports_itself_back_not_even_for_types() -> None:
    """docs/architecture.md: the import graph has no cycle, type-only (``if TYPE_CHECKING``) imports included,
    package ``__init__`` re-exports left out (the public API's lazy names)."""
    import graphlib

    graph: dict[str, set[str]] = {}
    for path in (ROOT / "optitac_edge").rglob("*.py"):
        if path.name == "__init__.py":
            continue
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        graph[name] = {m for m in _imports(path, "optitac_edge") if not (ROOT / Path(*m.split("."))).is_dir()}
    try:
        order = list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        raise AssertionError(f"an import cycle: {' -> '.join(exc.args[1])}") from None
    assert "optitac_edge.core.pipeline" in order and "optitac_edge.core.compiled" in order


#: The frame loop's modules: they read the time through the clock they are given (docs/architecture.md).
CLOCKED = ("optitac_edge/service/loop.py", "optitac_edge/service/channel.py", "optitac_edge/service/camera_keeper.py",
           "optitac_edge/service/status.py", "optitac_edge/service/commands.py", "optitac_edge/service/stats.py",
           "optitac_edge/service/pool.py", "optitac_edge/service/session.py")


def test_the_loop_and_the_core_read_no_time_but_their_clocks() -> None:
    """docs/architecture.md, "Time": no module of the frame loop, nor any of ``core/``, calls the ``time``
    module (a virtual clock runs the service as fast as it computes, the same on every machine)."""
    import ast

    paths = [ROOT / p for p in CLOCKED] + sorted((ROOT / "optitac_edge" / "core").rglob("*.py"))
    offenders = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import) and any(a.name == "time" for a in node.names):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} import time")
            elif isinstance(node, ast.ImportFrom) and node.module == "time":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} from time import ...")
    assert offenders == []


def test_every_registry_entry_is_a_device_of_its_kind() -> None:
    """docs/architecture.md, "Adding a device": each kind's registry maps a name to a "module:Class" of the
    kind's base class (imported here: the optional packages are test dependencies)."""
    from optitac_edge.errors import OptiTacError
    from optitac_edge.io.cameras import CAMERAS
    from optitac_edge.io.cameras.base import Camera
    from optitac_edge.io.led import LEDS, LedRing
    from optitac_edge.io.publishers import PUBLISHERS
    from optitac_edge.io.publishers.base import Publisher
    from optitac_edge.io.rigs import RIGS, Rig
    from optitac_edge.io.transports import TRANSPORTS
    from optitac_edge.io.transports.base import Transport

    kinds = ((CAMERAS, Camera), (TRANSPORTS, Transport), (PUBLISHERS, Publisher), (LEDS, LedRing), (RIGS, Rig))
    for registry, base in kinds:
        for name in registry:
            try:
                cls = registry.load(name)
            except OptiTacError as exc:  # an optional package not installed here: the message names the extra
                assert "pip install" in str(exc), (name, exc)
                continue
            assert isinstance(cls, type) and issubclass(cls, base), (name, cls)
