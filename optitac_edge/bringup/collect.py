"""``optitac-edge collect``: run an experiment on an indentation rig into a recording with truth.

One loop at the edge: read a frame, poll the rig, write both. The steps:

1. **Rest** at the start position (the operator jogged the tip over the middle
   of the skin, a few mm above it): the recording's rest frames and baseline.
2. **Touch-off**: step down until the camera sees a contact, then on in small
   steps; the skin's surface is where the contact strength extrapolates to 0.
3. **Registration**: five presses around the start point; the rig-to-sensor
   transform (origin, rotation) is fitted to where the bundle reads them, and
   any symmetry the bundle's fiber map is off by is reported
   (:mod:`optitac_edge.bringup.rig_frame`).
4. **The experiment's presses** (:mod:`optitac_edge.bringup.experiments`):
   every target is checked against the rig's limits before the first moves;
   each press is rest frames at the hover height, approach, hold, release.
   A journal line is appended after each press (its frames made durable
   first), so an interrupted collection -- Ctrl-C, SIGTERM, a dropped SSH
   session, a kill or a power cut -- continues after its last complete press.
5. **Park**: the tip ends at the safe height over the start point, where the
   next collection starts.

Every frame gets a truth row with its phase and the rig's pose; on Ctrl-C, a
rig alarm, a lost connection or any error the tip is retracted first. A
continued collection first lifts the tip straight up (a kill or a power cut
leaves it where it was, maybe in the skin); its frames may carry a clock that
restarted (a reboot, the simulator's virtual clock): the recording's segments
say so, and its times stay in order (:class:`~optitac_edge.io.recording.RecordingWriter`).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.bringup.experiments import PlannedPress, plan, spread
from optitac_edge.bringup.rig_frame import RigFrame, fit_rig_frame
from optitac_edge.calibration.orientation import Symmetry, layout_symmetries
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import CameraError, RecordingError, RigError
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.frame_store import FindFibers
from optitac_edge.io.recording import COLLECT_JOURNAL, INCOMPLETE_MARKER, RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.io.rigs.base import STOPPED_STATES, Rig

log = logging.getLogger(__name__)

JOURNAL = COLLECT_JOURNAL
#: Registration fit RMS (mm) above which the operator is warned (docs/bring-up.md: good is <= 0.3 mm) ...
REGISTER_WARN_MM = 0.3
#: ... and above which the collection is refused: the rig frame would misplace every press.
REGISTER_REFUSE_MM = 0.6


@dataclass(frozen=True)
class CollectSettings:
    """How each press is made (frames at the camera's rate, distances in mm).

    Attributes
    ----------
    initial_rest_frames : int
        Contact-free frames at the start (the recording's ``rest_frames``).
    rest_frames, hold_frames : int
        Frames at the hover height before each press, and at full depth.
    hover_mm : float
        Height of the tip above the skin between presses.
    approach_feed_mm_s : float
        Speed into and out of the skin.
    touch_step_mm : float
        Step of the touch-off descent.
    touch_extra_mm : float
        How far the touch-off goes on below the first contact (for the extrapolation).
    register_depth_mm : float
        Depth of the registration presses.
    register_fraction : float
        Registration presses this fraction of the array radius from the start point.
    """

    initial_rest_frames: int = 30
    rest_frames: int = 10
    hold_frames: int = 8
    hover_mm: float = 1.5
    approach_feed_mm_s: float = 10.0
    touch_step_mm: float = 0.05
    touch_extra_mm: float = 0.6
    register_depth_mm: float = 2.0
    register_fraction: float = 0.45


@dataclass
class CollectResult:
    """What a collection did (also in the recording's ``meta.json`` under ``collect``)."""

    experiment: str
    presses: int
    frames: int
    rig_frame: RigFrame
    bundle_symmetry: str
    resumed_at: int = 0
    touch_off: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"experiment": self.experiment, "presses": self.presses, "frames": self.frames,
                "rig_frame": self.rig_frame.to_json(), "bundle_orientation": self.bundle_symmetry,
                "resumed_at_press": self.resumed_at, "touch_off": self.touch_off}


class Collector:
    """The collection loop. See the module docstring.

    Parameters
    ----------
    camera : Camera
    rig : Rig
    bundle : CalibrationBundle
        Reads the registration presses (its fiber map; centroid models are not applied).
    settings : CollectSettings
    prompt : callable
        Shows one line to the operator.
    confirm : callable
        Shows one line and waits until the operator is ready (indenter changes).
    read_timeout_s : float
        Longest wait for a frame.
    storage : {"raw", "fibers"}
        How the recording keeps its frames (:mod:`optitac_edge.io.frame_store`); ``fibers`` needs ``find_fibers``.
    find_fibers : callable, optional
        Finds the fibers in the recording's rest frames (e.g. :func:`optitac_edge.service.bundles.fiber_finder`).
    """

    def __init__(self, camera: Camera, rig: Rig, bundle: CalibrationBundle, settings: CollectSettings = CollectSettings(),  # noqa: PLR0913
                 prompt: Callable[[str], None] = print, confirm: Callable[[str], None] | None = None,
                 read_timeout_s: float = 2.0, storage: str = "raw", find_fibers: FindFibers | None = None) -> None:
        self.camera, self.rig, self.bundle, self.settings = camera, rig, bundle, settings
        self.storage, self.find_fibers = storage, find_fibers
        self.prompt = prompt
        self.confirm = confirm or prompt
        self.read_timeout_s = read_timeout_s
        self.pipeline = Pipeline(bundle)
        self.pipeline.set_corrector(None)
        self.writer: RecordingWriter | None = None
        self.frame: RigFrame | None = None
        self._index = 0
        self._rows: list[dict[str, Any]] = []
        self._times: list[int] = []
        self._mounted = ""
        #: Where the operator left the tip (the park position is the safe height over it), and the last target.
        self._start = self._at = (math.nan, math.nan, math.nan)

    # -- the loop's one step: a frame, the rig's pose, a row ---------------------------------

    def _step(self, phase: str, press: PlannedPress | None) -> Any:
        captured = self.camera.read(self.read_timeout_s)
        if captured is None:
            raise CameraError("the camera ended during the collection")
        st = self.rig.status()
        if st.state in STOPPED_STATES:
            raise RigError(f"the rig is {STOPPED_STATES[st.state]} ({st.raw_state or st.state}); the collection "
                           "stopped: run the same command to continue")
        assert self.writer is not None
        t_ns = self.writer.write(self._index, captured.frame, captured.t_ns)
        self._rows.append(self._row(phase, press, st.xyz_mm))
        self._times.append(int(captured.t_ns if t_ns is None else t_ns))
        self._index += 1
        self.pipeline.bundle.fibers.check_frame(captured.frame, self.camera.pixel_format)
        # a copy: the callers keep the estimates of several frames (the pipeline's own is reused)
        return self.pipeline.process(captured.frame, captured.t_ns).primary.copy(), st

    def _row(self, phase: str, press: PlannedPress | None, xyz: tuple[float, float, float]) -> dict[str, Any]:
        row: dict[str, Any] = {"frame": self._index, "phase": phase, "rig": [round(v, 4) for v in xyz]}
        if self.frame is None:
            return {**row, "_press": press}  # before registration: completed once the rig frame is fitted
        return self._complete(row, press)

    def _complete(self, row: dict[str, Any], press: PlannedPress | None) -> dict[str, Any]:
        assert self.frame is not None
        x, y, z = row["rig"]
        depth = self.frame.surface_z_mm - z
        if press is None or depth <= 0:
            return {**row, "contact": False}
        sx, sy = self.frame.to_sensor(np.array([[x, y]]))[0]
        return {**row, "contact": True, "shape": press.shape, "x": round(float(sx), 4), "y": round(float(sy), 4),
                "angle": round(self.frame.angle_in_sensor(press.angle_deg), 3) if press.shape != "circle" else 0.0,
                "size": press.size_mm, "depth": round(depth, 4)}

    def _frames(self, n: int, phase: str, press: PlannedPress | None) -> list[Any]:
        return [self._step(phase, press)[0] for _ in range(n)]

    def _move(self, xyz: tuple[float, float, float], phase: str, press: PlannedPress | None,
              feed_mm_s: float | None = None) -> list[Any]:
        """Move the tip, recording every frame until the rig is idle there."""
        self.rig.move_to(xyz, feed_mm_s)
        self._at = xyz
        feed = min(feed_mm_s or self.rig.limits.feed_mm_s, self.rig.limits.feed_mm_s)
        budget = max(5, int((20.0 + 3.0 * math.dist(xyz, self._pose()) / feed) * self.camera.fps))
        estimates = []
        for _ in range(budget):
            est, st = self._step(phase, press)
            estimates.append(est)
            if st.state == "idle" and math.dist(st.xyz_mm, xyz) < 0.01:
                return estimates
        raise RigError(f"the rig did not reach {xyz} within {budget} frames")

    def _pose(self) -> tuple[float, float, float]:
        return self.rig.status().xyz_mm

    def _start_pose(self) -> tuple[float, float, float]:
        """Where the operator left the tip: two reports in a row that agree (no single report is trusted)."""
        last = self._pose()
        for _ in range(10):
            pose = self._pose()
            if math.dist(pose, last) < 0.01:
                return pose
            last = pose
        raise RigError("the rig reports a different position every time although it should stand still "
                       f"(last {last}); is it moving, or is the line noisy?")

    # -- setup: rest, touch-off, registration --------------------------------------------------

    def _touch_off(self, x: float, y: float, z0: float, tip: PlannedPress) -> tuple[float, dict[str, float]]:
        """Coarse steps down to the first contact, back up, then fine steps through the surface."""
        s = self.settings
        lowest = self.rig.limits.z_mm[0]

        def probe(z: float) -> tuple[bool, float]:
            if z < lowest:
                raise RigError(f"touch-off: no contact down to the rig's lowest z ({lowest:g} mm): "
                               "is the tip over the skin?")
            self._move((x, y, z), "approach", tip, s.approach_feed_mm_s)
            est = self._frames(3, "approach", tip)
            return (sum(bool(e.contact) for e in est) >= 2,
                    float(np.mean([e.strength if e.contact else 0.0 for e in est])))

        coarse = 5 * s.touch_step_mm
        z = z0
        while not probe(z := round(z - coarse, 4))[0]:
            pass
        z = round(z + coarse + s.touch_step_mm, 4)  # above the first contact again, then fine steps
        self._move((x, y, z + s.hover_mm), "release", tip, s.approach_feed_mm_s)
        samples: list[tuple[float, float]] = []
        found_at: float | None = None
        while found_at is None or found_at - z < s.touch_extra_mm - 1e-9:
            z = round(z - s.touch_step_mm, 4)
            contact, strength = probe(z)
            if contact and found_at is None:
                found_at = z
            if found_at is not None:
                samples.append((z, strength))
        zs, st = np.array(samples).T
        slope, intercept = np.polyfit(zs, st, 1)
        surface = float(-intercept / slope) if slope < 0 else found_at
        surface = min(max(surface, found_at), found_at + 1.0)  # between the first contact and 1 mm above it
        self._move((x, y, surface + s.hover_mm), "release", tip, s.approach_feed_mm_s)
        return surface, {"first_contact_z_mm": round(found_at, 4), "surface_z_mm": round(surface, 4),
                         "steps": len(samples)}

    def _register(self, x0: float, y0: float, surface: float, tip: PlannedPress) -> tuple[RigFrame, Symmetry]:
        s = self.settings
        d = s.register_fraction * self.bundle.layout.radius_mm
        points = [(x0, y0), (x0 + d, y0), (x0, y0 + d), (x0 - d, y0), (x0, y0 - d)]
        hover, depth = surface + s.hover_mm, surface - s.register_depth_mm
        for px, py in points:
            self.rig.limits.check((px, py, hover))
            self.rig.limits.check((px, py, depth))
        seen = []
        for px, py in points:
            self._move((px, py, hover), "move", tip)
            self._frames(s.rest_frames, "rest", tip)
            self._move((px, py, depth), "approach", tip, s.approach_feed_mm_s)
            est = [e for e in self._frames(s.hold_frames, "hold", tip) if e.contact]
            if len(est) < s.hold_frames // 2:
                raise RigError(f"registration press at rig ({px:.2f}, {py:.2f}) was not seen by the camera: "
                               "is the start point over the middle of the skin?")
            seen.append((np.mean([e.x_mm for e in est]), np.mean([e.y_mm for e in est])))
            self._move((px, py, hover), "release", tip, s.approach_feed_mm_s)
        try:
            return fit_rig_frame(np.array(points), np.array(seen), surface, layout_symmetries(self.bundle.layout))
        except ValueError as exc:
            raise RigError(str(exc)) from None

    # -- the whole collection --------------------------------------------------------------------

    def run(self, experiment: str, out: Path, seed: int = 0, limit: int | None = None,
            fresh: bool = False) -> CollectResult:
        """Collect ``experiment`` into the recording ``out`` (continuing an interrupted one unless ``fresh``).

        ``limit`` takes that many presses spread over the whole experiment. A complete recording at
        ``out`` is refused, or with ``fresh`` replaced once the new one is complete.

        Raises
        ------
        RigError, CameraError, OutputError, RecordingError
            After retracting the tip; the recording is left incomplete and can be continued.
        """
        presses = spread(plan(experiment, self.bundle.layout, seed), limit)
        setup, done = ({}, []) if fresh else _read_journal(out / JOURNAL, experiment, seed, len(presses))
        meta = RecordingMeta(rest_frames=self.settings.initial_rest_frames, fps=self.camera.fps,
                             extra={"collect": {"experiment": experiment, "seed": seed}})
        entries = ([setup] if setup else []) + done
        kept = entries[-1]["end_frame"] if entries else 0
        kept_rows = [r for entry in entries for r in entry["rows"]]
        kept_t = [t for entry in entries for t in entry["t_ns"]]
        segments = next((e["segments"] for e in reversed(entries) if "segments" in e), None)
        self.writer = RecordingWriter(out, None, self.camera.frame_shape, meta, rig_columns=True,
                                      keep_frames=kept, kept_t_ns=np.asarray(kept_t, np.int64) if kept else None,
                                      kept_segments=segments, replace=fresh, storage=self.storage,
                                      find_fibers=self.find_fibers)
        journal = self.writer.path / JOURNAL
        try:
            result = self._run(experiment, presses, setup, done, journal, kept_rows, seed)
            self._park()
        except BaseException as exc:
            unsafe = self._retract_after(exc)
            self.writer.abort("interrupted" if isinstance(exc, KeyboardInterrupt) else f"failed: {exc}")
            if unsafe is not None:  # never "tip retracted" when it was not
                raise RigError(f"{exc if isinstance(exc, Exception) else 'interrupted'}; {unsafe}") from None
            raise
        meta.extra["collect"] = result.to_json()
        self.writer.close()
        (self.writer.target / JOURNAL).unlink(missing_ok=True)
        return result

    def _retract_after(self, exc: BaseException) -> str | None:
        """Retract the tip after ``exc``; None, or why the tip was not retracted (for the one line)."""
        try:
            self.rig.retract()
        except Exception as err:  # noqa: BLE001 - the original error is what the user must see first
            log.debug("could not retract the tip after %s: %s", type(exc).__name__, err)
            return f"the tip was NOT retracted: {err}"
        try:
            self.prompt(f"retracted the tip to z = {self.rig.limits.safe_z_mm:g} mm")
        except OSError as err:  # a terminal gone with the SSH session that sent SIGHUP
            log.debug("could not say the tip was retracted: %s", err)
        return None

    def _park(self) -> None:
        """The tip to the safe height over the start point, where the next collection starts."""
        x0, y0, _ = self._start
        safe = self.rig.limits.safe_z_mm
        self.rig.lift(safe)
        self.rig.move_and_wait((x0, y0, safe))
        self.prompt(f"parked the tip at z = {safe:g} mm over the start point ({x0:.2f}, {y0:.2f})")

    def _run(self, experiment: str, presses: list[PlannedPress], setup: dict[str, Any],  # noqa: PLR0915
             done: list[dict[str, Any]], journal: Path, kept_rows: list[dict[str, Any]], seed: int) -> CollectResult:
        assert self.writer is not None
        s = self.settings
        for row in kept_rows:
            self._write_truth(row)
        self._index = self.writer.frames_written
        if setup:
            saved = setup["rig_frame"]
            self.frame = RigFrame(origin_xy_mm=(float(saved["origin_xy_mm"][0]), float(saved["origin_xy_mm"][1])),
                                  rotation_deg=float(saved["rotation_deg"]), surface_z_mm=float(saved["surface_z_mm"]),
                                  fit_rms_mm=float(saved["fit_rms_mm"]))
            symmetry = setup["bundle_orientation"]
            touch = setup.get("touch_off", {})
            start = setup.get("start_xyz_mm") or setup["rows"][0]["rig"]
            self._start = (float(start[0]), float(start[1]), float(start[2]))
            self._at = self._start
            self.prompt(f"continuing {experiment} after press {len(done)} of {len(presses)}")
            # a kill or a power cut left the tip where it was, maybe in the skin: straight up first
            self.rig.retract()
            self._frames(s.rest_frames, "rest", None)  # a fresh baseline
        else:
            x0, y0, z0 = self._start = self._at = self._start_pose()
            self.prompt(f"rest at the start point ({x0:.2f}, {y0:.2f}, {z0:.2f}); nothing may touch the skin")
            self._frames(s.initial_rest_frames, "rest", None)
            # registration presses with the experiment's first circle (an edge's centroid along it is ill-defined)
            first = next((p for p in presses if p.shape == "circle"), presses[0])
            tip = PlannedPress(0.0, 0.0, s.register_depth_mm, first.shape, first.size_mm, first.angle_deg)
            if tip.indenter != self._mounted:
                self._change_indenter(tip)
                self._move((x0, y0, z0), "move", None)
            self.prompt("touch-off: finding the skin's surface")
            surface, touch = self._touch_off(x0, y0, z0, tip)
            self.prompt(f"registration: 5 presses around ({x0:.2f}, {y0:.2f})")
            frame, h = self._register(x0, y0, surface, tip)
            if frame.fit_rms_mm > REGISTER_REFUSE_MM:
                raise RigError(f"registration fit RMS {frame.fit_rms_mm:.2f} mm is too poor (good: <= "
                               f"{REGISTER_WARN_MM} mm): every press would be misplaced; check that the indenter sits "
                               "tight, the start point is over the middle of the skin and the bundle is this sensor's")
            self.frame = frame
            symmetry = h.label
            self._rows = [self._complete(r, r.pop("_press")) for r in self._rows]
            setup = {"kind": "setup", "experiment": experiment, "seed": seed, "presses": len(presses),
                     "rig_frame": asdict(frame), "bundle_orientation": symmetry, "touch_off": touch,
                     "start_xyz_mm": [x0, y0, z0], "end_frame": self._index, "rows": self._rows,
                     "t_ns": self._times, "segments": self.writer.segments}
            self._flush_rows()
            self.writer.sync()
            _append(journal, setup, new=True)
            self._rows, self._times = [], []
            self.prompt(f"sensor origin at rig ({frame.origin_xy_mm[0]:.2f}, {frame.origin_xy_mm[1]:.2f}), "
                        f"+x at {frame.rotation_deg:+.1f}° from the rig's +X, surface z {frame.surface_z_mm:.2f}, "
                        f"fit RMS {frame.fit_rms_mm:.2f} mm")
            if frame.fit_rms_mm > REGISTER_WARN_MM:
                self.prompt(f"warning: registration fit RMS {frame.fit_rms_mm:.2f} mm (good: <= {REGISTER_WARN_MM} mm): "
                            "check that the indenter sits tight and the bundle's fiber map is this sensor's")
            if not h.is_identity:
                self.prompt(f"warning: the bundle's fiber map is {h.label} from the rig's presses; after this "
                            "collection run: optitac-edge calibrate orientation REC --cal CAL")
        frame = self.frame
        assert frame is not None
        targets = frame.to_rig(np.array([(p.x_mm, p.y_mm) for p in presses]).reshape(-1, 2))
        for k, p in enumerate(presses):  # every target inside the limits before anything more moves
            for z in (frame.surface_z_mm + s.hover_mm, frame.surface_z_mm - p.depth_mm):
                try:
                    self.rig.limits.check((float(targets[k, 0]), float(targets[k, 1]), z))
                except RigError as exc:
                    raise RigError(f"press {k + 1} at sensor ({p.x_mm:.2f}, {p.y_mm:.2f}): {exc}") from None
        for k in range(len(done), len(presses)):
            p = presses[k]
            tx, ty = float(targets[k, 0]), float(targets[k, 1])
            hover = frame.surface_z_mm + s.hover_mm
            if p.indenter != self._mounted:
                self._change_indenter(p)
            self._move((tx, ty, hover), "move", p)
            self._frames(s.rest_frames, "rest", p)
            self._move((tx, ty, frame.surface_z_mm - p.depth_mm), "approach", p, s.approach_feed_mm_s)
            self._frames(s.hold_frames, "hold", p)
            self._move((tx, ty, hover), "release", p, s.approach_feed_mm_s)
            self._flush_rows()
            self.writer.sync()
            _append(journal, {"kind": "press", "index": k, "end_frame": self._index, "rows": self._rows,
                              "t_ns": self._times, "segments": self.writer.segments})
            self._rows, self._times = [], []
            if (k + 1) % 25 == 0:
                log.info("press %d of %d", k + 1, len(presses))
        return CollectResult(experiment, len(presses), self._index, frame, symmetry,
                             resumed_at=len(done), touch_off=dict(touch))

    def _change_indenter(self, p: PlannedPress) -> None:
        if not self.rig.changes_indenters:
            x, y, _ = self._at  # where the last move went: no report's x or y goes into a target
            self._move((x, y, self.rig.limits.safe_z_mm), "move", None)
            self.confirm(f"mount the {p.shape} indenter, {p.size_mm:g} mm, at {p.angle_deg:g}° from the rig's +X; "
                         "then press Enter")
        self.rig.change_indenter(p.indenter)
        self._mounted = p.indenter

    def _flush_rows(self) -> None:
        for row in self._rows:
            self._write_truth(row)

    def _write_truth(self, row: dict[str, Any]) -> None:
        assert self.writer is not None
        xyz = (float(row["rig"][0]), float(row["rig"][1]), float(row["rig"][2]))
        if row.get("contact"):
            self.writer.write_truth(row["frame"], True, row["shape"], row["x"], row["y"], row["angle"], row["size"],
                                    row["depth"], phase=row["phase"], rig_xyz_mm=xyz)
        else:
            self.writer.write_truth(row["frame"], False, phase=row["phase"], rig_xyz_mm=xyz)


def _append(journal: Path, entry: dict[str, Any], new: bool = False) -> None:
    """Append one line to the journal and make it durable (the resume point)."""
    with journal.open("w" if new else "a", encoding="utf-8") as f:
        f.write(json.dumps(entry, separators=(",", ":")) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _read_journal(journal: Path, experiment: str, seed: int, n_presses: int
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


def _check_entry(entry: Any, first: bool, start_frame: int, index: int) -> str:
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
                and all(_is_num(frame.get(k)) for k in ("rotation_deg", "surface_z_mm", "fit_rms_mm"))):
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
    if not all(_is_int(t) for t in times) or any(b < a for a, b in itertools.pairwise(times)):
        return "frame times that are not integers in order"
    for k, row in enumerate(rows):
        why = _check_row(row, start_frame + k)
        if why:
            return why
    segments = entry.get("segments", [])
    if not (isinstance(segments, list) and all(
            isinstance(g, dict) and _is_int(g.get("first_frame")) and _is_int(g.get("offset_ns")) for g in segments)):
        return "segments that are not frame numbers and shifts"
    return ""


def _check_row(row: Any, frame: int) -> str:
    from optitac_edge.io.recording import PHASES, SHAPES

    if not isinstance(row, dict) or row.get("frame") != frame:
        return f"the row of frame {frame} is missing"
    rig = row.get("rig")
    if row.get("phase") not in PHASES or not (isinstance(rig, list) and len(rig) == 3 and all(map(_is_num, rig))):
        return f"frame {frame}: a phase or rig pose that collect does not write"
    if row.get("contact") is True and not (row.get("shape") in SHAPES and all(
            _is_num(row.get(k)) for k in ("x", "y", "angle", "size", "depth"))):
        return f"frame {frame}: a contact without its shape, position, angle, size or depth"
    return ""
