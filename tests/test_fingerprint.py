"""A bundle knows its sensor: frames of another sensor, or of a moved camera, are refused before any contact.

Issue 52 §1: a 61-fiber bundle on the built-in 217-fiber camera printed ``61/61 fibers; running`` and
streamed contacts; ``replay`` of a 217-fiber recording wrote 74 contact frames; the API returned plausible
contacts. Each consumer below failed before (it processed the frames).
"""

from __future__ import annotations

import re
import threading

import numpy as np
import pytest
from fakes.packing import decoded
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.cli import main
from optitac_edge.config import load_board_config
from optitac_edge.core.fingerprint import (
    FINGERPRINT_KEY,
    MIN_FIT_FRACTION,
    SensorMismatchError,
    check_sensor,
    sensor_fit,
)
from optitac_edge.core.frame_engine import Skip
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.clock import VirtualClock
from optitac_edge.io.layout_csv import save_layout_csv
from optitac_edge.io.protocol.messages import SensorState
from optitac_edge.io.protocol.wire import MsgType
from optitac_edge.io.recording import Recording
from optitac_edge.io.transports.base import NullTransport
from optitac_edge.service.loop import Service
from optitac_edge.sim.camera import SimCamera
from optitac_edge.sim.scenarios import write_scenario


@pytest.fixture(scope="module")
def hex61(tmp_path_factory):
    """A 61-fiber layout at 4 mm (the RGB_sensor's), its rest recording and its bundle (saved)."""
    d = tmp_path_factory.mktemp("hex61")
    layout = hex_layout(rings=4, pitch_mm=4.0)
    csv = d / "hex61.csv"
    save_layout_csv(layout, csv)
    rec = Recording(write_scenario(d / "rest61", "rest", seed=3, layout=layout))
    bundle = save_bundle(calibrate_fibers(rec.rest_frames(), rec.pixel_format, layout=layout), d / "cal61.npz")
    return csv, d / "cal61.npz", bundle


def _one_line(capsys, argv, *needles):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("optitac-edge: error:") and "\n" not in err and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


def test_a_bundle_keeps_its_sensors_fingerprint(hex61, bundle_path):
    _, path, _ = hex61
    meta = load_bundle(path).extra_meta[FINGERPRINT_KEY]
    assert meta["n_fibers"] == 61 and meta["pitch_mm"] == pytest.approx(4.0)
    assert (meta["width"], meta["height"], meta["pixel_format"]) == (640, 480, "gray")
    assert meta["contrast"] > 0.9  # the simulator's spots, dark between them
    other = load_bundle(bundle_path).extra_meta[FINGERPRINT_KEY]
    assert other["layout"] != meta["layout"] and other["n_fibers"] == 217


def test_replay_evaluate_and_calibrate_refuse_another_sensors_bundle(hex61, unseen_rec, tmp_path, capsys):
    _, cal61, _ = hex61
    for argv in (["replay", str(unseen_rec), "--cal", str(cal61), "-o", str(tmp_path / "c.csv")],
                 ["evaluate", str(unseen_rec), "--cal", str(cal61)],
                 ["calibrate", "levels", str(unseen_rec), "--cal", str(cal61)]):
        _one_line(capsys, argv, str(unseen_rec), str(cal61), "61 fibers", "of 61 fibers light")
    assert not (tmp_path / "c.csv").exists()


def test_the_bundle_of_the_sensor_itself_fits(unseen_rec, bundle_path):
    rec, bundle = Recording(unseen_rec), load_bundle(bundle_path)
    fit = check_sensor(bundle, rec.rest_frames(), rec.pixel_format, str(unseen_rec))
    assert fit.fitting == fit.live == 217 and fit.fits


def test_the_api_refuses_frames_of_another_sensor_before_a_contact(hex61):
    import optitac_edge as ot

    _, cal61, _ = hex61
    readings = 0
    with ot.open_sensor("sim", cal=str(cal61)) as sensor, pytest.raises(SensorMismatchError) as info:
        for _ in range(50):
            sensor.read()
            readings += 1
    assert "cal61.npz (61 fibers, 640x480 gray)" in str(info.value) and "camera frames" in str(info.value)
    assert readings < 5  # the first baseline's frames (no contact can come before them)


class _Statuses(NullTransport):
    delivers = True

    def __init__(self) -> None:
        super().__init__()
        self.states: list[SensorState] = []
        self.messages = self.contacts = 0

    def send(self, packet):
        super().send(packet)
        if packet.kind is MsgType.STATUS:
            self.states.append(SensorState.from_bits(decoded(packet).state))
        elif packet.kind in (MsgType.CONTACT, MsgType.CONTACT2):
            self.messages += 1
            self.contacts += bool(decoded(packet).flags & 1)  # bit 0: CONTACT


def test_the_service_streams_no_contact_and_tells_the_mcu(hex61):
    """On another sensor's bundle the service keeps running (no watchdog exit: the camera works), sends no
    CONTACT, and every STATUS after the check says: baseline not ready, camera fault."""
    _, _, bundle61 = hex61
    config = load_board_config("sim", env={}, overrides={"camera.fps": 300, "status.period_s": 0.1,
                                                         "camera.timeout_s": 0.2})
    clock = VirtualClock()
    transport = _Statuses()
    service = Service(config, bundle61, None, transport, clock=clock,
                      camera_factory=lambda: SimCamera(fps=300, realtime=False, seed=1, rest_frames=10, clock=clock))
    stats = service.run(threading.Event(), duration_s=3.0)  # > watchdog.max_frame_gap_s
    # the first baseline's frames before the last (baseline not ready, no contact); nothing after
    assert transport.contacts == 0 and transport.messages == stats.frames == bundle61.baseline_frames - 1
    assert stats.mismatched_frames > 800 and stats.camera_errors == 0
    assert len(transport.states) >= 20
    assert all(not s.baseline_ready and s.camera_fault for s in transport.states[1:]), [(s.baseline_ready, s.camera_fault) for s in transport.states]


def test_a_channel_refuses_once_and_skips_every_later_frame(hex61, rest_rec):
    from optitac_edge.io.cameras.base import CapturedFrame
    from optitac_edge.service.channel import SensorChannel

    _, _, bundle61 = hex61
    rec = Recording(rest_rec)
    ch = SensorChannel(0, "sim", bundle61)
    skips = []
    for i in range(12):
        ch.take(CapturedFrame(frame=rec.frame(i), t_ns=i * 10**7, seq=i))
        skips.append(ch.run_pipeline())
    assert skips[bundle61.baseline_frames - 1:] == [Skip.MISMATCH] * (13 - bundle61.baseline_frames)
    assert ch.mismatch is not None and "61 fibers" in ch.mismatch


def _shifted(frames: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """The frames as a camera moved by (dx, dy) px sees them (the edge filled with the background)."""
    out = np.full_like(frames, int(np.percentile(frames, 5)))
    h, w = frames.shape[1:3]
    out[:, max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = \
        frames[:, max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dx=st.integers(-40, 40), dy=st.integers(-40, 40))
def test_a_moved_camera_fits_while_the_spots_stay_under_the_map(rest_rec, bundle_path, dx, dy):
    """Generated camera shifts: within a third of the spot spacing the bundle still fits (its map's
    centres still on the spots); beyond two thirds it is refused. Nothing in between is asserted."""
    rec, bundle = Recording(rest_rec), load_bundle(bundle_path)
    frames = np.stack([rec.frame(i) for i in range(bundle.baseline_frames)])
    c = bundle.fibers.centroid_px
    spacing = float(np.median(np.hypot(*(c[bundle.layout.neighbour_pairs()[:, 0]]
                                         - c[bundle.layout.neighbour_pairs()[:, 1]]).T)))
    shift = float(np.hypot(dx, dy))
    fit = sensor_fit(bundle, _shifted(frames, dx, dy), rec.pixel_format)
    if shift <= spacing / 3:
        assert fit.fits, (dx, dy, fit)
    elif shift >= 2 * spacing / 3 and not _on_the_lattice(dx, dy, c, bundle, spacing):
        assert not fit.fits, (dx, dy, fit)


def _on_the_lattice(dx: int, dy: int, c: np.ndarray, bundle, spacing: float) -> bool:
    """A shift by about a lattice vector puts the spots under the map again (an array shifted by one fiber
    looks the same but for its rim): such a shift is not asserted."""
    pairs = bundle.layout.neighbour_pairs()
    vectors = c[pairs[:, 1]] - c[pairs[:, 0]]
    k = np.round(np.linalg.lstsq(vectors[:2].T, np.array([dx, dy], float), rcond=None)[0])
    near = vectors[:2].T @ k
    return bool(np.hypot(*(near - (dx, dy))) < spacing / 2.5)


def test_a_press_during_the_first_baseline_is_not_a_mismatch(unseen_rec, bundle_path):
    """A start during a grasp: the pressed fibers darken but their gaps stay dark."""
    rec, bundle = Recording(unseen_rec), load_bundle(bundle_path)
    truth = rec.truth
    pressed = [i for i in range(len(rec)) if truth.contact[i] and truth.depth_mm[i] >= 2.5]
    assert pressed
    fit = sensor_fit(bundle, [rec.frame(i) for i in pressed[:5]], rec.pixel_format)
    assert fit.fraction >= 0.9 > MIN_FIT_FRACTION, fit


def test_a_refused_pipeline_keeps_no_baseline_and_refuses_every_later_frame(hex61, rest_rec):
    _, _, bundle61 = hex61
    rec = Recording(rest_rec)
    pipe = Pipeline(bundle61)
    with pytest.raises(SensorMismatchError):
        for i in range(bundle61.baseline_frames):
            pipe.process_recorded(rec.frame(i), i)
    assert not pipe.baseline_ready
    with pytest.raises(SensorMismatchError):  # every later frame: the same line
        pipe.process_recorded(rec.frame(10), 10)


def test_one_recording_given_twice_or_copied_is_not_two_sessions(unseen_rec, bundle_path, tmp_path, capsys):
    """Issue 52 §1: ``calibrate depth d1 d1`` said "heldout by 2 sessions" and scored its own fitted figure."""
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(unseen_rec, copy)
    cal = tmp_path / "cal.npz"
    shutil.copy(bundle_path, cal)
    before = cal.read_bytes()
    _one_line(capsys, ["calibrate", "levels", str(unseen_rec), str(unseen_rec), "--cal", str(cal)], "given twice")
    _one_line(capsys, ["calibrate", "levels", str(unseen_rec), str(copy), "--cal", str(cal)],
              f"{copy}: the same frames as {unseen_rec}")
    _one_line(capsys, ["evaluate", str(copy), str(unseen_rec), "--cal", str(cal)], "the same frames")
    assert cal.read_bytes() == before


def test_a_recording_of_another_frame_size_is_refused_naming_it(bundle_path, tmp_path, capsys):
    from optitac_edge.sim.optics import CameraOptics

    small = write_scenario(tmp_path / "small", "rest", seed=1, optics=CameraOptics(width=320, height=240))
    _one_line(capsys, ["replay", str(small), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")],
              f"{small}: frame is uint8 (240, 320)", str(bundle_path))


def test_run_says_once_why_a_sensor_sent_no_contact_and_each_event_once(hex61):
    """run printed each event twice (a plain line and an INFO line); on another sensor's bundle it must say
    why no contact was sent, in its summary."""
    import subprocess
    import sys

    _, cal61, _ = hex61
    proc = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--cal", str(cal61), "--duration", "1"],
                          check=False, capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert "sensor 0 'sim': no contact sent: sim's camera frames are not of the sensor of" in proc.stdout
    assert out.count("are not of the sensor of") == 2  # the log once, the summary once
    assert "stopped after" not in out  # run's own summary says it
    proc = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--duration", "1"], check=False,
                          capture_output=True, text=True, timeout=120, cwd=str(cal61.parent))
    out = proc.stdout + proc.stderr
    assert out.count("calibrating") == 1, out


@pytest.mark.parametrize("policy", ["refuse", "remap"])
def test_a_board_that_allows_it_maps_the_fibers_again_keeping_the_old_bundle(hex61, tmp_path, policy):
    """calibration.if_mismatched: 'refuse' (the default) runs on the bundle and sends no contact; 'remap'
    checks the bundle against the rest frames at start and, when they do not fit, maps the fibers again,
    saying so, and keeps the old bundle beside the new (it may be the other skin's)."""
    import subprocess
    import sys

    _, cal61, _ = hex61
    bundle = tmp_path / "calibration.npz"
    bundle.write_bytes(cal61.read_bytes())
    board = tmp_path / "b.toml"
    board.write_text(f'[calibration]\nbundle = "calibration.npz"\nif_mismatched = "{policy}"\n[camera]\nfps = 120\n')
    proc = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board), "--frames", "240"],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    if policy == "refuse":
        assert "no contact sent" in proc.stdout and sorted(p.name for p in tmp_path.iterdir()) == [
            "b.toml", "calibration.npz"]
        assert bundle.read_bytes() == cal61.read_bytes()
        return
    kept = tmp_path / "calibration.another-sensor.npz"
    assert kept.read_bytes() == cal61.read_bytes()  # the old bundle, never deleted
    assert load_bundle(bundle).layout.n_fibers == 217
    assert re.search(r"the camera's rest frames are not of the sensor of .*61 fibers.*; mapping the fibers again from the rest "
                     r"frames \(calibration.if_mismatched = 'remap'\)", proc.stderr), proc.stderr
    assert f"the old bundle is kept as {kept}" in proc.stderr
    assert "no contact sent" not in proc.stdout and re.search(r"processed 240 frames, [1-9]\d* with contact",
                                                              proc.stdout), proc.stdout
