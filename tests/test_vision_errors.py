"""The vision errors carry fields: ``where`` (a param, a file), ``what`` (what came in) and ``expected``.

One table of representative failures, each raised by the real code on real files; every row
checks the three fields, the message composed from them and the JSON form.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import DyKnowError
from transformations import params
from transformations.calibration import load_calibration
from transformations.detection import DetectorConfig
from transformations.errors import CalibrationError, MediaError, ParamError, VisionError
from transformations.scene import Scene
from transformations.sources import IMAGE_EXTENSIONS, VideoSource, list_images


def _open_video(path: Path) -> None:
    # VideoSource checks its file in setup(), before it needs a manager: run just that
    source = VideoSource()
    source.params = {"path": str(path)}
    source.setup()


Raiser = Callable[[Path, Path], object]  # (data_dir, tmp_path) -> raises

CASES: list[tuple[str, Raiser, type[VisionError], str | None, str, str | None]] = [
    # id, what raises, class, where, what, expected ({data}: the shared data, {tmp}: a fresh folder)
    ("param-out-of-range", lambda d, t: DetectorConfig.from_params({"min_fill": 1.5}),
     ParamError, "param 'min_fill'", "got 1.5", "a number >= 0 and <= 1"),
    ("param-not-a-number", lambda d, t: DetectorConfig.from_params({"min_radius": "big"}),
     ParamError, "param 'min_radius'", "got 'big'", "a number"),
    ("param-not-whole", lambda d, t: DetectorConfig.from_params({"max_detections": 2.5}),
     ParamError, "param 'max_detections'", "got 2.5", "a whole number"),
    ("param-missing", lambda d, t: params.text({}, "path"),
     ParamError, "param 'path'", "is missing", "it in the spec or at spawn time"),
    ("unknown-choice", lambda d, t: DetectorConfig.from_params({"method": "yolo"}),
     ParamError, "param 'method'", "got 'yolo'", "one of 'contours', 'hough'"),
    ("two-params-disagree", lambda d, t: DetectorConfig.from_params({"hsv_lower": "40,90,80", "hsv_upper": "80,85,255"}),
     ParamError, "params 'hsv_lower'/'hsv_upper'", "saturation 90 > 85", "lower <= upper (only the hue may wrap around)"),
    ("unknown-camera", lambda d, t: Scene().render("side", 0, 64, 48),
     ParamError, None, "unknown camera 'side'", "one of bottom, top, ceiling"),
    ("missing-video-file", lambda d, t: _open_video(t / "nope.mp4"),
     MediaError, "param 'path'", "no such video file {tmp}/nope.mp4", None),
    ("not-a-video", lambda d, t: _open_video(d / "SOURCES.md"),
     MediaError, "video {data}/SOURCES.md", "OpenCV cannot open it", "a video file (e.g. .mp4, .avi) of a codec FFmpeg decodes"),
    ("folder-without-images", lambda d, t: list_images(t),
     MediaError, "folder {tmp}", "has no images", "files ending in " + ", ".join(IMAGE_EXTENSIONS)),
    ("calibration-without-matrix", lambda d, t: load_calibration(d / "calibration" / "calibration.yml"),
     CalibrationError, "{data}/calibration/calibration.yml", "missing key 'camera_matrix'", "a 3x3 !!opencv-matrix"),
    ("missing-calibration-file", lambda d, t: load_calibration(t / "nope.yml"),
     CalibrationError, "{tmp}/nope.yml", "no such calibration file", None),
]  # fmt: skip


@pytest.mark.parametrize(("raiser", "cls", "where", "what", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_errors_carry_where_what_and_expected(
    data_dir: Path,
    tmp_path: Path,
    raiser: Raiser,
    cls: type[VisionError],
    where: str | None,
    what: str,
    expected: str | None,
) -> None:
    def fill(text: str | None) -> str | None:
        return None if text is None else text.format(data=data_dir, tmp=tmp_path)

    with pytest.raises(cls) as info:
        raiser(data_dir, tmp_path)
    error = info.value
    assert isinstance(error, DyKnowError)
    assert (error.where, error.what, error.expected) == (fill(where), fill(what), fill(expected))
    message = f"{error.where}: {error.what}" if error.where else error.what
    assert str(error) == (f"{message}; expected {error.expected}" if error.expected else message)
    assert error.to_dict() == {
        "error": cls.__name__,
        "message": str(error),
        "what": fill(what),
        "where": fill(where),
        "expected": fill(expected),
    }


def test_the_vision_errors_stay_the_builtin_errors_they_were() -> None:
    # callers that caught ValueError or OSError before the errors had fields still catch them
    with pytest.raises(ValueError, match=r"^param 'rate_hz': got -1; expected a number >= 0$"):
        params.number({"rate_hz": -1}, "rate_hz", low=0)
    with pytest.raises(ValueError, match=r"^param 'hsv_lower': got '1,2,300'; expected every number in \[0, 255\]$"):
        params.numbers("1,2,300", "hsv_lower", 3, low=0, high=255)
    with pytest.raises(ValueError, match=r"^param 'x': got '-5'; expected every number >= 0$"):
        params.numbers("-5", "x", 1, low=0)  # one bound only
    with pytest.raises(OSError, match="^/nonexistent/folder: no such folder; expected a folder of images"):
        list_images("/nonexistent/folder")
