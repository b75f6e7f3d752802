"""The SoC temperature (Raspberry Pi and Jetson sysfs), reported in STATUS."""

from __future__ import annotations

from pathlib import Path


def cpu_temperature_c() -> float | None:
    """SoC temperature from sysfs (Pi and Jetson), °C, or None."""
    for zone in sorted(Path("/sys/class/thermal").glob("thermal_zone*/temp")):
        try:
            return int(zone.read_text().strip()) / 1000.0
        except (OSError, ValueError):
            continue
    return None
