"""The compiled per-frame kernel (``kernel/frame_kernel.c``), wired to a pipeline's parts.

The kernel does steps 2 to 10 of :mod:`optitac_edge.core.pipeline` in one call per
frame, in C, with the GIL released: the fiber means (gray, RGB, YUV's Y plane),
the signal (relative, gain-compensated, dead fibers), the surface (factored or
dense), the truncation, the split into contacts and their moments and shape
features, and the baseline's tracking and raise test. It reads and writes the
same buffers as the numpy parts (the fiber means, signal, surface, baseline,
levels), so the numpy pipeline stays the readable reference and everything
reading those buffers (the live view, the bench) sees the same thing.

What stays in Python, per contact: the tracking of ids (:class:`ContactTracker`),
and a corrector other than the bundle's own (the ONNX shape backend). The
kernel applies the bundle's calibration models (centroid map, width, depth and
force, the numpy shape classifier) itself.

The kernel is built by ``pip install`` where a C compiler and Python's headers
exist (``setup.py``: an optional extension); nothing is compiled at run time or
on import. :func:`kernel_status` says whether it is here, and why not; the
service logs it at start. ``OPTITAC_EDGE_KERNEL=numpy`` runs the numpy pipeline
although the kernel is built.
"""

from __future__ import annotations

import math
import os
from importlib import import_module
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core import motion, vibration
from optitac_edge.core.baseline import BRIGHT_HOLD_S
from optitac_edge.core.frame_check import CHECK_REASONS, check_kernel_arrays
from optitac_edge.core.gain import LedGain
from optitac_edge.core.options import MAX_CONTACTS

if TYPE_CHECKING:
    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.corrections import ContactCorrector
    from optitac_edge.core.pipeline import Pipeline

#: The extension module's name.
MODULE = "optitac_edge.core._frame_kernel"
#: Set to ``numpy`` to run the numpy pipeline although the kernel is built (a comparison on the robot).
ENV = "OPTITAC_EDGE_KERNEL"

_loaded: ModuleType | None = None
_why_not = ""


def _load() -> ModuleType | None:
    global _loaded, _why_not
    if _loaded is None and not _why_not:
        try:
            _loaded = import_module(MODULE)
        except ImportError as exc:
            _why_not = f"not built ({exc}); pip install it where a C compiler and Python's headers exist"
    return _loaded


def _require() -> ModuleType:
    """The extension module, or ImportError saying why it is not here."""
    mod = _load()
    if mod is None:
        raise ImportError(f"the compiled kernel is {_why_not}")
    return mod


def kernel_status() -> tuple[bool, str]:
    """(whether pipelines run the compiled kernel by default, a sentence saying what runs the frames)."""
    if os.environ.get(ENV, "").strip().lower() == "numpy":
        return False, f"the numpy pipeline runs the frames ({ENV}=numpy)"
    if _load() is None:
        return False, f"the numpy pipeline runs the frames: the compiled kernel is {_why_not}"
    return True, "the compiled kernel runs the frames"


def fields() -> int:
    """Values per contact in the kernel's output (strength, x, y, major, minor, angle, area, peak, 7 log-Hu, q4)."""
    mod = _load()
    return 20 if mod is None else int(mod.FIELDS)


def compiled_vibration(signal: np.ndarray, live: np.ndarray) -> Any:
    """:class:`~optitac_edge.core.vibration.VibrationMeter`'s steps in C, on the same ``signal`` buffer.

    The same interface (``update(trunc, dt_ns) -> level``, ``reset()``, ``level``, ``quiet``,
    ``vibrating``, ``began``) and constants; the filter's float32 steps in the same order.

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """
    live_idx = np.flatnonzero(np.asarray(live, dtype=bool)).astype(np.int32)
    vib = vibration
    return _require().Vibration(signal, live_idx, vib.CUTOFF_HZ, vib.RATE_FRACTION, vib.WINDOW, vib.LEARN_FRAMES,
                                vib.MIN_FIBERS, vib.ON_SIGMAS, vib.QUIET_TAU_S, vib.VIBRATING_TAU_S)


def compiled_motion() -> Any:
    """:class:`~optitac_edge.core.motion.ContactMotion`'s steps in C: the same interface (``update(contacts, n,
    frame, now_ns)``, ``reset()``) and constants, the same sums in the same order.

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """
    m = motion
    return _require().Motion(m.WINDOW, m.SLIP_SIGMAS, m.MIN_SLIP_SPEED_MM_S, m.MIN_SLIP_SHIFT_MM, m.HOLD_FRACTION,
                             m.NOISE_RATE, m.PRIOR_NOISE_MM, m.STEADY_RATIO, m.MIN_SPAN_FRACTION)


class FrameKernel:
    """One pipeline's compiled kernel: its plan from the pipeline's parts, and the frame's contacts.

    Parameters
    ----------
    pipe : Pipeline
        Built with every numpy part (the kernel shares their buffers and constants).

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """

    def __init__(self, pipe: Pipeline) -> None:
        mod = _require()
        o, grid, baseline = pipe.options, pipe.bundle.grid, pipe.baseline
        #: The contacts of the last frame, strongest first: (MAX_CONTACTS, fields) float64: strength, x, y,
        #: major, minor, angle, area, peak, 7 log-Hu, q4, depth, force, shape index (-1: none), confidence.
        self.contacts = np.full((MAX_CONTACTS, int(mod.FIELDS)), math.nan)
        #: The rest light a raise sets the baseline to (written by the kernel when it finds one).
        self.rest = np.zeros(pipe.bundle.fibers.n_fibers, dtype=np.float32)
        live = np.flatnonzero(~np.asarray(pipe.bundle.fibers.dead, dtype=bool)).astype(np.int32)
        plan: dict[str, Any] = {
            **pipe.sampler.kernel_arrays(), **pipe.surface_op.kernel_arrays(),
            **check_kernel_arrays(pipe.bundle.fibers),
            "n_fibers": pipe.bundle.fibers.n_fibers, "n": grid.n,
            "dead": np.flatnonzero(pipe.bundle.fibers.dead).astype(np.int32),
            "live": live if live.size else np.arange(pipe.bundle.fibers.n_fibers, dtype=np.int32),
            "relative": int(o.relative), "compensate_gain": int(o.compensate_gain),
            "track_baseline": int(o.track_baseline), "bright_from_common": int(not o.compensate_gain),
            "black_level": float(np.float32(o.black_level)), "gain_rate_per_ns": float(o.gain_rate_per_s) * 1e-9,
            "tau_ns": float(o.baseline_tau_s) * 1e9, "holdoff_ns": float(o.holdoff_s) * 1e9,
            "bright_hold_ns": float(int(BRIGHT_HOLD_S * 1e9)),
            "x0_mm": float(grid.x0_mm), "y0_mm": float(grid.y0_mm), "step_mm": float(grid.step_mm),
            "cell_area_mm2": float(grid.cell_area_mm2),
            "min_area_mm2": float(pipe.bundle.thresholds.min_area_mm2),
            "min_cells": float(pipe.bundle.thresholds.min_area_mm2) / float(grid.cell_area_mm2),
            "peak_fraction": float(o.peak_fraction), "shape_fraction": float(o.shape_fraction),
            "split_fraction": float(o.split_fraction), "max_contacts": int(o.max_contacts),
            "means": pipe.means, "signal": pipe.signal, "surface": pipe.surface,
            "baseline": baseline.values, "level": baseline.level, "inv_level": baseline.inv_level,
            "rest": self.rest, "contacts": self.contacts,
        }
        if pipe.levels.bands is not None:  # each fiber's band (the levels write it; the kernel reads it)
            plan["band"] = pipe.levels.bands.reshape(-1)
        if pipe.support is not None:  # each fiber's neighbours, for its support
            plan["support_nbr"] = pipe.support.table.reshape(-1)
        #: The corrector whose models the kernel applies (None: the kernel gives raw contacts).
        self.corrector = pipe.corrector
        models = None if pipe.corrector is None else pipe.corrector.kernel_arrays()
        if models is None:
            self.corrector = None
        else:
            plan.update(models)
        #: Class names of the kernel's shape model (its OK_SHAPE field indexes them).
        self.shape_names: list[str] = (list(pipe.corrector.shapes.class_names)
                                       if self.corrector is not None and pipe.corrector is not None
                                       and pipe.corrector.shapes is not None else [])
        #: What the kernel was built from (its arrays are the pipeline's buffers; tools/kernel_aarch64.py
        #: writes it out for the C harness).
        self.plan = plan
        #: The extension's kernel object (its members: gain, light_changed, raise_pending, common, ...).
        self.kernel = mod.Kernel(plan)
        self.kernel.set_correct(self.corrector is not None)
        self.frame = self.kernel.frame
        for c, row in zip(pipe.contacts, self.contacts):  # each contact's shape features where the kernel writes them
            c.hu, c.features = row[8:15], row[8:16]
            c.hu.fill(math.nan)

    def run(self, frame: Any, now_ns: int, dt_ns: int, est: ContactEstimate, contacts: list[ContactEstimate],
            corrector: ContactCorrector | None, means_ready: bool = False) -> int:
        """Steps 2-10 of one frame (the baseline ready): its contacts into ``contacts`` (their shape features
        are there already), corrected by ``corrector`` when the kernel does not (None: it did, or raw);
        without contact ``est`` says so. Returns their number. ``means_ready``: :meth:`check` took this
        frame's fiber means."""
        n = self.frame(frame, now_ns, dt_ns, means_ready)
        if n == 0:
            est.clear(self.kernel.clear_strength, self.kernel.clear_area)
            return 0
        index, t_ns, names = est.frame, est.t_ns, self.shape_names
        rows = self.contacts[:n].tolist()
        for i in range(n):
            c, r = contacts[i], rows[i]
            c.strength, c.x_mm, c.y_mm, c.major_mm, c.minor_mm, c.angle_deg, c.area_mm2, c.peak = r[:8]
            c.frame, c.t_ns, c.baseline_ready, c.n_contacts, c.contact = index, t_ns, True, n, True
            c.depth_mm, c.force_n, c.confidence = r[16], r[17], r[19]
            c.shape = names[int(r[18])] if r[18] >= 0 else ""
            if corrector is not None:
                c.shape, c.confidence, c.depth_mm, c.force_n = "", math.nan, math.nan, math.nan
                corrector.apply(c)
        return n

    @property
    def light_changed(self) -> bool:
        """The last frame's light changed common-mode (the LED gain taken at once)."""
        return bool(self.kernel.light_changed)

    @property
    def raise_pending(self) -> bool:
        """The last frame found fibers brighter than their baseline to raise (to :attr:`rest`, from :attr:`common`)."""
        return bool(self.kernel.raise_pending)

    @property
    def common(self) -> float:
        """The level the last frame's brightness was measured from (signal units)."""
        return float(self.kernel.common)

    def check(self, frame: Any) -> str | None:
        """The fiber means of ``frame``, then :class:`~optitac_edge.core.frame_check.FrameCheck`'s verdict on
        it from the same pixels (in the caches by then): ``"dark"``, ``"saturated"`` or None (process it,
        with :attr:`saturated` telling whether a fiber centre was at full scale). Nothing else changes."""
        code = self.kernel.check(frame)
        return CHECK_REASONS[code - 1] if code else None

    @property
    def saturated(self) -> bool:
        """The last :meth:`check` found a live fiber centre at full scale."""
        return bool(self.kernel.saturated)

    def means(self, frame: Any, out: Any) -> Any:
        """Step 2 alone (the baseline's frames): the fiber means into ``out`` (the pipeline's buffer)."""
        self.kernel.means(frame)
        return out

    def reset_gain(self, now_ns: int) -> None:
        """The LED gain 1 from ``now_ns`` on (a new baseline)."""
        self.kernel.reset_gain(now_ns)

    def led_gain(self) -> LedGain:
        """The LED gain compensation's state after the last frame."""
        k = self.kernel
        return LedGain(k.gain, k.frame_gain, k.reference, k.reference_ns, k.light_changes)

    def use_corrector(self, corrector: object) -> bool:
        """Whether the kernel applies ``corrector`` (the one it was built with) or the caller does."""
        on = corrector is not None and corrector is self.corrector
        self.kernel.set_correct(on)
        return on
