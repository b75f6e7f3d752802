"""Recordings as MCAP files: camera frames as sensor_msgs/Image, the recording's meta as MCAP metadata.

``optitac-edge record --mcap`` writes them; :class:`~optitac_edge.io.recording.Recording`
opens a ``*.mcap`` file as it opens a recording directory (``replay``, ``calibrate``,
``evaluate`` take either). Frames are on :data:`IMAGE_TOPIC` (``mono8`` for gray,
``rgb8`` for RGB), each stamped with its capture time (CLOCK_MONOTONIC ns in the
header, as in ``timestamps.npy``); the metadata record :data:`META_NAME` holds
``meta.json``'s keys as JSON text, and a simulated or rig-collected recording's
``truth.csv`` is an attachment of that name. Needs the ``mcap`` extra.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.errors import OutputError, RecordingError
from optitac_edge.io.mcap_file import PeriodicSync, complete, open_part
from optitac_edge.io.recording_rate import state_rate_shown
from optitac_edge.io.ros2.messages import IMAGE, encode_image, ros2msg_schema

if TYPE_CHECKING:
    from typing_extensions import Self

IMAGE_TOPIC = "/optitac/camera/image"
META_NAME = "optitac.recording"
TRUTH_NAME = "truth.csv"


class McapRecordingWriter:
    """Write frames to ``path`` (``path.part`` until :meth:`close`; :meth:`abort` removes it).

    Parameters
    ----------
    path : path
    meta : dict
        ``meta.json``'s keys (``rest_frames``, ``fps``, ...).
    truth_csv : bytes, optional
        The recording's ``truth.csv``.
    replace : bool
        ``path`` may be a complete recording; it is replaced when this one is complete (never before).

    Raises
    ------
    OutputError
        ``path`` is a complete recording and ``replace`` is not given, or cannot be written.
    """

    def __init__(self, path: str | Path, meta: dict[str, Any], truth_csv: bytes | None = None,
                 replace: bool = False) -> None:
        from mcap.writer import CompressionType, Writer

        from optitac_edge.io.recording_paths import check_writable_recording

        self.path = check_writable_recording(path, replace)
        self._stream, self._part = open_part(self.path)
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="optitac-edge")
        self._writer.add_metadata(META_NAME, {k: json.dumps(v) for k, v in meta.items()})
        if truth_csv is not None:
            self._writer.add_attachment(0, 0, TRUTH_NAME, "text/csv", truth_csv)
        schema = self._writer.register_schema(IMAGE, "ros2msg", ros2msg_schema(IMAGE).encode())
        self._channel = self._writer.register_channel(IMAGE_TOPIC, "cdr", schema)
        self.frames_written = 0
        self._done = False
        self._sync = PeriodicSync()
        self._meta = dict(meta)
        self._t_ns = np.zeros(4096, np.int64)  # for the rate the frames show (8 bytes a frame)

    def write(self, index: int, frame: np.ndarray, t_ns: int) -> None:
        """Frame ``index`` (written in order) captured at ``t_ns``."""
        if index != self.frames_written:
            raise ValueError(f"frames must be written in order: {index} after {self.frames_written}")
        try:
            self._writer.add_message(self._channel, int(t_ns), encode_image(frame, t_ns, "optitac_camera"),
                                     int(t_ns), index)
            self._sync.after(self._writer, self._stream, int(t_ns))  # a power cut loses at most about a second
        except OSError as exc:
            raise OutputError(f"cannot write {self._part}: {exc.strerror or exc}") from None
        if index >= self._t_ns.size:
            self._t_ns = np.concatenate([self._t_ns, np.zeros(self._t_ns.size, np.int64)])
        self._t_ns[index] = t_ns
        self.frames_written += 1

    def close(self) -> None:
        """Complete the file at ``path`` (idempotent); where the frames' times show another rate than the
        metadata's, a second metadata record says it (the reader takes the last)."""
        if self._done:
            return
        self._done = True
        meta = dict(self._meta)
        state_rate_shown(meta, self._t_ns[: self.frames_written], self.path)
        try:
            if meta != self._meta:
                self._writer.add_metadata(META_NAME, {k: json.dumps(v) for k, v in meta.items()})
        except OSError as exc:
            self._stream.close()
            raise OutputError(f"cannot write {self._part}: {exc.strerror or exc}") from None
        complete(self._writer, self._stream, self._part, self.path)

    def abort(self) -> None:
        """Drop what was written (idempotent)."""
        if self._done:
            return
        self._done = True
        self._stream.close()
        self._part.unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def read_mcap_recording(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any], str | None]:
    """(frames (N, H, W[, 3]) uint8, capture times (N,) int64 ns, meta, truth.csv's text or None) of an
    MCAP recording.

    Every chunk's CRC and the truth attachment's are checked: a flipped byte is refused, never replayed.

    Raises
    ------
    RecordingError
        Naming the file: not MCAP, damaged (a CRC that does not match), no frames on
        :data:`IMAGE_TOPIC`, frames of another encoding or size than the first, no recording metadata.
    """
    try:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory
    except ModuleNotFoundError as exc:
        from optitac_edge.errors import missing_extra

        raise missing_extra(exc.name or "mcap", "MCAP recordings") from None
    frames: list[np.ndarray] = []
    stamps: list[int] = []
    meta: dict[str, Any] | None = None
    truth: str | None = None
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for record in reader.iter_metadata():
                if record.name == META_NAME:
                    meta = {k: json.loads(v) for k, v in record.metadata.items()}
            f.seek(0)
            for attachment in make_reader(f).iter_attachments():
                if attachment.name == TRUTH_NAME:
                    truth = attachment.data.decode("utf-8")
            f.seek(0)
            _check_attachment_crcs(f, make_reader(f).get_summary(), path)
            f.seek(0)
            reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
            for _, _, message, image in reader.iter_decoded_messages(topics=[IMAGE_TOPIC], log_time_order=False):
                frames.append(_image_array(image, path, len(frames)))
                stamps.append(int(message.log_time))
    except RecordingError:
        raise
    except Exception as exc:  # noqa: BLE001 - mcap raises many kinds on a damaged file: one line
        raise RecordingError(f"{path}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from None
    if meta is None:
        raise RecordingError(f"{path}: no {META_NAME!r} metadata (not written by optitac-edge record --mcap)")
    if not frames:
        raise RecordingError(f"{path}: no frames on {IMAGE_TOPIC}")
    if any(f.shape != frames[0].shape for f in frames):
        raise RecordingError(f"{path}: frames of several sizes")
    return np.stack(frames), np.asarray(stamps, dtype=np.int64), meta, truth


def recording_to_mcap(rec: Any,  # a Recording (io/recording.py needs this module: no type here)
                       path: str | Path, replace: bool = False) -> Path:
    """Write a :class:`~optitac_edge.io.recording.Recording` (frames, times, meta, truth) as one MCAP file."""
    truth = rec.path / TRUTH_NAME if rec.path.is_dir() else None
    data = truth.read_bytes() if truth is not None and truth.exists() else None
    with McapRecordingWriter(path, rec.meta.to_json(), truth_csv=data, replace=replace) as writer:
        for i in range(len(rec)):
            writer.write(i, rec.frame(i), int(rec.t_ns[i]))
    return Path(path)


def _image_array(image: Any, path: Path, index: int) -> np.ndarray:
    channels = {"mono8": 1, "rgb8": 3}.get(image.encoding)
    if channels is None:
        raise RecordingError(f"{path}: frame {index} is {image.encoding!r}, not mono8 or rgb8")
    data = np.frombuffer(bytes(image.data), dtype=np.uint8)
    if image.step != image.width * channels or data.size != image.height * image.step:
        raise RecordingError(f"{path}: frame {index}: {data.size} bytes for {image.width}x{image.height} "
                             f"{image.encoding}")
    shape = (image.height, image.width) if channels == 1 else (image.height, image.width, 3)
    return data.reshape(shape)


def _check_attachment_crcs(f: Any, summary: Any, path: Path) -> None:
    """Each attachment record's CRC (the ``mcap`` reader skips it): over the record after its opcode and
    length, up to the CRC; 0 means none was written."""
    import zlib

    for index in getattr(summary, "attachment_indexes", None) or ():
        f.seek(index.offset)
        raw = f.read(index.length)
        if len(raw) != index.length or len(raw) < 13:
            raise RecordingError(f"{path}: attachment {index.name!r} is cut short")
        crc = int.from_bytes(raw[-4:], "little")
        if crc and zlib.crc32(raw[9:-4]) != crc:
            raise RecordingError(f"{path}: attachment {index.name!r} is damaged (its CRC does not match)")
