"""What every device shares: an idempotent, thread-safe close, and the board it is opened on."""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Self


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

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class BoardView:
    """What a device reads of its board beyond its own section (``from_config(section, board)``).

    The config layer makes one for each device it opens
    (:meth:`optitac_edge.config.BoardConfig.view`); a test makes its own.
    """

    #: Where the board came from (a file path, or ``(defaults)``): errors start with it.
    source: str = "(defaults)"
    #: Where the device's section is in the board: ``camera``, ``cameras.left``, ``link``, ``publish.mcap``.
    key: str = ""
    #: The ids of the sensors the board runs, in file order (the link carries each).
    sensor_ids: tuple[int, ...] = (0,)
    #: A camera's: the region (x, y, width, height) of each sensor of the board it reads (``()``: whole frame).
    regions: tuple[tuple[int, ...], ...] = ()
    #: Contact-free frames calibrated from at start (``[calibration] rest_frames``).
    rest_frames: int = 10
    #: The ROS 2 namespace of every topic (``[network] namespace``).
    namespace: str = ""
    #: "section.key" -> where its value came from (file, environment variable, command line).
    origins: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}), compare=False)

    def where(self, key: str) -> str:
        """Who set ``KEY`` of the device's section (the board's source when nobody did): an error's start."""
        return self.origins.get(f"{self.key}.{key}", self.source)
