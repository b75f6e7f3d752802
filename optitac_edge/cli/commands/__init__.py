"""One module per command, in the order ``optitac-edge --help`` lists them.

Each module has ``add_parser(sub)`` (its arguments), ``run(args) -> int`` (its
handler, the exit status) and, when an interrupted run leaves something behind,
``left(args) -> str`` (what, for the one line it ends with). A new command is a
module here and a line in :data:`COMMANDS`.
"""

from __future__ import annotations

from importlib import import_module
from types import ModuleType

#: Command name -> its module (``optitac_edge.cli.commands.<module>``), in ``--help`` order.
COMMANDS: dict[str, str] = {
    "sim": "sim", "calibrate": "calibrate", "evaluate": "evaluate", "export-onnx": "export_onnx",
    "report": "report", "replay": "replay", "run": "run", "record": "record", "soak": "soak", "bench": "bench",
    "orient": "orient", "collect": "collect", "monitor": "monitor", "view": "view", "snapshot": "snapshot",
    "layout": "layout", "export-lerobot": "export_lerobot",
}


def command(name: str) -> ModuleType:
    """The module of command ``name``."""
    return import_module(f"optitac_edge.cli.commands.{COMMANDS[name]}")


def left(name: str, args: object) -> str:
    """What an interrupted ``name`` left behind, for its one line."""
    module = command(name)
    return module.left(args) if hasattr(module, "left") else "nothing written"
