"""The frame ring between a camera's capture thread and the frame loop (cameras/frame_ring.py)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.frame_ring import MAX_DEPTH, FrameRing


def _publish(ring: FrameRing, seq: int) -> None:
    ring.back.fill(seq % 256)
    ring.publish(1000 * seq, seq)


def test_up_to_depth_waiting_frames_are_all_delivered_in_order() -> None:
    ring = FrameRing((4, 6), depth=4)
    for seq in range(1, 5):
        _publish(ring, seq)
    got = [ring.take(0.1, "test") for _ in range(4)]
    assert [s for _, _, s in got] == [1, 2, 3, 4]
    assert [t for _, t, _ in got] == [1000, 2000, 3000, 4000]
    assert ring.overwritten == 0
    assert int(got[-1][0][0, 0]) == 4


def test_one_frame_more_than_depth_drops_the_oldest_and_counts_it() -> None:
    ring = FrameRing((4, 6), depth=3)
    for seq in range(1, 9):  # 8 published, 3 may wait
        _publish(ring, seq)
    assert ring.overwritten == 5
    seqs = []
    for _ in range(3):
        frame, _, seq = ring.take(0.1, "test")
        assert int(frame[0, 0]) == seq  # the buffer holds that frame's pixels
        seqs.append(seq)
    assert seqs == [6, 7, 8]
    assert ring.published == 8


def test_depth_one_is_a_latest_frame_slot() -> None:
    ring = FrameRing((2, 2), depth=1)
    for seq in range(1, 4):
        _publish(ring, seq)
    assert ring.take(0.1, "test")[2] == 3
    assert ring.overwritten == 2


def test_a_held_frame_is_not_written_until_the_next_take() -> None:
    ring = FrameRing((8, 8), depth=2)
    _publish(ring, 1)
    held, _, _ = ring.take(0.1, "test")
    for seq in range(2, 40):  # the writer laps the ring many times over
        _publish(ring, seq)
        assert not np.shares_memory(ring.back, held)
    assert np.all(held == 1)
    assert not held.flags.writeable


def test_take_times_out_with_a_camera_error_naming_the_source() -> None:
    ring = FrameRing((2, 2), depth=2)
    with pytest.raises(CameraError, match="no frame from cam0 within 0.05 s"):
        ring.take(0.05, "cam0")


def test_a_failure_is_raised_once_the_waiting_frames_are_taken() -> None:
    ring = FrameRing((2, 2), depth=4)
    _publish(ring, 1)
    _publish(ring, 2)
    ring.fail("device gone")
    assert ring.error == "device gone"
    assert [ring.take(0.1, "t")[2] for _ in range(2)] == [1, 2]
    with pytest.raises(CameraError, match="device gone"):
        ring.take(0.1, "t")


def test_wait_first_returns_on_the_first_frame_or_a_failure() -> None:
    ring = FrameRing((2, 2), depth=1)
    assert not ring.wait_first(0.01)
    _publish(ring, 1)
    assert ring.wait_first(0.01)
    failed = FrameRing((2, 2), depth=1)
    failed.fail("no stream")
    assert failed.wait_first(0.01)


@pytest.mark.parametrize("depth", [0, MAX_DEPTH + 1, 2.0, True])
def test_a_depth_out_of_range_is_refused(depth: object) -> None:
    with pytest.raises(CameraError, match="queue_frames"):
        FrameRing((2, 2), depth=depth)  # type: ignore[arg-type]


def test_every_published_frame_is_either_taken_or_counted_as_dropped_across_threads() -> None:
    ring = FrameRing((16, 16), depth=3)
    n = 3000
    taken: list[int] = []
    done = threading.Event()

    def writer() -> None:
        for seq in range(1, n + 1):
            _publish(ring, seq)
        done.set()

    thread = threading.Thread(target=writer)
    thread.start()
    while True:
        try:
            frame, _, seq = ring.take(0.2, "test")
        except CameraError:
            if done.is_set():
                break
            continue
        assert int(frame[0, 0]) == seq % 256 and int(frame[-1, -1]) == seq % 256
        taken.append(seq)
    thread.join()
    assert taken == sorted(taken) and len(set(taken)) == len(taken)
    assert taken[-1] == n
    assert len(taken) + ring.overwritten == n
