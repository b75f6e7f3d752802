"""A virtual indentation rig pressing the simulated skin (``sim://``), on a shared clock.

The rig moves its tip in straight lines at its feed rate; the simulated
camera renders each frame with the indenter where the rig's tip is at that
frame's time. With a :class:`~optitac_edge.io.clock.VirtualClock` a whole
collection runs as fast as the machine computes and gives the same frames
on every machine. The rig's mounting over the sensor (origin, rotation,
mirror, surface height) is the simulator's truth; ``collect`` must find it
from presses, as on a real rig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, urlsplit

from optitac_edge.errors import RigError
from optitac_edge.io.clock import Clock, VirtualClock
from optitac_edge.io.rigs.base import Rig, RigConfig, RigLimits, RigStatus
from optitac_edge.sim.physics import PHYSICS_NAMES
from optitac_edge.sim.skin import Indenter

if TYPE_CHECKING:
    from optitac_edge.io.cameras.section import CameraConfig
    from optitac_edge.sim.camera import SimCamera


@dataclass(frozen=True)
class SimMount:
    """Where the sensor sits in the rig's coordinates (the simulator's truth).

    Attributes
    ----------
    origin_xy_mm : (float, float)
        The sensor's origin (the array's centre) in rig coordinates.
    rotation_deg : float
        The sensor's +x, counter-clockwise from the rig's +X.
    mirror : bool
        The sensor's x is negated (a rig whose axes are left-handed over the skin).
    surface_z_mm : float
        Rig z of the skin's surface.
    physics : str
        The simulated skin's physics (:data:`~optitac_edge.sim.physics.PHYSICS`).
    day : int
        The session's drift (:meth:`~optitac_edge.sim.drift.SessionDrift.for_day`; 0: none).
    """

    origin_xy_mm: tuple[float, float] = (100.0, 80.0)
    rotation_deg: float = 7.0
    mirror: bool = False
    surface_z_mm: float = 2.0
    physics: str = "default"
    day: int = 0

    def to_sensor(self, x: float, y: float) -> tuple[float, float]:
        dx, dy = x - self.origin_xy_mm[0], y - self.origin_xy_mm[1]
        t = math.radians(-self.rotation_deg)
        sx, sy = math.cos(t) * dx - math.sin(t) * dy, math.sin(t) * dx + math.cos(t) * dy
        return (-sx if self.mirror else sx), sy


class SimRig(Rig):
    """The virtual rig. ``change_indenter`` mounts any indenter at once (labels ``shape:size[@angle]``).

    Parameters
    ----------
    limits : RigLimits
    clock : Clock
        Shared with the simulated camera.
    mount : SimMount
    start_xyz_mm : (float, float, float), optional
        Where the tip starts (default: 3 mm above the sensor's origin, as an operator jogs it).
    """

    changes_indenters = True
    shakes = True

    #: Where the tip may go when the board sets no ``[rig]`` limits (its sensor sits at 100, 80; surface z 2).
    default_limits = RigLimits(x_mm=(40.0, 160.0), y_mm=(20.0, 140.0), z_mm=(-6.0, 20.0), feed_mm_s=20.0,
                               safe_z_mm=12.0)

    @classmethod
    def from_url(cls, url: str, config: RigConfig) -> SimRig:
        """``sim://?...`` (:func:`parse_sim_url`) on a virtual clock of its own."""
        return cls(config.limits(cls.default_limits), VirtualClock(), parse_sim_url(url))

    def own_camera(self, section: CameraConfig) -> SimCamera:
        """The simulated camera that sees this rig's presses on the rig's clock, as the board's camera
        ``section`` says (its fps, size, pixel format and ``options.layout``)."""
        from optitac_edge.sim.camera import SimCamera

        mount = self.mount
        return SimCamera(fps=section.fps, width=section.width, height=section.height,
                         rgb=section.pixel_format == "rgb", realtime=False, clock=self.clock, program=self,
                         physics=mount.physics, day=mount.day, layout=str(section.options.get("layout", "")))

    def __init__(self, limits: RigLimits, clock: Clock, mount: SimMount = SimMount(),
                 start_xyz_mm: tuple[float, float, float] | None = None) -> None:
        super().__init__(limits, sleep=clock.sleep, clock_ns=clock.monotonic_ns)
        self.clock = clock
        self.mount = mount
        start = start_xyz_mm or (mount.origin_xy_mm[0] + 0.6, mount.origin_xy_mm[1] - 0.4, mount.surface_z_mm + 3.0)
        self._from = self._to = start
        self._t0 = self._t1 = clock.monotonic_ns()
        self.indenter = ("circle", 5.0, 0.0)
        self.moves = 0
        self.alarm = ""
        #: A shake: (axis index, amplitude mm, Hz, start ns, end ns), or None.
        self._shake: tuple[int, float, float, int, int] | None = None

    def pose_at(self, t_ns: int) -> tuple[float, float, float]:
        """The tip's position at ``t_ns`` (rig coordinates, mm), a shake included."""
        if t_ns >= self._t1 or self._t1 == self._t0:
            pose = self._to
        else:
            f = max(0.0, (t_ns - self._t0) / (self._t1 - self._t0))
            a, b = self._from, self._to
            pose = (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]))
        if self._shake is not None and self._shake[3] <= t_ns < self._shake[4]:
            axis, amplitude, hz, t0, _ = self._shake
            d = amplitude * math.sin(2 * math.pi * hz * (t_ns - t0) * 1e-9)
            pose = tuple(v + d if k == axis else v for k, v in enumerate(pose))  # type: ignore[assignment]
        return pose

    def shake(self, axis: str, amplitude_mm: float, hz: float, duration_s: float) -> None:
        if axis not in ("x", "y", "z") or not (0 < amplitude_mm <= 1.0 and 0 < hz <= 1000 and duration_s > 0):
            raise RigError(f"sim rig: a shake along x, y or z by up to 1 mm, got {axis!r} {amplitude_mm} mm {hz} Hz")
        now = self.clock.monotonic_ns()
        self._shake = ("xyz".index(axis), amplitude_mm, hz, now, now + round(duration_s * 1e9))

    def indenter_at(self, t_ns: int) -> Indenter | None:
        """What the tip presses into the skin at ``t_ns`` (sensor frame), or None above it."""
        x, y, z = self.pose_at(t_ns)
        depth = self.mount.surface_z_mm - z
        if depth <= 0.0:
            return None
        sx, sy = self.mount.to_sensor(x, y)
        shape, size, angle = self.indenter
        sensor_angle = (-1.0 if self.mount.mirror else 1.0) * (angle - self.mount.rotation_deg)
        return Indenter(shape=shape, x_mm=sx, y_mm=sy, angle_deg=sensor_angle, size_mm=size, depth_mm=depth)

    def _move(self, xyz: tuple[float, float, float], feed_mm_s: float) -> None:
        if self.alarm:
            raise RigError(f"sim rig: alarm ({self.alarm})")
        now = self.clock.monotonic_ns()
        self._from = self.pose_at(now)
        self._to = xyz
        dist = math.dist(self._from, self._to)
        self._t0, self._t1 = now, now + round(dist / feed_mm_s * 1e9)
        self.moves += 1

    def _status(self) -> RigStatus:
        now = self.clock.monotonic_ns()
        if self.alarm:
            return RigStatus("alarm", self.pose_at(now), self.alarm)
        return RigStatus("moving" if now < self._t1 else "idle", self.pose_at(now))

    def _stop(self) -> None:
        now = self.clock.monotonic_ns()
        self._from = self._to = self.pose_at(now)
        self._t0 = self._t1 = now
        self.alarm = ""

    def change_indenter(self, label: str) -> bool:
        shape, _, rest = label.partition(":")
        size, _, angle = rest.partition("@")
        self.indenter = (shape, float(size), float(angle or 0.0))
        return True

    def at(self, frame: int) -> Indenter | None:  # the camera's PressSource: frames render at the clock's now
        return self.indenter_at(self.clock.monotonic_ns())


def parse_sim_url(url: str) -> SimMount:
    """``sim://?rotation=7&mirror=0&origin=100,80&surface=2&physics=default&day=0``: the virtual rig's mounting,
    the skin's physics and the session's drift (all optional).

    Raises
    ------
    RigError
        On an unknown key or a value that is not a number.
    """
    parts = urlsplit(url)
    if parts.scheme != "sim" or parts.path not in ("", "/") or parts.netloc:
        raise RigError(f"sim rig URL must be sim://?key=value&..., got {url!r}")
    query = parse_qs(parts.query, keep_blank_values=True)
    known = {"rotation", "mirror", "origin", "surface", "physics", "day"}
    unknown = sorted(set(query) - known)
    if unknown:
        raise RigError(f"sim rig URL {url!r}: unknown key {unknown[0]!r} (known: {', '.join(sorted(known))})")
    values = {k: v[-1] for k, v in query.items()}
    name = values.get("physics", "default")
    if name not in PHYSICS_NAMES:
        raise RigError(f"sim rig URL {url!r}: unknown physics {name!r} (known: {', '.join(PHYSICS_NAMES)})")
    day = values.get("day", "0")
    if not (day.isascii() and day.isdigit() and int(day) <= 10_000):
        raise RigError(f"sim rig URL {url!r}: day must be a whole number 0-10000, got {day!r}")
    try:
        origin = tuple(float(v) for v in values.get("origin", "100,80").split(","))
        mount = SimMount(origin_xy_mm=(origin[0], origin[1]), rotation_deg=float(values.get("rotation", 7.0)),
                         mirror=values.get("mirror", "0") in ("1", "true", "yes"),
                         surface_z_mm=float(values.get("surface", 2.0)), physics=name, day=int(day))
        if len(origin) != 2 or not all(math.isfinite(v) for v in (*origin, mount.rotation_deg, mount.surface_z_mm)):
            raise ValueError
    except (ValueError, IndexError):
        raise RigError(f"sim rig URL {url!r}: values must be finite numbers (origin=X,Y)") from None
    return mount
