"""Interrupt a collection and continue it, on the simulator's rig and on the fake GRBL, and compare.

For each way out -- SIGINT (Ctrl-C), SIGTERM (a stop), SIGHUP (a closed SSH session), SIGKILL (a kill or a
power cut) -- a ``seen`` collection is interrupted after a few presses and the same collection is run again
with a clock that starts again (the simulator's virtual clock in every process; for GRBL a camera whose
times start at 0 in every process, as CLOCK_MONOTONIC after a reboot). Reported for each: whether the tip
was retracted, the recording's segments, and the calibration's figures (centroid fit, and accuracy on
another recording's presses) beside those of an uninterrupted collection.

    python tools/resume_check.py [--rig sim|grbl|both] [--presses 24] [--workdir DIR]

The GRBL runs drive the fake GRBL of the tests (tests/fakes/grbl.py: GRBL 1.1's protocol and alarms) on a
pty from this process, and the collection from a process of its own, as a real bench would.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

SIGNALS = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM, "SIGHUP": signal.SIGHUP, "SIGKILL": signal.SIGKILL}
#: Starts the CLI as from a terminal: SIGINT raises, as Ctrl-C does.
START = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
         "sys.argv = ['optitac-edge', *sys.argv[1:]]; runpy.run_module('optitac_edge.cli', run_name='__main__')")


def figures(rec_path: Path, unseen: Path) -> dict[str, Any]:
    """The calibration's figures from a collection: the fiber map from its rest frames, the centroid maps from
    its presses, and accuracy on another recording's presses."""
    from optitac_edge.calibration.evaluation import centroid_accuracy, detection
    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.calibration.measure import measure_recording
    from optitac_edge.calibration.steps import calibrate_centroid
    from optitac_edge.io.recording import Recording

    rec = Recording(rec_path)
    cal = calibrate_fibers(rec.rest_frames(), rec.pixel_format)
    cal, fit = calibrate_centroid(rec, cal)
    other = Recording(unseen)
    m = measure_recording(other, cal)
    c, d = centroid_accuracy(m, other.truth), detection(m, other.truth)
    return {"frames": len(rec), "segments": rec.meta.extra.get("segments", []),
            "times_in_order": bool((rec.t_ns[1:] > rec.t_ns[:-1]).all()),
            "fitted_rmse_mm": fit["fitted_rmse_mm"], "unseen_rmse_mm": [round(c.rmse_x, 4), round(c.rmse_y, 4)],
            "unseen_detection": f"{d.detected}/{d.contact_frames}, false {d.false_contacts}/{d.rest_frames}"}


def _journal_presses(out: Path) -> int:
    journal = out / "collect.jsonl"
    return max(len(journal.read_text().splitlines()) - 1, 0) if journal.exists() else 0


def _interrupt(cmd: list[str], out: Path, signum: int, after: int) -> tuple[int, str]:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    while proc.poll() is None and _journal_presses(out) < after:
        time.sleep(0.01)
    proc.send_signal(signum)
    text, _ = proc.communicate(timeout=120)
    return proc.returncode, text


# -- the simulator's rig, through the command line --------------------------------------------------------

def sim_rig(work: Path, presses: int, unseen: Path) -> dict[str, Any]:
    def cmd(out: Path) -> list[str]:
        return [sys.executable, "-c", START, "collect", "seen", "--rig", "sim://", "-o", str(out),
                "--limit", str(presses)]

    report: dict[str, Any] = {}
    whole = work / "sim-whole"
    subprocess.run(cmd(whole), check=True, capture_output=True)
    report["uninterrupted"] = figures(whole, unseen)
    for name, signum in SIGNALS.items():
        out = work / f"sim-{name}"
        code, text = _interrupt(cmd(out), out, signum, presses // 3)
        kept = _journal_presses(out)
        again = subprocess.run(cmd(out), check=False, capture_output=True, text=True)
        report[name] = {"exit": code, "retracted": "retracted the tip" in text, "kept_presses": kept,
                        "continued": f"continuing seen after press {kept}" in again.stdout,
                        "parked": "parked the tip" in again.stdout, **figures(out, unseen)}
    return report


# -- the fake GRBL, the collection in a process of its own ------------------------------------------------

def grbl_child(port: str, out: Path, bundle: Path, presses: int) -> int:
    """The collection's process: GRBL on ``port``, a camera whose skin follows the machine's reports and
    whose times start at 0 in this process (a reboot's CLOCK_MONOTONIC)."""
    from test_rig_gcode import LIMITS, MOUNT

    from optitac_edge.bringup.collect import Collector, CollectSettings
    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.cli import _interrupt_on_signals
    from optitac_edge.errors import Interrupted
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.cameras.base import CapturedFrame
    from optitac_edge.io.rigs.gcode import GcodeRig
    from optitac_edge.sim.camera import SimCamera
    from optitac_edge.sim.skin import Indenter

    class Follows:
        """The skin pressed where the machine last said its tip is."""

        def __init__(self) -> None:
            self.xyz = (0.0, 0.0, 100.0)

        def at(self, frame: int) -> Indenter | None:
            x, y, z = self.xyz
            depth = MOUNT.surface_z_mm - z
            if depth <= 0:
                return None
            sx, sy = MOUNT.to_sensor(x, y)
            return Indenter("circle", sx, sy, 0.0, 5.0, depth)

    skin = Follows()

    class RestartedClock:
        def __init__(self, camera: SimCamera) -> None:
            self.camera, self.t0 = camera, time.monotonic_ns()

        def __getattr__(self, name: str) -> Any:
            return getattr(self.camera, name)

        def read(self, timeout_s: float = 1.0) -> CapturedFrame | None:
            f = self.camera.read(timeout_s)
            return None if f is None else CapturedFrame(f.frame, f.t_ns - self.t0, f.seq)

    _interrupt_on_signals()
    with GcodeRig(port, LIMITS) as rig:
        poll = rig.poll

        def noted() -> Any:
            st = poll()
            if st.plausible and st.state != "alarm":
                skin.xyz = st.xyz_mm
            return st

        rig.poll = noted  # type: ignore[method-assign]
        rig.poll()
        camera = RestartedClock(SimCamera(realtime=False, program=skin))
        settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=5)
        collector = Collector(camera, rig, load_bundle(bundle), settings, prompt=lambda line: print(line, flush=True),
                              storage="fibers",
                              find_fibers=lambda rest, fmt: calibrate_fibers(rest, fmt).fibers)
        try:
            collector.run("seen", out, limit=presses)
        except Interrupted as exc:
            return 128 + exc.signum
        except KeyboardInterrupt:
            return 130
    return 0


def grbl_rig(work: Path, presses: int, unseen: Path) -> dict[str, Any]:
    from fakes.grbl import FakeGrbl

    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.sim.camera import SimCamera

    bundle = work / "grbl-cal.npz"
    with SimCamera(realtime=False) as camera:
        save_bundle(calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray"), bundle)

    def cmd(port: str, out: Path) -> list[str]:
        return [sys.executable, __file__, "--child", port, str(out), str(bundle), str(presses)]

    report: dict[str, Any] = {}
    machine = FakeGrbl(speed=20.0)
    try:
        whole = work / "grbl-whole"
        subprocess.run(cmd(machine.port, whole), check=True, capture_output=True)
        report["uninterrupted"] = figures(whole, unseen)
        for name, signum in SIGNALS.items():
            machine.close()
            machine = FakeGrbl(speed=20.0)
            out = work / f"grbl-{name}"
            code, text = _interrupt(cmd(machine.port, out), out, signum, presses // 3)
            time.sleep(0.2)
            z_after = machine.position()[2]
            kept = _journal_presses(out)
            again = subprocess.run(cmd(machine.port, out), check=False, capture_output=True, text=True)
            report[name] = {"exit": code, "tip_z_after_mm": round(z_after, 3), "kept_presses": kept,
                            "retracted": "retracted the tip" in text, "parked_at": [round(v, 3) for v in
                                                                                   machine.position()],
                            "continued": f"continuing seen after press {kept}" in again.stdout,
                            **figures(out, unseen)}
    finally:
        machine.close()
    return report


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        port, out, bundle, presses = sys.argv[2:6]
        sys.exit(grbl_child(port, Path(out), Path(bundle), int(presses)))
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rig", choices=("sim", "grbl", "both"), default="both")
    ap.add_argument("--presses", type=int, default=24)
    ap.add_argument("--workdir", type=Path, default=Path("resume_check"))
    args = ap.parse_args()
    import shutil

    from optitac_edge.sim.scenarios import write_scenario

    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    unseen = write_scenario(args.workdir / "unseen", "unseen", seed=21)
    report: dict[str, Any] = {}
    if args.rig in ("sim", "both"):
        report["sim://"] = sim_rig(args.workdir, args.presses, unseen)
    if args.rig in ("grbl", "both"):
        report["fake GRBL"] = grbl_rig(args.workdir, args.presses, unseen)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
