"""The exceptions the vision units and tools raise.

They extend dyknow's tree, so ``except DyKnowError`` catches them too::

    DyKnowError
    └── VisionError          a vision unit or tool cannot do its job
        ├── ParamError       a unit param is malformed or out of range (also a ValueError)
        ├── MediaError       a video, image, folder or camera cannot be opened or decoded (also an OSError)
        └── CalibrationError a calibration file cannot be read or written, or calibration failed

Messages name the param or file, say what came in and what was expected.
"""

from __future__ import annotations

from dyknow import DyKnowError

__all__ = ["CalibrationError", "MediaError", "ParamError", "VisionError"]


class VisionError(DyKnowError):
    """Root of the errors raised by the vision units and tools."""


class ParamError(VisionError, ValueError):
    """A unit param is malformed or out of range."""


class MediaError(VisionError, OSError):
    """A video, image, folder or camera cannot be opened or decoded."""


class CalibrationError(VisionError, ValueError):
    """A calibration file cannot be read or written, or a calibration failed."""
