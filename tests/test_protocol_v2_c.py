"""Protocol v2 across two independent implementations: the Python encoder's golden vectors decoded by the C
reference (tools/mcu/optitac_proto_v2.c), and frames the C encoder writes decoded by Python.

The v1 reference (optitac_proto.c, test_vectors.c and the v1 vectors) is untouched by v2: an MCU that
never asks for v2 builds and behaves as before (tests/test_protocol_c.py runs it unchanged).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.wire import MsgType, encode_frame, parse_command
from optitac_edge.io.protocol.wire_v2 import (
    CONTACT2,
    CONTACT2_KEYS,
    MOTION,
    MOTION_KEYS,
    RELEASE,
    RELEASE_KEYS,
    contact2_fields,
)

ROOT = Path(__file__).resolve().parents[1]
MCU = ROOT / "tools" / "mcu"
V2 = ROOT / "tests" / "vectors" / "v2"

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc (the C reference)")


@pytest.fixture(scope="module")
def v2_tool(tmp_path_factory) -> Path:
    exe = tmp_path_factory.mktemp("mcu2") / "v2_tool"
    r = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-I", str(MCU),
                        str(MCU / "v2_tool.c"), str(MCU / "optitac_proto_v2.c"), str(MCU / "optitac_proto.c"),
                        "-o", str(exe)], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    return exe


def _run(tool: Path, mode: str, lines: list[str]) -> list[str]:
    r = subprocess.run([str(tool), mode], input="\n".join(lines) + "\n", capture_output=True, text=True,
                       timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()


def _vectors() -> list[tuple[str, dict[str, int], str]]:
    out = []
    for path in sorted(V2.glob("*.hex")):
        pending = None
        for line in path.read_text().splitlines():
            announced = re.match(r"# (\w+): expect=", line)
            if announced:
                name, rest = announced.group(1), line.split(":", 1)[1]
                keys = dict(kv.split("=") for kv in rest.split(" -- ")[0].split() if not kv.startswith("expect="))
                pending = (name, {k: int(v, 0) for k, v in keys.items()})
            elif pending and not line.startswith("#"):
                out.append((*pending, line.strip()))
                pending = None
    return out


def test_every_v2_golden_vector_decodes_in_c_to_its_announced_fields(v2_tool):
    vectors = _vectors()
    assert {name for name, _, _ in vectors} >= {"contact2_touch", "contact2_saturated", "release_wrapped",
                                                "set_protocol_2", "set_protocol_3", "motion_slide_began",
                                                "motion_saturated"}
    decoded = _run(v2_tool, "decode", [hexline for _, _, hexline in vectors])
    for (name, keys, _), line in zip(vectors, decoded, strict=True):
        kind, *fields = line.split()
        got = {k: int(v) for k, v in (f.split("=") for f in fields)}
        want = {k: v for k, v in keys.items() if k not in ("type", "payload_len", "result")}
        assert kind == {0x03: "contact2", 0x04: "release", 0x05: "motion", 0x14: "set_protocol"}[keys["type"]], name
        assert got == want, name


def test_the_set_protocol_vectors_get_the_announced_answer_in_python():
    for name, keys, hexline in _vectors():
        if keys["type"] != MsgType.SET_PROTOCOL:
            continue
        (frame,) = FrameDecoder().feed(bytes.fromhex(hexline))
        parsed = parse_command(frame.type, frame.seq, frame.payload)
        result = 0 if not isinstance(parsed, tuple) else int(parsed[1])
        assert result == keys["result"], name


def test_frames_the_c_encoder_writes_decode_in_python_and_match_the_python_encoder(v2_tool):
    rng = np.random.default_rng(16)
    lows = {"x": -32768, "y": -32768, "angle": -9000}
    highs = {"sensor_id": 255, "flags": 127, "frame": 65535, "index": 3, "n_contacts": 4, "contact_id": 255,
             "shape": 255, "x": 32767, "y": 32767, "angle": 9000, "confidence": 255}
    contacts = []
    for _ in range(300):
        ints = {k: int(rng.integers(lows.get(k, 0), highs.get(k, 65535) + 1)) for k in CONTACT2_KEYS}
        ints["reserved"] = 0
        contacts.append((int(rng.integers(0, 65536)), int(rng.integers(0, 2**32)), ints))
    releases = [(int(rng.integers(0, 65536)), int(rng.integers(0, 2**32)),
                 [int(rng.integers(0, m)) for m in (256, 256, 65536, 65536)]) for _ in range(100)]
    lines = [f"contact2 {seq} {t} " + " ".join(str(ints[k]) for k in CONTACT2_KEYS if k != "reserved")
             for seq, t, ints in contacts]
    lines += [f"release {seq} {t} " + " ".join(map(str, vals)) for seq, t, vals in releases]
    wires = _run(v2_tool, "encode", lines)
    assert len(wires) == len(lines)
    for (seq, t, ints), hexline in zip(contacts, wires[:len(contacts)]):
        wire = bytes.fromhex(hexline)
        (frame,) = FrameDecoder().feed(wire)
        assert (frame.type, frame.seq, frame.t_us) == (MsgType.CONTACT2, seq, t)
        assert dict(zip(CONTACT2_KEYS, contact2_fields(frame.payload))) == ints
        assert wire == encode_frame(MsgType.CONTACT2, seq, t, CONTACT2.pack(*(ints[k] for k in CONTACT2_KEYS)))
    for (seq, t, vals), hexline in zip(releases, wires[len(contacts):]):
        (frame,) = FrameDecoder().feed(bytes.fromhex(hexline))
        assert frame.type == MsgType.RELEASE and (frame.seq, frame.t_us) == (seq, t)
        assert dict(zip(RELEASE_KEYS, RELEASE.unpack(frame.payload))) == dict(zip(RELEASE_KEYS, vals))


def test_motion_frames_the_c_encoder_writes_decode_in_python_and_match_the_python_encoder(v2_tool):
    """Protocol v3's MOTION both ways: random wire integers through the C encoder, decoded by Python and compared
    byte for byte with the Python encoder of the same integers."""
    rng = np.random.default_rng(29)
    lows = {"vx": -32768, "vy": -32768}
    highs = {"sensor_id": 255, "flags": 63, "index": 3, "contact_id": 255, "vx": 32767, "vy": 32767}
    cases = [(int(rng.integers(0, 65536)), int(rng.integers(0, 2**32)),
              {k: int(rng.integers(lows.get(k, 0), highs.get(k, 65535) + 1)) for k in MOTION_KEYS})
             for _ in range(300)]
    wires = _run(v2_tool, "encode", [f"motion {seq} {t} " + " ".join(str(ints[k]) for k in MOTION_KEYS)
                                      for seq, t, ints in cases])
    for (seq, t, ints), hexline in zip(cases, wires, strict=True):
        wire = bytes.fromhex(hexline)
        (frame,) = FrameDecoder().feed(wire)
        assert (frame.type, frame.seq, frame.t_us) == (MsgType.MOTION, seq, t)
        assert dict(zip(MOTION_KEYS, MOTION.unpack(frame.payload))) == ints
        assert wire == encode_frame(MsgType.MOTION, seq, t, MOTION.pack(*(ints[k] for k in MOTION_KEYS)))
