"""The collection's journal: one durable line per completed step, from which an interrupted collection continues.

The first line is the setup (experiment, seed, rig frame, touch-off, the rest and registration frames'
truth rows and times); each further line one completed press (its rows, times and the recording's
clock segments). :func:`append_entry` makes each line durable before the next press begins;
:func:`read_journal` checks every line (an edited or damaged journal is refused, naming the line)
and drops a last line cut short by the interruption.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from pathlib import Path
from typing import Any

from optitac_edge.errors import RecordingError, RigError
from optitac_edge.io.recording import COLLECT_JOURNAL, INCOMPLETE_MARKER, PHASES, SHAPES

#: The journal's file name inside the recording.
JOURNAL = COLLECT_JOURNAL


def append_entry(journal: Path, entry: dict[str, Any], new: bool = False) -> None:
    """Append one line to the journal and make it durable (the resume point)."""
    with journal.open("w" if new else "a", encoding="utf-8") as f:
        f.write(json.dumps(entry, separators=(",", ":")) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_journal(journal: Path, experiment: str, seed: int, n_presses: int
                  ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The setup and the completed presses of an interrupted collection ({} and [] when there is none).

    A last line cut short by the interruption is dropped (that press is made again); any other line
    is checked (:func:`_check_entry`): the journal decides which frames are kept.

    Raises
    ------
    RigError
        If the recording was collected with another experiment, seed or number of presses.
    RecordingError
        If a line is not what ``collect`` writes (edited or damaged), naming the line.
    """
    if not journal.exists() or not (journal.parent / INCOMPLETE_MARKER).exists():
        return {}, []
    try:
        lines = journal.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{journal}: cannot read the journal ({exc}); --fresh starts the collection again") \
            from None
    entries: list[dict[str, Any]] = []
    for n, line in enumerate(lines, start=1):
        try:
            entry = json.loads(line)
        except (ValueError, RecursionError):
            if n == len(lines):
                break  # a line cut short by the interruption: the press is done again
            entry = None
        if n == 1 and isinstance(entry, dict) and entry.get("kind") == "setup":
            made = (entry.get("experiment"), entry.get("seed"), entry.get("presses"))
            if made != (experiment, seed, n_presses):
                raise RigError(f"{journal.parent}: an interrupted collection of {made[0]} (seed {made[1]}, "
                               f"{made[2]} presses); continue it with the same arguments, or use --fresh to start "
                               "again")
        why = _check_entry(entry, n == 1, entries[-1]["end_frame"] if entries else 0, len(entries) - 1)
        if why:
            raise RecordingError(f"{journal}: line {n}: {why} (edited or damaged?); --fresh starts the collection "
                                 "again")
        entries.append(entry)
    if not entries:
        return {}, []
    return entries[0], entries[1:]


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_entry(entry: object, first: bool, start_frame: int, index: int) -> str:
    """Why ``entry`` is not the journal line ``collect`` writes there ('' when it is)."""
    if not isinstance(entry, dict):
        return "not a JSON object"
    kind = "setup" if first else "press"
    if entry.get("kind") != kind:
        return f"expected a {kind} entry"
    if first:
        frame = entry.get("rig_frame")
        if not (isinstance(entry.get("experiment"), str) and _is_int(entry.get("seed"))
                and _is_int(entry.get("presses")) and isinstance(entry.get("bundle_orientation"), str)
                and isinstance(entry.get("touch_off", {}), dict) and isinstance(frame, dict)):
            return "a setup without its experiment, seed, presses, rig frame or orientation"
        origin = frame.get("origin_xy_mm")
        if not (isinstance(origin, list) and len(origin) == 2 and all(map(_is_num, origin))
                and all(_is_num(frame.get(k)) for k in ("rotation_deg", "surface_z_mm", "fit_rms_mm"))
                and all(_is_num(frame.get(k, 1.0)) for k in ("centroid_scale", "shape_rms_mm"))):
            return "a rig frame that is not finite numbers"
        start = entry.get("start_xyz_mm", [0.0, 0.0, 0.0])
        if not (isinstance(start, list) and len(start) == 3 and all(map(_is_num, start))):
            return "a start point that is not three finite numbers"
    elif entry.get("index") != index:
        return f"press {entry.get('index')!r} where press {index} comes"
    end, rows, times = entry.get("end_frame"), entry.get("rows"), entry.get("t_ns")
    if not (isinstance(end, int) and isinstance(rows, list) and isinstance(times, list)
            and end - start_frame == len(rows) == len(times)):
        return "frames, rows and times that do not add up"
    if not all(_is_int(t) and 0 <= t < MAX_T_NS for t in times) or any(b < a for a, b in itertools.pairwise(times)):
        return "frame times that are not integers in order (0..2^62 ns)"
    for k, row in enumerate(rows):
        why = _check_row(row, start_frame + k)
        if why:
            return why
    segments = entry.get("segments", [])
    if not (isinstance(segments, list) and all(
            isinstance(g, dict) and _is_int(g.get("first_frame")) and _is_int(g.get("offset_ns"))
            and abs(g["offset_ns"]) < MAX_T_NS for g in segments)):
        return "segments that are not frame numbers and shifts"
    return ""


#: Frame times and clock shifts a journal may hold, ns (146 years: a shift added to a time stays in int64).
MAX_T_NS = 2**62
#: The largest position, size, depth (mm) or angle (degrees) a journal row may hold: no sensor is a metre wide.
MAX_TRUTH_MM = 1000.0


def _check_row(row: object, frame: int) -> str:
    if not isinstance(row, dict) or row.get("frame") != frame:
        return f"the row of frame {frame} is missing"
    rig = row.get("rig")
    if row.get("phase") not in PHASES or not (isinstance(rig, list) and len(rig) == 3 and all(map(_is_num, rig))):
        return f"frame {frame}: a phase or rig pose that collect does not write"
    if row.get("contact", False) not in (True, False):
        return f"frame {frame}: a contact that is not true or false"
    if row.get("contact") is True and not (row.get("shape") in SHAPES and all(
            _is_num(row.get(k)) and abs(row[k]) <= MAX_TRUTH_MM for k in ("x", "y", "angle", "size", "depth"))):
        return (f"frame {frame}: a contact without its shape, position, angle, size or depth (each a number of at "
                f"most {MAX_TRUTH_MM:g})")
    return ""
