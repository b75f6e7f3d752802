"""Types of the compiled per-frame kernel (``kernel/module.c``, ``motion_type.c``, ``vibration_type.c``).

Built by ``pip install`` where a C compiler exists; :mod:`optitac_edge.core.compiled` loads it and says
whether it is here. A test checks this stub against the built module's names.
"""

from collections.abc import Sequence

import numpy as np

from optitac_edge.core.contact import ContactEstimate

#: Values per contact in a row of the plan's ``contacts`` (len(FIELD_NAMES)).
FIELDS: int
#: The names of a contact's values, in their order in a row (frame_kernel.h's enum).
FIELD_NAMES: tuple[str, ...]
#: Most contacts a plan may ask for (contact_finder.MAX_CANDIDATES).
MAX_CANDIDATES: int
#: Values and gradients per mesh cell of the factored surface (surface.CELL_TERMS).
CELL_TERMS: int

class Kernel:
    """One pipeline's kernel, built from a plan (:meth:`KernelPlan.as_dict
    <optitac_edge.core.kernel_plan.KernelPlan.as_dict>`): every key checked, an unknown one refused."""

    gain: float
    frame_gain: float
    reference: float
    reference_ns: int
    light_changed: int
    light_changes: int
    common: float
    raise_pending: int
    in_contact: int
    saturated: int
    cells: int
    evaluated: int
    correct: int
    clear_strength: float
    clear_area: float
    def __init__(self, plan: dict[str, np.ndarray | int | float]) -> None: ...
    def set_correct(self, on: bool) -> None: ...
    def frame(self, frame: np.ndarray, now_ns: int, dt_ns: int, means_ready: bool = ...) -> int: ...
    def means(self, frame: np.ndarray) -> None: ...
    def check(self, frame: object) -> int: ...
    def set_levels(self, trunc: float, off: float, on: float, gain_delta: float, gain_tolerance: float,
                   gain_significant: float) -> None: ...
    def reset_gain(self, now_ns: int) -> None: ...
    def reset_contact(self) -> None: ...

class Motion:
    """:class:`~optitac_edge.core.motion.ContactMotion` in C."""

    period_s: float
    def __init__(self, window: int, slip_sigmas: float, min_speed: float, min_shift: float, hold_fraction: float,
                 noise_rate: float, prior: float, steady_ratio: float, min_span_fraction: float) -> None: ...
    def update(self, contacts: Sequence[ContactEstimate], n: int, frame: int, now_ns: int) -> None: ...
    def reset(self) -> None: ...

class Vibration:
    """:class:`~optitac_edge.core.vibration.VibrationMeter` in C."""

    period_s: float
    level: float
    quiet: float
    unit: float
    vibrating: bool
    began: bool
    def __init__(self, signal: np.ndarray, live: np.ndarray, cutoff_hz: float, rate_fraction: float, window: int,
                 learn_frames: int, min_fibers: int, on_sigmas: float, quiet_tau_s: float,
                 vibrating_tau_s: float) -> None: ...
    def update(self, trunc: float, dt_ns: int) -> float: ...
    def reset(self) -> None: ...

def sort(a: np.ndarray) -> None: ...
def label8(mask: np.ndarray, labels: np.ndarray) -> int: ...
def nearest_seed(seed_labels: np.ndarray, nearest: np.ndarray) -> None: ...
