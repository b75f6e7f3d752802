"""The colour mix an RGB camera's fiber light is read through (issue 37: colour-coded fibers).

An RGB camera gives each fiber three values. The per-frame loop reads one per
fiber: a fixed-point mix of the three, ``(w_r R + w_g G + w_b B + 2^14) >> 15``
per pixel (weights summing to 2^15). ``luma`` is BT.601's (OpenCV's
``COLOR_RGB2GRAY`` to the bit); the others weigh the channels in which a
coloured skin's press shows most. A mix's relative change is the luma's plus
a chromaticity term: ``calibrate levels`` adopts another mix than luma only
where held-out presses show it tells contact frames from rest frames better.
"""

from __future__ import annotations

import numpy as np

#: The mixes, by name: Q15 weights of (R, G, B).
COLOUR_MIXES: dict[str, tuple[int, int, int]] = {
    "luma": (9798, 19235, 3735), "red": (32768, 0, 0), "green": (0, 32768, 0), "blue": (0, 0, 32768),
    "mean": (10923, 10923, 10922),
}


def mix_weights(name: str) -> np.ndarray:
    """The Q15 weights of mix ``name``, shape (3,), int32.

    Raises
    ------
    ValueError
        For a mix not in :data:`COLOUR_MIXES`.
    """
    try:
        return np.asarray(COLOUR_MIXES[name], dtype=np.int32)
    except KeyError:
        raise ValueError(f"unknown colour mix {name!r} (known: {', '.join(COLOUR_MIXES)})") from None


def mix_pixels(rgb: np.ndarray, weights: np.ndarray, work: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``(w . rgb + 2^14) >> 15`` of every pixel into ``out``.

    Parameters
    ----------
    rgb : ndarray, shape (P, 3), uint8
    weights : ndarray, shape (3,), int32
        Q15 weights summing to 2^15.
    work : ndarray, shape (P,), int32
        Scratch.
    out : ndarray, shape (P,), uint8
    """
    np.matmul(rgb, weights, out=work, casting="unsafe")
    work += 1 << 14
    np.right_shift(work, 15, out=work)
    np.copyto(out, work, casting="unsafe")
    return out
