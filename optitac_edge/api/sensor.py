"""The public Python API: open a sensor, read its contacts frame by frame, tare it, close it.

Everything a script or a ROS 2 node needs, and the names the project promises to keep (``optitac_edge``
exports them; docs/api.md has examples). The modules below it are internal and may change.

    import optitac_edge as ot

    with ot.open_sensor("sim") as sensor:           # the built-in simulated sensor
        for reading in sensor.readings(duration_s=2.0):
            for c in reading.contacts:
                print(c.id, c.x_mm, c.y_mm, c.vx_mm_s, c.vy_mm_s, c.sliding)

A :class:`Sensor` reads its camera in the calling thread: each :meth:`Sensor.read` takes the next frame and
returns what it gave (a :class:`Reading`). It does not open the link to the MCU nor publish anything (that
is ``optitac-edge run``). The first frames of every session are the baseline (``baseline_ready`` False,
no contacts); a sensor without a calibration bundle calibrates its fiber map from its first rest frames,
as ``run`` does.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator, Mapping
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from optitac_edge.errors import ConfigError, OptiTacError

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.config import BoardConfig, BoardSensor
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.frame_result import FrameResult
    from optitac_edge.io.cameras.base import Camera


@dataclass(frozen=True, slots=True)
class Contact:
    """One contact of one frame (a copy: it stays as it is).

    Attributes
    ----------
    id : int
        1…255, the same from the contact's touch to its release.
    touch_frame : int
        The frame it touched in (``touch_frame == Reading.frame``: a new contact).
    x_mm, y_mm : float
        Centroid in the sensor frame, mm.
    major_mm, minor_mm, angle_deg : float
        FWHM widths along the principal axes, mm, and the major axis from +x, degrees (−90, 90].
    strength : float
        Darkening × area (the paper's m00).
    depth_mm, force_n : float
        Indentation depth (mm) and normal force (N); NaN without a depth / force calibration.
    shape : str
        The shape class (``""`` without a shape calibration).
    confidence : float
        The shape's posterior probability, 0…1 (NaN without a shape calibration).
    vx_mm_s, vy_mm_s : float
        Velocity, mm/s, from the last 5 centroids (NaN in the frame it touched in).
    sliding : bool
        It slides (gross motion above its own noise) rather than being held.
    slide_frame : int
        The frame its slide was found in; −1 while held.
    """

    id: int
    touch_frame: int
    x_mm: float
    y_mm: float
    major_mm: float
    minor_mm: float
    angle_deg: float
    strength: float
    depth_mm: float
    force_n: float
    shape: str
    confidence: float
    vx_mm_s: float
    vy_mm_s: float
    sliding: bool
    slide_frame: int

    @classmethod
    def of(cls, c: ContactEstimate) -> Contact:
        """A copy of a pipeline's contact."""
        return cls(int(c.contact_id), int(c.touch_frame), float(c.x_mm), float(c.y_mm), float(c.major_mm),
                   float(c.minor_mm), float(c.angle_deg), float(c.strength), float(c.depth_mm), float(c.force_n),
                   c.shape or "", float(c.confidence), float(c.vx_mm_s), float(c.vy_mm_s), bool(c.sliding),
                   int(c.slide_frame))


@dataclass(frozen=True, slots=True)
class Reading:
    """What one camera frame gave one sensor (a copy).

    Attributes
    ----------
    sensor_id : int
    frame : int
        The sensor's frame counter, from 0.
    t_ns : int
        The frame's capture time, CLOCK_MONOTONIC ns (a recording's own times when replaying one).
    contacts : tuple of Contact
        Every contact, strongest first (0…4).
    released : tuple of int
        Ids of the contacts gone since the previous frame.
    vibration : float
        The fibers' energy above 20 Hz in units of their noise (about 1 at rest); NaN while it is learned.
    vibrating : bool
        The vibration is above its quiet level.
    baseline_ready : bool
        False during the first frames of a session (and after a tare), while the rest light is taken.
    saturated : bool
        Some fiber was at full scale.
    """

    sensor_id: int
    frame: int
    t_ns: int
    contacts: tuple[Contact, ...]
    released: tuple[int, ...]
    vibration: float
    vibrating: bool
    baseline_ready: bool
    saturated: bool

    @classmethod
    def of(cls, sensor_id: int, result: FrameResult) -> Reading:
        """A copy of a pipeline's frame result."""
        return cls(sensor_id, int(result.frame), int(result.t_ns), tuple(Contact.of(c) for c in result.touching()),
                   tuple(cid for cid, _ in result.releases()), float(result.vibration), bool(result.vibrating),
                   bool(result.baseline_ready), bool(result.saturated))


@dataclass(frozen=True, slots=True)
class Status:
    """How a sensor is doing.

    Attributes
    ----------
    sensor_id : int
    name : str
    frames : int
        Frames processed.
    contact_frames : int
        Frames with a contact.
    skipped : int
        Frames not processed: dark, saturated or not of the camera's shape (counted, never trusted).
    baseline_ready : bool
    calibration_id : str
        The bundle's id.
    compiled : bool
        The compiled kernel runs the frames (else the numpy pipeline).
    fps : float
        The camera's configured frame rate.
    dropped : int
        Frames the camera lost before they were read (a loop slower than the camera; gaps in its sequence).
    """

    sensor_id: int
    name: str
    frames: int
    contact_frames: int
    skipped: int
    baseline_ready: bool
    calibration_id: str
    compiled: bool
    fps: float
    dropped: int = 0


class Sensor:
    """One sensor of a board, open: its camera (and LED ring) and its pipeline. Use :func:`open_sensor`.

    A context manager; :meth:`close` is idempotent. Not thread-safe: read it from one thread.
    """

    def __init__(self, board: BoardConfig, sensor: BoardSensor, camera: Camera, bundle: CalibrationBundle,
                 stack: ExitStack) -> None:
        from optitac_edge.core.pipeline import Pipeline

        self._board, self._sensor, self._camera, self._stack = board, sensor, camera, stack
        self._pipeline = Pipeline(bundle, fps=camera.fps)
        self._frames = self._contacts = self._skipped = 0
        self._closed = False
        #: The board config's id of this sensor (what the MCU hears).
        self.sensor_id: int = int(sensor.sensor.id)
        #: Its name in the board config.
        self.name: str = str(sensor.sensor.name)

    def read(self, timeout_s: float = 1.0) -> Reading | None:
        """The next frame's reading; None when no frame came within ``timeout_s`` or a recording ended.

        A frame the check refuses (dark, saturated, of another shape) is counted in :meth:`status` and the
        next one is read, within the same timeout.

        Raises
        ------
        OptiTacError
            The sensor is closed, or the camera failed (one line naming it).
        """
        from optitac_edge.core.frame_engine import Skip

        if self._closed:
            raise OptiTacError(f"sensor {self.sensor_id} {self.name!r} is closed")
        deadline = time.monotonic() + _seconds(timeout_s, "timeout_s")
        while True:
            captured = self._camera.read(max(deadline - time.monotonic(), 0.0))
            if captured is None:
                return None
            result = self._pipeline.process(captured.frame, captured.t_ns)
            if isinstance(result, Skip):
                self._skipped += 1
                if time.monotonic() >= deadline:
                    return None
                continue
            self._frames += 1
            self._contacts += result.n_contacts > 0
            return Reading.of(self.sensor_id, result)

    def readings(self, duration_s: float | None = None, timeout_s: float = 1.0) -> Iterator[Reading]:
        """Every frame's reading, for ``duration_s`` of frame time (None: until the camera or recording ends
        or ``timeout_s`` passes without a frame)."""
        if duration_s is not None:
            _seconds(duration_s, "duration_s")
        _seconds(timeout_s, "timeout_s")
        end: int | None = None
        while True:
            reading = self.read(timeout_s)
            if reading is None:
                return
            if duration_s is not None:
                end = reading.t_ns + round(duration_s * 1e9) if end is None else end
                if reading.t_ns >= end:
                    return
            yield reading

    def __iter__(self) -> Iterator[Reading]:
        return self.readings()

    def tare(self) -> None:
        """Take the rest light again from the next frames (nothing may touch the skin meanwhile)."""
        self._pipeline.reset_baseline()

    def status(self) -> Status:
        """The sensor's counters and state now."""
        return Status(self.sensor_id, self.name, self._frames, self._contacts, self._skipped,
                      bool(self._pipeline.baseline_ready), self._pipeline.bundle.calibration_id,
                      self._pipeline.compiled, float(self._camera.fps), int(self._camera.frames_dropped))

    def close(self) -> None:
        """Close the camera and the LED ring (idempotent)."""
        self._closed = True
        self._stack.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _seconds(value: object, name: str) -> float:
    """``value`` as a finite number of seconds >= 0, or one line naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise OptiTacError(f"{name} must be a finite number of seconds >= 0, got {value!r}")
    return float(value)


def open_sensor(board: str | os.PathLike[str] = "sim", *, sensor: int | None = None,
                cal: str | os.PathLike[str] | None = None, recording: str | os.PathLike[str] | None = None,
                settings: Mapping[str, Any] | None = None) -> Sensor:
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

    Raises
    ------
    OptiTacError
        A board, sensor, bundle, camera or recording that cannot be opened: one line naming it.
    """
    from optitac_edge.config import load_board_config

    if not isinstance(board, (str, os.PathLike)) or isinstance(board, bytes):
        raise OptiTacError(f"board must be a board name or a config file's path, got {board!r}")
    if settings is not None and not isinstance(settings, Mapping):
        raise OptiTacError(f"settings must be a mapping of 'section.key' to values, got {type(settings).__name__}")
    if sensor is not None and (isinstance(sensor, bool) or not isinstance(sensor, int)):
        raise OptiTacError(f"sensor must be a sensor's id (an integer), got {sensor!r}")
    if recording is not None:
        rec = Path(recording)
        if not (rec.is_dir() or (rec.suffix == ".mcap" and rec.is_file())):
            raise OptiTacError(f"{recording}: no such recording (a directory, or an .mcap file)")
    config = load_board_config(board, overrides=dict(settings or {}))
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
        return _open(config, chosen, cal_path, recording, stack)
    except BaseException:
        stack.close()
        raise


def _open(config: BoardConfig, chosen: BoardSensor, cal_path: Path | None, recording: str | os.PathLike[str] | None,
          stack: ExitStack) -> Sensor:
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
    return Sensor(config, chosen, camera, bundle, stack)
