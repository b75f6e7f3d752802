"""Install the fake camera stacks for a test (through ``monkeypatch``, undone afterwards)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

FAKES = Path(__file__).resolve().parent


def install_picamera2(monkeypatch, **hardware):
    """Make ``import picamera2`` find the fake; returns its ``HARDWARE`` (fresh, with ``hardware`` set)."""
    monkeypatch.syspath_prepend(str(FAKES))
    monkeypatch.delitem(sys.modules, "picamera2", raising=False)
    fake = importlib.import_module("picamera2")
    assert Path(fake.__file__).resolve().parent.parent == FAKES, "a real picamera2 shadows the fake"
    hw = fake.reset()
    for key, value in hardware.items():
        setattr(hw, key, value)
    return hw


def install_cv2(monkeypatch, **device):
    """Point the v4l2 backend at the fake OpenCV with one device; returns the device."""
    monkeypatch.syspath_prepend(str(FAKES))
    fake_cv2 = importlib.import_module("fake_cv2")
    from optitac_edge.io.cameras import v4l2

    monkeypatch.setattr(v4l2, "cv2", fake_cv2)
    monkeypatch.setattr(fake_cv2, "DEVICES", {})
    monkeypatch.setattr(fake_cv2, "BUILD_GSTREAMER", False)
    return fake_cv2.add_device(fake_cv2.FakeDevice(**device))
