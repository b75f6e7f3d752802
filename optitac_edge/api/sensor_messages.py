"""The messages between :class:`~optitac_edge.api.sensor_process.SensorProcess` and its child, as data: a JSON
header, then the raw bytes of each array it names (``Connection.send_bytes``; nothing is pickled, so neither side
runs code the other sent).

A call is ``{"call": NAME, "args": [...], "id": N}`` (the first message: ``{"open": BOARD, "options": {...}}``); an
answer is ``{"kind": ..., "id": N}``, N the call's number (0: the open's): ``none``, ``value`` (a bool or number), ``opened``, ``status``, ``reading`` (its arrays follow,
each ``[dtype, shape]`` in the header) or ``error`` (an :mod:`optitac_edge.errors` class name and its line).
Floats cross exactly (JSON writes a float's shortest round-trip form; NaN as ``NaN``). A message is at most
:data:`MAX_MESSAGE_BYTES` long and nested at most as deep as Python's parser allows: anything else is a
:class:`MalformedMessage` (one line), never a ``MemoryError`` or ``RecursionError``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, fields
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from optitac_edge import errors
from optitac_edge.api.readings import Contact, Reading, Status
from optitac_edge.errors import OptiTacError

#: The dtypes an array of an answer may have (a reading's fibers and surface).
ARRAY_DTYPES = frozenset({"<f4", "<f8"})
#: The longest message either side reads, bytes (a reading's arrays: a 100 x 100 float32 surface is 40 kB).
MAX_MESSAGE_BYTES = 64 << 20
_READING_SCALARS = [f.name for f in fields(Reading) if f.name not in ("contacts", "released", "fibers", "surface")]


class MalformedMessage(OptiTacError):
    """A message between a sensor and its process that is not one of this module's."""


def encode(message: object, what: str) -> bytes:
    """``message`` (JSON data) as bytes; one line naming ``what`` when it holds a value JSON cannot carry."""
    try:
        return json.dumps(message, allow_nan=True).encode()
    except (TypeError, ValueError, RecursionError) as exc:
        raise OptiTacError(f"{what}: its arguments cannot be sent to the sensor's process: {exc}") from None


def receive(conn: Connection) -> bytes:
    """One message's bytes; :class:`MalformedMessage` for one longer than :data:`MAX_MESSAGE_BYTES` (the stream
    cannot be trusted after it: the caller ends the connection). ``EOFError`` when the other side closed."""
    try:
        return conn.recv_bytes(MAX_MESSAGE_BYTES)
    except OSError as exc:
        if "bad message length" in str(exc):
            raise MalformedMessage(f"sensor process: a message longer than {MAX_MESSAGE_BYTES} bytes") from None
        raise


def decode(data: bytes) -> dict[str, Any]:
    """A message's header (a JSON object)."""
    try:
        message = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MalformedMessage(f"sensor process: a message that is not JSON: {exc}") from None
    except RecursionError:
        raise MalformedMessage("sensor process: a message nested too deeply") from None
    if not isinstance(message, dict):
        raise MalformedMessage("sensor process: a message that is not a JSON object")
    return message


def call_id(message: dict[str, Any]) -> int:
    """A call's number (``id``: a whole number >= 0; 0 for a call without one)."""
    value = message.get("id", 0)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise MalformedMessage(f"sensor process: a call numbered {value!r}")
    return value


def send_answer(conn: Connection, value: object, number: int = 0) -> None:
    """Send call ``number``'s result (None, a bool or number, a :class:`Status`, a :class:`Reading`, the opened
    sensor's ``(id, name, camera timeout)``) or its error."""
    arrays: list[np.ndarray] = []
    header: dict[str, Any]
    if value is None:
        header = {"kind": "none"}
    elif isinstance(value, BaseException):
        kind = type(value).__name__ if isinstance(value, OptiTacError) else "OptiTacError"
        text = str(value) if isinstance(value, OptiTacError) else \
            f"the sensor process failed: {type(value).__name__}: {value}"
        header = {"kind": "error", "type": kind, "message": text}
    elif isinstance(value, Status):
        header = {"kind": "status", "fields": asdict(value)}
    elif isinstance(value, Reading):
        header = {"kind": "reading", "fields": {name: getattr(value, name) for name in _READING_SCALARS},
                  "contacts": [asdict(c) for c in value.contacts], "released": list(value.released), "arrays": {}}
        for name in ("fibers", "surface"):
            a = getattr(value, name)
            if a is not None:
                a = np.ascontiguousarray(a)
                header["arrays"][name] = [a.dtype.str, list(a.shape)]
                arrays.append(a)
    elif isinstance(value, tuple):
        header = {"kind": "opened", "value": list(value)}
    elif isinstance(value, (bool, int, float)):
        header = {"kind": "value", "value": value}
    else:
        raise TypeError(f"sensor process: no message for a {type(value).__name__}")
    header["id"] = number
    conn.send_bytes(json.dumps(header, allow_nan=True).encode())
    for a in arrays:
        conn.send_bytes(a.tobytes())


def recv_answer(conn: Connection) -> object:
    """One answer of :func:`send_answer`: its value, or its error raised (an :mod:`optitac_edge.errors` class).

    Raises
    ------
    MalformedMessage
        An answer that is not one of :func:`send_answer`'s.
    """
    value = recv_reply(conn)[1]
    if isinstance(value, OptiTacError):
        raise value
    return value


def recv_reply(conn: Connection) -> tuple[int, object]:
    """One answer of :func:`send_answer`, whole (a reading's arrays too): the number of the call it answers and
    its value, or its error (an :mod:`optitac_edge.errors` instance, not raised).

    Raises
    ------
    MalformedMessage
        An answer that is not one of :func:`send_answer`'s.
    """
    header = decode(receive(conn))
    kind = header.get("kind")
    number = header.get("id")
    if not isinstance(number, int) or isinstance(number, bool) or number < 0:
        raise MalformedMessage(f"sensor process: an answer numbered {number!r}")
    return number, _value(conn, header, kind)


def _value(conn: Connection, header: dict[str, Any], kind: object) -> object:
    try:
        if kind == "none":
            return None
        if kind == "value":
            return header["value"]
        if kind == "opened":
            sensor_id, name, timeout_s = header["value"]
            return int(sensor_id), str(name), float(timeout_s)
        if kind == "status":
            return Status(**header["fields"])
        if kind == "error":
            cls = getattr(errors, str(header["type"]), None)
            cls = cls if isinstance(cls, type) and issubclass(cls, OptiTacError) else OptiTacError
            return cls(str(header["message"]))
        if kind == "reading":
            arrays = {name: _array(receive(conn), spec) for name, spec in header["arrays"].items()}
            return Reading(**header["fields"], contacts=tuple(Contact(**c) for c in header["contacts"]),
                           released=tuple(int(i) for i in header["released"]),
                           fibers=arrays.get("fibers"), surface=arrays.get("surface"))
    except (KeyError, TypeError, ValueError) as exc:
        raise MalformedMessage(f"sensor process: a malformed {kind} answer: {exc}") from None
    raise MalformedMessage(f"sensor process: an answer of no known kind ({kind!r})")


def _array(data: bytes, spec: object) -> np.ndarray:
    """The array ``spec`` (``[dtype, shape]``) describes, from its bytes (a copy: writable, as the sensor's)."""
    if not (isinstance(spec, list) and len(spec) == 2 and spec[0] in ARRAY_DTYPES and isinstance(spec[1], list)
            and all(isinstance(n, int) and n >= 0 for n in spec[1])):
        raise ValueError(f"an array of {spec!r}")
    dtype, shape = np.dtype(spec[0]), tuple(spec[1])
    if len(data) != dtype.itemsize * math.prod(shape):
        raise ValueError(f"{len(data)} bytes for an array of {spec!r}")
    return np.frombuffer(data, dtype).reshape(shape).copy()
