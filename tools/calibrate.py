"""Calibrate a camera from chessboard images and write an OpenCV calibration file.

    python tools/calibrate.py IMAGE_DIR --pattern 9x6 [--square 0.025] -o OUT.yml [--json]

IMAGE_DIR is a folder of images (or a glob such as ``'shots/*.png'``). The chessboard's inner
corners are found in each image (refined with ``cv2.cornerSubPix``, 11 x 11 window), then
``cv2.calibrateCamera`` computes the camera matrix and the distortion coefficients. OUT.yml
(YAML, or XML/JSON by extension) holds ``camera_matrix``, ``distortion_coefficients``, the image
size, the RMS reprojection error and the board geometry; ``Undistort`` reads it.

With ``--json`` it prints one line::

    {"images": n, "boards_found": k, "rms_px": e, "camera_matrix": [[...], [...], [...]], "dist_coeffs": [...]}

Errors (missing folder, no images, a corrupt image, no board found) are one line on stderr and
exit status 1; bad arguments exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout without installing

from transformations.calibration import calibrate_chessboard, save_calibration
from transformations.errors import VisionError
from transformations.sources import list_images


class ArgumentValueError(VisionError, argparse.ArgumentTypeError):
    """A malformed option value. ``where`` is None: argparse puts the option's name before the message, then exits with 2."""


def _pattern(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", text)
    if match is None or int(match.group(1)) < 2 or int(match.group(2)) < 2:
        raise ArgumentValueError(f"got {text!r}", expected="inner corners as COLSxROWS, such as 9x6")
    return int(match.group(1)), int(match.group(2))


def _square(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value > 0:
        raise ArgumentValueError(f"got {text!r}", expected="the square size in metres, such as 0.025")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command line: IMAGE_DIR, ``--pattern``, ``--square``, ``-o`` and ``--json``."""
    parser = argparse.ArgumentParser(prog="calibrate.py", description="Calibrate a camera from chessboard images.")
    parser.add_argument("images", metavar="IMAGE_DIR", help="folder of chessboard images, or a glob such as 'shots/*.png'")
    parser.add_argument("--pattern", type=_pattern, required=True, help="inner corners, COLSxROWS (e.g. 9x6)")
    parser.add_argument("--square", type=_square, default=0.025, help="side of a square in metres (default 0.025)")
    parser.add_argument(
        "-o", "--output", required=True, metavar="OUT.yml", help="calibration file to write (.yml, .yaml, .xml, .json)"
    )
    parser.add_argument("--json", action="store_true", help="print the result as one JSON line")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Calibrate from the images, write the file and print the result; 1 on a vision error (one line on stderr)."""
    args = build_parser().parse_args(argv)
    try:
        images = list_images(args.images)
        result = calibrate_chessboard(images, args.pattern, args.square)
        cols, rows = args.pattern
        path = save_calibration(
            args.output,
            result.calibration,
            extra={"nframes": result.boards_found, "board_width": cols, "board_height": rows, "square_size": args.square},
        )
    except VisionError as exc:
        print(f"calibrate.py: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result.to_dict()))
        return 0
    cal = result.calibration
    k = cal.camera_matrix
    missing = [str(image) for image, ok in zip(images, result.found, strict=True) if not ok]
    print(f"boards found: {result.boards_found}/{result.images}" + (f" (not in: {', '.join(missing)})" if missing else ""))
    print(f"RMS reprojection error: {cal.rms_px or 0.0:.4f} px")
    print(f"fx={k[0, 0]:.2f} fy={k[1, 1]:.2f} cx={k[0, 2]:.2f} cy={k[1, 2]:.2f}")
    print("distortion: " + ", ".join(f"{v:.5f}" for v in cal.dist_coeffs))
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
