"""Fault injection for tests and the soak run: a camera wrapper that misbehaves on purpose.

:class:`FaultyCamera` wraps any :class:`~optitac_edge.io.cameras.Camera` and, per
read, with probability ``rate`` (deterministic from ``seed``) injects one of
:data:`FAULT_KINDS`:

``timeout``     the read waits ``timeout_s`` (capped at ``max_wait_s``) and raises CameraError
``exception``   the read raises CameraError at once (a driver error)
``crash``       the read raises a non-camera exception (RuntimeError: a backend bug)
``shape``       a frame of the wrong shape
``dtype``       a frame of the right shape but uint16
``black``       an all-zero frame
``saturated``   an all-255 frame
``gone``        the device disappears for ``gone_s``: every read raises CameraError, and
                so does opening it again through :meth:`FaultInjector.factory` until it is back

Used by ``optitac-edge soak`` and tests/test_reliability.py. Every injected fault is
counted in :attr:`FaultInjector.injected` so a run can check all of them were seen.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock

FAULT_KINDS: tuple[str, ...] = ("timeout", "exception", "crash", "shape", "dtype", "black", "saturated", "gone")


class FaultInjector:
    """Shared state of the faults: the random stream, what was injected, whether the device is gone.

    Parameters
    ----------
    rate : float
        Probability that one read is faulty.
    seed : int
        Seed of the fault sequence (same seed, same faults in the same reads).
    kinds : sequence of str
        Which faults to inject (default: all of :data:`FAULT_KINDS`).
    gone_s : float
        How long the device stays gone after a ``gone`` fault, s.
    max_wait_s : float
        Longest wait of a ``timeout`` fault, s.
    clock : Clock
        The time of ``gone`` and the waits of ``timeout`` (a
        :class:`~optitac_edge.io.clock.VirtualClock` with the service's makes a run deterministic).
    """

    def __init__(self, rate: float = 0.01, seed: int = 0, kinds: Sequence[str] = FAULT_KINDS,
                 gone_s: float = 0.5, max_wait_s: float = 0.2,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        unknown = set(kinds) - set(FAULT_KINDS)
        if unknown:
            raise ValueError(f"unknown fault kinds {sorted(unknown)} (known: {', '.join(FAULT_KINDS)})")
        if not 0.0 <= rate <= 1.0:
            raise ValueError("rate must be in 0..1")
        self.rate = rate
        self.kinds = tuple(kinds)
        self.gone_s = gone_s
        self.max_wait_s = max_wait_s
        self.clock = clock
        self.rng = np.random.default_rng(seed)
        self.injected: Counter[str] = Counter()
        self.gone_until_ns: int | None = None

    @property
    def gone(self) -> bool:
        return self.gone_until_ns is not None and self.clock.monotonic_ns() < self.gone_until_ns

    def draw(self) -> str | None:
        """The fault of the next read, or None."""
        if self.rate <= 0 or not self.kinds or self.rng.random() >= self.rate:
            return None
        kind = self.kinds[int(self.rng.integers(len(self.kinds)))]
        self.injected[kind] += 1
        if kind == "gone":
            self.gone_until_ns = self.clock.monotonic_ns() + round(self.gone_s * 1e9)
        return kind

    def factory(self, open_camera: Callable[[], Camera]) -> Callable[[], Camera]:
        """A camera factory for :class:`~optitac_edge.service.loop.Service` that fails while the device is gone."""

        def open_faulty() -> Camera:
            if self.gone:
                raise CameraError("camera device not found (injected: gone)")
            return FaultyCamera(open_camera(), self)

        return open_faulty


class FaultyCamera(Camera):
    """``inner`` with the faults of ``injector`` injected into its reads; closes ``inner`` on close."""

    def __init__(self, inner: Camera, injector: FaultInjector) -> None:
        super().__init__()
        self.inner = inner
        self.injector = injector
        self.pixel_format = inner.pixel_format
        self.height, self.width, self.fps = inner.height, inner.width, inner.fps
        self.reuses_buffer = inner.reuses_buffer

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        inj = self.injector
        if inj.gone:
            raise CameraError("camera device gone (injected)")
        kind = inj.draw()
        if kind == "gone":
            raise CameraError("camera device gone (injected)")
        if kind == "timeout":
            inj.clock.sleep(min(timeout_s, inj.max_wait_s))
            raise CameraError(f"no frame within {timeout_s:.2f} s (injected timeout)")
        if kind == "exception":
            raise CameraError("VIDIOC_DQBUF: Input/output error (injected)")
        if kind == "crash":
            raise RuntimeError("backend bug (injected)")
        captured = self.inner.read(timeout_s)
        if captured is None or kind is None:
            return captured
        frame = captured.frame
        if kind == "shape":
            frame = np.zeros((frame.shape[0] // 2, frame.shape[1] + 3) + frame.shape[2:], np.uint8)
        elif kind == "dtype":
            frame = frame.astype(np.uint16) * 257
        elif kind == "black":
            frame = np.zeros_like(frame)
        elif kind == "saturated":
            frame = np.full_like(frame, 255)
        return CapturedFrame(frame, captured.t_ns, captured.seq)

    def _close_internal(self) -> None:
        self.inner.close()


__all__ = ["FAULT_KINDS", "FaultInjector", "FaultyCamera"]
