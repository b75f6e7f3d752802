"""The indentation rig interface every backend implements (cf. python-can's ``BusABC``).

Coordinates are the rig's own, mm, with +z away from the skin (up). Every
target is checked against :class:`RigLimits` before anything moves.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

from optitac_edge.errors import RigError
from optitac_edge.io.device import Device

#: Rig states reported by :meth:`Rig.status`.
STATES = ("idle", "moving", "hold", "alarm", "homing", "offline")


@dataclass(frozen=True)
class RigLimits:
    """Where the indenter tip may go, rig coordinates (mm), and how fast.

    Attributes
    ----------
    x_mm, y_mm, z_mm : (float, float)
        Travel limits (low, high) of the tip.
    feed_mm_s : float
        Speed of every move, mm/s.
    safe_z_mm : float
        Height every retract goes to (inside ``z_mm``).
    """

    x_mm: tuple[float, float] = (-1e9, 1e9)
    y_mm: tuple[float, float] = (-1e9, 1e9)
    z_mm: tuple[float, float] = (-1e9, 1e9)
    feed_mm_s: float = 5.0
    safe_z_mm: float = 10.0

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "z_mm"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"rig limit {name} must be two finite numbers, low < high")
        if not (math.isfinite(self.feed_mm_s) and 0 < self.feed_mm_s <= 500):
            raise ValueError("rig feed_mm_s must be in (0, 500]")
        if not self.z_mm[0] <= self.safe_z_mm <= self.z_mm[1]:
            raise ValueError("rig safe_z_mm must lie inside z_mm")

    def check(self, xyz: tuple[float, float, float]) -> None:
        """Raise :class:`RigError` naming the axis if ``xyz`` is outside the limits (before any move)."""
        for axis, value, (lo, hi) in zip("xyz", xyz, (self.x_mm, self.y_mm, self.z_mm)):
            if not (math.isfinite(value) and lo <= value <= hi):
                raise RigError(f"rig target {axis} = {value:.3f} mm is outside the limits {lo:g}..{hi:g} mm; "
                               "nothing moved")


@dataclass(frozen=True)
class RigStatus:
    """What a rig reports: its state and the tip's position (rig coordinates, mm)."""

    state: str
    xyz_mm: tuple[float, float, float]
    alarm: str = ""


class Rig(Device, ABC):
    """An indentation rig. Subclasses implement ``_move``, ``_status``, ``_stop`` and ``_close_internal``.

    Moves are one segment at a time: :meth:`move_to` starts it (after checking
    the limits) and returns; :meth:`status` tells when it is done. Use as a
    context manager; :meth:`close` is idempotent.
    """

    #: True when the rig can swap indenters itself (the simulator); else the operator is asked.
    changes_indenters: bool = False

    def __init__(self, limits: RigLimits) -> None:
        Device.__init__(self)
        self.limits = limits

    @abstractmethod
    def _move(self, xyz: tuple[float, float, float], feed_mm_s: float) -> None:
        """Start a straight move of the tip to ``xyz``."""

    @abstractmethod
    def _status(self) -> RigStatus:
        """Poll the rig."""

    @abstractmethod
    def _stop(self) -> None:
        """Stop any motion now, keeping the position known."""

    def move_to(self, xyz: tuple[float, float, float], feed_mm_s: float | None = None) -> None:
        """Start moving the tip to ``xyz`` (mm); the target is checked against the limits first.

        Raises
        ------
        RigError
            Outside the limits (nothing moves), or the rig refused the move.
        """
        if self._closed:
            raise RigError("rig is closed")
        self.limits.check(xyz)
        self._move(xyz, self.limits.feed_mm_s if feed_mm_s is None else min(feed_mm_s, self.limits.feed_mm_s))

    def status(self) -> RigStatus:
        """The rig's state and position.

        Raises
        ------
        RigError
            If the rig is in alarm or stopped answering.
        """
        if self._closed:
            raise RigError("rig is closed")
        st = self._status()
        if st.state == "alarm":
            raise RigError(f"rig alarm{': ' + st.alarm if st.alarm else ''}")
        return st

    def retract(self, sleep: Callable[[float], None] = time.sleep) -> None:
        """Stop, then lift the tip straight up to ``limits.safe_z_mm`` and wait until it is there.

        Raises
        ------
        RigError
            If the rig cannot stop or lift, or is not up within the move's time plus 5 s.
        """
        self._stop()
        x, y, z = self._status().xyz_mm
        if z >= self.limits.safe_z_mm:
            return
        self._move((x, y, self.limits.safe_z_mm), self.limits.feed_mm_s)
        deadline = time.monotonic() + (self.limits.safe_z_mm - z) / self.limits.feed_mm_s + 5.0
        while time.monotonic() < deadline:
            st = self._status()
            if st.state == "idle" and abs(st.xyz_mm[2] - self.limits.safe_z_mm) < 0.01:
                return
            if st.state == "alarm":
                raise RigError(f"rig alarm while retracting ({st.alarm})")
            sleep(0.01)
        raise RigError(f"the tip did not reach the safe height z = {self.limits.safe_z_mm:g} mm")

    def change_indenter(self, label: str) -> bool:
        """Mount the indenter ``label`` (True), or False when the operator must do it."""
        return False
