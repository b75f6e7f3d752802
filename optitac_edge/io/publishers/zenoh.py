"""Publish on Zenoh the way rmw_zenoh does, so that ROS 2 nodes see ROS 2 topics.

Needs the ``zenoh`` extra (``eclipse-zenoh``, ``xxhash``), imported when this
backend is opened. The names, tokens and attachments are built by
:mod:`optitac_edge.io.ros2.rmw_zenoh`; see docs/network.md.

The robot's network is not the sensor's first job: a session that cannot open
yet (a client whose router is not up, a port still in use) does not stop the
service. It is tried again from the publishing thread, 1 s after the first
attempt and then twice as long each time, up to :data:`RETRY_MAX_S`; until it
opens, :meth:`ZenohPublisher.publish` refuses every message (counted by the
caller). A configuration that cannot be right (file, endpoint, name) is still
refused at once.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from optitac_edge.errors import PublishError
from optitac_edge.fields import ROS_NAME, choice, endpoint_list, integer, path_text, setting, string
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock
from optitac_edge.io.device import BoardView
from optitac_edge.io.publishers.base import Publisher
from optitac_edge.io.ros2 import rmw_zenoh

log = logging.getLogger(__name__)

#: The QoS the topics are declared with: reliable, volatile, keep last 10.
TOPIC_QOS = rmw_zenoh.Qos(depth=10)
#: The first wait before opening a session again, and the longest, s.
RETRY_FIRST_S = 1.0
RETRY_MAX_S = 30.0


@dataclass(frozen=True)
class ZenohPublish:
    """``[publish.zenoh]``: every sensor's contacts, status and signal as ROS 2 topics via rmw_zenoh."""

    config: str = setting(path_text, "", "a Zenoh JSON5 config file (endpoints, scouting, TLS); '' = Zenoh's defaults")
    mode: str = setting(choice("", "peer", "client", "router"), "", "session mode ('' = the config file's, else peer)")
    connect: tuple[str, ...] = setting(endpoint_list, (), "endpoints to connect to, e.g. ['tcp/192.168.1.10:7447']")
    listen: tuple[str, ...] = setting(endpoint_list, (), "endpoints to listen on, e.g. ['tcp/0.0.0.0:7447']")
    domain_id: int = setting(integer(0, 232), 0, "ROS 2 domain id (ROS_DOMAIN_ID)")
    node: str = setting(string(64, pattern=ROS_NAME, empty=False), "optitac_edge", "ROS 2 node name")


def session_config(config: str | Path | None, mode: str, connect: tuple[str, ...],
                   listen: tuple[str, ...]) -> Any:
    """A ``zenoh.Config``: the file ``config`` (JSON5) if given, then ``mode``, ``connect`` and ``listen``
    where set."""
    import json

    import zenoh  # not at import: the board config reads this module's section without it

    if config and not Path(config).is_file():
        raise PublishError(f"Zenoh config {config}: no such file")
    try:
        cfg = zenoh.Config.from_file(str(config)) if config else zenoh.Config()
        if mode:
            cfg.insert_json5("mode", json.dumps(mode))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    except Exception as exc:  # noqa: BLE001 - zenoh raises ZError or ValueError: one line either way
        where = f"Zenoh config {config}" if config else "Zenoh settings"
        raise PublishError(f"{where}: {_one_line(exc)}") from None
    for kind in ("connect", "listen"):
        for endpoint in _endpoints(cfg, kind):
            why = endpoint_problem(endpoint, listen=kind == "listen")
            if why:
                where = f"Zenoh config {config}" if config else "publish"
                raise PublishError(f"{where}: {kind} endpoint {endpoint!r}: {why}")
    return cfg


#: Zenoh's link protocols (zenoh-link crates); the first group's address is HOST:PORT.
IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")


def _endpoints(cfg: Any, kind: str) -> list[str]:
    """The endpoints of ``connect`` or ``listen`` in a zenoh.Config (a list, or a list per mode)."""
    import json

    try:
        value = json.loads(cfg.get_json(f"{kind}/endpoints"))
    except Exception:  # noqa: BLE001 - not set
        return []
    lists = value.values() if isinstance(value, dict) else [value]
    return [e for items in lists if isinstance(items, list) for e in items if isinstance(e, str)]


def endpoint_problem(endpoint: str, listen: bool = False) -> str:
    """Why a Zenoh endpoint (``PROTO/ADDRESS[?metadata][#config]``) can never work ('' when it may).

    Before, ``tcp/127.0.0.1:70000`` and ``foo/bar`` were tried again for ever instead of refused at start.
    """
    proto, slash, rest = endpoint.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not slash or not address:
        return "not PROTOCOL/ADDRESS (e.g. tcp/192.168.1.10:7447)"
    if proto not in IP_PROTOCOLS + OTHER_PROTOCOLS:
        return f"unknown protocol {proto!r} (known: {', '.join(IP_PROTOCOLS + OTHER_PROTOCOLS)})"
    if proto not in IP_PROTOCOLS:
        return ""
    host, colon, port = address.rpartition(":")
    if not colon or not host or not port.isascii() or not port.isdigit():
        return "the address must be HOST:PORT"
    lowest = 0 if listen else 1  # a listener may take port 0: any free port
    if not lowest <= int(port) <= 65535:
        return f"port {port} is outside {lowest}..65535"
    bracketed = host.startswith("[") and host.endswith("]")
    if (":" in host or "[" in host or "]" in host) and not bracketed:
        return "an IPv6 address goes in brackets: [::1]:7447"
    return ""


def _one_line(exc: Exception) -> str:
    """Zenoh's error text on one line, without the Rust source location it ends with."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return re.sub(r"\s+at\s+\S+\.rs:\d+", "", text)


class ZenohPublisher(Publisher):
    """One Zenoh session, one ROS 2 node (``node`` in ``namespace``) with a publisher per topic.

    Parameters
    ----------
    config : path, optional
        A Zenoh JSON5 configuration file (endpoints, scouting, TLS, ...).
    mode : {"", "peer", "client", "router"}
        Overrides the file's mode ("" keeps it; Zenoh's default is peer).
    connect, listen : tuple of str
        Endpoints (``tcp/192.168.1.10:7447``), overriding the file's when given.
    domain_id : int
        The ROS 2 domain (``ROS_DOMAIN_ID``).
    namespace : str
        The node's ROS 2 namespace ("" or ``/robot1``); the topics are under it.
    node : str
        The node's name.
    clock : Clock
        When to try a session that could not open again.

    Raises
    ------
    PublishError
        A configuration file, endpoint or name that cannot be right.
    """

    Section = ZenohPublish

    @classmethod
    def from_config(cls, section: ZenohPublish, board: BoardView) -> ZenohPublisher:
        """``[publish.zenoh]`` under the board's namespace."""
        return cls(config=Path(section.config) if section.config else None, mode=section.mode,
                   connect=section.connect, listen=section.listen, domain_id=section.domain_id,
                   namespace=board.namespace, node=section.node)

    def __init__(self, config: str | Path | None = None, mode: str = "", connect: tuple[str, ...] = (),
                 listen: tuple[str, ...] = (), domain_id: int = 0, namespace: str = "",
                 node: str = "optitac_edge", clock: Clock = SYSTEM_CLOCK) -> None:
        super().__init__()
        try:
            self.namespace = rmw_zenoh.check_namespace(namespace)
            self.node = rmw_zenoh.check_ros_name(node, "node name")
        except ValueError as exc:
            raise PublishError(f"publish: {exc}") from None
        self.domain_id = domain_id
        self._config = session_config(config, mode, connect, listen)
        self._clock = clock
        self._session: Any = None
        self.zid = ""
        self._tokens: list[Any] = []
        self._publishers: list[tuple[Any, bytes]] = []
        self._topics: list[tuple[str, str]] = []
        self._seq: list[int] = []
        self.keyexprs: list[str] = []
        self.liveliness: list[str] = []
        #: Attempts to open the session so far, and why the last one failed ("" once open).
        self.attempts = 0
        self.failure = ""
        self._retry = Backoff(RETRY_FIRST_S, RETRY_MAX_S)
        self._next_ns = 0
        if not self._try_open():
            log.warning("Zenoh: cannot open a session yet (%s): nothing is published until it opens; trying again "
                        "from the publishing thread every %g-%g s (the MCU link does not wait)", self.failure,
                        RETRY_FIRST_S, RETRY_MAX_S)

    @property
    def connected(self) -> bool:
        """The session is open."""
        return self._session is not None

    def _try_open(self) -> bool:
        """Open the session and declare the node and every topic advertised so far; False if it cannot yet."""
        self.attempts += 1
        try:
            import zenoh

            session = zenoh.open(self._config)
        except Exception as exc:  # noqa: BLE001 - a router not up, a port in use: tried again later
            self.failure = _one_line(exc)
            now = self._clock.monotonic_ns()
            self._next_ns = now + int(self._retry.next() * 1e9)
            return False
        self._session, self.zid, self.failure = session, str(session.zid()), ""
        self._tokens.append(session.liveliness().declare_token(
            rmw_zenoh.node_token(self._node())))
        for topic, type_name in self._topics:
            self._declare(topic, type_name)
        if self.attempts > 1:
            log.info("Zenoh: session %s open (attempt %d)", self.zid, self.attempts)
        return True

    def _node(self) -> rmw_zenoh.Node:
        """This session's node (id 0)."""
        return rmw_zenoh.Node(self.domain_id, self.zid, 0, self.namespace, self.node)

    def _declare(self, topic: str, type_name: str) -> None:
        import zenoh

        from optitac_edge.io.ros2.messages import TYPE_HASHES, dds_type_name  # numpy: not when a board is read

        type_hash, dds_type = TYPE_HASHES[type_name], dds_type_name(type_name)
        eid = len(self._publishers) + 1  # entity ids: 0 is the node's
        key = rmw_zenoh.topic_keyexpr(self.domain_id, topic, dds_type, type_hash)
        token = rmw_zenoh.publisher_token(self._node(), eid, topic, dds_type, type_hash, TOPIC_QOS)
        publisher = self._session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self._tokens.append(self._session.liveliness().declare_token(token))
        self._publishers.append((publisher, rmw_zenoh.entity_gid(token)))
        self.keyexprs.append(key)
        self.liveliness.append(token)

    def advertise(self, topic: str, type_name: str) -> int:
        self._topics.append((topic, type_name))
        self._seq.append(0)
        if self._session is not None:
            self._declare(topic, type_name)
        return len(self._topics) - 1

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        if self._session is None and (self._clock.monotonic_ns() < self._next_ns or not self._try_open()):
            raise PublishError("no Zenoh session yet")
        publisher, gid = self._publishers[handle]
        self._seq[handle] += 1
        publisher.put(payload, attachment=rmw_zenoh.attachment(self._seq[handle], source_ns, gid))

    @property
    def where(self) -> str:
        if self._session is None:
            return (f"Zenoh, no session yet after {self.attempts} attempt(s): {self.failure} "
                    f"(ROS 2 domain {self.domain_id}, node {self.namespace}/{self.node})")
        return f"Zenoh session {self.zid} (ROS 2 domain {self.domain_id}, node {self.namespace}/{self.node})"

    def _close_internal(self) -> None:
        if self._session is None:
            return
        for entity in [*self._tokens, *(p for p, _ in self._publishers)]:
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - closing anyway
                log.debug("zenoh: undeclare failed: %s", exc)
        self._session.close()
