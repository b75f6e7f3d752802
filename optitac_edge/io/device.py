"""What every device wrapper shares: an idempotent, thread-safe close and a lazy backend registry."""

from __future__ import annotations

import importlib
import threading
from typing import Any

from optitac_edge.errors import OptiTacError, missing_extra


class Device:
    """Mixin: ``close()`` runs :meth:`_close_internal` once; usable as a context manager."""

    def __init__(self) -> None:
        self._closed = False
        self._close_lock = threading.Lock()

    def _close_internal(self) -> None:
        """Release the device; called once."""

    def close(self) -> None:
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._close_internal()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def load_backend(registry: dict[str, str], name: str, kind: str, error: type[OptiTacError]) -> Any:
    """The class registered as ``"module:Class"`` under ``name``, imported on first use (python-can style)."""
    try:
        target = registry[name]
    except KeyError:
        raise error(f"unknown {kind} {name!r} (known: {', '.join(sorted(registry))})") from None
    module_name, class_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:  # the backend's optional library: say which extra installs it
        if exc.name is None or exc.name.split(".")[0] == "optitac_edge":
            raise
        raise missing_extra(exc.name, f"the {name} {kind}") from None
    return getattr(module, class_name)
