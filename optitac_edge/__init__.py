"""optitac-edge: OptiTac optical-fiber tactile sensor processing for robot grippers.

The public Python API (docs/api.md) is what this package exports: :func:`open_sensor`, :class:`Sensor`,
:func:`open_sensor_process`, :class:`SensorProcess`, :class:`Reading`, :class:`Contact`, :class:`Status` and :class:`OptiTacError`. They are imported when first
used, so ``import optitac_edge`` stays light; nothing in the package touches hardware at import time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: The names the project promises to keep (tests/test_api.py lists them).
__all__ = ["Contact", "OptiTacError", "Reading", "Sensor", "SensorProcess", "Status", "__version__", "open_sensor",
           "open_sensor_process"]

if TYPE_CHECKING:
    from optitac_edge.api import Contact, Reading, Sensor, SensorProcess, Status, open_sensor, open_sensor_process
    from optitac_edge.errors import OptiTacError


def __getattr__(name: str) -> Any:
    if name == "OptiTacError":
        from optitac_edge.errors import OptiTacError

        return OptiTacError
    if name in __all__:
        from optitac_edge import api

        return getattr(api, name)
    raise AttributeError(f"module 'optitac_edge' has no attribute {name!r}")
