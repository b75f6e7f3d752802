"""The CAN database (``optitac.dbc``) and the encoder/decoder built on it.

The DBC describes the messages of sensor 0 (CONTACT_A 0x300, CONTACT_B 0x301,
STATUS 0x302); sensor ``s`` uses the same layouts at ``base + 0x10 * s``
(+0 CONTACT_A, +1 CONTACT_B, +2 STATUS), 11-bit standard identifiers.
See docs/can.md. Needs ``cantools`` (the ``can`` extra).
"""

from .codec import (
    BASE_ID,
    DBC_PATH,
    MESSAGE_OFFSETS,
    SENSOR_STRIDE,
    CanCodec,
    decode_frame,
    load_database,
    max_sensor_id,
    message_ids,
    split_id,
)

__all__ = [
    "BASE_ID",
    "DBC_PATH",
    "MESSAGE_OFFSETS",
    "SENSOR_STRIDE",
    "CanCodec",
    "decode_frame",
    "load_database",
    "max_sensor_id",
    "message_ids",
    "split_id",
]
