"""A synthetic scene with known ground truth: a green ball rolling over a textured field.

The scene of the DyKnow paper's example, rendered instead of filmed: a robot stands at one end of
the field with two cameras (``top`` looks ahead, ``bottom`` looks down in front of its feet) and a
``ceiling`` camera looks straight down on the whole field.

Coordinates
    The *field* frame is metric, its origin at the centre of the field, ``x`` along the length
    (towards the far goal, as the robot looks), ``y`` across (to the robot's left), ``z`` up. The
    field is :data:`FIELD_LENGTH_M` x :data:`FIELD_WIDTH_M`. Images use OpenCV's convention:
    pixel ``(u, v)``, ``u`` to the right, ``v`` down, the centre of the top-left pixel at (0, 0).

Ball
    A sphere of radius :data:`BALL_RADIUS_M` rolling on the floor (its centre at height
    ``BALL_RADIUS_M``) along a Lissajous curve with period ``period_s``; :meth:`Scene.ball_at`
    gives its position and velocity at any time. Time is integer nanoseconds on the
    ``time.time_ns()`` clock, so a frame's ground truth is ``scene.ball_at(msg.origin_ns)``.

Cameras
    Pinhole cameras without distortion, with square pixels and the principal point at the image
    centre; :data:`CAMERA_POSES` places them. Every function takes the image size, so any
    resolution works. :func:`field_to_image` is the homography from field ``(x, y)`` on the plane
    of the ball's centre (``z = BALL_RADIUS_M``) to pixels: the detected centre of the ball maps
    back exactly with its inverse, :func:`image_to_field` (what ``Localization`` is configured
    with; ``homography=scene:<camera>`` in its params).

Rendering
    :meth:`Scene.render` is deterministic for a given seed, camera, size and time. The static
    background (field texture, lines, floor, wall) is warped once per camera and size; a frame is
    a copy of it plus the ball, a few drawing calls (well under a millisecond at 640x480).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np

from transformations.errors import ParamError

__all__ = [
    "BALL_BGR",
    "BALL_RADIUS_M",
    "CAMERAS",
    "CAMERA_POSES",
    "FIELD_LENGTH_M",
    "FIELD_WIDTH_M",
    "BallState",
    "CameraPose",
    "ImageBall",
    "Scene",
    "camera_matrix",
    "field_to_image",
    "image_to_field",
    "project",
]

FIELD_LENGTH_M: Final = 6.0
"""Length of the field along x, in metres (from goal line to goal line)."""

FIELD_WIDTH_M: Final = 4.0
"""Width of the field along y, in metres."""

BALL_RADIUS_M: Final = 0.1
"""Radius of the ball, in metres; its centre rolls at this height."""

BALL_BGR: Final = (50, 205, 70)
"""The ball's main colour (BGR); in OpenCV HSV about (56, 193, 205), inside the detector's defaults."""

_BALL_RIM_BGR = (30, 150, 45)  # shaded edge, HSV about (56, 204, 150)
_BALL_SHINE_BGR = (130, 245, 150)  # highlight, HSV about (55, 120, 245)
_CARPET_BGR = np.array([118.0, 98.0, 78.0])  # blue-grey carpet, hue about 105: far from green
_FLOOR_BGR = (88, 88, 92)
_WALL_BGR = (196, 204, 210)
_LINE_BGR = (235, 235, 235)
_TEXTURE_PX_PER_M = 100
_TEXTURE_MARGIN_M = 1.0


@dataclass(frozen=True, slots=True)
class CameraPose:
    """Where a camera is (metres, field frame) and where it looks.

    ``yaw_deg`` turns the viewing direction about z (0: along +x); ``pitch_deg`` tilts it down
    (90: straight down); ``hfov_deg`` is the horizontal field of view.
    """

    x: float
    y: float
    z: float
    yaw_deg: float
    pitch_deg: float
    hfov_deg: float

    def rotation(self) -> np.ndarray:
        """The 3x3 rotation from field axes to camera axes (x right, y down, z forward)."""
        yaw, pitch = math.radians(self.yaw_deg), math.radians(self.pitch_deg)
        forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
        right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
        down = np.cross(forward, right)
        return np.stack([right, down, forward]).astype(np.float64)

    def translation(self) -> np.ndarray:
        """The camera's translation: camera coordinates of a point ``p`` are ``R @ p + t``."""
        translation: np.ndarray = -self.rotation() @ np.array([self.x, self.y, self.z])
        return translation


CAMERA_POSES: Final[dict[str, CameraPose]] = {
    # The robot stands near its own goal line, on the centre line, looking along +x.
    "bottom": CameraPose(x=-2.75, y=0.0, z=0.45, yaw_deg=0.0, pitch_deg=40.0, hfov_deg=61.0),
    "top": CameraPose(x=-2.75, y=0.0, z=0.50, yaw_deg=0.0, pitch_deg=12.0, hfov_deg=61.0),
    # 6 m above the centre, image x along field +x and image y along field -y (a map view).
    "ceiling": CameraPose(x=0.0, y=0.0, z=6.0, yaw_deg=90.0, pitch_deg=90.0, hfov_deg=65.0),
}
"""The cameras of the scene by name."""

CAMERAS: Final = tuple(CAMERA_POSES)
"""The camera names: ``bottom``, ``top``, ``ceiling``."""


def _pose(camera: str) -> CameraPose:
    pose = CAMERA_POSES.get(camera)
    if pose is None:
        raise ParamError(f"unknown camera {camera!r}", expected=f"one of {', '.join(CAMERAS)}")
    return pose


def _check_size(width: int, height: int) -> None:
    if width <= 0 or height <= 0:
        raise ParamError(f"got {width}x{height}", where="image size", expected="a positive width and height")


def camera_matrix(camera: str, width: int, height: int) -> np.ndarray:
    """The 3x3 intrinsic matrix of ``camera`` for images of ``width`` x ``height`` pixels."""
    _check_size(width, height)
    pose = _pose(camera)
    f = (width / 2.0) / math.tan(math.radians(pose.hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def project(camera: str, width: int, height: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project field points (N x 3, metres) into ``camera``: pixel coordinates (N x 2) and depths (N)."""
    pose = _pose(camera)
    cam = (pose.rotation() @ np.asarray(points, dtype=np.float64).reshape(-1, 3).T).T + pose.translation()
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pix = (camera_matrix(camera, width, height) @ cam.T).T
        uv = pix[:, :2] / pix[:, 2:3]
    return uv, depth


def _plane_to_image(camera: str, width: int, height: int, z: float) -> np.ndarray:
    pose = _pose(camera)
    r, t = pose.rotation(), pose.translation()
    h: np.ndarray = camera_matrix(camera, width, height) @ np.column_stack([r[:, 0], r[:, 1], r[:, 2] * z + t])
    return _normalised(h)


def field_to_image(camera: str, width: int, height: int) -> np.ndarray:
    """Homography from field ``(x, y)`` on the plane of the ball's centre to pixels of ``camera``."""
    return _plane_to_image(camera, width, height, BALL_RADIUS_M)


def image_to_field(camera: str, width: int, height: int) -> np.ndarray:
    """Homography from pixels of ``camera`` to field ``(x, y)`` on the plane of the ball's centre."""
    return _normalised(np.linalg.inv(field_to_image(camera, width, height)))


def _normalised(h: np.ndarray) -> np.ndarray:
    out: np.ndarray = h / h[2, 2]
    return out


@dataclass(frozen=True, slots=True)
class BallState:
    """The ball at one instant: position (m) and velocity (m/s) in the field frame."""

    t_ns: int
    x: float
    y: float
    vx: float
    vy: float


@dataclass(frozen=True, slots=True)
class ImageBall:
    """The ball as a camera sees it: centre and radius in pixels.

    ``complete`` says whether the whole disc lies inside the image (a detector can then find its
    centre exactly); a ball cut by the image border has ``complete`` false.
    """

    x: float
    y: float
    radius: float
    complete: bool


_SHARED_BACKGROUNDS: dict[tuple[int, str, int, int], np.ndarray] = {}  # read-only images
_SHARED_NOISE: dict[tuple[int, int, int, float], list[np.ndarray]] = {}


class Scene:
    """The ball's trajectory and the renderer, for one ``seed``.

    The seed fixes the field texture and where on its path the ball is at a given time; the
    cameras and the field are the same for every seed. ``epoch_ns`` is the time from which laps
    count (a demo that wants the same story each run starts them when it starts).
    """

    def __init__(self, seed: int = 0, period_s: float = 20.0, epoch_ns: int = 0) -> None:
        if not period_s > 0:
            raise ParamError(f"got {period_s}", where="period_s", expected="a positive number of seconds")
        self.seed = int(seed)
        self.period_ns = round(period_s * 1e9)
        self.epoch_ns = int(epoch_ns)  # the time the ball's lap starts from (0: the Unix epoch, as before)
        rng = np.random.default_rng(self.seed)
        # A figure of eight: y = 0 at both ends of the x swing, so every period the ball rolls
        # through the view of the robot's bottom camera. The seed sets where on the path the
        # ball is at a given time and how wide the eight is.
        self._phase = float(rng.uniform(0.0, 2.0 * math.pi))
        self._amp_x = FIELD_LENGTH_M / 2.0 - 0.8
        self._amp_y = (FIELD_WIDTH_M / 2.0 - 0.6) * float(rng.uniform(0.75, 1.0))
        self._texture: np.ndarray | None = None
        self._backgrounds: dict[tuple[str, int, int], np.ndarray] = {}
        self._noise: dict[tuple[int, int, float], list[np.ndarray]] = {}

    # -- ground truth

    def ball_at(self, t_ns: int) -> BallState:
        """Where the ball is at ``t_ns`` (``time.time_ns()`` clock), and how fast it moves."""
        t_ns = int(t_ns)
        phase = 2.0 * math.pi * (((t_ns - self.epoch_ns) % self.period_ns) / self.period_ns)
        omega = 2.0 * math.pi / (self.period_ns / 1e9)
        ax, ay, psi = self._amp_x, self._amp_y, phase + self._phase
        return BallState(
            t_ns=t_ns,
            x=ax * math.sin(psi),
            y=ay * math.sin(2.0 * psi),
            vx=ax * omega * math.cos(psi),
            vy=2.0 * ay * omega * math.cos(2.0 * psi),
        )

    def ball_in_image(self, camera: str, t_ns: int, width: int, height: int) -> ImageBall | None:
        """The ball as ``camera`` renders it at ``t_ns``; None when no part of it is in the image."""
        ball = self.ball_at(t_ns)
        (uv,), (depth,) = project(camera, width, height, np.array([[ball.x, ball.y, BALL_RADIUS_M]]))
        if depth <= BALL_RADIUS_M:
            return None
        f = camera_matrix(camera, width, height)[0, 0]
        radius = f * BALL_RADIUS_M / depth
        u, v = float(uv[0]), float(uv[1])
        if u + radius < 0 or v + radius < 0 or u - radius > width - 1 or v - radius > height - 1:
            return None
        complete = radius <= u <= width - 1 - radius and radius <= v <= height - 1 - radius
        return ImageBall(u, v, float(radius), complete)

    # -- rendering

    def render(self, camera: str, t_ns: int, width: int, height: int, noise: float = 0.0) -> np.ndarray:
        """The BGR image ``camera`` sees at ``t_ns``: a new ``height x width x 3`` uint8 array.

        ``noise`` adds Gaussian pixel noise of that standard deviation (grey levels), drawn from
        a small bank fixed by the seed, so rendering stays cheap and deterministic.
        """
        frame = self._background(camera, width, height).copy()
        ball = self.ball_in_image(camera, t_ns, width, height)
        if ball is not None:
            _draw_ball(frame, ball)
        if noise > 0:
            bank = self._noise_bank(width, height, noise)
            cv2.add(frame, bank[(int(t_ns) // 33_000_000) % len(bank)], dst=frame, dtype=cv2.CV_8U)
        return frame

    def _background(self, camera: str, width: int, height: int) -> np.ndarray:
        key = (camera, width, height)
        background = self._backgrounds.get(key)
        if background is None:
            # shared by every scene of this seed in the process: a camera started again (after a
            # switch back, say) does not warp its background again (about 0.1 s at 640x480)
            shared = (self.seed, camera, width, height)
            background = _SHARED_BACKGROUNDS.get(shared)
            if background is None:
                background = _SHARED_BACKGROUNDS[shared] = self._warp_background(camera, width, height)
            self._backgrounds[key] = background
        return background

    def _warp_background(self, camera: str, width: int, height: int) -> np.ndarray:
        texture = self.texture()
        s, m = _TEXTURE_PX_PER_M, _TEXTURE_MARGIN_M
        u0, v0 = (FIELD_LENGTH_M / 2 + m) * s, (FIELD_WIDTH_M / 2 + m) * s
        texture_to_field = np.array([[1.0 / s, 0.0, -u0 / s], [0.0, -1.0 / s, v0 / s], [0.0, 0.0, 1.0]])
        ground_to_image = _plane_to_image(camera, width, height, 0.0)
        image = cv2.warpPerspective(
            texture, ground_to_image @ texture_to_field, (width, height),
            flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=_FLOOR_BGR,
        )  # fmt: skip
        # Rays that do not go down never reach the floor: there is the wall (the warp would show
        # the floor mirrored through the horizon instead).
        pose = _pose(camera)
        k_inv = np.linalg.inv(camera_matrix(camera, width, height))
        us, vs = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays = np.stack([us, vs, np.ones_like(us)], axis=-1) @ (pose.rotation().T @ k_inv).T
        image[rays[..., 2] >= -1e-3] = _WALL_BGR
        image.flags.writeable = False
        return image

    def texture(self) -> np.ndarray:
        """The top-down field texture (BGR, 100 px per metre, with a 1 m margin of floor)."""
        if self._texture is not None:
            return self._texture
        s, m = _TEXTURE_PX_PER_M, _TEXTURE_MARGIN_M
        width, height = round((FIELD_LENGTH_M + 2 * m) * s), round((FIELD_WIDTH_M + 2 * m) * s)
        rng = np.random.default_rng([self.seed, 1])
        # Carpet: brightness varies smoothly and with a fine grain; the hue stays blue-grey.
        coarse = cv2.GaussianBlur(rng.normal(0.0, 1.0, (height, width)).astype(np.float32), (0, 0), 12)
        coarse = coarse * (0.12 / max(float(np.abs(coarse).max()), 1e-6))
        grain = rng.normal(0.0, 0.05, (height, width)).astype(np.float32)
        shade = (1.0 + coarse + grain)[..., None]
        image: np.ndarray = np.clip(_CARPET_BGR * shade, 0, 255).astype(np.uint8)

        def px(x: float, y: float) -> tuple[int, int]:
            return round((x + FIELD_LENGTH_M / 2 + m) * s), round((FIELD_WIDTH_M / 2 + m - y) * s)

        field_mask = np.zeros((height, width), np.uint8)
        cv2.rectangle(field_mask, px(-FIELD_LENGTH_M / 2, FIELD_WIDTH_M / 2), px(FIELD_LENGTH_M / 2, -FIELD_WIDTH_M / 2), 255, -1)
        floor = np.clip(np.array(_FLOOR_BGR, np.float32) * shade, 0, 255).astype(np.uint8)
        image[field_mask == 0] = floor[field_mask == 0]
        line = round(0.05 * s)
        half_l, half_w = FIELD_LENGTH_M / 2, FIELD_WIDTH_M / 2
        cv2.rectangle(image, px(-half_l, half_w), px(half_l, -half_w), _LINE_BGR, line, cv2.LINE_AA)
        cv2.line(image, px(0, half_w), px(0, -half_w), _LINE_BGR, line, cv2.LINE_AA)
        cv2.circle(image, px(0, 0), round(0.6 * s), _LINE_BGR, line, cv2.LINE_AA)
        for sign in (-1, 1):
            cv2.rectangle(image, px(sign * half_l, 1.1), px(sign * (half_l - 0.6), -1.1), _LINE_BGR, line, cv2.LINE_AA)
            cv2.circle(image, px(sign * (half_l - 1.3), 0), round(0.04 * s), _LINE_BGR, -1, cv2.LINE_AA)
        image.flags.writeable = False
        self._texture = image
        return image

    def _noise_bank(self, width: int, height: int, sigma: float) -> list[np.ndarray]:
        key = (width, height, sigma)
        bank = self._noise.get(key)
        if bank is None:
            shared = (self.seed, width, height, sigma)  # like the backgrounds: made once per process
            bank = _SHARED_NOISE.get(shared)
            if bank is None:
                rng = np.random.default_rng([self.seed, 2])
                bank = [np.clip(rng.normal(0.0, sigma, (height, width, 3)), -127, 127).astype(np.int16) for _ in range(4)]
                for b in bank:
                    b.flags.writeable = False
                _SHARED_NOISE[shared] = bank
            self._noise[key] = bank
        return bank


def _draw_ball(frame: np.ndarray, ball: ImageBall) -> None:
    shift = 4  # sub-pixel drawing: coordinates in 1/16 pixel, so the disc is centred exactly
    scale = 1 << shift

    def circle(dx: float, dy: float, radius: float, colour: tuple[int, int, int]) -> None:
        centre = (round((ball.x + dx) * scale), round((ball.y + dy) * scale))
        cv2.circle(frame, centre, max(1, round(radius * scale)), colour, -1, cv2.LINE_AA, shift)

    r = ball.radius
    circle(0.0, 0.0, r, _BALL_RIM_BGR)
    circle(-0.06 * r, -0.06 * r, 0.82 * r, BALL_BGR)
    circle(-0.3 * r, -0.3 * r, 0.28 * r, _BALL_SHINE_BGR)
