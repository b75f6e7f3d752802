"""Soak: `optitac-edge soak` runs the full loop on the simulator with injected camera faults and
serial unplugs; every fault must be recovered, no exception escape, memory stay flat.

CI runs OPTITAC_SOAK_MINUTES (default 2) minutes; docs/reliability.md records a 60-minute run.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from optitac_edge.cli import main


@pytest.mark.slow
def test_soak_recovers_every_injected_fault_with_flat_memory():
    minutes = float(os.environ.get("OPTITAC_SOAK_MINUTES", "2"))
    out = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "soak", "--minutes", str(minutes),
                          "--fault-rate", "0.02", "--seed", "3"], capture_output=True, text=True, check=False,
                         timeout=minutes * 60 + 120, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stdout + out.stderr
    line = out.stdout.strip().splitlines()[-1]
    assert line.endswith(": OK"), line
    assert "Traceback" not in out.stderr
    injected = int(re.search(r"faults injected (\d+)", line).group(1))
    counted = int(re.search(r"camera faults counted (\d+)", line).group(1))
    assert injected == counted and injected >= 10 * minutes
    assert int(re.search(r"unhandled exceptions (\d+)", line).group(1)) == 0
    assert int(re.search(r"serial unplugs (\d+)", line).group(1)) >= 1
    assert int(re.search(r"reconnects (\d+)", line).group(1)) >= int(re.search(r"serial unplugs (\d+)", line).group(1)) - 1


def test_soak_rejects_bad_arguments(capsys):
    assert main(["soak", "--minutes", "0"]) == 2
    assert "--minutes must be positive" in capsys.readouterr().err
