"""The collection's one loop at the edge: read a frame, poll the rig, write both, and journal each step."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.bringup.experiments import PlannedPress
from optitac_edge.bringup.journal import append_entry
from optitac_edge.bringup.rig_frame import RigFrame
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import CameraError, RigError
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.recording_writer import Press, RecordingWriter
from optitac_edge.io.rigs.base import STOPPED_STATES, Rig, RigStatus


class RigRecorder:
    """Every frame of a collection into the recording, with a truth row of its phase and the rig's pose.

    Truth rows wait in :attr:`rows` until :meth:`commit` writes them with a journal line (a step is
    kept whole or not at all). Before the rig frame is known (:meth:`set_frame`), rows keep their
    press and get the contact's position in the sensor's frame once it is.

    Parameters
    ----------
    camera, rig : Camera, Rig
    pipeline : Pipeline
        Reads each frame (raw estimates: the collection places presses itself).
    writer : RecordingWriter
        The recording being written.
    read_timeout_s : float
        Longest wait for a frame.
    """

    def __init__(self, camera: Camera, rig: Rig, pipeline: Pipeline, writer: RecordingWriter,
                 read_timeout_s: float) -> None:
        self.camera, self.rig, self.pipeline, self.writer = camera, rig, pipeline, writer
        self.read_timeout_s = read_timeout_s
        #: The next frame's index in the recording.
        self.index = writer.frames_written
        #: Truth rows and frame times since the last :meth:`commit`.
        self.rows: list[dict[str, Any]] = []
        self.times: list[int] = []
        #: The rig-to-sensor transform (None until registration).
        self.frame: RigFrame | None = None
        #: The last move's target (no report's x or y goes into a target).
        self.at = (math.nan, math.nan, math.nan)

    def step(self, phase: str, press: PlannedPress | None) -> tuple[ContactEstimate, RigStatus]:
        """One frame and the rig's state: written, its row kept; the frame's primary estimate (a copy)."""
        captured = self.camera.read(self.read_timeout_s)
        if captured is None:
            raise CameraError("the camera ended during the collection")
        st = self.rig.status()
        if st.state in STOPPED_STATES:
            raise RigError(f"the rig is {STOPPED_STATES[st.state]} ({st.raw_state or st.state}); the collection "
                           "stopped: run the same command to continue")
        t_ns = self.writer.write(self.index, captured.frame, captured.t_ns)
        self.rows.append(self._row(phase, press, st.xyz_mm, st.t_ns))
        self.times.append(int(captured.t_ns if t_ns is None else t_ns))
        self.index += 1
        # a frame of the recording being written: every one processed as its replay will (none skipped), a copy
        # (the callers keep the estimates of several frames; the pipeline's own is reused)
        self.pipeline.bundle.fibers.check_frame(captured.frame, self.camera.pixel_format)
        return self.pipeline.process_recorded(captured.frame, captured.t_ns).primary.copy(), st

    def frames(self, n: int, phase: str, press: PlannedPress | None) -> list[ContactEstimate]:
        """``n`` frames where the tip is."""
        return [self.step(phase, press)[0] for _ in range(n)]

    def move(self, xyz: tuple[float, float, float], phase: str, press: PlannedPress | None,
             feed_mm_s: float | None = None) -> list[ContactEstimate]:
        """Move the tip, recording every frame until the rig is idle there."""
        self.rig.move_to(xyz, feed_mm_s)
        self.at = xyz
        feed = min(feed_mm_s or self.rig.limits.feed_mm_s, self.rig.limits.feed_mm_s)
        budget = max(5, int((20.0 + 3.0 * math.dist(xyz, self.rig.status().xyz_mm) / feed) * self.camera.fps))
        estimates = []
        for _ in range(budget):
            est, st = self.step(phase, press)
            estimates.append(est)
            if st.state == "idle" and math.dist(st.xyz_mm, xyz) < 0.01:
                return estimates
        raise RigError(f"the rig did not reach {xyz} within {budget} frames")

    def start_pose(self) -> tuple[float, float, float]:
        """Where the operator left the tip: two reports in a row that agree (no single report is trusted)."""
        last = self.rig.status().xyz_mm
        for _ in range(10):
            pose = self.rig.status().xyz_mm
            if math.dist(pose, last) < 0.01:
                return pose
            last = pose
        raise RigError("the rig reports a different position every time although it should stand still "
                       f"(last {last}); is it moving, or is the line noisy?")

    def set_frame(self, frame: RigFrame) -> None:
        """The rig frame is known: the rows kept so far get their contacts in the sensor's frame."""
        self.frame = frame
        self.rows = [self._complete(r, r.pop("_press")) for r in self.rows]

    def write_rows(self, rows: list[dict[str, Any]], times: list[int]) -> None:
        """Write truth rows into the recording (kept ones of an interrupted collection, or a step's), with
        ``times`` their frames' (ns): the press's motion from the rig's pose when the recording has the
        motion columns."""
        motions = row_motions(rows, times)
        for row, motion in zip(rows, motions):
            xyz = (float(row["rig"][0]), float(row["rig"][1]), float(row["rig"][2]))
            press = Press(row["shape"], row["x"], row["y"], row["angle"], row["size"], row["depth"]) \
                if row.get("contact") else None
            self.writer.write_truth(row["frame"], press, phase=row["phase"], rig_xyz_mm=xyz, motion=motion)

    def flush(self) -> None:
        """Write the rows kept since the last :meth:`commit` (the end of a collection: no journal line, as the
        journal goes with it; interrupted before the end, the journal's last step decides what is kept)."""
        self.write_rows(self.rows, self.times)
        self.rows, self.times = [], []

    def commit(self, journal: Path, entry: dict[str, Any], new: bool = False) -> None:
        """End a step: its rows written, its frames durable, then its journal line (``entry`` with the step's
        rows, times and the recording's segments) appended and made durable: the resume point."""
        self.write_rows(self.rows, self.times)
        self.writer.sync()
        append_entry(journal, {**entry, "end_frame": self.index, "rows": self.rows, "t_ns": self.times,
                               "segments": self.writer.segments}, new=new)
        self.rows, self.times = [], []

    def _row(self, phase: str, press: PlannedPress | None, xyz: tuple[float, float, float],
             t_ns: int | None) -> dict[str, Any]:
        row: dict[str, Any] = {"frame": self.index, "phase": phase, "rig": [round(v, 4) for v in xyz]}
        if t_ns is not None:
            row["rig_t_ns"] = t_ns  # when the pose was read: the motion's time (row_motions)
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


#: A contact moving slower than this while the tip slides is held (the rig at the slide's end), mm/s.
HELD_BELOW_MM_S = 0.5


def row_motions(rows: list[dict[str, Any]], times: list[int]) -> list[tuple[float, float, str]]:
    """Each truth row's motion: the press's velocity in the sensor frame (mm/s) over the frame before it (from
    the rig's poses and the times they were read, ``rig_t_ns``, or else ``times``, the frames'; over the frame
    after it at the start of a run of rows in contact), and ``sliding``
    (the ``slide`` phase, faster than :data:`HELD_BELOW_MM_S`), ``vibrating`` (``shake``), ``held`` (``hold``,
    or a slide at rest), ``pressing`` (in contact while approaching or releasing) or '' (no contact)."""
    out: list[tuple[float, float, str]] = []
    n = len(rows)
    if all(r.get("rig_t_ns") is not None for r in rows):  # a pose's own time: the frame's may be older
        times = [int(r["rig_t_ns"]) for r in rows]
    for k, row in enumerate(rows):
        if not row.get("contact"):
            out.append((math.nan, math.nan, ""))
            continue
        if k > 0 and rows[k - 1].get("contact"):
            a, b = k - 1, k
        else:
            a, b = k, (k + 1 if k + 1 < n and rows[k + 1].get("contact") else k)
        dt = (times[b] - times[a]) * 1e-9 if b != a else 0.0
        vx, vy = ((rows[b]["x"] - rows[a]["x"]) / dt, (rows[b]["y"] - rows[a]["y"]) / dt) if dt > 0 else (0.0, 0.0)
        phase = row["phase"]
        if phase == "slide":
            state = "sliding" if math.hypot(vx, vy) > HELD_BELOW_MM_S else "held"
        elif phase == "shake":
            state = "vibrating"
        else:
            state = "held" if phase == "hold" else "pressing"
        out.append((vx, vy, state))
    return out
