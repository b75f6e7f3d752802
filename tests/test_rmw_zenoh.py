"""The names, tokens and attachments rmw_zenoh puts on Zenoh, against its documented examples
(rmw_zenoh docs/design.md), and an encoder other than ours (zenoh-ext's serializer)."""

from __future__ import annotations

import time

import pytest
import xxhash
import zenoh
from fakes.net import free_port
from zenoh.ext import Int64, z_serialize

from optitac_edge.io.ros2 import rmw_zenoh
from optitac_edge.io.ros2.messages import TYPE_HASHES, dds_type_name

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_the_design_documents_talker_and_listener_tokens():
    assert rmw_zenoh.node_token(rmw_zenoh.Node(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "", "listener")) == \
        "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    talker = rmw_zenoh.Node(0, "8b20917502ee955ac4476e0266340d5c", 0, "", "talker")
    token = rmw_zenoh.publisher_token(talker, 10, "/chatter", "std_msgs::msg::dds_::String_", STRING_HASH,
                                      rmw_zenoh.Qos(depth=7))
    assert token == ("@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                     "std_msgs::msg::dds_::String_/" + STRING_HASH + "/::,7:,:,:,,")
    assert rmw_zenoh.topic_keyexpr(0, "/chatter", "std_msgs::msg::dds_::String_", STRING_HASH) == \
        "0/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH


def test_namespaces_and_qos_components():
    topic = "/robot1/optitac/thumb/contacts"
    dds = dds_type_name("optitac_msgs/msg/Contacts")
    h = TYPE_HASHES["optitac_msgs/msg/Contacts"]
    assert rmw_zenoh.topic_keyexpr(3, topic, dds, h) == f"3/robot1/optitac/thumb/contacts/{dds}/{h}"
    token = rmw_zenoh.publisher_token(rmw_zenoh.Node(3, "1f", 0, "/robot1", "optitac_edge"), 2, topic, dds, h,
                                      rmw_zenoh.Qos())
    assert token.split("/") == ["@ros2_lv", "3", "1f", "0", "2", "MP", "%", "%robot1", "optitac_edge",
                                "%robot1%optitac%thumb%contacts", dds, h, "::,:,:,:,,"]
    best_effort = rmw_zenoh.Qos(reliability=rmw_zenoh.RELIABILITY_BEST_EFFORT, depth=5)
    assert best_effort.keyexpr() == "2::,5:,:,:,,"
    assert rmw_zenoh.Qos(depth=rmw_zenoh.DEFAULT_DEPTH).keyexpr() == "::,:,:,:,,"


@pytest.mark.parametrize("name", ["thumb", "index_1", "a1b2"])
def test_ros_names_accepted(name):
    assert rmw_zenoh.check_ros_name(name, "sensor") == name


@pytest.mark.parametrize("name", ["1thumb", "a-b", "a__b", "a_", "", "a.b"])
def test_bad_ros_names_refused_naming_them(name):
    with pytest.raises(ValueError, match="sensor"):
        rmw_zenoh.check_ros_name(name, "sensor")


def test_the_attachment_is_what_zenoh_ext_serializes():
    gid = bytes(range(16))
    ours = rmw_zenoh.attachment(1, 1_795_000_000_000_000_123, gid)
    theirs = z_serialize(Int64(1)).to_bytes() + z_serialize(Int64(1_795_000_000_000_000_123)).to_bytes() + \
        z_serialize(gid).to_bytes()
    assert ours == theirs and len(ours) == 33
    assert rmw_zenoh.parse_attachment(ours) == (1, 1_795_000_000_000_000_123, gid)
    with pytest.raises(ValueError):
        rmw_zenoh.parse_attachment(ours[:-1])


def test_the_gid_is_xxh3_128_of_the_token_low_half_first():
    token = "@ros2_lv/0/1f/0/1/MP/%/%/n/%t/T/RIHS01_0/::,:,:,:,,"
    digest = xxhash.xxh3_128_digest(token.encode())  # canonical: big endian
    assert rmw_zenoh.entity_gid(token) == digest[::-1]
    assert rmw_zenoh.entity_gid(token) != rmw_zenoh.entity_gid(token + "x")


def test_the_zid_string_is_what_rmw_zenoh_writes():
    # rmw_zenoh: the zid as a little-endian u128 in lowercase hex without leading zeros
    session = zenoh.open(_isolated())
    try:
        zid = session.zid()
        assert str(zid) == f"{int.from_bytes(bytes(zid), 'little'):x}"
    finally:
        session.close()


def _isolated(listen: str | None = None, connect: str | None = None):
    cfg = zenoh.Config()
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", f'["{listen}"]' if listen else "[]")
    if connect:
        cfg.insert_json5("connect/endpoints", f'["{connect}"]')
    return cfg


def test_a_zenoh_subscriber_sees_the_topic_the_tokens_and_the_attachments(tmp_path):
    from optitac_edge.io.publishers import open_publisher

    locator = f"tcp/127.0.0.1:{free_port()}"
    cfg = tmp_path / "z.json5"
    cfg.write_text('{ mode: "peer", scouting: { multicast: { enabled: false } } }')
    with open_publisher("zenoh", config=cfg, listen=(locator,), domain_id=7, namespace="/robot1",
                        node="hand") as pub:
        h = pub.advertise("/robot1/optitac/thumb/contacts", "optitac_msgs/msg/Contacts")
        sub_session = zenoh.open(_isolated(connect=locator))
        try:
            tokens = _wait_for(lambda: [str(r.ok.key_expr) for r in sub_session.liveliness().get("@ros2_lv/7/**")
                                        if r.ok is not None], 2)
            assert f"@ros2_lv/7/{pub.zid}/0/0/NN/%/%robot1/hand" in tokens
            assert pub.liveliness[h] in tokens
            got: list = []
            sub = sub_session.declare_subscriber("7/robot1/optitac/thumb/contacts/**", got.append)
            deadline = time.monotonic() + 10
            while len(got) < 3 and time.monotonic() < deadline:
                pub.publish(h, b"\x00\x01\x00\x00payload", 1_795_000_000_000_000_000)
                time.sleep(0.02)
            assert got, "no sample reached the subscriber"
            sample = got[-1]
            assert str(sample.key_expr) == pub.keyexprs[h]
            seq, source_ns, gid = rmw_zenoh.parse_attachment(bytes(sample.attachment))
            assert source_ns == 1_795_000_000_000_000_000 and gid == rmw_zenoh.entity_gid(pub.liveliness[h])
            seqs = [rmw_zenoh.parse_attachment(bytes(s.attachment))[0] for s in got]
            assert seqs == sorted(seqs) and seqs[-1] == seq >= 1
            sub.undeclare()
        finally:
            sub_session.close()


def _wait_for(get, want: int, timeout_s: float = 10.0) -> list:
    deadline = time.monotonic() + timeout_s
    while True:
        found = get()
        if len(found) >= want or time.monotonic() > deadline:
            return found
        time.sleep(0.05)
