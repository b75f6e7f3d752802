import json

import numpy as np
import pytest

from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import Recording, RecordingMeta
from optitac_edge.io.recording_writer import Press, RecordingWriter


def _write(path, n=8, shape=(12, 16), rest=5, truth=True):
    with RecordingWriter(path, n, shape, RecordingMeta(rest_frames=rest, fps=30.0, extra={"k": 1}),
                         with_truth=truth) as w:
        for i in range(n):
            w.write(i, np.full(shape, i, dtype=np.uint8))
            if truth:
                if i < rest:
                    w.write_truth(i, None)
                else:
                    w.write_truth(i, Press("circle", 1.0, -2.0, 0.0, 5.0, 3.0))
    return path


def test_round_trip_streams_memory_mapped(tmp_path):
    rec = Recording(_write(tmp_path / "r"))
    assert len(rec) == 8 and rec.pixel_format == "gray" and (rec.height, rec.width) == (12, 16)
    assert isinstance(rec.frames, np.memmap)
    assert rec.meta.rest_frames == 5 and rec.meta.fps == 30.0 and rec.meta.extra == {"k": 1}
    assert [int(f[0, 0]) for f in rec] == list(range(8))
    t = rec.truth
    assert t is not None and len(t) == 8
    assert not t.contact[:5].any() and t.contact[5:].all()
    assert np.isnan(t.x_mm[0]) and t.x_mm[6] == 1.0 and t.shape[6] == "circle" and t.shape[0] == ""


def test_rgb_recording(tmp_path):
    rec = Recording(_write(tmp_path / "r", shape=(6, 7, 3), truth=False))
    assert rec.pixel_format == "rgb" and rec.frame_shape == (6, 7, 3) and rec.truth is None


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: (p / "meta.json").unlink(), "no meta.json"),
        (lambda p: (p / "frames.npy").unlink(), "no frames.npy"),
        (lambda p: (p / "meta.json").write_text("{nope"), "garbled meta.json"),
        (lambda p: (p / "meta.json").write_text(json.dumps({"rest_frames": 2, "fps": 30})), "rest_frames"),
        (lambda p: (p / "meta.json").write_text(json.dumps({"rest_frames": 5, "fps": -1})), "fps"),
        (lambda p: (p / "frames.npy").write_bytes(b"garbage" * 10), "garbled or truncated"),
        (lambda p: (p / "frames.npy").write_bytes((p / "frames.npy").read_bytes()[:500]), "garbled or truncated"),
        (lambda p: np.save(p / "frames.npy", np.zeros((4, 3, 3), np.float32)), "uint8"),
        (lambda p: (p / "truth.csv").write_text("frame,contact\n"), "header"),
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm\n99,1,circle,0,0,0,5,3\n"), "out of range"),
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm\n1,1,blob,0,0,0,5,3\n"), "unknown shape"),
        # implausible values: depths x 1e300 gave "fitted rmse inf", a force of 1e308 N the wrong reason
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm\n1,1,circle,0,0,0,5,3e300\n"),
         r"line 2: depth_mm 3e\+300 is outside 0..1000"),
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm\n1,1,circle,1e300,0,0,5,3\n"),
         "x_mm 1e\\+300 is outside"),
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm,force_n\n1,1,circle,0,0,0,5,3,1e308\n"),
         "force_n must be a force of 0..100000 N"),
        # a rig's collection has a row for every frame: lost rows were scored without a word
        (lambda p: (p / "truth.csv").write_text(
            "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm,phase,rig_x_mm,rig_y_mm,rig_z_mm\n"
            + "".join(f"{i},0,,,,,,,rest,1,2,3\n" for i in range(7))), "rows for 7 of the recording's 8 frames"),
    ],
)
def test_damaged_recording_is_refused_with_a_reason(tmp_path, damage, message):
    path = _write(tmp_path / "r")
    damage(path)
    with pytest.raises(RecordingError, match=message):
        Recording(path)


def test_missing_directory(tmp_path):
    with pytest.raises(RecordingError, match="not found"):
        Recording(tmp_path / "absent")


def test_a_blank_angle_does_not_make_every_frame_a_press(tmp_path):
    """A circle's angle may be blank (the format allows it): NaN != NaN made every frame a press of its own
    (224 presses instead of 112)."""
    from optitac_edge.calibration.evaluation import press_ids

    path = tmp_path / "truth.csv"
    rows = ["frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm"]
    rows += [f"{i},0,,,,,," for i in range(3)] + [f"{i},1,circle,1,2,,5,3" for i in range(3, 7)]
    rows += ["7,0,,,,,,"] + [f"{i},1,circle,1,2,,5,3" for i in range(8, 10)]
    path.write_text("\n".join(rows) + "\n")
    from optitac_edge.io.recording import read_truth

    assert press_ids(read_truth(path, 10)).tolist() == [-1, -1, -1, 0, 0, 0, 0, -1, 1, 1]
