"""The calibration bundle's file: one versioned ``.npz`` holding everything the runtime needs.

Format (a contract, see docs/formats.md): an uncompressed NumPy ``.npz``
archive, loaded with ``allow_pickle=False``. Member ``meta`` is UTF-8 JSON (as
a uint8 array) with ``format``, ``version``, the frame size and pixel format
the bundle was built for, the image transform, surface grid, thresholds and
reports; the other members are plain numeric arrays (the three
``interpolation_*`` members of the surface factors are optional: all or none,
see :class:`~optitac_edge.core.surface.SurfaceFactors`). Member ``digest`` is the
SHA-256 over ``meta`` and every array (name, dtype, shape, bytes), so a
bit-flipped or truncated file is refused. Written atomically: temporary file
in the same directory, fsync, rename, fsync of the directory.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.corrections import read_models
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.options import ContactOptions, ContactThresholds
from optitac_edge.core.surface import SurfaceFactors
from optitac_edge.errors import BundleError, OutputError
from optitac_edge.io.files import AtomicFile
from optitac_edge.io.npz_members import NpzLimits, read_npz_members

BUNDLE_FORMAT = "optitac-edge-calibration"
BUNDLE_VERSION = 1
#: Largest member a bundle may hold (the interpolation matrix of 1027 fibers on a 100 x 100 mesh is 41 MiB).
MAX_MEMBER_BYTES = 256 << 20
#: Largest bundle, all members together, uncompressed.
MAX_BUNDLE_BYTES = 512 << 20
#: Most members a bundle may hold (calibration models add a few each).
MAX_MEMBERS = 256
_LIMITS = NpzLimits("calibration bundle", MAX_MEMBER_BYTES, MAX_BUNDLE_BYTES, MAX_MEMBERS)
#: Bundle members holding :class:`SurfaceFactors` (all three or none), by field name.
FACTOR_MEMBERS = {
    "vertex_operator": "interpolation_vertex_operator",
    "cell_columns": "interpolation_cell_columns",
    "cell_weights": "interpolation_cell_weights",
}


def _load_factors(path: Path, members: Mapping[str, np.ndarray]) -> SurfaceFactors | None:
    """The surface factors of a loaded bundle, None if it has none; BundleError if incomplete or invalid."""
    present = [m for m in FACTOR_MEMBERS.values() if m in members]
    if not present:
        return None
    if len(present) != len(FACTOR_MEMBERS):
        missing = sorted(set(FACTOR_MEMBERS.values()) - set(present))
        raise BundleError(f"{path}: incomplete surface factors in calibration bundle "
                          f"(missing {', '.join(missing)})")
    try:
        return SurfaceFactors(**{f: members[m] for f, m in FACTOR_MEMBERS.items()})
    except ValueError as exc:
        raise BundleError(f"{path}: invalid surface factors in calibration bundle: {exc}") from None


def _arrays(bundle: CalibrationBundle) -> dict[str, np.ndarray]:
    t = bundle.fibers
    arrays: dict[str, np.ndarray] = {
        "layout_ids": bundle.layout.ids.astype(np.int64),
        "layout_xy_mm": bundle.layout.xy_mm.astype(np.float64),
        "fiber_pixel_index": t.pixel_index.astype(np.int32),
        "fiber_pixel_start": t.pixel_start.astype(np.int64),
        "fiber_centroid_px": t.centroid_px.astype(np.float64),
        "fiber_dead": t.dead.astype(np.uint8),
        "fiber_unmatched_px": t.unmatched_px.astype(np.float64).reshape(-1, 2),
        "interpolation": np.ascontiguousarray(bundle.interpolation, dtype=np.float32),
    }
    if bundle.surface_factors is not None:
        for f, m in FACTOR_MEMBERS.items():
            arrays[m] = np.ascontiguousarray(getattr(bundle.surface_factors, f))
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


def save_bundle(bundle: CalibrationBundle, path: str | Path) -> CalibrationBundle:
    """Write ``bundle`` to ``path`` atomically; returns it with its id and time set.

    The calibration id is the first 16 hex digits of the content digest.

    Raises
    ------
    OutputError
        If ``path`` exists and is not a regular file, or cannot be written
        (the old bundle, if any, is left as it was).
    """
    path = Path(path)
    created = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    bundle = replace(bundle, created_utc=created)
    arrays = _arrays(bundle)
    meta_bytes = json.dumps(_meta(bundle), sort_keys=True).encode()
    digest = _digest(meta_bytes, arrays)
    members = {**arrays, "meta": np.frombuffer(meta_bytes, dtype=np.uint8),
               "digest": np.frombuffer(digest.encode(), dtype=np.uint8)}
    with AtomicFile(path, "wb") as f:
        try:
            np.savez(f.file, **members)  # type: ignore[arg-type]  # numpy's stub: the first keyword is allow_pickle
        except OSError as exc:
            raise OutputError(f"{path}: {exc.strerror or exc}") from None
    return replace(bundle, calibration_id=digest[:16], source=str(path))


def _load_options(path: Path, meta: Mapping[str, Any]) -> ContactOptions:
    if "contact_options" not in meta:  # written before the options existed: the paper's method
        return ContactOptions.paper()
    try:
        return ContactOptions.from_dict(meta["contact_options"])
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{path}: bad contact_options in calibration bundle: {exc}") from None


def _read_members(path: Path) -> dict[str, np.ndarray]:
    """Every member of the ``.npz``, each checked for size before it is read or decompressed
    (:func:`~optitac_edge.io.npz_members.read_npz_members`)."""
    return read_npz_members(path, _LIMITS, BundleError)


def load_bundle(path: str | Path) -> CalibrationBundle:
    """Read and verify a bundle written by :func:`save_bundle`.

    Raises
    ------
    BundleError
        If the file is missing, not a bundle, truncated, corrupted (digest
        mismatch), of another format version, or has incomplete or invalid
        surface factors.
    """
    path = Path(path)
    try:
        members = _read_members(path)
    except BundleError:
        raise
    except FileNotFoundError:
        raise BundleError(f"{path}: calibration bundle not found") from None
    except IsADirectoryError:
        raise BundleError(f"{path}: is a directory, not a calibration bundle") from None
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zipfile.LargeZipFile) as exc:
        raise BundleError(f"{path}: not a readable calibration bundle (corrupted or truncated: {exc})") from None
    except Exception as exc:  # noqa: BLE001 - zipfile/zlib raise assorted errors on damaged data
        raise BundleError(f"{path}: corrupted calibration bundle ({type(exc).__name__})") from None
    try:
        meta_bytes = members.pop("meta").tobytes()
        stored = members.pop("digest").tobytes().decode("ascii")
        meta = json.loads(meta_bytes)
    except (KeyError, UnicodeDecodeError, ValueError, RecursionError):
        raise BundleError(f"{path}: not a calibration bundle (no valid meta)") from None
    if not isinstance(meta, dict) or meta.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{path}: not an optitac-edge calibration bundle")
    if meta.get("version") != BUNDLE_VERSION:
        raise BundleError(
            f"{path}: bundle version {meta.get('version')!r}, this optitac-edge reads version {BUNDLE_VERSION}"
        )
    if _digest(meta_bytes, members) != stored:
        raise BundleError(f"{path}: calibration bundle is corrupted (checksum mismatch)")
    factors = _load_factors(path, members)
    _check_meta_kinds(path, meta)
    try:
        frame = meta["frame"]
        fibers = FiberTable(
            height=int(frame["height"]), width=int(frame["width"]), pixel_format=str(frame["pixel_format"]),
            pixel_index=members["fiber_pixel_index"], pixel_start=members["fiber_pixel_start"],
            centroid_px=members["fiber_centroid_px"], dead=members["fiber_dead"].astype(bool),
            unmatched_px=members["fiber_unmatched_px"],
        )
        bundle = CalibrationBundle(
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
            surface_factors=factors,
            source=str(path),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise BundleError(f"{path}: inconsistent calibration bundle ({type(exc).__name__}: {exc})") from None
    try:
        read_models(bundle)
    except BundleError as exc:
        raise BundleError(f"{path}: {exc}") from None
    return bundle


def readable_bundle(path: str | Path) -> CalibrationBundle | None:
    """The bundle at ``path``, or None: no file there, or not a readable bundle (what a new one may replace)."""
    if not Path(path).is_file():
        return None
    try:
        return load_bundle(path)
    except BundleError:
        return None


#: Members of the bundle's ``extra`` that, when present, are objects (the steps' summaries, the orientation
#: record, the region a sensor's bundle was placed in).
_OBJECT_EXTRAS = ("centroid_fit", "width_fit", "shapes_fit", "depth_fit", "orientation", "region")


def _check_meta_kinds(path: Path, meta: Mapping[str, Any]) -> None:
    """The meta's parts are of the kinds the readers expect (a crafted bundle with a valid digest is refused
    here in one line, not with an AttributeError later)."""
    extra = meta.get("extra")
    if not isinstance(extra, dict) or not all(isinstance(k, str) for k in extra):
        raise BundleError(f"{path}: inconsistent calibration bundle ('extra' must be an object)")
    if not isinstance(meta.get("fiber_map_report"), dict):
        raise BundleError(f"{path}: inconsistent calibration bundle ('fiber_map_report' must be an object)")
    for key in _OBJECT_EXTRAS:
        if key in extra and not isinstance(extra[key], dict):
            raise BundleError(f"{path}: inconsistent calibration bundle ('extra.{key}' must be an object)")
