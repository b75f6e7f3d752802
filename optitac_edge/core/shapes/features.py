"""The shape classifier's input transform: robust log-Hu features and the 4-fold symmetry q4.

Input: the pipeline's shape feature vector ``ContactEstimate.features``, shape
(8,) = ``[L1 .. L7, q4]`` with ``L = -sign(h) * log10|h|`` the log-Hu
invariants (:func:`optitac_edge.core.moments.log_hu`, exactly ``ContactEstimate.hu``)
and ``q4 = |c40| / mu00**3`` the rotation/scale-invariant 4-fold symmetry of
the binarised contact (0 for a disc or a triangle, 1/60 for a square, large
for an edge). A 7-wide input (log-Hu only, q4 absent) is accepted too.

For symmetric shapes several invariants are zero in theory and ~1e-33
rounding noise in practice, which that log turns into +-30..65 outliers with a
random sign; :func:`optitac_edge.core.moments.log_hu` also maps an exact ``h == 0``
to 0, the value of ``|h| == 1``. The classifier therefore sees, per input
(``L`` the input value, ``C`` = :data:`LOG_HU_CAP` = 20, i.e. ``|h|`` floored
at 1e-20):

* ``h1 .. h4`` (non-negative by construction): ``clip(L, -C, C)`` -- the
  paper's feature with ``h`` floored at 1e-20 (and capped at 1e20). For
  ``h2 .. h4`` an exact ``L == 0`` means ``h == 0`` (``log_hu``'s guard) and
  becomes ``C``. ``h1 > 0`` always, so for it ``L == 0`` is ``h1 == 1``.
* ``h5 .. h7`` (signed): a symmetric log, continuous and increasing in ``h``
  through 0: ``sign(h) * max(0, C + log10|h|) = sign(L) * max(0, C - |L|)``
  (assumes ``|h| <= 1``, true for real shapes). ``|h| <= 1e-20``, ``h == 0``
  and ``L = +-inf`` all give 0.
* ``q4``: ``ln(clip(q4, 0, Q4_MAX) + q4_floor)`` with ``q4_floor`` =
  :data:`Q4_FLOOR` = 1e-3, about the discretisation noise of a disc's q4 on
  the 100 x 100 mesh: discs and triangles (q4 ~ 0..3e-3) form a compact
  cluster at -6.9 .. -5.7 instead of a long log tail, squares sit at -4.0
  (blurred small squares lower), ellipses of ratio 0.6 at -4.1 (M1/M2 tell
  them from squares) and edge bars above -2.5.

NaN stays NaN (no contact). The transform is identical in
:func:`shape_features`, the numpy evaluator and the ONNX graph
(:mod:`optitac_edge.calibration.onnx_export`).
"""

from __future__ import annotations

import numpy as np

#: ``|h|`` is floored at ``10 ** -LOG_HU_CAP`` (log-Hu clipped to +-LOG_HU_CAP).
LOG_HU_CAP = 20.0
#: Number of Hu invariants.
N_HU = 7
#: Width of the full feature vector ``[L1 .. L7, q4]``.
N_FEATURES = 8
#: Index of q4 in the feature vector.
Q4_INDEX = 7
#: Added to q4 before the log (the discretisation noise level of a disc's q4).
Q4_FLOOR = 1e-3
#: q4 is clipped to ``[0, Q4_MAX]`` (an edge bar of aspect 8 has ~0.8).
Q4_MAX = 1e6
#: True for the signed invariants h5, h6, h7 (symmetric-log rule); False for q4.
SIGNED = np.array([False, False, False, False, True, True, True, False])
#: True where an exact log-Hu 0 means ``h == 0`` (h2 .. h4; h1 is never 0).
ZERO_IS_NULL = np.array([False, True, True, True, False, False, False, False])
#: True for q4.
IS_Q4 = np.arange(N_FEATURES) == Q4_INDEX


def shape_features(
    features: np.ndarray, cap: float = LOG_HU_CAP, q4_floor: float = Q4_FLOOR
) -> np.ndarray:
    """Classifier features from the pipeline's shape feature vector.

    Parameters
    ----------
    features : array_like, shape (..., 8) or (..., 7), float
        ``[L1 .. L7, q4]`` as ``ContactEstimate.features`` (dimensionless;
        ``L`` = ``ContactEstimate.hu``), or the 7 log-Hu values alone. Any
        finite or infinite value; NaN propagates.
    cap : float
        ``C``: ``|h|`` is floored at ``10 ** -C`` (default 20).
    q4_floor : float
        Added to q4 before the natural log (default :data:`Q4_FLOOR`).

    Returns
    -------
    ndarray, same shape, float64
        Columns 0..6 in ``[-C, C]``, column 7 in ``[ln q4_floor, ln(Q4_MAX + q4_floor)]``
        (or NaN); see the module docstring.
    """
    L = np.asarray(features, dtype=np.float64)
    w = L.shape[-1] if L.ndim else 0
    if w not in (N_HU, N_FEATURES):
        raise ValueError(f"expected shape features of shape (..., 8) ([log-Hu x 7, q4]) "
                         f"or (..., 7) (log-Hu only), got {L.shape}")
    with np.errstate(invalid="ignore"):
        nonneg = np.clip(L, -cap, cap)
        nonneg = np.where((L == 0.0) & ZERO_IS_NULL[:w], cap, nonneg)
        a = np.abs(L)
        signed = np.where(a >= cap, 0.0, np.sign(L) * (cap - a))
    out = np.where(SIGNED[:w], signed, nonneg)
    if w == N_FEATURES:
        out[..., Q4_INDEX] = q4_log(L[..., Q4_INDEX], q4_floor)
    return out


def q4_log(q4: np.ndarray, q4_floor: float = Q4_FLOOR) -> np.ndarray:
    """The q4 transform ``ln(clip(q4, 0, Q4_MAX) + q4_floor)``, any shape, float64; NaN stays NaN."""
    q = np.asarray(q4, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        q = np.where(q > Q4_MAX, Q4_MAX, np.where(q < 0.0, 0.0, q))
    return np.log(q + q4_floor)
