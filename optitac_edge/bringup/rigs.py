"""Open the rig a board config (or ``--rig URL``) names, by URL scheme, importing only its backend.

``gcode://PORT``  a GRBL machine on a serial port or pyserial URL (:mod:`optitac_edge.io.rigs.gcode`).
``ur://HOST``     a Universal Robots arm through ``ur_rtde`` (extra ``[ur]``, :mod:`optitac_edge.io.rigs.ur`).
``sim://?...``    the simulator's virtual rig and its camera on a virtual clock (:mod:`optitac_edge.sim.rig`).
"""

from __future__ import annotations

from optitac_edge.config import BoardConfig
from optitac_edge.errors import RigError
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.rigs.base import Rig, RigLimits

#: Rig URL scheme -> the prefix a URL of it starts with (the simulator's takes ``sim:`` with or without ``//``).
RIG_SCHEMES = {"gcode": "gcode://", "ur": "ur://", "sim": "sim:"}
#: Limits of the simulated rig when the board config sets none (its sensor sits at 100, 80; surface z 2).
SIM_LIMITS = RigLimits(x_mm=(40.0, 160.0), y_mm=(20.0, 140.0), z_mm=(-6.0, 20.0), feed_mm_s=20.0, safe_z_mm=12.0)


def rig_scheme(url: str) -> str:
    """The scheme of a rig URL (a key of :data:`RIG_SCHEMES`).

    Raises
    ------
    RigError
        For any other URL, in one line naming the known forms.
    """
    for scheme, prefix in RIG_SCHEMES.items():
        if url.startswith(prefix):
            return scheme
    raise RigError(f"unknown rig URL {url!r} (gcode://PORT, ur://HOST or sim://)")


def rig_limits(config: BoardConfig, url: str) -> RigLimits:
    """The board's ``[rig]`` limits (the simulator's defaults for ``sim://``).

    Raises
    ------
    RigError
        When a real rig has no limits set, or they are inconsistent.
    """
    r = config.rig
    if not r.limits_set:
        if rig_scheme(url) == "sim":
            return SIM_LIMITS
        raise RigError(f"{config.source}: set the rig's travel limits (rig.x_min, x_max, y_min, y_max, z_min, "
                       "z_max) before moving a real rig")
    try:
        return RigLimits(x_mm=(r.x_min, r.x_max), y_mm=(r.y_min, r.y_max), z_mm=(r.z_min, r.z_max),
                         feed_mm_s=r.feed_mm_s, safe_z_mm=r.safe_z or r.z_max)
    except ValueError as exc:
        raise RigError(f"{config.source}: {exc}") from None


def open_rig(config: BoardConfig, url: str | None = None) -> tuple[Rig, Camera | None]:
    """The rig, and for ``sim://`` the simulated camera it presses (None: use the board's camera).

    Raises
    ------
    RigError
        For an unknown scheme, missing limits, or a rig that cannot be reached.
    """
    url = url or config.rig.url
    if not url:
        raise RigError(f"{config.source}: no rig: give --rig URL or set rig.url")
    scheme = rig_scheme(url)
    limits = rig_limits(config, url)
    rest = url[len(RIG_SCHEMES[scheme]):]
    if scheme == "gcode":
        from optitac_edge.io.rigs.gcode import GcodeRig

        return GcodeRig(rest, limits, baudrate=config.rig.baudrate, home=config.rig.home), None
    if scheme == "ur":
        from optitac_edge.io.rigs.ur import UrRig

        return UrRig(rest.strip("/"), limits), None
    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.sim.camera import SimCamera
    from optitac_edge.sim.rig import SimRig, parse_sim_url

    mount = parse_sim_url(url)
    clock = VirtualClock()
    rig = SimRig(limits, clock, mount)
    cam = config.camera
    camera = SimCamera(fps=cam.fps, width=cam.width, height=cam.height, rgb=cam.pixel_format == "rgb",
                       realtime=False, clock=clock, program=rig, physics=mount.physics, day=mount.day,
                       layout=str(cam.options.get("layout", "")))
    return rig, camera
