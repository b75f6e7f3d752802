"""The messages to and from the gripper MCU and their wire formats, no I/O.

:mod:`.messages` (what is said: CONTACT, STATUS, commands; no dependencies),
:mod:`.wire` and :mod:`.decoder` (serial protocol v1, docs/protocol.md; needs
``cobs``), :mod:`.can_codec` and ``optitac.dbc`` (the CAN database, docs/can.md;
needs ``cantools``). Nothing is imported here, so the messages cost no
optional package.
"""
