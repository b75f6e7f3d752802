"""The serial protocol v1 to the gripper MCU (docs/protocol.md): framing and messages, no I/O."""

from optitac_edge.io.protocol.decoder import DecoderCounters, FrameDecoder
from optitac_edge.io.protocol.wire import (
    CSV_HEADER,
    MAX_ENCODED,
    VERSION,
    Ack,
    Frame,
    MsgType,
    ProtocolError,
    contact_csv_row,
    contact_fields,
    contact_payload,
    crc16,
    decode_ack,
    decode_contact,
    decode_status,
    encode_ack,
    encode_command,
    encode_contact,
    encode_frame,
    encode_status,
    is_sensor_type,
    parse_command,
    status_payload,
    threshold_relative,
)

__all__ = [
    "CSV_HEADER", "MAX_ENCODED", "VERSION", "Ack", "DecoderCounters", "Frame", "FrameDecoder",
    "MsgType", "ProtocolError", "contact_csv_row", "contact_fields", "contact_payload", "crc16",
    "decode_ack", "decode_contact", "decode_status", "encode_ack", "encode_command",
    "encode_contact", "encode_frame", "encode_status", "is_sensor_type", "parse_command",
    "status_payload", "threshold_relative",
]
