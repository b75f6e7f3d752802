"""The service end to end: simulated camera -> pipeline -> serial over a pty -> the C reference decoder."""

from __future__ import annotations

import itertools
import os
import re
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from optitac_edge.io.protocol.messages import CommandType, ShapeCode
from optitac_edge.io.protocol.wire import encode_command

MCU = Path(__file__).resolve().parents[1] / "tools" / "mcu"


@pytest.fixture(scope="module")
def optitac_rx(tmp_path_factory) -> Path:
    exe = tmp_path_factory.mktemp("rx") / "optitac_rx"
    subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-I", str(MCU),
                    str(MCU / "optitac_rx.c"), str(MCU / "optitac_proto.c"), "-o", str(exe)], check=True)
    return exe


def _wait_for_line(proc: subprocess.Popen, text: str, timeout_s: float = 60.0) -> str:
    """Read ``proc``'s stdout up to the first line holding ``text``; the lines read."""
    lines = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if text in line or not line:
            break
    assert text in lines[-1], "".join(lines)
    return "".join(lines)


def _summary(stderr: str) -> dict[str, int]:
    return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", stderr)}


def test_run_streams_every_frame_to_the_c_decoder_at_120_fps(optitac_rx):
    """`optitac-edge run` at 120 fps for 1200 frames over a pty; TARE and STREAM are acknowledged."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    rx = subprocess.Popen([str(optitac_rx), "-t", "60", "-"], stdin=master, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--serial", path, "--fps", "120",
                            "--frames", "1200"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"})
    try:
        first = _wait_for_line(run, "running")  # calibrated; the loop starts now
        os.close(slave)  # the service holds it open now; the decoder sees EOF when the service ends
        slave = -1
        os.write(master, encode_command(CommandType.TARE, 1))
        os.write(master, encode_command(CommandType.STREAM, 2, stream_on=True, rate_divider=1))
        out, err = run.communicate(timeout=120)
        assert run.returncode == 0, err
        rx_out, rx_err = rx.communicate(timeout=30)  # EOF (EIO) once the sensor side closed the pty
    finally:
        for proc in (run, rx):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        os.close(master)
        if slave >= 0:
            os.close(slave)
    out = first + out
    written = int(re.search(r"link: (\d+) messages written, 0 not sent", out).group(1))
    assert "commands STREAM=1 TARE=1" in out, out
    rows = [r.split(",") for r in rx_out.splitlines()[1:]]
    summary = _summary(rx_err)
    print(f"written {written}, received {len(rows)} CONTACT frames; decoder {summary}")
    assert "processed 1200 frames" in out
    assert written >= 1200 + 2 + summary["status"]  # every CONTACT, the two ACKs and the STATUS messages
    assert len(rows) >= 0.999 * 1200
    assert summary["crc"] == summary["cobs"] == summary["length"] == summary["overflow"] == 0
    assert summary["ack"] == 2 and summary["status"] >= 8
    seqs = [int(r[0]) for r in rows]
    total = summary["contact"] + summary["status"] + summary["ack"]
    assert seqs[-1] - seqs[0] + 1 <= total  # continuous: no sequence number missing in between
    assert all(b > a for a, b in itertools.pairwise(seqs))


def test_decoded_values_equal_the_pipeline_values_to_the_wire_resolution(optitac_rx):
    from optitac_edge.config import load_board_config
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.service.loop import Service
    from optitac_edge.service.wiring import open_board_camera, open_board_transport

    master, slave = os.openpty()
    path = os.ttyname(slave)
    rx = subprocess.Popen([str(optitac_rx), "-q", "-t", "20", "-"], stdin=master, stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
    config = load_board_config("sim", env={}, overrides={"link.transport": "serial", "link.serial_url": path,
                                                         "camera.fps": 120})
    sent: dict[int, object] = {}
    stop = threading.Event()

    def keep(result, stats):
        sent[(result.t_ns // 1000) % 2**32] = result.primary.copy()
        if len(sent) == 360:  # 3 s at 120 fps
            stop.set()

    try:
        with open_board_camera(config) as camera, open_board_transport(config) as transport:
            bundle = obtain_bundle(config, camera, None)[0]
            Service(config, bundle, camera, transport).run(stop, on_result=keep)
            transport.wait_idle()
        os.close(slave)
        out, _err = rx.communicate(timeout=30)
    finally:
        if rx.poll() is None:
            rx.kill()
            rx.wait()
        os.close(master)
    rows = [list(map(int, r.split(","))) for r in out.splitlines()]
    assert len(sent) == 360 and len(rows) >= 0.999 * len(sent)
    contacts = 0
    for seq, t_us, flags, x, y, major, minor, angle, strength, shape, confidence, age in rows:
        est = sent[t_us]
        assert bool(flags & 1) == est.contact
        if not est.contact:
            assert (x, y, major, minor, shape) == (0, 0, 0, 0, ShapeCode.NONE)
            continue
        contacts += 1
        assert abs(x - est.x_mm * 100) <= 0.5 + 1e-6 and abs(y - est.y_mm * 100) <= 0.5 + 1e-6
        assert abs(major - est.major_mm * 100) <= 0.5 + 1e-6 and abs(minor - est.minor_mm * 100) <= 0.5 + 1e-6
        assert abs(angle - est.angle_deg * 100) <= 0.5 + 1e-6
        assert abs(strength - min(est.strength * 100, 65535)) <= 0.5 + 1e-6
        assert 0 <= age <= 65535
    assert contacts > 50


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_stop_the_service_within_a_second_with_a_final_status(signum):
    """systemd's stop (SIGTERM) and a closed terminal or `kill -HUP` (SIGHUP) end the loop cleanly:
    exit 0, the summary, and a last STATUS to the MCU after the last CONTACT."""
    from optitac_edge.io.protocol.decoder import FrameDecoder
    from optitac_edge.io.protocol.wire import MsgType

    master, slave = os.openpty()
    tty_path = os.ttyname(slave)
    frames: list[int] = []
    done = threading.Event()

    def read_link() -> None:
        dec = FrameDecoder()
        while not done.is_set():
            try:
                data = os.read(master, 65536)
            except OSError:  # the service closed its end
                return
            frames.extend(f.type for f in dec.feed(data))

    reader = threading.Thread(target=read_link, daemon=True)
    reader.start()
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--serial", tty_path],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        _wait_for_line(run, "running")
        os.close(slave)
        slave = -1
        time.sleep(0.5)  # the loop is streaming
        t0 = time.monotonic()
        run.send_signal(signum)
        out, err = run.communicate(timeout=10)
        elapsed = time.monotonic() - t0
        reader.join(5.0)
    finally:
        done.set()
        if run.poll() is None:
            run.kill()
        os.close(master)
        if slave >= 0:
            os.close(slave)
    assert run.returncode == 0, err
    assert elapsed < 1.0, elapsed
    assert "processed" in out and "Traceback" not in err
    assert MsgType.CONTACT in frames and frames[-1] == MsgType.STATUS


def test_run_waits_for_a_missing_mcu_port_and_streams_when_it_appears(tmp_path):
    """Issue 13.6: `run --serial` on a port that is not there yet exited 2 in 0.55 s (and systemd gave
    up after ten restarts). It now runs, and streams to the MCU as soon as the port appears."""
    from optitac_edge.io.protocol.decoder import FrameDecoder
    from optitac_edge.io.protocol.wire import MsgType

    link = tmp_path / "optitac-mcu"
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--serial", str(link)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "PYTHONUNBUFFERED": "1"})
    master, slave = os.openpty()
    try:
        _wait_for_line(run, "running")
        assert run.poll() is None
        os.symlink(os.ttyname(slave), link)  # the MCU is plugged in
        dec, frames = FrameDecoder(), []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and sum(f.type == MsgType.CONTACT for f in frames) < 30:
            r, _, _ = select.select([master], [], [], 0.1)
            if r:
                frames += dec.feed(os.read(master, 65536))
        run.send_signal(signal.SIGTERM)
        _out, err = run.communicate(timeout=10)
    finally:
        if run.poll() is None:
            run.kill()
        os.close(master)
        os.close(slave)
    assert sum(f.type == MsgType.CONTACT for f in frames) >= 30
    assert run.returncode == 0 and "not present" in err and "Traceback" not in err


def _full_pipe() -> tuple[int, int]:
    """A pipe whose buffer is already full: the next write to it blocks until someone reads."""
    import fcntl

    r, w = os.pipe()
    fcntl.fcntl(w, 1031, 4096)  # F_SETPIPE_SZ: one page
    os.set_blocking(w, False)
    try:
        while True:
            os.write(w, b"x" * 4096)
    except BlockingIOError:
        pass
    os.set_blocking(w, True)
    return r, w


def test_a_stdout_and_stderr_nobody_reads_never_stall_the_loop():
    """Issue 13.9: with an unread pipe as stdout the loop stopped within 5 s (the status line and the
    log wrote from it) and then exited 'no good camera frame'. With both stdout and stderr full and
    unread, -v logging and a 120 fps run, every CONTACT still reaches the MCU."""
    from optitac_edge.io.protocol.decoder import FrameDecoder
    from optitac_edge.io.protocol.wire import MsgType

    out_r, out_w = _full_pipe()
    master, slave = os.openpty()
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "-v", "--serial", os.ttyname(slave),
                            "--fps", "120", "--frames", "600"], stdout=out_w, stderr=out_w)
    os.close(out_w)
    dec, contacts = FrameDecoder(), 0
    try:
        deadline = time.monotonic() + 90
        while contacts < 600 and time.monotonic() < deadline and run.poll() is None:
            r, _, _ = select.select([master], [], [], 0.1)
            if r:
                contacts += sum(f.type == MsgType.CONTACT for f in dec.feed(os.read(master, 65536)))
        received_while_blocked = contacts
        drained = b""
        while run.poll() is None or select.select([out_r], [], [], 0)[0]:  # now read the pipe: it can finish
            if select.select([out_r], [], [], 0.1)[0]:
                chunk = os.read(out_r, 65536)
                if not chunk:
                    break
                drained += chunk
        run.wait(timeout=30)
    finally:
        if run.poll() is None:
            run.kill()
        for fd in (master, slave, out_r):
            os.close(fd)
    assert received_while_blocked == 600  # the whole run streamed while nobody read its output
    assert run.returncode == 0
    assert b"processed 600 frames" in drained and b"Traceback" not in drained
