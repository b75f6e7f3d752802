"""Plain little-endian CDR (XCDR1), the serialization ROS 2 and rmw_zenoh use on the wire.

A message starts with the 4-byte encapsulation header ``00 01 00 00`` (CDR, little
endian); every primitive is aligned to its size (8 at most) counted from the end
of that header; a string is its length with the terminating NUL (uint32), its
UTF-8 bytes and the NUL; a sequence is its length (uint32) and its elements.
"""

from __future__ import annotations

import struct

import numpy as np

#: The encapsulation header of a little-endian plain-CDR payload.
CDR_LE_HEADER = b"\x00\x01\x00\x00"

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_U64 = struct.Struct("<Q")
_F32 = struct.Struct("<f")
_F64 = struct.Struct("<d")


class CdrWriter:
    """Appends CDR-encoded values to a payload; :meth:`payload` returns the bytes so far.

    Examples
    --------
    >>> w = CdrWriter()
    >>> w.u8(1); w.u32(7)
    >>> w.payload().hex()
    '000100000100000007000000'
    """

    __slots__ = ("_buf",)

    def __init__(self) -> None:
        self._buf = bytearray(CDR_LE_HEADER)

    def _align(self, size: int) -> None:
        pad = -(len(self._buf) - 4) % size
        if pad:
            self._buf += b"\x00" * pad

    def u8(self, value: int) -> None:
        self._buf.append(value)

    def boolean(self, value: bool) -> None:
        self._buf.append(1 if value else 0)

    def u16(self, value: int) -> None:
        self._align(2)
        self._buf += _U16.pack(value)

    def u32(self, value: int) -> None:
        self._align(4)
        self._buf += _U32.pack(value)

    def i32(self, value: int) -> None:
        self._align(4)
        self._buf += _I32.pack(value)

    def u64(self, value: int) -> None:
        self._align(8)
        self._buf += _U64.pack(value)

    def f32(self, value: float) -> None:
        self._align(4)
        self._buf += _F32.pack(value)

    def f64(self, value: float) -> None:
        self._align(8)
        self._buf += _F64.pack(value)

    def string(self, value: str) -> None:
        data = value.encode()
        self.u32(len(data) + 1)
        self._buf += data
        self._buf.append(0)

    def u16_sequence(self, values: list[int]) -> None:
        self.u32(len(values))
        if values:
            self._align(2)
            self._buf += struct.pack(f"<{len(values)}H", *values)

    def array_sequence(self, values: np.ndarray, dtype: str) -> None:
        """A sequence of numbers: ``dtype`` is the element's little-endian numpy type
        (``"<f4"`` for float32[], ``"u1"`` for bool[] holding 0/1, ...)."""
        arr = np.ascontiguousarray(values, dtype=dtype)
        self.u32(arr.size)
        if arr.size:
            self._align(arr.itemsize)
            self._buf += arr.tobytes()

    def struct_sequence(self, values: np.ndarray, align: int) -> None:
        """A sequence of structs of equal numbers laid out as the rows of ``values`` (e.g. Point2[] as an
        (N, 2) float64 array): the count, then the rows' bytes, aligned to ``align`` when there are any."""
        arr = np.ascontiguousarray(values)
        self.u32(len(arr))
        if len(arr):
            self._align(align)
            self._buf += arr.astype(arr.dtype.newbyteorder("<"), copy=False).tobytes()

    def payload(self, tail: bytes | memoryview = b"") -> bytes:
        """The payload: what was written, then ``tail`` (bytes that need no alignment, e.g. a uint8[]'s
        data after its count) without copying them twice."""
        return b"".join((self._buf, tail)) if tail else bytes(self._buf)
