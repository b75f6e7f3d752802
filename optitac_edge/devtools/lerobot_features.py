"""The tactile features of a LeRobot dataset: their names, shapes and dtypes, and one frame's values.

Numpy only (no LeRobot, no torch): the export (:mod:`optitac_edge.devtools.lerobot_export`) and the LeRobot
plugin fill the same features from a frame's result. Every value is named in the dataset's ``info.json``:

``observation.tactile.contacts``  float64 (MAX_CONTACTS × 12,): for each contact slot, strongest first,
                                  :data:`CONTACT_FIELDS` (``present`` 0: an empty slot, all its fields 0;
                                  an unknown value of a present contact, e.g. a depth without a depth model: NaN)
``observation.tactile.state``     float64 (5,): :data:`STATE_FIELDS`
``observation.tactile.t_ns``      int64 (1,): the frame's capture time, CLOCK_MONOTONIC ns (LeRobot's own
                                  ``timestamp`` is the frame's index over the rate)
``observation.tactile.fibers``    float32 (N,): each fibre's inverted signal (``Pipeline.signal``), layout order
``observation.images.tactile``    video 224 × 224 × 3 (optional): the tactile surface, :func:`surface_image`
``truth.contact``                 float64 (9,): the recording's truth (:data:`TRUTH_FIELDS`; all NaN in a frame
                                  without a truth row, e.g. a rig's moves, or a recording without truth)
``truth.shape``                   int64 (1,): index into the feature's names (``none`` first)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import cv2
import numpy as np

from optitac_edge.core.options import MAX_CONTACTS

if TYPE_CHECKING:
    from optitac_edge.core.frame_result import FrameResult
    from optitac_edge.io.recording import Truth

#: The fields of one contact slot of ``observation.tactile.contacts``.
CONTACT_FIELDS: tuple[str, ...] = ("present", "x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg", "depth_mm",
                                   "force_n", "vx_mm_s", "vy_mm_s", "sliding", "contact_id")
#: ``observation.tactile.state``: the frame's contact count, vibration (NaN while learned) and flags (0/1).
STATE_FIELDS: tuple[str, ...] = ("n_contacts", "vibration", "vibrating", "baseline_ready", "saturated")
#: ``truth.contact``: the truth.csv columns (``contact`` 0/1; NaN where the recording has no such column).
TRUTH_FIELDS: tuple[str, ...] = ("contact", "x_mm", "y_mm", "angle_deg", "size_mm", "depth_mm", "force_n",
                                 "vx_mm_s", "vy_mm_s")
#: The side of the tactile image, px (tactile encoders such as Sparsh take 224 × 224).
IMAGE_SIDE = 224
#: The surface shown white in the tactile image, in units of the level the pipeline truncates it at (the API's
#: ``Reading.surface``): the simulated sensor's presses peak at 35 to 73 (10th and 99th percentile, 240 fps).
IMAGE_FULL_SCALE = 64.0
CONTACTS = "observation.tactile.contacts"
STATE = "observation.tactile.state"
T_NS = "observation.tactile.t_ns"
FIBERS = "observation.tactile.fibers"
IMAGE = "observation.images.tactile"
TRUTH = "truth.contact"
TRUTH_SHAPE = "truth.shape"


def tactile_features(fiber_ids: Sequence[int] | np.ndarray, *, video: bool = False,
                     truth_shapes: Sequence[str] | None = None) -> dict[str, dict[str, object]]:
    """LeRobot's feature description of the tactile features (``LeRobotDataset.create(features=...)``).

    Parameters
    ----------
    fiber_ids : sequence of int, or ndarray of shape (N,)
        The layout's fibre ids, in layout order (the names of ``observation.tactile.fibers``).
    video : bool
        Add ``observation.images.tactile``.
    truth_shapes : sequence of str, optional
        Add the truth features; the shape names the recordings' truth holds (``none`` is put first).
    """
    names = [f"contact{k}.{f}" for k in range(MAX_CONTACTS) for f in CONTACT_FIELDS]
    out: dict[str, dict[str, object]] = {
        CONTACTS: {"dtype": "float64", "shape": (len(names),), "names": names},
        STATE: {"dtype": "float64", "shape": (len(STATE_FIELDS),), "names": list(STATE_FIELDS)},
        T_NS: {"dtype": "int64", "shape": (1,), "names": ["t_ns"]},
        FIBERS: {"dtype": "float32", "shape": (len(fiber_ids),), "names": [f"fiber{int(i)}" for i in fiber_ids]},
    }
    if video:
        out[IMAGE] = {"dtype": "video", "shape": (IMAGE_SIDE, IMAGE_SIDE, 3),
                      "names": ["height", "width", "channels"]}
    if truth_shapes is not None:
        out[TRUTH] = {"dtype": "float64", "shape": (len(TRUTH_FIELDS),), "names": list(TRUTH_FIELDS)}
        out[TRUTH_SHAPE] = {"dtype": "int64", "shape": (1,), "names": shape_names(truth_shapes)}
    return out


def shape_names(shapes: Sequence[str]) -> list[str]:
    """``none`` and the other shape names, sorted: the index ``truth.shape`` holds."""
    return ["none", *sorted(set(shapes) - {"", "none"})]


class ContactFields(Protocol):
    """What a contact slot is made of: a pipeline's ``ContactEstimate`` or the public API's ``Contact``."""

    x_mm: float
    y_mm: float
    major_mm: float
    minor_mm: float
    angle_deg: float
    depth_mm: float
    force_n: float
    vx_mm_s: float
    vy_mm_s: float
    sliding: bool


def contact_slot(c: ContactFields, contact_id: int) -> tuple[float, ...]:
    """One present contact's values in :data:`CONTACT_FIELDS` order (its id given: the two kinds name it
    ``contact_id`` and ``id``)."""
    return (1.0, float(c.x_mm), float(c.y_mm), float(c.major_mm), float(c.minor_mm), float(c.angle_deg),
            float(c.depth_mm), float(c.force_n), float(c.vx_mm_s), float(c.vy_mm_s), float(bool(c.sliding)),
            float(contact_id))


def frame_values(result: FrameResult, signal: np.ndarray) -> dict[str, np.ndarray]:
    """The tactile features of one frame: ``observation.tactile.*`` (new arrays).

    Parameters
    ----------
    result : FrameResult
        The pipeline's result of the frame.
    signal : ndarray, shape (N,), float32
        The pipeline's per-fibre signal after the frame (``Pipeline.signal``).
    """
    contacts = np.zeros((MAX_CONTACTS, len(CONTACT_FIELDS)), dtype=np.float64)
    for k, c in enumerate(result.touching()):
        contacts[k] = contact_slot(c, c.contact_id)
    state = np.array([result.n_contacts, result.vibration, bool(result.vibrating), bool(result.baseline_ready),
                      bool(result.saturated)], dtype=np.float64)
    return {CONTACTS: contacts.reshape(-1), STATE: state, T_NS: np.array([result.t_ns], dtype=np.int64),
            FIBERS: np.array(signal, dtype=np.float32)}


def truth_rows(truth: Truth) -> dict[int, int]:
    """Frame number -> its row of ``truth`` (a rig's recording has rows for some frames only: its holds)."""
    return {int(f): k for k, f in enumerate(truth.frame)}


def truth_values(truth: Truth | None, i: int | None, names: Sequence[str]) -> dict[str, np.ndarray]:
    """Row ``i`` of a recording's truth as ``truth.contact`` and ``truth.shape`` (an index into ``names``);
    ``i`` or ``truth`` None: a frame without a truth row (every value NaN, the shape ``none``)."""
    if truth is None or i is None:
        return {TRUTH: np.full(len(TRUTH_FIELDS), np.nan), TRUTH_SHAPE: np.array([0], dtype=np.int64)}

    def col(a: np.ndarray | None) -> float:
        return math.nan if a is None else float(a[i])

    row = np.array([float(bool(truth.contact[i])), col(truth.x_mm), col(truth.y_mm), col(truth.angle_deg),
                    col(truth.size_mm), col(truth.depth_mm), col(truth.force_n), col(truth.vx_mm_s),
                    col(truth.vy_mm_s)], dtype=np.float64)
    shape = str(truth.shape[i]) or "none"
    return {TRUTH: row, TRUTH_SHAPE: np.array([names.index(shape)], dtype=np.int64)}


def surface_image(surface: np.ndarray, full_scale: float = IMAGE_FULL_SCALE) -> np.ndarray:
    """The tactile surface as a 224 × 224 RGB image: a press bright on black (uint8, all three channels equal).

    Parameters
    ----------
    surface : ndarray, shape (n, n), float32
        The tactile surface in units of its truncation level (the API's ``Reading.surface``).
    full_scale : float
        The value shown white (> 0); more is clipped.
    """
    level = np.clip(surface * np.float32(255.0 / full_scale), 0.0, 255.0).astype(np.uint8)
    gray = cv2.resize(level, (IMAGE_SIDE, IMAGE_SIDE), interpolation=cv2.INTER_LINEAR)
    return np.repeat(gray[:, :, None], 3, axis=2)
