"""The C code cantools generates from the packaged DBC, compiled with a test's harness (an MCU's view)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from optitac_edge.io.protocol.can_codec import DBC_PATH


def build_generated_c(workdir: Path, harness_c: str) -> Path:
    """``cantools generate_c_source`` of the packaged DBC (database ``optitac``) and ``harness_c`` compiled
    together with gcc (C99, every warning an error) into ``workdir``; the executable."""
    subprocess.run([sys.executable, "-m", "cantools", "generate_c_source", str(DBC_PATH), "--database-name",
                    "optitac", "--output-directory", str(workdir)], check=True, capture_output=True)
    (workdir / "harness.c").write_text(harness_c)
    exe = workdir / "harness"
    r = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-I", str(workdir),
                        "-o", str(exe), str(workdir / "optitac.c"), str(workdir / "harness.c"), "-lm"],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    return exe
