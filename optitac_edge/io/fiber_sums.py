"""The frames of a recording kept as fiber sums (:mod:`optitac_edge.io.frame_store`), given back as frames.

A frame after the rest frames is made from the rest frames' mean and the
frame's sum of every fiber's gray levels:

* each pixel of a fiber's group gets its rest level scaled by the fiber's
  light (its sum over its sum at rest), rounded so that the group's pixels add
  up to the recorded sum *exactly*: a fiber map whose pixel groups are the
  recording's own (a bundle calibrated from its rest frames) reads exactly the
  fiber light of the raw frames, and gives the same figures;
* the pixels around a group (up to half a fiber's radius, :data:`ZONE_FRACTION`)
  are scaled the same way, so that a fiber map found elsewhere, whose groups
  are a pixel larger or smaller, reads nearly the same light
  (:meth:`FiberSumFrames.exact_for` tells which case it is);
* everything else is the rest frames' mean.

An RGB recording with its fibers' colours (``colours.npy``) gives RGB frames:
each fiber pixel takes the red and blue its fiber's recorded colour gives at
the pixel's gray level (shared so that the group's sums are the recorded
ones), and a green that makes OpenCV's BT.601 gray of the pixel that gray
level exactly (:func:`green_for`; of two that do, the one that brings the
group's green nearer its sum; where none in 0..255 does, the pixel is gray):
the gray a bundle reads stays exact, and each channel's mean over a group is
the recorded one to within a fraction of a level. Around the groups and elsewhere: the rest frames' colour, scaled with
the fiber's light. Without ``colours.npy`` (gray recordings, or RGB ones
recorded before colours were kept) an RGB recording gives gray frames in
three channels (their BT.601 gray is the gray level itself).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.errors import FrameMismatchError, RecordingError
from optitac_edge.io.frame_store import COLOURS, REST_FRAMES, SPOTS, SUMS, read_spots

#: Pixels around a fiber's group, up to this fraction of its radius, follow its light.
ZONE_FRACTION = 0.5
#: The rest frames must give the typical fiber (the median) the light of the first sums after them to within
#: this fraction: rest frames shifted, replaced or black do not fit the sums (a camera's light does not move
#: by a third between the rest frames and the next).
REST_FIT = 0.3
#: Sum rows the rest frames are compared with.
FIT_ROWS = 5
#: OpenCV's fixed-point BT.601 RGB -> gray for 8-bit pixels (``cv2.cvtColor(..., COLOR_RGB2GRAY)``,
#: modules/imgproc/src/color_rgb.simd.hpp: ``RY15 = 9798, GY15 = 19235, BY15 = 3735``, ``gray_shift = 15``,
#: rounded). :meth:`FiberSumFrames.frame` checks the pixels it makes with OpenCV itself all the same.
GRAY_WEIGHTS, GRAY_SHIFT = (9798, 19235, 3735), 15


def gray_of(r: np.ndarray, g: np.ndarray, b: np.ndarray) -> np.ndarray:
    """OpenCV's BT.601 gray of 8-bit pixels (integer arrays of one shape), int64."""
    wr, wg, wb = GRAY_WEIGHTS
    total = wr * r.astype(np.int64) + wg * g.astype(np.int64) + wb * b.astype(np.int64)
    return (total + (1 << (GRAY_SHIFT - 1))) >> GRAY_SHIFT


def green_for(gray: np.ndarray, r: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest green whose pixel ``(r, green, b)`` has OpenCV's gray ``gray`` (int64; outside 0..255
    where none in range has). A green step moves the gray by 0.587: every gray level is reached, by one
    green or two."""
    wr, wg, wb = GRAY_WEIGHTS
    need = (gray.astype(np.int64) << GRAY_SHIFT) - (1 << (GRAY_SHIFT - 1)) - wr * r.astype(np.int64) \
        - wb * b.astype(np.int64)
    return -((-need) // wg)  # ceil(need / wg)


def _load(path: Path, what: str) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except FileNotFoundError:
        raise RecordingError(f"{path.parent}: a recording of fiber sums without {path.name}") from None
    except (OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: garbled or truncated {what} ({exc})") from None


class FiberSumFrames:
    """The frames of a fiber-sums recording, as an array-like of shape (N, H, W[, 3]), uint8.

    Indexing with an integer makes that frame (a new array); a slice within the rest frames is a view of
    them. ``np.asarray`` makes every frame (small recordings only).

    Parameters
    ----------
    directory : Path
    rest_frames : int
        The recording's rest frames (``meta.json``), kept as they are in ``rest.npy``.
    stated : dict, optional
        ``meta.json``'s ``frame_storage`` (its ``frame_shape`` and ``fibers``, checked against the files).

    Raises
    ------
    RecordingError
        Naming the file that is missing, garbled, or does not fit the others.
    """

    def __init__(self, directory: Path, rest_frames: int, stated: dict[str, Any] | None = None) -> None:
        rest = _load(directory / REST_FRAMES, "rest frames")
        if rest.dtype != np.uint8 or rest.ndim not in (3, 4) or rest.shape[0] != rest_frames:
            raise RecordingError(f"{directory / REST_FRAMES}: must hold the {rest_frames} rest frames, uint8 "
                                 f"(K,H,W) or (K,H,W,3), got {rest.dtype} {rest.shape}")
        frame_shape = tuple(int(v) for v in rest.shape[1:])
        try:
            infer_pixel_format(frame_shape)
        except FrameMismatchError:
            raise RecordingError(f"{directory / REST_FRAMES}: frames of shape {frame_shape} are not gray or RGB") \
                from None
        self.table = read_spots(directory / SPOTS, frame_shape)
        sums = _load(directory / SUMS, "fiber sums")
        n = self.table.n_fibers
        stated = stated or {}
        if "frame_shape" in stated and list(stated["frame_shape"]) != list(frame_shape):
            raise RecordingError(f"{directory / 'meta.json'}: frame_shape {stated['frame_shape']} but the rest frames "
                                 f"are {list(frame_shape)}")
        if "fibers" in stated and stated["fibers"] != n:
            raise RecordingError(f"{directory / 'meta.json'}: {stated['fibers']} fibers but {SPOTS} holds {n}")
        if sums.dtype not in (np.uint16, np.uint32) or sums.ndim != 2 or sums.shape[1] != n:
            raise RecordingError(f"{directory / SUMS}: must be uint16 or uint32 of shape (frames, {n}), got "
                                 f"{sums.dtype} {sums.shape}")
        counts = self.table.pixel_count
        if sums.shape[0] and np.any(np.asarray(sums).max(axis=0) > 255 * counts):
            raise RecordingError(f"{directory / SUMS}: a sum larger than its fiber's pixels can hold")
        self._colours: np.ndarray | None = None
        if len(frame_shape) == 3 and (directory / COLOURS).exists():
            colours = _load(directory / COLOURS, "fiber colours")
            if colours.dtype != sums.dtype or colours.shape != (sums.shape[0], n, 3):
                raise RecordingError(f"{directory / COLOURS}: must be {sums.dtype} of shape ({sums.shape[0]}, {n}, "
                                     f"3) beside {SUMS}, got {colours.dtype} {colours.shape}")
            self._colours = colours
        self._rest, self._sums = rest, sums
        self.rest_frames = rest_frames
        self.shape: tuple[int, ...] = (rest_frames + int(sums.shape[0]), *frame_shape)
        self.dtype = np.dtype(np.uint8)
        self.ndim = len(self.shape)
        self._check_rest_fits(directory, self._prepare(frame_shape, counts), counts)

    def _check_rest_fits(self, directory: Path, at_rest: np.ndarray, counts: np.ndarray) -> None:
        """The rest frames' light of the typical fiber (``at_rest``: each fiber's sum of the rest frames' mean
        gray) is the first sums' (:data:`REST_FIT`)."""
        rows = min(FIT_ROWS, int(self._sums.shape[0]))
        if not rows:
            return
        t = self.table
        after = np.median(np.asarray(self._sums[:rows], dtype=np.float64), axis=0)
        live = ~np.asarray(t.dead, dtype=bool)
        off = np.abs(at_rest - after) / np.maximum(after, counts)  # at least a gray level a pixel
        if np.median(off[live] if live.any() else off) > REST_FIT:
            raise RecordingError(f"{directory / REST_FRAMES}: the rest frames do not fit the fiber sums after them "
                                 f"(the typical fiber's light differs by {np.median(off):.0%}: frames shifted, "
                                 "replaced or black?)")

    def _prepare(self, frame_shape: tuple[int, ...], counts: np.ndarray) -> np.ndarray:
        """The rest level of every pixel, the groups' weights and the zones around them; each fiber's sum of the
        rest level, shape (N,)."""
        from scipy import ndimage

        h, w = frame_shape[:2]
        level = np.zeros((h, w), dtype=np.float64)
        for frame in self._rest:
            level += frame if frame.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
        level /= len(self._rest)
        flat = level.reshape(-1)
        self._base = np.clip(np.rint(flat), 0, 255).astype(np.uint8)
        t = self.table
        self._index = t.pixel_index.astype(np.intp)
        self._fiber = np.repeat(np.arange(t.n_fibers), counts)
        self._starts = t.pixel_start[:-1].astype(np.intp)
        self._ends = t.pixel_start[1:].astype(np.intp) - 1
        weight = flat[self._index]
        rest_sum = at_rest = np.add.reduceat(weight, self._starts)
        dark = rest_sum <= 0  # no light at rest (a dead fiber on black): share equally
        weight[dark[self._fiber]] = 1.0
        rest_sum = np.where(dark, counts.astype(np.float64), rest_sum)
        self._weight, self._rest_sum, self._counts = weight, rest_sum, counts
        label = np.full(h * w, -1, dtype=np.int64)
        label[self._index] = self._fiber
        distance, (rows, cols) = ndimage.distance_transform_edt(label.reshape(h, w) < 0, return_indices=True)
        reach = ZONE_FRACTION * float(np.median(np.sqrt(counts / np.pi)))
        zone = np.flatnonzero((distance.reshape(-1) > 0) & (distance.reshape(-1) <= reach))
        self._zone = zone
        self._zone_fiber = label[(rows.reshape(-1) * w + cols.reshape(-1))[zone]]
        self._zone_level = flat[zone]
        self._label = label
        if self._colours is not None:  # the rest frames' colour, pixel by pixel, (H*W, 3) float64
            colour = np.zeros((h * w, 3), dtype=np.float64)
            for frame in self._rest:
                colour += frame.reshape(-1, 3)
            self._rest_colour = colour / len(self._rest)
        return at_rest

    # -- array-like ------------------------------------------------------------------

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, slice):
            start, stop, step = key.indices(len(self))
            if stop <= self.rest_frames and step > 0:
                return self._rest[key]
            return np.stack([self.frame(i) for i in range(start, stop, step)]) if len(range(start, stop, step)) \
                else np.zeros((0, *self.shape[1:]), np.uint8)
        index = int(key)
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"frame {key} outside 0..{len(self) - 1}")
        return self.frame(index)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = np.stack([self.frame(i) for i in range(len(self))])
        return out if dtype is None else out.astype(dtype)

    # -- frames ------------------------------------------------------------------------

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` (0 .. N-1) as a new C-contiguous array."""
        if index < self.rest_frames:
            return np.array(self._rest[index])
        sums = np.asarray(self._sums[index - self.rest_frames], dtype=np.float64)
        ratio = sums / self._rest_sum
        out = self._base.copy()
        out[self._zone] = np.clip(np.rint(self._zone_level * ratio[self._zone_fiber]), 0, 255)
        out[self._index] = self._share(sums, ratio)
        gray = out.reshape(self.shape[1:3])
        if len(self.shape) == 3:
            return gray
        if self._colours is None:
            return np.repeat(gray[:, :, None], 3, axis=2)
        return self._coloured(out, ratio, np.asarray(self._colours[index - self.rest_frames], dtype=np.float64),
                              sums)

    def _coloured(self, gray: np.ndarray, ratio: np.ndarray, colour_sums: np.ndarray,
                  sums: np.ndarray) -> np.ndarray:
        """The RGB frame of gray levels ``gray`` (H*W,) whose fibers have the channel sums ``colour_sums``
        (N, 3) and gray sums ``sums``: see the module docstring."""
        out = np.clip(np.rint(self._rest_colour), 0, 255).astype(np.uint8)
        zone = self._zone
        out[zone] = np.clip(np.rint(self._rest_colour[zone] * ratio[self._zone_fiber][:, None]), 0, 255)
        per_gray = colour_sums / np.maximum(sums, 1.0)[:, None]  # each fiber's channel per gray level
        g = gray[self._index].astype(np.int64)
        fiber = self._fiber
        # red and blue: each group's recorded sum exactly (within 0..255), in proportion to the pixels' gray
        r = np.clip(self._rounded(g * per_gray[fiber, 0], colour_sums[:, 0]), 0, 255).astype(np.int64)
        b = np.clip(self._rounded(g * per_gray[fiber, 2], colour_sums[:, 2]), 0, 255).astype(np.int64)
        green = green_for(g, r, b)
        # where green + 1 gives the same gray too, take it on as many pixels as bring the group's green to
        # its recorded sum (the smallest green alone reads about a third of a level dark)
        spare = (green >= 0) & (green < 255) & (gray_of(r, green + 1, b) == g)
        short = colour_sums[:, 1] - np.bincount(fiber, np.clip(green, 0, 255), minlength=sums.size)
        before = np.cumsum(spare) - spare
        rank = before - before[self._starts][fiber]  # spare pixels before this one in its group
        green = green + (spare & (rank < short[fiber]))
        fits = (green >= 0) & (green <= 255)
        pixels = np.where(fits[:, None], np.stack([r, np.clip(green, 0, 255), b], axis=1), g[:, None])
        pixels = pixels.astype(np.uint8)
        seen = cv2.cvtColor(pixels.reshape(1, -1, 3), cv2.COLOR_RGB2GRAY).reshape(-1)
        off = seen != g  # (another OpenCV's rounding): gray pixels, whose gray is exact in any
        pixels[off] = g[off, None]
        out[self._index] = pixels
        return out.reshape(*self.shape[1:3], 3)

    def _share(self, sums: np.ndarray, ratio: np.ndarray) -> np.ndarray:
        """Each group's pixels, in proportion to their rest level, adding up to the group's sum exactly."""
        values = self._rounded(self._weight * ratio[self._fiber], sums)
        bad = (values < 0) | (values > 255)
        if bad.any():  # a group brighter than its rest level allows: equal shares, still exact
            for f in np.unique(self._fiber[bad]):
                lo, n = int(self._starts[f]), int(self._counts[f])
                q, r = divmod(int(sums[f]), n)
                values[lo:lo + n] = q + (np.arange(n) < r)
        return values.astype(np.uint8)

    def _rounded(self, part: np.ndarray, sums: np.ndarray) -> np.ndarray:
        """Integers near ``part`` (one value per fiber pixel, float64) whose groups add up to ``sums``
        exactly: the rounded running total within each group, differenced (float64)."""
        total = np.cumsum(part)
        before = np.concatenate([[0.0], total[self._ends[:-1]]])
        within = total - before[self._fiber]
        within[self._ends] = sums  # the group's total, exact (no float drift)
        rounded = np.floor(within + 0.5)
        prev = np.empty_like(rounded)
        prev[1:] = rounded[:-1]
        prev[self._starts] = 0.0
        return rounded - prev

    def exact_for(self, table: FiberTable) -> bool:
        """True when every fiber of ``table`` reads exactly one of the recording's pixel groups (a bundle
        calibrated from this recording's rest frames): its fiber light is then the raw frames'."""
        if (table.height, table.width) != self.shape[1:3]:
            return False
        lab = self._label[table.pixel_index.astype(np.intp)]
        starts = table.pixel_start[:-1].astype(np.intp)
        lo, hi = np.minimum.reduceat(lab, starts), np.maximum.reduceat(lab, starts)
        return bool(np.all(lo == hi) and np.all(lo >= 0) and np.array_equal(self._counts[lo], table.pixel_count))
