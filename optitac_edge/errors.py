"""One exception hierarchy for everything optitac-edge reports to a user.

The CLI turns any :class:`OptiTacError` into a one-line message and a non-zero
exit status; anything else is a bug.
"""

from __future__ import annotations


class OptiTacError(Exception):
    """Base class of every expected, user-facing error."""


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a stop, a closed SSH session) ends a command as Ctrl-C does: the rig is retracted,
    what was written is kept or marked incomplete."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class ConfigError(OptiTacError):
    """A configuration or layout file is malformed (message names file and key)."""


class RecordingError(OptiTacError):
    """A recording directory is missing, incomplete or garbled."""


class BundleError(OptiTacError):
    """A calibration bundle is missing, corrupted, truncated or of another version."""


class FrameMismatchError(OptiTacError):
    """A frame does not match the size or pixel format a bundle was built for."""


class FiberMapError(OptiTacError):
    """The fiber array could not be found reliably in the rest frames."""


class OrientationError(OptiTacError):
    """A bundle's fiber map disagrees with presses of known position, or presses cannot settle it."""


class CameraError(OptiTacError):
    """A camera backend failed to open or deliver a frame."""


class TransportError(OptiTacError):
    """A link to the MCU (serial, CAN) cannot be opened or is misconfigured."""


class PublishError(OptiTacError):
    """A network publisher (Zenoh) cannot be opened or is misconfigured."""


class RigError(OptiTacError):
    """An indentation rig refused a move, raised an alarm, or stopped answering."""


class OutputError(OptiTacError):
    """An output file cannot be written (the message names it): full disk, I/O error, a target
    that is not a regular file."""


class PipelineBusy(OptiTacError, RuntimeError):
    """A :class:`~optitac_edge.core.pipeline.Pipeline` was asked to process a frame while another thread's
    frame was still in it: a pipeline keeps one sensor's state from frame to frame, so it serves one thread
    (one pipeline per thread, or a lock around it)."""


class MissingExtraError(OptiTacError):
    """A feature needs an optional package that is not installed (the message says which extra)."""


#: The pip extra that installs each optional module (``pip install 'optitac-edge[EXTRA]'``).
EXTRA_OF_MODULE = {
    "sklearn": "calibrate", "threadpoolctl": "calibrate", "matplotlib": "calibrate", "onnx": "calibrate",
    "onnxruntime": "onnx", "can": "can", "cantools": "can", "smbus2": "board", "rtde_control": "ur",
    "rtde_receive": "ur", "zenoh": "zenoh", "xxhash": "zenoh", "mcap": "mcap", "mcap_ros2": "mcap", "foxglove": "foxglove",
}


def missing_extra(module: str, feature: str, extra: str | None = None) -> MissingExtraError:
    """The one-line error for ``feature`` when the optional ``module`` is not installed (``extra``: the pip
    extra that installs it, default from :data:`EXTRA_OF_MODULE`)."""
    root = module.split(".")[0]
    extra = extra or EXTRA_OF_MODULE.get(root)
    if root == "picamera2":
        return MissingExtraError(f"{feature} needs picamera2: on Raspberry Pi OS, sudo apt install python3-picamera2 "
                                 "and a virtual environment with --system-site-packages (tools/install.sh does both)")
    how = f"pip install 'optitac-edge[{extra}]'" if extra else f"pip install {root}"
    return MissingExtraError(f"{feature} needs {root}, which is not installed: {how}")
