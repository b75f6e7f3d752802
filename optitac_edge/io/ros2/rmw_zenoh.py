"""How rmw_zenoh (ROS 2's Zenoh middleware) names topics and entities on Zenoh.

What a publisher must put on Zenoh for ROS 2 nodes running ``rmw_zenoh_cpp`` to see
its topics (rmw_zenoh's docs/design.md and ``liveliness_utils.cpp``,
``attachment_helpers.cpp``; ROS 2 Jazzy, Kilted, Rolling):

* data on ``<domain_id>/<topic without its leading slash>/<pkg::msg::dds_::Name_>/<RIHS01 hash>``,
  CDR payload, no Zenoh encoding;
* a liveliness token per node,
  ``@ros2_lv/<domain_id>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``, and per
  publisher, ``@ros2_lv/<domain_id>/<zid>/<nid>/<id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  every ``/`` inside a name written ``%`` (an empty namespace or enclave is ``%``);
* an attachment on every sample: sequence number (int64, from 1), source timestamp
  (int64, ns since the Unix epoch) and the publisher's 16-byte GID, as zenoh-ext
  serializes them (little endian, the GID's length as one LEB128 byte);
* the GID: XXH3-128 of the publisher's liveliness key expression, low 64 bits then
  high 64 bits, little endian.

Pure functions: the Zenoh backend (:mod:`optitac_edge.io.publishers.zenoh`) uses them.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
NODE = "NN"
PUBLISHER = "MP"

#: rmw's QoS enums (rmw/types.h).
RELIABILITY_RELIABLE, RELIABILITY_BEST_EFFORT = 1, 2
DURABILITY_TRANSIENT_LOCAL, DURABILITY_VOLATILE = 1, 2
HISTORY_KEEP_LAST, HISTORY_KEEP_ALL = 1, 2
#: rmw_zenoh's default QoS: a component equal to it is left empty in a token.
DEFAULT_DEPTH = 42

_ATTACHMENT = struct.Struct("<qqB16s")
_ROS_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def mangle(name: str) -> str:
    """A name as one chunk of a liveliness token: every ``/`` becomes ``%`` (``""`` becomes ``%``)."""
    return name.replace("/", "%") if name else "%"


def check_ros_name(name: str, what: str) -> str:
    """``name`` if it is a valid ROS 2 name token (letters, digits, ``_``; not starting with a digit).

    Raises
    ------
    ValueError
        Naming ``what``.
    """
    if not _ROS_NAME.fullmatch(name) or "__" in name or name.endswith("_"):
        raise ValueError(f"{what} {name!r} is not a ROS 2 name (letters, digits and single _, "
                         "not starting with a digit or ending with _)")
    return name


def check_namespace(namespace: str) -> str:
    """A ROS 2 namespace: ``""`` / ``"/"`` (none) or ``/a/b``; returns it without a trailing slash."""
    ns = namespace.rstrip("/")
    if ns:
        if not ns.startswith("/"):
            raise ValueError(f"namespace {namespace!r} must start with '/'")
        for part in ns[1:].split("/"):
            check_ros_name(part, "namespace part")
    return ns


def topic_keyexpr(domain_id: int, topic: str, dds_type: str, type_hash: str) -> str:
    """The key expression of a topic's data (``topic`` fully qualified, e.g. ``/optitac/thumb/contacts``)."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type}/{type_hash}"


@dataclass(frozen=True)
class Qos:
    """The QoS of a publisher (rmw enums; None: rmw_zenoh's default, left empty in the token)."""

    reliability: int | None = None
    durability: int | None = None
    history: int | None = None
    depth: int | None = None

    def keyexpr(self) -> str:
        """``<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>``, each
        component empty when it is the default (deadline, lifespan and liveliness always are)."""
        def part(value: int | None, default: int) -> str:
            return "" if value is None or value == default else str(value)

        return (f"{part(self.reliability, RELIABILITY_RELIABLE)}:{part(self.durability, DURABILITY_VOLATILE)}:"
                f"{part(self.history, HISTORY_KEEP_LAST)},{part(self.depth, DEFAULT_DEPTH)}:,:,:,,")


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as rmw_zenoh names it in liveliness tokens: its domain, session (``zid``), node id,
    namespace, name and security enclave."""

    domain_id: int
    zid: str
    nid: int
    namespace: str
    name: str
    enclave: str = ""

    def prefix(self, eid: int, kind: str) -> str:
        """The tokens' common start, for entity ``eid`` of ``kind`` (``NN`` the node, ``MP`` a publisher)."""
        return (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.nid}/{eid}/{kind}/{mangle(self.enclave)}/"
                f"{mangle(self.namespace)}/{self.name}")


def node_token(node: Node) -> str:
    """The liveliness token of a node."""
    return node.prefix(node.nid, NODE)


def publisher_token(node: Node, eid: int, topic: str, dds_type: str, type_hash: str, qos: Qos) -> str:
    """The liveliness token of a publisher of ``topic`` (fully qualified), entity ``eid`` of ``node``."""
    return f"{node.prefix(eid, PUBLISHER)}/{mangle(topic)}/{mangle(dds_type)}/{mangle(type_hash)}/{qos.keyexpr()}"


def entity_gid(token: str) -> bytes:
    """The 16-byte GID of the entity with liveliness token ``token`` (XXH3-128, low half first)."""
    import xxhash  # the zenoh extra; only publishers need it

    return int(xxhash.xxh3_128_intdigest(token.encode())).to_bytes(16, "little")


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment of a sample: sequence number, source timestamp (ns, Unix epoch), GID."""
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, 16, gid)


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of a sample's attachment.

    Raises
    ------
    ValueError
        When it is not 33 bytes with a GID of 16.
    """
    if len(data) != _ATTACHMENT.size or data[16] != 16:
        raise ValueError(f"not an rmw_zenoh attachment: {len(data)} bytes")
    seq, ts, _, gid = _ATTACHMENT.unpack(data)
    return seq, ts, gid
