"""Run the BallDetector unit over every frame of a video and report what it found.

    python tools/eval_ball.py VIDEO [--spec LABEL] [--specs FILE ...] [--param NAME=VALUE ...] [--json]

The detector is the real unit: it is spawned from its spec (``ball-detector(bottom)`` in
``specs/vision.xml`` unless ``--spec``/``--specs`` say otherwise) in a dyknow manager, with the
``--param`` overrides typed and checked as for any spawn, and each frame goes through the same
code path as in a running pipeline: the Subsampler's BGR -> HSV conversion, then the unit's own
``detect``. Every frame is evaluated (none is dropped, unlike a live stream).

With ``--json`` it prints one line::

    {"frames": n, "detections": [{"frame": i, "x": px, "y": px, "radius": px} or null, ...]}

with the best detection of each frame (null when there is none). Errors (a missing or unreadable
video, an unknown spec or param) are one line on stderr and exit status 1.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout without installing

import cv2

from dyknow import DyKnowError, Manager
from transformations.detection import BallDetector
from transformations.errors import VisionError
from transformations.imaging import convert

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SPECS = REPO / "specs" / "vision.xml"
DEFAULT_LABEL = "ball-detector(bottom)"


class EvalError(VisionError):
    """A problem with the video or the detector spec; the message is printed as is."""


class ArgumentValueError(VisionError, argparse.ArgumentTypeError):
    """A malformed option value. ``where`` is None: argparse puts the option's name before the message, then exits with 2."""


def _param(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise ArgumentValueError(f"got {text!r}", expected="NAME=VALUE, such as hsv_lower=40,80,80")
    return name.strip(), value


def build_parser() -> argparse.ArgumentParser:
    """The command line: VIDEO, ``--spec``, ``--specs``, ``--param`` (repeatable) and ``--json``."""
    parser = argparse.ArgumentParser(prog="eval_ball.py", description="Run the BallDetector unit over every frame of a video.")
    parser.add_argument("video", metavar="VIDEO", help="video file (anything OpenCV's FFmpeg reads)")
    parser.add_argument("--spec", default=DEFAULT_LABEL, metavar="LABEL", help=f"detector spec label (default {DEFAULT_LABEL})")
    parser.add_argument(
        "--specs",
        nargs="+",
        default=[str(DEFAULT_SPECS)],
        metavar="FILE",
        help="spec files or folders (default specs/vision.xml)",
    )
    parser.add_argument(
        "--param", type=_param, action="append", default=[], metavar="NAME=VALUE", help="override a detector param (repeatable)"
    )
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    return parser


def evaluate(video: str, label: str, specs: list[str], overrides: dict[str, str]) -> dict[str, Any]:
    """Run the detector spawned from ``label`` over every frame of ``video``; the JSON result."""
    path = Path(video).expanduser()
    if not path.is_file():
        raise EvalError("no such video file", where=str(path), expected="a video file (e.g. .mp4, .avi)")
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise EvalError("OpenCV cannot open it", where=f"video {path}", expected="a video file (e.g. .mp4, .avi)")
        with Manager("eval-ball", specs=specs, serve=False) as manager:
            info = manager.spawn(label, "detector", params=overrides)
            if info.state != "running":
                raise EvalError(f"did not start: {info.error}", where=f"detector {label!r}")
            unit = manager.unit("detector")
            if not isinstance(unit, BallDetector):
                raise EvalError(
                    f"runs {type(unit).__name__}", where=f"spec {label!r}", expected=f"a BallDetector spec such as {DEFAULT_LABEL}"
                )
            detections: list[dict[str, float] | None] = []
            while True:
                ok, frame = capture.read()
                if not ok:
                    break
                found = unit.detect(convert(frame, "hsv"))["detections"]
                best = found[0] if found else None
                i = len(detections)
                detections.append(
                    None if best is None else {"frame": i, "x": best["x"], "y": best["y"], "radius": best["radius"]}
                )
    finally:
        capture.release()
    if not detections:
        raise EvalError("no frame could be decoded", where=f"video {path}", expected="a video file OpenCV can read")
    return {"frames": len(detections), "detections": detections}


def main(argv: list[str] | None = None) -> int:
    """Evaluate the video and print the result; 1 on an error of the video, the spec or a param (one line on stderr)."""
    args = build_parser().parse_args(argv)
    # A detector that fails at setup is reported below, in one line; the proxy's log would repeat it.
    logging.getLogger("dyknow.proxy").setLevel(logging.CRITICAL)
    try:
        result = evaluate(args.video, args.spec, args.specs, dict(args.param))
    except DyKnowError as exc:  # EvalError, and the manager's errors (an unknown spec or param)
        print(f"eval_ball.py: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result))
        return 0
    n = result["frames"]
    hits = sum(d is not None for d in result["detections"])
    print(f"{args.video}: {n} frames, a ball in {hits} ({100.0 * hits / n:.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
