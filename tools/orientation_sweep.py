"""Every symmetry of the default hexagon given as the orientation hint, exactly and 20 degrees off either way
(36 fiber maps), each taken through the commands a user runs: ``calibrate fibers`` with the hint,
``calibrate centroid`` (which must refuse a wrong map), ``calibrate orientation`` (which must fix it or refuse),
``calibrate centroid`` again, then ``evaluate`` on other presses. Counts right, refused and silently wrong.

    python tools/orientation_sweep.py [--workdir DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
from pathlib import Path

from optitac_edge.cli import main


def run(*argv: str) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue() + err.getvalue()


def sweep() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workdir", type=Path, default=Path("orientation_sweep"))
    args = ap.parse_args()
    wd = args.workdir
    wd.mkdir(parents=True, exist_ok=True)
    seen, unseen = wd / "seen", wd / "unseen"
    if not (seen / "meta.json").exists():
        run("sim", str(seen), "--scenario", "seen", "--seed", "11")
    if not (unseen / "meta.json").exists():
        run("sim", str(unseen), "--scenario", "unseen", "--seed", "12")
    tally = {"right first time": 0, "corrected": 0, "refused": 0, "silently wrong": 0}
    for mirror in (False, True):
        for k in range(6):
            for off in (-20, 0, 20):
                hint = 60 * k + off
                cal = wd / f"cal_{int(mirror)}_{hint}.npz"
                flags = ["--mirror"] if mirror else []
                run("calibrate", "fibers", str(seen), "-o", str(cal), "--rotation-deg", str(hint), *flags)
                first, text = run("calibrate", "centroid", str(seen), "--cal", str(cal))
                outcome = "right first time" if first == 0 else ""
                if first != 0:
                    assert "calibrate orientation" in text or "cannot confirm" in text, text
                    code, text = run("calibrate", "orientation", str(seen), "--cal", str(cal))
                    if code != 0:
                        outcome = "refused"
                    else:
                        code, text = run("calibrate", "centroid", str(seen), "--cal", str(cal))
                        outcome = "corrected" if code == 0 else "refused"
                rmse = float("nan")
                if outcome != "refused":
                    _, text = run("evaluate", str(unseen), "--cal", str(cal))
                    m = re.search(r"RMSE x ([0-9.]+) mm, y ([0-9.]+) mm", text)
                    rmse = max(float(m.group(1)), float(m.group(2))) if m else float("nan")
                    if not rmse <= 0.4:
                        outcome = "silently wrong"
                tally[outcome] += 1
                print(f"hint {hint:4d}°{' mirrored' if mirror else '         '}: {outcome:16s} "
                      f"unseen RMSE {rmse:.3f} mm")
    print(", ".join(f"{k} {v}" for k, v in tally.items()))


if __name__ == "__main__":
    sweep()
