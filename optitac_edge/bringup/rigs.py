"""Open the rig a board config (or ``--rig URL``) names: its URL scheme chooses the class
(:data:`optitac_edge.io.rigs.RIGS`), imported only then."""

from __future__ import annotations

from optitac_edge.config import BoardConfig
from optitac_edge.errors import RigError
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.rigs import RIGS
from optitac_edge.io.rigs.base import Rig


def open_rig(config: BoardConfig, url: str | None = None) -> tuple[Rig, Camera | None]:
    """The rig, and the camera that sees what it presses when it brings one (the simulator's; None: use the
    board's camera).

    Raises
    ------
    RigError
        For an unknown scheme, missing limits, or a rig that cannot be reached.
    """
    url = url or config.rig.url
    if not url:
        raise RigError(f"{config.source}: no rig: give --rig URL or set rig.url")
    scheme = url.partition(":")[0]
    if scheme not in RIGS:
        forms = ", ".join(f"{name}://..." for name in sorted(RIGS))
        raise RigError(f"unknown rig URL {url!r} (known: {forms})")
    cls = RIGS.load(scheme)
    with RIGS.importing(scheme):
        rig = cls.from_url(url, config.rig)
    try:
        return rig, rig.own_camera(config.camera)
    except BaseException:
        rig.close()
        raise
