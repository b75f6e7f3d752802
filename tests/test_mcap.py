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


def _killed(path, frames, **kw):
    """A run that ended without closing its publisher (a kill, a power cut): its file stays a .part."""
    pub = open_publisher("mcap", path=path, **kw)
    h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
    for k in frames:
        pub.publish(h, msgs.encode_contacts(sample(k), k * 10**7, "f"), k * 10**7)
    pub._stream.flush()
    return pub._part


def test_a_part_file_a_crash_left_is_kept_and_named(tmp_path, caplog):
    path = tmp_path / "run.mcap"
    _write(path, range(3), max_bytes=10**9)
    part = _killed(path, range(300), max_bytes=10**9)
    assert part == tmp_path / "run-0001.mcap.part"
    before = part.read_bytes()
    with caplog.at_level("WARNING", logger="optitac_edge.io.publishers.mcap"):
        pub = _write(path, range(3), max_bytes=10**9)
    assert part.read_bytes() == before  # was truncated by the next start
    assert pub.files == [tmp_path / "run-0002.mcap"]
    assert any("run-0001.mcap.part" in r.getMessage() and "mcap recover" in r.getMessage() for r in caplog.records)


def test_keep_deletes_only_what_the_service_wrote_and_numbers_after_its_own_files(tmp_path):
    """Before: keep_mb deleted any run-*.mcap in the directory (a user's run-1999.mcap holding "precious"),
    and numbering went on after foreign names (run-20250101.mcap -> run-20250102.mcap)."""
    path = tmp_path / "run.mcap"
    precious = tmp_path / "run-1999.mcap"
    precious.write_bytes(b"precious")
    dated = tmp_path / "run-20250101.mcap"
    dated.write_bytes(b"a user's recording")
    taken = tmp_path / "run-0001.mcap"
    taken.write_bytes(b"a user's file where the service would write next")
    pub = _write(path, range(3000), max_bytes=20_000, keep_bytes=40_000)
    assert pub.files[0] == tmp_path / "run-0000.mcap" and taken not in pub.files
    assert all(len(f.stem.split("-")[1]) == 4 for f in pub.files)
    assert precious.read_bytes() == b"precious" and dated.exists() and taken.read_bytes().startswith(b"a user")
    assert pub.deleted and all(f in pub.files for f in pub.deleted)
    again = _write(path, range(10), max_bytes=20_000)
    assert again.files == [rotated_name(path, int(pub.files[-1].stem.split("-")[1]) + 1)]


def test_keep_never_deletes_a_users_file_that_took_a_deleted_files_name(tmp_path):
    """keep_mb deleted a user's file whose name the service had once written (and deleted): the names stayed
    in NAME.files after their files were gone. A deleted file's name now leaves the list."""
    from optitac_edge.io.publishers.mcap import manifest_path

    path = tmp_path / "run.mcap"
    first = _write(path, range(3000), max_bytes=20_000, keep_bytes=40_000)
    assert first.deleted
    listed = manifest_path(path).read_text().split()
    assert not any(f.name in listed for f in first.deleted)
    mine = first.deleted[0]
    mine.write_bytes(b"a user's file under a name the service once used")
    _write(path, range(3000), max_bytes=20_000, keep_bytes=40_000)
    assert mine.read_bytes().startswith(b"a user's file")


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


def test_a_kill_loses_at_most_a_second_of_messages(tmp_path):
    """With the default chunking the .part stayed 0 bytes for the first 120 s of a run: a kill at 220 s
    lost ~100 s. Now the chunk is closed, written and synced every second of message time."""
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    path = tmp_path / "run.mcap"
    # 250 s of contacts at 100 Hz (message time), then the process dies without closing the file
    part = _killed(path, range(25_000))
    times = []
    with open(part, "rb") as f:  # as far as it reads (the last chunk is cut short)
        try:
            for r in StreamReader(f, validate_crcs=True).records:
                if isinstance(r, Message):
                    times.append(r.log_time)
        except Exception:  # noqa: BLE001, S110
            pass
    assert times and times[0] == 0
    assert 249e9 - times[-1] <= 1.0e9 + 1e7  # at most about a second lost
    assert times == [k * 10**7 for k in range(len(times))]  # everything before it, none missing
    from optitac_edge.io.mcap_file import part_contents

    held = part_contents(part)
    assert (held.messages, held.first_ns, held.last_ns) == (len(times), 0, times[-1])


class _FillingDisk:
    """A file whose writes fail with ENOSPC once ``room`` bytes were written (a disk filling up)."""

    def __init__(self, f, room: int) -> None:
        self._f, self.room = f, room

    def write(self, data) -> int:
        import errno

        if self.room < len(data):
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)


def test_a_full_disk_is_counted_and_the_stop_stays_clean(tmp_path, caplog):
    """Before: a full disk under run --mcap turned the clean stop into exit 2 (the file's completion
    raised); now the run warns once, counts what it could not write and says what the file holds."""
    from optitac_edge.io.mcap_file import open_part

    def filling(final):
        stream, part = open_part(final)
        return _FillingDisk(stream, 60_000), part

    path = tmp_path / "run.mcap"
    with caplog.at_level("WARNING", logger="optitac_edge.io.publishers.mcap"):
        pub = open_publisher("mcap", path=path, open_file=filling)
        h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
        for k in range(20_000):
            pub.publish(h, msgs.encode_contacts(sample(k), k * 10**7, "f"), k * 10**7)
        pub.close()  # no exception
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("No space left on device" in w and "run.mcap.part" in w for w in warnings)
    assert pub.lost > 0 and pub.written[0].messages > 0
    summary = pub.summary
    assert summary[0].startswith(f"{tmp_path / 'run.mcap.part'}: ") and "failed write (No space left" in summary[0]
    assert "'mcap recover' restores its index" in summary[0]
    assert pub.undelivered == pub.lost and len(summary) == len([f for f in pub.written if f.messages or not f.failed])
    from optitac_edge.io.mcap_file import part_contents

    on_disk = part_contents(tmp_path / "run.mcap.part")
    assert on_disk.messages > 0  # what was written before is readable
    # the summary names the messages on disk, not those the writer took before the disk filled (issue 38,
    # item 22); every message is either on disk or counted lost
    assert pub.written[0].messages == on_disk.messages and pub.written[0].last_ns == on_disk.last_ns
    assert sum(f.messages for f in pub.written) + pub.lost == 20_000


def test_a_write_that_fails_inside_a_chunk_counts_every_message_once(tmp_path):
    """Messages a microsecond apart (no periodic sync within a file): the disk fills when a chunk is written
    from inside add_message, before the message is in the file's count. Every message is either in a file's
    count, which is what the file holds, or counted lost; none twice, none missing."""
    from optitac_edge.io.mcap_file import open_part, part_contents

    def filling(final):
        stream, part = open_part(final)
        return _FillingDisk(stream, 60_000), part

    path = tmp_path / "run.mcap"
    pub = open_publisher("mcap", path=path, open_file=filling)
    h = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
    for k in range(20_000):
        pub.publish(h, msgs.encode_contacts(sample(k), k * 1000, "f"), k * 1000)
    pub.close()
    assert pub.lost > 0 and pub.written[0].failed
    assert pub.written[0].messages == part_contents(tmp_path / "run.mcap.part").messages
    assert sum(f.messages for f in pub.written) + pub.lost == 20_000


def test_run_with_a_full_disk_ends_cleanly_naming_the_file(tmp_path, monkeypatch, capsys):
    from optitac_edge.cli import main
    from optitac_edge.io import mcap_file
    from optitac_edge.io.publishers import mcap as mcap_publisher

    def filling(final):
        stream, part = mcap_file.open_part(final)
        return _FillingDisk(stream, 4_000), part

    monkeypatch.setattr(mcap_publisher, "open_part", filling)
    path = tmp_path / "run.mcap"
    assert main(["run", "--frames", "60", "--mcap", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'run.mcap.part'}: " in out and "No space left on device" in out
