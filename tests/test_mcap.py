"""MCAP recordings of what the service publishes: decoded by mcap-ros2-support message for message,
rotated into complete files, and bad paths refused in one line."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from optitac_edge.errors import OutputError
from optitac_edge.io.publishers import open_publisher
from optitac_edge.io.publishers.mcap import rotated_name
from optitac_edge.io.ros2 import messages as msgs


def decoded(path):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(channel.topic, schema.name, message.sequence, message.log_time, msg)
                for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False)]


def sample(frame: int) -> msgs.ContactsSample:
    c = msgs.ContactValues(1, frame == 0, 0, 1.5, -2.0, 3.0, 2.0, 45.0, 9.0, 0.75, 1.25, "edge", 0.5)
    return msgs.ContactsSample(2, frame, frame * 1000, True, False, False, [c], [])


def test_every_message_decodes_with_the_ros2_decoder_in_order(tmp_path):
    path = tmp_path / "run.mcap"
    with open_publisher("mcap", path=path) as pub:
        h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
        for k in range(200):
            pub.publish(h, msgs.encode_contacts(sample(k), 10**18 + k, "optitac_thumb"), 10**18 + k)
    assert not (tmp_path / "run.mcap.part").exists()
    got = decoded(path)
    assert [(t, s, q, lt) for t, s, q, lt, _ in got] == \
        [("/optitac/thumb/contacts", msgs.CONTACTS, k + 1, 10**18 + k) for k in range(200)]
    m = got[7][4]
    assert m.frame == 7 and m.contacts[0].shape == "edge" and m.contacts[0].depth_mm == 0.75
    assert m.header.frame_id == "optitac_thumb"


def test_rotation_leaves_complete_files_holding_every_message(tmp_path):
    path = tmp_path / "run.mcap"
    with open_publisher("mcap", path=path, max_bytes=20_000) as pub:
        h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
        s = pub.advertise("/optitac/thumb/status", msgs.STATUS)
        for k in range(3000):
            pub.publish(h, msgs.encode_contacts(sample(k), k, "f"), k)
    files = sorted(tmp_path.glob("run-*.mcap"))
    assert len(files) >= 3 and files == pub.files and files[0] == rotated_name(path, 0)
    assert not list(tmp_path.glob("*.part"))
    frames = [m.frame for f in files for _, _, _, _, m in decoded(f)]
    assert frames == list(range(3000))
    with open(files[1], "rb") as f:  # every file carries the schemas and channels of all topics
        assert {c.topic for c in make_reader(f).get_summary().channels.values()} == \
            {"/optitac/thumb/contacts", "/optitac/thumb/status"}
    assert s == 1


def test_a_directory_in_the_way_is_refused_naming_it(tmp_path):
    (tmp_path / "run.mcap").mkdir()
    with pytest.raises(OutputError, match="run.mcap: exists and is not a regular file"):
        open_publisher("mcap", path=tmp_path / "run.mcap")


def test_run_writes_the_mcap_the_network_gets(tmp_path):
    path = tmp_path / "run.mcap"
    out = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--frames", "80", "--mcap", str(path)],
                         capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    got = decoded(path)
    contacts = [m for t, *_, m in got if t == "/optitac/sim/contacts"]
    counts = Counter(t for t, *_ in got)
    frames = int(out.stdout.split("processed ")[1].split(" frames")[0])
    assert [m.frame for m in contacts] == list(range(frames)) and counts["/optitac/sim/status"] >= 1
    assert any(m.contacts for m in contacts)
    assert f"{len(got)} messages published, 0 dropped" in out.stdout


def _write(path, frames, **kw):
    with open_publisher("mcap", path=path, **kw) as pub:
        h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
        for k in frames:
            pub.publish(h, msgs.encode_contacts(sample(k), k, "f"), k)
    return pub


def test_a_second_run_never_replaces_the_first(tmp_path):
    """The service starts again with the same [mcap] path (a restart, a power cut): the first run's file
    was silently replaced by the second's."""
    path = tmp_path / "run.mcap"
    _write(path, range(10))
    second = _write(path, range(100, 105))
    assert second.files == [tmp_path / "run-0000.mcap"]
    assert [m.frame for *_, m in decoded(path)] == list(range(10))
    assert [m.frame for *_, m in decoded(tmp_path / "run-0000.mcap")] == list(range(100, 105))
    third = _write(path, range(200, 202), max_bytes=10**9)  # rotating: numbered after every file there
    assert third.files == [tmp_path / "run-0001.mcap"]


def test_a_part_file_a_crash_left_is_kept_and_named(tmp_path, caplog):
    path = tmp_path / "run.mcap"
    part = tmp_path / "run-0004.mcap.part"
    part.write_bytes(b"\x89MCAP0\r\n what a power cut left")
    with caplog.at_level("WARNING", logger="optitac_edge.io.publishers.mcap"):
        pub = _write(path, range(3), max_bytes=10**9)
    assert part.read_bytes() == b"\x89MCAP0\r\n what a power cut left"  # was truncated by the next start
    assert pub.files == [tmp_path / "run-0005.mcap"]
    assert any("run-0004.mcap.part" in r.getMessage() and "mcap recover" in r.getMessage() for r in caplog.records)


def test_keep_deletes_the_oldest_complete_files_and_never_a_part(tmp_path):
    path = tmp_path / "run.mcap"
    part = tmp_path / "run-0000.mcap.part"
    part.write_bytes(b"left by a crash")
    pub = _write(path, range(3000), max_bytes=20_000, keep_bytes=40_000)
    kept = sorted(tmp_path.glob("run-*.mcap"))
    assert pub.deleted and not any(f.exists() for f in pub.deleted) and part.exists()
    assert sum(f.stat().st_size for f in kept) <= 40_000 + max(f.stat().st_size for f in kept)
    assert kept == pub.files[-len(kept):]  # the newest files, in order
    frames = [m.frame for f in kept for *_, m in decoded(f)]
    assert frames == list(range(frames[0], 3000))  # the newest messages, none missing


def test_run_twice_with_the_same_mcap_path_keeps_both_runs(tmp_path):
    path = tmp_path / "run.mcap"
    for frames in ("40", "20"):
        out = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--frames", frames, "--mcap",
                              str(path)], capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
        assert out.returncode == 0, out.stderr[-2000:]
    first = [m.frame for t, *_, m in decoded(path) if t.endswith("/contacts")]
    second = [m.frame for t, *_, m in decoded(tmp_path / "run-0000.mcap") if t.endswith("/contacts")]
    assert first == list(range(40)) and second == list(range(20))
    assert "run-0000.mcap" in out.stderr  # said where this run went
