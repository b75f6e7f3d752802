"""The built-in simulated sensor as a live camera: rest, then random presses."""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.core.region import Region
from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.cameras.frame_ring import check_queue_frames
from optitac_edge.io.clock import Clock
from optitac_edge.io.layout_csv import load_layout_csv
from optitac_edge.io.threads import NamedThread
from optitac_edge.sim.arrays import optics_for, skin_for
from optitac_edge.sim.drift import SessionDrift
from optitac_edge.sim.motion_scenarios import LIVE_MOTION_SCENARIOS, MotionProgram
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.patches import PatchFrames
from optitac_edge.sim.physics import physics as physics_named
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

if TYPE_CHECKING:
    from optitac_edge.io.cameras.section import CameraConfig
    from optitac_edge.io.device import BoardView

_SHAPES = ("edge", "circle", "square", "ellipse", "triangle")
#: A realtime simulated camera renders this much ahead of the frames' times at least, s.
RENDER_AHEAD_S = 0.1


class PressSource(Protocol):
    """What presses the simulated skin: the indenter (shape, pose, size, current depth) at a frame, or None."""

    def at(self, frame: int) -> Indenter | None: ...


@dataclass(frozen=True)
class _Press:
    """One press of the program: the indenter at full depth and its timing (frames)."""

    indenter: Indenter
    t0: int
    ramp: int
    hold: int


class PressProgram:
    """A random sequence of presses over time, as a pure function of the frame number.

    After ``rest_frames`` contact-free frames, repeats: a gap, a ramp down to
    depth, a hold, a ramp back up. Positions keep the indenter on the array.
    """

    def __init__(self, fps: float, rest_frames: int, seed: int, array_radius_mm: float) -> None:
        self._rng = np.random.default_rng(seed)
        self._fps = fps
        self._rest = rest_frames
        self._radius = array_radius_mm
        self._press: _Press | None = None
        self._start = self._end = rest_frames

    def _new_press(self, start: int) -> _Press:
        rng, fps = self._rng, self._fps
        shape = str(rng.choice(_SHAPES))
        size = float(rng.uniform(1.5, 2.5) if shape == "edge" else rng.uniform(3.0, 9.0))
        reach = max(self._radius * 0.8 - (6.0 if shape == "edge" else size / 2.0) - 1.0, 0.0)
        r, phi = reach * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        gap, ramp, hold = (int(rng.uniform(a, b) * fps) + 1 for a, b in ((0.3, 1.0), (0.1, 0.25), (0.4, 1.5)))
        angle = float(rng.uniform(-90, 90))
        depth = float(rng.uniform(1.5, 3.5))
        indenter = Indenter(shape=shape, x_mm=r * math.cos(phi), y_mm=r * math.sin(phi), angle_deg=angle,
                            size_mm=size, depth_mm=depth)
        self._start = start
        self._end = start + gap + 2 * ramp + hold
        return _Press(indenter, start + gap, ramp, hold)

    def at(self, frame: int) -> Indenter | None:
        """The indenter at ``frame`` (shape, pose, size, current depth), or None."""
        if frame < self._rest:
            return None
        if self._press is None or frame >= self._end:
            self._press = self._new_press(max(frame, self._end))
        p = self._press
        t = frame - p.t0
        if t < 0 or t >= 2 * p.ramp + p.hold:
            return None
        frac = min(t / p.ramp, 1.0, (2 * p.ramp + p.hold - t) / p.ramp)
        return replace(p.indenter, depth_mm=p.indenter.depth_mm * frac) if frac > 0.05 else None


def _live_program(scenario: str, fps: float, rest_frames: int, seed: int, layout: FiberLayout) -> PressSource:
    """What presses a live simulated camera: ``presses`` (random, :class:`PressProgram`) or a motion scenario
    played over and over (``slide``, ``vibrate``: :class:`~optitac_edge.sim.motion_scenarios.MotionProgram`)."""
    if scenario == "presses":
        return PressProgram(fps, rest_frames, seed, layout.radius_mm)
    if scenario in LIVE_MOTION_SCENARIOS:
        return MotionProgram(scenario, fps, rest_frames, layout)
    raise CameraError(f"simulated camera: unknown scenario {scenario!r} (presses, "
                      f"{', '.join(LIVE_MOTION_SCENARIOS)})")


class SimCamera(Camera):
    """The built-in simulated sensor (the default camera).

    Parameters
    ----------
    fps : float
        Frame rate; frames are paced in real time when ``realtime``.
    width, height : int
        Image size.
    rgb : bool
        Deliver (H, W, 3) RGB frames instead of gray.
    rotation_deg, mirror
        How the array appears in the image (see docs/formats.md).
    seed : int
        Seed of the noise and of the press program.
    rest_frames : int
        Contact-free frames at the start (for calibration and baseline).
    queue_frames : int
        Realtime: frames that may wait for the reader, as in a camera's frame
        ring (:mod:`optitac_edge.io.cameras.frame_ring`); a frame is dropped once
        ``queue_frames`` newer ones are due. 1 = the latest frame only.
    realtime : bool
        Deliver frame ``k`` at ``k / fps`` after the start, stamped with that time,
        rendered ahead by a thread (the simulator's rendering, ~1 ms a frame, is
        the sensor's exposure and readout, not part of the loop being measured);
        otherwise frames come as fast as rendered, stamped when rendered.
    program : PressSource, optional
        What presses the skin at each frame (default: random presses,
        :class:`PressProgram`); the simulated rig drives it instead.
    regions : sequence of (x, y, width, height), optional
        Several fiber patches in one frame, one per region (a board whose
        sensors share this camera, :class:`~optitac_edge.sim.patches.PatchFrames`):
        patch ``k`` is its own simulated sensor with its own random presses
        (``program`` then presses patch 0). Default: one sensor filling the frame.
    clock : Clock, optional
        Not realtime: frame ``k`` is due at ``k / fps`` on this clock; a read
        sleeps on it until then and stamps the frame with that time, in the
        calling thread. With a :class:`~optitac_edge.io.clock.VirtualClock`
        the frames, their times and everything computed from them are the same
        on any machine.
    physics : str
        The skin's simulated physics (:data:`~optitac_edge.sim.physics.PHYSICS`, default ``default``).
    day : int
        The session's drift (:meth:`~optitac_edge.sim.drift.SessionDrift.for_day`, default 0: none).
    layout : str
        A layout CSV (docs/formats.md): the simulated array (default '': the paper's 217 fibers at 1.5 mm);
        its skin and end faces scale with its pitch (:mod:`~optitac_edge.sim.arrays`). A board sets it in
        ``[camera.options] layout``.
    scenario : str
        What presses the skin when ``program`` is not given: ``presses`` (default: random presses), or a motion
        scenario played over and over, ``slide`` (a held press slid at 2 to 100 mm/s, then 30 mm out and back)
        or ``vibrate`` (:mod:`~optitac_edge.sim.motion_scenarios`), to try slip and vibration live. A board sets
        it in ``[camera.options] scenario`` (``OPTITAC_CAMERA_OPTIONS_SCENARIO=slide``).
    """

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """``[camera]`` fps, width, height, pixel_format, queue_frames; one fiber patch in each sensor's region."""
        c = section
        out: dict[str, Any] = {"fps": c.fps, "width": c.width, "height": c.height, "rgb": c.pixel_format == "rgb",
                               "rest_frames": max(board.rest_frames, 10), "queue_frames": c.queue_frames}
        if any(board.regions):
            out["regions"] = board.regions
        return out

    def __init__(self, fps: float = 60.0, width: int = 640, height: int = 480, rgb: bool = False,  # noqa: PLR0913
                 rotation_deg: float = 0.0, mirror: bool = False, seed: int = 0, rest_frames: int = 10,
                 realtime: bool = True, queue_frames: int = 4, clock: Clock | None = None,
                 program: PressSource | None = None,
                 regions: Sequence[tuple[int, int, int, int]] | None = None, physics: str = "default",
                 day: int = 0, layout: str = "", scenario: str = "presses") -> None:
        super().__init__()
        if realtime and clock is not None:
            raise ValueError("a simulated camera paced on a clock is not realtime (realtime=False)")
        check_queue_frames(queue_frames)

        world = physics_named(physics)
        array = load_layout_csv(layout) if layout else hex_layout()
        self.sensor = SimulatedSensor(
            layout=array,
            optics=optics_for(array, CameraOptics(width=width, height=height, rgb=rgb, rotation_deg=rotation_deg,
                                                  mirror=mirror)),
            skin=skin_for(array, world.skin), seed=seed, drift=SessionDrift.for_day(day, scale=world.day_drift),
            fps=fps,
        )
        self.pixel_format = "rgb" if rgb else "gray"
        self.height, self.width, self.fps = height, width, float(fps)
        self.rest_frames = rest_frames
        self._program: PressSource = program or _live_program(scenario, self.fps, rest_frames, seed,
                                                              self.sensor.layout)
        self.patches: PatchFrames | None = None
        self._patch_programs: list[PressSource] = []
        if regions:
            self.patches = PatchFrames([Region(*r) for r in regions], width, height,
                                       optics=CameraOptics(width=width, height=height, rgb=rgb), seed=seed)
            self._patch_programs = [self._program] + [
                PressProgram(self.fps, rest_frames, seed + 7919 * k, s.layout.radius_mm)
                for k, s in enumerate(self.patches.sensors[1:], start=1)]
        self._realtime = realtime
        self._seq = 0
        # realtime: frames rendered ahead by a thread (at most ``_ahead`` waiting): 0.1 s of frames at least, so a
        # render that takes long (a new press's skin field: up to 29 ms measured at 240 fps) is not a dropped frame
        self._queue_frames = queue_frames
        self._ahead = max(3, queue_frames + 1, math.ceil(RENDER_AHEAD_S * fps))
        self._ready: deque[tuple[int, np.ndarray, Indenter | None]] = deque()
        self._cond = threading.Condition()
        self._stop_render = threading.Event()
        self._render_thread: threading.Thread | None = None
        self._clock = clock
        self._t0_ns = time.monotonic_ns() if clock is None else clock.monotonic_ns()
        #: Ground truth of the last frame delivered (None when no contact).
        self.truth: Indenter | None = None

    def _render(self, seq: int) -> tuple[np.ndarray, Indenter | None]:
        if self.patches is not None:
            presses = [program.at(seq) for program in self._patch_programs]
            return self.patches.frame([() if p is None else (p,) for p in presses]), presses[0]
        press = self._program.at(seq)
        return self.sensor.frame(() if press is None else (press,)), press

    @property
    def program(self) -> PressSource:
        """What presses the skin (of the first patch)."""
        return self._program

    def press_with(self, program: PressSource) -> None:
        """From now on (the frames not yet rendered), ``program`` presses the skin (of the first patch)."""
        self._program = program
        if self._patch_programs:
            self._patch_programs[0] = program

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        if self._realtime:
            return self._read_paced(timeout_s)
        if self._clock is None:
            frame, press = self._render(self._seq)
            t_ns = time.monotonic_ns()
        else:  # paced on the clock: sleep until the frame is due, stamp it with that time
            t_ns = self._t0_ns + round(self._seq * 1e9 / self.fps)
            self._clock.sleep((t_ns - self._clock.monotonic_ns()) / 1e9)
            frame, press = self._render(self._seq)
        self.truth = press
        self._seq += 1
        return CapturedFrame(frame, t_ns, self._seq)

    # -- realtime: a render thread works ahead, frames are delivered at their time -----------

    def _render_loop(self) -> None:
        seq, period = 0, 1e9 / self.fps
        while not self._stop_render.is_set():
            with self._cond:
                while len(self._ready) >= self._ahead and not self._stop_render.is_set():
                    self._cond.wait(0.1)
                if self._stop_render.is_set():
                    return
                # a frame the reader would skip as overrun is not rendered (the sequence gap counts it)
                overdue = (time.monotonic_ns() - self._t0_ns) / period - self._queue_frames
                seq = max(seq, math.floor(overdue) + 1)
            frame, press = self._render(seq)
            with self._cond:
                self._ready.append((seq, frame, press))
                self._cond.notify_all()
            seq += 1

    def _read_paced(self, timeout_s: float) -> CapturedFrame:
        """The next frame at its time, like a camera: rendered ahead by a thread.

        The stream starts at the first read (its renderer starts there, so the
        time a sensor takes to open after its camera is not frames lost).
        Frame ``k`` is due at ``t0 + k / fps`` and stamped with that time. A
        frame is skipped once ``queue_frames`` newer ones are due, as a camera's
        ring drops its oldest frame (the gap in ``seq`` counts it as dropped);
        after a second behind (e.g. suspended) the clock resynchronises.
        """
        if self._render_thread is None:  # the stream starts here: frame k is due k periods after this read
            self._t0_ns = time.monotonic_ns()
            self._render_thread = NamedThread(target=self._render_loop, name="optitac-sim-render", daemon=True)
            self._render_thread.start()
        period = 1e9 / self.fps
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            with self._cond:
                while not self._ready:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise CameraError(f"simulated camera: no frame within {timeout_s:.3f} s")
                    self._cond.wait(min(left, 0.1))
                seq, frame, press = self._ready[0]
                now = time.monotonic_ns()
                frame_ns = self._t0_ns + int(seq * period)
                if now - frame_ns > 1_000_000_000:  # fell far behind: resynchronise
                    self._t0_ns = now - int(seq * period)
                    frame_ns = now
                elif now - frame_ns >= self._queue_frames * period and len(self._ready) > 1:  # overrun
                    self._ready.popleft()
                    self._cond.notify_all()
                    continue
                self._ready.popleft()
                self._cond.notify_all()
            if frame_ns > now:
                time.sleep((frame_ns - now) / 1e9)
            self.truth = press
            self._seq = seq + 1
            return CapturedFrame(frame, frame_ns, seq + 1)

    def _close_internal(self) -> None:
        self._stop_render.set()
        with self._cond:
            self._cond.notify_all()
        if self._render_thread is not None and self._render_thread is not threading.current_thread():
            self._render_thread.join(timeout=2.0)
