"""A baseline taken while the skin was pressed: the service started (or restarted, or was tared) during a
grasp. A press only darkens fibers, so fibers that stay brighter than their baseline after the release
show it; their baseline is raised to their light. Before, every frame after the release was a phantom
contact (the brightest fibers were taken for the LED's gain) and a new press at the same place was never
found, until a TARE."""

from __future__ import annotations

import logging
import threading

import numpy as np
import pytest
from fakes.list_camera import ListCamera

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.core.baseline import BRIGHT_HOLD_S, BrightFibers
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.options import ContactOptions
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

FPS = 240.0
PERIOD_NS = int(1e9 / FPS)
HOLD_FRAMES = int(BRIGHT_HOLD_S * FPS) + 1


def _press(x: float, y: float, size: float = 5.0, depth: float = 3.0) -> tuple[Indenter, ...]:
    return (Indenter("circle", x, y, 0.0, size, depth),)


@pytest.fixture(scope="module")
def sensor_and_bundle() -> tuple[SimulatedSensor, CalibrationBundle]:
    sensor = SimulatedSensor(seed=3, fps=FPS)
    return sensor, calibrate_fibers([sensor.frame() for _ in range(10)], "gray")


def _run(pipe: Pipeline, sensor: SimulatedSensor, phases: list[tuple[str, tuple[Indenter, ...], int]],
         tare_at: int | None = None) -> dict[str, list]:
    """Each phase's estimates (copies), frame by frame at 240 fps; the pipeline is reset at frame ``tare_at``."""
    out: dict[str, list] = {}
    k = 0
    for name, indenters, frames in phases:
        for _ in range(frames):
            if k == tare_at:
                pipe.reset_baseline()
            est = pipe.process_recorded(sensor.frame(indenters, t_s=k / FPS), k * PERIOD_NS).primary
            out.setdefault(name, []).append((est.copy(), pipe.result.baseline_raised))
            k += 1
    return out


def _found_at(estimates: list, x: float, y: float, ramp: int = 10) -> bool:
    return all(e.contact and abs(e.x_mm - x) < 0.5 and abs(e.y_mm - y) < 0.5 for e, _ in estimates[ramp:])


@pytest.mark.parametrize(("size", "options"), [(5.0, None), (20.0, None), (5.0, ContactOptions.paper())],
                         ids=["5mm", "20mm", "paper-mode"])
def test_a_start_during_a_press_gives_no_phantom_after_the_release_and_finds_the_next_press_there(
        sensor_and_bundle, size, options):
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle, options)
    held = _press(0.0, 0.0, size)
    got = _run(pipe, sensor, [("held", held, 120), ("released", (), 600), ("again", held, 120), ("rest", (), 120)])
    assert not any(e.contact for e, _ in got["held"])  # taken into the baseline: nothing to see yet
    assert not any(e.contact for e, _ in got["released"])  # no phantom, not even before the raise
    raised = [i for i, (_, r) in enumerate(got["released"]) if r]
    assert raised and raised[0] <= HOLD_FRAMES  # within the hold of the release
    assert _found_at(got["again"], 0.0, 0.0)  # the same press again: found where it is, every frame
    assert not any(e.contact for e, _ in got["rest"])


def test_the_gain_reference_does_not_follow_an_estimate_it_held(sensor_and_bundle):
    """At the release a quarter of the fibers are brighter than their baseline: the frame's own gain estimate
    (the brightest cluster) jumps; it is held to the band, and must not become the reference."""
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle)
    _run(pipe, sensor, [("held", _press(0.0, 0.0), 120), ("released", (), 2)])
    g = pipe.led_gain
    assert g is not None and g.frame_gain > 1.2  # the estimate off the released fibers
    assert g.reference == pytest.approx(1.0, abs=0.01) and pipe.led_gain.gain == pytest.approx(1.0, abs=0.01)


def test_a_tare_during_a_grasp_heals_after_the_release(sensor_and_bundle):
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle)
    press = _press(2.0, -3.0)
    got = _run(pipe, sensor, [("rest", (), 60), ("grasp", press, 240), ("released", (), 600), ("again", press, 120)],
               tare_at=200)
    assert not any(e.contact for e, _ in got["released"])
    assert _found_at(got["again"], 2.0, -3.0)


def test_the_raise_waits_for_a_frame_without_contact(sensor_and_bundle):
    """Another press made right after the release: the released fibers are raised once the skin is free."""
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle)
    got = _run(pipe, sensor, [("held", _press(0.0, 0.0), 120), ("gap", (), 12), ("other", _press(5.0, 3.0), 240),
                              ("free", (), 600), ("again", _press(0.0, 0.0), 120)])
    assert not any(r for _, r in got["other"])
    assert _found_at(got["other"], 5.0, 3.0)
    assert not any(e.contact for e, _ in got["free"]) and any(r for _, r in got["free"])
    assert _found_at(got["again"], 0.0, 0.0)


def test_a_baseline_taken_at_rest_is_never_raised(sensor_and_bundle):
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle)
    got = _run(pipe, sensor, [("rest", (), 60), ("press", _press(1.0, 1.0), 240), ("rest2", (), 1200)])
    assert not any(r for phase in got.values() for _, r in phase)


@pytest.mark.parametrize("options", [None, ContactOptions.paper()], ids=["default", "paper-mode"])
@pytest.mark.parametrize("scale", [1.03, 1.10])
def test_a_uniform_brightening_of_the_light_is_no_press_under_the_baseline(sensor_and_bundle, options, scale):
    """Every fiber brighter alike (the LED): not a baseline taken over a press. Without the gain compensation
    brightness is measured from the common level (a raise here changed the shape figures of an ablation)."""
    sensor, bundle = sensor_and_bundle
    pipe = Pipeline(bundle, options)
    raised = 0
    for k in range(600):
        frame = sensor.frame((), t_s=k / FPS)
        if k >= 60:
            frame = np.clip(frame.astype(np.float32) * scale, 0, 255).astype(np.uint8)
        pipe.process_recorded(frame, k * PERIOD_NS)
        raised += pipe.result.baseline_raised
    assert raised == 0


def test_bright_fibers_must_stay_bright_for_the_hold_and_the_frame_be_free():
    check = BrightFibers(7, from_common=False, hold_s=0.1)
    bright, rest = np.zeros(7, np.float32), np.zeros(7, np.float32)
    bright[3] = -0.5
    ms = 1_000_000
    assert not check.check(bright, 0.1, 0, True)  # the timer starts
    assert not check.check(bright, 0.1, 99 * ms, True)
    assert not check.check(bright, 0.1, 120 * ms, False)  # held long enough, but a contact
    assert check.check(bright, 0.1, 130 * ms, True)
    assert not check.check(bright, 0.1, 140 * ms, True)  # acted on: the timer starts again
    assert not check.check(rest, 0.1, 300 * ms, True)  # not bright: the timer stops
    assert not check.check(bright, 0.1, 310 * ms, True) and not check.check(bright, 0.1, 400 * ms, True)
    bright[3] = -0.05  # above the level: noise
    assert not check.check(bright, 0.1, 10_000 * ms, True)


def test_the_service_counts_and_logs_a_raise_once(caplog):
    """Every raise counted, the first logged. Its own sensor: the module's shared one gives other noise
    depending on which tests ran before it (pytest-xdist's order), and with it one raise or two."""
    from optitac_edge.config import load_board_config
    from optitac_edge.io.transports.base import NullTransport
    from optitac_edge.service.loop import Service

    sensor = SimulatedSensor(seed=3, fps=FPS)
    bundle = calibrate_fibers([sensor.frame() for _ in range(10)], "gray")
    frames = ([sensor.frame(_press(0.0, 0.0), t_s=k / FPS) for k in range(60)]
              + [sensor.frame((), t_s=(60 + k) / FPS) for k in range(2 * HOLD_FRAMES)])
    pipe = Pipeline(bundle)
    raises = sum(pipe.process_recorded(f, (k + 1) * 4_166_667).baseline_raised for k, f in enumerate(frames))  # ListCamera's clock
    assert raises >= 1
    service = Service(load_board_config("sim", env={}), bundle, ListCamera(frames), NullTransport())
    with caplog.at_level(logging.WARNING, logger="optitac_edge.service.loop"):
        stats = service.run(threading.Event())
    assert stats.baseline_raises == raises and stats.contacts == 0
    lines = [r.getMessage() for r in caplog.records if "baseline raised" in r.getMessage()]
    assert len(lines) == 1 and "sensor 0" in lines[0] and "taken while the skin was pressed" in lines[0]
