"""What a board pays per frame: the real ``optitac-edge run`` on a paced camera, measured from outside.

Usage::

    python tools/pace_run.py [--workdir DIR] [--seconds 20] [--rounds 2] [--configs gray1,rgb1,hand6]
                             [--backends compiled,numpy] [--reference-frames 300] [--json pace.json]

For each configuration it runs ``optitac-edge run`` (a subprocess, the installed command's code) on a board
file of its own: the ``recording`` camera with ``live = true`` (a capture thread copies each frame at its
time into the camera's queue, as a V4L2 or Picamera2 camera's grab thread does: the loop's thread reads a
frame another core wrote), looping a pre-rendered recording at 240 fps, and the serial transport on a pty
whose other end this script drains. Configurations:

* ``gray0``, ``gray1``, ``rgb1``: the simulator's 217-fibre bundle with every calibration model, 640×480,
  0 or 1 indenter pressed throughout (12 rest frames, then 240 distinct frames, looped);
* ``hand6``: six placed 217-fibre patches on one 1280×720 camera, one pressed at a time and every third
  frame a two-patch grasp (the bench's hand).

Per run, after ``--warmup`` seconds, over ``--seconds``: every thread's CPU from
``/proc/PID/task/TID/schedstat`` (the scheduler's own run time, ns; threads by the names they give
themselves, the loop's thread is the process's main thread), per frame at the camera's rate and as a share
of one core; from the run's ``--stage-times`` file the loop's pipeline and send path per frame (paced, as
the run had them) and the frames dropped. In this process: the same pipeline on the same frames back to back
(warm). Configurations and backends (``compiled``, ``numpy``: ``OPTITAC_EDGE_KERNEL=numpy``) alternate run
by run, so a ratio between two of them holds on a noisy machine. ``--reference-frames``: the paper's method
done literally against the pipeline in paper mode (``optitac-edge bench``'s ratio), once per round.
docs/performance.md has the figures and how they were taken.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.devtools.bench.link import open_pty

FPS = 240.0
CONFIGS = ("gray0", "gray1", "rgb1", "hand6")
HAND_SIZE = (1280, 720)


def _recording(path: Path, frames: list[np.ndarray], rest: int) -> Path:
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_writer import RecordingWriter

    if (path / "meta.json").exists():
        return path
    with RecordingWriter(path, len(frames), frames[0].shape, RecordingMeta(rest_frames=rest, fps=FPS)) as w:
        for i, f in enumerate(frames):
            w.write(i, f, int(i * 1e9 / FPS))
    return path


def _board(path: Path, recording: Path, sensors: list[tuple[Path, list[int] | None]]) -> Path:
    from optitac_edge.io.recording import Recording

    rec = Recording(recording)
    lines = ['config_version = 1', 'description = "tools/pace_run.py"', "",
             "[camera]", 'backend = "recording"', f'recording = "{recording}"', "warmup_frames = 0",
             f"width = {rec.width}", f"height = {rec.height}", f"fps = {FPS:g}",
             f'pixel_format = "{rec.pixel_format}"',
             "queue_frames = 4", "", "[camera.options]", "loop = true", "live = true", "",
             "[link]", 'transport = "serial"', "", "[led]", "enabled = false", ""]
    for k, (bundle, region) in enumerate(sensors):
        lines += ["[[sensors]]", f"id = {k}", f'name = "patch{k}"', f'bundle = "{bundle}"']
        if region is not None:
            lines.append(f"region = {region}")
        lines.append("")
    path.write_text("\n".join(lines))
    return path


def prepare(workdir: Path, config: str) -> dict[str, Any]:
    """The board file, recording and bundles of one configuration (cached in ``workdir``)."""
    from optitac_edge.devtools.bench.scaling import REST_FRAMES, contact_frames
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.sim.bundles import cached_sim_bundle

    workdir.mkdir(parents=True, exist_ok=True)
    board = workdir / f"board-{config}.toml"
    rec = workdir / f"rec-{config}"
    if config == "hand6":
        from optitac_edge.devtools.bench.patches import patch_pipelines, patch_regions

        regions = patch_regions(6, *HAND_SIZE)
        bundles = [workdir / f"hand6-patch{k}.npz" for k in range(6)]
        if not (rec / "meta.json").exists() or not all(b.exists() for b in bundles):
            pipes, rest, frames = patch_pipelines(6, *HAND_SIZE)
            for p, path in zip(pipes, bundles):
                save_bundle(p.bundle, path)
            _recording(rec, rest + frames, len(rest))
        _board(board, rec, [(b, [r.x, r.y, r.width, r.height]) for b, r in zip(bundles, regions)])
        return {"board": board, "recording": rec, "bundles": bundles}
    n_contacts, rgb = int(config[-1]), config.startswith("rgb")
    bundle = cached_sim_bundle(workdir, rgb=rgb)
    if not (rec / "meta.json").exists():
        _recording(rec, contact_frames(n_contacts, rgb, FPS), REST_FRAMES)
    _board(board, rec, [(bundle, None)])
    return {"board": board, "recording": rec, "bundles": [bundle]}


def _threads(pid: int) -> dict[int, tuple[str, int]]:
    """Every thread of ``pid``: its name and CPU time so far, ns."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            ns = int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue
        out[int(tid)] = ("main" if int(tid) == pid else name, ns)
    return out


def _drain(fd: int, stop: threading.Event, got: list[int]) -> None:
    while not stop.is_set():
        try:
            data = os.read(fd, 65536)
        except OSError:
            return
        if not data:
            return
        got[0] += len(data)


def run_once(prep: dict[str, Any], backend: str, warmup_s: float, seconds: float) -> dict[str, Any]:
    """One ``optitac-edge run`` on the configuration's board: its threads' CPU over the window, its stages."""
    master, slave, port = open_pty()
    stop, got = threading.Event(), [0]
    drainer = threading.Thread(target=_drain, args=(master, stop, got), daemon=True)
    drainer.start()
    env = {k: v for k, v in os.environ.items() if k != "OPTITAC_EDGE_KERNEL"}
    if backend == "numpy":
        env["OPTITAC_EDGE_KERNEL"] = "numpy"
    with tempfile.TemporaryDirectory(prefix="optitac-pace-") as tmp:
        stages_path = Path(tmp) / "stages.json"
        cmd = [sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(prep["board"]), "--serial", port,
               "--duration", f"{warmup_s + seconds + 0.5:g}", "--stage-times", str(stages_path), "-q"]
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            time.sleep(warmup_s)
            t0, a = time.monotonic_ns(), _threads(proc.pid)
            time.sleep(seconds)
            t1, b = time.monotonic_ns(), _threads(proc.pid)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
            stop.set()
            os.close(slave)
            os.close(master)
        if proc.returncode != 0:
            raise SystemExit(f"pace_run: optitac-edge run exited {proc.returncode}: {err.strip()[-500:]}")
        stages = json.loads(stages_path.read_text())[0]
    window_s = (t1 - t0) / 1e9
    frames = window_s * FPS
    threads: dict[str, float] = {}
    for tid, (name, ns) in b.items():
        threads[name] = threads.get(name, 0.0) + (ns - a.get(tid, (name, 0))[1])
    return {"backend": backend, "window_s": round(window_s, 3), "bytes_received": got[0],
            "main_us_per_frame": round(threads.get("main", 0.0) / 1e3 / frames, 1),
            "process_share_of_one_core": round(sum(threads.values()) / (t1 - t0), 4),
            "threads_us_per_frame": {k: round(v / 1e3 / frames, 1) for k, v in sorted(threads.items())},
            "pipeline_paced": stages["pipeline"], "send_path": stages["send"],
            "frames_processed": stages["frames_processed"], "frames_dropped": stages["frames_dropped"],
            "kernel": stages["kernel"]}


def startup_once(prep: dict[str, Any]) -> dict[str, Any]:
    """Process start to the first byte on the link (``optitac-edge run`` on the configuration's board, its
    bundle stored), and the run's own start-up marks (``-v``: imports, config, camera, link, bundles, kernel
    plans, first frame; ms after the process started)."""
    master, slave, port = open_pty()
    cmd = [sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(prep["board"]), "--serial", port,
           "--duration", "1.5", "-v"]
    t0 = time.monotonic_ns()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    first_ns = None
    try:
        os.read(master, 1)  # blocks until the first packet's first byte
        first_ns = time.monotonic_ns()
        stop, got = threading.Event(), [0]
        threading.Thread(target=_drain, args=(master, stop, got), daemon=True).start()
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(slave)
        os.close(master)
    marks = {}
    for line in err.splitlines():
        if "start-up: " in line and " done " in line:
            phase = line.split("start-up: ", 1)[1].split(" done ", 1)[0]
            marks[phase] = int(line.split(" done ", 1)[1].split(" ms", 1)[0])
    return {"start_to_first_packet_s": round((first_ns - t0) / 1e9, 3), "exit_code": proc.returncode,
            "marks_ms": marks}


def warm_pipeline(prep: dict[str, Any], backend: str, n: int = 2000) -> dict[str, float]:
    """The configuration's pipelines on its frames back to back (every sensor's, one camera frame): µs."""
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    rec = Recording(prep["recording"])
    frames = [np.ascontiguousarray(f) for f in rec]
    pipes = [Pipeline(load_bundle(b), compiled=backend == "compiled", fps=FPS) for b in prep["bundles"]]
    period, samples = int(1e9 / FPS), []
    for i in range(n + len(frames)):
        f = frames[i % len(frames)]
        t = time.thread_time_ns()
        for p in pipes:
            p.process(f, i * period)
        if i >= len(frames):
            samples.append(time.thread_time_ns() - t)
    v = np.array(samples) / 1e3
    return {"median_us": round(float(np.median(v)), 2), "p99_us": round(float(np.percentile(v, 99)), 2)}


def reference_ratio(workdir: Path, n: int) -> float | None:
    """The paper's method done literally ÷ the pipeline in paper mode (bench's measurement), gray."""
    from optitac_edge.devtools.bench.inputs import load_inputs
    from optitac_edge.devtools.bench.scaling import measure_reference

    bundle, _, frames, _ = load_inputs("sim", None, False, workdir, 600, FPS)
    rest = max(int(bundle.baseline_frames), 10)
    res: float | None = measure_reference(bundle, frames, rest, n)["ratio_reference_to_fast_paper_mode"]
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-pace")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured window of each run, s")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds of each run before the window")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--configs", default="gray0,gray1,rgb1,hand6")
    ap.add_argument("--backends", default="compiled,numpy")
    ap.add_argument("--reference-frames", type=int, default=300, help="0: skip the reference's ratio")
    ap.add_argument("--startups", type=int, default=7, help="start-to-first-packet runs (0: skip)")
    ap.add_argument("--json", type=Path, default=Path("pace.json"))
    args = ap.parse_args(argv)
    configs = args.configs.split(",")
    backends = args.backends.split(",")
    unknown = sorted(set(configs) - set(CONFIGS)) + sorted(set(backends) - {"compiled", "numpy"})
    if unknown:
        ap.error(f"unknown configuration or backend: {', '.join(unknown)}")
    preps = {c: prepare(args.workdir, c) for c in configs}
    out: dict[str, Any] = {"fps": FPS, "seconds": args.seconds, "runs": [], "warm": {}, "reference_ratio": []}
    for c in configs:
        out["warm"][c] = {b: warm_pipeline(preps[c], b) for b in backends}
        print(f"{c}: warm pipeline " + ", ".join(f"{b} {v['median_us']} µs" for b, v in out["warm"][c].items()),
              flush=True)
    for r in range(args.rounds):
        for c in configs:
            for b in backends:
                res = {"round": r + 1, "config": c, **run_once(preps[c], b, args.warmup, args.seconds)}
                out["runs"].append(res)
                others = {k: v for k, v in res["threads_us_per_frame"].items() if k != "main"}
                print(f"round {r + 1} {c} {b}: main thread {res['main_us_per_frame']} µs/frame, process "
                      f"{100 * res['process_share_of_one_core']:.1f} % of a core (others: {others}); pipeline "
                      f"paced {res['pipeline_paced']['median_us']} µs, send path {res['send_path']['median_us']} "
                      f"µs (medians); {res['frames_processed']} frames, {res['frames_dropped']} dropped", flush=True)
        if args.reference_frames:
            ratio = reference_ratio(args.workdir, args.reference_frames)
            out["reference_ratio"].append(ratio)
            print(f"round {r + 1}: reference ÷ pipeline in paper mode ×{ratio}", flush=True)
    if args.startups:
        prep = preps[configs[0]]
        runs = [startup_once(prep) for _ in range(args.startups)]
        times = sorted(r["start_to_first_packet_s"] for r in runs)
        out["startup"] = {"config": configs[0], "runs": runs, "median_s": times[len(times) // 2]}
        print(f"start to first packet ({configs[0]}, {args.startups} runs): median {times[len(times) // 2]} s, "
              f"{times[0]}-{times[-1]} s; phases of the median run: "
              f"{next(r for r in runs if r['start_to_first_packet_s'] == times[len(times) // 2])['marks_ms']}")
    args.json.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
