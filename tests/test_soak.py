"""Soak: `optitac-edge soak` runs the full loop on the simulator with injected camera faults and
serial unplugs; every fault must be recovered, no exception escape, memory stay flat.

The tests run it on the virtual clock (``--virtual-time``): OPTITAC_SOAK_MINUTES (default 0.5)
minutes of service time in seconds of computing, the same counts for the same seed on any
machine. docs/reliability.md records the 60-minute runs in real time.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from optitac_edge.cli import main

#: Fields of the summary line that the seed alone decides (the serial link's threads run in real time).
DETERMINISTIC = ("frames", "faults injected", "camera faults counted", "reopens", "failed", "serial unplugs")


def _soak(minutes: float, seed: int) -> str:
    out = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "soak", "--minutes", str(minutes),
                          "--fault-rate", "0.02", "--seed", str(seed), "--virtual-time"],
                         capture_output=True, text=True, check=False, timeout=600,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stdout + out.stderr
    assert "Traceback" not in out.stderr
    return out.stdout.strip().splitlines()[-1]


def _field(line: str, name: str) -> int:
    found = re.search(rf"\b{name} \(?(\d+)", line)
    assert found, (name, line)
    return int(found.group(1))


def test_soak_recovers_every_injected_fault_with_flat_memory_and_repeats_exactly():
    minutes = float(os.environ.get("OPTITAC_SOAK_MINUTES", "0.5"))
    line = _soak(minutes, seed=3)
    assert line.endswith(": OK"), line
    assert line.startswith(f"soak {minutes * 60:.0f} s:")  # service time, whatever the machine's speed
    injected, counted = _field(line, "faults injected"), _field(line, "camera faults counted")
    assert injected == counted and injected >= 30 * minutes
    kinds = re.search(r"faults injected \d+ \(([^)]*)\)", line).group(1)
    assert len(kinds.split()) == 8  # every kind of fault
    assert _field(line, "unhandled exceptions") == 0
    unplugs = _field(line, "serial unplugs")
    assert unplugs == int(minutes * 60 // 7)  # every 7 s of service time
    assert _field(line, "reconnects") >= unplugs - 1
    again = _soak(minutes, seed=3)
    assert [_field(again, k) for k in DETERMINISTIC] == [_field(line, k) for k in DETERMINISTIC]


def test_soak_rejects_bad_arguments(capsys):
    with pytest.raises(SystemExit) as info:
        main(["soak", "--minutes", "0"])
    assert info.value.code == 2
    assert "argument --minutes: 0 is outside (0..1e+06)" in capsys.readouterr().err
