"""The shape classifier's input transform: robust log-Hu features.

The pipeline reports ``hu = -sign(h) * log10|h|`` (:func:`optitac_edge.moments.log_hu`).
For symmetric shapes several invariants are zero in theory and ~1e-33
rounding noise in practice, which that log turns into +-30..65 outliers with a
random sign; :func:`optitac_edge.moments.log_hu` also maps an exact ``h == 0``
to 0, the value of ``|h| == 1``. The classifier therefore sees, per invariant
(``L`` the input log-Hu value, ``C`` = :data:`LOG_HU_CAP` = 20, i.e. ``|h|``
floored at 1e-20):

* ``h1 .. h4`` (non-negative by construction): ``clip(L, -C, C)`` -- the
  paper's feature with ``h`` floored at 1e-20 (and capped at 1e20). For
  ``h2 .. h4`` an exact ``L == 0`` means ``h == 0`` (``log_hu``'s guard) and
  becomes ``C``. ``h1 > 0`` always, so for it ``L == 0`` is ``h1 == 1``.
* ``h5 .. h7`` (signed): a symmetric log, continuous and increasing in ``h``
  through 0: ``sign(h) * max(0, C + log10|h|) = sign(L) * max(0, C - |L|)``
  (assumes ``|h| <= 1``, true for real shapes). ``|h| <= 1e-20``, ``h == 0``
  and ``L = +-inf`` all give 0.

NaN stays NaN (no contact). The transform is identical in
:func:`shape_features`, the numpy evaluator and the ONNX graph
(:mod:`optitac_edge.shapes.onnx_export`).
"""

from __future__ import annotations

import numpy as np

#: ``|h|`` is floored at ``10 ** -LOG_HU_CAP`` (log-Hu clipped to +-LOG_HU_CAP).
LOG_HU_CAP = 20.0
#: Number of Hu invariants.
N_HU = 7
#: True for the signed invariants h5, h6, h7 (symmetric-log rule).
SIGNED = np.array([False, False, False, False, True, True, True])
#: True where an exact log-Hu 0 means ``h == 0`` (h2 .. h4; h1 is never 0).
ZERO_IS_NULL = np.array([False, True, True, True, False, False, False])


def shape_features(hu_log: np.ndarray, cap: float = LOG_HU_CAP) -> np.ndarray:
    """Robust classifier features from log-Hu invariants.

    Parameters
    ----------
    hu_log : array_like, shape (..., 7), float
        ``-sign(h) * log10|h|`` as reported in ``ContactEstimate.hu``
        (dimensionless). Any finite or infinite value; NaN propagates.
    cap : float
        ``C``: ``|h|`` is floored at ``10 ** -C`` (default 20).

    Returns
    -------
    ndarray, shape (..., 7), float64
        Features in ``[-C, C]`` (or NaN), see the module docstring.
    """
    L = np.asarray(hu_log, dtype=np.float64)
    if L.shape[-1:] != (N_HU,):
        raise ValueError(f"expected log-Hu features of shape (..., 7), got {L.shape}")
    with np.errstate(invalid="ignore"):
        nonneg = np.clip(L, -cap, cap)
        nonneg = np.where((L == 0.0) & ZERO_IS_NULL, cap, nonneg)
        a = np.abs(L)
        signed = np.where(a >= cap, 0.0, np.sign(L) * (cap - a))
    return np.where(SIGNED, signed, nonneg)
