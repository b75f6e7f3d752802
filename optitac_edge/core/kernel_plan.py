"""What the compiled kernel is built from: :class:`KernelPlan`, typed, handed to C as one flat dict.

The kernel (``kernel/module.c``) reads every key it knows, checks each array's type and size, and refuses a
key it does not read (a misspelt or stale one), so a plan and the C side cannot drift apart silently.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np

#: One value of the plan as the kernel reads it: an array (kept alive and shared), an int or a float.
PlanValue = np.ndarray | int | float
#: A part's own entries (its names are the kernel's, e.g. ``pixel_index``, ``tri_cols``, ``cmap_ex``).
PlanArrays = Mapping[str, PlanValue]


@dataclass(frozen=True, eq=False)
class KernelPlan:
    """Everything one pipeline's compiled kernel reads: sizes, switches, constants, its tables, the buffers it
    shares with the numpy parts, and each part's own entries.

    Attributes
    ----------
    n_fibers, n : int
        Fibers; cells on a side of the surface mesh.
    relative, compensate_gain, track_baseline, bright_from_common : bool
        :class:`~optitac_edge.core.options.ContactOptions`' switches (the last: step 10 measures brightness
        from the common level, i.e. without gain compensation).
    max_contacts : int
        Contacts a frame may have (1 .. ``MAX_CANDIDATES``).
    black_level, gain_rate_per_ns, tau_ns, holdoff_ns, bright_hold_ns : float
        Gray levels; 1/ns; ns.
    x0_mm, y0_mm, step_mm, cell_area_mm2, min_area_mm2, min_cells : float
        The mesh (mm, mm^2) and the smallest contact (mm^2, cells).
    peak_fraction, shape_fraction, split_fraction : float
        The options' fractions.
    dead, live : ndarray, int32
        Fiber indices.
    band, support_nbr : ndarray or None
        Each fiber's band (2 N float32) and its 6 neighbours (6 N int32, -1: none), when the options use them.
    means, signal, surface, baseline, level, inv_level, rest : ndarray, float32
        The buffers shared with the numpy parts (the kernel writes them).
    contacts : ndarray, float64, shape (MAX_CONTACTS, FIELDS)
        Where the kernel writes a frame's contacts (the fields named by ``_frame_kernel.FIELD_NAMES``).
    sampler, surface_op, check, models : mapping
        The fiber table's, the surface operator's, the frame check's and the calibration models' entries.
    """

    n_fibers: int
    n: int
    relative: bool
    compensate_gain: bool
    track_baseline: bool
    bright_from_common: bool
    max_contacts: int
    black_level: float
    gain_rate_per_ns: float
    tau_ns: float
    holdoff_ns: float
    bright_hold_ns: float
    x0_mm: float
    y0_mm: float
    step_mm: float
    cell_area_mm2: float
    min_area_mm2: float
    min_cells: float
    peak_fraction: float
    shape_fraction: float
    split_fraction: float
    dead: np.ndarray
    live: np.ndarray
    band: np.ndarray | None
    support_nbr: np.ndarray | None
    means: np.ndarray
    signal: np.ndarray
    surface: np.ndarray
    baseline: np.ndarray
    level: np.ndarray
    inv_level: np.ndarray
    rest: np.ndarray
    contacts: np.ndarray
    sampler: PlanArrays
    surface_op: PlanArrays
    check: PlanArrays
    models: PlanArrays

    def as_dict(self) -> dict[str, PlanValue]:
        """The flat dict ``_frame_kernel.Kernel`` takes: switches as 0/1, absent tables left out, each part's
        entries merged in.

        Raises
        ------
        ValueError
            If two parts give the same name.
        """
        out: dict[str, PlanValue] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Mapping):
                clash = out.keys() & value.keys()
                if clash:
                    raise ValueError(f"kernel plan: {f.name} gives {min(clash)} again")
                out.update(value)
            elif isinstance(value, bool):
                out[f.name] = int(value)
            elif value is not None:
                out[f.name] = value
        return out
