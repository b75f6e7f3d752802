"""Where board configs are: the packaged NAMEs, a path, and reading the TOML file."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from optitac_edge.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6 / Ubuntu 22.04)
    import tomli as tomllib


# --------------------------------------------------------------------------- loading


def packaged_config_dirs() -> list[Path]:
    """Directories searched for a board NAME, in order.

    The checkout's ``board_configs/`` (next to the package), then the installed
    copy (``<prefix>/share/optitac-edge/board_configs``, from the wheel's data files).
    """
    checkout = Path(__file__).resolve().parents[2]  # optitac_edge/config/files.py
    dirs = [checkout / "board_configs"]
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix, "/usr/local", "/usr")):
        dirs.append(Path(prefix) / "share" / "optitac-edge" / "board_configs")
    return dirs


def available_boards() -> list[str]:
    """Names of the packaged board configs."""
    names: set[str] = set()
    for d in packaged_config_dirs():
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.toml"))
    return sorted(names)


def resolve_board_config(name_or_path: str | os.PathLike[str]) -> Path:
    """The file a board NAME (``sim``) or a path (anything with a ``/`` or ``.toml``) stands for."""
    text = os.fspath(name_or_path)
    if not text:
        raise ConfigError("board config: empty name")
    if "/" in text or text.endswith(".toml") or os.sep in text:
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{text}: board config not found")
        return path
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", text):
        raise ConfigError(f"{text!r}: not a board name (known: {', '.join(available_boards())})")
    for d in packaged_config_dirs():
        candidate = d / f"{text}.toml"
        if candidate.is_file():
            return candidate
    raise ConfigError(f"{text}: no such board (known: {', '.join(available_boards()) or 'none'})")


def working_dir() -> Path | None:
    """The working directory, or None when it was removed under the running process."""
    try:
        return Path.cwd()
    except OSError:
        return None


def _display(path: Path) -> str:
    """``path`` relative to the working directory when it is below it (and that is not ``/``); as it is
    when there is no working directory any more (removed under the running process)."""
    here = working_dir()
    if here is None:
        return str(path)
    cwd = here.resolve()
    try:
        rel = path.resolve().relative_to(cwd)
    except ValueError:
        return str(path)
    return str(path) if cwd == Path(cwd.anchor) else str(rel)


def _read_toml(path: Path) -> dict[str, Any]:
    shown = _display(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except RecursionError:
        raise ConfigError(f"{shown}: not a board config (arrays or tables nested too deeply)") from None
    except FileNotFoundError:
        raise ConfigError(f"{shown}: board config not found") from None
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot read board config ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{shown}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{shown}: not valid TOML ({str(exc).splitlines()[0]})") from None
