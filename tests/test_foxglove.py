"""Foxglove live: `run --foxglove` serves every topic over the Foxglove WebSocket protocol; a client
subscribes and decodes the contacts, the sensor's image and the overlay with the advertised schemas."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
import websocket
from fakes.net import free_port
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

from optitac_edge.errors import PublishError
from optitac_edge.io.publishers import open_publisher
from optitac_edge.io.ros2.messages import ContactValues
from optitac_edge.service.network import NetworkSensor, contact_outline

TOPICS = ("/optitac/sim/contacts", "/optitac/sim/image", "/optitac/sim/annotations", "/optitac/sim/surface")


def _connect(port: int, timeout_s: float = 60.0) -> websocket.WebSocket:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return websocket.create_connection(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                               timeout=10)
        except (ConnectionError, OSError):
            assert time.monotonic() < deadline, "the Foxglove server did not come up"
            time.sleep(0.2)


def _refused_channel(data: str | bytes) -> int | None:
    """The channel id of an "Unknown channel ID: N" error status, else None.

    foxglove-sdk (0.30.x, rust/foxglove/src/websocket/connected_client.rs, ``advertise_channels``) sends a
    channel's advertisement to the client before it records the channel as advertised to that client, so a
    client that subscribes the moment the advertisement arrives can be told the channel is unknown. A
    client then subscribes again, as this one does; the channel is known by then.
    """
    if not isinstance(data, str):
        return None
    msg = json.loads(data)
    text = str(msg.get("message", ""))
    if msg.get("op") == "status" and text.startswith("Unknown channel ID: "):
        return int(text.rsplit(" ", 1)[1])
    return None


def test_a_foxglove_client_gets_contacts_image_and_overlay_decoded_with_the_advertised_schemas():
    port = free_port()
    run = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--foxglove", f"127.0.0.1:{port}",
                            "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ws = _connect(port)
        channels: dict[str, dict] = {}
        while set(TOPICS) - set(channels):
            msg = ws.recv()
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                channels.update({c["topic"]: c for c in json.loads(msg)["channels"]})
        subscriptions = {channels[t]["id"]: {"id": k + 1, "channelId": channels[t]["id"]}
                         for k, t in enumerate(TOPICS)}
        ws.send(json.dumps({"op": "subscribe", "subscriptions": list(subscriptions.values())}))
        store = get_typestore(Stores.EMPTY)
        for t in TOPICS:
            c = channels[t]
            assert (c["encoding"], c["schemaEncoding"]) == ("cdr", "ros2msg")
            store.register(get_types_from_msg(c["schema"], c["schemaName"]))
        got: dict[str, list] = {t: [] for t in TOPICS}
        lost = ""  # what the client had when the server went away (the run's stderr is added below)
        resubscribed = 0
        try:
            while not all(got.values()) or not any(m.contacts for m in got[TOPICS[0]]):
                data = ws.recv()
                refused = _refused_channel(data)
                if refused in subscriptions and resubscribed < 3:
                    resubscribed += 1
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [subscriptions[refused]]}))
                elif isinstance(data, bytes) and data[0] == 1:  # message data: sub id u32, log time u64, payload
                    _, sub, _ = struct.unpack_from("<BIQ", data)
                    topic = TOPICS[sub - 1]
                    got[topic].append(store.deserialize_cdr(data[13:], channels[topic]["schemaName"]))
            ws.close()
        except websocket.WebSocketException as exc:
            counts = {t: len(v) for t, v in got.items()}
            lost = (f"{type(exc).__name__} ({exc}) with {counts} received, "
                    f"{sum(bool(m.contacts) for m in got[TOPICS[0]])} with contacts")
    finally:
        run.terminate()
        out, err = run.communicate(timeout=30)
    assert not lost, f"{lost}; the run's stderr: {err[-2000:]}"
    assert run.returncode == 0, err[-2000:]
    assert "Foxglove ws://127.0.0.1:" in out
    image = got["/optitac/sim/image"][0]
    assert (image.width, image.height, image.encoding, image.step) == (640, 480, "mono8", 640)
    surface = got["/optitac/sim/surface"][0]
    assert surface.encoding == "32FC1" and surface.width == surface.height > 10
    overlay = got["/optitac/sim/annotations"]
    fibers = overlay[0].points[0]
    assert fibers.type == 1 and len(fibers.points) == 217  # every fiber of the simulated sensor, live
    pressed = [m for m in got["/optitac/sim/contacts"] if m.contacts]
    assert pressed and pressed[0].contacts[0].id >= 1
    outlined = [a for a in overlay if a.texts]
    if outlined:  # a picture taken during a press outlines it, labelled with its id
        assert outlined[0].points[-1].type == 2 and outlined[0].texts[0].text.split()[0].isdigit()


def test_the_overlay_maps_a_contacts_ellipse_onto_the_image():
    n = 7
    x = np.array([0, 1, 0, -1, 0, 2, -2], dtype=np.float32)
    y = np.array([0, 0, 1, 0, -1, 2, -2], dtype=np.float32)
    px = np.column_stack([100 + 10 * x, 50 - 10 * y])  # 10 px per mm, y up on the skin, down in the image
    s = NetworkSensor(1, "thumb", x, y, np.zeros(n, bool), fiber_px=px)
    affine = s.mm_to_px()
    np.testing.assert_allclose(affine, [[10, 0, 100], [0, -10, 50]], atol=1e-9)
    outline = contact_outline(affine, ContactValues(3, True, 0, 1.0, 0.5, 4.0, 2.0, 90.0, 1.0, 0.0, 0.0, "edge", 0.9))
    assert outline.label == "3 edge" and outline.at == pytest.approx((110.0, 45.0))
    # major axis 4 mm along y (90 degrees): 40 px tall, minor 2 mm: 20 px wide
    assert np.ptp(outline.points[:, 1]) == pytest.approx(40.0) and np.ptp(outline.points[:, 0]) == pytest.approx(20.0)


@pytest.mark.parametrize(("bind", "message"), [("8765", "is not HOST:PORT"), ("localhost:99999", "is not HOST:PORT"),
                                               ("192.0.2.1:0", "cannot serve on 192.0.2.1:0")])
def test_a_bad_address_is_refused_in_one_line(bind, message):
    with pytest.raises(PublishError, match=message):
        open_publisher("foxglove", bind=bind)
