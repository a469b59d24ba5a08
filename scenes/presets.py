"""Named scene presets: textured planes (metres) and a camera arc, from easy to extreme.

World frame: z up, metres. Planes are rectangles `origin + a*u + b*v` (a in [0, width],
b in [0, height]) whose front side faces `normal = u x v`. Cameras sit on an arc around a
look-at point at a fixed distance and elevation; their azimuth is measured in degrees in the
x-y plane from the +x axis. The viewing angle of a camera to a plane is the angle between the
plane's normal and the ray from the plane's centre to the camera (0 = frontal, 90 = grazing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Plane:
    """A textured rectangle: `origin` corner, unit axes `u` (width) and `v` (height), in metres."""

    name: str
    origin: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    width: float
    height: float

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(self.origin) + 0.5 * self.width * np.asarray(self.u) + 0.5 * self.height * np.asarray(self.v)

    def corners(self) -> np.ndarray:
        o, u, v = (np.asarray(x, float) for x in (self.origin, self.u, self.v))
        return np.array([o, o + self.width * u, o + self.width * u + self.height * v, o + self.height * v])


@dataclass(frozen=True)
class CameraArc:
    """Cameras at `azimuths_deg` around `look_at`, `distance` m away, `elevation_deg` up."""

    azimuths_deg: tuple[float, ...]
    distance: float
    elevation_deg: float
    look_at: tuple[float, float, float]


@dataclass(frozen=True)
class ScenePreset:
    """A scene: planes, cameras, image size (px) and focal length (px)."""

    name: str
    description: str
    planes: tuple[Plane, ...]
    cameras: CameraArc
    image_size: tuple[int, int] = (800, 600)
    focal_px: float = 720.0
    px_per_m: float = 160.0  # texture resolution on the planes
    noise_sigma: float = 2.0  # gray levels of seeded sensor noise

    @property
    def azimuth_step(self) -> float:
        a = self.cameras.azimuths_deg
        return float(np.median(np.abs(np.diff(a)))) if len(a) > 1 else 0.0


def _arc(first: float, last: float, n: int) -> tuple[float, ...]:
    return tuple(float(x) for x in np.linspace(first, last, n))


def corner_planes(size: float = 12.0, height: float = 5.0) -> tuple[Plane, ...]:
    """An inside building corner: wall A in y = 0 (facing +y), wall B in x = 0 (facing +x), ground."""
    return (
        Plane("wall_a", (size, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), size, height),
        Plane("wall_b", (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), size, height),
        Plane("ground", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), size, size),
    )


def facade_planes() -> tuple[Plane, ...]:
    """A stepped facade facing +y: wall segments at depths 0, -1.5, 0 m (x in [-6, 6]) joined
    by the recess's side walls, and the ground in front."""
    h = 5.0
    return (
        Plane("left", (-2.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 4.0, h),
        Plane("recess_side_l", (-2.0, -1.5, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), 1.5, h),
        Plane("middle", (2.0, -1.5, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 4.0, h),
        Plane("recess_side_r", (2.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), 1.5, h),
        Plane("right", (6.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 4.0, h),
        Plane("ground", (-6.0, -1.5, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), 12.0, 7.5),
    )


def corner_preset(name: str, n_views: int, az_first: float, az_last: float, description: str) -> ScenePreset:
    return ScenePreset(name=name, description=description, planes=corner_planes(),
                       cameras=CameraArc(_arc(az_first, az_last, n_views), distance=12.0,
                                         elevation_deg=10.0, look_at=(1.0, 1.0, 1.5)))


def facade_sweep(num_views: int, max_azimuth_deg: float, name: str | None = None) -> ScenePreset:
    """The stepped facade seen from `num_views` cameras spread over +-`max_azimuth_deg` about
    its normal (+y): the difficulty axis of the benchmarks (azimuth step between neighbours)."""
    az = _arc(90.0 - max_azimuth_deg, 90.0 + max_azimuth_deg, num_views)
    return ScenePreset(
        name=name or f"facade-{num_views}x{int(round(max_azimuth_deg))}",
        description=f"stepped facade, {num_views} views over +-{max_azimuth_deg:g} deg",
        planes=facade_planes(),
        cameras=CameraArc(az, distance=11.0, elevation_deg=12.0, look_at=(0.0, -0.5, 2.0)))


def facade_groups(name: str = "facade-groups") -> ScenePreset:
    """The stepped facade photographed from two spots: three views 6 deg apart at -40 deg and three
    at +30 deg about its normal (58-82 deg between the groups). The common shape of a casual
    capture: easy pairs within each group, only wide-baseline pairs joining them (the bridges of
    `recon run --simulate needed`)."""
    az = tuple(90.0 + a for a in (-80.0, -74.0, -68.0, 26.0, 32.0, 38.0))
    return ScenePreset(
        name=name, description="stepped facade, two groups of 3 views 6 deg apart, 58-82 deg between the groups",
        planes=facade_planes(),
        cameras=CameraArc(az, distance=11.0, elevation_deg=12.0, look_at=(0.0, -0.5, 2.0)))


def building_planes(width: float = 8.0, depth: float = 6.0, height: float = 5.0,
                    ground: float = 16.0) -> tuple[Plane, ...]:
    """A free-standing block building centred on the origin: four walls facing outwards
    (`width` m along x, `depth` m along y, `height` m tall) and a square ground of `ground` m."""
    w, d = width / 2.0, depth / 2.0
    return (
        Plane("south", (-w, -d, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), width, height),   # faces -y
        Plane("east", (w, -d, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), depth, height),    # faces +x
        Plane("north", (w, d, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), width, height),   # faces +y
        Plane("west", (-w, d, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), depth, height),   # faces -x
        Plane("ground", (-ground / 2, -ground / 2, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), ground, ground),
    )


ORBIT_MIN_VIEWS = 3
ORBIT_MAX_VIEWS = 2000


def orbit(num_views: int, name: str | None = None) -> ScenePreset:
    """A walk all around a block building (`building_planes`), `num_views` photos evenly spaced
    over 360 deg of azimuth, 12 m from its centre and 20 deg up: the scale benchmark's capture
    (`recon bench scale`). Neighbours overlap (360/N deg apart) and opposite sides never do, as
    in a real capture, so the pairs worth matching grow like N while all pairs grow like N^2."""
    if not ORBIT_MIN_VIEWS <= num_views <= ORBIT_MAX_VIEWS:
        raise ValueError(f"orbit: {num_views} views; choose {ORBIT_MIN_VIEWS}-{ORBIT_MAX_VIEWS}")
    az = tuple(float(x) for x in -90.0 + 360.0 * np.arange(num_views) / num_views)  # first view faces south
    return ScenePreset(
        name=name or f"orbit-{num_views}",
        description=f"block building, {num_views} views all around (360 deg, {360.0 / num_views:.3g} deg apart)",
        planes=building_planes(),
        cameras=CameraArc(az, distance=12.0, elevation_deg=20.0, look_at=(0.0, 0.0, 1.5)))


PRESETS: dict[str, ScenePreset] = {
    p.name: p for p in (
        corner_preset("corner-easy", 8, 25.0, 65.0, "building corner, 8 views over 40 deg (easy)"),
        corner_preset("corner", 6, 2.0, 88.0, "building corner, 6 views 17 deg apart, viewing angles to ~80 deg (default)"),
        corner_preset("corner-wide", 4, 2.0, 88.0, "building corner, 4 views 29 deg apart, viewing angles to ~80 deg"),
        facade_sweep(5, 75.0, "facade-wide"),
        facade_sweep(4, 80.0, "facade-extreme"),
        facade_groups(),
    )
}
DEFAULT_PRESET = "corner"


def get_preset(name: str) -> ScenePreset:
    """The preset called `name`, `facade-<N>x<DEG>` for a facade sweep or `orbit-<N>` for N views
    all around a building (`orbit`); ValueError listing names."""
    if name in PRESETS:
        return PRESETS[name]
    if name.startswith("orbit-"):
        try:
            n_views = int(name[len("orbit-"):])
        except ValueError:
            n_views = -1
        if ORBIT_MIN_VIEWS <= n_views <= ORBIT_MAX_VIEWS:
            return orbit(n_views)
    if name.startswith("facade-") and "x" in name:
        try:
            n, deg = name[len("facade-"):].split("x", 1)
            if 2 <= int(n) <= 30 and 0 < float(deg) <= 85:
                return facade_sweep(int(n), float(deg))
        except ValueError:
            pass
    raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}, facade-<N>x<DEG> "
                     f"or orbit-<N> ({ORBIT_MIN_VIEWS}-{ORBIT_MAX_VIEWS} views)")


def viewing_angle_deg(plane: Plane, cam_centre: np.ndarray) -> float:
    """Angle between the plane's normal and the ray from its centre to the camera (degrees)."""
    ray = np.asarray(cam_centre, float) - plane.centre
    c = float(np.dot(ray, plane.normal) / np.linalg.norm(ray))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))
