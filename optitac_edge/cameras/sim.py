"""The built-in simulated sensor as a live camera: rest, then random presses."""

from __future__ import annotations

import math
import time

import numpy as np

from .base import Camera, CapturedFrame

_SHAPES = ("edge", "circle", "square", "ellipse", "triangle")


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
        self._press: dict[str, float] | None = None
        self._start = self._end = rest_frames

    def _new_press(self, start: int) -> None:
        rng, fps = self._rng, self._fps
        shape = str(rng.choice(_SHAPES))
        size = float(rng.uniform(1.5, 2.5) if shape == "edge" else rng.uniform(3.0, 9.0))
        reach = max(self._radius * 0.8 - (6.0 if shape == "edge" else size / 2.0) - 1.0, 0.0)
        r, phi = reach * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        gap, ramp, hold = (int(rng.uniform(a, b) * fps) + 1 for a, b in ((0.3, 1.0), (0.1, 0.25), (0.4, 1.5)))
        self._press = {"shape": shape, "x": r * math.cos(phi), "y": r * math.sin(phi),
                       "angle": float(rng.uniform(-90, 90)), "size": size,
                       "depth": float(rng.uniform(1.5, 3.5)), "ramp": ramp, "hold": hold,
                       "t0": start + gap}
        self._start = start
        self._end = start + gap + 2 * ramp + hold

    def at(self, frame: int) -> dict[str, float] | None:
        """The press at ``frame`` (shape, pose, size, current depth), or None."""
        if frame < self._rest:
            return None
        if self._press is None or frame >= self._end:
            self._new_press(max(frame, self._end))
        p = self._press
        assert p is not None
        t = frame - p["t0"]
        ramp, hold = p["ramp"], p["hold"]
        if t < 0 or t >= 2 * ramp + hold:
            return None
        frac = min(t / ramp, 1.0, (2 * ramp + hold - t) / ramp)
        return {**p, "depth": p["depth"] * frac} if frac > 0.05 else None


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
    realtime : bool
        Sleep to keep ``fps``; otherwise frames come as fast as rendered.
    """

    def __init__(self, fps: float = 60.0, width: int = 640, height: int = 480, rgb: bool = False,
                 rotation_deg: float = 0.0, mirror: bool = False, seed: int = 0, rest_frames: int = 10,
                 realtime: bool = True) -> None:
        super().__init__()
        from ..sim import CameraOptics, Indenter, SimulatedSensor

        self._indenter_cls = Indenter
        self.sensor = SimulatedSensor(
            optics=CameraOptics(width=width, height=height, rgb=rgb, rotation_deg=rotation_deg, mirror=mirror),
            seed=seed,
        )
        self.pixel_format = "rgb" if rgb else "gray"
        self.height, self.width, self.fps = height, width, float(fps)
        self.rest_frames = rest_frames
        self._program = PressProgram(self.fps, rest_frames, seed, self.sensor.layout.radius_mm)
        self._realtime = realtime
        self._seq = 0
        self._t0_ns = time.monotonic_ns()
        #: Ground truth of the last frame delivered (None when no contact).
        self.truth: dict[str, float] | None = None

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        frame_ns = self._t0_ns + int(self._seq * 1e9 / self.fps)
        if self._realtime:
            now = time.monotonic_ns()
            if frame_ns > now:
                time.sleep((frame_ns - now) / 1e9)
            elif now - frame_ns > 1_000_000_000:  # fell far behind (e.g. suspended): resynchronise
                self._t0_ns = now - int(self._seq * 1e9 / self.fps)
                frame_ns = now
        press = self._program.at(self._seq)
        indenters = () if press is None else (self._indenter_cls(
            shape=press["shape"], x_mm=press["x"], y_mm=press["y"], angle_deg=press["angle"],
            size_mm=press["size"], depth_mm=press["depth"]),)
        frame = self.sensor.frame(indenters)
        self.truth = press
        self._seq += 1
        return CapturedFrame(frame, frame_ns if self._realtime else time.monotonic_ns(), self._seq)
