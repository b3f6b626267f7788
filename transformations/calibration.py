"""Camera calibration: OpenCV calibration files and chessboard calibration.

Files are OpenCV ``FileStorage`` documents (YAML, XML or JSON, chosen by the extension) holding
at least::

    camera_matrix: !!opencv-matrix            # 3 x 3
       rows: 3
       cols: 3
       dt: d
       data: [ fx, 0., cx, 0., fy, cy, 0., 0., 1. ]
    distortion_coefficients: !!opencv-matrix  # 5 x 1 or 1 x 5 (4, 8, 12 or 14 values also work)
       ...

and optionally ``image_width`` / ``image_height`` (the size the matrix refers to) and the RMS
reprojection error (``rms`` or ``avg_reprojection_error``). This covers the files OpenCV's own
calibration samples write (``left_intrinsics.yml``), the ChArUco tutorial's (a 1 x 5 distortion
row) and hand-written ones without size fields.

:func:`load_calibration` reads one, :func:`save_calibration` writes one, and
:func:`calibrate_chessboard` computes one from images of a chessboard (what
``tools/calibrate.py`` runs). Every failure is a :class:`~transformations.errors.CalibrationError`
whose ``where`` names the file (or image) and ``what`` what was wrong.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from transformations.errors import CalibrationError

__all__ = [
    "Calibration",
    "ChessboardCalibration",
    "calibrate_chessboard",
    "find_chessboard",
    "load_calibration",
    "save_calibration",
]

# Accepted names, the first being the one written.
_MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
_DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
_RMS_KEYS = ("rms", "avg_reprojection_error")
_DIST_SIZES = (4, 5, 8, 12, 14)


@dataclass(frozen=True, slots=True)
class Calibration:
    """A camera's intrinsics: the 3x3 ``camera_matrix`` and the distortion coefficients.

    ``image_size`` is ``(width, height)`` the matrix refers to, when known; ``rms_px`` the RMS
    reprojection error of the calibration, when known; ``path`` the file it was read from.
    """

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int] | None = None
    rms_px: float | None = None
    path: str | None = None

    def matrix_for(self, width: int, height: int) -> np.ndarray:
        """The camera matrix for images of ``width`` x ``height`` (scaled when the size differs).

        Raises :class:`CalibrationError` when the aspect ratio differs from the calibrated one:
        such frames were cropped, and no scaling makes the matrix right.
        """
        matrix = self.camera_matrix.copy()
        if self.image_size is None or self.image_size == (width, height):
            return matrix
        cal_w, cal_h = self.image_size
        sx, sy = width / cal_w, height / cal_h
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise CalibrationError(
                f"frame size {width}x{height} does not match the calibration ({cal_w}x{cal_h})",
                where=self.path,
                expected="frames of the calibrated size or of the same aspect ratio",
            )
        matrix[0, :] *= sx
        matrix[1, :] *= sy
        return matrix


@dataclass(frozen=True, slots=True)
class ChessboardCalibration:
    """The result of :func:`calibrate_chessboard`: the calibration and what was used for it.

    ``found`` lists, per image in input order, whether the board was found in it.
    """

    calibration: Calibration
    images: int
    boards_found: int
    found: tuple[bool, ...] = field(default=())

    def to_dict(self) -> dict[str, object]:
        """The machine-readable summary ``tools/calibrate.py --json`` prints."""
        cal = self.calibration
        return {
            "images": self.images,
            "boards_found": self.boards_found,
            "rms_px": cal.rms_px,
            "camera_matrix": [[float(v) for v in row] for row in cal.camera_matrix],
            "dist_coeffs": [float(v) for v in cal.dist_coeffs],
        }


def _open(path: Path, mode: int) -> cv2.FileStorage:
    try:
        storage = cv2.FileStorage(str(path), mode)
    except (cv2.error, SystemError) as exc:
        # OpenCV's parser reports through a chained cv2.error; keep its last line (the reason).
        reason = str(exc.__cause__ or exc).strip().splitlines()[-1]
        raise CalibrationError(
            f"not an OpenCV FileStorage file ({reason})", where=str(path), expected="YAML, XML or JSON as cv2.FileStorage writes"
        ) from exc
    if not storage.isOpened():
        raise CalibrationError(f"cannot open it for {'reading' if mode == cv2.FILE_STORAGE_READ else 'writing'}", where=str(path))
    return storage


def _find(root: cv2.FileNode, keys: Sequence[str]) -> tuple[str, cv2.FileNode] | None:
    for key in keys:
        node = root.getNode(key)
        if not node.empty() and not node.isNone():
            return key, node
    return None


def _matrix(path: Path, key: str, node: cv2.FileNode) -> np.ndarray:
    # A !!opencv-matrix node is a map (rows, cols, dt, data); calling mat() on anything else
    # trips an assertion inside OpenCV, so check first. A plain list of numbers is accepted too.
    value: np.ndarray | None = None
    if node.isMap():
        value = node.mat()
    elif node.isSeq():
        items = [node.at(i) for i in range(node.size())]
        if all(item.isReal() or item.isInt() for item in items):
            value = np.array([item.real() for item in items], dtype=np.float64)
    if value is None or value.size == 0:
        raise CalibrationError(f"key {key!r} is not a matrix", where=str(path), expected="an !!opencv-matrix or a list of numbers")
    return np.asarray(value, dtype=np.float64)


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read an OpenCV calibration file (see the module documentation for what it must hold)."""
    file = Path(path).expanduser()
    if not file.exists():
        raise CalibrationError("no such calibration file", where=str(file))
    if not file.is_file():
        raise CalibrationError("is not a file", where=str(file), expected="an OpenCV calibration file (.yml, .yaml, .xml, .json)")
    storage = _open(file, cv2.FILE_STORAGE_READ)
    try:
        root = storage.root()
        if not root.isMap():
            raise CalibrationError(
                "the document is not a map of keys", where=str(file), expected="camera_matrix and distortion_coefficients"
            )
        found = _find(root, _MATRIX_KEYS)
        if found is None:
            raise CalibrationError(
                "missing key 'camera_matrix'", where=str(file), expected="a 3x3 !!opencv-matrix"
            )
        matrix = _matrix(file, *found)
        if matrix.size != 9:
            raise CalibrationError(f"{found[0]!r} has shape {matrix.shape}", where=str(file), expected="3x3")
        matrix = matrix.reshape(3, 3)
        if not np.all(np.isfinite(matrix)) or matrix[0, 0] <= 0 or matrix[1, 1] <= 0:
            raise CalibrationError(f"{found[0]!r} is {matrix.tolist()}", where=str(file), expected="positive focal lengths fx, fy")
        found = _find(root, _DIST_KEYS)
        if found is None:
            raise CalibrationError(
                "missing key 'distortion_coefficients'", where=str(file), expected="a 5x1 or 1x5 !!opencv-matrix"
            )
        dist = _matrix(file, *found)
        if (dist.ndim == 2 and 1 not in dist.shape) or dist.ndim > 2 or dist.size not in _DIST_SIZES:
            raise CalibrationError(
                f"{found[0]!r} has shape {dist.shape}", where=str(file), expected="a row or column of 4, 5, 8, 12 or 14 values"
            )
        dist = dist.reshape(-1)
        size = None
        width, height = root.getNode("image_width"), root.getNode("image_height")
        if not width.empty() and not height.empty():
            w, h = round(width.real()), round(height.real())
            if w <= 0 or h <= 0:
                raise CalibrationError(f"image_width/image_height are {w}x{h}", where=str(file), expected="positive sizes")
            size = (w, h)
        rms = None
        found = _find(root, _RMS_KEYS)
        if found is not None and (found[1].isReal() or found[1].isInt()):
            rms = float(found[1].real())
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"cannot read it: {str(exc.__cause__ or exc).strip().splitlines()[-1]}", where=str(file)) from exc
    finally:
        storage.release()
    return Calibration(matrix, dist, size, rms, str(file))


def save_calibration(
    path: str | os.PathLike[str],
    calibration: Calibration,
    *,
    extra: dict[str, int | float | str] | None = None,
) -> Path:
    """Write ``calibration`` as an OpenCV FileStorage file (format by extension); returns the path.

    Written keys: ``calibration_time``, ``image_width``/``image_height`` (when known),
    ``camera_matrix`` (3x3), ``distortion_coefficients`` (a column, as OpenCV's samples write
    it), ``rms`` and ``avg_reprojection_error`` (the same value; the second is the name OpenCV's
    calibration sample uses), then ``extra`` (numbers or text, e.g. the board size).
    """
    file = Path(path).expanduser()
    if file.suffix.lower() not in (".yml", ".yaml", ".xml", ".json"):
        raise CalibrationError(
            f"unknown calibration file extension {file.suffix!r}", where=str(file), expected=".yml, .yaml, .xml or .json"
        )
    if not file.parent.is_dir():
        raise CalibrationError(f"folder {file.parent} does not exist", where=str(file))
    storage = _open(file, cv2.FILE_STORAGE_WRITE)
    try:
        storage.write("calibration_time", time.strftime("%Y-%m-%d %H:%M:%S %z"))
        if calibration.image_size is not None:
            storage.write("image_width", int(calibration.image_size[0]))
            storage.write("image_height", int(calibration.image_size[1]))
        storage.write(_MATRIX_KEYS[0], np.asarray(calibration.camera_matrix, dtype=np.float64).reshape(3, 3))
        storage.write(_DIST_KEYS[0], np.asarray(calibration.dist_coeffs, dtype=np.float64).reshape(-1, 1))
        if calibration.rms_px is not None:
            for key in _RMS_KEYS:
                storage.write(key, float(calibration.rms_px))
        for key, value in (extra or {}).items():
            storage.write(key, value)
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"cannot write it: {str(exc.__cause__ or exc).strip().splitlines()[-1]}", where=str(file)) from exc
    finally:
        storage.release()
    return file


def find_chessboard(grey: np.ndarray, pattern: tuple[int, int]) -> np.ndarray | None:
    """The inner corners of a ``pattern`` (columns x rows) chessboard in a grey image, or None.

    Corners are refined to sub-pixel accuracy with ``cv2.cornerSubPix`` (11 x 11 window).
    """
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(grey, pattern, None, flags)
    if not ok or corners is None:
        return None
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    return cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), criteria)


def calibrate_chessboard(
    images: Sequence[str | os.PathLike[str]],
    pattern: tuple[int, int] = (9, 6),
    square_m: float = 0.025,
) -> ChessboardCalibration:
    """Calibrate a camera from chessboard images (``pattern`` = inner corners, columns x rows).

    Every image must decode and all must have the same size; images where the board is not
    found are skipped. Raises :class:`CalibrationError` naming the offending image, or when no
    board is found anywhere.
    """
    if not images:
        raise CalibrationError("no images given", expected="chessboard images")
    cols, rows = pattern
    if cols < 2 or rows < 2:
        raise CalibrationError(f"got {cols}x{rows}", where="chessboard pattern", expected="at least 2x2 inner corners")
    if not square_m > 0 or not math.isfinite(square_m):
        raise CalibrationError(f"got {square_m}", where="square size", expected="a positive length in metres")
    board = np.zeros((rows * cols, 3), np.float32)
    board[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    object_points: list[np.ndarray] = []
    image_points: list[np.ndarray] = []
    found: list[bool] = []
    size: tuple[int, int] | None = None
    first: str | None = None
    for image in images:
        grey = cv2.imread(os.fspath(image), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise CalibrationError("cannot decode the image (corrupt or not an image OpenCV reads)", where=os.fspath(image))
        this = (grey.shape[1], grey.shape[0])
        if size is None:
            size, first = this, os.fspath(image)
        elif this != size:
            raise CalibrationError(
                f"image size {this[0]}x{this[1]} differs from {size[0]}x{size[1]} of {first}",
                where=os.fspath(image),
                expected="every image from the same camera at the same resolution",
            )
        corners = find_chessboard(grey, pattern)
        found.append(corners is not None)
        if corners is not None:
            object_points.append(board)
            image_points.append(corners)
    if not image_points or size is None:
        raise CalibrationError(
            f"no {cols}x{rows} chessboard found in any of the {len(images)} images",
            expected=f"a whole {cols}x{rows} board in view (check --pattern: inner corners, columns x rows)",
        )
    rms, matrix, dist, _rvecs, _tvecs = cv2.calibrateCamera(object_points, image_points, size, None, None)
    calibration = Calibration(np.asarray(matrix, np.float64), np.asarray(dist, np.float64).reshape(-1), size, float(rms))
    return ChessboardCalibration(calibration, len(images), len(image_points), tuple(found))
