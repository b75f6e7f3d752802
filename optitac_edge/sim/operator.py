"""A simulated operator for the procedures that ask a person to press (``orient``, the view's orientation).

On a real sensor the operator reads the prompt and presses near the edge it
names. The simulator's own presses (:class:`~optitac_edge.sim.camera.PressProgram`)
ignore prompts, so on the simulated camera ``orient`` never finished; this
follower is given every prompt and presses where it asks, in the sensor's own
frame (the physical +x and +y edges), whatever the bundle's fiber map says.
"""

from __future__ import annotations

from optitac_edge.calibration.edge_presses import EDGE_FRACTION
from optitac_edge.sim.skin import Indenter


class PromptFollower:
    """Presses near the +x edge, releases, presses near the +y edge, as the prompts say (a PressSource).

    Parameters
    ----------
    radius_mm : float
        The sensor's array radius.
    size_mm, depth_mm : float
        The fingertip: a circle of this diameter, this deep.
    """

    def __init__(self, radius_mm: float, size_mm: float = 6.0, depth_mm: float = 2.5) -> None:
        self.radius_mm, self.size_mm, self.depth_mm = radius_mm, size_mm, depth_mm
        self._target: tuple[float, float] | None = None

    def follow(self, prompt: str) -> None:
        """Do what ``prompt`` (an :class:`~optitac_edge.calibration.edge_presses.EdgePresses` prompt) asks."""
        r = EDGE_FRACTION * self.radius_mm
        if prompt.startswith("press near the +x edge"):
            self._target = (r, 0.0)
        elif prompt.startswith("press near the +y edge"):
            self._target = (0.0, r)
        else:  # release, too near the centre, done, not decided
            self._target = None

    def at(self, frame: int) -> Indenter | None:
        target = self._target
        if target is None:
            return None
        return Indenter("circle", target[0], target[1], 0.0, self.size_mm, self.depth_mm)
