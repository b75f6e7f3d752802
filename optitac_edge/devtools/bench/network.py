"""The bench's end to end with the network on: Zenoh and Foxglove to a client in another process, and MCAP.

:class:`BenchNetwork` gives the service a :class:`~optitac_edge.service.network.NetworkOutput`
publishing every sensor's contacts, status, signal (10 Hz) and pictures (image, surface,
overlay; 10 Hz) on Zenoh (a peer on loopback), to a Foxglove server, and into an MCAP
file. One client process subscribes to every Zenoh topic and every Foxglove channel
(``websocket-client``) and counts what it receives; the figures say what was published,
dropped, received and written.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

#: The client: counts every Zenoh sample and every Foxglove message until stdin closes, then prints the counts.
_CLIENT = r"""
import json, sys, threading, time, zenoh, websocket
cfg = zenoh.Config()
cfg.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
cfg.insert_json5("scouting/multicast/enabled", "false")
counts = {}
foxglove = [0]
def on_sample(sample):
    key = str(sample.key_expr).split("/optitac_msgs::")[0].split("/sensor_msgs::")[0].split("/foxglove_msgs::")[0]
    counts[key] = counts.get(key, 0) + 1
session = zenoh.open(cfg)
sub = session.declare_subscriber("**", on_sample)
print("ready", flush=True)
url = sys.stdin.readline().strip()
ws = websocket.create_connection(url, subprotocols=["foxglove.sdk.v1"], timeout=1)
done = threading.Event()
def read():
    subscribed = set()
    while not done.is_set():
        try:
            m = ws.recv()
        except websocket.WebSocketTimeoutException:
            continue
        except Exception:
            return
        if not m:  # the server closed the connection
            return
        if isinstance(m, str):
            d = json.loads(m)
            if d["op"] == "advertise":
                new = [c["id"] for c in d["channels"] if c["id"] not in subscribed]
                subscribed.update(new)
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": i} for i in new]}))
        elif m[:1] == b"\x01":
            foxglove[0] += 1
reader = threading.Thread(target=read)
reader.start()
sys.stdin.read()
done.set()
reader.join()
ws.close()
sub.undeclare()
session.close()
print(json.dumps({"zenoh": counts, "foxglove": foxglove[0]}), flush=True)
"""


class BenchNetwork:
    """The subscriber process, the publishers and the service's publishing thread."""

    def __init__(self, sensors: list[Any]) -> None:
        from optitac_edge.io.publishers.fanout import FanoutPublisher
        from optitac_edge.io.publishers.foxglove import FoxglovePublisher
        from optitac_edge.io.publishers.mcap import McapPublisher
        from optitac_edge.io.publishers.zenoh import ZenohPublisher
        from optitac_edge.service.network import NetworkOutput

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        self.subscriber = subprocess.Popen([sys.executable, "-c", _CLIENT, endpoint], stdin=subprocess.PIPE,
                                           stdout=subprocess.PIPE, text=True)
        assert self.subscriber.stdout is not None and self.subscriber.stdout.readline().strip() == "ready"
        self._dir = tempfile.TemporaryDirectory(prefix="optitac-bench-")  # the MCAP file: 100s of MB a minute
        self.mcap_path = Path(self._dir.name) / "e2e.mcap"
        zenoh = ZenohPublisher(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))
        foxglove = FoxglovePublisher("127.0.0.1:0")
        self.publisher = FanoutPublisher([zenoh, foxglove, McapPublisher(self.mcap_path)])
        self.output = NetworkOutput(self.publisher, sensors, signal_hz=10.0, picture_hz=10.0)
        assert self.subscriber.stdin is not None
        self.subscriber.stdin.write(foxglove.url + "\n")
        self.subscriber.stdin.flush()
        self.sensor_ids = [s.sensor_id for s in sensors]

    def close(self) -> dict[str, Any]:
        """Stop publishing; the figures."""
        from mcap.reader import make_reader

        try:
            self.output.close()
            out, _ = self.subscriber.communicate("", timeout=30)
            with open(self.mcap_path, "rb") as f:
                summary = make_reader(f).get_summary()
            size = self.mcap_path.stat().st_size
        finally:
            self._dir.cleanup()
        got = json.loads(out.strip().splitlines()[-1])
        received = got["zenoh"]
        written = summary.statistics.message_count if summary is not None and summary.statistics else 0
        counters = [self.output.counters(i) for i in self.sensor_ids]
        return {"published": sum(p for p, _ in counters), "dropped": sum(d for _, d in counters),
                "errors": self.output.errors, "received_by_subscriber": sum(received.values()),
                "received_by_foxglove_client": got["foxglove"],
                "topics": len(received), "mcap_messages": int(written),
                "mcap_bytes": size}
