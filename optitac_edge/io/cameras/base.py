"""The camera interface every backend implements (cf. python-can's ``BusABC``)."""

from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from dataclasses import fields
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from optitac_edge.errors import CameraError, ConfigError
from optitac_edge.io.device import BoardView, Device

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.io.cameras.section import CameraConfig


class CapturedFrame(NamedTuple):
    """One frame as delivered by a camera.

    Attributes
    ----------
    frame : ndarray, uint8
        In the camera's ``pixel_format`` (see :mod:`optitac_edge.core.frames`),
        C-contiguous, shape ``Camera.frame_shape``. Valid until the next
        :meth:`Camera.read` or :meth:`Camera.close`: hardware backends reuse
        one preallocated buffer (``Camera.reuses_buffer``) and deliver it
        read-only. Callers that keep a frame copy it.
    t_ns : int
        Frame timestamp, CLOCK_MONOTONIC nanoseconds (which instant of the
        exposure depends on the backend; see docs/cameras.md). Strictly
        increasing.
    seq : int
        Frame sequence number from the source, strictly increasing; gaps mean
        dropped frames (counted in ``Camera.frames_dropped``).
    """

    frame: np.ndarray
    t_ns: int
    seq: int


class Camera(Device, ABC):
    """A frame source. Subclasses implement :meth:`_read_internal` and :meth:`_close_internal`.

    Use as a context manager; :meth:`close` is idempotent and thread-safe.
    """

    pixel_format: str
    height: int
    width: int
    fps: float
    #: True when every frame is written into the same buffer, so a frame is
    #: only valid until the next read (the hardware backends).
    reuses_buffer: bool = False

    @classmethod
    def from_config(cls, section: CameraConfig, board: BoardView) -> Self:
        """The camera a board's ``[camera]`` (or ``[cameras.NAME]``) describes: the constructor's arguments
        from the section's typed keys (:meth:`section_kwargs`), then its ``options`` for what the backend
        takes beyond them.

        Raises
        ------
        ConfigError
            If an option sets what a typed key sets (``camera.options.fps``: use ``camera.fps``, which is
            validated), or names no parameter of the backend.
        """
        typed = cls.section_kwargs(section, board)
        cls._check_options(section, board, typed)
        return cls(**typed, **dict(section.options))

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """Constructor arguments from the section's typed keys (and the regions and rest frames of the
        ``board``). The default takes none."""
        return {}

    @classmethod
    def _check_options(cls, section: CameraConfig, board: BoardView, typed: dict[str, Any]) -> None:
        if not section.options:
            return
        shadowed = {f.name for f in fields(section)} | set(typed)
        params = inspect.signature(cls).parameters
        takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
        key = board.key or "camera"
        for option in section.options:
            where = board.where(f"options.{option}")
            if option in shadowed:
                raise ConfigError(f"{where}: {key}.options.{option}: set it with the camera key that does "
                                  f"({key}.{option if option in {f.name for f in fields(section)} else '...'}), "
                                  "which is checked")
            if not takes_any and (option not in params or option in ("clock", "regions")):
                known = sorted(set(params) - shadowed - {"self", "clock", "regions"})
                raise ConfigError(f"{where}: {key}.options.{option}: not an option of the {section.backend} "
                                  f"camera (its options: {', '.join(known) or 'none'})")

    def __init__(self) -> None:
        Device.__init__(self)
        self.frames_read = 0
        #: Frames the source lost, from gaps in ``seq``.
        self.frames_dropped = 0
        self._last_seq: int | None = None

    @abstractmethod
    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        """Return the next frame, ``None`` at the end of a finite source."""

    def read(self, timeout_s: float = 1.0) -> CapturedFrame | None:
        """Next frame, or ``None`` when a finite source (a recording) is exhausted.

        Raises
        ------
        CameraError
            If the camera is closed or fails to deliver within ``timeout_s``.
        """
        if self._closed:
            raise CameraError("camera is closed")
        captured = self._read_internal(timeout_s)
        if captured is not None:
            self.frames_read += 1
            if self._last_seq is not None and captured.seq > self._last_seq + 1:
                self.frames_dropped += captured.seq - self._last_seq - 1
            self._last_seq = captured.seq
        return captured

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Array shape of the frames this camera delivers."""
        if self.pixel_format == "rgb":
            return (self.height, self.width, 3)
        if self.pixel_format == "yuv420":
            return (self.height * 3 // 2, self.width)
        return (self.height, self.width)
