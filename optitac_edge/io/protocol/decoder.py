"""Stream decoder: bytes in (any chunking), validated frames out, errors counted by kind."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from cobs import cobs

from optitac_edge.io.protocol.wire import CRC, HEADER, MAX_ENCODED, MIN_FRAME, VERSION, Frame, crc16


@dataclass
class DecoderCounters:
    """Frames accepted and rejected, by reason (the C decoder keeps the same counters)."""

    frames: int = 0  # accepted
    cobs: int = 0  # COBS code points past the end of the frame
    length: int = 0  # decoded frame shorter than header + crc (10 bytes)
    crc: int = 0
    version: int = 0
    overflow: int = 0  # more than MAX_ENCODED bytes before a delimiter (rest of it skipped)

    @property
    def errors(self) -> int:
        return self.cobs + self.length + self.crc + self.version + self.overflow

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class FrameDecoder:
    """Splits a byte stream at 0x00 delimiters and validates each frame.

    Checks, in order: overflow (encoded length > :data:`MAX_ENCODED`), COBS, length
    (>= 10 decoded bytes), CRC, version. Empty frames (consecutive delimiters) are ignored
    without counting, so a sender may start with a 0x00 to resynchronise. Bytes before the
    first delimiter after start-up form a frame like any other (usually counted as an error).
    Never raises on input; memory is bounded by :data:`MAX_ENCODED`.
    """

    def __init__(self, max_encoded: int = MAX_ENCODED) -> None:
        self.max_encoded = max_encoded
        self.counters = DecoderCounters()
        self._buf = bytearray()
        self._overflow = False

    def reset(self) -> None:
        """Drop a partial frame (counters kept)."""
        self._buf.clear()
        self._overflow = False

    def feed(self, data: bytes | bytearray | memoryview | int) -> list[Frame]:
        """Feed bytes (or one byte as an int); returns the frames completed by them, in order."""
        if isinstance(data, int):
            data = bytes((data & 0xFF,))
        data = bytes(data)
        out: list[Frame] = []
        start, n = 0, len(data)
        while start <= n:
            end = data.find(0, start)
            part = data[start:] if end < 0 else data[start:end]
            if part:
                if not self._overflow and len(self._buf) + len(part) > self.max_encoded:
                    self._overflow = True
                    self.counters.overflow += 1
                    self._buf.clear()
                if not self._overflow:
                    self._buf += part
            if end < 0:
                break
            if self._overflow:
                self._overflow = False
            elif self._buf:
                frame = self._complete(bytes(self._buf))
                if frame is not None:
                    out.append(frame)
            self._buf.clear()
            start = end + 1
        return out

    def _complete(self, encoded: bytes) -> Frame | None:
        c = self.counters
        try:
            raw = cobs.decode(encoded)
        except cobs.DecodeError:
            c.cobs += 1
            return None
        if len(raw) < MIN_FRAME:
            c.length += 1
            return None
        body = raw[: -CRC.size]
        if crc16(body) != CRC.unpack_from(raw, len(body))[0]:
            c.crc += 1
            return None
        version, msg_type, seq, t_us = HEADER.unpack_from(body)
        if version != VERSION:
            c.version += 1
            return None
        c.frames += 1
        return Frame(msg_type, seq, t_us, body[HEADER.size:])
