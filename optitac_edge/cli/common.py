"""What every command's parser shares: one-line usage errors, checked numbers, the board option."""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from optitac_edge.errors import OptiTacError
from optitac_edge.io.recording_paths import staging_path
from optitac_edge.text import parse_float, parse_int

if TYPE_CHECKING:
    from typing import TypeAlias

    from optitac_edge.config import BoardConfig

    #: The table of sub-commands each command module adds its parser to.
    Subcommands: TypeAlias = argparse._SubParsersAction[argparse.ArgumentParser]

EXIT_ERROR = 2
#: Exit status of work interrupted by Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130


class Parser(argparse.ArgumentParser):
    """Argument parser whose usage errors are one line."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see --help)\n")


def number(lo: float, hi: float, *, integer: bool = False, lo_open: bool = False) -> Callable[[str], Any]:
    """An argparse type: a finite number (an integer with ``integer``) in ``lo..hi``; one-line errors."""
    def parse(text: str) -> float | int:
        try:
            value: float | int = parse_int(text) if integer else parse_float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if integer else 'a number'}") from None
        low_ok = value > lo if lo_open else value >= lo
        if not (math.isfinite(value) and low_ok and value <= hi):
            raise argparse.ArgumentTypeError(
                f"{text} is outside {'(' if lo_open else ''}{lo:g}..{hi:g}{')' if lo_open else ''}")
        return value
    return parse


def frame_size(text: str) -> tuple[int, int]:
    """An argparse type: ``WxH``, a frame size of 64..8192 px a side; one-line errors."""
    parts = text.lower().split("x")
    try:
        width, height = (parse_int(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a frame size WxH (e.g. 1280x720)") from None
    if not (64 <= width <= 8192 and 64 <= height <= 8192):
        raise argparse.ArgumentTypeError(f"{text} is outside 64..8192 px a side")
    return width, height


COUNT = number(1, 10**9, integer=True)
SEED = number(0, 2**32 - 1, integer=True)
FPS = number(1, 1000)


SENSOR_ID = number(0, 255, integer=True)


def add_board(p: argparse.ArgumentParser, default: str | None = "sim") -> None:
    """``--board`` and ``--sensor`` (one sensor of a board with several)."""
    p.add_argument("--board", default=default, metavar="NAME|PATH",
                   help="board config: a name in board_configs/ or a TOML file"
                        + (f" (default: {default})" if default else ""))
    p.add_argument("--sensor", type=SENSOR_ID, default=None, metavar="ID",
                   help="the board's sensor with this id (a board with several sensors)")


def add_storage(p: argparse.ArgumentParser, default: str | None, text: str) -> None:
    """``--storage``: how a recording keeps its frames (:mod:`optitac_edge.io.frame_store`), ``text`` its help."""
    p.add_argument("--storage", choices=("fibers", "raw"), default=default, help=f"how the frames are kept: {text}")


def board_config(args: argparse.Namespace, **overrides: Any) -> BoardConfig:
    """The board config of ``--board`` (with ``overrides``), narrowed to ``--sensor`` when given."""
    from optitac_edge.config import load_board_config

    config = load_board_config(args.board, env=os.environ,
                               overrides={k: v for k, v in overrides.items() if v is not None})
    sensor = getattr(args, "sensor", None)
    return config if sensor is None else config.for_sensor(sensor)


def one_sensor_config(args: argparse.Namespace, **overrides: Any) -> BoardConfig:
    """:func:`board_config` of a command that serves one sensor: a board with several needs ``--sensor``."""
    return board_config(args, **overrides).for_sensor(getattr(args, "sensor", None))


def add_orientation(p: argparse.ArgumentParser, default: float | None = 0.0) -> None:
    """``--rotation-deg A`` and ``--mirror``: how the array appears in the image (``default``: None tells a
    hint given from none)."""
    p.add_argument("--rotation-deg", type=number(-360, 360), default=default, metavar="A",
                   help="the array appears rotated counter-clockwise by about A degrees in the image")
    p.add_argument("--mirror", action="store_true", help="the layout's x is negated before the rotation")


def add_fresh(p: argparse.ArgumentParser) -> None:
    """``--fresh``: replace a complete recording at the output, once the new one is complete."""
    p.add_argument("--fresh", action="store_true",
                   help="replace a complete recording at the output (it is kept until the new one is complete)")


def board_sensor(args: argparse.Namespace) -> BoardConfig | None:
    """The board config narrowed to ``--sensor`` for an offline command (None without ``--board``)."""
    if args.board is None:
        if args.sensor is not None:
            raise OptiTacError("--sensor needs --board (the board config that lists the sensor)")
        return None
    return one_sensor_config(args)


def recording_left(args: argparse.Namespace) -> str:
    """What an interrupted ``sim`` or ``record`` left behind: the recording it was writing, or the complete
    one it was replacing (unchanged)."""
    out = getattr(args, "out_dir", None) or args.output
    if getattr(args, "replacing", False):
        if not staging_path(Path(out)).exists():  # the signal came as the complete new one took its place
            return f"recording {out} replaced by the new one (complete)"
        return f"recording {out} unchanged (the new one was not complete)"
    return f"recording {out} is incomplete (not usable; record it again)"
