"""What runs a frame's steps 2-10 (:mod:`optitac_edge.core.pipeline`): the engine protocol, and a frame's skip.

Two engines implement :class:`FrameEngine`: the numpy parts
(:class:`~optitac_edge.core.numpy_engine.NumpyEngine`, the readable reference) and the compiled kernel
(:class:`~optitac_edge.core.compiled.CompiledEngine`, the same steps in C on the same buffers).
:class:`~optitac_edge.core.pipeline.Pipeline` owns one and everything the two share (the baseline, the
levels, the tracking, the motion and the result); it never asks which engine it holds.
"""

from __future__ import annotations

from enum import Enum
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.corrections import ContactCorrector
    from optitac_edge.core.gain import LedGain
    from optitac_edge.core.levels import ContactLevels


class Skip(str, Enum):
    """Why :meth:`Pipeline.process <optitac_edge.core.pipeline.Pipeline.process>` skipped a frame
    (compares equal to its value: ``Skip.DARK == "dark"``)."""

    #: Not a frame of this camera: not a uint8 array of the bundle's frame shape.
    BAD = "bad"
    #: Fewer than :data:`~optitac_edge.core.frame_check.DARK_FRACTION` of the fiber centres are lit.
    DARK = "dark"
    #: Most fiber centres are at full scale.
    SATURATED = "saturated"
    #: The frames are not of the bundle's sensor (:mod:`~optitac_edge.core.fingerprint`): nothing is processed.
    MISMATCH = "mismatch"

    def __str__(self) -> str:
        return self.value


class MotionSteps(Protocol):
    """Step 8b's velocities and slip (:class:`~optitac_edge.core.motion.ContactMotion`, or the kernel's)."""

    #: The camera's nominal frame period, s (0: not known).
    period_s: float

    def update(self, contacts: list[ContactEstimate], n: int, frame: int, now_ns: int) -> None: ...

    def reset(self) -> None: ...


class VibrationSteps(Protocol):
    """Step 8b's vibration (:class:`~optitac_edge.core.vibration.VibrationMeter`, or the kernel's)."""

    #: The camera's nominal frame period, s (0: not known).
    period_s: float

    @property
    def vibrating(self) -> bool: ...

    @property
    def began(self) -> bool: ...

    def update(self, trunc: float, dt_ns: int) -> float: ...

    def reset(self) -> None: ...


class FrameEngine(Protocol):
    """Steps 2-10 of a frame on the pipeline's shared buffers (the fiber means, the signal, the surface, the
    baseline, the levels, the contacts)."""

    @property
    def saturated(self) -> bool:
        """The last checked frame had a live fiber centre at full scale."""
        ...

    @property
    def light_changed(self) -> bool:
        """The last frame's light changed common-mode (the LED gain taken at once)."""
        ...

    @property
    def raise_pending(self) -> bool:
        """The last frame found fibers brighter than their baseline to raise, to :attr:`rest` from :attr:`common`."""
        ...

    @property
    def rest(self) -> np.ndarray:
        """The rest light a raise sets those fibers' baseline to, shape (N,), float32."""
        ...

    @property
    def common(self) -> float:
        """The level the brightness was measured from (signal units)."""
        ...

    def check(self, frame: object) -> Skip | None:
        """Why ``frame`` is skipped, or None (:attr:`saturated` set). An engine may take the fiber means
        from the same pixels; :meth:`means` and :meth:`run` then go on from them."""
        ...

    def means(self, frame: np.ndarray) -> None:
        """Step 2 alone (the baseline's frames): the fiber means into the shared buffer."""
        ...

    def run(self, frame: np.ndarray, now_ns: int, dt_ns: int) -> int:
        """Steps 2-10 of a frame (the baseline ready): its contacts into the shared contacts, corrected by
        the corrector of :meth:`use_corrector`, their number returned; without contact the first says so."""
        ...

    def set_levels(self, levels: ContactLevels) -> None:
        """The levels changed (a new or raised baseline, a new contact level)."""
        ...

    def reset_contact(self) -> None:
        """A tare or a gap: the hysteresis, the end of the last contact and the bright-fiber timer dropped."""
        ...

    def reset_gain(self, now_ns: int | None) -> None:
        """The LED gain 1 from ``now_ns`` on (None: from the last reference's time)."""
        ...

    def led_gain(self) -> LedGain | None:
        """The LED gain compensation's state after the last frame; None without ``compensate_gain``."""
        ...

    def use_corrector(self, corrector: ContactCorrector | None) -> None:
        """Correct every contact with ``corrector`` (None: raw estimates)."""
        ...

    def motion_parts(self) -> tuple[MotionSteps, VibrationSteps]:
        """Step 8b's parts, on this engine's signal buffer."""
        ...
