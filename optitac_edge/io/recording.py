"""Recordings: a directory of frames plus metadata and optional ground truth.

Layout of a recording directory (a contract; see docs/formats.md):

``frames.npy``  uint8, shape (N, H, W) gray or (N, H, W, 3) RGB; opened
                memory-mapped and streamed, never loaded whole. Or, when
                ``meta.json`` says ``frame_storage: {"storage": "fibers"}``,
                ``rest.npy``, ``spots.npz`` and ``sums.npy``: the rest frames
                and each fiber's light for the others
                (:mod:`optitac_edge.io.frame_store`; read back as frames by
                :mod:`optitac_edge.io.fiber_sums`).
``meta.json``   at least ``rest_frames`` (int >= 5, leading contact-free
                frames) and ``fps`` (> 0); other keys are kept as ``extra``.
                A collection continued after an interruption lists the
                ``segments`` of its frames, each with the shift its times got.
``truth.csv``   optional, header
                ``frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm``,
                optionally followed by ``phase,rig_x_mm,rig_y_mm,rig_z_mm``
                (a rig's pose for every frame, written by ``collect``).
``meta.json``'s ``tares`` (optional): frames where the baseline was taken again (a tare mid-recording),
                each ``F`` or ``{"frame": F, "frames": K}`` (the baseline from frames F..F+K-1;
                default K: the bundle's baseline frames), in order; every reader that
                processes the frames honours them (:attr:`Recording.tares`).
``timestamps.npy`` optional, int64 shape (N,): each frame's capture time,
                CLOCK_MONOTONIC ns (the camera's own where it gives one),
                non-decreasing; without it frame ``i`` is at ``i / fps``.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.core.layout import FiberLayout
from optitac_edge.errors import FrameMismatchError, RecordingError
from optitac_edge.io.frame_store import COLOURS, RAW_FRAMES, REST_FRAMES, SPOTS, STORAGES, SUMS
from optitac_edge.io.npy_rows import npy_shape
from optitac_edge.io.recording_paths import interrupted_swap
from optitac_edge.io.recording_rate import FPS_RANGE, check_stated_rate

TRUTH_HEADER = ("frame", "contact", "shape", "x_mm", "y_mm", "angle_deg", "size_mm", "depth_mm")
#: Optional columns after TRUTH_HEADER: the phase of the press and the rig's pose (rig frame, mm).
RIG_COLUMNS = ("phase", "rig_x_mm", "rig_y_mm", "rig_z_mm")
#: Optional columns after those (before the force): the press's true velocity in the sensor frame (mm/s)
#: and how it moves (:data:`MOTION_STATES`; '' without contact): the simulator's ``slide``, ``vibrate`` and
#: ``hold``. ``pressing``: being pressed in or lifted out.
MOTION_COLUMNS = ("vx_mm_s", "vy_mm_s", "motion")
MOTION_STATES = ("pressing", "held", "sliding", "vibrating")
#: Optional last column: the normal force a load cell measured, N ('' where none).
FORCE_COLUMN = "force_n"
#: Phases of a rig-collected frame; only ``rest``, ``hold`` and ``slide`` frames (and rows without a phase) are
#: scored (``slide``: the tip moving in the skin, ``collect slide``; ``shake``: shaken, ``collect vibrate``).
PHASES = ("rest", "approach", "hold", "release", "move", "slide", "shake")
SCORED_PHASES = ("", "rest", "hold", "slide", "shake")
SHAPES = ("edge", "circle", "square", "ellipse", "triangle")
MIN_REST_FRAMES = 5


@dataclass(frozen=True)
class RecordingMeta:
    """``meta.json`` of a recording."""

    rest_frames: int
    fps: float
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"rest_frames": self.rest_frames, "fps": self.fps, **self.extra}


@dataclass(frozen=True)
class Tare:
    """A tare point of a recording: the baseline taken again from frame ``frame`` on, over ``frames`` frames
    (None: as many as the bundle averages)."""

    frame: int
    frames: int | None = None


#: The key of ``meta.json`` holding the layout of the sensor a recording was made from.
LAYOUT_KEY = "layout"


def layout_meta(layout: FiberLayout) -> dict[str, list[float] | list[int]]:
    """A layout as a recording's meta keeps it: ``{"fiber": [...], "x_mm": [...], "y_mm": [...]}`` (exact:
    JSON writes each float's shortest round-trip form)."""
    return {"fiber": [int(i) for i in layout.ids], "x_mm": [float(v) for v in layout.xy_mm[:, 0]],
            "y_mm": [float(v) for v in layout.xy_mm[:, 1]]}


def read_layout_meta(raw: object, where: Path) -> FiberLayout | None:
    """A recording's ``layout`` (:func:`layout_meta`), checked as a layout CSV is; None when it has none."""
    if raw is None:
        return None
    ok = (isinstance(raw, dict) and set(raw) == {"fiber", "x_mm", "y_mm"}
          and all(isinstance(raw[k], list) and len(raw[k]) == len(raw["fiber"]) for k in ("x_mm", "y_mm"))
          and all(_whole(i) and 0 <= i < 2**31 for i in raw["fiber"])
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) for k in ("x_mm", "y_mm") for v in raw[k]))
    if not ok or not isinstance(raw, dict):
        raise RecordingError(f"{where}: 'layout' must be {{\"fiber\": [ids], \"x_mm\": [...], \"y_mm\": [...]}} "
                             "of one length (whole fiber numbers, numbers in mm)")
    try:
        return FiberLayout(ids=np.array(raw["fiber"], dtype=np.int64),
                           xy_mm=np.c_[np.array(raw["x_mm"], dtype=np.float64), np.array(raw["y_mm"], dtype=np.float64)])
    except ValueError as exc:
        raise RecordingError(f"{where}: 'layout': {exc}") from None


#: Most tare points a recording may list.
MAX_TARES = 100_000


def _whole(value: object) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def read_tares(raw: object, n_frames: int, where: Path) -> tuple[Tare, ...]:
    """``meta.json``'s ``tares``: a list of frame numbers or ``{"frame": F, "frames": K}`` objects, in order,
    each past the leading rest frames' start and before the recording's end.

    Raises
    ------
    RecordingError
        One line naming the file and the entry.
    """
    if raw is None:
        return ()
    if not isinstance(raw, list) or len(raw) > MAX_TARES:
        raise RecordingError(f"{where}: 'tares' must be a list of frame numbers or {{\"frame\": F, \"frames\": K}} "
                             f"(at most {MAX_TARES})")
    out: list[Tare] = []
    for k, entry in enumerate(raw):
        item = entry if isinstance(entry, dict) else {"frame": entry}
        frame, frames = item.get("frame"), item.get("frames")
        if (set(item) - {"frame", "frames"} or not _whole(frame) or not 1 <= frame < n_frames
                or (frames is not None and not (_whole(frames) and 1 <= frames <= n_frames - frame))
                or (out and frame <= out[-1].frame)):
            raise RecordingError(f"{where}: tares[{k}] = {json.dumps(entry)[:80]}: a tare is a frame 1..{n_frames - 1} "
                                 "after the one before it, or {\"frame\": F, \"frames\": K} with K >= 1 frames "
                                 "the recording has from F on")
        out.append(Tare(frame, frames))
    return tuple(out)


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth per frame (columns of ``truth.csv``); NaN / '' where no contact."""

    frame: np.ndarray  # (N,) int64
    contact: np.ndarray  # (N,) bool
    shape: np.ndarray  # (N,) str ('' when no contact)
    x_mm: np.ndarray  # (N,) float64
    y_mm: np.ndarray
    angle_deg: np.ndarray
    size_mm: np.ndarray
    depth_mm: np.ndarray
    #: (N,) float64, N: the load cell's force (NaN where none); None: the recording has no force column.
    force_n: np.ndarray | None = None
    #: (N,) float64, mm/s: the press's true velocity (NaN without contact); None: no motion columns.
    vx_mm_s: np.ndarray | None = None
    vy_mm_s: np.ndarray | None = None
    #: (N,) str: ``held``, ``sliding`` or ``vibrating`` ('' without contact); None: no motion columns.
    motion: np.ndarray | None = None
    #: (N,) int64: which recording of several each row comes from (a press never spans two); None: one.
    session: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.frame.shape[0])


@dataclass(frozen=True, eq=False)
class RigPoses:
    """The rig's pose for every row of a rig-collected ``truth.csv``.

    Attributes
    ----------
    frame : ndarray, shape (N,), int64
    phase : ndarray, shape (N,), str
        One of :data:`PHASES`.
    xyz_mm : ndarray, shape (N, 3), float64
        The indenter tip in the rig's coordinates, mm.
    """

    frame: np.ndarray
    phase: np.ndarray
    xyz_mm: np.ndarray


#: The values a contact's truth may take (mm, degrees): anything else is not a press on a fingertip sensor.
TRUTH_RANGES = {"x_mm": (-1000.0, 1000.0), "y_mm": (-1000.0, 1000.0), "angle_deg": (-3600.0, 3600.0),
                "size_mm": (0.0, 1000.0), "depth_mm": (0.0, 1000.0)}
#: The largest velocity a truth row may hold, mm/s.
MAX_SPEED_MM_S = 10_000.0
#: The largest force a truth row may hold, N.
MAX_FORCE_N = 100_000.0
#: Largest truth.csv read, bytes (a row a frame).
MAX_TRUTH_BYTES = 64 << 20
#: Largest meta.json read, bytes (it holds a few numbers and the simulator's parameters).
MAX_META_BYTES = 1 << 20
#: Written instead of meta.json by a writer that did not finish (see RecordingWriter).
INCOMPLETE_MARKER = "incomplete.json"
#: Per-frame capture times, int64 ns.
TIMESTAMPS = "timestamps.npy"
#: Every file a recording directory may hold (each must be a regular file where it exists).
RECORDING_FILES = ("meta.json", RAW_FRAMES, "truth.csv", TIMESTAMPS, REST_FRAMES, SPOTS, SUMS, COLOURS)
#: The journal of a collection on a rig (``optitac-edge collect``), there until it completes.
COLLECT_JOURNAL = "collect.jsonl"


def read_timestamps(path: Path, n_frames: int) -> np.ndarray:
    """Load and check ``timestamps.npy``: int64, shape (n_frames,), non-decreasing, ns.

    Raises
    ------
    RecordingError
        One line naming the file when it is garbled, of another length or dtype, or goes backwards.
    """
    try:
        t = np.load(path, allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: garbled timestamps ({exc})") from None
    if t.dtype != np.int64 or t.shape != (n_frames,):
        raise RecordingError(f"{path}: timestamps must be int64 of shape ({n_frames},), got {t.dtype} {t.shape}")
    t = np.array(t)
    if n_frames > 1 and np.any(np.diff(t) < 0):
        raise RecordingError(f"{path}: timestamps go backwards at frame {int(np.argmax(np.diff(t) < 0)) + 1}")
    return t


def check_rest_frames(rest_frames: int, truth: Truth | None, where: Path) -> None:
    """The ``rest_frames`` leading frames hold no contact by the recording's own truth (when it has one).

    Raises
    ------
    RecordingError
        The truth has a contact in one of them (the baseline would be taken from a press).
    """
    if truth is None:
        return
    pressed = np.flatnonzero(truth.contact & (truth.frame < rest_frames))
    if pressed.size:
        raise RecordingError(f"{where}: 'rest_frames' is {rest_frames} but its truth has a contact at frame "
                             f"{int(truth.frame[pressed[0]])}: the rest frames must be contact-free")


def _check_regular_files(directory: Path) -> None:
    """Every recording file that exists is a regular file (a FIFO in its place hung the reader)."""
    for name in RECORDING_FILES:
        member = directory / name
        if (member.exists() or member.is_symlink()) and not member.is_file():
            raise RecordingError(f"{member}: not a regular file")


def _check_sum_rows(directory: Path, n_frames: int, rest_frames: int) -> None:
    """A fiber-sum recording's frames are as many as its timestamps (else sums.npy is the one short)."""
    stamps = directory / TIMESTAMPS
    stated = npy_shape(stamps) if stamps.exists() else None
    n_stamped = stated[0] if stated else None
    if n_stamped is not None and n_stamped != n_frames:
        raise RecordingError(f"{directory / SUMS}: {n_frames - rest_frames} frames after the rest frames "
                             f"where {TIMESTAMPS} has {n_stamped - rest_frames} (truncated?)")


def read_meta(path: Path) -> RecordingMeta:
    """Parse and validate ``meta.json``.

    Raises
    ------
    RecordingError
        If it is missing (the recording is incomplete or not one), unreadable,
        too large, not a JSON object, or ``rest_frames`` / ``fps`` are out of range.
    """
    try:
        size = path.stat().st_size
        if size > MAX_META_BYTES:
            raise RecordingError(f"{path}: {size} bytes, larger than a meta.json can be ({MAX_META_BYTES})")
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingError(f"{path.parent}: {_missing_meta(path.parent)}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, ValueError, RecursionError) as exc:
        why = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise RecordingError(f"{path}: garbled meta.json ({why})") from None
    if not isinstance(raw, dict):
        raise RecordingError(f"{path}: meta.json must hold an object")
    return _checked_meta(raw, path)


def _checked_meta(raw: dict[str, Any], path: Path) -> RecordingMeta:
    """A recording's meta from its keys (meta.json's, or an MCAP recording's metadata)."""
    raw = dict(raw)
    rest = raw.pop("rest_frames", None)
    fps = raw.pop("fps", None)
    if not isinstance(rest, int) or isinstance(rest, bool) or not MIN_REST_FRAMES <= rest <= 1_000_000_000:
        raise RecordingError(f"{path}: 'rest_frames' must be an integer >= {MIN_REST_FRAMES}")
    lo, hi = FPS_RANGE
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not lo <= fps <= hi:
        raise RecordingError(f"{path}: 'fps' must be a number in {lo:g}..{hi:g}")
    return RecordingMeta(rest_frames=rest, fps=float(fps), extra=raw)


def _missing_meta(directory: Path) -> str:
    """Why a directory without meta.json is not a usable recording."""
    marker = directory / INCOMPLETE_MARKER
    if marker.exists() and (directory / COLLECT_JOURNAL).exists():
        return ("interrupted collection: run the same 'optitac-edge collect' command to continue it after its "
                "last complete press")
    if marker.exists():
        try:
            info = json.loads(marker.read_text(encoding="utf-8"))
            if info.get("reason") == "being written":  # its writer never came back to say how far it got
                return ("incomplete recording (its writer stopped without finishing: killed, crashed or the power "
                        "lost while it wrote); record it again")
            return (f"incomplete recording ({info.get('reason', 'not finished')}: "
                    f"{int(info.get('frames_written', 0))} of {int(info.get('frames', 0))} frames written); "
                    "record it again")
        except (OSError, ValueError, TypeError, AttributeError, RecursionError):
            return "incomplete recording (interrupted or failed while being written); record it again"
    if (directory / "frames.npy").exists():
        return "incomplete recording (no meta.json: interrupted or failed while being written); record it again"
    return "not a recording (no meta.json)"


def _cell_float(value: str) -> float:
    return float(value) if value.strip() else math.nan


def read_truth(path: Path, n_frames: int) -> Truth:
    """The scored rows of ``truth.csv`` (see :func:`read_truth_file`)."""
    return read_truth_file(path, n_frames)[0]


def read_truth_file(path: Path, n_frames: int, text: str | None = None) -> tuple[Truth, RigPoses | None]:
    """Parse and validate ``truth.csv`` against a recording of ``n_frames`` frames (``text``: its
    contents, kept elsewhere than ``path``, e.g. in an MCAP recording; ``path`` then names it).

    Returns the truth of the scored rows -- every row, or with the rig columns
    the ``rest`` and ``hold`` frames (during approach and release the depth
    changes within a frame) -- and the rig's pose of every row when present.

    Raises
    ------
    RecordingError
        One line naming the file and line: unreadable or not UTF-8, another
        header, no rows, a cell not a number, a frame out of range or listed
        twice, a contact row without its position, shape, size or depth, an
        unknown shape or phase.
    """
    rows = _truth_rows(path, text)
    header = tuple(c.strip() for c in rows[0]) if rows else ()
    force, rig, moving = _truth_columns(path, header)
    if len(rows) < 2:
        raise RecordingError(f"{path}: no rows after the header")
    cols: list[list[Any]] = [[] for _ in TRUTH_HEADER]
    rig_cols: list[list[Any]] = [[], [], []]
    forces: list[float] = []
    motions: list[tuple[float, float, str]] = []
    seen: set[int] = set()
    n_values = len(TRUTH_HEADER) - 3
    n_base = len(header) - force
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise RecordingError(f"{path}: line {line_no}: expected {len(header)} cells")
        try:
            frame, contact = int(row[0]), int(row[1])
            values = [_cell_float(c) for c in row[3:3 + n_values]]
            pose = [float(c) for c in row[len(TRUTH_HEADER) + 1:len(TRUTH_HEADER) + 1 + 3 * rig]]
            motion = _motion_cells(row[n_base - 3:n_base]) if moving else (math.nan, math.nan, "")
            force_n = _cell_float(row[-1]) if force else math.nan
        except ValueError:
            raise RecordingError(f"{path}: line {line_no}: not a number") from None
        shape = row[2].strip()
        if not 0 <= frame < n_frames or contact not in (0, 1):
            raise RecordingError(f"{path}: line {line_no}: frame or contact out of range")
        if frame in seen:
            raise RecordingError(f"{path}: line {line_no}: frame {frame} is listed twice")
        seen.add(frame)
        phase = row[len(TRUTH_HEADER)].strip() if rig else ""
        if rig and (phase not in PHASES or not all(math.isfinite(v) for v in pose)):
            raise RecordingError(f"{path}: line {line_no}: unknown phase {phase!r} or a rig pose not finite")
        if contact:
            _check_contact(path, line_no, shape, values)
        if moving and (motion[2] not in (MOTION_STATES if contact else ("",))
                       or not all(abs(v) <= MAX_SPEED_MM_S for v in motion[:2] if not math.isnan(v))):
            raise RecordingError(f"{path}: line {line_no}: motion must be one of {', '.join(MOTION_STATES)} on a "
                                 f"contact ('' without), its velocity at most {MAX_SPEED_MM_S:g} mm/s")
        if force and (math.isinf(force_n) or not (math.isnan(force_n) or 0 <= force_n <= MAX_FORCE_N)):
            raise RecordingError(f"{path}: line {line_no}: force_n must be a force of 0..{MAX_FORCE_N:g} N or empty")
        if rig:
            rig_cols[0].append(frame)
            rig_cols[1].append(phase)
            rig_cols[2].append(pose)
        if phase not in SCORED_PHASES:
            continue
        for col, value in zip(cols, [frame, bool(contact), shape if contact else "", *values]):
            col.append(value)
        forces.append(force_n)
        motions.append(motion)
    if rig and len(seen) != n_frames:
        raise RecordingError(f"{path}: rows for {len(seen)} of the recording's {n_frames} frames; a rig's "
                             "collection has a row for every frame (rows lost?)")
    truth = Truth(
        frame=np.asarray(cols[0], dtype=np.int64),
        contact=np.asarray(cols[1], dtype=bool),
        shape=np.asarray(cols[2], dtype=str),
        **{name: np.asarray(c, dtype=np.float64) for name, c in zip(TRUTH_HEADER[3:], cols[3:])},
        force_n=np.asarray(forces, dtype=np.float64) if force else None,
        vx_mm_s=np.asarray([m[0] for m in motions], dtype=np.float64) if moving else None,
        vy_mm_s=np.asarray([m[1] for m in motions], dtype=np.float64) if moving else None,
        motion=np.asarray([m[2] for m in motions], dtype=str) if moving else None,
    )
    poses = RigPoses(np.asarray(rig_cols[0], dtype=np.int64), np.asarray(rig_cols[1], dtype=str),
                     np.asarray(rig_cols[2], dtype=np.float64).reshape(-1, 3)) if rig else None
    return truth, poses


def _truth_rows(path: Path, text: str | None) -> list[list[str]]:
    """The CSV rows of ``truth.csv`` (``text``: its contents kept elsewhere), size-checked."""
    try:
        if text is not None:
            if len(text) > MAX_TRUTH_BYTES:
                raise RecordingError(f"{path}: larger than a truth file can be ({MAX_TRUTH_BYTES >> 20} MiB)")
            return list(csv.reader(io.StringIO(text.removeprefix("\ufeff"), newline="")))
        if path.stat().st_size > MAX_TRUTH_BYTES:
            raise RecordingError(f"{path}: larger than a truth file can be ({MAX_TRUTH_BYTES >> 20} MiB)")
        with path.open(newline="", encoding="utf-8-sig") as f:
            return list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(f"{path}: cannot read truth ({exc})") from None


def _truth_columns(path: Path, header: tuple[str, ...]) -> tuple[bool, bool, bool]:
    """Whether the header has the force column, the rig's columns and the motion columns; anything else is
    refused."""
    force = bool(header) and header[-1] == FORCE_COLUMN
    base = header[:-1] if force else header
    moving = base[-len(MOTION_COLUMNS):] == MOTION_COLUMNS
    base = base[:-len(MOTION_COLUMNS)] if moving else base
    if base not in (TRUTH_HEADER, TRUTH_HEADER + RIG_COLUMNS):
        raise RecordingError(f"{path}: header must be '{','.join(TRUTH_HEADER)}' "
                             f"(optionally followed by ',{','.join(RIG_COLUMNS)}', then ',{','.join(MOTION_COLUMNS)}'"
                             f", then ',{FORCE_COLUMN}')")
    return force, len(base) > len(TRUTH_HEADER), moving


def _motion_cells(cells: list[str]) -> tuple[float, float, str]:
    """The motion columns of a row: (vx, vy, state); ValueError when a velocity is not a number."""
    return _cell_float(cells[0]), _cell_float(cells[1]), cells[2].strip()


def _check_contact(path: Path, line_no: int, shape: str, values: list[float]) -> None:
    """A contact row: a known shape, every value but the angle given, each in its range."""
    if shape not in SHAPES:
        raise RecordingError(f"{path}: line {line_no}: unknown shape {shape!r}")
    missing = [name for name, v in zip(TRUTH_HEADER[3:], values) if not math.isfinite(v) and name != "angle_deg"]
    if missing:
        raise RecordingError(f"{path}: line {line_no}: a contact without {', '.join(missing)}")
    for name, v in zip(TRUTH_HEADER[3:], values):
        lo, hi = TRUTH_RANGES[name]
        if not (math.isnan(v) and name == "angle_deg") and not lo <= v <= hi:
            raise RecordingError(f"{path}: line {line_no}: {name} {v:g} is outside {lo:g}..{hi:g}")


class Recording:
    """A recording opened for streaming. Frames are memory-mapped, never loaded whole.

    Parameters
    ----------
    path : path-like
        The recording directory.

    Raises
    ------
    RecordingError
        If the directory, ``frames.npy`` or ``meta.json`` is missing or garbled.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.suffix == ".mcap" and self.path.is_file():
            self._open_mcap()
            return
        if not self.path.is_dir():
            left = interrupted_swap(self.path)
            if left is not None:  # a --fresh replacement killed between its two renames
                raise RecordingError(f"{self.path}: not found, but {left} is a complete recording (a replacement "
                                     f"was interrupted): the next record, sim or collect to {self.path.name} puts it "
                                     f"back, or rename it to {self.path.name}")
            raise RecordingError(f"{self.path}: recording directory not found")
        if (self.path / INCOMPLETE_MARKER).exists():
            raise RecordingError(f"{self.path}: {_missing_meta(self.path)}")
        _check_regular_files(self.path)
        self.meta = read_meta(self.path / "meta.json")
        frames_path = self.path / "frames.npy"
        storage = self.meta.extra.get("frame_storage")
        if storage is not None and not (isinstance(storage, dict) and storage.get("storage") in STORAGES):
            raise RecordingError(f"{self.path / 'meta.json'}: 'frame_storage' must be {{\"storage\": \"fibers\"}} "
                                 "or \"raw\"")
        try:
            if isinstance(storage, dict) and storage.get("storage") == "fibers":
                from optitac_edge.io.fiber_sums import FiberSumFrames

                frames: Any = FiberSumFrames(self.path, self.meta.rest_frames, storage)
            else:
                frames = np.load(frames_path, mmap_mode="r", allow_pickle=False)
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: not a recording (no frames.npy)") from None
        except (OSError, ValueError, EOFError) as exc:
            raise RecordingError(f"{frames_path}: garbled or truncated frames ({exc})") from None
        if frames.dtype != np.uint8 or frames.ndim not in (3, 4) or frames.shape[0] < 1:
            raise RecordingError(
                f"{frames_path}: frames must be uint8 (N,H,W) or (N,H,W,3), "
                f"got {frames.dtype} {frames.shape}"
            )
        try:
            self.pixel_format = infer_pixel_format(frames.shape[1:])
        except FrameMismatchError:
            raise RecordingError(f"{frames_path}: frames of shape {frames.shape} are not gray or RGB") from None
        self.frames = frames
        if self.meta.rest_frames > len(frames):
            raise RecordingError(f"{self.path}: rest_frames={self.meta.rest_frames} but only {len(frames)} frames")
        if not isinstance(frames, np.ndarray):  # fiber sums: the frames after the rest
            _check_sum_rows(self.path, len(frames), self.meta.rest_frames)
        truth_path = self.path / "truth.csv"
        self.truth: Truth | None = None
        #: The rig's pose of every frame, when a rig collected the recording.
        self.rig_poses: RigPoses | None = None
        if truth_path.exists():
            self.truth, self.rig_poses = read_truth_file(truth_path, len(frames))
        #: The tare points (``meta.json``'s ``tares``), in order.
        self.tares = read_tares(self.meta.extra.get("tares"), len(frames), self.path / "meta.json")
        #: The layout of the sensor it was recorded from (``meta.json``'s ``layout``), or None (not kept).
        self.layout = read_layout_meta(self.meta.extra.get(LAYOUT_KEY), self.path / "meta.json")
        stamps = self.path / TIMESTAMPS
        #: True when ``t_ns`` holds the capture times, False when they are nominal (``i / fps``).
        self.timestamped = stamps.exists()
        #: Capture time of each frame, int64 ns, shape (N,).
        self.t_ns: np.ndarray = (read_timestamps(stamps, len(frames)) if self.timestamped else
                                 np.round(np.arange(len(frames)) * (1e9 / self.meta.fps)).astype(np.int64))
        check_stated_rate(self.meta.fps, self.t_ns, self.path / "meta.json")
        check_rest_frames(self.meta.rest_frames, self.truth, self.path / "meta.json")

    def _open_mcap(self) -> None:
        """A recording in one MCAP file (:mod:`optitac_edge.io.recording_mcap`), with its truth if it holds one."""
        from optitac_edge.io.recording_mcap import read_mcap_recording

        frames, t_ns, raw, truth = read_mcap_recording(self.path)
        self.meta = _checked_meta(raw, self.path)
        back = np.flatnonzero(np.diff(t_ns) < 0)
        if back.size:  # as timestamps.npy's (read_timestamps): motion and vibration need times in order
            raise RecordingError(f"{self.path}: frame times go backwards at frame {int(back[0]) + 1}")
        self.pixel_format = infer_pixel_format(frames.shape[1:])
        self.frames = frames
        if self.meta.rest_frames > len(frames):
            raise RecordingError(f"{self.path}: rest_frames={self.meta.rest_frames} but only {len(frames)} frames")
        self.truth = None
        self.rig_poses = None
        self.tares = read_tares(self.meta.extra.get("tares"), len(frames), self.path)
        self.layout = read_layout_meta(self.meta.extra.get(LAYOUT_KEY), self.path)
        if truth is not None:
            self.truth, self.rig_poses = read_truth_file(Path(f"{self.path}#truth.csv"), len(frames), text=truth)
        self.timestamped = True
        self.t_ns = t_ns
        check_stated_rate(self.meta.fps, self.t_ns, self.path)
        check_rest_frames(self.meta.rest_frames, self.truth, self.path)

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Array shape of one frame."""
        return tuple(int(s) for s in self.frames.shape[1:])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    def rest_frames(self) -> np.ndarray:
        """The leading contact-free frames (a memory-mapped view)."""
        return self.frames[: self.meta.rest_frames]

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self.frames[i]

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as a C-contiguous array in memory."""
        return np.ascontiguousarray(self.frames[index])


#: Frames a recording's content digest reads (evenly spaced, the first and last among them).
DIGEST_FRAMES = 16


def content_digest(rec: Recording) -> str:
    """16 hex digits that tell one recording's frames from another's: SHA-256 over the frame count, shape,
    capture times and :data:`DIGEST_FRAMES` evenly spaced frames. A copy of a recording (another directory,
    or its MCAP) has the same; two sessions of a sensor never do (each frame has its own noise)."""
    import hashlib

    h = hashlib.sha256()
    n = len(rec)
    h.update(repr((n, tuple(rec.frames.shape[1:]))).encode())
    h.update(np.ascontiguousarray(rec.t_ns, dtype="<i8").tobytes())
    for i in sorted({round(k * (n - 1) / (DIGEST_FRAMES - 1)) for k in range(DIGEST_FRAMES)}):
        h.update(np.ascontiguousarray(rec.frames[i]).tobytes())
    return h.hexdigest()[:16]


def refuse_repeated(recs: list[Recording]) -> None:
    """Raise :class:`RecordingError` when two of ``recs`` are one recording: the same path, or the same frames
    (a copy): as two sessions it would be its own held-out data."""
    seen: dict[str, Recording] = {}
    for rec in recs:
        digest = content_digest(rec)
        first = seen.setdefault(digest, rec)
        if first is not rec:
            same = "given twice" if first.path.resolve() == rec.path.resolve() else f"the same frames as {first.path}"
            raise RecordingError(f"{rec.path}: {same}: one recording cannot be two sessions (its own held-out "
                                 "data); give each recording once")
