"""Synthetic tilt pairs: one textured plane seen frontally and obliquely, with the exact homography.

The absolute-tilt test of ASIFT (Morel and Yu) with rendered views instead of photographs: a
pinhole camera looks at the centre of a textured plane from the front (image 0) and from a
viewing angle `angle_deg` away from the plane's normal (image 1; tilt t = 1 / cos(angle)),
towards the in-plane direction `azimuth_deg`, turned by `roll_deg` about its optical axis and
zoomed by `zoom`; `Photometry` optionally gives the oblique photo another exposure, tone curve,
noise and JPEG compression. Both cameras stand at the same distance with the same focal length (times
`zoom` for image 1), so the oblique view shows the plane foreshortened by t along one direction
and in perspective, as a photograph would; pixels outside the plane are a flat grey.

Geometry: the world is the texture's own frame, in texture pixels, with the origin at the
texture's centre, x right, y down, the plane at z = 0, and the cameras on its -z side. Pixels are
in OpenCV's convention (centre of the top-left pixel at (0, 0)), as the matchers' keypoints are.
Views are rendered at `supersample` x the output resolution from the texture (bilinear) and
area-averaged down, so the foreshortened direction does not alias up to a tilt of `supersample`
(8 by default: an 82.8 degree view). The same texture and view always give the same bytes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .render import centred_K, look_at_pose, supersampled

BACKGROUND = 128  # grey level outside the plane
FOCAL_FACTOR = 1.0  # focal length / image width: a 53 degree horizontal field of view


@dataclass(frozen=True)
class TiltView:
    """Where the oblique camera stands, relative to the frontal one (degrees; `zoom` unitless)."""

    angle_deg: float
    """Viewing angle from the plane's normal, 0 <= angle < 90; the tilt is 1 / cos(angle)."""
    azimuth_deg: float = 0.0
    """In-plane direction the camera moves towards: 0 = along the texture's x axis (to the right)."""
    roll_deg: float = 0.0
    """Rotation of the oblique camera about its optical axis."""
    zoom: float = 1.0
    """Focal length of the oblique camera over the frontal one's (2 = twice the detail)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.angle_deg < 89.0:
            raise ValueError(f"angle_deg {self.angle_deg}: must be in [0, 89)")
        if not self.zoom > 0:
            raise ValueError(f"zoom {self.zoom}: must be positive")

    @property
    def tilt(self) -> float:
        return 1.0 / math.cos(math.radians(self.angle_deg))

    @property
    def name(self) -> str:
        parts = [f"{self.angle_deg:g}deg", f"az{self.azimuth_deg:g}"]
        if self.roll_deg:
            parts.append(f"roll{self.roll_deg:g}")
        if self.zoom != 1.0:
            parts.append(f"zoom{self.zoom:g}")
        return " ".join(parts)


@dataclass(frozen=True)
class Photometry:
    """How the oblique photo differs from the frontal one beyond geometry (applied to image 1 only):
    another exposure and tone curve, sensor noise, JPEG compression."""

    gain: float = 1.0
    """Multiplies the intensities (exposure), after `gamma`."""
    gamma: float = 1.0
    """Tone curve I' = 255 (I / 255) ** gamma (1 = none; > 1 darkens the mid-tones)."""
    noise_sigma: float = 0.0
    """Standard deviation of additive Gaussian noise, grey levels (seeded: same view, same noise)."""
    jpeg_quality: int = 0
    """JPEG quality of a compression round trip, 1-100 (0 = none)."""

    def __post_init__(self) -> None:
        finite = all(math.isfinite(v) for v in (self.gain, self.gamma, self.noise_sigma))
        if not (finite and self.gain > 0 and self.gamma > 0 and self.noise_sigma >= 0 and 0 <= self.jpeg_quality <= 100):
            raise ValueError(f"{self}: gain and gamma must be positive, noise_sigma >= 0, jpeg_quality in 0..100")

    def apply(self, img: NDArray[np.uint8], seed: int) -> NDArray[np.uint8]:
        out = img.astype(np.float64)
        if self.gamma != 1.0 or self.gain != 1.0:
            out = self.gain * 255.0 * (out / 255.0) ** self.gamma
        if self.noise_sigma > 0:
            out = out + np.random.default_rng([seed, 0x71E7]).normal(0.0, self.noise_sigma, out.shape)
        res = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        if self.jpeg_quality:
            ok, buf = cv2.imencode(".jpg", res, [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality)])
            res = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if ok else res
        return res


def cam_from_world(view: TiltView, distance: float) -> NDArray[np.float64]:
    """[R | t] of the camera of `view` (world = texture frame, see the module doc), looking at the
    origin from `distance` texture px; the frontal camera is TiltView(0), with the texture unmirrored
    (x right, y down). The view angle stays below 90 degrees, so the view never looks along y."""
    a, az, roll = (math.radians(v) for v in (view.angle_deg, view.azimuth_deg, view.roll_deg))
    centre = distance * np.array([math.sin(a) * math.cos(az), math.sin(a) * math.sin(az), -math.cos(a)])
    P = look_at_pose(centre, np.zeros(3), up=(0.0, -1.0, 0.0))
    c, s = math.cos(roll), math.sin(roll)
    roll_R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # x, y turned about the optical axis
    return roll_R @ P


def H_img_from_tex(K: NDArray, cam: NDArray, tex_size: tuple[int, int]) -> NDArray[np.float64]:
    """Homography from texture pixels to image pixels for camera `cam` = [R | t]."""
    w, h = tex_size
    to_world = np.array([[1.0, 0.0, -(w - 1) / 2.0], [0.0, 1.0, -(h - 1) / 2.0], [0.0, 0.0, 1.0]])
    M = np.stack([cam[:, 0], cam[:, 1], cam[:, 3]], axis=1)  # plane z = 0: columns r1, r2, t
    H = K @ M @ to_world
    return H / H[2, 2]


def render(texture: NDArray[np.uint8], view: TiltView, image_size: tuple[int, int], distance: float,
           supersample: int) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """The 8-bit grey image of `view` and its H_img_from_tex."""
    w, h = image_size
    K = centred_K(image_size, FOCAL_FACTOR * w * view.zoom)
    cam = cam_from_world(view, distance)
    tex_size = (texture.shape[1], texture.shape[0])
    H_big = H_img_from_tex(supersampled(K, supersample), cam, tex_size)
    big = cv2.warpPerspective(texture, H_big, (w * supersample, h * supersample), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA)
    return img, H_img_from_tex(K, cam, tex_size)


def render_tilt_pair(texture: NDArray[np.uint8], view: TiltView, image_size: tuple[int, int] = (800, 600),
                     supersample: int = 8, photometry: Photometry | None = None, seed: int = 0
                     ) -> tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.float64]]:
    """(frontal image, oblique image, H_1_from_0) for `texture` (8-bit grey or BGR).

    The frontal camera's distance makes the texture's width fill the image width (the texture
    is read at texture width / image width texture px per pixel: give it at least twice the
    image's width so that `zoom` 2 still has detail to show). `photometry` (seeded by `seed`)
    alters the oblique image only.
    """
    if texture.ndim == 3:
        texture = cv2.cvtColor(texture, cv2.COLOR_BGR2GRAY)
    distance = FOCAL_FACTOR * texture.shape[1]  # f = FOCAL_FACTOR * w: the texture's width spans the image's
    img0, H0 = render(texture, TiltView(0.0), image_size, distance, supersample)
    img1, H1 = render(texture, view, image_size, distance, supersample)
    if photometry is not None:
        img1 = photometry.apply(img1, seed)
    H = H1 @ np.linalg.inv(H0)
    return img0, img1, H / H[2, 2]
