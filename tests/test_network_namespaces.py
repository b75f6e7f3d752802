"""Two robots on one LAN: each board in a network namespace of its own, the robot's main computer in a third,
joined by a bridge; Zenoh peers find each other by multicast scouting, with no endpoint configured
(issue 17: "two boards as two Zenoh peers in separate network namespaces").

Making namespaces needs root and iproute2 (``.ci/run`` runs as root on a machine that has both).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SUBSCRIBER = ROOT / "examples" / "zenoh_subscriber.py"
HOSTS = ("main", "robot1", "robot2")
FRAMES = 60


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


@pytest.fixture
def lan() -> Iterator[dict[str, str]]:
    """Three namespaces on one bridge: host name -> namespace name (each with its interface ``e0``)."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    tag = f"ot{os.getpid() % 100000}"
    bridge, names = f"{tag}br", {h: f"{tag}{h}" for h in HOSTS}
    subnet = f"10.{200 + os.getpid() % 50}.{os.getpid() % 250}"
    made: list[str] = []
    try:
        _ip("link", "add", bridge, "type", "bridge")
        _ip("link", "set", bridge, "up")
        for k, (host, ns) in enumerate(names.items(), start=1):
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("link", "add", f"{tag}v{k}", "type", "veth", "peer", "name", "e0", "netns", ns)
            _ip("link", "set", f"{tag}v{k}", "master", bridge, "up")
            _ip("-n", ns, "addr", "add", f"{subnet}.{k}/24", "dev", "e0")
            _ip("-n", ns, "link", "set", "e0", "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", "e0")  # Zenoh's scouting multicast
        yield names
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True, timeout=30)
        subprocess.run(["ip", "link", "del", bridge], check=False, capture_output=True, timeout=30)


def _scouting_config(path: Path) -> Path:
    path.write_text('{ mode: "peer", scouting: { multicast: { enabled: true, interface: "e0" } } }')
    return path


def test_two_robots_in_their_own_namespaces_are_found_by_scouting_and_heard_by_the_main_computer(lan, tmp_path):
    out = tmp_path / "received.jsonl"
    sub = subprocess.Popen(["ip", "netns", "exec", lan["main"], sys.executable, str(SUBSCRIBER), "--config",
                            str(_scouting_config(tmp_path / "main.json5")), "--json", "--idle", "5",
                            "--seconds", "120"], stdout=out.open("w"), stderr=subprocess.PIPE, text=True)
    try:
        assert sub.stderr is not None and "listening" in sub.stderr.readline()
        runs = []
        for robot in ("robot1", "robot2"):
            board = tmp_path / f"{robot}.toml"
            board.write_text(f'[sensor]\nname = "hand"\n[network]\nnamespace = "/{robot}"\n[publish.zenoh]\n'
                             f'config = "{_scouting_config(tmp_path / f"{robot}.json5")}"\n')
            runs.append(subprocess.Popen(["ip", "netns", "exec", lan[robot], sys.executable, "-m", "optitac_edge.cli",
                                          "run", "--board", str(board), "--frames", str(FRAMES)],
                                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        for r in runs:
            _, err = r.communicate(timeout=120)
            assert r.returncode == 0, err[-2000:]
        sub.wait(60)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.wait()
    got = Counter(json.loads(line)["topic"] for line in out.read_text().splitlines() if line.strip())
    # every frame of both robots, each under its own namespace, and each robot's status
    assert got["/robot1/optitac/hand/contacts"] == FRAMES and got["/robot2/optitac/hand/contacts"] == FRAMES
    assert got["/robot1/optitac/hand/status"] >= 1 and got["/robot2/optitac/hand/status"] >= 1
