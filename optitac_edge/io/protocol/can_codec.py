"""Encode :mod:`~optitac_edge.io.protocol.messages` into the frames of ``optitac.dbc`` (and back).

Encoding goes through cantools with ``scaling=True``: every physical value is
first clipped to its signal's [minimum, maximum] from the DBC, so values out of
range saturate instead of raising. Counters that only grow (frames dropped,
errors) are sent modulo their field width instead; the receiver takes
differences.
"""

from __future__ import annotations

import math
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import cantools

from optitac_edge.errors import TransportError
from optitac_edge.io.protocol.messages import (
    TEMP_UNKNOWN,
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ShapeCode,
    StatusMessage,
    fold_angle_deg,
)

#: The packaged database (a regular file next to this module).
DBC_PATH = Path(__file__).with_name("optitac.dbc")

#: Identifier of sensor 0's CONTACT_A; sensor ``s`` adds ``SENSOR_STRIDE * s``.
BASE_ID = 0x300
SENSOR_STRIDE = 0x10
#: Message name -> offset from the sensor's base identifier.
MESSAGE_OFFSETS: dict[str, int] = {"CONTACT_A": 0, "CONTACT_B": 1, "STATUS": 2, "CONTACT2": 3, "RELEASE": 4,
                                   "MOTION": 5}
_MAX_STANDARD_ID = 0x7FF
COUNTER_MODULO = 16

#: Signals each message must have (a custom ``dbc_path`` is checked against these).
REQUIRED_SIGNALS: dict[str, tuple[str, ...]] = {
    "CONTACT_A": ("X", "Y", "MAJOR", "MINOR", "CONFIDENCE", "COUNTER"),
    "CONTACT_B": ("ANGLE", "STRENGTH", "SHAPE", "FLAGS", "AGE", "COUNTER"),
    "STATUS": ("CALIBRATION_ID", "FPS", "STATE", "CPU_TEMP", "FRAMES_DROPPED", "LINK_ERRORS",
               "CAMERA_ERRORS", "COUNTER"),
}

#: Protocol v2's messages (``link.can_protocol = 2``): required only then.
V2_SIGNALS: dict[str, tuple[str, ...]] = {
    "CONTACT2": ("PART", "SLOT", "COUNTER", "X", "Y", "MAJOR", "MINOR", "ANGLE", "STRENGTH", "SHAPE", "CONFIDENCE",
                 "N_CONTACTS", "DEPTH", "FORCE", "CONTACT_ID", "FLAGS", "AGE"),
    "RELEASE": ("CONTACT_ID", "COUNTER"),
}
#: Protocol v3's message (``link.can_protocol = 3``, with v2's): required only then.
V3_SIGNALS: dict[str, tuple[str, ...]] = {
    "MOTION": ("SLOT", "COUNTER", "FLAGS", "CONTACT_ID", "VX", "VY", "VIBRATION"),
}

#: STATUS.CPU_TEMP physical value meaning "unknown" (raw 255).
CPU_TEMP_UNKNOWN = 215.0


@lru_cache(maxsize=8)
def load_database(dbc_path: str | None = None) -> Any:
    """The cantools database from ``dbc_path`` (default: the packaged ``optitac.dbc``)."""
    try:
        if dbc_path is None:
            text = resources.files(__package__).joinpath("optitac.dbc").read_text(encoding="utf-8")
            return cantools.database.load_string(text, database_format="dbc")
        return cantools.database.load_file(str(dbc_path), database_format="dbc")
    except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as exc:
        raise TransportError(f"cannot load CAN database {dbc_path or DBC_PATH}: {exc}") from exc


def max_sensor_id(base_id: int = BASE_ID) -> int:
    """The largest sensor id whose three identifiers stay 11-bit."""
    return (_MAX_STANDARD_ID - base_id - max(MESSAGE_OFFSETS.values())) // SENSOR_STRIDE


def message_ids(sensor_id: int, base_id: int = BASE_ID) -> dict[str, int]:
    """CAN identifiers of ``sensor_id``'s messages: ``{"CONTACT_A": ..., ...}``."""
    if not 0 <= base_id <= _MAX_STANDARD_ID or base_id % SENSOR_STRIDE:
        raise TransportError(f"CAN base id {base_id:#x} must be an 11-bit multiple of {SENSOR_STRIDE:#x}")
    if not 0 <= sensor_id <= max_sensor_id(base_id):
        raise TransportError(
            f"sensor_id {sensor_id} out of range for CAN base id {base_id:#x} "
            f"(0..{max_sensor_id(base_id)} keep the identifiers 11-bit)")
    first = base_id + SENSOR_STRIDE * sensor_id
    return {name: first + offset for name, offset in MESSAGE_OFFSETS.items()}


def split_id(arbitration_id: int, base_id: int = BASE_ID) -> tuple[int, str] | None:
    """``(sensor_id, message name)`` of an identifier, or None if it is not ours."""
    rel = arbitration_id - base_id
    if rel < 0 or arbitration_id > _MAX_STANDARD_ID:
        return None
    sensor_id, offset = divmod(rel, SENSOR_STRIDE)
    for name, off in MESSAGE_OFFSETS.items():
        if off == offset:
            return sensor_id, name
    return None


def decode_frame(arbitration_id: int, data: bytes, *, base_id: int = BASE_ID, dbc_path: str | None = None,
                 decode_choices: bool = False) -> tuple[int, str, dict[str, Any]] | None:
    """Decode one received frame of any sensor: ``(sensor_id, name, physical signals)`` or None."""
    where = split_id(arbitration_id, base_id)
    if where is None:
        return None
    sensor_id, name = where
    message = load_database(dbc_path).get_message_by_name(name)
    return sensor_id, name, message.decode(bytes(data), decode_choices=decode_choices, scaling=True)


def _finite(value: float) -> float:
    """float(value); NaN -> 0, ±inf kept (they saturate)."""
    value = float(value)
    return 0.0 if math.isnan(value) else value


def _int_or_zero(value: float) -> int | float:
    """int(value) for finite values (truncation, as the serial protocol); ±inf kept; NaN -> 0."""
    value = float(value)
    if math.isnan(value):
        return 0
    return value if math.isinf(value) else int(value)


class CanCodec:
    """Payloads of one sensor's frames, encoded with cantools from the DBC.

    Parameters
    ----------
    sensor_id : int
        Selects the identifiers (``base_id + 0x10 * sensor_id``).
    dbc_path : str or Path, optional
        A database with the same message and signal names (default: packaged).
    base_id : int
        Identifier of sensor 0's CONTACT_A.
    protocol : int
        2: the database must also hold protocol v2's CONTACT2 and RELEASE.
    """

    def __init__(self, sensor_id: int = 0, dbc_path: str | Path | None = None,
                 base_id: int = BASE_ID, protocol: int = 1) -> None:
        self.sensor_id = int(sensor_id)
        self.base_id = int(base_id)
        self.ids = message_ids(self.sensor_id, self.base_id)
        self.dbc_path = None if dbc_path is None else str(dbc_path)
        self.db = load_database(self.dbc_path)
        self._messages: dict[str, Any] = {}
        self._limits: dict[str, dict[str, tuple[float, float]]] = {}
        self._signals: dict[str, dict[str, Any]] = {}
        wanted = {**REQUIRED_SIGNALS, **(V2_SIGNALS if protocol >= 2 else {}), **(V3_SIGNALS if protocol == 3 else {})}
        for name, required in wanted.items():
            try:
                message = self.db.get_message_by_name(name)
            except KeyError:
                raise TransportError(f"CAN database has no message {name}") from None
            if message.length != 8:
                raise TransportError(f"CAN message {name} must be 8 bytes, not {message.length}")
            signals = {s.name: s for s in message.signals}
            missing = [s for s in required if s not in signals]
            if missing:
                raise TransportError(f"CAN message {name} lacks signals {', '.join(missing)}")
            self._messages[name] = message
            self._limits[name] = {s.name: self._range(s) for s in message.signals}
            self._signals[name] = signals

    @staticmethod
    def _range(signal: Any) -> tuple[float, float]:
        """Physical [lo, hi] of a signal: the DBC's min/max, else what its raw width allows."""
        if signal.is_signed:
            raw_lo, raw_hi = -(1 << (signal.length - 1)), (1 << (signal.length - 1)) - 1
        else:
            raw_lo, raw_hi = 0, (1 << signal.length) - 1
        a, b = raw_lo * signal.scale + signal.offset, raw_hi * signal.scale + signal.offset
        lo, hi = min(a, b), max(a, b)
        if signal.minimum is not None:
            lo = max(lo, signal.minimum)
        if signal.maximum is not None:
            hi = min(hi, signal.maximum)
        return lo, hi

    def _encode(self, name: str, values: dict[str, float]) -> bytes:
        """Clip every physical value to its signal's range, round it to the signal's resolution
        (half away from zero, like the serial protocol) and encode with cantools (scaling=True)."""
        limits, signals = self._limits[name], self._signals[name]
        physical = {}
        for key, value in values.items():
            lo, hi = limits[key]
            value = min(max(value, lo), hi)
            signal = signals[key]
            x = (value - signal.offset) / signal.scale
            n = math.floor(abs(x) + 0.5)
            physical[key] = (n if x >= 0 else -n) * signal.scale + signal.offset
        return bytes(self._messages[name].encode(physical, scaling=True, padding=False, strict=False))

    def contact_payloads(self, msg: ContactMessage, counter: int) -> tuple[bytes, bytes]:
        """CONTACT_A and CONTACT_B payloads of one frame, both with ``counter`` (mod 16)."""
        counter %= COUNTER_MODULO
        a = self._encode("CONTACT_A", {
            "X": _finite(msg.x_mm),
            "Y": _finite(msg.y_mm),
            "MAJOR": _finite(msg.major_mm),
            "MINOR": _finite(msg.minor_mm),
            "CONFIDENCE": _finite(msg.confidence),
            "COUNTER": counter,
        })
        b = self._encode("CONTACT_B", {
            "ANGLE": fold_angle_deg(_finite(msg.angle_deg)),
            "STRENGTH": _finite(msg.strength),
            "SHAPE": ShapeCode.coerce(msg.shape),
            "FLAGS": int(msg.flags) & 0x1F,
            "AGE": _int_or_zero(msg.age_us),
            "COUNTER": counter,
        })
        return a, b

    def status_payload(self, msg: StatusMessage, counter: int) -> bytes:
        """STATUS payload; cumulative counts are sent modulo their field width."""
        temp = CPU_TEMP_UNKNOWN if msg.cpu_temp_c_x10 == TEMP_UNKNOWN else min(msg.cpu_temp_c_x10 / 10.0,
                                                                        CPU_TEMP_UNKNOWN - 1)
        return self._encode("STATUS", {
            "CALIBRATION_ID": (int(msg.calibration_id) >> 16) & 0xFFFF,
            "FPS": max(int(msg.fps_x10), 0) / 10.0,
            "STATE": int(msg.state) & 0x0F,
            "CPU_TEMP": temp,
            "FRAMES_DROPPED": max(int(msg.frames_dropped), 0) % 256,
            "LINK_ERRORS": max(int(msg.link_errors), 0) % 256,
            "CAMERA_ERRORS": max(int(msg.camera_errors), 0) % 16,
            "COUNTER": counter % COUNTER_MODULO,
        })

    def contact2_payloads(self, msg: ContactV2Message, counter: int) -> tuple[bytes, bytes, bytes]:
        """The three CONTACT2 parts of one contact (SLOT = its index), with the frame's ``counter``."""
        head = {"SLOT": min(max(int(msg.index), 0), 3), "COUNTER": counter % COUNTER_MODULO}
        geometry = self._encode("CONTACT2", {**head, "PART": 0, "X": _finite(msg.x_mm), "Y": _finite(msg.y_mm),
                                             "MAJOR": _finite(msg.major_mm), "MINOR": _finite(msg.minor_mm)})
        shape = self._encode("CONTACT2", {**head, "PART": 1, "ANGLE": fold_angle_deg(_finite(msg.angle_deg)),
                                          "STRENGTH": _finite(msg.strength), "SHAPE": ShapeCode.coerce(msg.shape),
                                          "CONFIDENCE": _finite(msg.confidence), "N_CONTACTS": int(msg.n_contacts)})
        force = self._encode("CONTACT2", {**head, "PART": 2, "DEPTH": _finite(msg.depth_mm),
                                          "FORCE": _finite(msg.force_n), "CONTACT_ID": int(msg.contact_id),
                                          "FLAGS": int(msg.flags) & 0x7F, "AGE": _int_or_zero(msg.age_us)})
        return geometry, shape, force

    def motion_payload(self, msg: MotionMessage, counter: int) -> bytes:
        """The MOTION of one contact (SLOT = its index; the frame's vibration), with the frame's ``counter``."""
        return self._encode("MOTION", {"SLOT": min(max(int(msg.index), 0), 3), "COUNTER": counter % COUNTER_MODULO,
                                       "FLAGS": int(msg.flags) & 0x3F, "CONTACT_ID": int(msg.contact_id),
                                       "VX": _finite(msg.vx_mm_s), "VY": _finite(msg.vy_mm_s),
                                       "VIBRATION": _finite(msg.vibration)})

    def release_payload(self, contact_id: int, counter: int) -> bytes:
        """A RELEASE of ``contact_id`` in the frame of ``counter``."""
        return self._encode("RELEASE", {"CONTACT_ID": int(contact_id), "COUNTER": counter % COUNTER_MODULO})

    def decode(self, arbitration_id: int, data: bytes,
               decode_choices: bool = False) -> tuple[str, dict[str, Any]] | None:
        """Decode a frame of this sensor: ``(name, physical signals)``, or None if it is not ours."""
        for name, frame_id in self.ids.items():
            if frame_id == arbitration_id:
                return name, self._messages[name].decode(bytes(data), decode_choices=decode_choices,
                                                         scaling=True)
        return None
