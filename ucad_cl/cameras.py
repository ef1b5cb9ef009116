"""Camera rings around a canonical mesh (float64 on the host).

Conventions (see ``ucad_cl/artifacts.py``): OpenCV camera (x right, y down, z forward), pixel (i, j)
centred at (j + 0.5, i + 0.5); azimuth 0 looks from +X toward the origin, azimuth grows
counter-clockwise seen from +Y (from +X toward -Z); elevation > 0 is above. Degrees.

The canonical mesh has its bounding box centred at the origin with diagonal 1, so it lies inside
the sphere of radius 0.5. The fitted distance puts that sphere inside the field of view (the
narrower of horizontal and vertical) with a small margin, from every direction.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .artifacts import CameraRing

BOUND_RADIUS = 0.5      # canonical bounding sphere radius (bbox diagonal 1)
BUILD_ELEVATIONS = (15.0, 5.0)   # the build's stored rings, the label ring first (label_ring)
MAX_SIZE = 8192         # the rasterizer's fixed-point range is proven for images up to this size
NEAR_FRACTION = 0.01    # default near plane: this fraction of the camera's distance


def make_ring(azimuth_step: float = 5.0, elevations: Sequence[float] = (15.0,),
              fov_deg: float = 40.0, size: int | tuple[int, int] = 256,
              azimuths: Sequence[float] | None = None, distance: float | None = None,
              margin: float = 1.05, near: float | None = None) -> CameraRing:
    """Cameras on a ring: ``M = 360/azimuth_step`` azimuths for each elevation (elevation-major).

    size: int (square) or (width, height) in pixels. fov_deg: field of view of the narrower side.
    distance: camera distance from the origin (canonical units); fitted when None.
    near: near-plane depth; default ``NEAR_FRACTION`` of the distance.
    """
    width, height = (size, size) if np.isscalar(size) else (int(size[0]), int(size[1]))
    if not (1 <= width <= MAX_SIZE and 1 <= height <= MAX_SIZE):
        raise ValueError(f"image size {width}x{height} outside 1..{MAX_SIZE}")
    if not 0.0 < fov_deg < 179.0:
        raise ValueError(f"fov_deg={fov_deg} must be in (0, 179)")
    if azimuths is None:
        if not 0.0 < azimuth_step <= 360.0:
            raise ValueError(f"azimuth_step={azimuth_step} must be in (0, 360]")
        m = int(round(360.0 / azimuth_step))
        if abs(m * azimuth_step - 360.0) > 1e-9:
            raise ValueError(f"azimuth_step={azimuth_step} must divide 360")
        azimuths = np.arange(m, dtype=np.float64) * azimuth_step
    az = np.asarray(azimuths, dtype=np.float64)
    el = np.asarray(list(elevations), dtype=np.float64)
    if el.size == 0 or az.size == 0:
        raise ValueError("need at least one azimuth and one elevation")
    if np.any(np.abs(el) >= 90.0):
        raise ValueError(f"elevations must be inside (-90, 90), got {el.tolist()}")
    half = np.radians(fov_deg) / 2.0
    f = 0.5 * min(width, height) / np.tan(half)
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    if distance is None:
        distance = margin * BOUND_RADIUS / np.sin(half)
    if near is None:
        near = NEAR_FRACTION * distance
    all_el = np.repeat(el, az.size)
    all_az = np.tile(az, el.size)
    w2c = look_at_many(all_az, all_el, distance)
    return CameraRing(K=K, w2c=w2c, width=width, height=height, azimuth=all_az,
                      elevation=all_el, distance=float(distance), near=float(near))


def camera_position(azimuth: float, elevation: float, distance: float) -> np.ndarray:
    """Camera centre in the canonical frame for the given azimuth/elevation (degrees)."""
    a, e = np.radians(azimuth), np.radians(elevation)
    return distance * np.array([np.cos(e) * np.cos(a), np.sin(e), -np.cos(e) * np.sin(a)])


def single_camera(K, w2c, width: int, height: int, *, azimuth: float = 0.0,
                  elevation: float = 0.0, distance: float | None = None) -> CameraRing:
    """A one-view ring of the camera ``K`` (3x3), ``w2c`` (4x4) over a ``width`` x ``height``
    image (a photo's camera, to render a mesh as the photo sees it). distance: the camera's
    distance from the vehicle's centre, default ``camera_distance(w2c)``; near plane
    ``NEAR_FRACTION`` of it, as on every ring."""
    if distance is None:
        distance = camera_distance(w2c)
    return CameraRing(K=np.asarray(K, np.float64), w2c=np.asarray(w2c, np.float64)[None],
                      width=int(width), height=int(height), azimuth=np.array([float(azimuth)]),
                      elevation=np.array([float(elevation)]), distance=float(distance),
                      near=NEAR_FRACTION * float(distance))


def camera_distance(w2c) -> float:
    """Distance of a camera's centre (-R^T t of a 4x4 world-to-camera matrix) from the
    canonical origin, the vehicle's centre."""
    w2c = np.asarray(w2c, np.float64)
    return float(np.linalg.norm(w2c[:3, :3].T @ w2c[:3, 3]))


def look_at_w2c(azimuth: float, elevation: float, distance: float,
                target: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 world-to-camera matrix of a camera looking at ``target`` (OpenCV axes, +Y world up)."""
    return look_at_many([azimuth], [elevation], distance, target)[0]


def look_at_many(azimuths, elevations, distance: float,
                 target: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(N, 4, 4) ``look_at_w2c`` of N cameras at once (degrees; one distance and target): the
    camera at ``camera_position`` + target, rows right, down, forward (forward toward the
    target, right = forward x up), translation -R c. Lengths are sqrt((x^2 + y^2) + z^2)."""
    a = np.radians(np.asarray(azimuths, np.float64))
    e = np.radians(np.asarray(elevations, np.float64))
    to = np.asarray(target, dtype=np.float64)
    pos = distance * np.stack([np.cos(e) * np.cos(a), np.sin(e), -np.cos(e) * np.sin(a)], -1)
    pos = pos + to
    fwd = to - pos
    fwd /= _lengths(fwd)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= _lengths(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd], 1)
    w2c = np.zeros((len(pos), 4, 4))
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = (-R @ pos[:, :, None])[:, :, 0]
    w2c[:, 3, 3] = 1.0
    return w2c


def _lengths(x: np.ndarray) -> np.ndarray:
    """(N, 1) Euclidean lengths of the rows of ``x`` (N, 3), summed in that order."""
    return np.sqrt((x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1]) + x[:, 2] * x[:, 2])[:, None]


def pixel_rays(K: np.ndarray, w2c: np.ndarray, width: int, height: int):
    """Ray origins (3,) and unit directions (H, W, 3) through pixel centres, canonical frame."""
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    pix = np.stack([j, i, np.ones_like(j)], axis=-1)
    d_cam = pix @ np.linalg.inv(K).T
    R, t = w2c[:3, :3], w2c[:3, 3]
    d = d_cam @ R                       # R^T d for each row
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return -R.T @ t, d


def label_ring(ring: CameraRing) -> slice:
    """The views of a stack's label ring: its first ring (views are stored ring by ring,
    elevation-major, the first ring labelling: docs/CONVENTIONS.md), i.e. views 0 .. M - 1 with
    M the number of azimuths a ring holds."""
    return slice(0, int(np.unique(np.asarray(ring.azimuth)).size))
