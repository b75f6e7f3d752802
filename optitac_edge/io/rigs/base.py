"""The indentation rig interface every backend implements (cf. python-can's ``BusABC``).

Coordinates are the rig's own, mm, with +z away from the skin (up). Every
target is checked against :class:`RigLimits` before anything moves.

No single status report is trusted (a serial line picks up electrical noise):
a report that cannot be parsed, or holds a position that is not finite or
absurdly far away, is counted and polled again (:data:`GARBLED_TRIES` in a
row before it is an error); a retract lifts the tip straight up without a
reported x or y in its command, and is done only when two reports in a row
agree that the tip is idle at the safe height.
"""

from __future__ import annotations

import dataclasses
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from optitac_edge.errors import RigError
from optitac_edge.fields import boolean, integer, number, setting, string
from optitac_edge.io.device import Device

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.io.cameras.base import Camera
    from optitac_edge.io.cameras.section import CameraConfig

#: Rig states reported by :meth:`Rig.status`: ``hold`` (a feed hold, stopping or stopped), ``door`` (a safety
#: door open), ``sleep``, ``tool`` (a tool change waits), ``check`` (G-code check mode: nothing moves) and
#: ``unknown`` (a state this backend does not know) all mean the rig will not go on by itself.
STATES = ("idle", "moving", "hold", "alarm", "homing", "offline", "door", "sleep", "tool", "check", "unknown")
#: Why each state that stops a collection does, and what the operator does about it.
STOPPED_STATES = {
    "hold": "in a feed hold (its hold button, or '!')",
    "door": "stopped by its safety door: close it",
    "sleep": "asleep: reset it",
    "tool": "waiting for a tool change: finish it on the machine",
    "check": "in G-code check mode, where nothing moves: turn it off ($C)",
    "unknown": "in a state this program does not know",
}
#: Garbled or implausible status reports in a row before the rig is taken as lost.
GARBLED_TRIES = 5
#: The wait before polling again after a garbled report (s), doubled each time: the 5 reports span 0.3 s, so
#: a burst of noise on the line (milliseconds) is outlasted (polled back to back, 2 ms of noise stopped a run).
GARBLED_SPACING_S = 0.02
#: A reported coordinate farther than this from the origin (mm) is a garbled report, not a position.
ABSURD_MM = 100_000.0


class GarbledReport(RigError):
    """One status report could not be read (noise on the line): poll again."""


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
        for axis, value in zip("xyz", xyz):
            self.check_axis(axis, value)

    def check_axis(self, axis: str, value: float) -> None:
        """Raise :class:`RigError` if ``value`` is outside the limits of ``axis`` (``x``, ``y`` or ``z``)."""
        lo, hi = getattr(self, f"{axis}_mm")
        if not (math.isfinite(value) and lo <= value <= hi):
            raise RigError(f"rig target {axis} = {value:.3f} mm is outside the limits {lo:g}..{hi:g} mm; "
                           "nothing moved")


@dataclass(frozen=True)
class RigStatus:
    """What a rig reports: its state and the tip's position (rig coordinates, mm)."""

    state: str
    xyz_mm: tuple[float, float, float]
    alarm: str = ""
    #: The backend's own name of the state (e.g. GRBL's ``Door:1``), for messages.
    raw_state: str = ""
    #: When the report was read, ns of the rig's clock (:attr:`Rig.clock_ns`; None: not stamped): a pose's
    #: time, not the camera frame's it is recorded with (a loop that falls behind reads old frames).
    t_ns: int | None = None

    @property
    def plausible(self) -> bool:
        """The position is finite and not absurdly far (an alarm may carry no position)."""
        return self.state == "alarm" or all(math.isfinite(v) and abs(v) < ABSURD_MM for v in self.xyz_mm)


@dataclass(frozen=True)
class RigConfig:
    """The indentation rig of ``optitac-edge collect`` (bench use only; the service never moves it)."""

    url: str = setting(string(256), "", "the rig: gcode://PORT (GRBL), ur://HOST (Universal Robots), sim:// (simulator) "
                          "or another registered scheme")
    baudrate: int = setting(integer(1200, 4_000_000), 115200, "gcode: serial baud rate")
    home: bool = setting(boolean, False, "gcode: home ($H) at start when the machine is locked")
    x_min: float = setting(number(-1e5, 1e5), 0.0, "lowest x the tip may go to, mm (rig coordinates)")
    x_max: float = setting(number(-1e5, 1e5), 0.0, "highest x, mm")
    y_min: float = setting(number(-1e5, 1e5), 0.0, "lowest y, mm")
    y_max: float = setting(number(-1e5, 1e5), 0.0, "highest y, mm")
    z_min: float = setting(number(-1e5, 1e5), 0.0, "lowest z (deepest), mm: keep it above what the skin can take")
    z_max: float = setting(number(-1e5, 1e5), 0.0, "highest z, mm")
    safe_z: float = setting(number(-1e5, 1e5), 0.0, "z of every retract, mm (0: z_max)")
    feed_mm_s: float = setting(number(0.1, 500), 10.0, "speed of every move, mm/s")

    @property
    def limits_set(self) -> bool:
        return self.x_min < self.x_max and self.y_min < self.y_max and self.z_min < self.z_max

    def limits(self, default: RigLimits | None = None) -> RigLimits:
        """The travel limits the keys set, ``default`` when they set none (the simulator's).

        Raises
        ------
        RigError
            When none are set and there is no ``default``, or they are inconsistent.
        """
        if not self.limits_set:
            if default is not None:
                return default
            raise RigError("set the rig's travel limits (rig.x_min, x_max, y_min, y_max, z_min, z_max) before "
                           "moving a real rig")
        try:
            return RigLimits(x_mm=(self.x_min, self.x_max), y_mm=(self.y_min, self.y_max),
                             z_mm=(self.z_min, self.z_max), feed_mm_s=self.feed_mm_s,
                             safe_z_mm=self.safe_z or self.z_max)
        except ValueError as exc:
            raise RigError(str(exc)) from None


def url_rest(url: str, scheme: str) -> str:
    """What follows ``SCHEME://`` in a rig URL.

    Raises
    ------
    RigError
        When ``url`` is not written ``SCHEME://...``.
    """
    prefix = f"{scheme}://"
    if not url.startswith(prefix):
        raise RigError(f"unknown rig URL {url!r} (a {scheme} rig is {prefix}...)")
    return url[len(prefix):]


class Rig(Device, ABC):
    """An indentation rig. Subclasses implement ``_move``, ``_status``, ``_stop`` and ``_close_internal``.

    Moves are one segment at a time: :meth:`move_to` starts it (after checking
    the limits) and returns; :meth:`status` tells when it is done. Use as a
    context manager; :meth:`close` is idempotent.
    """

    #: True when the rig can swap indenters itself (the simulator); else the operator is asked.
    changes_indenters: bool = False
    #: True when the rig can shake the tip at 30-100 Hz by a fraction of a millimetre (:meth:`shake`: the
    #: simulator; a GRBL machine or an arm cannot: reversing 0.05 mm at 30 Hz takes 1.8 m/s² per cycle).
    shakes: bool = False

    #: Where the tip may go when the board sets no ``[rig]`` limits (None: a real rig, which needs them).
    default_limits: ClassVar[RigLimits | None] = None

    @classmethod
    def from_url(cls, url: str, config: RigConfig) -> Self:
        """The rig ``url`` names (its scheme chose this class), with the board's ``[rig]`` section ``config``.

        Raises
        ------
        RigError
            A URL this rig does not take, limits missing, or a rig that cannot be reached.
        """
        raise NotImplementedError(f"{cls.__name__} is not opened from a URL")

    def own_camera(self, section: CameraConfig) -> Camera | None:
        """The camera that sees the skin this rig presses when the rig brings its own (the simulator's, made
        as the board's camera ``section`` says); None: the board's camera."""
        return None

    def __init__(self, limits: RigLimits, sleep: Callable[[float], None] = time.sleep,
                 clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        Device.__init__(self)
        self.limits = limits
        #: How waits on the rig pass time (the simulator's rig: its virtual clock).
        self.sleep = sleep
        #: The clock status reports are stamped with (ns; the simulator's rig: its virtual clock).
        self.clock_ns = clock_ns
        #: Status reports refused as garbled or implausible so far.
        self.garbled_reports = 0

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

    def shake(self, axis: str, amplitude_mm: float, hz: float, duration_s: float) -> None:
        """Shake the tip where it is along ``axis`` (``x``, ``y`` or ``z`` of the rig) by ``amplitude_mm`` at
        ``hz`` for ``duration_s`` (only when :attr:`shakes`).

        Raises
        ------
        RigError
            The rig cannot shake.
        """
        raise RigError(f"{type(self).__name__} cannot shake the tip (vibrate needs sim:// or a shaker)")

    def status(self) -> RigStatus:
        """The rig's state and position (a garbled report is polled again, see :meth:`poll`).

        Raises
        ------
        RigError
            If the rig is in alarm or stopped answering.
        """
        if self._closed:
            raise RigError("rig is closed")
        st = self.poll()
        if st.state == "alarm":
            raise _alarm_error(st)
        return st

    def poll(self) -> RigStatus:
        """One status report that can be read and holds a plausible position, alarms included.

        Raises
        ------
        RigError
            After :data:`GARBLED_TRIES` garbled or implausible reports in a row, or when the rig does not answer.
        """
        last = ""
        for k in range(GARBLED_TRIES):
            if k:
                self.sleep(GARBLED_SPACING_S * 2 ** (k - 1))
            asked = self.clock_ns()
            try:
                st = self._status()
            except GarbledReport as exc:
                last = str(exc)
            else:
                if st.plausible:
                    return dataclasses.replace(st, t_ns=(asked + self.clock_ns()) // 2)
                last = f"implausible position {st.xyz_mm}"
            self.garbled_reports += 1
        raise RigError(f"{GARBLED_TRIES} garbled status reports in a row (the last: {last}); check the cable")

    def _lift(self, z_mm: float, feed_mm_s: float) -> None:
        """Start a move straight up (or down) to ``z_mm``, x and y unchanged.

        Backends whose controller can move one axis alone override this, so that no reported x
        or y goes into the command; this one moves to the reported x and y, checked against the
        limits like every target.
        """
        x, y, _ = self.poll().xyz_mm
        self.limits.check((x, y, z_mm))
        self._move((x, y, z_mm), feed_mm_s)

    def wait_until_at(self, xyz: tuple[float | None, float | None, float], timeout_s: float) -> None:
        """Wait until two status reports in a row say the rig is idle at ``xyz`` (None: any x or y).

        Raises
        ------
        RigError
            On an alarm, a state that stops the rig, or not there within ``timeout_s`` (seconds of
            :attr:`sleep`).
        """
        agreed = 0
        waited = 0.0
        while waited <= timeout_s:
            st = self.poll()
            if st.state == "alarm":
                raise _alarm_error(st)
            if st.state in STOPPED_STATES and st.state != "hold":
                raise RigError(f"the rig is {STOPPED_STATES[st.state]} ({st.raw_state or st.state})")
            there = st.state == "idle" and all(want is None or abs(got - want) < 0.01
                                               for got, want in zip(st.xyz_mm, xyz))
            agreed = agreed + 1 if there else 0
            if agreed >= 2:
                return
            self.sleep(0.01)
            waited += 0.01
        where = ", ".join("any" if v is None else f"{v:g}" for v in xyz)
        raise RigError(f"the tip did not reach ({where}) mm within {timeout_s:.0f} s")

    def _travel_s(self) -> float:
        """The longest a move inside the limits may take, plus 5 s."""
        reach = max(hi - lo for lo, hi in (self.limits.x_mm, self.limits.y_mm, self.limits.z_mm))
        return min(reach, 1000.0) / self.limits.feed_mm_s + 5.0

    def lift(self, z_mm: float) -> None:
        """Move the tip straight to ``z_mm`` (x and y unchanged) and wait until two reports agree it is there."""
        if self._closed:
            raise RigError("rig is closed")
        self._lift(z_mm, self.limits.feed_mm_s)
        self.wait_until_at((None, None, z_mm), self._travel_s())

    def retract(self) -> None:
        """Stop, then move the tip straight to ``limits.safe_z_mm`` and wait until it is there.

        The lift is commanded whatever height the tip reports (a garbled report must not keep it in
        the skin; at or above the safe height the move is harmless), and is done when two reports in
        a row agree.

        Raises
        ------
        RigError
            If the rig cannot stop or lift (the message says what to do), or is not up in time.
        """
        self._stop()
        self.lift(self.limits.safe_z_mm)

    def move_and_wait(self, xyz: tuple[float, float, float]) -> None:
        """Move the tip to ``xyz`` (checked against the limits) and wait until it is idle there."""
        self.move_to(xyz)
        self.wait_until_at(xyz, self._travel_s())

    def change_indenter(self, label: str) -> bool:
        """Mount the indenter ``label`` (True), or False when the operator must do it."""
        return False


def _alarm_error(st: RigStatus) -> RigError:
    """The one line of a rig in alarm."""
    return RigError(f"rig alarm{': ' + st.alarm if st.alarm else ''}")
