"""One exponential backoff for every retry (camera reopen, serial and CAN reconnect, Zenoh session)."""

from __future__ import annotations

import pytest

from optitac_edge.io.backoff import Backoff


def test_the_delays_double_up_to_the_cap_and_start_again_after_a_success():
    b = Backoff(0.1, 1.0)
    assert [b.next() for _ in range(6)] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    assert b.delay == 1.0  # the next one, without taking it
    b.reset()
    assert b.next() == 0.1


def test_a_cap_below_the_first_delay_is_the_first_delay_and_a_zero_start_is_refused():
    b = Backoff(2.0, 0.5)
    assert [b.next() for _ in range(3)] == [2.0, 2.0, 2.0]
    with pytest.raises(ValueError, match="first backoff delay must be > 0"):
        Backoff(0.0, 1.0)


def test_every_retry_in_the_package_uses_it():
    """The doubling arithmetic is written once: no module but io/backoff.py doubles a delay itself."""
    import re
    from pathlib import Path

    import optitac_edge

    root = Path(optitac_edge.__file__).parent
    doubling = re.compile(r"min\([^)]*\*\s*2(\.0)?\s*,")
    found = [str(p.relative_to(root)) for p in root.rglob("*.py")
             if p.name != "backoff.py" and doubling.search(p.read_text())]
    assert found == []
