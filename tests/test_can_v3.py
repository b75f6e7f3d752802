"""Protocol v3 on CAN (``link.can_protocol = 3``): each contact's MOTION beside v2's and v1's frames.

The codec against cantools, the service on python-can's virtual bus (the v1 stream unchanged, each MOTION
with its contact's CONTACT2 slot and counter), and the C code cantools generates from the DBC.
"""

from __future__ import annotations

import shutil
import subprocess
import threading

import cantools
import numpy as np
import pytest

from optitac_edge.errors import TransportError
from optitac_edge.io.protocol.can_codec import DBC_PATH, CanCodec, decode_frame
from optitac_edge.io.protocol.messages import MotionFlags, MotionMessage


def test_a_motion_decodes_to_its_values_within_the_dbc_resolution_and_saturates():
    codec = CanCodec(protocol=3)
    msg = MotionMessage(flags=0x1B, frame=9, index=2, contact_id=42, vx_mm_s=-12.344, vy_mm_s=30.011,
                        vibration=3.27)
    got = cantools.database.load_file(str(DBC_PATH)).decode_message("MOTION", codec.motion_payload(msg, 21))
    assert (got["SLOT"], got["COUNTER"], got["FLAGS"], got["CONTACT_ID"]) == (2, 21 % 16, 0x1B, 42)
    assert abs(got["VX"] + 12.344) <= 0.01 + 1e-9 and abs(got["VY"] - 30.011) <= 0.01 + 1e-9
    assert abs(got["VIBRATION"] - 3.27) <= 0.025 + 1e-9
    fast = MotionMessage(flags=0xFF, index=7, vx_mm_s=1e9, vy_mm_s=float("nan"), vibration=1e9)
    got = cantools.database.load_file(str(DBC_PATH)).decode_message("MOTION", codec.motion_payload(fast, 0))
    assert (got["SLOT"], got["FLAGS"], got["VY"]) == (3, 0x3F, 0) and got["VX"] == pytest.approx(163.82)
    assert got["VIBRATION"] == pytest.approx(204.75)


def test_a_database_without_motion_serves_v2_and_is_refused_for_v3(tmp_path):
    text = DBC_PATH.read_text()
    block = text[text.index("BO_ 773 MOTION"):]
    block = block[:block.index("\n\n")]  # the message and its signals
    path = tmp_path / "v2.dbc"
    path.write_text("\n".join(line for line in text.replace(block, "").splitlines() if " 773 " not in line) + "\n")
    CanCodec(dbc_path=path, protocol=2)
    with pytest.raises(TransportError, match="no message MOTION"):
        CanCodec(dbc_path=path, protocol=3)


def test_the_service_sends_each_contacts_motion_beside_unchanged_v1_and_v2_streams(bundle_path):
    """A press held then slid at 30 mm/s: the v1 pairs as before, three CONTACT2 parts per contact and frame,
    and one MOTION per contact with its slot and the frame's counter, the slide flagged."""
    import can
    from fakes.list_camera import ListCamera
    from fakes.slide import slide_frames

    from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.service.loop import Service
    from optitac_edge.service.wiring import open_board_transport

    bundle = load_bundle(bundle_path)
    frames = slide_frames(bundle.baseline_frames + 20, 40, 40, 30.0, seed=6)
    config = load_board_config("sim", env={}, overrides={
        "link.transport": "can", "link.can_interface": "virtual", "link.can_channel": "v3-test",
        "link.can_protocol": 3})
    with can.Bus(interface="virtual", channel="v3-test") as mcu:
        with open_board_transport(config) as transport:
            stats = Service(config, bundle, ListCamera(frames), transport).run(threading.Event())
        received = []
        while (msg := mcu.recv(timeout=0.2)) is not None:
            received.append(decode_frame(msg.arbitration_id, msg.data))
    names = [name for _, name, _ in received]
    assert [n for n in names if n in ("CONTACT_A", "CONTACT_B")] == ["CONTACT_A", "CONTACT_B"] * stats.sent
    motions = [s for _, name, s in received if name == "MOTION"]
    assert len(motions) == len(frames)  # one per frame: the contact's, or one saying "no contact"
    last_counter = None
    for k, (_, name, s) in enumerate(received):
        if name == "CONTACT_A":
            last_counter = s["COUNTER"]
        if name == "MOTION":
            assert s["COUNTER"] == last_counter
            if s["CONTACT_ID"]:
                part = received[k - 1]  # after the contact's three CONTACT2 parts
                assert part[1] == "CONTACT2" and part[2]["CONTACT_ID"] == s["CONTACT_ID"]
    sliding = [s for s in motions if s["FLAGS"] & MotionFlags.SLIDING]
    began = [s for s in motions if s["FLAGS"] & MotionFlags.SLIDE_BEGAN]
    assert len(began) == 1 and sliding and abs(sliding[-1]["VX"] - 30.0) < 3.0


HARNESS_C = r"""/* Reads lines "<16 hex digits>" (MOTION payloads) and prints the generated unpack's raw values:
 * slot counter flags contact_id vx vy vibration. */
#include <stdio.h>
#include <string.h>
#include "optitac.h"

int main(void)
{
    char line[64];
    while (fgets(line, sizeof line, stdin) != NULL) {
        uint8_t p[8];
        unsigned int b;
        int i, ok = 1;
        struct optitac_motion_t m;
        for (i = 0; i < 8; i++) {
            if (sscanf(line + 2 * i, "%2x", &b) != 1) ok = 0;
            p[i] = (uint8_t)b;
        }
        if (!ok || optitac_motion_unpack(&m, p, sizeof p) != 0) {
            printf("ERR\n");
            continue;
        }
        printf("%u %u %u %u %d %d %u\n", m.slot, m.counter, m.flags, m.contact_id, m.vx, m.vy, m.vibration);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")
def test_generated_c_unpacks_the_motion_cantools_packs(tmp_path):
    from fakes.generated_c import build_generated_c

    exe = build_generated_c(tmp_path, HARNESS_C)
    rng = np.random.default_rng(29)
    codec = CanCodec(protocol=3)
    payloads = [codec.motion_payload(MotionMessage(flags=int(rng.integers(0, 64)), index=int(rng.integers(0, 4)),
                                                   contact_id=int(rng.integers(0, 256)),
                                                   vx_mm_s=float(rng.uniform(-170, 170)),
                                                   vy_mm_s=float(rng.uniform(-170, 170)),
                                                   vibration=float(rng.uniform(0, 210))), k) for k in range(200)]
    out = subprocess.run([str(exe)], input="".join(f"{p.hex()}\n" for p in payloads), capture_output=True,
                         text=True, check=True, timeout=30).stdout.splitlines()
    db = cantools.database.load_file(str(DBC_PATH))
    assert len(out) == len(payloads) and "ERR" not in out
    for payload, line in zip(payloads, out):
        raw = db.decode_message("MOTION", payload, scaling=False)
        assert [int(v) for v in line.split()] == [raw[s] for s in ("SLOT", "COUNTER", "FLAGS", "CONTACT_ID", "VX",
                                                                   "VY", "VIBRATION")]
