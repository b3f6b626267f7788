"""The exceptions the vision units and tools raise.

They extend dyknow's tree, so ``except DyKnowError`` catches them too::

    DyKnowError
    └── VisionError          a vision unit or tool cannot do its job
        ├── ParamError       a unit param (or a vision function's argument) is malformed or out of range
        │                    (also a ValueError)
        ├── MediaError       a video, image, folder or camera cannot be opened or decoded (also an OSError)
        └── CalibrationError a calibration file cannot be read or written, or calibration failed

Like every dyknow error they carry fields: ``where`` names the param (``param 'min_fill'``), the
file, image, video or camera concerned (None when nothing in particular), ``what`` is the problem
with what came in (``got 1.5``) and ``expected`` what would have been accepted; the message is
``"WHERE: WHAT; expected EXPECTED"`` (see :mod:`dyknow.errors`).
"""

from __future__ import annotations

from dyknow import DyKnowError

__all__ = ["CalibrationError", "MediaError", "ParamError", "VisionError"]


class VisionError(DyKnowError):
    """Root of the errors raised by the vision units and tools."""


class ParamError(VisionError, ValueError):
    """A unit param, or an argument of a vision function (a camera name, an image size), is malformed or out of range."""


class MediaError(VisionError, OSError):
    """A video, image, folder or camera cannot be opened or decoded."""


class CalibrationError(VisionError, ValueError):
    """A calibration file cannot be read or written, or a calibration failed."""
