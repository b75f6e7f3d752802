"""An open sensor (:class:`Sensor`) and how to open one (:func:`open_sensor`)."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from optitac_edge.api.background import BackgroundReader
from optitac_edge.api.readings import Reading, Status
from optitac_edge.errors import ConfigError, OptiTacError

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.config import BoardConfig, BoardSensor
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.io.cameras.base import Camera


class Sensor:
    """One sensor of a board, open: its camera (and LED ring) and its pipeline. Use :func:`open_sensor`.

    Two ways to read it. In the calling thread, frame by frame: :meth:`read`, :meth:`readings` or a ``for``
    loop (each call waits for the next frame). Or in the background, for a control loop slower than the
    camera: :meth:`start` reads every frame in a thread of the sensor's own, and :meth:`latest` returns the
    newest reading without waiting; the ones it never returned are counted (``status().unread``).

    A context manager; :meth:`close` is idempotent and ends the background thread. Use one sensor from one
    thread: its methods are not to be called from two threads at once (the background thread is the sensor's
    own and is safe).
    """

    def __init__(self, board: BoardConfig, sensor: BoardSensor, camera: Camera, bundle: CalibrationBundle,
                 stack: ExitStack, arrays: bool = False) -> None:
        from optitac_edge.core.pipeline import Pipeline

        self._board, self._sensor, self._camera, self._stack = board, sensor, camera, stack
        self._pipeline = Pipeline(bundle, fps=camera.fps, source=f"{sensor.label}'s camera frames")
        self._arrays = arrays
        self._frames = self._contacts = self._skipped = 0
        self._closed = False
        self._reader: BackgroundReader | None = None
        self._unread_before = 0  # of readers stopped before
        #: The board config's id of this sensor (what the MCU hears).
        self.sensor_id: int = int(sensor.sensor.id)
        #: Its name in the board config.
        self.name: str = str(sensor.sensor.name)
        #: The longest wait for one frame, s (the camera's ``timeout_s`` in the board config).
        self.camera_timeout_s: float = float(board.camera.timeout_s)

    def _check_open(self) -> None:
        if self._closed:
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r} is closed")

    def _check_foreground(self, what: str) -> None:
        self._check_open()
        if self._reader is not None:
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r} is read in the background (start()): "
                               f"{what} would take its frames; use latest(), or stop() first")

    def read(self, timeout_s: float = 1.0) -> Reading | None:
        """The next frame's reading; None when no frame came within ``timeout_s`` or a recording ended.

        A frame the check refuses (dark, saturated, of another shape) is counted in :meth:`status` and the
        next one is read, within the same timeout.

        Raises
        ------
        OptiTacError
            The sensor is closed or read in the background, or the camera failed (one line naming it).
        """
        self._check_foreground("read()")
        return self._step(_seconds(timeout_s, "timeout_s"))[0]

    def _step(self, timeout_s: float) -> tuple[Reading | None, bool]:
        """(The next frame's reading within ``timeout_s``, or None; True when the source ended.)"""
        from optitac_edge.core.frame_engine import Skip

        deadline = time.monotonic() + timeout_s
        while True:
            captured = self._camera.read(max(deadline - time.monotonic(), 0.0))
            if captured is None:
                return None, True
            result = self._pipeline.process(captured.frame, captured.t_ns)
            if isinstance(result, Skip):
                self._skipped += 1
                if time.monotonic() >= deadline:
                    return None, False
                continue
            self._frames += 1
            self._contacts += result.n_contacts > 0
            if not self._arrays:
                return Reading.of(self.sensor_id, result), False
            pipe = self._pipeline
            return Reading.of(self.sensor_id, result, pipe.signal.copy(), pipe.surface_levels()), False

    def readings(self, duration_s: float | None = None, timeout_s: float = 1.0) -> Iterator[Reading]:
        """Every frame's reading, for ``duration_s`` of frame time (None: until the camera or recording ends
        or ``timeout_s`` passes without a frame)."""
        return iter_readings(self.read, duration_s, timeout_s)

    def __iter__(self) -> Iterator[Reading]:
        return self.readings()

    def start(self) -> None:
        """Read every frame in a background thread from now on (idempotent); take the newest with
        :meth:`latest`. The thread waits for a frame at most the camera's ``timeout_s`` (board config) and
        ends when the camera fails (the next :meth:`latest` raises it) or a recording ends."""
        self._check_open()
        if self._reader is not None and self._reader.running:
            return
        self.stop()
        self._reader = BackgroundReader(self._step, self._pipeline.reset_baseline,
                                        self.camera_timeout_s, f"optitac-sensor-{self.sensor_id}")

    def latest(self, timeout_s: float = 0.0) -> Reading | None:
        """The newest reading not returned before, at once (default), or waiting up to ``timeout_s`` for one;
        None when there is none (no new frame yet, or the recording ended).

        A reading is returned at most once; the ones a newer reading replaced before this was called are
        counted in ``status().unread``, never lost silently.

        Raises
        ------
        OptiTacError
            The sensor is closed or not started (:meth:`start`), or its camera failed in the background.
        """
        self._check_open()
        wait = _seconds(timeout_s, "timeout_s")
        if self._reader is None:
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r}: latest() reads what start() reads in the "
                               "background: call start() first (or read() in this thread)")
        return self._reader.take(wait)

    def stop(self) -> None:
        """End the background reading of :meth:`start` and wait for its thread (idempotent); :meth:`read`
        works again. The counters stay."""
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                reader.stop()
            finally:
                self._unread_before += reader.unread

    def tare(self, wait_s: float | None = None) -> bool:
        """Take the rest light again from the next frames (nothing may touch the skin meanwhile).

        Parameters
        ----------
        wait_s : float, optional
            Wait up to this long, s, until the baseline is ready again (read in the background when started,
            else frames are read here and their readings counted as unread). None (default): return at once.

        Returns
        -------
        bool
            The baseline is ready (False at once without ``wait_s``; False when ``wait_s`` passed first).
        """
        self._check_open()
        wait = None if wait_s is None else _seconds(wait_s, "wait_s")
        if self._reader is not None:
            return self._reader.tare(wait)
        self._pipeline.reset_baseline()
        if wait is None:
            return False
        deadline = time.monotonic() + wait
        while (left := deadline - time.monotonic()) > 0:
            reading, ended = self._step(left)
            if ended:
                return False
            if reading is not None:
                self._unread_before += 1  # read here, never returned: counted as unread
                if reading.baseline_ready:
                    return True
        return False

    def status(self) -> Status:
        """The sensor's counters and state now."""
        unread = self._unread_before + (self._reader.unread if self._reader is not None else 0)
        return Status(self.sensor_id, self.name, self._frames, self._contacts, self._skipped,
                      bool(self._pipeline.baseline_ready), self._pipeline.bundle.calibration_id,
                      self._pipeline.compiled, float(self._camera.fps), int(self._camera.frames_dropped), unread)

    def close(self) -> None:
        """End the background reading, close the camera and the LED ring (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.stop()
        finally:
            self._stack.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def check_open_arguments(board: object, sensor: object, settings: object, cal: object = None,
                         recording: object = None) -> None:
    """The types :func:`open_sensor` takes, or one line naming the argument."""
    if not isinstance(board, (str, os.PathLike)) or isinstance(board, bytes):
        raise OptiTacError(f"board must be a board name or a config file's path, got {board!r}")
    for name, value in (("cal", cal), ("recording", recording)):
        if value is not None and (not isinstance(value, (str, os.PathLike)) or isinstance(value, bytes)):
            raise OptiTacError(f"{name} must be a path (str or os.PathLike), got {type(value).__name__} {value!r:.40}")
    if settings is not None and not isinstance(settings, Mapping):
        raise OptiTacError(f"settings must be a mapping of 'section.key' to values, got {type(settings).__name__}")
    if settings is not None:
        for key in settings:
            if not isinstance(key, str):
                raise OptiTacError(f"settings: a key must be 'section.key' (a str), got {type(key).__name__} "
                                   f"{key!r:.40}")
    if sensor is not None and (isinstance(sensor, bool) or not isinstance(sensor, int)):
        raise OptiTacError(f"sensor must be a sensor's id (an integer), got {sensor!r}")


def iter_readings(read: Callable[[float], Reading | None], duration_s: float | None,
                  timeout_s: float) -> Iterator[Reading]:
    """The readings ``read(timeout_s)`` returns, for ``duration_s`` of frame time (None: until it returns None)."""
    if duration_s is not None:
        _seconds(duration_s, "duration_s")
    _seconds(timeout_s, "timeout_s")
    return _readings(read, duration_s, timeout_s)


def _readings(read: Callable[[float], Reading | None], duration_s: float | None,
              timeout_s: float) -> Iterator[Reading]:
    end: int | None = None
    while True:
        reading = read(timeout_s)
        if reading is None:
            return
        if duration_s is not None:
            end = reading.t_ns + round(duration_s * 1e9) if end is None else end
            if reading.t_ns >= end:
                return
        yield reading


#: The longest duration or wait a call takes, s (about 31 years: ``duration_s=None`` reads until the end).
MAX_SECONDS = 1e9


def _seconds(value: object, name: str) -> float:
    """``value`` as a finite number of seconds in 0..:data:`MAX_SECONDS`, or one line naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0 <= value <= MAX_SECONDS:
        raise OptiTacError(f"{name} must be a number of seconds in 0..{MAX_SECONDS:g}, got {value!r}")
    return float(value)


def open_sensor(board: str | os.PathLike[str] = "sim", *, sensor: int | None = None,
                cal: str | os.PathLike[str] | None = None, recording: str | os.PathLike[str] | None = None,
                settings: Mapping[str, Any] | None = None, arrays: bool = False) -> Sensor:
    """Open one sensor of a board.

    Parameters
    ----------
    board : str or path
        A packaged board (``sim``: the built-in simulated sensor; ``rpi5-gs``, ...: the files of ``board_configs/``)
        or a board config file (TOML). ``OPTITAC_<SECTION>_<KEY>`` environment variables apply, as for
        ``optitac-edge run``.
    sensor : int, optional
        The sensor's id in the board config (default: its first sensor).
    cal : path, optional
        A calibration bundle to use (default: the board config's; without one the fiber map is calibrated
        from the first rest frames, and saved where the config says).
    recording : path, optional
        Replay this recording (a directory ``optitac-edge record`` or ``sim`` wrote) through the sensor
        instead of its camera: as fast as it is read, each frame at its recorded time (moved to the moment
        it was opened).
    settings : mapping, optional
        Board config overrides, ``{"section.key": value}`` (e.g. ``{"camera.fps": 120}``).
    arrays : bool
        Fill each reading's ``fibers`` and ``surface`` (copies, ~20 KB a frame: off by default).

    Raises
    ------
    OptiTacError
        A board, sensor, bundle, camera or recording that cannot be opened: one line naming it.
    """
    from optitac_edge.config import load_board_config

    check_open_arguments(board, sensor, settings, cal, recording)
    if recording is not None:
        rec = Path(recording)
        if not (rec.is_dir() or (rec.suffix == ".mcap" and rec.is_file())):
            raise OptiTacError(f"{recording}: no such recording (a directory, or an .mcap file)")
    config = load_board_config(board, overrides=dict(settings or {}), overrides_from="settings")
    chosen = config.sensors[0] if sensor is None else next((s for s in config.sensors if s.sensor.id == sensor),
                                                           None)
    if chosen is None:
        ids = ", ".join(str(s.sensor.id) for s in config.sensors)
        raise ConfigError(f"board {board}: no sensor with id {sensor} (its sensors: {ids})")
    cal_path = Path(cal) if cal is not None else None
    if cal_path is not None and not cal_path.is_file():
        raise OptiTacError(f"{cal_path}: no such calibration bundle")
    stack = ExitStack()
    try:
        return _open(config, chosen, cal_path, recording, stack, bool(arrays))
    except BaseException:
        stack.close()
        raise


def _open(config: BoardConfig, chosen: BoardSensor, cal_path: Path | None, recording: str | os.PathLike[str] | None,
          stack: ExitStack, arrays: bool) -> Sensor:
    """The LED ring, the camera (or the recording) and the bundle of ``chosen``, closed with ``stack``."""
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.service.bundles import obtain_bundles
    from optitac_edge.service.wiring import open_board_camera, open_led

    led = open_led(config)
    stack.callback(led.close)
    led.set_brightness(config.led.brightness)
    camera_name = chosen.sensor.camera
    camera: Camera
    if recording is not None:  # as fast as it is read, each frame at its recorded time
        from optitac_edge.io.cameras.recording import RecordingCamera

        camera = stack.enter_context(RecordingCamera(Path(recording)))
    else:
        camera = stack.enter_context(open_board_camera(config, camera_name))
    if cal_path is not None:
        bundle = chosen.check_bundle(load_bundle(cal_path), cal_path)
        t = bundle.fibers
        if (t.height, t.width) != tuple(camera.frame_shape[:2]):
            raise OptiTacError(f"{cal_path}: calibrated on {t.width}x{t.height} frames, the camera gives "
                               f"{camera.frame_shape[1]}x{camera.frame_shape[0]}: calibrate this sensor again "
                               "or give its own bundle")
    else:
        found = obtain_bundles(config, camera_name, camera, None, led)
        bundle = next(b.bundle for b in found if b.sensor.sensor.id == chosen.sensor.id)
    return Sensor(config, chosen, camera, bundle, stack, arrays)
