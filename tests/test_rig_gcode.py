"""The GRBL rig backend against a fake GRBL on a pty, and ``collect`` through it: Ctrl-C, retract, resume."""

from __future__ import annotations

import math
import re
import time as time_module

import numpy as np
import pytest
from fakes.grbl import FakeGrbl

from optitac_edge.bringup.collect import JOURNAL, Collector, CollectSettings
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.steps import calibrate_centroid
from optitac_edge.errors import RecordingError, RigError
from optitac_edge.io.clock import VirtualClock
from optitac_edge.io.recording import Recording
from optitac_edge.io.rigs.base import RigLimits
from optitac_edge.io.rigs.gcode import GcodeRig
from optitac_edge.sim.camera import SimCamera
from optitac_edge.sim.rig import SimMount

LIMITS = RigLimits(x_mm=(60.0, 140.0), y_mm=(40.0, 120.0), z_mm=(-3.0, 20.0), feed_mm_s=10.0, safe_z_mm=12.0)
MOUNT = SimMount(origin_xy_mm=(100.0, 80.0), rotation_deg=-9.0, surface_z_mm=2.0)


@pytest.fixture
def grbl():
    machine = FakeGrbl(speed=20.0)
    yield machine
    machine.close()


class GrblSkin:
    """The simulated skin pressed by the fake machine's tool head (a PressSource)."""

    def __init__(self, machine: FakeGrbl, mount: SimMount) -> None:
        self.machine, self.mount = machine, mount

    def at(self, frame: int):
        from optitac_edge.sim.skin import Indenter

        x, y, z = self.machine.position()
        depth = self.mount.surface_z_mm - z
        if depth <= 0:
            return None
        sx, sy = self.mount.to_sensor(x, y)
        return Indenter("circle", sx, sy, 0.0, 5.0, depth)


def test_moves_status_and_limits(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        assert rig.status().state == "idle" and rig.status().xyz_mm == pytest.approx((100.6, 79.6, 5.0))
        sent = len(grbl.lines)
        with pytest.raises(RigError, match=r"z = -4.000 mm is outside the limits -3..20 mm; nothing moved"):
            rig.move_to((100.0, 80.0, -4.0))
        assert len(grbl.lines) == sent  # refused before anything was sent
        rig.move_to((101.0, 80.0, 4.0))
        assert grbl.lines[-1] == "G1 X101.000 Y80.000 Z4.000 F600.0"
        # idle there: the fake moves in real time, so wait on its reports (200 polls were too few on a busy machine)
        rig.wait_until_at((101.0, 80.0, 4.0), timeout_s=30.0)
        assert rig.status().xyz_mm == pytest.approx((101.0, 80.0, 4.0))
        with pytest.raises(RigError, match=r"'M3' refused \(error:20\)"):
            rig.command("M3")


def test_an_alarm_is_one_line_and_stops_the_rig(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        grbl.inject_alarm(1)
        with pytest.raises(RigError, match="ALARM:1 \\(hard limit: a limit switch was hit\\)"):
            for _ in range(50):
                rig.status()


def test_after_a_soft_limit_grbl_is_silent_until_reset_then_unlocked_and_the_tip_retracted(grbl) -> None:
    """GRBL's critical event: nothing answered until Ctrl-X, then alarm until $X. The position is kept, so
    the retract resets, unlocks and lifts. Before: the retract waited for a status report that never came."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, 1.0))
        rig.wait_until_at((100.0, 80.0, 1.0), 5.0)
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 5.0))  # the machine's travel is less than our limits
        with pytest.raises(RigError, match=r"ALARM:2 \(soft limit.*rig limits must lie inside the machine's travel"):
            rig.move_to((100.0, 80.0, 6.0))
        assert grbl.critical  # the fake is silent now: '?' gets no answer
        sent = len(grbl.realtime)
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 40.0))
        rig.retract()
        assert b"\x18" in grbl.realtime[sent:] and "$X" in grbl.lines
        assert grbl.state == "Idle" and grbl.position() == pytest.approx((100.0, 80.0, 12.0))


def test_after_a_hard_limit_the_tip_is_not_moved_and_the_message_says_what_to_do(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, -2.0), 2.0)
        grbl.inject_alarm(1)
        moves = [line for line in grbl.lines if line.startswith("G1")]
        with pytest.raises(RigError, match=r"ALARM:1 .*position is lost, so the tip was not moved: jog it clear of "
                                           r"the skin, home the machine \(\$H\)"):
            rig.retract()
        assert [line for line in grbl.lines if line.startswith("G1")] == moves  # no move after the alarm
        assert "$X" not in grbl.lines


def test_the_retract_lifts_straight_up_whatever_a_report_says(grbl) -> None:
    """A report of x = 190 outside the travel, nan, 1e999 or a 309-digit work offset sent the tip there
    (G1 X190, G1 Xnan, G1 Xinf); now the lift carries Z alone and garbled reports are polled again."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, 1.0))
        rig.wait_until_at((100.0, 80.0, 1.0), 5.0)
        grbl.garble("<Idle|MPos:190.000,10.000,5.000|FS:0,0>", "<Idle|MPos:nan,80.000,1.000|FS:0,0>",
                    "<Idle|MPos:1e999,80.000,1.000|FS:0,0>", "<Idle|MPos:100.000,80.000,1.000|WCO:1e308,0,0>",
                    "ok")
        rig.retract()
        moves = [line for line in grbl.lines if line.startswith("G1")]
        assert moves[-1] == "G1 Z12.000 F600.0"
        assert all("nan" not in m and "inf" not in m and "X190" not in m for m in moves)
        assert grbl.position() == pytest.approx((100.0, 80.0, 12.0))
        assert rig.garbled_reports >= 4


def test_a_run_of_garbled_reports_is_one_line_not_a_traceback(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        grbl.garble(*["<Idle|MPos:nan,0,0>"] * 10)
        with pytest.raises(RigError, match="5 garbled status reports in a row .* check the cable"):
            rig.status()


@pytest.mark.parametrize("state, message", [
    ("Tool", "waiting for a tool change"), ("Door:1", "stopped by its safety door: close it"), ("Sleep", "asleep"),
])
def test_states_that_stop_the_machine_end_a_wait_at_once(grbl, state, message) -> None:
    """grblHAL's Tool, Door and Sleep were waited on for 34 s; now they end the wait with what to do."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        grbl.set_state(state)
        assert rig.status().raw_state == state
        with pytest.raises(RigError, match=message):
            rig.wait_until_at((100.6, 79.6, 5.0), 30.0)


def test_a_locked_machine_is_refused_unless_homing_is_allowed(grbl) -> None:
    grbl.state = "Alarm"
    with pytest.raises(RigError, match="in alarm .* home it"):
        GcodeRig(grbl.port, LIMITS)
    with GcodeRig(grbl.port, LIMITS, home=True) as rig:
        assert "$H" in grbl.lines and rig.status().state == "idle"


def test_no_grbl_on_the_port_is_one_line(tmp_path) -> None:
    with pytest.raises(RigError, match="cannot open the port"):
        GcodeRig(str(tmp_path / "absent"), LIMITS)


def test_retract_holds_resets_and_lifts_without_losing_the_position(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.6, 79.6, -2.0), 1.0)  # slow: still moving when we stop
        rig.retract()
        assert grbl.realtime.count(b"!") == 1 and b"\x18" in grbl.realtime
        assert grbl.state == "Idle"  # held before the reset: no ALARM:3
        assert grbl.lines[-1] == "G1 Z12.000 F600.0"  # straight up, x and y left where the machine is
        assert grbl.position()[:2] == pytest.approx((100.6, 79.6))


class InterruptDuringPress:
    """A camera that raises KeyboardInterrupt (Ctrl-C) a few frames into press ``k`` of a collection."""

    def __init__(self, camera: SimCamera, journal, k: int) -> None:
        self.camera, self.journal, self.k, self.frames = camera, journal, k, 0

    def __getattr__(self, name: str):
        return getattr(self.camera, name)

    def read(self, timeout_s: float = 1.0):
        if self.journal.exists() and len(self.journal.read_text().splitlines()) > self.k:
            self.frames += 1
            if self.frames == 20:  # in the middle of press k + 1, with the tip in the skin or near it
                raise KeyboardInterrupt
        return self.camera.read(timeout_s)


def test_collect_seen_through_grbl_interrupted_retracted_and_continued(grbl, tmp_path) -> None:
    out = tmp_path / "seen"
    settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=5)
    camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
    lines: list[str] = []
    with GcodeRig(grbl.port, LIMITS) as rig:
        with pytest.raises(KeyboardInterrupt):
            Collector(InterruptDuringPress(camera, out / JOURNAL, 7), rig, bundle, settings,
                      prompt=lines.append).run("seen", out, limit=14)
        assert grbl.position()[2] == pytest.approx(12.0)  # the tip went up
        assert lines[-1] == "retracted the tip to z = 12 mm"
    with pytest.raises(RecordingError, match="interrupted collection: run the same 'optitac-edge collect' command"):
        Recording(out)
    done = len((out / JOURNAL).read_text().splitlines()) - 1
    assert done == 7
    asked: list[str] = []
    with GcodeRig(grbl.port, LIMITS) as rig:
        result = Collector(camera, rig, bundle, settings, prompt=lines.append,
                           confirm=asked.append).run("seen", out, limit=14)
    assert result.resumed_at == done and result.presses == 14
    assert f"continuing seen after press {done} of 14" in lines
    # issue 52 §3: the resume asked again to mount the indenter its presses had on (one indenter for all)
    assert asked == [] and "continuing with the circle indenter, 5 mm, mounted as it was" in lines
    # parked at the safe height over the start point (before: over the last press, off-centre for the next run)
    assert grbl.position() == pytest.approx((100.6, 79.6, 12.0))
    assert lines[-1] == "parked the tip at z = 12 mm over the start point (100.60, 79.60)"
    rec = Recording(out)
    assert rec.timestamped and rec.rig_poses is not None and len(rec.rig_poses.frame) == len(rec)
    assert np.all(np.diff(rec.t_ns) >= 0)
    assert abs(result.rig_frame.rotation_deg - MOUNT.rotation_deg) < 0.5
    assert np.hypot(*(np.array(result.rig_frame.origin_xy_mm) - MOUNT.origin_xy_mm)) < 0.3
    assert not (out / JOURNAL).exists()
    _, summary = calibrate_centroid(rec, calibrate_fibers(rec.rest_frames(), rec.pixel_format))
    assert summary["frames"] >= 14 * settings.hold_frames


def test_a_soft_limit_during_a_collection_is_recovered_and_the_tip_retracted(grbl, tmp_path) -> None:
    """Before: after ALARM:2 the tip stayed where it stopped (GRBL answered nothing to the retract's status
    polls) and the message did not say what GRBL needs."""
    settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
    camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
    grbl.travel = ((0.0, 200.0), (0.0, 200.0), (1.5, 40.0))  # the machine ends above the registration depth
    lines: list[str] = []
    with GcodeRig(grbl.port, LIMITS) as rig, pytest.raises(RigError) as caught:
        Collector(camera, rig, bundle, settings, prompt=lines.append).run("seen", tmp_path / "r", limit=3)
    message = str(caught.value)
    assert "ALARM:2 (soft limit" in message and "rig limits must lie inside the machine's travel" in message
    assert lines[-1] == "retracted the tip to z = 12 mm" and "$X" in grbl.lines
    assert grbl.position()[2] == pytest.approx(12.0) and not grbl.critical


def test_an_interrupt_whose_retract_fails_says_the_tip_was_not_retracted(grbl, tmp_path) -> None:
    """Ctrl-C after a hard limit: the line must not say 'tip retracted' (the position is lost, the tip stays)."""
    settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
    camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")

    class HardLimitThenCtrlC:
        def __init__(self) -> None:
            self.frames = 0

        def __getattr__(self, name):
            return getattr(camera, name)

        def read(self, timeout_s=1.0):
            self.frames += 1
            if self.frames == 40:
                grbl.inject_alarm(1)
                raise KeyboardInterrupt
            return camera.read(timeout_s)

    with GcodeRig(grbl.port, LIMITS) as rig, pytest.raises(RigError) as caught:
        Collector(HardLimitThenCtrlC(), rig, bundle, settings, prompt=lambda line: None).run("seen", tmp_path / "r",
                                                                                              limit=3)
    assert str(caught.value).startswith("interrupted; the tip was NOT retracted: ")
    assert "home the machine ($H)" in str(caught.value)


def test_collect_slide_through_grbl_slides_at_the_feed_rate(tmp_path) -> None:
    """``collect slide`` on a GRBL machine: each slide is one G1 in the skin at its speed (capped at the rig's feed
    limit, here 10 mm/s), and truth.csv's motion columns say the press slid. The machine's time moves 1/60 s at
    each status report (one a frame), so the frames in each slide are the same on any machine (on the wall clock
    a busy CI machine once caught 17 sliding frames where more than 20 were asked)."""
    out = tmp_path / "slide"
    settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=5)
    grbl = FakeGrbl(speed=4.0, tick_s=1 / 60)
    try:
        camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
        bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
        with GcodeRig(grbl.port, LIMITS) as rig:
            Collector(camera, rig, bundle, settings, prompt=lambda line: None).run("slide", out, limit=3)
    finally:
        grbl.close()
    feeds = [float(m.group(1)) / 60 for line in grbl.lines if (m := re.search(r"^G1 .*F([\d.]+)", line))]
    assert {round(f, 3) for f in feeds} >= {2.0, 10.0}  # 2 mm/s, and 20 and 100 mm/s capped at 10
    truth = Recording(out).truth
    assert truth.motion is not None and (truth.motion == "sliding").sum() > 20


# -- issue 38: GRBL 1.1h as its source behaves ------------------------------------------------------------


def test_a_reset_during_grbls_half_second_after_a_soft_limit_is_not_lost(grbl) -> None:
    """GRBL 1.1h prints ALARM:2, waits 500 ms, prints [MSG:Reset to continue] and forgets any reset sent before
    it (grbl/report.c, grbl/protocol.c; the fake does the same). Before: the retract sent Ctrl-X 3 ms after the
    alarm, it was lost, GRBL stayed locked and the line said 'no banner after a reset': the tip stayed deep."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, 1.0))
        rig.wait_until_at((100.0, 80.0, 1.0), 5.0)
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 5.0))
        with pytest.raises(RigError, match=r"ALARM:2"):
            rig.move_to((100.0, 80.0, 6.0))
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 40.0))
        rig.retract()
        assert not grbl.critical and grbl.position() == pytest.approx((100.0, 80.0, 12.0))


def test_a_reset_lost_anyway_is_sent_again(grbl) -> None:
    """A reset lost on the line (or sent early by another program): the backend sends Ctrl-X again until
    GRBL's banner comes."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, 1.0))
        rig.wait_until_at((100.0, 80.0, 1.0), 5.0)
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 5.0))
        grbl.alarm_delay_s = 1.5  # longer than the backend waits for the message
        with pytest.raises(RigError, match=r"ALARM:2"):
            rig.move_to((100.0, 80.0, 6.0))
        grbl.travel = ((0.0, 200.0), (0.0, 200.0), (-10.0, 40.0))
        rig.retract()
        assert grbl.lost_resets >= 1 and grbl.position() == pytest.approx((100.0, 80.0, 12.0))


@pytest.mark.parametrize("state", ["\x12un", "R\x00n", "Idl\xe5"])
def test_a_flipped_bit_in_a_state_name_is_a_garbled_report_polled_again(grbl, state) -> None:
    """'<\\x12un|...' was read as a state this program does not know and ended the run, with the raw control
    byte in the line; a state word that is not one GRBL sends is a garbled report, polled again."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        grbl.garble(f"<{state}|MPos:100.600,79.600,5.000|FS:0,0>")
        assert rig.status().state == "idle" and rig.garbled_reports == 1
        grbl.garble(*[f"<{state}|MPos:100.600,79.600,5.000|FS:0,0>"] * 5)
        with pytest.raises(RigError, match="garbled status reports in a row") as caught:
            rig.status()
        assert all(c.isprintable() for c in str(caught.value))
        grbl.set_state("Bogus")  # a word that stays: one line saying so
        with pytest.raises(RigError, match=r"5 garbled .* a state this program does not know \('Bogus'\)"):
            rig.wait_until_at((100.6, 79.6, 5.0), 30.0)


def test_a_work_offset_read_once_is_not_trusted(grbl) -> None:
    """GRBL sends WCO every 10-30 reports (grbl/report.c). One flipped bit in it made the start point z 1.00
    while the tip was at 5.00, and the next move pressed into the skin. A new offset counts once a second
    report carries the same."""
    with GcodeRig(grbl.port, LIMITS) as rig:
        assert rig.status().xyz_mm == pytest.approx((100.6, 79.6, 5.0))
        grbl.garble("<Idle|MPos:100.600,79.600,5.000|FS:0,0|WCO:0.000,0.000,4.000>")
        for _ in range(25):  # the flipped offset, then the true one every 10th report
            assert rig.status().xyz_mm == pytest.approx((100.6, 79.6, 5.0))


def test_a_changed_work_offset_is_adopted_when_two_reports_agree(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        assert rig.status().xyz_mm == pytest.approx((100.6, 79.6, 5.0))
        grbl.wco = (10.0, 0.0, 0.0)  # G92 on the machine: the machine position 10 mm further in x
        seen = [rig.status().xyz_mm[0] for _ in range(25)]
        assert seen[-1] == pytest.approx(100.6)  # adopted with its second report
        assert all(x == pytest.approx(100.6) or x == pytest.approx(110.6) for x in seen)


def test_polls_after_a_garbled_report_are_spaced_to_outlast_a_burst_of_noise() -> None:
    """The 5 polls after a garbled report went out within 2 ms, so 2 ms of noise on the line stopped a run;
    now they are spaced (20, 40, 80, 160 ms, on the rig's own clock): a 0.2 s burst is outlasted, and a
    line that stays garbled still ends in one line."""
    from optitac_edge.io.rigs.base import GarbledReport, Rig, RigStatus

    class NoisyLine(Rig):
        def __init__(self, burst_s: float) -> None:
            self.now, self.burst_s = 0.0, burst_s
            super().__init__(LIMITS, sleep=self._advance)

        def _advance(self, s: float) -> None:
            self.now += s

        def _status(self) -> RigStatus:
            if self.now < self.burst_s:
                raise GarbledReport("noise")
            return RigStatus("idle", (100.0, 80.0, 12.0))

        def _move(self, xyz, feed_mm_s) -> None:
            pass

        def _stop(self) -> None:
            pass

        def _close_internal(self) -> None:
            pass

    rig = NoisyLine(burst_s=0.2)
    assert rig.status().state == "idle" and rig.garbled_reports == 4
    assert rig.now == pytest.approx(0.3)
    with pytest.raises(RigError, match="5 garbled status reports in a row"):
        NoisyLine(burst_s=1.0).status()


def test_the_safety_door_stops_the_tip_and_it_is_lifted_once_the_door_is_closed(grbl) -> None:
    """Door:0 / Door:1 were not taken as stopped: the retract waited 10 s for a stop and left the tip 3 mm deep.
    Now the retract waits for the door (GRBL: a reset once stopped keeps the position and drops the held move,
    grbl/motion_control.c mc_reset), and lifts once it is closed."""
    import threading

    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.move_to((100.0, 80.0, 8.0))
        rig.wait_until_at((100.0, 80.0, 8.0), 5.0)
        grbl.speed = 1.0
        rig.move_to((100.0, 80.0, -1.0))  # 0.9 s down at 10 mm/s
        grbl.open_door()
        threading.Timer(0.5, grbl.close_door).start()
        rig.retract()
        assert not grbl.in_door and "ALARM:3" not in "".join(grbl.lines)
        assert grbl.position() == pytest.approx((100.0, 80.0, 12.0))


def test_a_door_left_open_is_one_line_and_nothing_moves(grbl) -> None:
    with GcodeRig(grbl.port, LIMITS) as rig:
        rig.door_wait_s = 0.5
        rig.move_to((100.0, 80.0, 3.0))
        rig.wait_until_at((100.0, 80.0, 3.0), 5.0)
        grbl.open_door()
        moves = len([line for line in grbl.lines if line.startswith("G1")])
        with pytest.raises(RigError, match=r"safety door is open.*the tip was not lifted: close the door"):
            rig.retract()
        assert len([line for line in grbl.lines if line.startswith("G1")]) == moves
        assert grbl.position() == pytest.approx((100.0, 80.0, 3.0))


def test_a_slides_truth_velocity_is_the_rigs_whatever_the_cameras_pace(tmp_path) -> None:
    """Poses polled at loop time were divided by the camera's frame times: when the loop falls behind the
    camera (here each frame's poll sees 50 ms of the machine's motion, the frames are 1/60 s apart) the truth
    velocity came out 3x too high (30-50 % high on a busy machine, 6x on the 2 mm/s slide). Now each pose
    keeps the time it was read (the rig's clock), and the velocity is the machine's."""
    out = tmp_path / "slide"
    settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=5)
    grbl = FakeGrbl(speed=1.0, tick_s=0.05)
    try:
        camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
        bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
        with GcodeRig(grbl.port, LIMITS, clock_ns=grbl.now_ns) as rig:
            Collector(camera, rig, bundle, settings, prompt=lambda line: None).run("slide", out, limit=2)
    finally:
        grbl.close()
    truth = Recording(out).truth
    assert truth.motion is not None and truth.vx_mm_s is not None and truth.vy_mm_s is not None
    sliding = truth.motion == "sliding"
    speeds = np.hypot(truth.vx_mm_s[sliding], truth.vy_mm_s[sliding])
    assert sliding.sum() >= 10
    # the 2 mm/s slide and the 20 mm/s one at the rig's 10 mm/s limit, each row within 5 %
    assert all(abs(v - 2.0) < 0.1 or abs(v - 10.0) < 0.5 for v in speeds), np.round(speeds, 2)
    assert (np.abs(speeds - 2.0) < 0.1).sum() >= 5 and (np.abs(speeds - 10.0) < 0.5).sum() >= 2


# -- issue 52 §3: the settings that change reports, a long hold (against GRBL 1.1h's source, tests/fakes/grbl.py)


@pytest.mark.parametrize(("inches", "mpos"), [(True, True), (True, False), (False, False)])
def test_reports_in_inches_or_work_positions_are_read_as_millimetres(inches, mpos) -> None:
    """``$13=1``: every position read 25.4x too small before (the tip at (100.6, 79.6, 5.0) said (3.96, 3.13,
    0.20)); ``$10`` without MPos: work positions."""
    machine = FakeGrbl(speed=20.0, report_inches=inches, report_mpos=mpos, wco=(10.0, -5.0, 2.0))
    try:
        with GcodeRig(machine.port, LIMITS) as rig:
            assert rig.report_unit_mm == (25.4 if inches else 1.0) and rig.settings[10] == str(int(mpos))
            assert rig.status().xyz_mm == pytest.approx((100.6, 79.6, 5.0), abs=2e-3)
            rig.move_to((101.0, 80.0, 4.0))
            rig.wait_until_at((101.0, 80.0, 4.0), timeout_s=30.0)
            rig.retract()
            assert machine.position()[2] == pytest.approx(LIMITS.safe_z_mm)
            # inches: 4 decimals (2.5 um), WPos and WCO each rounded
            assert rig.status().xyz_mm == pytest.approx((101.0, 80.0, LIMITS.safe_z_mm), abs=6e-3)
    finally:
        machine.close()


def test_a_controller_whose_settings_do_not_say_its_units_is_refused_in_one_line(grbl, monkeypatch) -> None:
    real = grbl._line

    def no_units(text):
        if text == "$$":
            grbl._send(b"$0=10\r\nok\r\n")
            return
        real(text)

    monkeypatch.setattr(grbl, "_line", no_units)
    with pytest.raises(RigError, match=r"do not say whether it reports millimetres or inches \(\$13 = None\)"):
        GcodeRig(grbl.port, LIMITS)


def test_a_hold_that_settles_in_15_s_is_waited_for_then_reset_and_lifted() -> None:
    """Before: the CLI gave up after 10 s without a reset; the rest of the move stayed queued (a cycle start
    would resume it into the skin). On the fake's virtual clock (tick_s): 15 s of deceleration in ~0.4 s."""
    machine = FakeGrbl(speed=1.0, tick_s=0.05, hold_s=15.0)
    try:
        with GcodeRig(machine.port, LIMITS, clock_ns=machine.now_ns) as rig:
            rig.move_to((100.6, 79.6, -2.0), 0.2)  # slow: 35 s to go, stopped mid-way
            for _ in range(3):
                rig.status()
            rig.retract()
            assert machine.state == "Idle"  # reset only once stopped: no ALARM:3
            assert grbl_z(machine) == pytest.approx(LIMITS.safe_z_mm)
            assert rig.status().xyz_mm[2] == pytest.approx(LIMITS.safe_z_mm)
            before = machine.position()
            machine._realtime(b"~")  # the machine's cycle-start button: nothing is left to resume
            assert machine.position() == before
    finally:
        machine.close()


def test_a_hold_that_never_completes_is_reset_all_the_same(monkeypatch) -> None:
    """A deceleration longer than HOLD_MAX_S of the machine's time: reset all the same (GRBL then loses the
    position, ALARM:3, grbl/motion_control.c mc_reset), said in one line with what to do; nothing is left
    queued for a cycle start."""
    from optitac_edge.io.rigs import gcode

    monkeypatch.setattr(gcode, "HOLD_MAX_S", 3.0)
    machine = FakeGrbl(speed=1.0, tick_s=0.05, hold_s=1000.0)
    try:
        with GcodeRig(machine.port, LIMITS, clock_ns=machine.now_ns) as rig:
            rig.move_to((100.6, 79.6, -2.0), 0.2)
            rig.status()
            with pytest.raises(RigError, match=r"ALARM:3 \(reset while in motion\); the machine's position is lost"):
                rig.retract()
            assert b"\x18" in machine.realtime
            before = machine.position()
            machine._realtime(b"~")
            assert machine.position() == before  # the rest of the move was dropped by the reset
    finally:
        machine.close()


def grbl_z(machine: FakeGrbl) -> float:
    return machine.position()[2]


class _FailsAt:
    """A camera whose frame ``n`` raises a rig error (an ALARM:2 mid-slide, a lost cable...)."""

    def __init__(self, camera: SimCamera, n: int) -> None:
        self.camera, self.n, self.frames = camera, n, 0

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def read(self, timeout_s=1.0):
        self.frames += 1
        if self.frames == self.n:
            raise RigError("the first error")
        return self.camera.read(timeout_s)


@pytest.mark.parametrize("signals", [1, 2])
def test_a_signal_during_the_retract_after_an_error(grbl, tmp_path, monkeypatch, signals) -> None:
    """Before: SIGTERM during the retract after an error cut it short, and the only line was 'interrupted by
    SIGTERM: tip retracted' with the tip unmoved and the first error lost. Now the first signal is held until
    the retract is done; a second stops it, and the line says so with where the machine says the tip is."""
    import os
    import signal as signals_module

    from optitac_edge.cli import _interrupt_on_signals

    settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
    camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
    real_stop = GcodeRig._stop

    def signalled_stop(self):
        for _ in range(signals):
            os.kill(os.getpid(), signals_module.SIGTERM)
            time_module.sleep(0.01)  # each handled before the next
        real_stop(self)

    monkeypatch.setattr(GcodeRig, "_stop", signalled_stop)
    lines: list[str] = []
    restore = _interrupt_on_signals()
    try:
        with GcodeRig(grbl.port, LIMITS) as rig, pytest.raises(RigError) as caught:
            Collector(_FailsAt(camera, 60), rig, bundle, settings, prompt=lines.append).run("seen", tmp_path / "r",
                                                                                            limit=3)
    finally:
        for signum, previous in restore.items():
            signals_module.signal(signum, previous)
    text = str(caught.value)
    assert text.startswith("the first error")
    if signals == 1:
        assert text == "the first error" and grbl.position()[2] == pytest.approx(LIMITS.safe_z_mm)
        assert lines[-1] == f"retracted the tip to z = {LIMITS.safe_z_mm:g} mm"
    else:
        assert "; the tip was NOT retracted: a second signal stopped the retract; the machine last reported it at" \
            in text and "jog it up clear of the skin" in text
        assert not lines[-1].startswith("retracted")


#: The retract's phases (io/rigs/gcode.py): feed hold and its wait, the reset and its banner, the lift's G1 Z,
#: the wait for two reports at safe z.
RETRACT_PHASES = ("_hold", "_reset", "_lift", "wait_until_at")


@pytest.mark.parametrize("signals", [1, 2])
@pytest.mark.parametrize("phase", RETRACT_PHASES)
def test_a_signal_in_every_phase_of_the_retract(grbl, tmp_path, monkeypatch, phase, signals) -> None:
    """The first signal in any phase of the retract after an error is held until the tip is at safe z (by the
    machine's report); a second stops it there, and the line keeps the first error and says where the machine
    last reported the tip. (The test above signals at the start of the stop only.)"""
    import os
    import signal as signals_module

    from optitac_edge.cli import _interrupt_on_signals
    from optitac_edge.io.rigs.base import Rig

    settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
    camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
    bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
    retracting = [False]
    sent = [0]
    real_stop = GcodeRig._stop
    owner = Rig if phase == "wait_until_at" else GcodeRig
    real_phase = getattr(owner, phase)

    def stop(self):
        retracting[0] = True
        real_stop(self)

    def signalled(self, *args, **kwargs):
        if retracting[0] and not sent[0]:
            for _ in range(signals):
                sent[0] += 1
                os.kill(os.getpid(), signals_module.SIGTERM)
                time_module.sleep(0.01)  # each handled before the next
        return real_phase(self, *args, **kwargs)

    monkeypatch.setattr(GcodeRig, "_stop", stop)
    monkeypatch.setattr(owner, phase, signalled)
    lines: list[str] = []
    restore = _interrupt_on_signals()
    try:
        with GcodeRig(grbl.port, LIMITS) as rig, pytest.raises(RigError) as caught:
            Collector(_FailsAt(camera, 60), rig, bundle, settings, prompt=lines.append).run("seen", tmp_path / "r",
                                                                                            limit=3)
    finally:
        for signum, previous in restore.items():
            signals_module.signal(signum, previous)
    assert sent[0] == signals  # the phase was reached during the retract
    text = str(caught.value)
    assert text.startswith("the first error")
    if signals == 1:
        assert text == "the first error" and grbl.position()[2] == pytest.approx(LIMITS.safe_z_mm)
        assert lines[-1] == f"retracted the tip to z = {LIMITS.safe_z_mm:g} mm"
    else:
        assert "; the tip was NOT retracted: a second signal stopped the retract; the machine last reported it at" \
            in text and "jog it up clear of the skin" in text, text
        assert not lines[-1].startswith("retracted")


def test_a_fresh_start_with_the_tip_in_the_skin_lifts_it_before_any_rest_frame(tmp_path) -> None:
    """Before: a fresh start took the tip's position as rest, 0.5 mm in the skin, and the board calibrated its
    baseline from those pressed frames."""
    machine = FakeGrbl(speed=20.0, start=(100.6, 79.6, MOUNT.surface_z_mm - 0.5))
    try:
        camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(machine, MOUNT))
        bundle = calibrate_fibers([SimCamera(realtime=False).read().frame.copy() for _ in range(8)], "gray")
        depths: list[float] = []

        class Watched:
            def __getattr__(self, name):
                return getattr(camera, name)

            def read(self, timeout_s=1.0):
                depths.append(MOUNT.surface_z_mm - machine.position()[2])
                return camera.read(timeout_s)

        settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
        with GcodeRig(machine.port, LIMITS) as rig:
            Collector(Watched(), rig, bundle, settings, prompt=lambda line: None).run("seen", tmp_path / "r", limit=1)
        assert depths[:settings.initial_rest_frames] == [MOUNT.surface_z_mm - LIMITS.safe_z_mm] * 8  # at safe z
        assert next(line for line in machine.lines if line.startswith("G1")) == "G1 Z12.000 F600.0"
    finally:
        machine.close()


@pytest.mark.parametrize(("experiment", "event"), [("seen", "door"), ("slide", "door"), ("slide", "alarm2")])
def test_a_door_or_a_soft_limit_with_the_tip_in_the_skin_ends_at_safe_z(tmp_path, experiment, event) -> None:
    """Issue 52 §3: a door (0x84) mid-press and mid-slide, ALARM:2 mid-slide, on GRBL 1.1h's behaviour
    (tests/fakes/grbl.py: a door holds the feed, Door:1 while open, a reset once stopped keeps the position;
    ALARM:2 keeps it, GRBL silent until a reset after [MSG:Reset to continue]). The collection ends with the
    event's line and the tip at the safe height as the machine itself reports it."""
    import threading

    grbl = FakeGrbl(speed=4.0, tick_s=1 / 60)
    fired: list[tuple[float, float, float]] = []
    try:
        camera = SimCamera(realtime=False, clock=VirtualClock(), program=GrblSkin(grbl, MOUNT))
        bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(8)], "gray")
        last = [grbl.position()]

        class Event:
            def __getattr__(self, name):
                return getattr(camera, name)

            def read(self, timeout_s=1.0):
                pos = grbl.position()
                deep = MOUNT.surface_z_mm - pos[2] > 0.3
                sliding = math.dist(pos[:2], last[0][:2]) > 1e-3
                last[0] = pos
                if not fired and deep and (experiment == "seen" or sliding):
                    fired.append(pos)
                    if event == "door":
                        grbl.open_door()
                        threading.Timer(0.5, grbl.close_door).start()
                    else:
                        grbl.inject_alarm(2)
                return camera.read(timeout_s)

        settings = CollectSettings(initial_rest_frames=8, rest_frames=4, hold_frames=4)
        lines: list[str] = []
        with GcodeRig(grbl.port, LIMITS, clock_ns=grbl.now_ns) as rig, pytest.raises(RigError) as caught:
            Collector(Event(), rig, bundle, settings, prompt=lines.append).run(experiment, tmp_path / "r", limit=3)
        assert fired, "the event never came with the tip in the skin"
        assert ("door" in str(caught.value)) if event == "door" else ("ALARM:2" in str(caught.value))
        assert "NOT retracted" not in str(caught.value)
        assert lines[-1] == f"retracted the tip to z = {LIMITS.safe_z_mm:g} mm"
        assert grbl.position()[2] == pytest.approx(LIMITS.safe_z_mm) and not grbl.in_door
    finally:
        grbl.close()
