"""Simulated recordings of moving presses, with their true velocity and motion per frame, at 240 fps.

``slide``    a 5 mm circle pressed (ramped in over 0.1 s), held 0.5 s, slid in a straight line at each of
             :data:`SLIDE_SPEEDS_MM_S` (a different direction each, :data:`SLIDE_DIRECTIONS_DEG` in turn)
             over up to 8 mm through the array's centre, held 0.5 s and lifted; then one press slid 15 mm
             along +x and 15 mm back at 20 mm/s without stopping (30 mm under one contact).
``vibrate``  a 5 mm circle pressed and held 0.5 s, shaken by :data:`VIBRATE_AMPLITUDE_MM` at each of
             :data:`VIBRATE_HZ` for 0.5 s (along x, y and z in turn), held quiet 0.5 s and lifted.
``hold``     static presses for the false-slip count: each held :data:`HOLD_S` s at a random place, its
             depth growing and shrinking slowly (±0.5 mm over seconds), with the LEDs warming up and the
             fibers drifting over the recording (as the ``drift`` scenario); default 10 minutes.

``truth.csv`` carries :data:`~optitac_edge.io.recording.MOTION_COLUMNS`: the press's velocity in the
sensor frame (mm/s; a shake along z has none) and ``pressing`` (pressed in or lifted over 0.1 s),
``held``, ``sliding`` or ``vibrating``. A press's
depth jitter (the session's ``depth_jitter``) is drawn once per press, not per frame, as a rig's error
in reaching a depth would be.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from optitac_edge.core.layout import FiberLayout
from optitac_edge.sim.skin import Indenter

MOTION_SCENARIOS: tuple[str, ...] = ("slide", "vibrate", "hold")
#: Frame rate of the motion scenarios, frames/s.
MOTION_FPS = 240.0
#: Contact-free frames a motion recording starts with (the baseline), and between presses.
MOTION_REST_FRAMES = 60
GAP_FRAMES = 30
SLIDE_SPEEDS_MM_S: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
SLIDE_DIRECTIONS_DEG: tuple[float, ...] = (0.0, 72.0, 144.0, 216.0, 288.0, 36.0)
VIBRATE_HZ: tuple[float, ...] = (30.0, 45.0, 60.0, 80.0, 100.0)
VIBRATE_AMPLITUDE_MM = 0.05
HOLD_S = 20.0
DEPTH_MM = 2.5
RAMP_FRAMES = 24  # 0.1 s pressing in and lifting out
QUIET_FRAMES = 120  # 0.5 s


@dataclass(frozen=True)
class MotionFrame:
    """One frame of a motion scenario: the indenter (None: contact-free), its press and its true motion."""

    indenter: Indenter | None
    press: int = -1
    vx_mm_s: float = math.nan
    vy_mm_s: float = math.nan
    motion: str = ""


def _rest(n: int) -> list[MotionFrame]:
    return [MotionFrame(None)] * n


def _circle(x: float, y: float, depth: float) -> Indenter:
    return Indenter(shape="circle", x_mm=x, y_mm=y, size_mm=5.0, depth_mm=depth)


def _press(press: int, x: float, y: float, held: int, depth: float = DEPTH_MM) -> Iterator[MotionFrame]:
    """Pressed in over RAMP_FRAMES, then ``held`` frames at ``depth``."""
    for k in range(RAMP_FRAMES):
        yield MotionFrame(_circle(x, y, depth * (k + 1) / RAMP_FRAMES), press, 0.0, 0.0, "pressing")
    for _ in range(held):
        yield MotionFrame(_circle(x, y, depth), press, 0.0, 0.0, "held")


def _lift(press: int, x: float, y: float, depth: float = DEPTH_MM) -> Iterator[MotionFrame]:
    for k in range(RAMP_FRAMES - 1, 0, -1):
        yield MotionFrame(_circle(x, y, depth * k / RAMP_FRAMES), press, 0.0, 0.0, "pressing")


def _slide(press: int, start: tuple[float, float], v: tuple[float, float], n: int) -> Iterator[MotionFrame]:
    """``n`` frames moving from ``start`` at ``v`` (mm/s): the first is one frame period along."""
    for k in range(1, n + 1):
        t = k / MOTION_FPS
        yield MotionFrame(_circle(start[0] + v[0] * t, start[1] + v[1] * t, DEPTH_MM), press, v[0], v[1], "sliding")


def _slides(radius_mm: float) -> list[MotionFrame]:
    out = _rest(MOTION_REST_FRAMES)
    for k, speed in enumerate(SLIDE_SPEEDS_MM_S):
        theta = math.radians(SLIDE_DIRECTIONS_DEG[k % len(SLIDE_DIRECTIONS_DEG)])
        length = min(max(speed * 1.0, 2.0), 8.0, radius_mm)
        n = max(round(length / speed * MOTION_FPS), 1)
        u = (math.cos(theta), math.sin(theta))
        start = (-u[0] * length / 2, -u[1] * length / 2)
        end = (start[0] + u[0] * speed * n / MOTION_FPS, start[1] + u[1] * speed * n / MOTION_FPS)
        out += _press(k, *start, QUIET_FRAMES)
        out += _slide(k, start, (speed * u[0], speed * u[1]), n)
        out += [MotionFrame(_circle(*end, DEPTH_MM), k, 0.0, 0.0, "held")] * QUIET_FRAMES
        out += _lift(k, *end)
        out += _rest(GAP_FRAMES)
    k = len(SLIDE_SPEEDS_MM_S)  # 30 mm under one contact: 15 mm out and back at 20 mm/s
    n = round(15.0 / 20.0 * MOTION_FPS)
    out += _press(k, -7.5, 0.0, QUIET_FRAMES)
    out += _slide(k, (-7.5, 0.0), (20.0, 0.0), n)
    out += _slide(k, (-7.5 + 20.0 * n / MOTION_FPS, 0.0), (-20.0, 0.0), n)
    out += [MotionFrame(_circle(-7.5, 0.0, DEPTH_MM), k, 0.0, 0.0, "held")] * QUIET_FRAMES
    out += _lift(k, -7.5, 0.0)
    return out + _rest(GAP_FRAMES)


def _shakes() -> list[MotionFrame]:
    out = _rest(MOTION_REST_FRAMES)
    for k, (hz, axis) in enumerate((hz, axis) for hz in VIBRATE_HZ for axis in "xyz"):
        x0, y0 = (1.0, -0.5)
        out += _press(k, x0, y0, QUIET_FRAMES)
        w, a = 2 * math.pi * hz, VIBRATE_AMPLITUDE_MM
        for j in range(QUIET_FRAMES):
            t = (j + 1) / MOTION_FPS
            d, v = a * math.sin(w * t), a * w * math.cos(w * t)
            ind = _circle(x0 + d * (axis == "x"), y0 + d * (axis == "y"), DEPTH_MM + d * (axis == "z"))
            out.append(MotionFrame(ind, k, v * (axis == "x"), v * (axis == "y"), "vibrating"))
        out += [MotionFrame(_circle(x0, y0, DEPTH_MM), k, 0.0, 0.0, "held")] * QUIET_FRAMES
        out += _lift(k, x0, y0)
        out += _rest(GAP_FRAMES)
    return out


def _holds(rng: np.random.Generator, radius_mm: float, n_frames: int) -> list[MotionFrame]:
    out = _rest(MOTION_REST_FRAMES)
    hold = round(HOLD_S * MOTION_FPS)
    k = 0
    while len(out) < n_frames:
        r, t = (radius_mm - 4.0) * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        x, y = r * math.cos(t), r * math.sin(t)
        period = rng.uniform(3.0, 8.0) * MOTION_FPS  # the depth breathes by +-0.5 mm over seconds
        out += _press(k, x, y, 0)
        for j in range(hold):
            depth = DEPTH_MM + 0.5 * math.sin(2 * math.pi * j / period)
            out.append(MotionFrame(_circle(x, y, depth), k, 0.0, 0.0, "held"))
        out += _lift(k, x, y, DEPTH_MM + 0.5 * math.sin(2 * math.pi * hold / period))
        out += _rest(GAP_FRAMES)
        k += 1
    return out[:n_frames]


def motion_schedule(name: str, seed: int = 0, frames: int | None = None,
                    layout: FiberLayout | None = None) -> list[MotionFrame]:
    """Every frame of motion scenario ``name`` (see the module's description).

    ``frames`` sets the length of ``hold`` (default 10 minutes) and truncates the others.

    Raises
    ------
    ValueError
        An unknown scenario, or ``frames`` shorter than the rest frames.
    """
    from optitac_edge.core.layout import hex_layout

    if name not in MOTION_SCENARIOS:
        raise ValueError(f"unknown motion scenario {name!r}; expected one of {MOTION_SCENARIOS}")
    if frames is not None and frames < MOTION_REST_FRAMES:
        raise ValueError(f"a motion recording needs at least {MOTION_REST_FRAMES} frames")
    radius = (hex_layout() if layout is None else layout).radius_mm
    if name == "slide":
        plan = _slides(radius)
    elif name == "vibrate":
        plan = _shakes()
    else:
        plan = _holds(np.random.default_rng([seed, 29]), radius, frames or round(600 * MOTION_FPS))
    return plan if frames is None else (plan + _rest(frames))[:frames]


def press_depth_factors(plan: list[MotionFrame], jitter: float, seed: int) -> dict[int, float]:
    """Each press's real depth as a factor of the commanded one: ``1 + jitter * z``, ``z`` a standard normal
    clipped at 2.5 (the session's depth jitter, drawn once per press)."""
    rng = np.random.default_rng([seed, 4, 29])
    presses = sorted({f.press for f in plan if f.press >= 0})
    z = np.clip(rng.standard_normal(len(presses)), -2.5, 2.5)
    return {p: 1.0 + jitter * float(zi) for p, zi in zip(presses, z)}


def real_indenter(frame: MotionFrame, factors: dict[int, float]) -> Indenter | None:
    """The frame's indenter at its press's real depth."""
    if frame.indenter is None:
        return None
    return replace(frame.indenter, depth_mm=frame.indenter.depth_mm * factors.get(frame.press, 1.0))


#: The motion scenarios the live simulated camera plays (``[camera.options] scenario``); ``hold`` is a recording's.
LIVE_MOTION_SCENARIOS: tuple[str, ...] = ("slide", "vibrate")


class MotionProgram:
    """A motion scenario pressing a live simulated camera, over and over (a camera's ``PressSource``).

    After the camera's ``rest_frames``, frame ``k`` shows the scenario at time ``(k - rest_frames) / fps``
    (its frame at :data:`MOTION_FPS` nearest that time), so the presses slide at their speeds whatever the
    camera's rate; at the end it starts again.

    Parameters
    ----------
    name : str
        One of :data:`LIVE_MOTION_SCENARIOS`.
    fps : float
        The camera's frame rate, frames/s.
    rest_frames : int
        Contact-free frames first (the baseline).
    layout : FiberLayout, optional
        The array (its radius bounds the slides); default the paper's.

    Raises
    ------
    ValueError
        An unknown scenario, or a rate that is not positive.
    """

    def __init__(self, name: str, fps: float, rest_frames: int, layout: FiberLayout | None = None) -> None:
        if name not in LIVE_MOTION_SCENARIOS:
            raise ValueError(f"unknown live scenario {name!r}; expected one of {', '.join(LIVE_MOTION_SCENARIOS)}")
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps!r}")
        self._plan = motion_schedule(name, layout=layout)
        self._fps, self._rest = float(fps), int(rest_frames)

    def at(self, frame: int) -> Indenter | None:
        """The indenter at camera frame ``frame``, or None."""
        if frame < self._rest:
            return None
        k = round((frame - self._rest) * MOTION_FPS / self._fps)
        return self._plan[k % len(self._plan)].indenter
