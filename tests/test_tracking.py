"""Stable contact ids, touch frames and release events (core/tracking.py)."""

from __future__ import annotations

import math

import pytest

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.tracking import MAX_ID, ContactTracker


def frame_of(*xy: tuple[float, float]) -> list[ContactEstimate]:
    out = []
    for x, y in xy:
        c = ContactEstimate(contact=True, x_mm=x, y_mm=y)
        out.append(c)
    return out


def step(tr: ContactTracker, frame: int, *xy: tuple[float, float]) -> list[ContactEstimate]:
    cs = frame_of(*xy)
    tr.update(cs, len(cs), frame)
    return cs


def test_two_presses_keep_their_ids_while_they_move_and_swap_rank():
    tr = ContactTracker(4.0)
    first = step(tr, 0, (-5.0, 0.0), (5.0, 0.0))
    ids = {round(c.x_mm): c.contact_id for c in first}
    assert sorted(ids.values()) == [1, 2] and all(c.touch_frame == 0 for c in first)
    for f in range(1, 100):  # both drift 0.05 mm a frame; the order in the list alternates
        a, b = (-5.0 + 0.05 * f, 0.1 * math.sin(f)), (5.0 - 0.02 * f, 0.0)
        cs = step(tr, f, *((a, b) if f % 2 else (b, a)))
        got = {("left" if c.x_mm < 0.5 * (a[0] + b[0]) else "right"): c.contact_id for c in cs}
        assert got == {"left": ids[-5], "right": ids[5]}
        assert all(c.touch_frame == 0 for c in cs) and tr.n_released == 0


def test_a_release_is_reported_in_the_frame_the_contact_is_gone_and_a_new_press_gets_a_new_id():
    tr = ContactTracker(4.0)
    (c,) = step(tr, 10, (0.0, 0.0))
    step(tr, 11, (0.1, 0.0))
    assert tr.n_released == 0
    step(tr, 12)
    assert tr.n_released == 1 and tr.released[0] == (c.contact_id, 10)
    step(tr, 13)
    assert tr.n_released == 0  # released once
    (again,) = step(tr, 14, (0.1, 0.0))  # the same place: a new press, a new id
    assert again.contact_id != c.contact_id and again.touch_frame == 14


def test_a_jump_beyond_the_gate_is_a_release_and_a_touch_in_the_same_frame():
    tr = ContactTracker(gate_mm=2.0)
    (a,) = step(tr, 0, (0.0, 0.0))
    (b,) = step(tr, 1, (3.0, 0.0))
    assert b.contact_id != a.contact_id and b.touch_frame == 1
    assert tr.n_released == 1 and tr.released[0] == (a.contact_id, 0)


def test_the_closest_pair_wins_and_a_third_contact_is_new():
    tr = ContactTracker(4.0)
    a, b = step(tr, 0, (0.0, 0.0), (3.0, 0.0))
    cs = step(tr, 1, (2.0, 0.0), (0.5, 0.0), (9.0, 9.0))
    assert [c.contact_id for c in cs] == [b.contact_id, a.contact_id, 3]
    assert [c.touch_frame for c in cs] == [0, 0, 1]


def test_ids_wrap_and_skip_ids_in_use():
    tr = ContactTracker(4.0)
    (held,) = step(tr, 0, (50.0, 50.0))  # id 1, held throughout
    f = 1
    seen = []
    for f in range(1, 2 * MAX_ID):  # a second contact touches and releases every other frame
        cs = step(tr, f, (50.0, 50.0), *(((0.0, 0.0),) if f % 2 else ()))
        assert cs[0].contact_id == held.contact_id
        if f % 2:
            seen.append(cs[1].contact_id)
    assert held.contact_id not in seen and 0 not in seen
    assert set(seen) == set(range(2, MAX_ID + 1))


def test_nan_centroids_never_match_and_reset_forgets_without_releasing():
    tr = ContactTracker(4.0)
    (a,) = step(tr, 0, (math.nan, 0.0))
    (b,) = step(tr, 1, (math.nan, 0.0))
    assert b.contact_id != a.contact_id
    tr.reset()
    assert tr.n_released == 0
    (c,) = step(tr, 2, (0.0, 0.0))
    assert c.touch_frame == 2 and tr.n_released == 0


@pytest.mark.parametrize("gate", [0.0, -1.0, math.nan, math.inf])
def test_a_bad_gate_is_refused(gate):
    with pytest.raises(ValueError, match="tracking gate"):
        ContactTracker(gate_mm=gate)


def test_the_pipeline_keeps_two_simultaneous_presses_apart_for_100_frames(bundle_path):
    """Issue 16: two presses held throughout keep their ids in every frame (the indenters change shape
    and shift by up to 1 mm every 48 frames); no touch or release after the first contact frame."""
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.multi_press import multi_press_frames

    bundle = load_bundle(bundle_path)
    rest = bundle.baseline_frames
    frames = multi_press_frames(2, 100, rest, layout=bundle.layout, seed=3)
    pipe = Pipeline(bundle)
    ids = None
    for i, f in enumerate(frames):
        result = pipe.process_recorded(f, i * 4_166_667)
        est = result.primary
        if i < rest:
            assert not est.contact and est.contact_id == 0 and pipe.result.releases() == []
            continue
        assert result.n_contacts == 2
        by_side = {pipe.contacts[k].x_mm > 0: (pipe.contacts[k].contact_id, pipe.contacts[k].touch_frame)
                   for k in range(2)}
        if ids is None:
            ids = by_side
            assert sorted(i_ for i_, _ in ids.values()) == [1, 2]
            assert all(t == result.frame for _, t in ids.values())  # both touched in this frame
        assert by_side == ids and pipe.result.releases() == []
    est = pipe.process_recorded(frames[0], len(frames) * 4_166_667).primary  # a rest frame: both released
    assert not est.contact and est.contact_id == 0
    assert sorted(pipe.result.releases()) == sorted(ids.values())
