"""What every cue reads: the budgets of a pass, area-weighted surface samples and face
samples of a mesh, and the side view (``Context``): the mirror plane's frame, the length
axis and the up direction being decided. Units: the mesh's file frame.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..artifacts import Mesh

N_SAMPLES = 4096                # area-weighted surface samples
MIRROR_STRIDE = 4               # every 4th sample (1,024) builds the mirror plane
SAMPLE_SEED = 0x0DE7            # fixed random stream: the same mesh gives the same samples
FACE_BLOCK = 8192               # faces per block in per-face passes (temporaries stay in cache)
WHEEL_MIN_VOTES = 10            # Hough votes a wheel circle needs (3 x 3 cells)


class Budget(NamedTuple):
    """How much work one pass of the estimate does: area samples and face samples
    (``surface_samples``); the mirror plane built on every ``mirror_stride``-th area
    sample, candidates ranked on ``mirror_rank`` of them, ``mirror_refined`` candidates
    refined two steps and ``mirror_final`` of them in full (``mirror_plane``); Hough radii
    and peaks per radius in the wheel search,
    and the Hough votes a wheel needs (it scales with the samples; ``find_wheels``)."""
    samples: int
    face_samples: int
    mirror_stride: int
    mirror_rank: int
    mirror_refined: int
    mirror_final: int
    radii: int
    peaks: int
    wheel_votes: int


#: today's estimate; FAST: the cheap first pass of the cascade (see ``_estimate``)
FULL = Budget(samples=N_SAMPLES, face_samples=N_SAMPLES, mirror_stride=MIRROR_STRIDE,
              mirror_rank=128, mirror_refined=6, mirror_final=2, radii=8, peaks=5,
              wheel_votes=WHEEL_MIN_VOTES)
FAST = Budget(samples=1024, face_samples=4096, mirror_stride=1, mirror_rank=64, mirror_refined=3,
              mirror_final=1, radii=6, peaks=3, wheel_votes=6)


# ----------------------------------------------------------------------------- samples

class Samples:
    """Area-weighted surface samples: points (N, 3), unit face normals (N, 3), face index (N,);
    and face samples: the centroids and normals of faces drawn uniformly by count (detail:
    finely tessellated parts such as tyres get many), ``detail_points`` / ``detail_normals``."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, face: np.ndarray,
                 detail_points: np.ndarray | None = None,
                 detail_normals: np.ndarray | None = None,
                 face_centroid: np.ndarray | None = None, face_area2: np.ndarray | None = None):
        self.points, self.normals, self.face = points, normals, face
        self.detail_points = detail_points if detail_points is not None else points[:0]
        self.detail_normals = detail_normals if detail_normals is not None else normals[:0]
        # all faces: centroids (F, 3), twice the areas (F,)
        self.face_centroid, self.face_area2 = face_centroid, face_area2


def surface_samples(mesh: Mesh, n: int = N_SAMPLES, skip_material: int = -1,
                     geometry: Geometry | None = None, n_faces: int | None = None) -> Samples:
    """``n`` points drawn uniformly over the surface (face by area, then a uniform point in
    it) and ``n_faces`` (default ``n``) faces drawn by count, from a fixed random stream.
    The stream does not depend on coordinates, so an axis-permuted copy of a mesh gets the
    same faces and the permuted points. Faces of material ``skip_material`` get none.
    ``geometry``: ``face_geometry(mesh)`` when known."""
    f = np.asarray(mesh.faces)
    a2, fc, xyz = face_geometry(mesh) if geometry is None else geometry
    if skip_material >= 0:
        a2 = np.where(np.asarray(mesh.face_material) == skip_material, 0.0, a2)
    cum = np.cumsum(a2)
    rng = np.random.default_rng(SAMPLE_SEED)
    u, r1, r2 = rng.random(n), rng.random(n), rng.random(n)
    total = float(cum[-1]) if cum.size else 0.0
    fi = np.zeros(n, np.intp)
    if total > 0.0:
        key = u * total
        up = np.argsort(key)                              # ascending keys search faster
        fi[up] = np.minimum(np.searchsorted(cum, key[up], side="right"), len(a2) - 1)
    flip = r1 + r2 > 1.0
    r1, r2 = np.where(flip, 1.0 - r1, r1), np.where(flip, 1.0 - r2, r2)
    p, nrm = _face_points(xyz, f, fi, r1, r2)
    n_live = np.count_nonzero(a2 > 0.0)                   # faces with an area
    fd = np.zeros(0, np.intp)
    if n_live:
        fd = rng.integers(0, n_live, n if n_faces is None else n_faces)   # the k-th of them
        if n_live < len(a2):
            fd = np.flatnonzero(a2 > 0.0)[fd]
    dp, dn = fc[fd], _face_points(xyz, f, fd, r1[:0], r2[:0])[1]
    return Samples(p, nrm, fi, dp, dn, fc, a2)


class Geometry(NamedTuple):
    """Per-mesh face geometry, shared by the cascade's passes: twice the face areas (F,),
    the face centroids (F, 3) and the vertices' x, y and z rows (3, V)."""
    area2: np.ndarray
    centroid: np.ndarray
    xyz: np.ndarray


def face_geometry(mesh: Mesh) -> Geometry:
    """The faces' areas and centroids (see ``Geometry``), a block of faces at a time with
    preallocated temporaries (they stay in cache)."""
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces)
    xyz = np.ascontiguousarray(v.T)
    x, y, z = xyz
    F = len(f)
    a2, fc = np.empty(F), np.empty((F, 3))                # twice the face areas, centroids
    tmp = [np.empty(min(FACE_BLOCK, F)) for _ in range(12)]
    corner = [np.empty(min(FACE_BLOCK, F), np.intp) for _ in range(3)]   # corner vertices
    for lo in range(0, F, FACE_BLOCK):
        hi = min(lo + FACE_BLOCK, F)
        x0, y0, z0, ax, ay, az, bx, by, bz, cx, cy, cz = (t[:hi - lo] for t in tmp)
        i0, i1, i2 = (c[:hi - lo] for c in corner)
        i0[:], i1[:], i2[:] = f[lo:hi].T                  # casts other index types once
        for row, c0, c1, c2 in ((x, x0, ax, bx), (y, y0, ay, by), (z, z0, az, bz)):
            row.take(i0, out=c0)
            row.take(i1, out=c1)
            row.take(i2, out=c2)
            c1 -= c0                                      # edges a = p1 - p0, b = p2 - p0
            c2 -= c0
        t = a2[lo:hi]                                     # a temporary until the last step
        np.multiply(ay, bz, out=cx)                       # a x b
        cx -= np.multiply(az, by, out=t)
        np.multiply(az, bx, out=cy)
        cy -= np.multiply(ax, bz, out=t)
        np.multiply(ax, by, out=cz)
        cz -= np.multiply(ay, bx, out=t)
        cx *= cx
        cx += np.multiply(cy, cy, out=t)
        cx += np.multiply(cz, cz, out=t)
        np.sqrt(cx, out=t)
        for k, (c0, c1, c2) in enumerate(((x0, ax, bx), (y0, ay, by), (z0, az, bz))):
            c1 += c2                                      # centroid p0 + (a + b) / 3
            c1 /= 3.0
            np.add(c0, c1, out=fc[lo:hi, k])
    return Geometry(a2, fc, xyz)


def _face_points(xyz: np.ndarray, f: np.ndarray, fi: np.ndarray, r1: np.ndarray,
                 r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``p0 + r1 (p1 - p0) + r2 (p2 - p0)`` of faces ``fi`` (none when r1 is empty)
    and the faces' unit normals (zero for a degenerate face); ``xyz``: the vertices' x, y
    and z rows (3, V). Coordinate by coordinate on contiguous rows (the same operations on
    each element as on (N, 3) columns, so the same bits)."""
    corner = f[fi].T.astype(np.intp)                      # (3, N) vertex of each corner
    x0, a, b = [], [], []
    for row in xyz:
        c0, c1, c2 = row.take(corner)
        x0.append(c0)
        a.append(c1 - c0)
        b.append(c2 - c0)
    cx, cy, cz = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                  a[0] * b[1] - a[1] * b[0])
    norm = np.maximum(np.sqrt(cx * cx + cy * cy + cz * cz), 1e-300)
    c = np.empty((len(fi), 3))
    c[:, 0], c[:, 1], c[:, 2] = cx / norm, cy / norm, cz / norm
    p = np.empty((len(fi) if r1.size else 0, 3))
    if r1.size:
        for k in range(3):
            p[:, k] = x0[k] + r1 * a[k] + r2 * b[k]
    return p, c


def quantile(x: np.ndarray, f: float) -> float:
    """The ``f`` quantile of ``x`` (lower order statistic; np.partition, no interpolation)."""
    k = min(max(int(f * (x.size - 1)), 0), x.size - 1)
    return float(np.partition(x, k)[k])


def cross3(a, b) -> np.ndarray:
    """``np.cross`` of two 3-vectors (the same products, without its array overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


# ----------------------------------------------------------------------------- side view

class Context:
    """Samples in the vehicle's provisional frame: s along the length axis a, t along the
    height axis b (both in [-1, 1] over the samples' extent), q across (signed distance from
    the mirror plane / its largest value). a, b, w are right-handed (w = a x b)."""

    def __init__(self, mesh: Mesh, S: Samples, w: np.ndarray, wd: float):
        self.mesh, self.S, self.w, self.wd = mesh, S, w, wd
        p = S.points
        side = p - np.outer(p @ w - wd, w)
        c = side - side.mean(axis=0)
        P = np.eye(3) - np.outer(w, w)
        _, V = np.linalg.eigh(P @ (c.T @ c) @ P)
        self.set_length_axis(V[:, 2])                      # the longer in-plane axis
        self._level_on_rectangle()

    def set_length_axis(self, a: np.ndarray) -> None:
        a = a - (a @ self.w) * self.w
        a = a / np.linalg.norm(a)
        self._set_axes(a, cross3(self.w, a))

    def flip_up(self, flip: bool) -> None:
        """Make -b the height axis (w flips too, keeping a, b, w right-handed)."""
        if flip:
            self.w, self.wd = -self.w, -self.wd
            self._set_axes(self.a, -self.b)

    def _set_axes(self, a: np.ndarray, b: np.ndarray) -> None:
        p, n = self.S.points, self.S.normals
        self.a, self.b = a, b
        s, t, q = p @ a, p @ b, p @ self.w - self.wd
        self.s0, self.t0 = 0.5 * (s.min() + s.max()), 0.5 * (t.min() + t.max())
        self.half_len = max(0.5 * float(np.ptp(s)), 1e-12)
        self.half_h = max(0.5 * float(np.ptp(t)), 1e-12)
        self.half_w = max(float(np.abs(q).max()), 1e-12)
        self.s = (s - self.s0) / self.half_len
        self.t = (t - self.t0) / self.half_h
        self.q = q / self.half_w
        self.ns, self.nt, self.nq = n @ a, n @ b, n @ self.w

    def face_s(self) -> np.ndarray:
        """(F,) every face centroid's position along the length axis, like ``s``."""
        fs = self.S.face_centroid @ self.a
        fs -= self.s0
        fs /= self.half_len
        return fs

    def side_points(self) -> np.ndarray:
        """(N, 2) samples in the side view, mesh units, centred on the side view's box."""
        return np.stack([self.s * self.half_len, self.t * self.half_h], axis=1)

    def side_hull(self) -> np.ndarray | None:
        """Vertices of the side view's convex hull, in order (None when degenerate). The
        hull is computed once: changing the in-plane axes only rotates or mirrors it."""
        if not hasattr(self, "_hull"):
            from scipy.spatial import ConvexHull, QhullError
            try:
                self._hull = ConvexHull(self.side_points()).vertices
            except (QhullError, ValueError):
                self._hull = None
        return None if self._hull is None else self.side_points()[self._hull]

    def _level_on_rectangle(self) -> None:
        """Turn the length axis onto the longer side of the side view's smallest-area
        bounding rectangle (one side of it lies on a hull edge): a vehicle's side view is
        roughly a rectangle standing on its wheels or sills, while the principal axis tilts
        with the mass (a tall cab, a high tail)."""
        hull = self.side_hull()
        if hull is None:
            return
        e = np.roll(hull, -1, axis=0) - hull
        ln = np.hypot(e[:, 0], e[:, 1])
        ok = ln > 1e-12
        d = e[ok] / ln[ok, None]
        along = hull @ d.T                                  # (K, E) projections
        across = hull @ np.stack([-d[:, 1], d[:, 0]], axis=1).T
        ext_a, ext_c = np.ptp(along, axis=0), np.ptp(across, axis=0)
        k = int(np.argmin(ext_a * ext_c + 1e-15 * np.arange(ext_a.size)))   # tie: first edge
        u = d[k] if ext_a[k] >= ext_c[k] else np.array([-d[k, 1], d[k, 0]])
        u = u if u[0] >= 0 else -u
        self.set_length_axis(u[0] * self.a + u[1] * self.b)

    def level_from_hull(self) -> None:
        """Without wheels: level the length axis on the longest side-view hull edge within
        8 degrees of it that spans at least 40 % of the length (a floor or sill line)."""
        hull = self.side_hull()
        if hull is None:
            return
        e = np.roll(hull, -1, axis=0) - hull
        ln = np.hypot(e[:, 0], e[:, 1])
        ok = (np.abs(e[:, 1]) < math.tan(math.radians(8.0)) * np.abs(e[:, 0])) & (
            ln > 0.8 * self.half_len)
        if ok.any():
            k = int(np.argmax(np.where(ok, ln, -1.0)))
            d = e[k] / ln[k] * (1.0 if e[k, 0] >= 0 else -1.0)
            self.set_length_axis(d[0] * self.a + d[1] * self.b)
