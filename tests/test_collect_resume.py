"""Nothing a collection collected is lost: a complete recording is never overwritten, an interrupted one
(SIGINT, SIGTERM, SIGHUP, SIGKILL, a clock that restarted) continues into a recording that calibrates, and
the tip is retracted on every way out but SIGKILL, and parked at the end."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys

import numpy as np
import pytest

from optitac_edge.bringup.collect import JOURNAL
from optitac_edge.cli import main
from optitac_edge.io.recording import Recording

#: Starts the CLI as from a terminal: SIGINT raises, as Ctrl-C does (background jobs start with it ignored).
START = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
         "sys.argv = ['optitac-edge', *sys.argv[1:]]; runpy.run_module('optitac_edge.cli', run_name='__main__')")


#: ... and sends itself ``signum`` once ``after`` presses are journalled, at the next press's first hold frame
#: (the tip in the skin): a real signal to the real handler, at one place whatever the machine's load. (Sent
#: from the test when the journal showed the presses, it came after the end on a loaded machine: the rest of a
#: 6-press collection takes about 1.5 s.)
AT_HOLD = ("import os, signal, sys; import optitac_edge.bringup.rig_recorder as rr; "
           "signum, after = int(sys.argv.pop(1)), int(sys.argv.pop(1)); done = []; "
           "commit, frames = rr.RigRecorder.commit, rr.RigRecorder.frames\n"
           "def counted(self, journal, entry, new=False):\n"
           "    commit(self, journal, entry, new); done.extend([1] if entry.get('kind') == 'press' else [])\n"
           "def held(self, n, phase, press):\n"
           "    if phase == 'hold' and len(done) >= after: os.kill(os.getpid(), signum)\n"
           "    return frames(self, n, phase, press)\n"
           "rr.RigRecorder.commit, rr.RigRecorder.frames = counted, held\n")


def _interrupt(out, signum: int, after_presses: int, limit: int = 8) -> tuple[int, str, str]:
    """Run ``collect seen`` on sim:// in a process of its own that gets ``signum`` in the press after
    ``after_presses`` presses are journalled; (exit status, stdout, stderr)."""
    proc = subprocess.run([sys.executable, "-c", AT_HOLD + START, str(int(signum)), str(after_presses), "collect",
                           "seen", "--rig", "sim://", "-o", str(out), "--limit", str(limit)],
                          check=False, capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGKILL])  # SIGINT: tests/test_collect.py
def test_an_interrupted_collection_continues_into_a_recording_that_calibrates(signum, tmp_path, capsys) -> None:
    """Before: SIGTERM and SIGHUP left the tip pressed (no retract); the continued collection ended 'frame
    times go backwards' (the simulator's clock starts again in a new process, as CLOCK_MONOTONIC does after a
    reboot) and every later try said the same."""
    out = tmp_path / "seen"
    code, stdout, err = _interrupt(out, signum, after_presses=2, limit=6)
    if signum == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        assert code == 128 + signum
        assert "retracted the tip to z = 12 mm" in stdout
        name = "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"
        assert err.strip().splitlines()[-1].startswith(f"optitac-edge: interrupted{name}: tip retracted; recording")
    kept = len((out / JOURNAL).read_text().splitlines()) - 1
    assert kept >= 2
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "6"]) == 0
    said = capsys.readouterr().out
    assert f"continuing seen after press {kept} of 6" in said and "parked the tip at z = 12 mm" in said
    rec = Recording(out)
    assert rec.timestamped and np.all(np.diff(rec.t_ns) > 0)
    segments = rec.meta.extra["segments"]
    assert len(segments) == 2 and segments[0] == {"first_frame": 0, "offset_ns": 0}
    assert segments[1]["offset_ns"] > 0  # the virtual clock started again at 0
    assert rec.rig_poses is not None and len(rec.rig_poses.frame) == len(rec)
    assert not (out / JOURNAL).exists()
    cal = tmp_path / "cal.npz"
    assert main(["calibrate", "fibers", str(out), "-o", str(cal)]) == 0
    assert main(["calibrate", "centroid", str(out), "--cal", str(cal)]) == 0
    said = capsys.readouterr().out
    fitted = [float(v) for v in said.split("fitted rmse mm ")[1].split()[0].rstrip(",").split("/")]
    assert max(fitted) < 0.05
    # the registration, the resumed collection's check of it and the presses, none twice
    assert int(np.sum(rec.rig_poses.phase == "hold")) == (5 + 5 + 6) * 8


def test_a_complete_recording_is_never_overwritten(tmp_path, capsys) -> None:
    """Before: collect (and record, sim) with -o on a finished recording started over at once; an interrupt
    then left only frames.npy and incomplete.json, the recording's meta, truth and times gone."""
    out = tmp_path / "seen"
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "2"]) == 0
    before = {f.name: f.read_bytes() for f in out.iterdir()}
    capsys.readouterr()
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds a complete recording" in err[0] and "--fresh" in err[0]
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before
    # --fresh, interrupted: the old recording is still there, whole
    proc = subprocess.Popen([sys.executable, "-c", START, "collect", "seen", "--rig", "sim://", "-o", str(out),
                             "--limit", "4", "--fresh"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("sensor origin at rig"):
            break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and f"recording {out} unchanged" in err.strip().splitlines()[-1]
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before
    # --fresh to the end: replaced only now
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "3", "--fresh"]) == 0
    assert Recording(out).meta.extra["collect"]["presses"] == 3
    assert not (tmp_path / "seen.new").exists() and not (tmp_path / "seen.old").exists()


def test_sim_and_record_follow_the_same_rule(tmp_path, capsys) -> None:
    rest = tmp_path / "rest"
    assert main(["sim", str(rest), "--scenario", "rest", "--frames", "12"]) == 0
    meta = (rest / "meta.json").read_bytes()
    for argv in (["sim", str(rest), "--scenario", "rest", "--frames", "20"],
                 ["record", "-o", str(rest), "--frames", "20"]):
        capsys.readouterr()
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "holds a complete recording" in err[0] and "--fresh" in err[0]
        assert (rest / "meta.json").read_bytes() == meta
    assert main(["record", "-o", str(rest), "--frames", "20", "--fresh"]) == 0
    assert len(Recording(rest)) == 20
    mcap = tmp_path / "rest.mcap"
    assert main(["record", "-o", str(mcap), "--frames", "10"]) == 0
    before = mcap.read_bytes()
    assert main(["record", "-o", str(mcap), "--frames", "12"]) == 2
    assert "holds a complete recording" in capsys.readouterr().err and mcap.read_bytes() == before
    assert main(["sim", str(mcap), "--scenario", "rest", "--frames", "12"]) == 2
    assert mcap.read_bytes() == before


def test_an_edited_journal_is_one_line_not_a_traceback(tmp_path, capsys) -> None:
    out = tmp_path / "seen"
    _interrupt(out, signal.SIGKILL, after_presses=2, limit=6)
    journal = out / JOURNAL
    lines = journal.read_text().splitlines()
    press = json.loads(lines[1])
    press["rows"][0]["rig"] = [1, "x", 3]
    journal.write_text("\n".join([lines[0], json.dumps(press), *lines[2:]]) + "\n")
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "6"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "collect.jsonl: line 2:" in err[0] and "--fresh" in err[0]
    journal.write_text("\n".join([lines[0], "[1, 2]", *lines[2:]]) + "\n")
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "6"]) == 2
    assert "line 2: not a JSON object" in capsys.readouterr().err
    # issue 38, item 20: a time past int64 and a contact 'yes' were tracebacks; x 5000 mm a 'complete' recording
    # no reader could open
    touching = next(k for k, r in enumerate(json.loads(lines[1])["rows"]) if r.get("contact"))
    for edit, words in ((lambda p: p["t_ns"].__setitem__(-1, 2**63), "frame times that are not integers"),
                        (lambda p: p["rows"][touching].__setitem__("contact", "yes"), "not true or false"),
                        (lambda p: p["rows"][touching].__setitem__("x", 5000.0), "each a number of at most 1000")):
        press = json.loads(lines[1])
        edit(press)
        journal.write_text("\n".join([lines[0], json.dumps(press), *lines[2:]]) + "\n")
        assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "6"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "collect.jsonl: line 2:" in err[0] and words in err[0], err


@pytest.mark.parametrize(("rig", "said"), [
    ("sim://?origin=101.5,80", r"the sensor's origin is at rig \(101\.\d\d, (79|80)\.\d\d\), 1\.\d\d mm from before"),
    ("sim://?surface=2.5", r"the skin's surface is at z = 2\.5\d mm, 2\.0\d mm before"),
])
def test_a_collection_continued_on_a_moved_rig_is_refused_and_continues_once_it_is_back(rig, said, tmp_path,
                                                                                         capsys) -> None:
    """Before: a resume used the journalled rig frame as it was, so every later press's truth was off by the
    move. Now the resume finds the surface again and fits the registration again first: a sensor moved by more
    than the touch-off's resolution or 0.2 pitch is refused in one line (the tip retracted, the recording
    kept), and once the rig is as it was the collection continues."""
    out = tmp_path / "seen"
    code, _, _ = _interrupt(out, signal.SIGTERM, after_presses=2, limit=4)
    assert code == 128 + signal.SIGTERM
    journal = (out / JOURNAL).read_text()
    assert main(["collect", "seen", "--rig", rig, "-o", str(out), "--limit", "4"]) == 2
    captured = capsys.readouterr()
    line = captured.err.strip().splitlines()[-1]
    assert line.startswith("optitac-edge: error: the sensor moved since the collection began: ")
    assert re.search(said, line) and line.endswith("put it back, or start again with --fresh"), line
    assert "retracted the tip to z = 12 mm" in captured.out
    assert (out / JOURNAL).read_text() == journal  # nothing of the refused resume kept
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "4"]) == 0
    said_out = capsys.readouterr().out
    assert "the sensor is where the collection left it" in said_out and "parked the tip" in said_out
    assert len(Recording(out)) > 0 and not (out / JOURNAL).exists()
