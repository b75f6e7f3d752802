"""The calibration bundle: one versioned file holding everything the runtime needs.

Format (a contract, see docs/formats.md): an uncompressed NumPy ``.npz``
archive, loaded with ``allow_pickle=False``. Member ``meta`` is UTF-8 JSON (as
a uint8 array) with ``format``, ``version``, the frame size and pixel format
the bundle was built for, the image transform, surface grid, thresholds and
reports; the other members are plain numeric arrays. Member ``digest`` is the
SHA-256 over ``meta`` and every array (name, dtype, shape, bytes), so a
bit-flipped or truncated file is refused. Written atomically: temporary file
in the same directory, fsync, rename, fsync of the directory.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BundleError
from .fiber_table import FiberTable
from .grid import SurfaceGrid
from .image_transform import ImageTransform
from .layout import FiberLayout

BUNDLE_FORMAT = "optitac-edge-calibration"
BUNDLE_VERSION = 1
#: Leading contact-free frames averaged into the baseline (the paper's 5).
BASELINE_FRAMES = 5
#: Most simultaneous contacts the pipeline reports.
MAX_CONTACTS = 4


@dataclass(frozen=True)
class ContactThresholds:
    """When the surface counts as a contact.

    Attributes
    ----------
    threshold : float
        Gray levels. The inverted, baseline-subtracted surface is truncated
        below this value (kept as it is above it).
    min_area_mm2 : float
        Minimum area above the threshold for a contact to be reported.
    """

    threshold: float = 6.0
    min_area_mm2: float = 1.0


@dataclass(frozen=True)
class ContactOptions:
    """Improvements beyond the paper's per-frame method, each switchable.

    Stored in the bundle's meta under ``contact_options`` (strictly validated:
    an unknown key or a bad value is a :class:`BundleError` naming the key).
    :meth:`paper` switches everything off: the pipeline then does exactly the
    paper's method with :class:`ContactThresholds` (and agrees with
    :class:`~optitac_edge.reference.ReferencePipeline`). A bundle file without
    ``contact_options`` (written before they existed) loads as :meth:`paper`.

    Signal units: gray levels, or relative units (fraction of the fiber's rest
    light above the black level) when ``relative`` is set. The *levels* below
    (truncation, off, on) are in those units.

    Attributes
    ----------
    relative : bool
        Per-fiber signal ``(baseline - mean) / (baseline - black_level)``:
        removes the fibers' transmission spread and LED vignetting, and makes
        the signal invariant to the overall brightness. The paper threshold
        (when ``noise_levels`` is off) is converted with the median rest level.
    noise_levels : bool
        Truncation / off / on levels from the rest-frame noise measured at
        calibration: ``max(k * noise, floor)`` (``noise_rel`` or ``noise_gray``,
        the worst surface cell's noise std). Off: the paper's single
        ``ContactThresholds.threshold`` for all three.
    hysteresis : bool
        A contact starts when a blob's peak exceeds the *on* level and stays
        while it exceeds the lower *off* level. Off: the on level for both.
    peak_fraction : float
        Each contact is truncated at ``max(truncation level, peak_fraction *
        its peak)``: widths and centroid then do not depend on the signal
        amplitude. 0 switches it off (truncation level only).
    shape_fraction : float
        The shape features (Hu, q4) are taken from the contact binarized at
        ``max(truncation level, shape_fraction * its peak)``. 0: the same
        cells as the moments (the paper: the truncated surface).
    fill_dead : bool
        Dead fibers take the (harmonic) mean of their neighbours, folded into
        the interpolation matrix (``A' = A F``, no per-frame cost). Off: 0.
    max_contacts : int
        1..4. More than 1: separate blobs (8-connected) of the surface above
        ``max(truncation level, split_fraction * the strongest peak)`` are
        separate contacts, strongest ``m00`` first. 1: the whole surface
        above the truncation level is one contact (the paper).
    split_fraction : float
        See ``max_contacts`` (the skin's spread joins nearby presses at the
        noise level, so blobs are separated higher up).
    track_baseline : bool
        Exponential moving average of the fiber means (time constant
        ``baseline_tau_s`` from the frame timestamps) while there is no
        contact, no contact ended in the last ``holdoff_s`` seconds and no
        fiber's signal departs from the median fiber signal by the off level
        or more (a uniform drift is tracked, a local press is not).
    compensate_gain : bool
        Common-mode LED gain compensation: every frame the fiber light above
        the black level is divided by the frame's LED gain relative to the
        baseline, ``g``, before the signal, so an LED dimming during a
        recording is not a press. ``g`` is the median ratio ``(mean -
        black_level) / (baseline - black_level)`` of the fibers within the off
        level of the brightest-relative cluster (contacts only darken
        fibers), limited to the gain of the last contact-free frame
        ``+- (truncation level / 10 + gain_rate_per_s * seconds since)``: a
        press covering the whole array cannot be taken for a dimming (its
        gain is held), and a contact that drift started ends when the limit
        has grown to the drift. The baseline tracking then follows the
        gain-compensated means (per-fiber drift only).
    gain_rate_per_s : float
        Fastest LED gain change (relative, per second) followed during a contact.
    k_trunc, k_off, k_on : float
        Levels in units of the measured noise.
    floor_trunc, floor_off, floor_on : float
        Lower bounds of the levels, relative units (converted to gray levels
        with the median rest level when ``relative`` is off).
    baseline_tau_s, holdoff_s : float
        See ``track_baseline``. The holdoff defaults to 0: the quiet-frame check
        already keeps a press's residue out of the baseline, and with presses in
        quick succession (a rest frame or two between them) any holdoff stops
        the tracking, so per-fiber drift accumulates (then, with the LED gain
        compensated, it alone can hold a contact on through a rest frame).
    noise_rel, noise_gray : float
        Measured by calibration: the largest per-cell std of the surface
        interpolated from the rest frames' per-fiber temporal noise, relative
        units and gray levels; 0 if unknown (then only the floors apply).
    black_level : float
        Measured by calibration: gray level of the image between the fibers
        (median), subtracted from the baseline in the relative signal.
    """

    relative: bool = True
    noise_levels: bool = True
    hysteresis: bool = True
    peak_fraction: float = 0.4
    shape_fraction: float = 0.3
    split_fraction: float = 0.5
    fill_dead: bool = True
    max_contacts: int = 4
    track_baseline: bool = True
    compensate_gain: bool = True
    k_trunc: float = 4.0
    k_off: float = 6.0
    k_on: float = 10.0
    floor_trunc: float = 0.004
    floor_off: float = 0.006
    floor_on: float = 0.01
    baseline_tau_s: float = 1.0
    holdoff_s: float = 0.0
    gain_rate_per_s: float = 0.005
    noise_rel: float = 0.0
    noise_gray: float = 0.0
    black_level: float = 0.0

    #: Switches (``paper()`` turns them off).
    SWITCHES = ("relative", "noise_levels", "hysteresis", "peak_fraction", "shape_fraction", "fill_dead",
                "max_contacts", "track_baseline", "compensate_gain")

    def __post_init__(self) -> None:
        for name in ("relative", "noise_levels", "hysteresis", "fill_dead", "track_baseline",
                     "compensate_gain"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be true or false, got {getattr(self, name)!r}")
        mc = self.max_contacts
        if isinstance(mc, bool) or not isinstance(mc, int) or not 1 <= mc <= MAX_CONTACTS:
            raise ValueError(f"max_contacts must be an integer 1..{MAX_CONTACTS}, got {mc!r}")
        for name in ("peak_fraction", "shape_fraction", "split_fraction", "k_trunc", "k_off", "k_on", "floor_trunc", "floor_off",
                     "floor_on", "baseline_tau_s", "holdoff_s", "gain_rate_per_s", "noise_rel",
                     "noise_gray", "black_level"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        for name in ("peak_fraction", "shape_fraction", "split_fraction"):
            if not getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be < 1, got {getattr(self, name)!r}")
        if self.baseline_tau_s <= 0:
            raise ValueError(f"baseline_tau_s must be > 0, got {self.baseline_tau_s!r}")

    @classmethod
    def paper(cls, **measured: Any) -> ContactOptions:
        """All improvements off: the paper's method (measured values may be kept)."""
        return cls(relative=False, noise_levels=False, hysteresis=False, peak_fraction=0.0, shape_fraction=0.0,
                   fill_dead=False, max_contacts=1, track_baseline=False, compensate_gain=False,
                   **measured)

    @property
    def is_paper(self) -> bool:
        p = ContactOptions.paper()
        return all(getattr(self, k) == getattr(p, k) for k in self.SWITCHES)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ContactOptions:
        """Strict: unknown keys and bad values raise ``ValueError`` naming the key."""
        if not isinstance(d, Mapping):
            raise TypeError("contact_options must be an object")
        known = {f.name for f in fields(cls)}
        for key in d:
            if key not in known:
                raise ValueError(f"unknown contact option {key!r}")
        values = dict(d)
        for key in ("peak_fraction", "shape_fraction", "split_fraction", "k_trunc", "k_off", "k_on", "floor_trunc", "floor_off",
                    "floor_on", "baseline_tau_s", "holdoff_s", "gain_rate_per_s", "noise_rel",
                    "noise_gray", "black_level"):
            if key in values and isinstance(values[key], int) and not isinstance(values[key], bool):
                values[key] = float(values[key])
        return cls(**values)


@dataclass(frozen=True, eq=False)
class CalibrationBundle:
    """Everything the runtime pipeline needs, as loaded from one file.

    Attributes
    ----------
    layout : FiberLayout
        The sensor's CAD layout (N fibers).
    transform : ImageTransform
        Fitted layout -> image transform.
    fibers : FiberTable
        Fiber lookup table; also records the frame size and pixel format.
    grid : SurfaceGrid
        The interpolation mesh.
    interpolation : ndarray, shape (grid.n ** 2, N), float32
        Surface = ``interpolation @ fiber_values`` (row-major mesh order);
        rows of mesh points outside the array are zero.
    thresholds : ContactThresholds
        The paper's threshold and minimum area.
    options : ContactOptions
        Improvements beyond the paper and the noise measured at calibration.
    fiber_map_report : dict
        JSON-able summary of the fiber calibration.
    extra_arrays : mapping of str to ndarray
        Later calibration models (numeric arrays only).
    extra_meta : dict
        JSON-able parameters of later calibration models.
    """

    layout: FiberLayout
    transform: ImageTransform
    fibers: FiberTable
    grid: SurfaceGrid
    interpolation: np.ndarray
    thresholds: ContactThresholds = ContactThresholds()
    options: ContactOptions = ContactOptions()
    baseline_frames: int = BASELINE_FRAMES
    fiber_map_report: dict[str, Any] = field(default_factory=dict)
    extra_arrays: Mapping[str, np.ndarray] = field(default_factory=dict)
    extra_meta: dict[str, Any] = field(default_factory=dict)
    created_utc: str = ""
    calibration_id: str = ""

    def __post_init__(self) -> None:
        n = self.layout.n_fibers
        if self.fibers.n_fibers != n:
            raise ValueError(f"fiber table has {self.fibers.n_fibers} fibers, layout {n}")
        if self.interpolation.shape != (self.grid.n * self.grid.n, n):
            raise ValueError(f"interpolation matrix has shape {self.interpolation.shape}")

    def with_updates(self, **changes: Any) -> CalibrationBundle:
        """A copy with some fields replaced (e.g. a new calibration model)."""
        return replace(self, **changes)


def _arrays(bundle: CalibrationBundle) -> dict[str, np.ndarray]:
    t = bundle.fibers
    arrays = {
        "layout_ids": bundle.layout.ids.astype(np.int64),
        "layout_xy_mm": bundle.layout.xy_mm.astype(np.float64),
        "fiber_pixel_index": t.pixel_index.astype(np.int32),
        "fiber_pixel_start": t.pixel_start.astype(np.int64),
        "fiber_centroid_px": t.centroid_px.astype(np.float64),
        "fiber_dead": t.dead.astype(np.uint8),
        "fiber_unmatched_px": t.unmatched_px.astype(np.float64).reshape(-1, 2),
        "interpolation": np.ascontiguousarray(bundle.interpolation, dtype=np.float32),
    }
    for name, value in bundle.extra_arrays.items():
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"extra array {name!r} is not numeric")
        arrays[f"extra/{name}"] = arr
    return arrays


def _meta(bundle: CalibrationBundle) -> dict[str, Any]:
    return {
        "format": BUNDLE_FORMAT,
        "version": BUNDLE_VERSION,
        "created_utc": bundle.created_utc,
        "frame": {"height": bundle.fibers.height, "width": bundle.fibers.width,
                  "pixel_format": bundle.fibers.pixel_format},
        "transform": bundle.transform.to_dict(),
        "grid": asdict(bundle.grid),
        "thresholds": asdict(bundle.thresholds),
        "contact_options": bundle.options.to_dict(),
        "baseline_frames": bundle.baseline_frames,
        "fiber_map_report": bundle.fiber_map_report,
        "extra": bundle.extra_meta,
    }


def _digest(meta_bytes: bytes, arrays: Mapping[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    h.update(meta_bytes)
    for name in sorted(arrays):
        arr = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{arr.dtype.str}|{arr.shape}".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files of saves that were killed (their process no longer exists)."""
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            pid = int(tmp.name[len(path.name) + 2:-4])
        except ValueError:
            continue
        if pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except OSError:  # alive but not ours: leave it
            continue


def save_bundle(bundle: CalibrationBundle, path: str | Path) -> CalibrationBundle:
    """Write ``bundle`` to ``path`` atomically; returns it with its id and time set.

    The calibration id is the first 16 hex digits of the content digest.
    """
    path = Path(path)
    created = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    bundle = replace(bundle, created_utc=created)
    arrays = _arrays(bundle)
    meta_bytes = json.dumps(_meta(bundle), sort_keys=True).encode()
    digest = _digest(meta_bytes, arrays)
    members = {**arrays, "meta": np.frombuffer(meta_bytes, dtype=np.uint8),
               "digest": np.frombuffer(digest.encode(), dtype=np.uint8)}
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as f:
            np.savez(f, **members)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return replace(bundle, calibration_id=digest[:16])


def _load_options(path: Path, meta: Mapping[str, Any]) -> ContactOptions:
    if "contact_options" not in meta:  # written before the options existed: the paper's method
        return ContactOptions.paper()
    try:
        return ContactOptions.from_dict(meta["contact_options"])
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{path}: bad contact_options in calibration bundle: {exc}") from None


def load_bundle(path: str | Path) -> CalibrationBundle:
    """Read and verify a bundle written by :func:`save_bundle`.

    Raises
    ------
    BundleError
        If the file is missing, not a bundle, truncated, corrupted (digest
        mismatch) or of another format version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            members = {name: npz[name] for name in npz.files}
    except FileNotFoundError:
        raise BundleError(f"{path}: calibration bundle not found") from None
    except IsADirectoryError:
        raise BundleError(f"{path}: is a directory, not a calibration bundle") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile) as exc:
        raise BundleError(f"{path}: not a readable calibration bundle (corrupted or truncated: {exc})") from None
    except Exception as exc:  # zipfile/zlib raise assorted errors on damaged data
        raise BundleError(f"{path}: corrupted calibration bundle ({type(exc).__name__})") from None
    try:
        meta_bytes = members.pop("meta").tobytes()
        stored = members.pop("digest").tobytes().decode("ascii")
        meta = json.loads(meta_bytes)
    except (KeyError, UnicodeDecodeError, json.JSONDecodeError):
        raise BundleError(f"{path}: not a calibration bundle (no valid meta)") from None
    if not isinstance(meta, dict) or meta.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{path}: not an optitac-edge calibration bundle")
    if meta.get("version") != BUNDLE_VERSION:
        raise BundleError(
            f"{path}: bundle version {meta.get('version')!r}, this optitac-edge reads version {BUNDLE_VERSION}"
        )
    if _digest(meta_bytes, members) != stored:
        raise BundleError(f"{path}: calibration bundle is corrupted (checksum mismatch)")
    try:
        frame = meta["frame"]
        fibers = FiberTable(
            height=int(frame["height"]), width=int(frame["width"]), pixel_format=str(frame["pixel_format"]),
            pixel_index=members["fiber_pixel_index"], pixel_start=members["fiber_pixel_start"],
            centroid_px=members["fiber_centroid_px"], dead=members["fiber_dead"].astype(bool),
            unmatched_px=members["fiber_unmatched_px"],
        )
        return CalibrationBundle(
            layout=FiberLayout(ids=members["layout_ids"], xy_mm=members["layout_xy_mm"]),
            transform=ImageTransform(**meta["transform"]),
            fibers=fibers,
            grid=SurfaceGrid(**meta["grid"]),
            interpolation=members["interpolation"],
            thresholds=ContactThresholds(**meta["thresholds"]),
            options=_load_options(path, meta),
            baseline_frames=int(meta["baseline_frames"]),
            fiber_map_report=meta["fiber_map_report"],
            extra_arrays={k[len("extra/"):]: v for k, v in members.items() if k.startswith("extra/")},
            extra_meta=meta["extra"],
            created_utc=meta["created_utc"],
            calibration_id=stored[:16],
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise BundleError(f"{path}: inconsistent calibration bundle ({exc})") from None
