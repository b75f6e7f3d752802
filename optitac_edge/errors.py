"""One exception hierarchy for everything optitac-edge reports to a user.

The CLI turns any :class:`OptiTacError` into a one-line message and a non-zero
exit status; anything else is a bug.
"""

from __future__ import annotations


class OptiTacError(Exception):
    """Base class of every expected, user-facing error."""


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


class CameraError(OptiTacError):
    """A camera backend failed to open or deliver a frame."""


class TransportError(OptiTacError):
    """A link to the MCU (serial, CAN) cannot be opened or is misconfigured."""


class OutputError(OptiTacError):
    """An output file cannot be written (the message names it): full disk, I/O error, a target
    that is not a regular file."""


class MissingExtraError(OptiTacError):
    """A feature needs an optional package that is not installed (the message says which extra)."""
