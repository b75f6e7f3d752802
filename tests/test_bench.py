"""Smoke test of ``optitac-edge bench`` with tiny runs: the structure of the results, not timings."""

from __future__ import annotations

import json

import pytest

from optitac_edge.cli import main
from optitac_edge.devtools.bench import STAGES


def _check_stats(d: dict) -> None:
    assert set(d) == {"n", "median_us", "p99_us", "max_us"}
    if d["n"]:
        assert 0 <= d["median_us"] <= d["p99_us"] <= d["max_us"]


def test_bench_sim_all_sections(tmp_path, bundle_path, capfd, monkeypatch) -> None:
    import tempfile

    from optitac_edge.devtools.bench import scaling

    scratch = tmp_path / "tmp"  # where the end-to-end runs keep their figures and the MCAP file
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))

    # small arrays and few distinct frames: the structure of every section, quickly
    monkeypatch.setattr(scaling, "FIBER_RINGS", (2, 3))
    monkeypatch.setattr(scaling, "DISTINCT_FRAMES", 6)
    out = tmp_path / "bench.json"
    assert main(["bench", "--frames", "40", "--cal", str(bundle_path), "--fps", "120",
                 "--reference-frames", "3", "--memory-frames", "20", "--e2e-seconds", "1",
                 "--paced-frames", "4", "--cpu-seconds", "0", "--patches", "2", "--patch-frame", "960x400",
                 "--workdir", str(tmp_path / "w"), "--queue-frames", "2", "--e2e-publish", "--workers", "1",
                 "--json", str(out)]) == 0
    text, err = capfd.readouterr()
    assert "| whole_frame |" in text
    assert "Traceback" not in err  # the subscriber process's threads end cleanly too
    assert list(scratch.iterdir()) == []  # nothing left behind (an MCAP file is 100s of MB a minute)
    res = json.loads(out.read_text())
    assert {"machine", "pipeline", "reference", "memory", "end_to_end", "startup"} <= set(res)
    stages = res["pipeline"]["stages"]
    assert set(stages) == set(STAGES)
    assert stages["whole_frame"]["n"] == 40
    for d in stages.values():
        _check_stats(d)
    ref = res["reference"]
    assert ref["frames"] == 3 and ref["ratio_reference_to_fast_paper_mode"] > 0
    assert ref["reference"]["n"] == 3 and ref["fast_paper_mode"]["n"] == 3 and ref["fast_all_options"]["n"] == 3
    contacts = res["contacts"]["per_contacts"]
    assert list(contacts) == ["0", "1", "2", "4"]
    for k, d in contacts.items():  # the simulator pressed that many indenters, and each was found
        assert d["n"] == 4 and d["contacts"] == int(k)
    assert res["contacts"]["ratio_4_to_1"] > 0 and res["contacts"]["ratio_0_to_1"] > 0
    fibers = res["fibers"]["per_fibers"]
    assert list(fibers) == ["19", "37"] and all(d["contacts"] == 1 for d in fibers.values())
    patches = res["patches"]  # two patches on one frame; one pressed at a time, and found
    assert patches["patches"] == 2 and patches["frame_size"] == [960, 400]
    assert patches["back_to_back"]["n"] == 4 and patches["paced"]["n"] == 4
    assert patches["paced"]["contacts"] == 1 and patches["back_to_back"]["median_us"] > 0
    heap = res["heap"]
    assert {"0", "1", "2", "4"} <= set(heap) and all("in_use_growth_bytes" in heap[k] for k in "0124")
    assert "service_cpu" not in res  # --cpu-seconds 0 (see the test of measure_service_cpu)
    mem = res["memory"]
    assert {"net_bytes_per_frame", "max_transient_bytes_in_frame", "rss_growth_bytes"} <= set(mem)
    e2e = res["end_to_end"]
    assert e2e["frames"] > 0 and e2e["received"] > 0 and e2e["queue_frames"] == 2
    assert {"p50", "p99", "max"} == set(e2e["latency_us"])
    assert e2e["received"] <= e2e["sent"] <= e2e["frames"]
    assert e2e["contacts_pressed"] == 2 and e2e["main_thread"]["cpu_us_per_frame"] > 0
    pub = e2e["publish"]  # every frame's Contacts (and status, signal) on Zenoh to a subscriber and in the MCAP
    # published or, on a busy machine whose publishing thread fell behind, counted as dropped (never waited on)
    assert pub["published"] + pub["dropped"] >= e2e["frames"] and pub["errors"] == 0
    assert pub["published"] + pub["dropped"] >= pub["mcap_messages"] == pub["published"]
    assert 0 < pub["received_by_subscriber"] <= pub["published"]
    pe = res["patches_end_to_end"]  # one service, a sensor per patch: each frame's CONTACTs of both patches
    assert pe["patches"] == 2 and pe["frames"] > 0 and pe["received"] > pe["frames"]
    assert pe["sensor_workers"] == 1  # the second patch's pipeline on a worker thread
    assert pe["received"] <= 2 * pe["sent"] and pe["sent"] <= pe["frames"]
    assert pe["publish"]["topics"] >= 4  # contacts and status of each patch
    assert pe["publish"]["published"] + pe["publish"]["dropped"] >= 2 * pe["frames"]
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


def test_the_replay_camera_starts_at_the_first_read_so_a_slow_start_keeps_the_rest_frames() -> None:
    """Building the service (publishers, a subscriber process) may take longer than the queue holds:
    the rest frames must still reach the loop, or its baseline is taken over presses."""
    import time

    import numpy as np

    from optitac_edge.devtools.bench.replay_camera import paced_replay_camera

    frames = [np.full((8, 8), i, np.uint8) for i in range(20)]
    # 20 fps: a busy machine may be 100 ms late between two reads before the ring of 2 drops one (issue 38)
    cam = paced_replay_camera(frames, rest=4, fps=20.0, pixel_format="gray", queue_frames=2)
    try:
        time.sleep(0.3)  # 6 periods, 3 rings' worth, before the loop reads
        got = [cam.read(2.0) for _ in range(4)]
    finally:
        cam.close()
    assert [c.seq for c in got] == [1, 2, 3, 4] and [int(c.frame[0, 0]) for c in got] == [0, 1, 2, 3]
    cam.close()  # idempotent, and a camera never read closes too
    paced_replay_camera(frames, rest=4, fps=200.0, pixel_format="gray", queue_frames=2).close()


def test_drops_are_blamed_on_the_loop_only_when_the_capture_thread_was_on_time() -> None:
    from optitac_edge.devtools.bench.replay_camera import dropped_in_stall

    period = 4_166_667.0
    # on time, the dropped frame waited its 4 periods: the loop's drop
    assert not dropped_in_stall(10 * period + 1e5, 10 * period, int(6 * period), period)
    # the pushing frame came a period or more late: a stall
    assert dropped_in_stall(11.2 * period, 10 * period, int(6 * period), period)
    # catch-up after a stall: on time by now, but the dropped frame was published 50 µs earlier
    assert dropped_in_stall(10 * period + 2e5, 10 * period, int(10 * period + 1.5e5), period)


def test_service_cpu_runs_every_contact_count_interleaved_and_takes_medians(monkeypatch, tmp_path) -> None:
    """The production loop's runs are faked: the order of the passes and the figures derived from them."""
    import numpy as np

    from optitac_edge.devtools.bench import end_to_end, scaling

    calls: list[int] = []
    cpu = {0: [100.0, 120.0, 80.0], 1: [200.0, 260.0, 220.0], 2: [300.0, 300.0, 330.0], 4: [400.0, 450.0, 420.0]}

    def frames(k, rgb, fps, layout=None):
        return [np.full((4, 4), k, np.uint8)] * (scaling.REST_FRAMES + 3)

    def fake(run):
        k = int(run.frames[0][0, 0])  # which contact count's frames the run got
        calls.append(k)
        return {"main_thread": {"cpu_us_per_frame": cpu[k][calls.count(k) - 1]},
                "frames_dropped": 0, "latency_us": {"p50": 1, "p99": 2, "max": 3}}

    monkeypatch.setattr(scaling, "contact_frames", frames)

    monkeypatch.setattr(end_to_end, "measure_end_to_end", fake)
    lines: list[str] = []
    res = scaling.measure_service_cpu(tmp_path / "cal.npz", 240.0, 5.0, 3, False, lines.append)
    assert calls == [1, 0, 2, 4] * 3
    assert res["cpu_us_per_frame"] == {"0": 100.0, "1": 220.0, "2": 300.0, "4": 420.0}
    assert res["ratio_4_to_1"] == round(420 / 220, 3) and res["ratio_0_to_1"] == round(100 / 220, 3)
    assert len(lines) == 12 and "1 contact(s), pass 1: 200.0" in lines[0]


def test_main_thread_cpu_counts_from_the_warm_frame_to_the_end() -> None:
    from types import SimpleNamespace

    from optitac_edge.devtools.bench.end_to_end import MainThreadCpu

    cpu = MainThreadCpu(warm_frames=10)
    for frames in range(1, 10):
        cpu.on_result(None, SimpleNamespace(frames=frames))
    assert cpu.result() == {"main_thread": None}  # not warm yet
    for frames in range(10, 200):
        cpu.on_result(None, SimpleNamespace(frames=frames))
    sum(i * i for i in range(200_000))  # some CPU on this thread
    cpu.stop(200)
    got = cpu.result()["main_thread"]
    assert got["frames"] == 190 and got["cpu_us_per_frame"] > 0


def test_paced_runs_take_turns_frame_by_frame_on_the_camera_clock() -> None:
    """Configuration i % C gets frame i, due at i / fps; the loop sleeps until then, counts late frames."""
    import numpy as np

    from optitac_edge.devtools.bench.paced import Paced, run_interleaved

    now = [0]
    slept: list[float] = []
    seen: list[tuple[str, int, int]] = []

    def clock() -> int:
        return now[0]

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += round(s * 1e9)

    def process(name: str, cost_ns: int):
        def run(frame: np.ndarray, t_ns: int) -> int:
            seen.append((name, int(frame[0]), t_ns))
            now[0] += cost_ns
            return int(frame[0])
        return run

    frames = [np.array([v], np.uint8) for v in range(6)]  # frame 0: rest; then 1..5 cycled
    configs = [Paced("a", process("a", 1_000_000), frames, 1, count=lambda e: e),
               Paced("b", process("b", 6_000_000), frames, 1)]  # b overruns a 10 ms period
    res = run_interleaved(configs, 100.0, 3, warmup_per_config=1, sleep=sleep, clock_ns=clock, timer_ns=clock)
    assert [s[0] for s in seen] == ["a", "b"] * 5  # rest frames, then turn by turn
    assert [s[1] for s in seen if s[0] == "a"] == [0, 1, 2, 3, 4]  # each its own frames (rest, then cycled)
    assert [s[2] for s in seen if s[0] == "a"] == [20_000_000 * i for i in range(5)]  # C periods a frame
    assert res["a"]["n"] == res["b"]["n"] == 3
    assert res["a"]["contacts"] == 3.0  # the median of its estimates' counts (frames 2, 3, 4)
    assert slept and all(s > 0 for s in slept) and res["a"]["late_frames"] == res["b"]["late_frames"] == 0
    assert res["a"]["median_us"] == 1000.0 and res["b"]["median_us"] == 6000.0
    # b now takes 25 ms, more than two 10-ms periods: the frames after each of its start late
    configs[1] = Paced("b", process("b", 25_000_000), frames, 1)
    seen.clear()
    res = run_interleaved(configs, 100.0, 3, warmup_per_config=1, sleep=sleep, clock_ns=clock, timer_ns=clock)
    assert res["a"]["late_frames"] >= 2 and res["b"]["late_frames"] >= 2


@pytest.mark.parametrize("bad", ["1280", "axb", "10x720", "1280x9000"])
def test_bench_refuses_a_bad_patch_frame_in_one_line(bad, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", "--patch-frame", bad])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--patch-frame" in err[0]


def test_the_reference_ratio_is_the_medians_quotient_not_the_inverse_of_a_rounded_one(monkeypatch, bundle_path):
    """The ratio was 1 / round(fast / reference, 3): every run between ×60.6 and ×64.5 read ×62.5."""
    from optitac_edge.devtools.bench import scaling
    from optitac_edge.io.bundle_file import load_bundle

    medians = {"reference": 6287.3, "fast_paper_mode": 100.0, "fast_all_options": 200.0}
    monkeypatch.setattr(scaling, "run_interleaved",
                        lambda configs, fps, n, warmup_per_config: {c.name: {"median_us": medians[c.name]}
                                                                    for c in configs})
    res = scaling.measure_reference(load_bundle(bundle_path), [], 0, 1)
    assert res["ratio_reference_to_fast_paper_mode"] == 62.873
    assert res["ratio_reference_to_fast_all_options"] == 31.437
