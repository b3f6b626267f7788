"""Frame sources on real files: a video, a folder of images, a (missing) camera."""

from __future__ import annotations

import shutil
import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from dyknow import Manager
from tests.vision_support import FailureWatch, failure_of, read_image, spawn_chain, vision_manager
from transformations.errors import MediaError
from transformations.sources import ImageFolderSource, Pacer, VideoSource, list_images


@pytest.fixture
def vision(make_manager: Callable[..., Manager]) -> Manager:
    return vision_manager(make_manager)


def test_video_source_publishes_every_frame_of_sim1(vision: Manager, data_dir: Path) -> None:
    path = data_dir / "video" / "sim1.mp4"
    unit, sink = spawn_chain(vision, "video-source(ceiling)", "video", params={"path": str(path), "rate_hz": 0}, deep=True)
    assert isinstance(unit, VideoSource)
    assert unit.finished.wait(30)
    messages = sink.wait_for(243)
    assert len(messages) == 243 and unit.frames_published == 243
    assert (unit.fps, unit.frame_count) == (30.0, 243)
    assert all(m.payload.shape == (684, 924, 3) and m.payload.dtype == np.uint8 for m in messages)
    origins = [m.origin_ns for m in messages]
    assert origins == sorted(origins)  # stamped at capture, in order
    first = cv2.VideoCapture(str(path)).read()[1]
    assert np.array_equal(messages[0].payload, first)


def test_video_source_paces_at_the_requested_rate(vision: Manager, data_dir: Path) -> None:
    # A lower bound only: a paced source cannot be faster than its rate, however loaded the machine.
    _, sink = spawn_chain(
        vision, "video-source(top)", "video", params={"path": str(data_dir / "video" / "ball.mp4"), "rate_hz": 100}
    )
    messages = sink.wait_for(11)
    assert messages[10].origin_ns - messages[0].origin_ns >= 10 * 10_000_000 * 0.9


def test_video_source_loops(vision: Manager, data_dir: Path) -> None:
    path = data_dir / "video" / "ball.mp4"  # 60 frames
    unit, sink = spawn_chain(
        vision, "video-source(top)", "video", params={"path": str(path), "rate_hz": 400, "loop": True}, deep=True
    )
    messages = sink.wait_for(70, timeout_s=20)
    assert isinstance(unit, VideoSource) and unit.loops >= 1
    assert np.array_equal(messages[60].payload, messages[0].payload)  # frame 0 again after the end


class FakeTime(threading.Event):
    """A clock and a stop event in one: waiting advances the clock instead of sleeping."""

    def __init__(self) -> None:
        super().__init__()
        self.now_ns = 0
        self.waits_ms: list[float] = []

    def clock(self) -> int:
        return self.now_ns

    def wait(self, timeout: float | None = None) -> bool:
        assert timeout is not None
        self.waits_ms.append(round(timeout * 1e3, 3))
        self.now_ns += round(timeout * 1e9)
        return self.is_set()


def test_the_pacer_keeps_its_rate_and_does_not_burst_after_a_stall() -> None:
    fake = FakeTime()
    pacer = Pacer(100.0, clock=fake.clock)  # 10 ms
    for _ in range(3):
        assert pacer.wait(fake)
    assert fake.waits_ms == [10.0, 10.0]  # the first tick is at once
    fake.now_ns += 4_000_000  # 4 ms of work: the next wait is shorter
    assert pacer.wait(fake) and fake.waits_ms[-1] == 6.0
    fake.now_ns += 500_000_000  # a stall of half a second: no burst of 50 ticks, a new schedule
    waits = len(fake.waits_ms)
    assert pacer.wait(fake) and len(fake.waits_ms) == waits  # at once...
    assert pacer.wait(fake) and fake.waits_ms[-1] == 10.0  # ...then at the rate again
    fake.set()
    assert not pacer.wait(fake)
    assert Pacer(0).wait(threading.Event()) and not Pacer(0).wait(fake)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d, t: t / "missing.mp4", "param 'path': no such video file {p}"),
        (lambda d, t: d / "SOURCES.md", "video {p}: OpenCV cannot open it; expected a video file"),
        (lambda d, t: t, "param 'path': {p} is not a file; expected a video file"),
    ],
    ids=["missing", "not-a-video", "a-folder"],
)
def test_video_source_names_the_file_it_cannot_play(
    vision: Manager, data_dir: Path, tmp_path: Path, make: Callable[[Path, Path], Path], message: str
) -> None:
    path = make(data_dir, tmp_path)
    error = failure_of(vision, "video-source(top)", "video", {"path": str(path)})
    assert message.format(p=path) in error and "MediaError" in error


def test_a_garbage_mp4_is_refused(vision: Manager, tmp_path: Path) -> None:
    path = tmp_path / "fake.mp4"
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    error = failure_of(vision, "video-source(top)", "video", {"path": str(path)})
    assert str(path) in error and ("cannot open it" in error or "no frame could be decoded" in error)


def test_image_folder_source_publishes_the_chessboards_in_order(vision: Manager, data_dir: Path) -> None:
    folder = data_dir / "images" / "chessboard"
    unit, sink = spawn_chain(
        vision, "image-folder-source(bottom)", "images", params={"path": str(folder), "rate_hz": 0}, deep=True
    )
    assert isinstance(unit, ImageFolderSource) and unit.finished.wait(10)
    messages = sink.wait_for(13)
    names = [p.name for p in unit.files]
    assert names == [f"left{i:02d}.jpg" for i in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)]
    assert len(messages) == 13 and all(m.payload.shape == (480, 640, 3) for m in messages)  # grey files come out as BGR
    assert np.array_equal(messages[12].payload, read_image(folder / "left14.jpg"))


def test_image_folder_source_takes_a_glob(vision: Manager, data_dir: Path) -> None:
    pattern = str(data_dir / "images" / "chessboard" / "left1*.jpg")
    unit, sink = spawn_chain(vision, "image-folder-source(bottom)", "images", params={"path": pattern, "rate_hz": 0}, deep=True)
    assert isinstance(unit, ImageFolderSource)
    assert [p.name for p in unit.files] == ["left11.jpg", "left12.jpg", "left13.jpg", "left14.jpg"]
    assert sink is not None and len(sink.wait_for(4)) == 4


@pytest.fixture
def folder_with_garbage(tmp_path: Path, data_dir: Path) -> Path:
    for name in ("left01.jpg", "left02.jpg"):
        shutil.copy(data_dir / "images" / "chessboard" / name, tmp_path / name)
    (tmp_path / "left01b.jpg").write_bytes(b"this is not a jpeg" * 20)
    (tmp_path / "notes.txt").write_text("not an image, and not taken: wrong extension")
    return tmp_path


def test_a_corrupt_image_fails_the_source_naming_it(vision: Manager, folder_with_garbage: Path) -> None:
    error = failure_of(vision, "image-folder-source(top)", "images", {"path": str(folder_with_garbage)})
    assert f"image {folder_with_garbage / 'left01b.jpg'}: no image format recognises it" in error
    assert "skip_corrupt=true" in error


def test_a_corrupt_image_is_skipped_with_a_warning_when_asked(
    vision: Manager, folder_with_garbage: Path, caplog: pytest.LogCaptureFixture
) -> None:
    params = {"path": str(folder_with_garbage), "rate_hz": 0, "skip_corrupt": True}
    unit, sink = spawn_chain(vision, "image-folder-source(top)", "images", params=params, deep=True)
    assert isinstance(unit, ImageFolderSource) and unit.finished.wait(10)
    assert len(sink.wait_for(2)) == 2
    assert unit.skipped == [folder_with_garbage / "left01b.jpg"]
    assert "skipping image" in caplog.text and "left01b.jpg" in caplog.text


def test_a_truncated_image_fails_the_running_source_naming_it(vision: Manager, tmp_path: Path, data_dir: Path) -> None:
    data = (data_dir / "images" / "ball" / "smarties.png").read_bytes()
    (tmp_path / "a.png").write_bytes(data)
    (tmp_path / "b.png").write_bytes(data[: len(data) // 2])  # a valid header, then nothing
    watch = FailureWatch(vision, "images")
    vision.spawn("image-folder-source(top)", "images", params={"path": str(tmp_path), "rate_hz": 0})
    error = watch.wait()
    assert f"image {tmp_path / 'b.png'}: cannot decode it (corrupt or truncated)" in error


def test_list_images_errors(tmp_path: Path) -> None:
    with pytest.raises(MediaError, match="no such folder"):
        list_images(tmp_path / "nope")
    with pytest.raises(MediaError, match="has no images"):
        list_images(tmp_path)
    with pytest.raises(MediaError, match="no file matches"):
        list_images(str(tmp_path / "*.png"))
    for name in ("f10.png", "f2.png", "f1.png"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in list_images(tmp_path)] == ["f1.png", "f2.png", "f10.png"]  # natural order
    with pytest.raises(MediaError, match="is a file; expected a folder"):
        list_images(tmp_path / "f1.png")


def test_camera_source_without_a_camera_fails_clearly(vision: Manager) -> None:
    error = failure_of(vision, "camera-source(bottom)", "cam", {"device": 97})
    assert "param 'device': no camera at index 97" in error
    assert "expected the index of a connected camera" in error
