"""The Universal Robots rig backend against a fake of ur_rtde's RTDEControlInterface / RTDEReceiveInterface."""

from __future__ import annotations

import pytest

from optitac_edge.errors import RigError
from optitac_edge.io.rigs.base import RigLimits
from optitac_edge.io.rigs.ur import UrRig

LIMITS = RigLimits(x_mm=(200.0, 600.0), y_mm=(-200.0, 200.0), z_mm=(50.0, 300.0), feed_mm_s=20.0, safe_z_mm=250.0)


class FakeUr:
    """Both interfaces in one: a TCP that moves a tenth of the way per poll (moveL asynchronous)."""

    def __init__(self) -> None:
        self.pose = [0.4, 0.0, 0.2, 3.14, 0.0, 0.0]
        self.target: list[float] | None = None
        self.calls: list[tuple] = []
        self.protective = False

    def moveL(self, pose, speed, acceleration, asynchronous):
        self.calls.append(("moveL", tuple(round(v, 6) for v in pose), speed, asynchronous))
        self.target = list(pose)
        return True

    def getAsyncOperationProgress(self):
        if self.target is None:
            return -1
        self.pose[:3] = [p + 0.5 * (t - p) if abs(t - p) > 1e-6 else t for p, t in zip(self.pose[:3], self.target[:3])]
        if all(abs(p - t) < 1e-6 for p, t in zip(self.pose[:3], self.target[:3])):
            self.pose[:3], self.target = self.target[:3], None
            return -1
        return 0

    def stopL(self, a):
        self.calls.append(("stopL", a))
        self.target = None

    def getActualTCPPose(self):
        return list(self.pose)

    def isProtectiveStopped(self):
        return self.protective

    def isEmergencyStopped(self):
        return False


def test_moves_keep_the_tool_orientation_and_report_mm() -> None:
    ur = FakeUr()
    rig = UrRig("10.0.0.2", LIMITS, control=ur, receive=ur)
    assert rig.status().xyz_mm == pytest.approx((400.0, 0.0, 200.0))
    rig.move_to((410.0, 5.0, 180.0), 10.0)
    assert ur.calls[-1] == ("moveL", (0.41, 0.005, 0.18, 3.14, 0.0, 0.0), 0.01, True)
    for _ in range(100):
        if rig.status().state == "idle":
            break
    assert rig.status().xyz_mm == pytest.approx((410.0, 5.0, 180.0))


def test_limits_protective_stop_and_retract() -> None:
    ur = FakeUr()
    rig = UrRig("10.0.0.2", LIMITS, control=ur, receive=ur)
    with pytest.raises(RigError, match="outside the limits"):
        rig.move_to((400.0, 0.0, 10.0))
    assert not ur.calls
    rig.move_to((400.0, 0.0, 100.0))
    rig.sleep = lambda s: None
    rig.retract()
    assert ("stopL", 2.0) in ur.calls and rig.status().xyz_mm[2] == pytest.approx(250.0)
    ur.protective = True
    with pytest.raises(RigError, match="protective or emergency stop"):
        rig.status()


def test_without_ur_rtde_the_extra_is_named(tmp_path, capsys) -> None:
    import sys

    from optitac_edge.cli import main

    board = tmp_path / "b.toml"
    board.write_text("[rig]\nx_min = 0.0\nx_max = 1.0\ny_min = 0.0\ny_max = 1.0\nz_min = 0.0\nz_max = 1.0\n")
    sys.modules["rtde_control"] = None  # type: ignore[assignment]  # as if not installed
    try:
        assert main(["collect", "seen", "--board", str(board), "--rig", "ur://10.0.0.2", "-o", str(tmp_path / "r")]) == 2
    finally:
        del sys.modules["rtde_control"]
    assert "pip install 'optitac-edge[ur]'" in capsys.readouterr().err
