"""The sensor's LED ring, driven by a PCA9685 16-channel 12-bit PWM chip over I2C.

smbus2 is imported only when a ring is opened by bus number; anything with
``write_byte_data(addr, reg, value)`` and ``write_i2c_block_data(addr, reg, data)``
(an ``smbus2.SMBus``, or a fake in tests) can be passed instead.

The LEDs stay at the set brightness while the ring is open and are switched off by
:meth:`LedRing.close` (idempotent; also on leaving a ``with`` block). The chip's
oscillator keeps running so other channels, if any, are not disturbed.

The brightness search run at calibration is
:func:`optitac_edge.calibration.led_brightness.adjust_brightness_for_saturation`;
the ring a board's ``[led]`` section describes is opened through :data:`LEDS`
(:func:`optitac_edge.service.wiring.open_led`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from optitac_edge.errors import OptiTacError, missing_extra
from optitac_edge.fields import boolean, channel_list, choice, integer, number, setting
from optitac_edge.io.device import BoardView
from optitac_edge.io.registry import Registry

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

# PCA9685 registers and bits (NXP datasheet, rev. 4, section 7.3)
MODE1 = 0x00
MODE2 = 0x01
LED0_ON_L = 0x06  # channel n: LED0_ON_L + 4 * n .. + 3 = ON_L, ON_H, OFF_L, OFF_H
ALL_LED_ON_L = 0xFA
ALL_LED_OFF_H = 0xFD
PRE_SCALE = 0xFE

MODE1_RESTART = 0x80
MODE1_AI = 0x20  # register auto-increment (needed for the 4-byte block writes)
MODE1_SLEEP = 0x10  # oscillator off; PRE_SCALE can only be written while asleep
MODE1_ALLCALL = 0x01
MODE2_INVRT = 0x10
MODE2_OUTDRV = 0x04  # totem-pole outputs (open-drain when clear)
FULL = 0x10  # bit 4 of ON_H (full on) / OFF_H (full off; wins over full on)

OSC_HZ = 25_000_000
COUNTS = 4096


class LedError(OptiTacError):
    """The LED driver cannot be opened or does not answer."""


def led_driver(value: object, from_text: bool) -> str:
    """A name of the LED registry (:data:`LEDS`, the one list of drivers)."""
    return choice(*LEDS)(value, from_text)


@dataclass(frozen=True)
class LedConfig:
    enabled: bool = setting(boolean, False, "drive an LED ring through an I2C PWM chip")
    driver: str = setting(led_driver, "pca9685", "LED driver chip: pca9685")
    i2c_bus: int = setting(integer(0, 255), 1, "I2C bus number (/dev/i2c-N)")
    address: int = setting(integer(0x03, 0x77, "a 7-bit I2C address"), 0x40, "I2C address of the chip")
    channels: tuple[int, ...] = setting(channel_list, (0,), "PWM channels the LEDs are on")
    brightness: float = setting(number(0, 1), 0.5, "LED brightness, 0..1 (duty cycle)")
    pwm_frequency_hz: int = setting(integer(24, 1526), 1000, "PWM frequency, Hz")
    invert: bool = setting(boolean, False, "invert outputs (LEDs wired to V+ without a driver)")
    open_drain: bool = setting(boolean, False, "open-drain outputs instead of totem pole")
    adjust_at_calibration: bool = setting(boolean, True, "lower brightness at calibration until no fiber saturates")
    max_peak: int = setting(integer(1, 255), 230, "highest allowed fiber peak, gray level")
    peak_percentile: float = setting(number(50, 100), 99.9, "percentile of fiber pixels taken as the peak")


class I2CBus(Protocol):
    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...

    def write_i2c_block_data(self, i2c_addr: int, register: int, data: list[int]) -> None: ...


def prescale_for(frequency_hz: float) -> int:
    """PRE_SCALE value for a PWM frequency (datasheet eq. 1), clamped to the chip's 3..255."""
    return max(3, min(255, round(OSC_HZ / (COUNTS * frequency_hz)) - 1))


def pwm_period_us(frequency_hz: float) -> float:
    """The real PWM period the chip produces for a requested frequency, µs."""
    return (prescale_for(frequency_hz) + 1) * COUNTS / OSC_HZ * 1e6


def channel_registers(brightness: float) -> list[int]:
    """The four bytes ON_L, ON_H, OFF_L, OFF_H for a brightness in 0..1.

    0 is full off, 1 is full on (no PWM edges at all), anything between is a
    duty cycle of ``round(brightness * 4096)`` counts starting at count 0.
    """
    if not 0.0 <= brightness <= 1.0:
        raise ValueError(f"brightness must be in 0..1, got {brightness!r}")
    counts = round(brightness * COUNTS)
    if counts <= 0:
        return [0, 0, 0, FULL]
    if counts >= COUNTS:
        return [0, FULL, 0, 0]
    return [0, 0, counts & 0xFF, counts >> 8]


class LedRing:
    """LEDs on one or more PCA9685 channels, all at the same brightness.

    Parameters
    ----------
    bus : int or I2CBus
        I2C bus number (opens ``smbus2.SMBus(bus)``, closed again by :meth:`close`)
        or an open bus object (left open).
    address : int
        7-bit I2C address of the chip (0x40 by default on most boards).
    channels : iterable of int
        PWM channels 0..15 the LEDs are on.
    brightness : float
        Initial brightness, 0..1.
    pwm_frequency_hz : float
        PWM frequency (24..1526 Hz; the chip rounds it, see :func:`pwm_period_us`).
    invert, open_drain : bool
        Output configuration (MODE2 INVRT, OUTDRV cleared).

    Raises
    ------
    LedError
        If smbus2 is missing or the chip does not answer.
    """

    @classmethod
    def from_config(cls, section: LedConfig, board: BoardView) -> Self:
        """The ring a board's ``[led]`` section describes: its bus, address, channels, brightness and outputs."""
        return cls(section.i2c_bus, section.address, section.channels, section.brightness,
                   pwm_frequency_hz=section.pwm_frequency_hz, invert=section.invert, open_drain=section.open_drain)

    def __init__(self, bus: int | I2CBus, address: int = 0x40, channels: Iterable[int] = (0,),
                 brightness: float = 0.5, *, pwm_frequency_hz: float = 1000.0, invert: bool = False,
                 open_drain: bool = False) -> None:
        self.address = int(address)
        self.channels = tuple(int(c) for c in channels)
        if not self.channels or any(not 0 <= c <= 15 for c in self.channels):
            raise ValueError(f"channels must be a non-empty list of 0..15, got {self.channels!r}")
        if not 0x03 <= self.address <= 0x77:
            raise ValueError(f"address must be a 7-bit I2C address, got {address!r}")
        self._lock = threading.Lock()
        self._closed = False
        self._owns_bus = isinstance(bus, int)
        self._bus: Any = self._open_bus(bus) if isinstance(bus, int) else bus
        self.brightness = 0.0
        self.prescale = prescale_for(pwm_frequency_hz)
        mode2 = (0 if open_drain else MODE2_OUTDRV) | (MODE2_INVRT if invert else 0)
        try:
            self._bus.write_byte_data(self.address, MODE1, MODE1_SLEEP | MODE1_AI)
            self._bus.write_byte_data(self.address, PRE_SCALE, self.prescale)
            self._bus.write_byte_data(self.address, MODE2, mode2)
            for ch in self.channels:  # dark before the oscillator starts
                self._write_channel(ch, [0, 0, 0, FULL])
            self._bus.write_byte_data(self.address, MODE1, MODE1_AI)
            time.sleep(0.0005)  # oscillator start-up, 500 µs
        except OSError as exc:
            self._close_bus()
            self._closed = True
            raise LedError(f"LED driver at I2C 0x{self.address:02x}: no answer ({exc.strerror or exc})") from None
        self.set_brightness(brightness)

    @staticmethod
    def _open_bus(number: int) -> Any:
        try:
            from smbus2 import SMBus
        except ImportError:
            raise missing_extra("smbus2", "the LED ring") from None
        try:
            return SMBus(number)
        except OSError as exc:
            raise LedError(f"cannot open /dev/i2c-{number} ({exc.strerror or exc})") from None

    @property
    def frequency_hz(self) -> float:
        """The PWM frequency the chip really runs at."""
        return OSC_HZ / (COUNTS * (self.prescale + 1))

    def _write_channel(self, channel: int, data: list[int]) -> None:
        self._bus.write_i2c_block_data(self.address, LED0_ON_L + 4 * channel, data)

    def set_brightness(self, brightness: float) -> None:
        """Set every channel to ``brightness`` (0..1; clamped).

        Raises
        ------
        LedError
            If the ring is closed or the chip does not answer.
        """
        b = min(max(float(brightness), 0.0), 1.0)
        data = channel_registers(b)
        with self._lock:
            if self._closed:
                raise LedError("LED ring is closed")
            try:
                for ch in self.channels:
                    self._write_channel(ch, data)
            except OSError as exc:
                raise LedError(f"LED driver at I2C 0x{self.address:02x}: write failed "
                               f"({exc.strerror or exc})") from None
            self.brightness = b

    def close(self) -> None:
        """Switch the LEDs off and release the bus (idempotent; never raises)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                for ch in self.channels:
                    self._write_channel(ch, [0, 0, 0, FULL])
            except OSError as exc:
                log.warning("LED ring: could not switch off (%s)", exc)
            self.brightness = 0.0
            self._close_bus()

    def _close_bus(self) -> None:
        if self._owns_bus:
            try:
                self._bus.close()
            except OSError:
                pass

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class NoLed:
    """Stands in for :class:`LedRing` on boards without one (``[led] enabled = false``)."""

    brightness = 1.0
    closed = False

    def set_brightness(self, brightness: float) -> None:
        self.brightness = min(max(float(brightness), 0.0), 1.0)

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- brightness vs. saturation


#: LED driver name (``[led] driver``) -> its class (python-can style lazy registry).
LEDS: Registry[LedRing] = Registry("LED driver", LedError, {"pca9685": "optitac_edge.io.led:LedRing"})


__all__ = ["LEDS", "LedConfig", "LedError", "LedRing", "NoLed", "channel_registers", "prescale_for",
           "pwm_period_us"]
