#!/usr/bin/env python3
"""Receive optitac-edge's contacts on Zenoh without ROS 2: plain ``eclipse-zenoh`` and ``rosbags``.

The service publishes the way ROS 2's rmw_zenoh does (docs/network.md): each
topic's messages on ``<domain>/<topic>/<pkg::msg::dds_::Type_>/<type hash>``, CDR
encoded. This program subscribes to every optitac_msgs topic, decodes each
message with the ``.msg`` definitions shipped in ``ros2/optitac_msgs/msg`` and
prints it, one line per message (``--json``: one JSON object per line, with the
receive time on CLOCK_MONOTONIC and the sample's attachment)::

    pip install 'optitac-edge[zenoh]'      # or: pip install eclipse-zenoh rosbags
    python examples/zenoh_subscriber.py --connect tcp/192.168.1.20:7447
    python examples/zenoh_subscriber.py --listen tcp/0.0.0.0:7447 --json > contacts.jsonl

Stops on Ctrl-C, after ``--seconds``, or ``--idle`` seconds without a message.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import signal
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

try:
    import zenoh
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
except ModuleNotFoundError as exc:  # one line, not a traceback
    sys.exit(f"zenoh_subscriber: needs {exc.name}: pip install 'optitac-edge[zenoh]' (or eclipse-zenoh rosbags)")

MSG_DIR = Path(__file__).resolve().parent.parent / "ros2" / "optitac_msgs" / "msg"
#: Every optitac_msgs topic of any domain and namespace.
KEY = "**/optitac_msgs::msg::dds_::$*/*"


def typestore(msg_dir: Path) -> Any:
    """A rosbags type store knowing ROS 2's standard messages and optitac_msgs from ``msg_dir``."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for path in sorted(msg_dir.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"optitac_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def plain(value: Any) -> Any:
    """A decoded message as JSON-able values (NaN as null)."""
    if hasattr(value, "__dataclass_fields__"):
        return {k: plain(getattr(value, k)) for k in value.__dataclass_fields__ if k != "__msgtype__"}
    if hasattr(value, "tolist"):
        return plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", help="a Zenoh JSON5 config file")
    p.add_argument("--connect", action="append", default=[], help="an endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", default=[], help="an endpoint to listen on (repeatable)")
    p.add_argument("--key", default=KEY, help=f"key expression to subscribe to (default {KEY})")
    p.add_argument("--json", action="store_true", help="one JSON object per message")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long")
    p.add_argument("--idle", type=float, default=None,
                   help="stop once this long has passed without a message (after the first)")
    args = p.parse_args(argv)

    store = typestore(MSG_DIR)
    cfg = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    if args.connect:
        cfg.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        cfg.insert_json5("listen/endpoints", json.dumps(args.listen))
    if args.connect or args.listen:
        cfg.insert_json5("scouting/multicast/enabled", "false")

    stop = threading.Event()
    last: list[float | None] = [None]  # when the last message came (None: none yet)

    received: queue.SimpleQueue[tuple[int, str, bytes, bytes] | None] = queue.SimpleQueue()

    def on_sample(sample: Any) -> None:
        # Zenoh's callback only notes the time and hands over: decoding here would hold up the next sample
        att = sample.attachment
        received.put((time.monotonic_ns(), str(sample.key_expr), bytes(sample.payload),
                      bytes(att) if att is not None else b""))
        last[0] = time.monotonic()

    failures = [0]

    def decode_and_print() -> None:
        while (item := received.get()) is not None:
            received_ns, key, payload, att = item
            try:
                line = describe(received_ns, key, payload, att)
            except Exception as exc:  # noqa: BLE001 - one message that cannot be decoded: say so, go on
                failures[0] += 1
                print(f"cannot decode a message on {key}: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)
                continue
            print(line, flush=True)

    def describe(received_ns: int, key: str, payload: bytes, att: bytes) -> str:
        chunks = key.split("/")
        pkg, kind, _, name = chunks[-2].split("::")
        type_name = f"{pkg}/{kind}/{name.rstrip('_')}"
        msg = store.deserialize_cdr(payload, type_name)
        seq, source_ns = struct.unpack_from("<qq", att) if len(att) >= 16 else (None, None)
        topic = "/" + "/".join(chunks[1:-2])
        if args.json:
            return json.dumps({"topic": topic, "type": type_name, "received_ns": received_ns, "seq": seq,
                               "source_ns": source_ns, "message": plain(msg)})
        line = f"{topic} {type_name} seq {seq}"
        contacts = getattr(msg, "contacts", None)
        if type_name.endswith("/Contacts") and isinstance(contacts, (list, tuple)):
            line += f": {len(contacts)} contact(s)" + "".join(
                f" [id {c.id} at {c.x_mm:+.2f},{c.y_mm:+.2f} mm]" for c in contacts)
        elif type_name.endswith("/SensorStatus"):  # its `contacts` is a count of frames with contact
            line += f": {msg.fps:.1f} fps, {msg.frames} frames, {msg.contacts} with contact"
        return line

    printer = threading.Thread(target=decode_and_print)
    printer.start()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = zenoh.open(cfg)
    subscriber = session.declare_subscriber(args.key, on_sample)
    print(f"listening on {args.key}", file=sys.stderr, flush=True)
    start = time.monotonic()
    while not stop.wait(0.05):
        now = time.monotonic()
        if args.seconds is not None and now - start >= args.seconds:
            break
        if args.idle is not None and last[0] is not None and now - last[0] >= args.idle:
            break
    subscriber.undeclare()
    session.close()
    received.put(None)
    printer.join()
    return 1 if failures[0] else 0


if __name__ == "__main__":
    sys.exit(main())
