"""The service's glue: board configs map onto the camera backends' real constructor arguments."""

from __future__ import annotations

import inspect

import pytest
from fakes.packing import decoded

from optitac_edge.config import available_boards, load_board_config
from optitac_edge.io.cameras import CAMERAS
from optitac_edge.io.protocol.wire import MsgType


@pytest.mark.parametrize("board", sorted(available_boards()))
def test_every_packaged_board_gives_arguments_its_camera_backend_accepts(board):
    config = load_board_config(board, env={})
    for name, section in config.cameras.items():
        cls = CAMERAS.load(section.backend)
        kwargs = cls.section_kwargs(section, config.view(config.camera_key(name)))
        inspect.signature(cls).bind(**kwargs, **section.options)  # raises TypeError on an unknown argument


def test_cli_and_environment_override_the_file():
    config = load_board_config("sim", env={"OPTITAC_CAMERA_FPS": "90"}, overrides={"link.rate_divider": 3})
    assert config.camera.fps == 90 and config.link.rate_divider == 3
    config = load_board_config("sim", env={"OPTITAC_CAMERA_FPS": "90"}, overrides={"camera.fps": 30})
    assert config.camera.fps == 30


def test_led_is_lowered_at_calibration_until_no_fiber_saturates():
    """A camera whose image scales with the LED: calibration ends below the saturation limit."""
    import numpy as np

    from optitac_edge.io.cameras.base import Camera, CapturedFrame
    from optitac_edge.service.bundles import adjust_led

    class LitCamera(Camera):
        pixel_format, height, width, fps = "gray", 8, 8, 30.0

        def __init__(self, led):
            super().__init__()
            self.led, self.seq = led, 0

        def _read_internal(self, timeout_s):
            self.seq += 1
            level = min(400.0 * self.led.brightness, 255.0)
            return CapturedFrame(np.full((8, 8), level, np.uint8), self.seq * 1000, self.seq)

    class FakeLed:
        brightness = 1.0

        def set_brightness(self, b):
            self.brightness = b

    led = FakeLed()
    config = load_board_config("sim", env={}, overrides={"led.enabled": True, "led.brightness": 1.0,
                                                         "led.max_peak": 230})
    with LitCamera(led) as cam:
        b = adjust_led(config, cam, led)
    assert led.brightness == b and 400 * b <= 230 and 400 * b > 230 - 30


def test_service_over_can_decodes_with_the_dbc():
    """The service with the CAN link on python-can's virtual bus; frames decode with cantools."""
    import threading

    import can

    from optitac_edge.io.protocol.can_codec import decode_frame
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.service.loop import Service
    from optitac_edge.service.wiring import open_board_camera, open_board_transport

    config = load_board_config("sim", env={}, overrides={
        "link.transport": "can", "link.can_interface": "virtual", "link.can_channel": "svc-test",
        "camera.fps": 200, "status.period_s": 0.2})
    with can.Bus(interface="virtual", channel="svc-test") as mcu:
        with open_board_camera(config) as camera, open_board_transport(config) as transport:
            bundle = obtain_bundle(config, camera, None)[0]
            stop = threading.Event()
            stats = Service(config, bundle, camera, transport).run(
                stop, on_result=lambda est, st: st.frames == 200 and stop.set())
        names = []
        while (msg := mcu.recv(timeout=0.2)) is not None:
            sensor, name, _signals = decode_frame(msg.arbitration_id, msg.data)
            assert sensor == 0
            names.append(name)
    assert names.count("CONTACT_A") == names.count("CONTACT_B") == stats.sent == 200
    assert names.count("STATUS") >= 2  # one every 0.2 s of the ~1 s run, and the last


def test_a_state_directory_that_cannot_hold_the_bundle_does_not_stop_the_service(tmp_path, caplog):
    """Issue 13.8: the bundle calibrated at start cannot be saved (a full or read-only state
    directory; here its parent is a file): the service runs on it from memory, says so once in the
    log and in every STATUS (bit5), instead of exiting and restart-looping."""
    import threading

    from optitac_edge.io.protocol.messages import STATE_CALIBRATION_UNSAVED
    from optitac_edge.service.session import BoardSession

    blocker = tmp_path / "state"
    blocker.write_text("not a directory")
    config = load_board_config("sim", env={}, overrides={
        "calibration.bundle": str(blocker / "calibration.npz"), "camera.fps": 300})
    stop = threading.Event()
    with BoardSession(config) as session:
        stats = session.run(stop, on_result=lambda est, st: st.frames == 60 and stop.set())
        assert stats.frames == 60
        assert session.unsaved is not None and "calibration.npz" in session.unsaved
        assert session.service.status.message(0).state & STATE_CALIBRATION_UNSAVED
    assert [r.levelname for r in caplog.records if "not saved" in r.getMessage()] == ["ERROR"]


def test_run_on_a_full_state_directory_keeps_streaming(tmp_path):
    """The same through the command: a file size limit makes the save fail (EFBIG, as ENOSPC)."""
    import resource
    import signal
    import subprocess
    import sys

    board = tmp_path / "b.toml"
    board.write_text(f'[calibration]\nbundle = "{tmp_path / "calibration.npz"}"\n[camera]\nfps = 300\n')

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    proc = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board),
                           "--frames", "100"], capture_output=True, text=True, timeout=120, check=False,
                          preexec_fn=limit)
    assert proc.returncode == 0, proc.stderr
    assert "processed 100 frames" in proc.stdout
    assert "calibration bundle not saved" in proc.stderr and "File too large" in proc.stderr
    assert not (tmp_path / "calibration.npz").exists()


def test_status_says_the_frame_rate_of_its_last_period_not_the_average_since_the_start() -> None:
    """The frames queued while the service started come at once, and the average since the start
    over-read for long after (85, then 62 fps on a 60-fps camera): STATUS now says the last period's rate."""
    import threading

    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.io.cameras.base import CapturedFrame
    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.io.transports import open_transport
    from optitac_edge.service.loop import Service
    from optitac_edge.sim.camera import SimCamera

    clock = VirtualClock()
    camera = SimCamera(realtime=False, clock=clock, fps=60.0)
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(10)], "gray")

    class Queued:
        """25 frames waiting in the camera's queue at the start, then one every 1/60 s."""

        def __getattr__(self, name):
            return getattr(camera, name)

        def __init__(self) -> None:
            self.backlog = [camera.read() for _ in range(25)]

        def read(self, timeout_s=1.0):
            if self.backlog:
                f = self.backlog.pop(0)
                return CapturedFrame(f.frame, clock.monotonic_ns(), f.seq)
            return camera.read(timeout_s)

    config = load_board_config("sim", env={}, overrides={"status.period_s": 1.0})
    transport = open_transport("none")
    transport.delivers = True  # packed as the serial link would
    sent = []
    transport.send = lambda p: sent.append((p.t_us, decoded(p).fps_x10 / 10)) if p.kind is MsgType.STATUS else None
    service = Service(config, bundle, Queued(), transport, clock=clock)
    service.run(threading.Event(), duration_s=4.0)
    rates = [fps for _, fps in sent]
    assert len(rates) >= 3 and abs(rates[1] - 60.0) < 1.0 and abs(rates[2] - 60.0) < 1.0, rates


@pytest.mark.parametrize("backlog", [0, 4])
def test_frames_the_camera_lost_before_the_loop_caught_up_are_counted_apart(backlog) -> None:
    """A camera streams while the service makes its bundles (the built-in board calibrates from its first frames,
    ~0.5 s): ``optitac-edge run`` said "dropped 33" of a run that lost none once running. The frames lost until the
    loop caught up (its first read that waited for a frame) are counted apart. A camera's ring hands out the
    frames it kept first (``backlog``, read at once), and the gap shows after them, as V4L2's sequence does."""
    import threading

    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.io.cameras.base import CapturedFrame
    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.io.transports import open_transport
    from optitac_edge.service.loop import Service
    from optitac_edge.sim.camera import SimCamera

    clock = VirtualClock()
    camera = SimCamera(realtime=False, clock=clock, fps=60.0)
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(10)], "gray")

    class Gaps:
        """The camera's gap counter: 9 frames lost after its backlog, 2 more at the loop's 30th read."""

        def __init__(self) -> None:
            self.frames_dropped = 0
            self.reads = 0
            self.backlog = [camera.read() for _ in range(backlog)]

        def __getattr__(self, name):
            return getattr(camera, name)

        def read(self, timeout_s=1.0):
            self.reads += 1
            self.frames_dropped += {backlog + 1: 9, 30: 2}.get(self.reads, 0)
            if self.backlog:  # kept in the ring: at once
                f = self.backlog.pop(0)
                return CapturedFrame(f.frame, clock.monotonic_ns(), f.seq)
            return camera.read(timeout_s)  # waits for the frame's time on the clock

    config = load_board_config("sim", env={}, overrides={})
    stats = Service(config, bundle, Gaps(), open_transport("none"), clock=clock).run(threading.Event(),
                                                                                      duration_s=1.0)
    assert stats.frames >= 50 and stats.frames_dropped == 2 and stats.frames_dropped_before_loop == 9
