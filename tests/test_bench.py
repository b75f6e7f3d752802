"""Smoke test of ``optitac-edge bench`` with tiny runs: the structure of the results, not timings."""

from __future__ import annotations

import json

from optitac_edge.cli import main
from optitac_edge.devtools.bench import FAST_PASSES, STAGES


def _check_stats(d: dict) -> None:
    assert set(d) == {"n", "median_us", "p99_us", "max_us"}
    if d["n"]:
        assert 0 <= d["median_us"] <= d["p99_us"] <= d["max_us"]


def test_bench_sim_all_sections(tmp_path, bundle_path, capsys) -> None:
    out = tmp_path / "bench.json"
    assert main(["bench", "--frames", "40", "--cal", str(bundle_path), "--fps", "120",
                 "--reference-frames", "3", "--memory-frames", "20", "--e2e-seconds", "1",
                 "--queue-frames", "2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| whole_frame |" in text
    res = json.loads(out.read_text())
    assert {"machine", "pipeline", "reference", "memory", "end_to_end", "startup"} <= set(res)
    stages = res["pipeline"]["stages"]
    assert set(stages) == set(STAGES)
    assert stages["whole_frame"]["n"] == 40
    for d in stages.values():
        _check_stats(d)
    ref = res["reference"]
    assert ref["frames"] == 3 and ref["ratio_reference_to_fast_paper_mode"] > 0
    assert ref["reference"]["n"] == 3 and ref["fast_paper_mode"]["n"] == 3 * FAST_PASSES
    mem = res["memory"]
    assert {"net_bytes_per_frame", "max_transient_bytes_in_frame", "rss_growth_bytes"} <= set(mem)
    e2e = res["end_to_end"]
    assert e2e["frames"] > 0 and e2e["received"] > 0 and e2e["queue_frames"] == 2
    assert {"p50", "p99", "max"} == set(e2e["latency_us"])
    assert e2e["received"] <= e2e["sent"] <= e2e["frames"]
    st = res["startup"]
    assert st["start_to_first_packet_s"] is not None and st["start_to_first_packet_s"] > 0
    assert st["heavy_modules_imported"] == []  # the runtime imports neither scipy nor scikit-learn


def test_bench_recording_source(tmp_path, unseen_rec, bundle_path) -> None:
    out = tmp_path / "b.json"
    assert main(["bench", "--frames", "15", "--source", str(unseen_rec), "--cal", str(bundle_path),
                 "--reference-frames", "0", "--memory-frames", "0", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["pipeline"]["stages"]["whole_frame"]["n"] == 15
    assert "skipped" in res["end_to_end"] and "skipped" in res["startup"]
    assert "reference" not in res


def test_bench_recording_source_without_a_bundle_calibrates_from_its_rest_frames(tmp_path, unseen_rec) -> None:
    out = tmp_path / "b.json"
    assert main(["bench", "--frames", "10", "--source", str(unseen_rec), "--workdir", str(tmp_path / "w"),
                 "--reference-frames", "0", "--memory-frames", "0", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["pipeline"]["stages"]["whole_frame"]["n"] == 10
    assert res["bundle"] == str(tmp_path / "w" / "cal-recording.npz") and res["fibers"] == 217


def test_bench_rejects_bad_arguments(capsys) -> None:
    import pytest

    with pytest.raises(SystemExit) as info:
        main(["bench", "--frames", "0"])
    assert info.value.code == 2 and "argument --frames: 0 is outside" in capsys.readouterr().err
    assert main(["bench", "--queue-frames", "0"]) == 2
    assert "--queue-frames must be 1..16" in capsys.readouterr().err


def test_the_replay_camera_queues_frames_like_the_hardware_ring() -> None:
    """A loop that pauses for fewer periods than the queue holds loses nothing; a longer one
    loses the oldest frames, counted."""
    import time

    import numpy as np

    from optitac_edge.devtools.bench.replay_camera import paced_replay_camera

    frames = [np.full((8, 8), i, np.uint8) for i in range(20)]
    fps = 50.0
    for depth, pause, lossless in ((6, 3.5, True), (1, 3.5, False)):
        cam = paced_replay_camera(frames, rest=2, fps=fps, pixel_format="gray", queue_frames=depth)
        try:
            first = cam.read(2.0).seq
            time.sleep(pause / fps)
            seqs = [cam.read(2.0).seq for _ in range(depth)]
        finally:
            cam.close()
        if lossless:
            assert seqs == list(range(first + 1, first + 1 + depth)) and cam.frames_dropped == 0
        else:
            assert cam.frames_dropped >= 2
            assert [seq for seq, _ in cam.overwritten if seq > first][:2] == [first + 1, first + 2]


def test_drops_are_blamed_on_the_loop_only_when_the_capture_thread_was_on_time() -> None:
    from optitac_edge.devtools.bench.replay_camera import dropped_in_stall

    period = 4_166_667.0
    # on time, the dropped frame waited its 4 periods: the loop's drop
    assert not dropped_in_stall(10 * period + 1e5, 10 * period, int(6 * period), period)
    # the pushing frame came a period or more late: a stall
    assert dropped_in_stall(11.2 * period, 10 * period, int(6 * period), period)
    # catch-up after a stall: on time by now, but the dropped frame was published 50 µs earlier
    assert dropped_in_stall(10 * period + 2e5, 10 * period, int(10 * period + 1.5e5), period)
