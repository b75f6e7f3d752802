"""The bench's end to end with the network on: Zenoh to a subscriber in another process, and MCAP.

:func:`open_bench_network` gives the service a :class:`~optitac_edge.service.network.NetworkOutput`
publishing every sensor's contacts, status and signal (10 Hz) on Zenoh (a peer on loopback,
read by a subscriber process that counts what it receives) and into an MCAP file; the
figures say what was published, dropped, received and written.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

#: The subscriber: counts every sample under the key until stdin closes, then prints the counts.
_SUBSCRIBER = r"""
import json, sys, zenoh
cfg = zenoh.Config()
cfg.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
cfg.insert_json5("scouting/multicast/enabled", "false")
counts = {}
def on_sample(sample):
    key = str(sample.key_expr).split("/optitac_msgs::")[0]
    counts[key] = counts.get(key, 0) + 1
session = zenoh.open(cfg)
sub = session.declare_subscriber("**", on_sample)
print("ready", flush=True)
sys.stdin.read()
sub.undeclare()
session.close()
print(json.dumps(counts), flush=True)
"""


class BenchNetwork:
    """The subscriber process, the publishers and the service's publishing thread."""

    def __init__(self, sensors: list[Any]) -> None:
        from optitac_edge.io.publishers.fanout import FanoutPublisher
        from optitac_edge.io.publishers.mcap import McapPublisher
        from optitac_edge.io.publishers.zenoh import ZenohPublisher
        from optitac_edge.service.network import NetworkOutput

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        self.subscriber = subprocess.Popen([sys.executable, "-c", _SUBSCRIBER, endpoint], stdin=subprocess.PIPE,
                                           stdout=subprocess.PIPE, text=True)
        assert self.subscriber.stdout is not None and self.subscriber.stdout.readline().strip() == "ready"
        self.mcap_path = Path(tempfile.mkdtemp(prefix="optitac-bench-")) / "e2e.mcap"
        zenoh = ZenohPublisher(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))
        self.publisher = FanoutPublisher([zenoh, McapPublisher(self.mcap_path)])
        self.output = NetworkOutput(self.publisher, sensors, signal_hz=10.0)
        self.sensor_ids = [s.sensor_id for s in sensors]

    def close(self) -> dict[str, Any]:
        """Stop publishing; the figures."""
        from mcap.reader import make_reader

        self.output.close()
        out, _ = self.subscriber.communicate("", timeout=30)
        received = json.loads(out.strip().splitlines()[-1])
        with open(self.mcap_path, "rb") as f:
            summary = make_reader(f).get_summary()
        written = summary.statistics.message_count if summary is not None and summary.statistics else 0
        counters = [self.output.counters(i) for i in self.sensor_ids]
        return {"published": sum(p for p, _ in counters), "dropped": sum(d for _, d in counters),
                "errors": self.output.errors, "received_by_subscriber": sum(received.values()),
                "topics": len(received), "mcap_messages": int(written),
                "mcap_bytes": self.mcap_path.stat().st_size}
