"""Protocol v2 on CAN (``link.can_protocol = 2``): CONTACT2 (multiplexed) and RELEASE beside the v1 frames.

The codec against cantools, the service on python-can's virtual bus (a v1 MCU filtering its ids sees
the v1 stream unchanged), and the C code cantools generates from the DBC, compiled with gcc.
"""

from __future__ import annotations

import shutil
import subprocess
import threading

import cantools
import numpy as np
import pytest

from optitac_edge.io.protocol.can_codec import DBC_PATH, CanCodec, decode_frame
from optitac_edge.io.protocol.messages import ContactV2Message, ShapeCode

RES = {"X": 0.005, "Y": 0.005, "MAJOR": 0.005, "MINOR": 0.005, "ANGLE": 0.005, "STRENGTH": 0.005,
       "CONFIDENCE": 0.5 / 255, "DEPTH": 0.001, "FORCE": 0.0025}


def _contact(**kw) -> ContactV2Message:
    msg = ContactV2Message(sensor_id=0, flags=0x73, t_us=5, frame=9, index=1, n_contacts=2, contact_id=42,
                           x_mm=-12.344, y_mm=7.005, major_mm=5.5, minor_mm=4.25, angle_deg=-33.3, strength=21.5,
                           depth_mm=2.345, force_n=3.21, shape=ShapeCode.CIRCLE, confidence=0.75, age_us=1500)
    for key, value in kw.items():
        setattr(msg, key, value)
    return msg


def test_the_three_parts_decode_to_the_contact_within_the_dbc_resolution():
    codec = CanCodec(protocol=2)
    msg = _contact()
    got = {}
    for part, payload in enumerate(codec.contact2_payloads(msg, 21)):
        sensor, name, signals = decode_frame(0x303, payload)
        assert (sensor, name, signals["PART"], signals["SLOT"], signals["COUNTER"]) == (0, "CONTACT2", part, 1, 5)
        got.update(signals)
    want = {"X": msg.x_mm, "Y": msg.y_mm, "MAJOR": msg.major_mm, "MINOR": msg.minor_mm, "ANGLE": msg.angle_deg,
            "STRENGTH": msg.strength, "CONFIDENCE": msg.confidence, "DEPTH": msg.depth_mm, "FORCE": msg.force_n}
    for key, value in want.items():
        assert abs(got[key] - value) <= RES[key] + 1e-9, key
    assert (got["SHAPE"], got["N_CONTACTS"], got["CONTACT_ID"], got["FLAGS"], got["AGE"]) == (2, 2, 42, 0x73, 1500)
    sat = {}
    for payload in codec.contact2_payloads(_contact(depth_mm=50.0, force_n=1e3, x_mm=-99.0, index=7), 0):
        sat.update(decode_frame(0x303, payload)[2])
    assert (sat["DEPTH"], sat["FORCE"], sat["X"], sat["SLOT"]) == (8.19, 20.475, -40.96, 3)
    sensor, name, signals = decode_frame(0x304, codec.release_payload(200, 17))
    assert (sensor, name, signals) == (0, "RELEASE", {"CONTACT_ID": 200, "COUNTER": 1})


def test_a_database_without_the_v2_messages_still_serves_v1_and_is_refused_for_v2(tmp_path):
    from optitac_edge.errors import TransportError

    text = DBC_PATH.read_text()
    v1_only = text[:text.index("BO_ 771 CONTACT2")] + text[text.index("CM_ BU_ OPTITAC"):]
    v1_only = "\n".join(line for line in v1_only.splitlines() if " 771 " not in line and " 772 " not in line)
    path = tmp_path / "v1.dbc"
    path.write_text(v1_only + "\n")
    CanCodec(dbc_path=path)  # v1: fine
    with pytest.raises(TransportError, match="no message CONTACT2"):
        CanCodec(dbc_path=path, protocol=2)


def test_the_service_sends_every_contact_beside_an_unchanged_v1_stream(bundle_path):
    """Two presses held for 30 frames: a v1 MCU (ids 0x300-0x302) sees one CONTACT pair per frame as before;
    a v2 MCU also gets three CONTACT2 parts per contact with stable ids, and both releases."""
    import can
    from fakes.list_camera import ListCamera

    from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.service.loop import Service
    from optitac_edge.service.wiring import open_board_transport
    from optitac_edge.sim.multi_press import multi_press_frames

    bundle = load_bundle(bundle_path)
    rest = bundle.baseline_frames
    frames = multi_press_frames(2, 30, rest, layout=bundle.layout, seed=2)
    frames += frames[:2]
    config = load_board_config("sim", env={}, overrides={
        "link.transport": "can", "link.can_interface": "virtual", "link.can_channel": "v2-test",
        "link.can_protocol": 2})
    with can.Bus(interface="virtual", channel="v2-test") as mcu:
        with open_board_transport(config) as transport:
            stats = Service(config, bundle, ListCamera(frames), transport).run(threading.Event())
        received = []
        while (msg := mcu.recv(timeout=0.2)) is not None:
            received.append(decode_frame(msg.arbitration_id, msg.data))
    names = [name for _, name, _ in received]
    assert names.count("CONTACT_A") == names.count("CONTACT_B") == stats.sent == len(frames)
    v1 = [name for name in names if name in ("CONTACT_A", "CONTACT_B")]
    assert v1 == ["CONTACT_A", "CONTACT_B"] * len(frames)  # the v1 stream, in order
    parts = [s for _, name, s in received if name == "CONTACT2"]
    assert len(parts) == 30 * 2 * 3
    ids = {s["CONTACT_ID"] for s in parts if s["PART"] == 2}
    assert len(ids) == 2
    per_counter: dict[int, set[int]] = {}
    for s in parts:
        if s["PART"] == 2:
            per_counter.setdefault(s["COUNTER"], set()).add(s["CONTACT_ID"])
    assert all(v == ids for v in per_counter.values())
    released = [s["CONTACT_ID"] for _, name, s in received if name == "RELEASE"]
    assert sorted(released) == sorted(ids)


# -- the C code cantools generates -------------------------------------------------------------

HARNESS_C = r"""/* Reads "U <16 hex digits>" (a CONTACT2 payload) and prints the generated unpack's raw values:
 * part slot counter, then the part's signals; "R <16 hex>" does the same for RELEASE. */
#include <stdio.h>
#include <string.h>
#include "optitac.h"

static int parse_hex(const char *text, uint8_t *out)
{
    size_t i;
    for (i = 0u; i < 8u; i++) {
        unsigned int byte;
        if (sscanf(&text[2u * i], "%2x", &byte) != 1) {
            return -1;
        }
        out[i] = (uint8_t)byte;
    }
    return 0;
}

int main(void)
{
    char line[128];
    while (fgets(line, sizeof(line), stdin) != NULL) {
        uint8_t d[8];
        if (strlen(line) < 18u || parse_hex(line + 2, d) != 0) {
            printf("ERR\n");
        } else if (line[0] == 'R') {
            struct optitac_release_t r;
            if (optitac_release_unpack(&r, d, 8u) != 0) {
                printf("ERR\n");
            } else {
                printf("%u %u\n", r.contact_id, r.counter);
            }
        } else {
            struct optitac_contact2_t m;
            if (optitac_contact2_unpack(&m, d, 8u) != 0) {
                printf("ERR\n");
            } else if (m.part == 0u) {
                printf("%u %u %u %d %d %u %u\n", m.part, m.slot, m.counter, m.x, m.y, m.major, m.minor);
            } else if (m.part == 1u) {
                printf("%u %u %u %d %u %u %u %u\n", m.part, m.slot, m.counter, m.angle, m.strength, m.shape,
                       m.confidence, m.n_contacts);
            } else {
                printf("%u %u %u %u %u %u %u %u\n", m.part, m.slot, m.counter, m.depth, m.force, m.contact_id,
                       m.flags, m.age);
            }
        }
    }
    return 0;
}
"""

SIGNALS = {0: ("X", "Y", "MAJOR", "MINOR"), 1: ("ANGLE", "STRENGTH", "SHAPE", "CONFIDENCE", "N_CONTACTS"),
           2: ("DEPTH", "FORCE", "CONTACT_ID", "FLAGS", "AGE")}


@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")
def test_generated_c_unpacks_what_cantools_packs(tmp_path):
    from fakes.generated_c import build_generated_c

    exe = build_generated_c(tmp_path, HARNESS_C)
    rng = np.random.default_rng(3)
    codec = CanCodec(protocol=2)
    payloads = []
    for k in range(60):
        msg = _contact(index=k % 4, contact_id=int(rng.integers(1, 256)), x_mm=float(rng.uniform(-41, 41)),
                       y_mm=float(rng.uniform(-41, 41)), angle_deg=float(rng.uniform(-90, 90)),
                       depth_mm=float(rng.uniform(0, 8.2)), force_n=float(rng.uniform(0, 20.5)),
                       flags=int(rng.integers(0, 128)), age_us=int(rng.integers(0, 65536)),
                       n_contacts=int(rng.integers(1, 5)))
        payloads += [("U", p) for p in codec.contact2_payloads(msg, k)]
        payloads.append(("R", codec.release_payload(int(rng.integers(0, 256)), k)))
    out = subprocess.run([str(exe)], input="".join(f"{kind} {p.hex()}\n" for kind, p in payloads),
                         capture_output=True, text=True, check=True, timeout=30).stdout.splitlines()
    db = cantools.database.load_file(str(DBC_PATH))
    assert len(out) == len(payloads) and "ERR" not in out
    for (kind, payload), line in zip(payloads, out):
        values = [int(v) for v in line.split()]
        if kind == "R":
            raw = db.decode_message("RELEASE", payload, scaling=False)
            assert values == [raw["CONTACT_ID"], raw["COUNTER"]]
            continue
        raw = db.decode_message("CONTACT2", payload, scaling=False, decode_choices=False)
        assert values == [raw["PART"], raw["SLOT"], raw["COUNTER"], *(raw[s] for s in SIGNALS[raw["PART"]])]
