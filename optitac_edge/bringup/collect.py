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

import logging
import math
import signal
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.bringup.experiments import VIBRATE_AMPLITUDE_MM, PlannedPress, plan, spread
from optitac_edge.bringup.journal import JOURNAL, read_journal
from optitac_edge.bringup.rig_frame import RigFrame, fit_rig_frame
from optitac_edge.bringup.rig_recorder import RigRecorder
from optitac_edge.calibration.orientation import Symmetry, layout_symmetries
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import RigError
from optitac_edge.io import interrupts
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.frame_store import FindFibers
from optitac_edge.io.recording import LAYOUT_KEY, RecordingMeta, layout_meta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.io.rigs.base import Rig

log = logging.getLogger(__name__)

#: Registration fit RMS (pitches) above which the operator is warned (docs/bring-up.md: good is <= 0.2 pitch,
#: 0.3 mm on the paper's 1.5 mm array) ...
REGISTER_WARN_PITCH = 0.2
#: ... and above which the collection is refused: the rig frame would misplace every press. Both judge the
#: residual once the uncalibrated centroid's scale is allowed (RigFrame.shape_rms_mm): the scale is the
#: centroid's to correct (calibrate centroid), not the rig's.
REGISTER_REFUSE_PITCH = 0.4
#: The scale an uncalibrated centroid may read the presses at: a weighted mean over the fibers a press darkens
#: only pulls towards the array's middle (below 1); below half, or above 1.2, the bundle's pitch is not this
#: sensor's (another layout or array) and the operator is warned.
CENTROID_SCALE_RANGE = (0.5, 1.2)


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
    read_timeout_s : float
        Longest wait for a frame, seconds.
    shake_s : float
        How long a ``vibrate`` press is shaken, seconds.
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
    read_timeout_s: float = 2.0
    shake_s: float = 0.5


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


_DEFAULTS = CollectSettings()


class Collector:
    """The collection: rest, touch-off, registration, the experiment's presses, park. See the module docstring.

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
    storage : {"raw", "fibers"}
        How the recording keeps its frames (:mod:`optitac_edge.io.frame_store`); ``fibers`` needs ``find_fibers``.
    find_fibers : callable, optional
        Finds the fibers in the recording's rest frames (e.g. :func:`optitac_edge.service.bundles.fiber_finder`).
    """

    def __init__(self, camera: Camera, rig: Rig, bundle: CalibrationBundle, settings: CollectSettings = _DEFAULTS,
                 prompt: Callable[[str], None] = print, confirm: Callable[[str], None] | None = None,
                 storage: str = "raw", find_fibers: FindFibers | None = None) -> None:
        self.camera, self.rig, self.bundle, self.settings = camera, rig, bundle, settings
        #: Called after each press is journalled with (presses done, presses in all): a progress bar or a line.
        self.progress: Callable[[int, int], None] = lambda done, total: None
        self.storage, self.find_fibers = storage, find_fibers
        self.prompt = prompt
        self.confirm = confirm or prompt
        self.pipeline = Pipeline(bundle, fps=camera.fps)
        self.pipeline.set_corrector(None)
        self.writer: RecordingWriter | None = None
        self._mounted = ""
        #: Where the operator left the tip (the park position is the safe height over it).
        self._start = (math.nan, math.nan, math.nan)

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
        if any(p.shake_hz > 0 for p in presses) and not self.rig.shakes:
            raise RigError(f"{experiment}: this rig cannot shake the tip at 30-100 Hz (a machine's acceleration "
                           "cannot reverse 0.05 mm that fast); use sim:// or a rig with a shaker")
        setup, done = ({}, []) if fresh else read_journal(out / JOURNAL, experiment, seed, len(presses))
        meta = RecordingMeta(rest_frames=self.settings.initial_rest_frames, fps=self.camera.fps,
                             extra={"collect": {"experiment": experiment, "seed": seed},
                                    LAYOUT_KEY: layout_meta(self.bundle.layout)})  # for calibrate fibers
        entries = ([setup] if setup else []) + done
        kept = entries[-1]["end_frame"] if entries else 0
        kept_t = [t for entry in entries for t in entry["t_ns"]]
        segments = next((e["segments"] for e in reversed(entries) if "segments" in e), None)
        self.writer = RecordingWriter(out, None, self.camera.frame_shape, meta, rig_columns=True,
                                      motion_columns=any(p.slide_mm_s > 0 or p.shake_hz > 0 for p in presses),
                                      keep_frames=kept, kept_t_ns=np.asarray(kept_t, np.int64) if kept else None,
                                      kept_segments=segments, replace=fresh, storage=self.storage,
                                      find_fibers=self.find_fibers)
        rec = RigRecorder(self.camera, self.rig, self.pipeline, self.writer, self.settings.read_timeout_s)
        journal = self.writer.path / JOURNAL
        try:
            rec.write_rows([r for entry in entries for r in entry["rows"]], kept_t)
            if setup:
                symmetry, touch = self._resume(rec, setup, f"{len(done)} of {len(presses)}", len(done) < len(presses))
                self._assume_mounted(presses, len(done))
                if len(done) < len(presses):
                    self._check_unmoved(rec, presses, len(done))
            else:
                symmetry, touch = self._set_up(rec, presses, journal, {"experiment": experiment, "seed": seed})
            self._press_all(rec, presses, len(done), journal)
            self._park()
            rec.flush()  # any frames since the last press get their rows
        except BaseException as exc:
            unsafe = self._retract_after(exc)
            self.writer.abort("interrupted" if isinstance(exc, KeyboardInterrupt) else f"failed: {exc}")
            if unsafe is not None:  # never "tip retracted" when it was not
                raise RigError(f"{exc if isinstance(exc, Exception) else 'interrupted'}; {unsafe}") from None
            raise
        assert rec.frame is not None
        result = CollectResult(experiment, len(presses), rec.index, rec.frame, symmetry,
                               resumed_at=len(done), touch_off=dict(touch))
        meta.extra["collect"] = result.to_json()
        self.writer.close()
        (self.writer.target / JOURNAL).unlink(missing_ok=True)
        return result

    def _resume(self, rec: RigRecorder, setup: dict[str, Any], after: str,
                presses_left: bool) -> tuple[str, dict[str, float]]:
        """Go on from an interrupted collection's setup: its rig frame, orientation and touch-off."""
        saved = setup["rig_frame"]
        rec.frame = RigFrame(origin_xy_mm=(float(saved["origin_xy_mm"][0]), float(saved["origin_xy_mm"][1])),
                             rotation_deg=float(saved["rotation_deg"]), surface_z_mm=float(saved["surface_z_mm"]),
                             fit_rms_mm=float(saved["fit_rms_mm"]),
                             centroid_scale=float(saved.get("centroid_scale", 1.0)),
                             shape_rms_mm=float(saved.get("shape_rms_mm", saved["fit_rms_mm"])))
        start = setup.get("start_xyz_mm") or setup["rows"][0]["rig"]
        self._start = rec.at = (float(start[0]), float(start[1]), float(start[2]))
        self.prompt(f"continuing {setup['experiment']} after press {after}")
        # a kill or a power cut left the tip where it was, maybe in the skin: straight up first
        self.rig.retract()
        if presses_left:
            rec.frames(self.settings.rest_frames, "rest", None)  # a fresh baseline
        return setup["bundle_orientation"], setup.get("touch_off", {})

    def _set_up(self, rec: RigRecorder, presses: list[PlannedPress], journal: Path,
                made: dict[str, Any]) -> tuple[str, dict[str, float]]:
        """Rest, touch-off and registration at the start point; journalled as the setup."""
        s = self.settings
        x0, y0, z0 = self._start = rec.at = rec.start_pose()
        safe = self.rig.limits.safe_z_mm
        if z0 < safe:  # the tip may be in the skin (left there by a kill or a power cut): up first, confirmed
            self.rig.lift(safe)
            rec.at = (x0, y0, safe)
        self.prompt(f"rest over the start point ({x0:.2f}, {y0:.2f}, {z0:.2f}) with the tip at z = "
                    f"{max(z0, safe):g} mm; nothing may touch the skin")
        rec.frames(s.initial_rest_frames, "rest", None)
        # registration presses with the experiment's first circle (an edge's centroid along it is ill-defined)
        first = next((p for p in presses if p.shape == "circle"), presses[0])
        tip = PlannedPress(0.0, 0.0, s.register_depth_mm, first.shape, first.size_mm, first.angle_deg)
        if tip.indenter != self._mounted:
            self._change_indenter(rec, tip)
            rec.move((x0, y0, z0), "move", None)
        self.prompt("touch-off: finding the skin's surface")
        surface, touch = touch_off(rec, (x0, y0, z0), tip, s)
        self.prompt(f"registration: 5 presses around ({x0:.2f}, {y0:.2f})")
        frame, h = register(rec, (x0, y0, surface), tip, s, self.bundle.layout)
        pitch = self.bundle.layout.pitch_mm
        if frame.shape_rms_mm > REGISTER_REFUSE_PITCH * pitch:
            raise RigError(f"registration fit RMS {frame.shape_rms_mm:.2f} mm is too poor (good: <= "
                           f"{REGISTER_WARN_PITCH * pitch:.2f} mm = {REGISTER_WARN_PITCH} pitch): every press would "
                           "be misplaced; check that the indenter sits "
                           "tight, the start point is over the middle of the skin and the bundle is this sensor's")
        rec.set_frame(frame)
        rec.commit(journal, {"kind": "setup", **made, "presses": len(presses), "rig_frame": asdict(frame),
                             "bundle_orientation": h.label, "touch_off": touch, "start_xyz_mm": [x0, y0, z0]},
                   new=True)
        self.prompt(f"sensor origin at rig ({frame.origin_xy_mm[0]:.2f}, {frame.origin_xy_mm[1]:.2f}), "
                    f"+x at {frame.rotation_deg:+.1f}° from the rig's +X, surface z {frame.surface_z_mm:.2f}, "
                    f"fit RMS {frame.shape_rms_mm:.2f} mm with the uncalibrated centroid's scale "
                    f"{frame.centroid_scale:.2f} ({frame.fit_rms_mm:.2f} mm without it; calibrate centroid corrects "
                    "the scale)")
        lo, hi = CENTROID_SCALE_RANGE
        if not lo <= frame.centroid_scale <= hi:
            self.prompt(f"warning: the bundle reads the registration presses {frame.centroid_scale:.2f} times as far "
                        f"apart as the rig pressed them (an uncalibrated centroid reads {lo:g} to {hi:g}): is the "
                        "bundle's layout this sensor's, with its pitch?")
        if frame.shape_rms_mm > REGISTER_WARN_PITCH * pitch:
            self.prompt(f"warning: registration fit RMS {frame.shape_rms_mm:.2f} mm (good: <= "
                        f"{REGISTER_WARN_PITCH * pitch:.2f} mm = {REGISTER_WARN_PITCH} pitch): "
                        "check that the indenter sits tight and the bundle's fiber map is this sensor's")
        if not h.is_identity:
            self.prompt(f"warning: the bundle's fiber map is {h.label} from the rig's presses; after this "
                        "collection run: optitac-edge calibrate orientation REC --cal CAL")
        return h.label, touch

    def _press_all(self, rec: RigRecorder, presses: list[PlannedPress], first: int, journal: Path) -> None:
        """The experiment's presses from ``first`` on, each journalled; every target is checked first."""
        s, frame = self.settings, rec.frame
        assert frame is not None
        targets = frame.to_rig(np.array([(p.x_mm, p.y_mm) for p in presses]).reshape(-1, 2))
        ends = frame.to_rig(np.array([(p.slide_x_mm, p.slide_y_mm) for p in presses]).reshape(-1, 2))
        for k, p in enumerate(presses):  # every target inside the limits before anything more moves
            points = [(targets[k], z) for z in (frame.surface_z_mm + s.hover_mm, frame.surface_z_mm - p.depth_mm)]
            points += [(ends[k], z) for _, z in points] if p.slide_mm_s > 0 else []
            for (x, y), z in points:
                try:
                    self.rig.limits.check((float(x), float(y), z))
                except RigError as exc:
                    raise RigError(f"press {k + 1} at sensor ({p.x_mm:.2f}, {p.y_mm:.2f}): {exc}") from None
        for k in range(first, len(presses)):
            p = presses[k]
            tx, ty = float(targets[k, 0]), float(targets[k, 1])
            hover = frame.surface_z_mm + s.hover_mm
            if p.indenter != self._mounted:
                self._change_indenter(rec, p)
            rec.move((tx, ty, hover), "move", p)
            rec.frames(s.rest_frames, "rest", p)
            rec.move((tx, ty, frame.surface_z_mm - p.depth_mm), "approach", p, s.approach_feed_mm_s)
            rec.frames(s.hold_frames, "hold", p)
            if p.slide_mm_s > 0:  # in the skin to the slide's end at its speed, held there, lifted there
                tx, ty = float(ends[k, 0]), float(ends[k, 1])
                rec.move((tx, ty, frame.surface_z_mm - p.depth_mm), "slide", p, p.slide_mm_s)
                rec.frames(s.hold_frames, "hold", p)
            if p.shake_hz > 0:  # shaken where it is, then held quiet
                self.rig.shake(p.shake_axis, VIBRATE_AMPLITUDE_MM, p.shake_hz, s.shake_s)
                rec.frames(round(s.shake_s * self.camera.fps), "shake", p)
                rec.frames(s.hold_frames, "hold", p)
            rec.move((tx, ty, hover), "release", p, s.approach_feed_mm_s)
            rec.commit(journal, {"kind": "press", "index": k})
            self.progress(k + 1, len(presses))

    def _check_unmoved(self, rec: RigRecorder, presses: list[PlannedPress], done: int) -> None:
        """Before a resumed collection presses again: the skin's surface found again (touch-off) and, with a
        circle mounted, the registration's five presses fitted again, each compared with the journalled rig
        frame. A sensor bumped, remounted or moved on the rig since is refused (every later press's truth
        would be wrong); the recording so far stays, to be continued once the rig is as it was, or
        started again with ``--fresh``."""
        s, frame, pitch = self.settings, rec.frame, self.bundle.layout.pitch_mm
        assert frame is not None  # the journalled one (_resume)
        x0, y0, _ = self._start
        last = presses[done - 1] if done else next((p for p in presses if p.shape == "circle"), presses[0])
        tip = PlannedPress(0.0, 0.0, s.register_depth_mm, last.shape, last.size_mm, last.angle_deg)
        self.prompt("checking that the sensor is where the collection left it: touch-off"
                    + (" and the registration presses" if tip.shape == "circle" else ""))
        surface, _ = touch_off(rec, (x0, y0, self.rig.limits.safe_z_mm), tip, s)
        moved: list[str] = []
        if abs(surface - frame.surface_z_mm) > 2 * s.touch_step_mm:  # the touch-off's own resolution, twice
            moved.append(f"the skin's surface is at z = {surface:.2f} mm, {frame.surface_z_mm:.2f} mm before")
        if tip.shape == "circle":
            again, _ = register(rec, (x0, y0, frame.surface_z_mm), tip, s, self.bundle.layout)
            shift = math.dist(again.origin_xy_mm, frame.origin_xy_mm)
            turn = abs((again.rotation_deg - frame.rotation_deg + 180.0) % 360.0 - 180.0)
            arc = math.radians(turn) * s.register_fraction * self.bundle.layout.radius_mm  # at the outer presses
            if shift > REGISTER_WARN_PITCH * pitch or arc > REGISTER_WARN_PITCH * pitch:
                moved.append(f"the sensor's origin is at rig ({again.origin_xy_mm[0]:.2f}, "
                             f"{again.origin_xy_mm[1]:.2f}), {shift:.2f} mm from before, its +x turned {turn:.1f}°")
        else:
            self.prompt(f"the sensor's x and y are not checked: the {tip.shape} indenter is mounted (a circle "
                        "reads a press's place)")
        if moved:
            raise RigError("the sensor moved since the collection began: " + "; ".join(moved) + " (allowed: "
                           f"{2 * s.touch_step_mm:g} mm in z, {REGISTER_WARN_PITCH * pitch:.2f} mm = "
                           f"{REGISTER_WARN_PITCH} pitch in x, y): put it back, or start again with --fresh")
        self.prompt("the sensor is where the collection left it")

    def _assume_mounted(self, presses: list[PlannedPress], done: int) -> None:
        """A resumed collection goes on with the indenter its last journalled step had on (the last press's,
        else the registration's circle), said in a line; the operator is asked only where the plan changes it
        (a rig that changes indenters itself is asked to mount each again)."""
        if self.rig.changes_indenters:
            return
        first = next((p for p in presses if p.shape == "circle"), presses[0])
        last = presses[done - 1] if done else first
        self._mounted = last.indenter
        self.prompt(f"continuing with the {last.shape} indenter, {last.size_mm:g} mm, mounted as it was")

    def _change_indenter(self, rec: RigRecorder, p: PlannedPress) -> None:
        if not self.rig.changes_indenters:
            x, y, _ = rec.at  # where the last move went: no report's x or y goes into a target
            rec.move((x, y, self.rig.limits.safe_z_mm), "move", None)
            self.confirm(f"mount the {p.shape} indenter, {p.size_mm:g} mm, at {p.angle_deg:g}° from the rig's +X; "
                         "then press Enter")
        self.rig.change_indenter(p.indenter)
        self._mounted = p.indenter

    def _retract_after(self, exc: BaseException) -> str | None:
        """Retract the tip after ``exc``; None, or why the tip was not retracted and where the machine last said
        it was (for the one line, after ``exc``'s). A retract once begun finishes: the first signal meanwhile
        is held (:func:`~optitac_edge.io.interrupts.deferred`), a second stops it. "Retracted" is said only
        on the machine's own reports (two in a row at the safe height, :meth:`Rig.lift`)."""
        with interrupts.deferred() as held:
            try:
                self.rig.retract()
            except BaseException as err:  # noqa: BLE001 - the original error is what the user must see first
                log.debug("could not retract the tip after %s: %s", type(exc).__name__, err)
                why = ("a second signal stopped the retract" if isinstance(err, KeyboardInterrupt)
                       else str(err))
                where = self._where()
                return f"the tip was NOT retracted: {why}" + (f"; {where}" if where else "")
        if held:
            log.info("%s came during the retract: held until it was done", signal.Signals(held[0]).name)
        try:
            self.prompt(f"retracted the tip to z = {self.rig.limits.safe_z_mm:g} mm")
        except OSError as err:  # a terminal gone with the SSH session that sent SIGHUP
            log.debug("could not say the tip was retracted: %s", err)
        return None

    def _where(self) -> str:
        """Where the machine's own report puts the tip, and what to do, for a line that says it is not safe
        ("" when the machine gives no position: its error says what to do)."""
        try:
            st = self.rig.status()
        except Exception:  # noqa: BLE001 - the line is about the tip, whatever the rig says
            return ""
        if not all(math.isfinite(v) for v in st.xyz_mm):
            return ""
        x, y, z = st.xyz_mm
        return (f"the machine last reported it at ({x:.2f}, {y:.2f}, {z:.2f}) mm, {st.raw_state or st.state}: "
                f"jog it up clear of the skin (safe z = {self.rig.limits.safe_z_mm:g} mm) before anything else")

    def _park(self) -> None:
        """The tip to the safe height over the start point, where the next collection starts."""
        x0, y0, _ = self._start
        safe = self.rig.limits.safe_z_mm
        self.rig.lift(safe)
        self.rig.move_and_wait((x0, y0, safe))
        self.prompt(f"parked the tip at z = {safe:g} mm over the start point ({x0:.2f}, {y0:.2f})")


def touch_off(rec: RigRecorder, start: tuple[float, float, float], tip: PlannedPress,
              s: CollectSettings) -> tuple[float, dict[str, float]]:
    """The skin's surface z under ``start``: coarse steps down to the first contact, back up, then fine steps
    through the surface; the surface is where the contact strength extrapolates to 0."""
    x, y, z0 = start
    lowest = rec.rig.limits.z_mm[0]

    def probe(z: float) -> tuple[bool, float]:
        if z < lowest:
            raise RigError(f"touch-off: no contact down to the rig's lowest z ({lowest:g} mm): "
                           "is the tip over the skin?")
        rec.move((x, y, z), "approach", tip, s.approach_feed_mm_s)
        est = rec.frames(3, "approach", tip)
        return (sum(bool(e.contact) for e in est) >= 2,
                float(np.mean([e.strength if e.contact else 0.0 for e in est])))

    coarse = 5 * s.touch_step_mm
    z = z0
    while not probe(z := round(z - coarse, 4))[0]:
        pass
    z = round(z + coarse + s.touch_step_mm, 4)  # above the first contact again, then fine steps
    rec.move((x, y, z + s.hover_mm), "release", tip, s.approach_feed_mm_s)
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
    rec.move((x, y, surface + s.hover_mm), "release", tip, s.approach_feed_mm_s)
    return surface, {"first_contact_z_mm": round(found_at, 4), "surface_z_mm": round(surface, 4),
                     "steps": len(samples)}


def register(rec: RigRecorder, centre: tuple[float, float, float], tip: PlannedPress, s: CollectSettings,
             layout: FiberLayout) -> tuple[RigFrame, Symmetry]:
    """Five presses around ``centre`` (x, y and the surface's z): the rig-to-sensor transform fitted to where
    the pipeline reads them, and the symmetry of the layout the bundle's fiber map is off by."""
    x0, y0, surface = centre
    d = s.register_fraction * layout.radius_mm
    points = [(x0, y0), (x0 + d, y0), (x0, y0 + d), (x0 - d, y0), (x0, y0 - d)]
    hover, depth = surface + s.hover_mm, surface - s.register_depth_mm
    for px, py in points:
        rec.rig.limits.check((px, py, hover))
        rec.rig.limits.check((px, py, depth))
    seen = []
    for px, py in points:
        rec.move((px, py, hover), "move", tip)
        rec.frames(s.rest_frames, "rest", tip)
        rec.move((px, py, depth), "approach", tip, s.approach_feed_mm_s)
        est = [e for e in rec.frames(s.hold_frames, "hold", tip) if e.contact]
        if len(est) < s.hold_frames // 2:
            raise RigError(f"registration press at rig ({px:.2f}, {py:.2f}) was not seen by the camera: "
                           "is the start point over the middle of the skin?")
        seen.append((np.mean([e.x_mm for e in est]), np.mean([e.y_mm for e in est])))
        rec.move((px, py, hover), "release", tip, s.approach_feed_mm_s)
    try:
        return fit_rig_frame(np.array(points), np.array(seen), surface, layout_symmetries(layout), layout.pitch_mm)
    except ValueError as exc:
        raise RigError(str(exc)) from None
