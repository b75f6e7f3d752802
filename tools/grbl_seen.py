"""A full ``seen`` collection (217 presses) through the GRBL backend against the fake GRBL of the tests,
interrupted by Ctrl-C half way, continued, then calibrated and evaluated.

The fake machine (tests/fakes/grbl.py) runs on a pty and follows GRBL 1.1's protocol; its tool head presses
the simulated skin (the simulated camera reads the machine's position for every frame). Motion runs
``--speed`` times faster than commanded, to keep the run short.

    python tools/grbl_seen.py [--speed 20] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from fakes.grbl import FakeGrbl

from optitac_edge.bringup.collect import JOURNAL, Collector
from optitac_edge.calibration.evaluation import centroid_accuracy, detection
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.measure import measure_recording
from optitac_edge.calibration.steps import calibrate_centroid, calibrate_orientation
from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import Recording
from optitac_edge.io.rigs.base import RigLimits
from optitac_edge.io.rigs.gcode import GcodeRig
from optitac_edge.sim.camera import SimCamera
from optitac_edge.sim.rig import SimMount
from optitac_edge.sim.scenarios import write_scenario
from optitac_edge.sim.skin import Indenter

LIMITS = RigLimits(x_mm=(60.0, 140.0), y_mm=(40.0, 120.0), z_mm=(-3.0, 20.0), feed_mm_s=10.0, safe_z_mm=12.0)
MOUNT = SimMount(origin_xy_mm=(100.0, 80.0), rotation_deg=-9.0, surface_z_mm=2.0)


class Skin:
    def __init__(self, machine: FakeGrbl) -> None:
        self.machine = machine

    def at(self, frame: int) -> Indenter | None:
        x, y, z = self.machine.position()
        depth = MOUNT.surface_z_mm - z
        if depth <= 0:
            return None
        sx, sy = MOUNT.to_sensor(x, y)
        return Indenter("circle", sx, sy, 0.0, 5.0, depth)


class CtrlC:
    def __init__(self, camera: SimCamera, journal: Path, after: int) -> None:
        self.camera, self.journal, self.after, self.frames = camera, journal, after, 0

    def __getattr__(self, name: str) -> object:
        return getattr(self.camera, name)

    def read(self, timeout_s: float = 1.0):  # type: ignore[no-untyped-def]
        if self.journal.exists() and len(self.journal.read_text().splitlines()) > self.after:
            self.frames += 1
            if self.frames == 25:
                raise KeyboardInterrupt
        return self.camera.read(timeout_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--speed", type=float, default=20.0)
    ap.add_argument("--workdir", type=Path, default=Path("grbl_seen"))
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    out = args.workdir / "seen"
    machine = FakeGrbl(speed=args.speed)
    camera = SimCamera(realtime=False, program=Skin(machine))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
    lines: list[str] = []
    t0 = time.monotonic()
    report: dict[str, object] = {}
    with GcodeRig(machine.port, LIMITS) as rig:
        try:
            Collector(CtrlC(camera, out / JOURNAL, 108), rig, bundle, prompt=lines.append,
                      confirm=lines.append).run("seen", out, fresh=True)
        except KeyboardInterrupt:
            report["interrupted_after_presses"] = len((out / JOURNAL).read_text().splitlines()) - 1
            report["tip_z_after_interrupt_mm"] = machine.position()[2]
            report["grbl_realtime_bytes"] = [b.decode("latin1") for b in machine.realtime if b != b"?"]
            report["last_line"] = lines[-1]
    try:
        Recording(out)
    except RecordingError as exc:
        report["recording_after_interrupt"] = str(exc).split(": ", 1)[1]
    with GcodeRig(machine.port, LIMITS) as rig:
        result = Collector(camera, rig, bundle, prompt=lines.append, confirm=lines.append).run("seen", out)
    report["resumed"] = result.to_json()
    report["collect_s"] = round(time.monotonic() - t0, 1)
    rec = Recording(out)
    cal = calibrate_fibers(rec.rest_frames(), rec.pixel_format)
    cal, fit = calibrate_orientation(rec, cal)
    cal, summary = calibrate_centroid(rec, cal)
    report["orientation"] = fit.symmetry.label if fit.symmetry else fit.reason
    report["centroid_fit"] = summary
    unseen = Recording(write_scenario(args.workdir / "unseen", "unseen", seed=21, fresh=True))
    m = measure_recording(unseen, cal)
    c, d = centroid_accuracy(m, unseen.truth), detection(m, unseen.truth)
    report["unseen_rmse_mm"] = [round(c.rmse_x, 4), round(c.rmse_y, 4)]
    report["unseen_detection"] = f"{d.detected}/{d.contact_frames}, false {d.false_contacts}/{d.rest_frames}"
    machine.close()
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
