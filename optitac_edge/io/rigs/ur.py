"""A Universal Robots arm as the rig, through ``ur_rtde`` (``pip install 'optitac-edge[ur]'``).

The indenter is the tool (set its TCP on the teach pendant). Rig coordinates
are the base frame in mm; the tool keeps the orientation it had at start.
Moves are ``moveL`` with ``asynchronous=True``; the position is
``getActualTCPPose``; a protective or emergency stop is reported as an alarm.
"""

from __future__ import annotations

from typing import Any

from optitac_edge.errors import RigError
from optitac_edge.io.rigs.base import Rig, RigConfig, RigLimits, RigStatus, url_rest

#: Linear acceleration of every move, m/s^2.
ACCELERATION = 0.5


class UrRig(Rig):
    """A UR arm over RTDE.

    Parameters
    ----------
    host : str
        The robot's address.
    limits : RigLimits
    control, receive : optional
        Open ``RTDEControlInterface`` / ``RTDEReceiveInterface`` objects (tests).
    """

    @classmethod
    def from_url(cls, url: str, config: RigConfig) -> UrRig:
        """``ur://HOST``, with the ``[rig]`` limits."""
        return cls(url_rest(url, "ur").strip("/"), config.limits())

    def __init__(self, host: str, limits: RigLimits, control: Any = None, receive: Any = None) -> None:
        super().__init__(limits)
        self.host = host
        if control is None or receive is None:
            import rtde_control
            import rtde_receive

            try:
                receive = rtde_receive.RTDEReceiveInterface(host)
                control = rtde_control.RTDEControlInterface(host)
            except RuntimeError as exc:
                raise RigError(f"ur rig {host}: cannot connect ({exc})") from None
        self._control, self._receive = control, receive
        pose = self._pose()
        self._orientation = pose[3:]
        self._target: list[float] | None = None

    def _pose(self) -> list[float]:
        try:
            pose = list(self._receive.getActualTCPPose())
        except RuntimeError as exc:
            raise RigError(f"ur rig {self.host}: connection lost ({exc})") from None
        if len(pose) != 6:
            raise RigError(f"ur rig {self.host}: no TCP pose (is the robot connected?)")
        return pose

    def _move(self, xyz: tuple[float, float, float], feed_mm_s: float) -> None:
        target = [xyz[0] / 1000.0, xyz[1] / 1000.0, xyz[2] / 1000.0, *self._orientation]
        try:
            ok = self._control.moveL(target, feed_mm_s / 1000.0, ACCELERATION, True)
        except RuntimeError as exc:
            raise RigError(f"ur rig {self.host}: move refused ({exc})") from None
        if ok is False:
            raise RigError(f"ur rig {self.host}: move to {xyz} refused by the controller")
        self._target = target

    def _status(self) -> RigStatus:
        pose = self._pose()
        xyz = (pose[0] * 1000.0, pose[1] * 1000.0, pose[2] * 1000.0)
        if self._receive.isProtectiveStopped() or self._receive.isEmergencyStopped():
            return RigStatus("alarm", xyz, "protective or emergency stop")
        moving = self._control.getAsyncOperationProgress() >= 0
        return RigStatus("moving" if moving else "idle", xyz)

    def _stop(self) -> None:
        try:
            self._control.stopL(2.0)
        except RuntimeError as exc:
            raise RigError(f"ur rig {self.host}: stop failed ({exc})") from None

    def _close_internal(self) -> None:
        for closer in (getattr(self._control, "stopScript", None), getattr(self._control, "disconnect", None),
                       getattr(self._receive, "disconnect", None)):
            if closer is not None:
                try:
                    closer()
                except RuntimeError:
                    pass
