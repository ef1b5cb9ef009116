"""Geometry primitives of the generator (NumPy, vectorised; faces wound counter-clockwise seen
from outside): tessellated patches, boxes, surfaces of revolution, mirrored copies; ``Part``,
one node with one material.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..artifacts import Material

# --------------------------------------------------------------------------------------------
# geometry primitives (NumPy, vectorised; faces wound counter-clockwise seen from outside)

@dataclass
class Part:
    node: str
    part: str
    material: Material
    vertices: np.ndarray      # (N, 3) float64 (float32-exact after _finish)
    faces: np.ndarray         # (F, 3) int64


def _lines(breaks: Sequence[float], length: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid parameters in [0, 1] through every break, cells of about ``cell`` (same unit as
    length); returns (params, segment index of each cell)."""
    b = np.asarray(breaks, dtype=np.float64)
    ts, seg = [np.zeros(1)], []
    for s in range(len(b) - 1):
        n = max(1, int(math.ceil((b[s + 1] - b[s]) * length / cell - 1e-9)))
        ts.append(b[s] + (b[s + 1] - b[s]) * np.arange(1, n + 1) / n)
        seg.append(np.full(n, s))
    t = np.concatenate(ts)
    t[0], t[-1] = b[0], b[-1]
    return t, np.concatenate(seg)


def patch(p00, p10, p01, p11, ubreaks, vbreaks, cell, bulge=0.0, label=None, drop=None):
    """Bilinear patch split into named panels.

    Corners p00 (u=0,v=0), p10, p01, p11; normal side = (p10-p00) x (p01-p00). ubreaks/vbreaks:
    panel boundaries in [0, 1]; label(su, sv) -> name or None (dropped). bulge: outward
    displacement (same unit) at the centre, zero on the border. drop(centroids) -> bool mask of
    faces to remove (wheel arches). Returns {name: (V, F)}.
    """
    p00, p10, p01, p11 = (np.asarray(p, dtype=np.float64) for p in (p00, p10, p01, p11))
    lu = max(np.linalg.norm(p10 - p00), np.linalg.norm(p11 - p01))
    lv = max(np.linalg.norm(p01 - p00), np.linalg.norm(p11 - p10))
    us, su = _lines(ubreaks, lu, cell)
    vs, sv = _lines(vbreaks, lv, cell)
    U, V = np.meshgrid(us, vs, indexing="ij")
    P = (((1 - U) * (1 - V))[..., None] * p00 + (U * (1 - V))[..., None] * p10
         + ((1 - U) * V)[..., None] * p01 + (U * V)[..., None] * p11)
    if bulge:
        n = np.cross(p10 - p00, p01 - p00)
        n /= np.linalg.norm(n)
        P += (bulge * (1 - (2 * U - 1) ** 2) * (1 - (2 * V - 1) ** 2))[..., None] * n
    nu, nv = len(us), len(vs)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    F = np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3)
    cu = np.repeat(np.repeat(su[:, None], nv - 1, 1), 2, axis=1).reshape(-1)
    cv = np.repeat(np.repeat(sv[None, :], nu - 1, 0), 2, axis=1).reshape(-1)
    Pf = P.reshape(-1, 3)
    keep = np.ones(len(F), bool)
    if drop is not None:
        keep &= ~drop(Pf[F].mean(axis=1))
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    label = label or (lambda i, j: "panel")
    for i in range(len(ubreaks) - 1):
        for j in range(len(vbreaks) - 1):
            name = label(i, j)
            if name is None:
                continue
            m = keep & (cu == i) & (cv == j)
            if not m.any():
                continue
            sub = compact(Pf, F[m])
            if name in out:
                sub = merge([out[name], sub])
            out[name] = sub
    return out


def compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inv = np.unique(F.reshape(-1), return_inverse=True)
    return V[used], inv.reshape(-1, 3)


def merge(meshes: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def box(lo, hi, cell, bulge=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box [lo, hi], each face a grid of ~cell; outward winding."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = np.array
    faces = [  # (p00, p10, p01, p11) with (p10-p00) x (p01-p00) outward
        (c([x1, y0, z0]), c([x1, y1, z0]), c([x1, y0, z1]), c([x1, y1, z1])),   # +X
        (c([x0, y0, z0]), c([x0, y0, z1]), c([x0, y1, z0]), c([x0, y1, z1])),   # -X
        (c([x0, y1, z0]), c([x0, y1, z1]), c([x1, y1, z0]), c([x1, y1, z1])),   # +Y
        (c([x0, y0, z0]), c([x1, y0, z0]), c([x0, y0, z1]), c([x1, y0, z1])),   # -Y
        (c([x0, y0, z1]), c([x1, y0, z1]), c([x0, y1, z1]), c([x1, y1, z1])),   # +Z
        (c([x0, y0, z0]), c([x0, y1, z0]), c([x1, y0, z0]), c([x1, y1, z0])),   # -Z
    ]
    return merge([patch(*f, [0, 1], [0, 1], cell, bulge)["panel"] for f in faces])


def revolve(profile: np.ndarray, segments: int, center):
    """Surface of revolution about an axis parallel to Z through ``center``.

    profile: (n, 2) points (r, a): radius and axial offset along +Z; the outside is on the right
    of the profile direction (walking outward in r faces -Z). Points with
    r == 0 (first/last only) become one pole vertex (no degenerate triangles).
    """
    prof = np.asarray(profile, dtype=np.float64)
    th = 2 * np.pi * np.arange(segments) / segments
    ct, st = np.cos(th), np.sin(th)
    verts, rings = [], []
    off = 0
    for r, a in prof:
        if r == 0.0:
            verts.append(np.array([[0.0, 0.0, a]]))
            rings.append(np.full(segments, off))
            off += 1
        else:
            verts.append(np.stack([r * ct, r * st, np.full(segments, a)], 1))
            rings.append(off + np.arange(segments))
            off += segments
    faces = []
    for i in range(len(prof) - 1):           # quad (r0, r0n, r1n, r1) -> two triangles;
        r0, r1 = rings[i], rings[i + 1]       # the one touching a pole twice is left out
        r0n, r1n = np.roll(r0, -1), np.roll(r1, -1)
        if prof[i, 0] != 0.0:
            faces.append(np.stack([r0, r0n, r1], 1))
        if prof[i + 1, 0] != 0.0:
            faces.append(np.stack([r1, r0n, r1n], 1))
    V = np.concatenate(verts)
    F = np.concatenate(faces)
    return V + np.asarray(center, dtype=np.float64), F


def mirror(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflect across z = 0 (exact: negation) and flip the winding."""
    return v * np.array([1.0, 1.0, -1.0]), f[:, ::-1].copy()
