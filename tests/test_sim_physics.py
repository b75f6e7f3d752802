"""Issue 26: the simulator's deliberately different physics (sim/physics.py, the skin model's options)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from optitac_edge.core.layout import hex_layout
from optitac_edge.sim.physics import PHYSICS, PHYSICS_NAMES, physics
from optitac_edge.sim.skin import (
    DEFAULT_SKIN,
    Indenter,
    SkinModel,
    contact_force_n,
    fiber_darkening,
    pin_response,
)

XY = hex_layout().xy_mm


def test_the_pin_responses():
    s = np.array([0.0, 0.1, 0.5, 1.0, 3.0])
    assert pin_response(s, DEFAULT_SKIN) == pytest.approx(1 - np.exp(-s))
    assert pin_response(s, SkinModel(response="linear")) == pytest.approx([0.0, 0.1, 0.5, 1.0, 1.0])
    thr = SkinModel(response="threshold", response_threshold=0.2)
    assert pin_response(s, thr) == pytest.approx(1 - np.exp(-np.maximum(s - 0.2, 0)))
    with pytest.raises(ValueError, match="unknown skin response"):
        SkinModel(response="cubic")


def _lit(skin: SkinModel, depth: float, level: float = 0.05) -> int:
    return int(np.sum(fiber_darkening(XY, [Indenter("circle", 0.0, 0.0, 0.0, 5.0, depth)], skin) > level))


def test_a_dome_touches_first_at_its_centre_and_its_footprint_grows_with_depth():
    flat, dome = DEFAULT_SKIN, SkinModel(dome=1.0)
    assert _lit(dome, 0.5) < _lit(flat, 0.5)
    assert _lit(dome, 4.0) >= _lit(dome, 0.5) + 6
    # Hertz: the contact radius sqrt(R d) with R = 2.5 mm (a 5 mm ball) until it reaches the outline
    shallow = Indenter("circle", 0.0, 0.0, 0.0, 5.0, 0.4)
    ratio = contact_force_n(shallow, 12.0, dome) / contact_force_n(shallow, 12.0, flat)
    assert ratio == pytest.approx(np.sqrt(2.5 * 0.4) / 2.5)
    deep = Indenter("circle", 0.0, 0.0, 0.0, 5.0, 3.0)
    assert contact_force_n(deep, 12.0, dome) == pytest.approx(contact_force_n(deep, 12.0, flat))


def test_pins_that_tilt_further_out_darken_fibers_beyond_the_indenter():
    wide = SkinModel(tilt_spread_mm=2.0, tilt_gain=0.8)
    press = [Indenter("circle", 0.0, 0.0, 0.0, 5.0, 2.0)]
    r = np.hypot(*XY.T)
    far = (r > 5.0) & (r < 8.0)
    assert fiber_darkening(XY, press, wide)[far].mean() > 1.5 * fiber_darkening(XY, press, DEFAULT_SKIN)[far].mean()


def test_a_stiff_rim_darkens_less_near_it_than_a_soft_one():
    press = [Indenter("circle", 8.0, 0.0, 0.0, 5.0, 2.0)]
    stiff, soft = physics("stiff-rim").skin, physics("soft-rim").skin
    assert fiber_darkening(XY, press, stiff).sum() < 0.8 * fiber_darkening(XY, press, soft).sum()


def test_every_physics_is_different_and_the_drifty_one_drifts_more():
    from optitac_edge.sim.drift import SessionDrift

    skins = {name: json.dumps(p.skin.to_dict(), sort_keys=True) for name, p in PHYSICS.items()
             if name not in ("drifty", "real")}  # those two differ in how the sensor drifts, not in the skin
    assert len(set(skins.values())) == len(skins)
    real = physics("real")
    assert real.wander is not None and real.colour_coded and real.array == (4, 4.0)
    base, drifty = SessionDrift.for_day(2), SessionDrift.for_day(2, scale=physics("drifty").day_drift)
    assert drifty.pin_gain - 1 == pytest.approx(3 * (base.pin_gain - 1), abs=1e-4)
    assert drifty.led_gain - 1 == pytest.approx(3 * (base.led_gain - 1), abs=1e-4)
    assert replace(drifty, pin_gain=base.pin_gain, led_gain=base.led_gain) == base
    with pytest.raises(ValueError, match="unknown simulated physics 'rubber'"):
        physics("rubber")


def test_sim_writes_the_physics_it_was_asked_for(tmp_path, capsys):
    from optitac_edge.cli import main

    assert main(["sim", str(tmp_path / "r"), "--scenario", "depths", "--frames", "30", "--physics", "sphere",
                 "-q"]) == 0
    sim = json.loads((tmp_path / "r" / "meta.json").read_text())["simulator"]
    assert sim["physics"] == "sphere" and sim["skin"]["dome"] == 1.0
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(["sim", str(tmp_path / "x"), "--scenario", "rest", "--physics", "rubber"])
    assert exit_.value.code == 2 and "invalid choice: 'rubber'" in capsys.readouterr().err


@pytest.mark.parametrize("url, problem", [("sim://?physics=rubber", "unknown physics 'rubber'"),
                                          ("sim://?day=-1", "day must be a whole number"),
                                          ("sim://?day=x", "day must be a whole number")])
def test_the_sim_rig_url_names_physics_and_day_or_refuses_them(url, problem):
    from optitac_edge.errors import RigError
    from optitac_edge.sim.rig import parse_sim_url

    with pytest.raises(RigError, match=problem):
        parse_sim_url(url)
    mount = parse_sim_url("sim://?physics=linear&day=3")
    assert (mount.physics, mount.day) == ("linear", 3)


def test_every_physics_name_is_documented():
    import optitac_edge.sim.physics as module

    assert all(f"``{name}``" in (module.__doc__ or "") for name in PHYSICS_NAMES)


@pytest.mark.parametrize("name", PHYSICS_NAMES)
def test_the_windowed_skin_field_equals_the_whole_grids_bit_for_bit(name):
    """fiber_darkening computes each indenter on the window of the grid it reaches: every physics, every shape,
    indenters near and beyond the rim, several at once, give the whole grid's values exactly."""
    from optitac_edge.sim.skin import fiber_darkening_whole_grid

    skin = physics(name).skin
    rng = np.random.default_rng(7)
    shapes = ("circle", "square", "edge", "ellipse", "triangle")
    for _ in range(40):
        press = [Indenter(shapes[rng.integers(5)], float(rng.uniform(-17, 17)), float(rng.uniform(-17, 17)),
                          float(rng.uniform(0, 180)), float(rng.uniform(1, 10)), float(rng.uniform(0.05, 3)))
                 for _ in range(rng.integers(1, 4))]
        assert np.array_equal(fiber_darkening(XY, press, skin), fiber_darkening_whole_grid(XY, press, skin))
