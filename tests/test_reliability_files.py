"""Reliability of the files and the process: power loss during a bundle save, security properties.

* SIGKILL at random points of a save loop (100 trials): the bundle always loads, old or new.
* No pickle / eval / exec on input anywhere in the package; no listening socket; the unit is hardened.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.io.bundle_file import load_bundle, save_bundle

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "optitac_edge"

SAVER = r"""
import json, os, pathlib, signal, sys
from optitac_edge.io.bundle_file import load_bundle, save_bundle

a, b = load_bundle(sys.argv[1]), load_bundle(sys.argv[2])
target, trials = pathlib.Path(sys.argv[3]), json.loads(sys.argv[4])


def die():
    os.kill(os.getpid(), signal.SIGKILL)


class KillAfter:
    # a file that dies once `left` more bytes are written (part of the write lands)
    def __init__(self, f, left):
        self._f, self._left = f, left

    def write(self, data):
        if len(data) >= self._left:
            self._f.write(bytes(data)[:self._left])
            self._f.flush()
            die()
        self._left -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self._f.__exit__(*exc)


def child(save, point, offset):
    # save b (number 0) then a (number 1) onto target; die at `point` of save number `save`
    saves = [0]
    real_open, real_fsync, real_replace = pathlib.Path.open, os.fsync, os.replace

    def opened(self, mode="r", *args, **kw):
        f = real_open(self, mode, *args, **kw)
        return KillAfter(f, offset) if point == "write" and saves[0] == save and "w" in mode else f

    def fsync(fd):
        if saves[0] == save and point == "fsync-file" and not os.path.isdir(f"/proc/self/fd/{fd}"):
            die()
        real_fsync(fd)

    def replace(src, dst):
        if saves[0] == save and point == "replace":
            die()
        real_replace(src, dst)
        if saves[0] == save and point == "after-replace":
            die()

    pathlib.Path.open, os.fsync, os.replace = opened, fsync, replace
    for bundle in (b, a):
        save_bundle(bundle, target)
        saves[0] += 1
    os._exit(0)


out = []
for save, point, offset in trials:
    save_bundle(a, target)
    pid = os.fork()
    if pid == 0:
        child(save, point, offset)
    _, status = os.waitpid(pid, 0)
    killed = os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
    out.append([killed, load_bundle(target).extra_meta.get("variant")])
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def two_bundles(tmp_path_factory):
    from optitac_edge.config import load_board_config
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.sim.camera import SimCamera

    d = tmp_path_factory.mktemp("bundles")
    with SimCamera(realtime=False, seed=0, rest_frames=10) as cam:
        bundle = obtain_bundle(load_board_config("sim", env={}), cam, None)[0]
    a = save_bundle(bundle.with_updates(extra_meta={**bundle.extra_meta, "variant": "a"}), d / "a.npz")
    b = save_bundle(bundle.with_updates(extra_meta={**bundle.extra_meta, "variant": "b"}), d / "b.npz")
    return d, a, b


def test_sigkill_during_save_always_leaves_a_loadable_old_or_new_bundle(two_bundles):
    """Calibration bundle / power loss: a save killed (SIGKILL) at every step -- part-way through
    writing the temporary file, before its fsync, before the rename, after it -- leaves the old
    bundle before the rename and the new one after it, always loadable."""
    d, _a, _b = two_bundles
    target = d / "cal.npz"
    size = (d / "a.npz").stat().st_size
    trials, expected = [], []
    for save, old, new in ((0, "a", "b"), (1, "b", "a")):  # the saver writes b over a, then a over b
        for offset in np.linspace(0, size - 1, 8).astype(int):
            trials.append((save, "write", int(offset)))
            expected.append(old)
        trials += [(save, "fsync-file", 0), (save, "replace", 0), (save, "after-replace", 0)]
        expected += [old, old, new]
    out = subprocess.run([sys.executable, "-c", SAVER, str(d / "a.npz"), str(d / "b.npz"), str(target),
                          json.dumps(trials)], capture_output=True, text=True, check=False, timeout=300,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    results = json.loads(out.stdout.strip().splitlines()[-1])  # load_bundle raised nothing
    assert all(killed for killed, _ in results)
    assert [variant for _, variant in results] == expected
    # killed saves may leave their private temporary file (never read by anything); nothing else
    others = {p.name for p in d.iterdir()} - {"a.npz", "b.npz", "cal.npz"}
    assert all(re.fullmatch(r"\.cal\.npz\.\d+\.tmp", n) for n in others), others


# -- security ----------------------------------------------------------------------------------

FORBIDDEN = [
    (re.compile(r"^\s*(import pickle|from pickle|import cPickle|import dill|import marshal)", re.MULTILINE), "pickle"),
    (re.compile(r"allow_pickle\s*=\s*True"), "allow_pickle=True"),
    (re.compile(r"(?<![\w.])eval\("), "eval("),
    (re.compile(r"(?<![\w.])exec\("), "exec("),
    (re.compile(r"\bpickle\.loads?\("), "pickle.load"),
    (re.compile(r"\byaml\.load\("), "yaml.load"),
    (re.compile(r"\btorch\.load\("), "torch.load"),
]


def test_the_package_never_unpickles_or_evaluates_input():
    """Security: bundles (npz, allow_pickle=False) and configs (TOML) are parsed as data only."""
    hits = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        for pattern, name in FORBIDDEN:
            for m in pattern.finditer(text):
                line = text.count("\n", 0, m.start()) + 1
                hits.append(f"{path.relative_to(ROOT)}:{line}: {name}")
    assert hits == []
    # every np.load in the package says allow_pickle=False explicitly
    for path in sorted(PACKAGE.rglob("*.py")):
        for m in re.finditer(r"np\.load\(([^)]*)\)", path.read_text()):
            assert "allow_pickle=False" in m.group(1), f"{path}: np.load({m.group(1)})"


def test_a_bundle_holding_a_pickled_object_is_refused(two_bundles, tmp_path):
    d, _a, _ = two_bundles
    from optitac_edge.errors import BundleError

    with np.load(d / "a.npz", allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    members["fiber_dead"] = np.array([object()], dtype=object)
    bad = tmp_path / "evil.npz"
    np.savez(bad, **members)
    with pytest.raises(BundleError):
        load_bundle(bad)


def _listening_sockets(pid: int) -> list[str]:
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    listening = []
    for table in ("tcp", "tcp6", "udp", "udp6"):
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            f = line.split()
            # tcp state 0A = LISTEN; any bound udp socket would also accept datagrams
            if f[9] in inodes and (table.startswith("udp") or f[3] == "0A"):
                listening.append(f"{table} {f[1]}")
    unix = Path("/proc/net/unix").read_text().splitlines()[1:]
    for line in unix:
        f = line.split()
        if f[6] in inodes and f[5] == "01" and int(f[3], 16) & 0x10000:  # __SO_ACCEPTCON: listening
            listening.append(f"unix {f[-1] if len(f) > 7 else ''}")
    return listening


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")
def test_the_running_service_opens_no_listening_socket():
    """Security: `optitac-edge run` holds no listening TCP/UDP/UNIX socket."""
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONUNBUFFERED": "1", "OPENBLAS_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "running" not in (run.stdout.readline() or ""):
            pass
        time.sleep(0.5)
        assert run.poll() is None
        assert _listening_sockets(run.pid) == []
    finally:
        run.send_signal(signal.SIGTERM)
        run.communicate(timeout=10)


def test_the_unit_runs_unprivileged_with_a_private_state_directory():
    """Security: own user, no capabilities, no IP, state directory writable by the service user only."""
    unit = (ROOT / "systemd" / "optitac-edge.service").read_text()
    settings = dict(re.findall(r"^(\w+)=(.*)$", unit, re.MULTILINE))
    assert settings["User"] == "optitac" and settings["Group"] == "optitac"
    assert settings["StateDirectoryMode"] in ("0700", "0750")
    assert settings["UMask"] in ("0077", "0027")
    assert settings["NoNewPrivileges"] == "yes" and settings["CapabilityBoundingSet"] == ""
    assert settings["IPAddressDeny"] == "any" and "AF_INET" not in settings["RestrictAddressFamilies"]
    assert settings["ProtectSystem"] == "strict"
