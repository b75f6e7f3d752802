"""Smoke test of ``optitac-edge bench`` with tiny runs: the structure of the results, not timings."""

from __future__ import annotations

import json

from optitac_edge.bench import STAGES
from optitac_edge.cli import main


def _check_stats(d: dict) -> None:
    assert set(d) == {"n", "median_us", "p99_us", "max_us"}
    if d["n"]:
        assert 0 <= d["median_us"] <= d["p99_us"] <= d["max_us"]


def test_bench_sim_all_sections(tmp_path, bundle_path, capsys) -> None:
    out = tmp_path / "bench.json"
    assert main(["bench", "--frames", "40", "--cal", str(bundle_path), "--fps", "120",
                 "--reference-frames", "3", "--memory-frames", "20", "--e2e-seconds", "1",
                 "--json", str(out)]) == 0
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
    mem = res["memory"]
    assert {"net_bytes_per_frame", "max_transient_bytes_in_frame", "rss_growth_bytes"} <= set(mem)
    e2e = res["end_to_end"]
    assert e2e["frames"] > 0 and e2e["received"] > 0
    assert {"p50", "p99", "max"} == set(e2e["latency_us"])
    assert e2e["frames_dropped"] >= 0 and e2e["packets_lost"] >= 0
    st = res["startup"]
    assert st["start_to_first_packet_s"] is not None and st["start_to_first_packet_s"] > 0
    assert st["heavy_modules_imported"] == [] or isinstance(st["heavy_modules_imported"], list)


def test_bench_recording_source(tmp_path, unseen_rec, bundle_path) -> None:
    out = tmp_path / "b.json"
    assert main(["bench", "--frames", "15", "--source", str(unseen_rec), "--cal", str(bundle_path),
                 "--reference-frames", "0", "--memory-frames", "0", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["pipeline"]["stages"]["whole_frame"]["n"] == 15
    assert "skipped" in res["end_to_end"] and "skipped" in res["startup"]
    assert "reference" not in res


def test_bench_rejects_bad_arguments(capsys) -> None:
    assert main(["bench", "--frames", "0"]) != 0
