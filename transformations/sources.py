"""Frame sources: a video file, a folder of images, a live camera, and the synthetic scene.

Every source publishes BGR frames (H x W x 3 uint8) on its output ``out``, each stamped with its
capture time (``time.time_ns()`` clock) as the message's origin time, so every later hop can tell
how old the picture is. The sources read on a thread of their own (``run``) and pace themselves:

- ``rate_hz`` > 0: that many frames per second; 0: as fast as they can be read;
- ``VideoSource`` only: ``rate_hz`` < 0 (the default) plays at the file's own frame rate.

When a source falls behind (a slow disk, a busy machine) it does not burst to catch up; it
carries on at the set rate from where it is.

Setup fails with a :class:`~transformations.errors.MediaError` naming the file, folder or device
when it cannot be opened, so a misconfigured source shows up as a failed unit with that message.
"""

from __future__ import annotations

import glob
import os
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from dyknow import Unit
from dyknow.security import bounded_glob
from transformations import params
from transformations.errors import MediaError
from transformations.scene import CAMERAS, Scene

__all__ = [
    "IMAGE_EXTENSIONS",
    "CameraSource",
    "ImageFolderSource",
    "Pacer",
    "SyntheticScene",
    "VideoSource",
    "list_images",
]

IMAGE_EXTENSIONS: Final = (".bmp", ".jpeg", ".jpg", ".jp2", ".pbm", ".pgm", ".png", ".pnm", ".ppm", ".tif", ".tiff", ".webp")
"""The file extensions ``ImageFolderSource`` takes from a folder (case-insensitive)."""


class Pacer:
    """Paces a loop at ``rate_hz`` against the monotonic clock (0: no pacing).

    ``wait(stop)`` returns at the next tick, at once for the first one; it returns False when
    ``stop`` was set meanwhile. A loop that falls more than a period behind restarts its schedule
    from now instead of bursting. ``clock`` is for tests.
    """

    def __init__(self, rate_hz: float, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.period_ns = round(1e9 / rate_hz) if rate_hz > 0 else 0
        self._clock = clock
        self._next_ns: int | None = None

    def wait(self, stop: threading.Event) -> bool:
        """Block until the next tick; False when ``stop`` is set (then the loop should end)."""
        if self.period_ns == 0:
            return not stop.is_set()
        now = self._clock()
        if self._next_ns is None or self._next_ns + self.period_ns < now:
            self._next_ns = now
        else:
            self._next_ns += self.period_ns
        delay = self._next_ns - now
        if delay > 0:
            return not stop.wait(delay / 1e9)
        return not stop.is_set()


def _natural_key(path: str) -> list[object]:
    # frame2.png before frame10.png
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path)]


def list_images(pattern: str | os.PathLike[str]) -> list[Path]:
    """The image files of a folder (by extension), or those matching a glob, in natural order.

    Raises :class:`MediaError` when the folder does not exist or nothing matches.
    """
    text = os.fspath(pattern)
    path = Path(text).expanduser()
    if path.is_dir():
        files = [p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS]
        if not files:
            raise MediaError("has no images", where=f"folder {path}", expected=f"files ending in {', '.join(IMAGE_EXTENSIONS)}")
    elif glob.has_magic(text):
        files = [Path(p) for p in bounded_glob(os.path.expanduser(text)) if Path(p).is_file()]  # bounded: cannot walk the disk
        if not files:
            raise MediaError("no file matches it", where=text, expected="a glob such as 'frames/*.png'")
    elif path.exists():
        raise MediaError("is a file", where=str(path), expected="a folder of images or a glob such as 'frames/*.png'")
    else:
        raise MediaError("no such folder", where=str(path), expected="a folder of images or a glob such as 'frames/*.png'")
    return sorted(files, key=lambda p: _natural_key(str(p)))


class _CaptureSource(Unit):
    """Common part of the sources read through ``cv2.VideoCapture``: the read loop.

    The capture belongs to the ``run`` thread; ``teardown`` may run while ``run`` is still in a
    read (dyknow calls ``teardown`` before it joins the run thread), so both hold
    ``_capture_lock`` around the capture and whichever comes first releases it.
    """

    dedicated_thread = True

    def setup(self) -> None:
        self._capture_lock = threading.Lock()
        self._capture: cv2.VideoCapture | None = None
        self._pending: np.ndarray | None = None  # a frame read at setup, published first
        self.frames_published = 0
        self.finished = threading.Event()

    def _grab(self) -> tuple[np.ndarray, int] | None:
        """The next frame and the time it was grabbed, or None at the end (or once released)."""
        with self._capture_lock:
            if self._capture is None or not self._capture.grab():
                return None
            stamp = time.time_ns()
            ok, frame = self._capture.retrieve()
        return (frame, stamp) if ok and frame is not None else None

    def _at_end(self, stop: threading.Event) -> tuple[np.ndarray, int] | None:
        """When a read fails: another frame to carry on with, or None to stop."""
        return None

    def _rate(self) -> float:
        raise NotImplementedError

    def _stamp(self, read_ns: int) -> int:
        """The origin time of the frame read at ``read_ns`` (the next to publish)."""
        return read_ns

    def run(self, stop: threading.Event) -> None:
        pacer = Pacer(self._rate())
        try:
            while pacer.wait(stop):
                if self._pending is not None:
                    frame, stamp = self._pending, time.time_ns()
                    self._pending = None
                else:
                    got = self._grab() or self._at_end(stop)
                    if got is None:
                        return
                    frame, stamp = got
                self.publish("out", frame, origin_ns=self._stamp(stamp))
                self.frames_published += 1
        finally:
            self._release()
            self.finished.set()

    def _release(self) -> None:
        with self._capture_lock:
            if self._capture is not None:
                self._capture.release()
                self._capture = None

    def teardown(self) -> None:
        self._release()


class VideoSource(_CaptureSource):
    """Publishes the frames of a video file on ``out``.

    Params: ``path`` (the video file), ``rate_hz`` (< 0, the default: the file's frame rate;
    0: as fast as possible; > 0: that rate), ``loop`` (start again at the end; default false),
    ``stamp``: ``read`` (the default) stamps a frame when it is read, just before it is
    published, as a camera's; ``video`` stamps it with its time in the video (frame ``i`` at the
    first frame's stamp plus ``i / fps``, counted on across loops), so what downstream units
    measure (a tracker's speeds) keeps the scene's timing when a loaded machine publishes late.

    Attributes for embedding and tests: ``fps`` (the file's frame rate), ``frame_count`` (as
    the container states it), ``frames_published``, ``loops`` (restarts so far) and
    ``finished`` (an event set when the video ended without ``loop``, or the unit stopped).
    """

    path_params = {"path": "read"}

    def setup(self) -> None:
        """Open the video and read its frame rate."""
        super().setup()
        self.path = Path(params.text(self.params, "path", required=True)).expanduser()
        self.rate_hz = params.number(self.params, "rate_hz", -1.0)
        self.loop = params.flag(self.params, "loop", False)
        self.stamping = params.text(self.params, "stamp", "read")
        if self.stamping not in ("read", "video"):
            raise MediaError(f"stamp {self.stamping[:40]!r}", where="param 'stamp'", expected="read (when read) or video (its time in the video)")
        self._first_ns: int | None = None
        self.loops = 0
        self._capture = self._open()
        self.fps = float(self._capture.get(cv2.CAP_PROP_FPS) or 0.0)
        self.frame_count = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        first = self._grab()  # a file OpenCV opens but cannot decode fails here, not later
        if first is None:
            self._release()
            raise MediaError("no frame could be decoded", where=f"video {self.path}", expected="a video file OpenCV can read")
        self._pending = first[0]
        if self.rate_hz < 0 and not self.fps > 0:
            self.log.warning("video %s does not state its frame rate; playing at 30 fps", self.path)

    def _stamp(self, read_ns: int) -> int:
        if self.stamping != "video":
            return read_ns
        if self._first_ns is None:
            self._first_ns = read_ns
        return self._first_ns + round(self.frames_published * 1e9 / (self.fps if self.fps > 0 else 30.0))

    def _open(self) -> cv2.VideoCapture:
        if not self.path.exists():
            raise MediaError(f"no such video file {self.path}", where="param 'path'")
        if not self.path.is_file():
            raise MediaError(f"{self.path} is not a file", where="param 'path'", expected="a video file")
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            capture.release()
            raise MediaError(
                "OpenCV cannot open it", where=f"video {self.path}", expected="a video file (e.g. .mp4, .avi) of a codec FFmpeg decodes"
            )
        return capture

    def _rate(self) -> float:
        if self.rate_hz >= 0:
            return self.rate_hz
        return self.fps if self.fps > 0 else 30.0

    def _at_end(self, stop: threading.Event) -> tuple[np.ndarray, int] | None:
        if not self.loop:
            self.log.info("video %s ended after %d frames", self.path, self.frames_published)
            return None
        with self._capture_lock:
            if self._capture is None:
                return None
            # Seeking back is not reliable for every container; reopening always works.
            self._capture.release()
            self._capture = cv2.VideoCapture(str(self.path))
        self.loops += 1
        return self._grab()


class CameraSource(_CaptureSource):
    """Publishes the frames of a live camera (``cv2.VideoCapture(device)``) on ``out``.

    Params: ``device`` (the camera index, 0 for ``/dev/video0``), ``width``/``height``/``fps``
    (requested from the driver; 0 keeps its default), ``rate_hz`` (0, the default: as the camera
    delivers; > 0: at most that rate). Setup fails when no camera answers at that index. Frames
    are stamped right after they are grabbed, before decoding.
    """

    #: Consecutive failed reads after which the camera counts as gone.
    MAX_FAILURES: Final = 50

    def setup(self) -> None:
        """Open the camera device and set its size and frame rate."""
        super().setup()
        self.device = params.whole(self.params, "device", 0, low=0)
        self.rate_hz = params.number(self.params, "rate_hz", 0.0, low=0)
        width = params.whole(self.params, "width", 0, low=0)
        height = params.whole(self.params, "height", 0, low=0)
        fps = params.number(self.params, "fps", 0.0, low=0)
        capture = cv2.VideoCapture(self.device)
        if not capture.isOpened():
            capture.release()
            raise MediaError(
                f"no camera at index {self.device} (cv2.VideoCapture({self.device}) cannot open it)",
                where="param 'device'",
                expected="the index of a connected camera, e.g. 0 for /dev/video0",
            )
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, width), (cv2.CAP_PROP_FRAME_HEIGHT, height), (cv2.CAP_PROP_FPS, fps)):
            if value:
                capture.set(prop, value)
        self._capture = capture
        if self._grab() is None:  # an old frame by the time run() starts: checked, not published
            self._release()
            raise MediaError(
                "opened but delivered no frame", where=f"camera {self.device}", expected="frames (is another program using it?)"
            )

    def _rate(self) -> float:
        return self.rate_hz

    def _at_end(self, stop: threading.Event) -> tuple[np.ndarray, int] | None:
        # A live camera has no end: a failed read is a hiccup until it lasts.
        for _ in range(self.MAX_FAILURES):
            if stop.wait(0.01):
                return None
            got = self._grab()
            if got is not None:
                return got
            with self._capture_lock:
                if self._capture is None:
                    return None
        raise MediaError(f"stopped delivering frames ({self.MAX_FAILURES} failed reads in a row)", where=f"camera {self.device}")


class ImageFolderSource(Unit):
    """Publishes the images of a folder (or a glob) on ``out``, in natural order.

    Params: ``path`` (a folder, whose files with an image extension are taken, or a glob such as
    ``frames/*.png``), ``rate_hz`` (default 10; 0: as fast as possible), ``loop`` (default
    false), ``skip_corrupt`` (default false).

    An image that cannot be decoded fails the unit with an error naming the file; with
    ``skip_corrupt`` it is skipped with a warning instead (counted in ``skipped``). Files whose
    header no image format recognises are caught at setup already. Grey and colour images both
    come out as BGR. Attributes: ``files``, ``frames_published``, ``skipped``, ``finished``.
    """

    path_params = {"path": "read"}

    dedicated_thread = True

    def setup(self) -> None:
        """List the images the ``path`` pattern names."""
        pattern = params.text(self.params, "path", required=True)
        self.rate_hz = params.number(self.params, "rate_hz", 10.0, low=0)
        self.loop = params.flag(self.params, "loop", False)
        self.skip_corrupt = params.flag(self.params, "skip_corrupt", False)
        self.frames_published = 0
        self.skipped: list[Path] = []
        self._skipped: set[Path] = set()
        self.finished = threading.Event()
        files = list_images(pattern)
        readable = []
        for file in files:
            if cv2.haveImageReader(str(file)):
                readable.append(file)
            elif self.skip_corrupt:
                self._skip(file, "no image format recognises its header")
            else:
                raise MediaError(
                    "no image format recognises it (corrupt or not an image)",
                    where=f"image {file}",
                    expected="an image (remove it, or set param skip_corrupt=true to skip it)",
                )
        if not readable:
            raise MediaError(f"none of the {len(files)} files is a readable image", where=pattern)
        self.files = readable

    def _skip(self, file: Path, reason: str) -> None:
        self.skipped.append(file)
        self._skipped.add(file)
        self.log.warning("skipping image %s: %s", file, reason)

    def run(self, stop: threading.Event) -> None:
        """Publish the images in order at ``rate_hz``, looping if asked."""
        pacer = Pacer(self.rate_hz)
        try:
            while True:
                published = 0
                for file in self.files:
                    if file in self._skipped:
                        continue
                    if not pacer.wait(stop):
                        return
                    frame = cv2.imread(str(file), cv2.IMREAD_COLOR)
                    stamp = time.time_ns()
                    if frame is None:
                        if not self.skip_corrupt:
                            raise MediaError(
                                "cannot decode it (corrupt or truncated)",
                                where=f"image {file}",
                                expected="an image (remove it, or set param skip_corrupt=true to skip it)",
                            )
                        self._skip(file, "cannot decode it (corrupt or truncated)")
                        continue
                    self.publish("out", frame, origin_ns=stamp)
                    self.frames_published += 1
                    published += 1
                if not self.loop or published == 0:
                    return
        finally:
            self.finished.set()


class SyntheticScene(Unit):
    """Renders the synthetic scene (:mod:`transformations.scene`) from one camera on ``out``.

    Params: ``camera`` (``bottom``, ``top`` or ``ceiling``), ``width``/``height`` (default
    640x480), ``rate_hz`` (default 30; 0: as fast as possible), ``seed`` (default 0), ``noise``
    (pixel noise standard deviation, default 2), ``period_s`` (the ball's lap time, default 20),
    ``epoch_ns`` (when the laps start, default 0: the Unix epoch).

    Each frame shows the scene at its origin time, so its ground truth is
    ``unit.scene.ball_at(msg.origin_ns)`` (field) or ``unit.scene.ball_in_image(camera,
    msg.origin_ns, width, height)`` (pixels). Units with the same seed and period show the same
    ball at the same time, whatever their camera.
    """

    dedicated_thread = True

    def setup(self) -> None:
        """Build the scene and the camera's view of it from the params."""
        self.camera = params.choice(self.params, "camera", CAMERAS, "ceiling")
        self.width = params.whole(self.params, "width", 640, low=16, high=8192)
        self.height = params.whole(self.params, "height", 480, low=16, high=8192)
        self.rate_hz = params.number(self.params, "rate_hz", 30.0, low=0)
        self.noise = params.number(self.params, "noise", 2.0, low=0, high=100)
        period = params.number(self.params, "period_s", 20.0, low=0, low_open=True)
        epoch = params.whole(self.params, "epoch_ns", 0, low=0)
        self.scene = Scene(seed=params.whole(self.params, "seed", 0), period_s=period, epoch_ns=epoch)
        self.frames_published = 0
        self.scene.render(self.camera, 0, self.width, self.height, self.noise)  # build the caches now

    def render(self, t_ns: int) -> np.ndarray:
        """The frame this unit publishes for time ``t_ns``."""
        return self.scene.render(self.camera, t_ns, self.width, self.height, self.noise)

    def run(self, stop: threading.Event) -> None:
        """Render and publish frames at ``rate_hz``, stamped at render time."""
        pacer = Pacer(self.rate_hz)
        while pacer.wait(stop):
            stamp = time.time_ns()
            self.publish("out", self.render(stamp), origin_ns=stamp)
            self.frames_published += 1
