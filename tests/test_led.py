"""LED ring on a fake smbus2 bus (exact PCA9685 register writes) and the saturation search."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from optitac_edge.calibration.led_brightness import adjust_brightness_for_saturation, fiber_peak
from optitac_edge.config import LedConfig
from optitac_edge.io import led as led_mod
from optitac_edge.io.led import LedError, LedRing, NoLed, channel_registers, prescale_for, pwm_period_us
from optitac_edge.service.wiring import open_led


class FakeBus:
    """Records writes like smbus2.SMBus; can be told to fail."""

    def __init__(self, fail: bool = False) -> None:
        self.calls: list[tuple] = []
        self.fail = fail
        self.closed = False

    def write_byte_data(self, addr, reg, value):
        if self.fail:
            raise OSError(121, "Remote I/O error")
        self.calls.append(("byte", addr, reg, value))

    def write_i2c_block_data(self, addr, reg, data):
        if self.fail:
            raise OSError(121, "Remote I/O error")
        self.calls.append(("block", addr, reg, list(data)))

    def close(self):
        self.closed = True


@pytest.fixture(autouse=True)
def _no_sleep(monkeypatch):
    monkeypatch.setattr(led_mod.time, "sleep", lambda s: None)


def test_init_sequence_and_brightness_registers():
    bus = FakeBus()
    ring = LedRing(bus, 0x40, [0, 3], 0.5, pwm_frequency_hz=1000)
    assert bus.calls == [
        ("byte", 0x40, 0x00, 0x30),  # MODE1: sleep + auto-increment
        ("byte", 0x40, 0xFE, 5),  # PRE_SCALE: round(25e6 / (4096 * 1000)) - 1
        ("byte", 0x40, 0x01, 0x04),  # MODE2: totem pole
        ("block", 0x40, 0x06, [0, 0, 0, 0x10]),  # ch 0 full off
        ("block", 0x40, 0x12, [0, 0, 0, 0x10]),  # ch 3 full off
        ("byte", 0x40, 0x00, 0x20),  # MODE1: wake, auto-increment
        ("block", 0x40, 0x06, [0, 0, 0x00, 0x08]),  # 0.5 -> OFF count 2048
        ("block", 0x40, 0x12, [0, 0, 0x00, 0x08]),
    ]
    assert ring.brightness == 0.5
    bus.calls.clear()
    ring.set_brightness(0.25)
    assert bus.calls == [("block", 0x40, 0x06, [0, 0, 0x00, 0x04]), ("block", 0x40, 0x12, [0, 0, 0x00, 0x04])]
    bus.calls.clear()
    ring.set_brightness(1.0)
    ring.set_brightness(0.0)
    assert bus.calls == [("block", 0x40, 0x06, [0, 0x10, 0, 0]), ("block", 0x40, 0x12, [0, 0x10, 0, 0]),
                         ("block", 0x40, 0x06, [0, 0, 0, 0x10]), ("block", 0x40, 0x12, [0, 0, 0, 0x10])]
    ring.close()


def test_invert_open_drain_and_frequency():
    bus = FakeBus()
    ring = LedRing(bus, 0x41, [15], 0.1, pwm_frequency_hz=1526, invert=True, open_drain=True)
    assert ("byte", 0x41, 0x01, 0x10) in bus.calls
    assert ("byte", 0x41, 0xFE, 3) in bus.calls
    assert bus.calls[-1] == ("block", 0x41, 0x06 + 4 * 15, [0, 0, 410 & 0xFF, 410 >> 8])
    assert ring.frequency_hz == pytest.approx(1525.88, abs=0.01)
    assert pwm_period_us(1526) == pytest.approx(655.36)


@pytest.mark.parametrize(("b", "regs"), [
    (0.0, [0, 0, 0, 0x10]), (1 / 4096, [0, 0, 1, 0]), (0.001, [0, 0, 4, 0]),
    (0.75, [0, 0, 0x00, 0x0C]), (4095 / 4096, [0, 0, 0xFF, 0x0F]), (1.0, [0, 0x10, 0, 0]),
])
def test_channel_registers(b, regs):
    assert channel_registers(b) == regs


def test_channel_registers_range():
    with pytest.raises(ValueError):
        channel_registers(1.01)
    assert prescale_for(24) == 253 and prescale_for(1) == 255 and prescale_for(1e6) == 3


def test_set_brightness_clamps():
    bus = FakeBus()
    with LedRing(bus, 0x40, [2], 0.0) as ring:
        ring.set_brightness(3.0)
        assert ring.brightness == 1.0 and bus.calls[-1] == ("block", 0x40, 0x0E, [0, 0x10, 0, 0])


def test_close_turns_off_once_and_is_idempotent():
    bus = FakeBus()
    ring = LedRing(bus, 0x40, [1], 0.8)
    bus.calls.clear()
    ring.close()
    ring.close()
    assert bus.calls == [("block", 0x40, 0x0A, [0, 0, 0, 0x10])]
    assert ring.closed and not bus.closed  # a bus passed in is left open
    with pytest.raises(LedError, match="closed"):
        ring.set_brightness(0.5)


def test_context_manager_turns_off_on_error():
    bus = FakeBus()
    with pytest.raises(RuntimeError), LedRing(bus, 0x40, [0], 0.8):
        raise RuntimeError("boom")
    assert bus.calls[-1] == ("block", 0x40, 0x06, [0, 0, 0, 0x10])


def test_no_answer_is_a_led_error():
    with pytest.raises(LedError, match="0x40: no answer"):
        LedRing(FakeBus(fail=True), 0x40, [0], 0.5)


def test_close_never_raises():
    bus = FakeBus()
    ring = LedRing(bus, 0x40, [0], 0.5)
    bus.fail = True
    ring.close()
    assert ring.closed


def test_bus_number_opens_smbus2_lazily(monkeypatch):
    opened = []

    class FakeSMBus(FakeBus):
        def __init__(self, number):
            super().__init__()
            opened.append(number)

    fake_module = type(sys)("smbus2")
    fake_module.SMBus = FakeSMBus
    monkeypatch.setitem(sys.modules, "smbus2", fake_module)
    ring = LedRing(3, 0x40, [0], 0.5)
    assert opened == [3]
    bus = ring._bus
    ring.close()
    assert bus.closed  # a bus it opened is closed


def test_missing_smbus2_says_which_extra_installs_it(monkeypatch):
    from optitac_edge.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "smbus2", None)
    with pytest.raises(MissingExtraError, match=r"smbus2, which is not installed: pip install 'optitac-edge\[board\]'"):
        LedRing(1, 0x40, [0], 0.5)


def test_bad_arguments():
    with pytest.raises(ValueError):
        LedRing(FakeBus(), 0x40, [16], 0.5)
    with pytest.raises(ValueError):
        LedRing(FakeBus(), 0x90, [0], 0.5)


def test_open_led_from_config(monkeypatch):
    from dataclasses import replace

    from optitac_edge.config import BoardConfig

    assert isinstance(open_led(BoardConfig()), NoLed)
    bus = FakeBus()
    monkeypatch.setattr(LedRing, "_open_bus", staticmethod(lambda number: bus if number == 3 else None))
    board = replace(BoardConfig(), led=LedConfig(enabled=True, i2c_bus=3, address=0x44, channels=(5,), brightness=0.25))
    with open_led(board) as ring:
        assert isinstance(ring, LedRing) and ring.address == 0x44
        assert bus.calls[-1] == ("block", 0x44, 0x06 + 20, [0, 0, 0, 4])
    with NoLed() as none:
        none.set_brightness(0.3)
        assert none.brightness == 0.3


# ---------------------------------------------------------------- saturation search


class FakeCamera:
    """Peak gray level of the fibers: gain * brightness, clipped at 255 (plus dark level)."""

    def __init__(self, gain: float, dark: float = 5.0) -> None:
        self.gain, self.dark = gain, dark
        self.set_to: list[float] = []

    def __call__(self, brightness: float) -> float:
        self.set_to.append(brightness)
        return min(255.0, self.dark + self.gain * brightness)


@pytest.mark.parametrize("gain", [300.0, 450.0, 1000.0, 5000.0])
def test_adjust_finds_bright_unsaturated_level(gain):
    cam = FakeCamera(gain)
    result = adjust_brightness_for_saturation(cam, max_peak=230, steps=8)
    assert result.ok
    assert result.peak <= 230 and cam(result.brightness) == result.peak
    best = (230 - cam.dark) / gain
    assert result.brightness <= best
    assert result.brightness >= best * 0.9 or result.peak >= 230 - 8  # close to the limit
    assert cam.set_to[-2] == result.brightness  # the LEDs were left at the answer
    assert result.measurements <= 10


def test_adjust_keeps_start_when_not_saturated():
    cam = FakeCamera(100.0)
    result = adjust_brightness_for_saturation(cam, start=0.8)
    assert (result.brightness, result.measurements, result.ok) == (0.8, 1, True)
    assert cam.set_to == [0.8]


def test_adjust_reports_hopeless_saturation():
    cam = FakeCamera(1e9, dark=240.0)  # saturated even when dark
    result = adjust_brightness_for_saturation(cam, low=0.05, steps=4)
    assert not result.ok and result.brightness == 0.05 and cam.set_to[-1] == 0.05


def test_adjust_with_a_real_ring_and_fiber_peak():
    bus = FakeBus()
    rng = np.random.default_rng(0)
    fibers = rng.uniform(0.6, 1.0, size=(40, 40))  # relative fiber brightness
    mask = np.zeros((40, 40), bool)
    mask[5:35, 5:35] = True
    with LedRing(bus, 0x40, [0], 1.0) as ring:
        def read_peak(b: float) -> float:
            ring.set_brightness(b)
            frame = np.clip(fibers * 600.0 * ring.brightness, 0, 255).astype(np.uint8)
            return fiber_peak(frame, mask, 99.9)

        result = adjust_brightness_for_saturation(read_peak, max_peak=230)
        assert result.ok and 200 <= result.peak <= 230
        assert ring.brightness == result.brightness
    assert fiber_peak(np.zeros((2, 2), np.uint8), np.zeros((2, 2), bool)) == 0.0


def test_adjust_validates_range():
    with pytest.raises(ValueError):
        adjust_brightness_for_saturation(lambda b: 0.0, start=0.2, low=0.5)
