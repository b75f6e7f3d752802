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
import weakref
from importlib import import_module
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from optitac_edge.core import motion, vibration
from optitac_edge.core.baseline import BRIGHT_HOLD_S
from optitac_edge.core.frame_check import CHECK_REASONS, check_kernel_arrays
from optitac_edge.core.frame_engine import MotionSteps, Skip, VibrationSteps
from optitac_edge.core.gain import LedGain
from optitac_edge.core.kernel_plan import KernelPlan
from optitac_edge.core.levels import ContactLevels
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.core.shared_tables import shared_tables

if TYPE_CHECKING:
    from optitac_edge.core import _frame_kernel
    from optitac_edge.core.corrections import ContactCorrector
    from optitac_edge.core.numpy_engine import NumpyEngine

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


def _require() -> None:
    """Nothing when the extension module is here, else ImportError saying why not (then import it by name:
    its types are in ``_frame_kernel.pyi``)."""
    if _load() is None:
        raise ImportError(f"the compiled kernel is {_why_not}")


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


def compiled_vibration(signal: np.ndarray, live: np.ndarray) -> _frame_kernel.Vibration:
    """:class:`~optitac_edge.core.vibration.VibrationMeter`'s steps in C, on the same ``signal`` buffer.

    The same interface (``update(trunc, dt_ns) -> level``, ``reset()``, ``level``, ``quiet``,
    ``vibrating``, ``began``) and constants; the filter's float32 steps in the same order.

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """
    _require()
    from optitac_edge.core import _frame_kernel

    live_idx = np.flatnonzero(np.asarray(live, dtype=bool)).astype(np.int32)
    vib = vibration
    return _frame_kernel.Vibration(signal, live_idx, vib.CUTOFF_HZ, vib.RATE_FRACTION, vib.WINDOW, vib.LEARN_FRAMES,
                                vib.MIN_FIBERS, vib.ON_SIGMAS, vib.QUIET_TAU_S, vib.VIBRATING_TAU_S)


def compiled_motion() -> _frame_kernel.Motion:
    """:class:`~optitac_edge.core.motion.ContactMotion`'s steps in C: the same interface (``update(contacts, n,
    frame, now_ns)``, ``reset()``) and constants, the same sums in the same order.

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """
    _require()
    from optitac_edge.core import _frame_kernel

    m = motion
    return _frame_kernel.Motion(m.WINDOW, m.SLIP_SIGMAS, m.MIN_SLIP_SPEED_MM_S, m.MIN_SLIP_SHIFT_MM, m.HOLD_FRACTION,
                             m.NOISE_RATE, m.PRIOR_NOISE_MM, m.STEADY_RATIO, m.MIN_SPAN_FRACTION)


def _arrays_of(value: object) -> list[np.ndarray]:
    """Every ndarray in a plan's dict (nested dicts and lists included)."""
    if isinstance(value, np.ndarray):
        return [value]
    if isinstance(value, dict):
        return [a for v in value.values() for a in _arrays_of(v)]
    if isinstance(value, (list, tuple)):
        return [a for v in value for a in _arrays_of(v)]
    return []


class CompiledEngine:
    """Steps 2-10 in the compiled kernel, on the numpy parts' buffers (a
    :class:`~optitac_edge.core.frame_engine.FrameEngine`).

    Parameters
    ----------
    parts : NumpyEngine
        The pipeline's numpy parts: the kernel's plan comes from their tables and shares their buffers, so the
        numpy pipeline stays the readable reference and everything reading those buffers (the live view, the
        bench) sees the same thing.
    corrector : ContactCorrector or None
        The bundle's calibration models, for the kernel to apply (None: raw contacts).

    Raises
    ------
    ImportError
        If the kernel is not built (see :func:`kernel_status`).
    """

    def __init__(self, parts: NumpyEngine, corrector: ContactCorrector | None) -> None:
        _require()
        from optitac_edge.core import _frame_kernel

        names = _frame_kernel.FIELD_NAMES
        #: Each field's index in a row of :attr:`contacts` (the kernel's FIELD_NAMES).
        self.field = {name: i for i, name in enumerate(names)}
        #: The contacts of the last frame, strongest first: (MAX_CONTACTS, len(FIELD_NAMES)) float64.
        self.contacts = np.full((MAX_CONTACTS, len(names)), math.nan)
        self._parts = parts
        self._frame_contacts = parts.contacts
        bundle_table, o, baseline, grid = parts.bundle.fibers, parts.options, parts.baseline, parts.bundle.grid
        min_area = float(parts.bundle.thresholds.min_area_mm2)
        models = None if corrector is None else corrector.kernel_arrays()
        #: The corrector whose models the kernel applies (None: the kernel gives raw contacts).
        self.built_with = corrector if models is not None else None
        #: What the kernel was built from (its arrays are the parts' buffers; tools/kernel_aarch64.py writes
        #: it out for the C harness).
        self.plan = KernelPlan(
            n_fibers=bundle_table.n_fibers, n=grid.n, relative=o.relative, compensate_gain=o.compensate_gain,
            track_baseline=o.track_baseline, bright_from_common=not o.compensate_gain, max_contacts=o.max_contacts,
            black_level=float(np.float32(o.black_level)), gain_rate_per_ns=float(o.gain_rate_per_s) * 1e-9,
            tau_ns=float(o.baseline_tau_s) * 1e9, holdoff_ns=float(o.holdoff_s) * 1e9,
            bright_hold_ns=float(int(BRIGHT_HOLD_S * 1e9)), x0_mm=float(grid.x0_mm), y0_mm=float(grid.y0_mm),
            step_mm=float(grid.step_mm), cell_area_mm2=float(grid.cell_area_mm2),
            min_area_mm2=min_area, min_cells=min_area / float(grid.cell_area_mm2),
            peak_fraction=float(o.peak_fraction), shape_fraction=float(o.shape_fraction),
            split_fraction=float(o.split_fraction),
            dead=parts.dead.astype(np.int32), live=parts.live_idx.astype(np.int32),
            band=None if parts.levels.bands is None else parts.levels.bands.reshape(-1),
            support_nbr=None if parts.support is None else parts.support.table.reshape(-1),
            means=parts.means_buf, signal=parts.signal_buf, surface=parts.surface_buf, baseline=baseline.values,
            level=baseline.level, inv_level=baseline.inv_level,
            rest=np.zeros(bundle_table.n_fibers, dtype=np.float32), contacts=self.contacts,
            sampler=parts.sampler.kernel_arrays(), surface_op=shared_tables(parts.surface_op.kernel_arrays()),
            check=check_kernel_arrays(bundle_table), models=models or {})
        #: The rest light a raise sets the baseline to (written by the kernel when it finds one).
        self.rest = self.plan.rest
        #: Class names of the kernel's shape model (its ``shape`` field indexes them).
        built = self.built_with
        self.shape_names: list[str] = (list(built.shapes.class_names) if built is not None
                                       and built.shapes is not None else [])
        #: The extension's kernel object (its members: gain, light_changed, raise_pending, common, ...).
        arrays = self.plan.as_dict()
        self.kernel = _frame_kernel.Kernel(arrays)
        #: A weak reference to every array the kernel holds a pointer into: numpy refuses to resize an array
        #: that has one, even with ``refcheck=False`` (which would free the memory under the kernel's pointers).
        self._pins = [weakref.ref(a) for a in _arrays_of(arrays)]
        self._frame = self.kernel.frame
        self._bad = parts.frame_check.bad
        self._gain = parts.gain_compensation is not None
        f = self.field
        #: The fields a contact's estimate takes from its row, by index: the first of the 8 geometric ones,
        #: depth, force, shape, confidence.
        self._at = (f["strength"], f["depth_mm"], f["force_n"], f["shape"], f["confidence"])
        self._means_ready = False
        #: The corrector applied here, per contact, after the kernel (one the kernel was not built with).
        self._python_corrector: ContactCorrector | None = None
        self.use_corrector(corrector)
        hu0, q4 = self.field["hu0"], self.field["q4"]
        for c, row in zip(parts.contacts, self.contacts):  # each contact's shape features where the kernel writes them
            c.hu, c.features = row[hu0:q4], row[hu0:q4 + 1]
            c.hu.fill(math.nan)

    # -- the FrameEngine protocol ---------------------------------------------

    @property
    def saturated(self) -> bool:
        """The last :meth:`check` found a live fiber centre at full scale."""
        return bool(self.kernel.saturated)

    @property
    def light_changed(self) -> bool:
        """The last frame's light changed common-mode (the LED gain taken at once)."""
        return self._gain and bool(self.kernel.light_changed)

    @property
    def raise_pending(self) -> bool:
        """The last frame found fibers brighter than their baseline to raise (to :attr:`rest`, from :attr:`common`)."""
        return bool(self.kernel.raise_pending)

    @property
    def common(self) -> float:
        """The level the last frame's brightness was measured from (signal units)."""
        return float(self.kernel.common)

    def check(self, frame: object) -> Skip | None:
        """The fiber means of ``frame``, then :class:`~optitac_edge.core.frame_check.FrameCheck`'s verdict on
        it from the same pixels (in the caches by then); the next :meth:`means` or :meth:`run` goes on from
        those means. Nothing else changes."""
        if self._bad(frame):
            return Skip.BAD
        code = self.kernel.check(frame)
        self._means_ready = code == 0
        return Skip(CHECK_REASONS[code - 1]) if code else None

    def means(self, frame: np.ndarray) -> None:
        if not self._means_ready:
            self.kernel.means(frame)
        self._means_ready = False

    def run(self, frame: np.ndarray, now_ns: int, dt_ns: int) -> int:
        ready, self._means_ready = self._means_ready, False
        n = self._frame(frame, now_ns, dt_ns, ready)
        contacts = self._frame_contacts
        est = contacts[0]
        if n == 0:
            est.clear(self.kernel.clear_strength, self.kernel.clear_area)
            return 0
        names, corrector = self.shape_names, self._python_corrector
        strength, depth, force, shape, confidence = self._at
        rows = self.contacts[:n].tolist()
        for i in range(n):
            c, r = contacts[i], rows[i]
            c.strength, c.x_mm, c.y_mm, c.major_mm, c.minor_mm, c.angle_deg, c.area_mm2, c.peak = \
                r[strength:strength + 8]
            c.contact = True
            c.depth_mm, c.force_n, c.confidence = r[depth], r[force], r[confidence]
            c.shape = names[int(r[shape])] if r[shape] >= 0 else ""
            if corrector is not None:
                c.shape, c.confidence, c.depth_mm, c.force_n = "", math.nan, math.nan, math.nan
                corrector.apply(c)
        return n

    def set_levels(self, levels: ContactLevels) -> None:
        self._parts.set_levels(levels)
        self.kernel.set_levels(levels.trunc, levels.off, levels.on, levels.gain_delta, levels.gain_tolerance,
                               levels.gain_significant)

    def reset_contact(self) -> None:
        self._parts.reset_contact()
        self.kernel.reset_contact()

    def reset_gain(self, now_ns: int | None) -> None:
        self._parts.reset_gain(now_ns)
        self.kernel.reset_gain(self.kernel.reference_ns if now_ns is None else now_ns)

    def led_gain(self) -> LedGain | None:
        """The LED gain compensation's state after the last frame; None without ``compensate_gain``."""
        if not self._gain:
            return None
        k = self.kernel
        return LedGain(k.gain, k.frame_gain, k.reference, k.reference_ns, k.light_changes)

    def use_corrector(self, corrector: ContactCorrector | None) -> None:
        """The kernel applies ``corrector`` when it is the one it was built with; another runs here, per
        contact (the ONNX shape backend); None: raw contacts."""
        on = corrector is not None and corrector is self.built_with
        self.kernel.set_correct(on)
        self._python_corrector = None if on else corrector

    @property
    def corrects(self) -> bool:
        """The kernel itself applies the calibration models."""
        return bool(self.kernel.correct)

    def motion_parts(self) -> tuple[MotionSteps, VibrationSteps]:
        return compiled_motion(), compiled_vibration(self._parts.signal_buf, self._parts.live)
