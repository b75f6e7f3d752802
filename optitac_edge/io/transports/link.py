"""A board's ``[link]``: the link to the gripper's MCU, the keys every transport reads its own from."""

from __future__ import annotations

from dataclasses import dataclass

from optitac_edge.fields import choice, integer, setting, string


def transport_name(value: object, from_text: bool) -> str:
    """A name of the transport registry (:data:`optitac_edge.io.transports.TRANSPORTS`, the one list)."""
    from optitac_edge.io.transports import TRANSPORTS

    return choice(*TRANSPORTS)(value, from_text)


@dataclass(frozen=True)
class LinkConfig:
    transport: str = setting(transport_name, "none", "link to the MCU: serial, can, none")
    serial_url: str = setting(string(4096), "", "serial: pyserial URL or device, e.g. /dev/optitac-mcu")
    baudrate: int = setting(integer(1200, 12_000_000), 115_200, "serial: baud rate (ignored by USB CDC)")
    can_channel: str = setting(string(64), "can0", "can: python-can channel (socketcan: interface name)")
    can_interface: str = setting(string(64, pattern=r"[a-z0-9_]+", empty=False), "socketcan",
                                 "can: python-can interface")
    can_bitrate: int = setting(integer(10_000, 1_000_000), 500_000,
                               "can: bit rate (socketcan: set on the interface, docs/deploy.md)")
    can_protocol: int = setting(integer(1, 3), 1,
                                "can: 2 adds protocol v2's CONTACT2 and RELEASE frames (every contact with depth, "
                                "force and id) on their own ids beside the v1 frames, 3 also each contact's MOTION "
                             "(velocity, slip, vibration) (docs/can.md)")
    rate_divider: int = setting(integer(1, 1000), 1, "send the contact of every Nth frame")
