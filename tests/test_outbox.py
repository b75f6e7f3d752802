"""The outbox alone (no I/O): which messages a sensor's frame sends, from its result and the link's state.

Frames come from the real tracker (contacts at a few far-apart sites, each present or not per frame), the
link's state changes as the MCU's commands would change it; hypothesis draws both.
"""

from __future__ import annotations

from fakes.packing import decoded
from hypothesis import given, settings
from hypothesis import strategies as st

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.tracking import ContactTracker
from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.messages import ContactMessage, ContactV2Flags
from optitac_edge.io.protocol.outbox import LinkState, SensorOutbox
from optitac_edge.io.protocol.wire import MsgType

#: Where contacts press (mm): farther apart than the tracker's gate, so a site keeps its contact's id.
SITES = ((-6.0, 0.0), (6.0, 0.0), (0.0, 6.0), (0.0, -6.0))
PERIOD_NS = 4_166_667


class Frames:
    """FrameResults as the pipeline fills them: one reused result, the tracker's ids and releases."""

    def __init__(self) -> None:
        self.contacts = [ContactEstimate() for _ in range(4)]
        self.tracker = ContactTracker(4.0, max_contacts=4)
        self.result = FrameResult(self.contacts, self.tracker.released)
        self.frame = 0

    def next(self, sites: list[int], jitter: float) -> FrameResult:
        """The next frame, with contacts at ``sites`` (strongest first)."""
        frame, t_ns = self.frame, self.frame * PERIOD_NS
        self.frame += 1
        for k, c in enumerate(self.contacts):
            if k < len(sites):
                x, y = SITES[sites[k]]
                c.contact, c.strength = True, 10.0 - k
                c.x_mm, c.y_mm, c.major_mm, c.minor_mm, c.angle_deg = x + jitter, y - jitter, 3.0, 2.0, 15.0
            elif k == 0:
                c.contact, c.strength = False, 0.25
                c.clear_geometry()
        self.tracker.update(self.contacts, len(sites), frame)
        r = self.result
        r.frame, r.t_ns, r.baseline_ready = frame, t_ns, True
        r.n_contacts, r.n_released, r.calibrated = len(sites), self.tracker.n_released, True
        return r


#: What the MCU may say between two frames.
COMMANDS = st.sampled_from(["none"] * 6 + ["v1", "v2", "divider", "off", "on"])
FRAME = st.tuples(st.lists(st.integers(0, 3), max_size=4, unique=True), COMMANDS, st.integers(1, 4),
                  st.floats(-0.2, 0.2))


def _apply(link: LinkState, outbox: SensorOutbox, command: str, divider: int) -> None:
    """The service's handling of a command (SET_PROTOCOL starts a new session)."""
    if command in ("v1", "v2"):
        link.protocol = 1 if command == "v1" else 2
        outbox.new_session()
    elif command == "divider":
        link.rate_divider = divider
    elif command in ("off", "on"):
        link.streaming = command == "on"
    elif command == "flush":  # the last frame: sent
        link.streaming, link.rate_divider = True, 1


def _run(frames: list[tuple[list[int], str, int, float]], alongside: bool) -> list[tuple]:
    """Every frame: (result's contacts as (id, touch), sent?, its messages as decoded bytes, session)."""
    source, outbox = Frames(), SensorOutbox(3, degraded=False)
    link = LinkState(protocol=2, from_start=frozenset({1, 2}) if alongside else frozenset())
    log, session = [], 0
    for number, (sites, command, divider, jitter) in enumerate([*frames, ([], "flush", 1, 0.0)], start=1):
        _apply(link, outbox, command, divider)
        session += command in ("v1", "v2")
        result = source.next(sites, jitter)
        send = link.due(number)
        out = []
        for packet in outbox.update(result, link, send, result.t_ns + 1000):  # packed for a serial link
            if packet.kind is MsgType.CONTACT2:
                out.append(("CONTACT2", decoded(packet)))
            elif packet.kind is MsgType.CONTACT:
                out.append(("CONTACT", packet.frames[0][1]))
            else:
                assert packet.kind is MsgType.RELEASE
                out.append(("RELEASE", decoded(packet)))
        ids = [(c.contact_id, c.touch_frame) for c in result.touching()]
        primary = (result.primary.copy(), result.t_ns, result.n_contacts)
        log.append((result.frame, ids, send, out, session, link.protocol, primary))
    return log


@settings(max_examples=150, deadline=None)
@given(frames=st.lists(FRAME, min_size=1, max_size=40), alongside=st.booleans())
def test_every_contact_is_reported_exactly_once_per_sent_frame(frames, alongside):
    for _frame, ids, send, out, _session, protocol, _primary in _run(frames, alongside):
        v2 = [m for kind, m in out if kind == "CONTACT2"]
        if not send:
            assert out == []
        elif protocol == 2 or alongside:
            if ids:
                assert [(m.contact_id, m.index) for m in v2] == [(cid, k) for k, (cid, _) in enumerate(ids)]
                assert all(m.n_contacts == len(ids) for m in v2)
            else:
                assert len(v2) == 1 and v2[0].n_contacts == 0 and v2[0].contact_id == 0
        else:
            assert v2 == []


@settings(max_examples=150, deadline=None)
@given(frames=st.lists(FRAME, min_size=1, max_size=40), alongside=st.booleans())
def test_every_touch_comes_before_its_release_and_every_told_contact_is_released_once(frames, alongside):
    told: dict[tuple[int, int], int] = {}  # (id, touch frame) -> session it was told in
    released: set[tuple[int, int, int]] = set()
    session = 0
    for _frame, ids, send, out, session, protocol, _primary in _run(frames, alongside):
        order = [kind for kind, _ in out]
        if "RELEASE" in order:  # the releases of a frame go before its contacts
            assert order.index("RELEASE") < order.index("CONTACT2")
        for kind, m in out:
            if kind == "RELEASE":
                key = (m.contact_id, m.touch_frame)
                assert told.get(key) == session, "released without having been told in this session"
                assert (*key, session) not in released, "released twice"
                released.add((*key, session))
                del told[key]
            elif kind == "CONTACT2" and m.n_contacts:
                key = (m.contact_id, next(t for cid, t in ids if cid == m.contact_id))
                touch = bool(m.flags & ContactV2Flags.TOUCH)
                assert touch == (told.get(key) != session), "TOUCH exactly in the first frame the MCU hears of it"
                told[key] = session
    if protocol == 2 or alongside:  # the last frame is sent and has no contact: nothing is left held
        assert [k for k, s in told.items() if s == session] == []


@settings(max_examples=100, deadline=None)
@given(frames=st.lists(FRAME, min_size=1, max_size=40), alongside=st.booleans())
def test_v1_is_the_primary_contact_whatever_v2_did(frames, alongside):
    """Protocol v1's CONTACT is the frame's primary contact and nothing else: the bytes a v1 MCU received
    before v2 existed."""
    for _frame, ids, send, out, _session, protocol, (primary, t_ns, n) in _run(frames, alongside):
        v1 = [m for kind, m in out if kind == "CONTACT"]
        if send and (protocol == 1 or alongside):
            expected = ContactMessage(sensor_id=3).fill(primary, t_ns, t_ns + 1000, True, n_contacts=n)
            assert v1 == [wire.contact_payload(expected)]
            fields = wire.contact_fields(v1[0])
            assert fields[0] == 3 and bool(fields[1] & 1) == bool(ids)
        else:
            assert v1 == []


def test_a_frame_not_sent_keeps_its_releases_for_the_next_sent_frame():
    """Rate divider 3: a contact told in frame 0 and gone in frame 1 is released with frame 2, once."""
    source, outbox = Frames(), SensorOutbox(0)
    link = LinkState(protocol=2, rate_divider=1)
    first = outbox.messages(source.next([0], 0.0), link, True, 0)
    assert [type(m).__name__ for m in first] == ["ContactV2Message"] and outbox.announcer.touched == [True]
    link.rate_divider = 3
    assert outbox.messages(source.next([], 0.0), link, False, 0) == []
    out = outbox.messages(source.next([], 0.0), link, True, 0)
    assert [(type(m).__name__, getattr(m, "contact_id", None)) for m in out] == [
        ("ReleaseMessage", 1), ("ContactV2Message", 0)]
    assert out[0].frame == 2 and out[0].touch_frame == 0
    assert [type(m).__name__ for m in outbox.messages(source.next([], 0.0), link, True, 0)] == ["ContactV2Message"]
