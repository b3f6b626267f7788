"""Calibration files (the three OpenCV YAML shapes of the shared data) and chessboard calibration."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.vision_support import read_image
from transformations.calibration import Calibration, calibrate_chessboard, find_chessboard, load_calibration, save_calibration
from transformations.errors import CalibrationError
from transformations.sources import list_images


@pytest.mark.parametrize(
    ("name", "fx", "dist_shape_in_file", "size", "rms"),
    [
        ("left_intrinsics.yml", 535.9157, (5, 1), (640, 480), 0.3926),  # OpenCV sample: 5x1, sizes, flags
        ("tutorial_camera_charuco.yml", 452.5107, (1, 5), (640, 480), 0.1823),  # a 1x5 row
        ("tutorial_camera_params.yml", 628.158, (5, 1), None, None),  # hand-written, no sizes, no '---'
    ],
)
def test_the_three_yaml_shapes_load(
    data_dir: Path, name: str, fx: float, dist_shape_in_file: tuple[int, int], size: tuple[int, int] | None, rms: float | None
) -> None:
    cal = load_calibration(data_dir / "calibration" / name)
    assert cal.camera_matrix.shape == (3, 3) and cal.camera_matrix[0, 0] == pytest.approx(fx, abs=1e-3)
    assert cal.camera_matrix[2].tolist() == [0.0, 0.0, 1.0]
    assert cal.dist_coeffs.shape == (5,)
    assert cal.image_size == size
    assert cal.rms_px == (None if rms is None else pytest.approx(rms, abs=1e-4))
    assert cal.path is not None and cal.path.endswith(name)
    raw = cv2.FileStorage(str(data_dir / "calibration" / name), cv2.FILE_STORAGE_READ)
    assert raw.getNode("distortion_coefficients").mat().shape == dist_shape_in_file
    assert np.allclose(cal.dist_coeffs, raw.getNode("distortion_coefficients").mat().reshape(-1))
    raw.release()


def test_a_file_without_the_keys_is_refused_naming_the_file_and_the_key(data_dir: Path) -> None:
    path = data_dir / "calibration" / "calibration.yml"  # an image list, not a calibration
    with pytest.raises(CalibrationError) as info:
        load_calibration(path)
    assert str(info.value) == (f"{path}: missing key 'camera_matrix'; expected a 3x3 !!opencv-matrix")  # no key names: the file's content


def test_a_missing_distortion_key_is_named(tmp_path: Path) -> None:
    path = tmp_path / "k_only.yml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("camera_matrix", np.eye(3) * 500)
    storage.release()
    with pytest.raises(
        CalibrationError, match=r"k_only.yml: missing key 'distortion_coefficients'; expected a 5x1"
    ):
        load_calibration(path)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"just text", r"garbage.yml: not an OpenCV FileStorage file \(.*\); expected YAML, XML or JSON"),
        (b"", r"garbage.yml: not an OpenCV FileStorage file"),
        (b"%YAML:1.0\ncamera_matrix: 5\ndistortion_coefficients: [0, 0, 0, 0, 0]\n", r"key 'camera_matrix' is not a matrix"),
        (b"%YAML:1.0\ncamera_matrix: [1, 0, 0, 0, 1, 0]\ndistortion_coefficients: [0, 0, 0, 0, 0]\n", r"'camera_matrix' has shape \(6,\); expected 3x3"),
        (b"%YAML:1.0\ncamera_matrix: [500, 0, 320, 0, 500, 240, 0, 0, 1]\ndistortion_coefficients: [1, 2, 3]\n",
         r"'distortion_coefficients' has shape \(3,\); expected a row or column of 4, 5, 8, 12 or 14 values"),
    ],
)  # fmt: skip
def test_malformed_files_are_refused_with_the_reason(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "garbage.yml"
    path.write_bytes(content)
    with pytest.raises(CalibrationError, match=message):
        load_calibration(path)


def test_plain_lists_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "lists.yml"
    path.write_text("%YAML:1.0\ncamera_matrix: [500, 0, 320, 0, 500, 240, 0, 0, 1]\ndistortion_coefficients: [0.1, 0, 0, 0]\n")
    cal = load_calibration(path)
    assert cal.camera_matrix[0, 2] == 320 and cal.dist_coeffs.tolist() == [0.1, 0, 0, 0]


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"nope\.yml: no such calibration file"):
        load_calibration(tmp_path / "nope.yml")


@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_save_and_load_round_trip(tmp_path: Path, suffix: str) -> None:
    cal = Calibration(
        np.array([[500.0, 0, 320], [0, 501, 240], [0, 0, 1]]), np.array([0.1, -0.2, 0.001, 0.002, 0.03]), (640, 480), 0.25
    )
    path = save_calibration(tmp_path / f"cam{suffix}", cal, extra={"board_width": 9})
    back = load_calibration(path)
    assert np.array_equal(back.camera_matrix, cal.camera_matrix) and np.array_equal(back.dist_coeffs, cal.dist_coeffs)
    assert (back.image_size, back.rms_px) == ((640, 480), 0.25)
    with pytest.raises(CalibrationError, match=r"unknown calibration file extension '\.txt'"):
        save_calibration(tmp_path / "cam.txt", cal)
    with pytest.raises(CalibrationError, match="does not exist"):
        save_calibration(tmp_path / "missing" / "cam.yml", cal)


def test_the_matrix_scales_to_frames_of_the_same_aspect_and_refuses_others(data_dir: Path) -> None:
    cal = load_calibration(data_dir / "calibration" / "left_intrinsics.yml")
    assert np.array_equal(cal.matrix_for(640, 480), cal.camera_matrix)
    scaled = cal.matrix_for(768, 576)  # vtest.avi's size, 1.2 x
    assert scaled[0, 0] == pytest.approx(cal.camera_matrix[0, 0] * 1.2) and scaled[1, 2] == pytest.approx(
        cal.camera_matrix[1, 2] * 1.2
    )
    with pytest.raises(
        CalibrationError, match=r"left_intrinsics.yml: frame size 640x360 does not match the calibration \(640x480\)"
    ):
        cal.matrix_for(640, 360)


def test_chessboard_calibration_matches_the_reference(data_dir: Path) -> None:
    images = list_images(data_dir / "images" / "chessboard")
    result = calibrate_chessboard(images, (9, 6), 0.025)
    assert (result.images, result.boards_found) == (13, 13)
    reference = load_calibration(data_dir / "calibration" / "left_intrinsics.yml").camera_matrix
    k = result.calibration.camera_matrix
    for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)):
        assert k[i, j] == pytest.approx(reference[i, j], rel=0.02)
    assert result.calibration.rms_px == pytest.approx(0.408, abs=0.02)
    assert result.calibration.image_size == (640, 480)


def test_no_board_and_corrupt_images_are_named(data_dir: Path, tmp_path: Path) -> None:
    ball = data_dir / "images" / "ball"
    with pytest.raises(CalibrationError, match="no 9x6 chessboard found in any of the 2 images"):
        calibrate_chessboard([ball / "basketball1.png", ball / "basketball2.png"], (9, 6))
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(CalibrationError, match=f"{bad}: cannot decode the image"):
        calibrate_chessboard([bad], (9, 6))
    grey = read_image(data_dir / "images" / "chessboard" / "left01.jpg", cv2.IMREAD_GRAYSCALE)
    corners = find_chessboard(grey, (9, 6))
    assert corners is not None and corners.reshape(-1, 2).shape == (54, 2)
    assert find_chessboard(grey, (7, 7)) is None
